//! SAVER's settings (`[saver]`; docs/ALGORITHM.md §7): the loss constants and the
//! update's options, with their own checks ([`SaverConfig::validate`]).

use super::{zero_is_none, DeltaTarget, ObsNorm};
use crate::env::EnvSpec;
use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// SAVER's loss constants.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SaverConfig {
    /// K: quantile copies per transition.
    pub quantiles: usize,
    /// κ of the Huber quantile loss; `None` (written 0: the κ → 0 limit): the plain
    /// quantile loss (paper).
    #[serde(with = "zero_is_none")]
    pub kappa: Option<f64>,
    /// λ_mon, weight of the monotonic penalty.
    pub lambda_mon: f64,
    /// λ_c, weight of the vector critic's squared error.
    pub lambda_critic: f64,
    /// Normalise the vector advantage per dimension over the batch (zero mean, unit
    /// std); the paper does not.
    pub adv_norm: bool,
    /// With `adv_norm`: divide by one standard deviation over every dimension (each
    /// dimension still centred) instead of one per dimension, so a dimension whose
    /// advantages are only noise (a coordinate already at the goal) stays small
    /// rather than being scaled up to the size of the informative ones.
    pub adv_norm_joint: bool,
    /// Weight of a penalty on the mean head's raw output beyond ±[`super::MU_RAW_LIMIT`]:
    /// `w · Σ_j mean_batch relu(|raw_j| − limit)²`. With μ = tanh(raw), a mean pushed
    /// deep into saturation gets no gradient back (tanh' ≈ 0) and stays there; on
    /// angle that freezes a pair's direction at 0 or π, so one of its coordinates can
    /// no longer move. 0: off (the paper).
    pub mu_raw_penalty: f64,
    /// The mean entries (0-based) [`Self::mu_raw_penalty`] applies to; empty: all. On
    /// angle the odd entries are the pairs' angles, whose bounds are the poles that
    /// trap a pair, while the even ones (step sizes) belong at their bounds far from
    /// the goal.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub mu_raw_penalty_entries: Vec<usize>,
    /// Where the actor loss takes its target from: the observed Δp (the paper) or the
    /// PCPN's prediction for the action taken (docs/ALGORITHM.md §7.1).
    #[serde(default)]
    pub target: DeltaTarget,
    /// Learning rate of the PCPN's own training on the policy's steps during the run
    /// (one pretraining step per update on the batch's [o, μ, log σ] → Δp;
    /// docs/ALGORITHM.md §7.1). 0: the PCPN stays frozen (the paper).
    #[serde(default)]
    pub pcpn_tune_lr: f64,
    /// Rows of each update's batch that the PCPN's training step of
    /// [`Self::pcpn_tune_lr`] reads, drawn at random without replacement; 0 (or the
    /// batch or more): every row.
    #[serde(default)]
    pub pcpn_tune_rows: usize,
    /// Passes over each batch, each in shuffled minibatches of [`Self::minibatch_size`]
    /// steps, every minibatch one optimiser step (docs/ALGORITHM.md §7.1). 1 with one
    /// minibatch: one step per batch (the paper).
    #[serde(default = "one_pass")]
    pub epochs: usize,
    /// Steps per minibatch of [`Self::epochs`]; 0: the whole batch.
    #[serde(default)]
    pub minibatch_size: usize,
    /// λ of the vector advantage: GAE(λ) per coordinate on the vector critic, the
    /// critic's target A + V (docs/ALGORITHM.md §6). 1: the n-step returns of the
    /// rollout (the paper).
    #[serde(default = "no_trace_decay")]
    pub gae_lambda: f64,
    /// λ of the env-return term's GAE(λ) on its scalar critic (docs/ALGORITHM.md §7.2),
    /// apart from [`Self::gae_lambda`]: on Reacher-v5 λ = 0.95 on both terms cost
    /// success and return at 200 k steps, on the vector term alone it did not cost
    /// success (results/env-return/README.md, "night"). 1: the rollout's n-step returns.
    #[serde(default = "no_trace_decay")]
    pub env_gae_lambda: f64,
    /// A trust region for [`Self::epochs`]' passes: before each minibatch step after
    /// the first, the passes over the batch stop once the minibatch's approximate
    /// KL(behaviour ‖ current policy), mean((ρ − 1) − log ρ) over its steps' actions, is
    /// above this (cleanrl's and SB3's `target_kl`; docs/ALGORITHM.md §7.1). 0: off.
    #[serde(default)]
    pub target_kl: f64,
    /// Weight w of the env-return term (docs/ALGORITHM.md §7.2): where the actors send
    /// the env's own scalar reward and it is not the progress reward, a scalar critic
    /// learns its return and the agent also takes −w·mean(Â_r·log π), Â_r normalised
    /// over the batch. 0: off (the paper, and every preset).
    #[serde(default)]
    pub env_reward: f64,
    /// ε of a clipped env-return term (docs/ALGORITHM.md §7.1): the term's policy
    /// gradient becomes PPO's surrogate −mean min(ρ·Â_r, clip(ρ, 1 − ε, 1 + ε)·Â_r),
    /// ρ = π(a|o)/μ(a|o) to the policy that acted, so a row stops pushing once its ratio
    /// has moved ε the way its advantage wants: over [`Self::epochs`]' passes and
    /// minibatches, and on a lagged (async) batch. 0: off (−mean Â_r·log π).
    #[serde(default)]
    pub env_clip: f64,
    /// How the agent and the critics see the observations: raw (the paper), by their
    /// running mean and variance, or mapped from the env's declared bounds to [−1, 1];
    /// the mean and scale travel with the weights, so every actor does the same. The
    /// PCPN reads them raw, as it was pretrained.
    #[serde(default)]
    pub obs_norm: ObsNorm,
}

fn no_trace_decay() -> f64 {
    1.0
}

fn one_pass() -> usize {
    1
}

impl SaverConfig {
    /// Minibatches per pass over a batch of `b` steps: ⌈b / minibatch_size⌉ of (nearly)
    /// equal size, 1 with `minibatch_size` 0.
    pub fn minibatches(&self, b: usize) -> usize {
        match self.minibatch_size {
            0 => 1,
            m => b.div_ceil(m).max(1),
        }
    }

    /// One optimiser step on the whole batch per update (the paper's update).
    pub fn one_step(&self, b: usize) -> bool {
        self.epochs == 1 && self.minibatches(b) == 1
    }
}

impl SaverConfig {
    /// Checks every field (some against the run's `env`); the message names it.
    pub fn validate(&self, env: &EnvSpec) -> Result<()> {
        let bad = |field: &str, why: String| Err(CoreError::Config(format!("{field}: {why}")));
        let s = self;
        if !(1..=1024).contains(&s.quantiles) {
            return bad(
                "saver.quantiles",
                format!("{} is not in 1..=1024", s.quantiles),
            );
        }
        if let Some(k) = s.kappa {
            if !(k.is_finite() && k > 0.0) {
                return bad("saver.kappa", format!("{k} must be >= 0 (0: plain loss)"));
            }
        }
        for (field, v) in [
            ("saver.lambda_mon", s.lambda_mon),
            ("saver.lambda_critic", s.lambda_critic),
            ("saver.mu_raw_penalty", s.mu_raw_penalty),
            ("saver.pcpn_tune_lr", s.pcpn_tune_lr),
            ("saver.env_reward", s.env_reward),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, format!("{v} must be finite and >= 0"));
            }
        }
        for (field, v) in [
            ("saver.gae_lambda", s.gae_lambda),
            ("saver.env_gae_lambda", s.env_gae_lambda),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return bad(field, format!("{v} is not in [0, 1]"));
            }
        }
        if !(s.target_kl.is_finite() && s.target_kl >= 0.0) {
            return bad(
                "saver.target_kl",
                format!("{} must be finite and >= 0 (0: off)", s.target_kl),
            );
        }
        if s.target_kl > 0.0 && s.epochs == 1 && s.minibatch_size == 0 {
            return bad(
                "saver.target_kl",
                "stops the passes of saver.epochs over minibatches of \
                 saver.minibatch_size; with one step on the whole batch there is nothing to stop"
                    .into(),
            );
        }
        if !(0.0..1.0).contains(&s.env_clip) {
            return bad(
                "saver.env_clip",
                format!("{} is not in [0, 1) (0: off)", s.env_clip),
            );
        }
        if !(1..=1000).contains(&s.epochs) {
            return bad("saver.epochs", format!("{} is not in 1..=1000", s.epochs));
        }
        if s.minibatch_size > 1 << 20 {
            return bad(
                "saver.minibatch_size",
                format!(
                    "{} is not in 0..=1048576 (0: the whole batch)",
                    s.minibatch_size
                ),
            );
        }
        if s.target != DeltaTarget::Observed && env.layout().choices > 0 {
            return bad(
                "saver.target",
                "predicted and noise need an env without a categorical choice (its action \
                 noise has no rank along the position change); use observed"
                    .into(),
            );
        }
        if !s.mu_raw_penalty_entries.is_empty() {
            let n = env.layout().mu_dim();
            let field = "saver.mu_raw_penalty_entries";
            if s.mu_raw_penalty == 0.0 {
                return bad(field, "set without saver.mu_raw_penalty (> 0)".into());
            }
            if let Some(e) = s.mu_raw_penalty_entries.iter().find(|&&e| e >= n) {
                return bad(
                    field,
                    format!("entry {e}: {} has {n} mean entries (0..{n})", env),
                );
            }
            let unique: std::collections::BTreeSet<_> = s.mu_raw_penalty_entries.iter().collect();
            if unique.len() != s.mu_raw_penalty_entries.len() {
                return bad(field, "an entry is listed twice".into());
            }
        }
        Ok(())
    }
}
