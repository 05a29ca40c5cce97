//! The run configuration: one validated type that every part of a run reads. Raw flags
//! and config files are turned into it in one place (the CLI); defaults reproduce the
//! paper (SPEC.md).

use crate::env::{EnvKind, EnvSpec};
use crate::nets::HeadConfig;
use crate::optim::OptimizerConfig;
use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// The learning algorithm.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Algo {
    /// Vector rewards through the frozen PCPN with the QRRL loss.
    Saver,
    /// The scalar-reward A2C baseline.
    A2c,
}

impl Algo {
    /// Parses `saver` or `a2c`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "saver" => Ok(Self::Saver),
            "a2c" => Ok(Self::A2c),
            other => Err(CoreError::Config(format!(
                "algo: unknown algorithm {other:?} (expected saver or a2c)"
            ))),
        }
    }
    /// The lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Saver => "saver",
            Self::A2c => "a2c",
        }
    }
}

/// How the learner forms batches.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// One rollout per registered actor at the current version, in actor-id order
    /// (exact on-policy A2C/SAVER, repeatable bit for bit).
    Sync,
    /// An update on every `actors` rollouts whose version lag is at most `max_lag`.
    Async,
}

impl Mode {
    /// Parses `sync` or `async`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "sync" => Ok(Self::Sync),
            "async" => Ok(Self::Async),
            other => Err(CoreError::Config(format!(
                "mode: unknown mode {other:?} (expected sync or async)"
            ))),
        }
    }
    /// The lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Sync => "sync",
            Self::Async => "async",
        }
    }
}

/// SAVER's loss constants.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SaverConfig {
    /// K: quantile copies per transition.
    pub quantiles: usize,
    /// κ of the Huber quantile loss; `None`: the plain quantile loss (paper).
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
    #[serde(default)]
    pub adv_norm_joint: bool,
    /// Weight of a penalty on the mean head's raw output beyond ±[`MU_RAW_LIMIT`]:
    /// `w · Σ_j mean_batch relu(|raw_j| − limit)²`. With μ = tanh(raw), a mean pushed
    /// deep into saturation gets no gradient back (tanh' ≈ 0) and stays there; on
    /// angle that freezes a pair's direction at 0 or π, so one of its coordinates can
    /// no longer move. 0: off (the paper).
    #[serde(default)]
    pub mu_raw_penalty: f64,
}

/// Where [`SaverConfig::mu_raw_penalty`] starts: tanh(2) = 0.964.
pub const MU_RAW_LIMIT: f64 = 2.0;

/// PCPN pretraining settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PretrainConfig {
    /// Number of fresh batches.
    pub batches: u64,
    /// Transitions per batch.
    pub batch_size: usize,
    /// Learning rate (paper: 0.1 × the agent's).
    pub lr: f64,
    /// Fresh held-out batches for the final quantile loss.
    pub eval_batches: usize,
}

/// Everything that defines a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunConfig {
    /// Environment preset and dimension.
    pub env: EnvSpec,
    /// Algorithm.
    pub algo: Algo,
    /// Env steps (transitions) to train for.
    pub steps: u64,
    /// Base seed: weights, tau draws and actor streams derive from it.
    pub seed: u64,
    /// Number of actors (sync: the learner waits for this many before the first
    /// update; async: rollouts per update).
    pub actors: u32,
    /// Batch formation.
    pub mode: Mode,
    /// Async mode: largest accepted policy lag (versions behind the learner).
    pub max_lag: u64,
    /// Env instances per actor.
    pub envs_per_actor: u32,
    /// Rollout length n.
    pub rollout: u32,
    /// Discount γ.
    pub gamma: f64,
    /// Agent (and critic) learning rate.
    pub lr: f64,
    /// Optimiser and its constants.
    pub optimizer: OptimizerConfig,
    /// Let the learning rate fall linearly from `lr` to zero over the run's updates
    /// (the paper: constant).
    #[serde(default)]
    pub lr_decay: bool,
    /// Clip the global gradient norm of each update to this (the paper: no clipping).
    pub grad_clip: Option<f64>,
    /// Bounds of the policy's μ and log σ (the paper: none).
    pub head: HeadConfig,
    /// Episode step limit (hitting it is terminal, as in the paper's code).
    pub max_episode_steps: u32,
    /// At the step limit, bootstrap the return from the value of the observation
    /// reached, instead of treating the limit as terminal (the paper's code).
    #[serde(default)]
    pub bootstrap_timeout: bool,
    /// A2C value-loss weight.
    pub value_coef: f64,
    /// SAVER constants.
    pub saver: SaverConfig,
    /// PCPN pretraining.
    pub pretrain: PretrainConfig,
}

/// The paper's learning rate for an env and algorithm (SPEC.md).
pub fn paper_lr(kind: EnvKind, algo: Algo) -> f64 {
    match (kind, algo) {
        (EnvKind::Angle, Algo::Saver) => 0.01,
        (EnvKind::Angle, Algo::A2c) => 0.0003,
        (EnvKind::Select, Algo::Saver) => 0.01,
        (EnvKind::Select, Algo::A2c) => 0.0001,
        (EnvKind::Arm, Algo::Saver) => 0.003,
        (EnvKind::Arm, Algo::A2c) => 0.0003,
    }
}

/// SAVER's learning rate by default (with Adam; the paper's is 0.01 with RMSProp).
/// 3e-4 before: at d = 16 it left SAVER at a mean length of 1000 for 2.56 M steps,
/// where 1e-3 moves every coordinate toward the goal ~2x as fast (results/README.md).
pub const RECOMMENDED_SAVER_LR: f64 = 1e-3;
/// PCPN pretraining batches by default (the paper's: 100,000 for angle).
pub const RECOMMENDED_PRETRAIN_BATCHES: u64 = 5_000;

/// The paper's number of pretraining batches for an env.
pub fn paper_pretrain_batches(kind: EnvKind) -> u64 {
    match kind {
        EnvKind::Angle => 100_000,
        EnvKind::Select | EnvKind::Arm => 10_000,
    }
}

impl RunConfig {
    /// The paper's settings for an env and algorithm, for `steps` steps.
    pub fn paper(env: EnvSpec, algo: Algo, steps: u64) -> Self {
        let lr = paper_lr(env.kind, algo);
        Self {
            env,
            algo,
            steps,
            seed: 0,
            actors: 16,
            mode: Mode::Sync,
            max_lag: 4,
            envs_per_actor: 1,
            rollout: 8,
            gamma: 0.99,
            lr,
            optimizer: OptimizerConfig::RMSPROP_TF1,
            lr_decay: false,
            grad_clip: None,
            head: HeadConfig::FAITHFUL,
            max_episode_steps: 1000,
            bootstrap_timeout: false,
            value_coef: 0.5,
            saver: SaverConfig {
                quantiles: 32,
                kappa: None,
                lambda_mon: 1.0,
                lambda_critic: 0.5,
                adv_norm: false,
                adv_norm_joint: false,
                mu_raw_penalty: 0.0,
            },
            pretrain: PretrainConfig {
                batches: paper_pretrain_batches(env.kind),
                batch_size: 128,
                lr: 0.1 * paper_lr(env.kind, Algo::Saver),
                eval_batches: 16,
            },
        }
    }

    /// SAVER with the smallest set of changes that make it learn (results/README.md
    /// has the ablations): TF1 Adam at 1e-3 instead of RMSProp at the paper's rate,
    /// μ = tanh(raw) and log σ in [-4.6, 0] so the actions stay where the PCPN was
    /// pretrained, the vector advantage centred per dimension over each batch and
    /// divided by one standard deviation over all dimensions, and a PCPN pretrained
    /// 5,000 batches (its held-out loss settles by ~1,000). A2C keeps the paper's
    /// settings.
    pub fn recommended(env: EnvSpec, algo: Algo, steps: u64) -> Self {
        let mut c = Self::paper(env, algo, steps);
        if algo == Algo::Saver {
            c.optimizer = OptimizerConfig::ADAM_TF1;
            c.lr = RECOMMENDED_SAVER_LR;
            c.head = HeadConfig::IN_PCPN_DOMAIN;
            c.saver.adv_norm = true;
            c.saver.adv_norm_joint = true;
            c.pretrain.batches = RECOMMENDED_PRETRAIN_BATCHES;
        }
        c
    }

    /// Checks every field; the message names the field.
    pub fn validate(&self) -> Result<()> {
        let bad = |field: &str, why: String| Err(CoreError::Config(format!("{field}: {why}")));
        EnvSpec::new(self.env.kind, self.env.dim)?;
        if self.steps == 0 {
            return bad("steps", "must be >= 1".into());
        }
        if !(1..=4096).contains(&self.actors) {
            return bad("actors", format!("{} is not in 1..=4096", self.actors));
        }
        if !(1..=1024).contains(&self.envs_per_actor) {
            return bad(
                "envs",
                format!("{} is not in 1..=1024", self.envs_per_actor),
            );
        }
        if !(1..=10_000).contains(&self.rollout) {
            return bad("rollout", format!("{} is not in 1..=10000", self.rollout));
        }
        if !(self.gamma > 0.0 && self.gamma <= 1.0) {
            return bad("gamma", format!("{} is not in (0, 1]", self.gamma));
        }
        for (field, lr) in [("lr", self.lr), ("pretrain.lr", self.pretrain.lr)] {
            if !(lr.is_finite() && lr > 0.0 && lr < 10.0) {
                return bad(field, format!("{lr} is not a learning rate in (0, 10)"));
            }
        }
        self.optimizer.validate()?;
        if let Some(c) = self.grad_clip {
            if !(c.is_finite() && c > 0.0) {
                return bad("grad_clip", format!("{c} must be > 0"));
            }
        }
        if let Some(b) = self.head.mu_bound {
            if !(b.is_finite() && b > 0.0) {
                return bad("mu_bound", format!("{b} must be > 0"));
            }
        }
        if let Some((lo, hi)) = self.head.log_std_bounds {
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return bad("log_std_bounds", format!("[{lo}, {hi}] is not an interval"));
            }
        }
        if self.max_episode_steps == 0 {
            return bad("max_episode_steps", "must be >= 1".into());
        }
        if !(self.value_coef.is_finite() && self.value_coef >= 0.0) {
            return bad(
                "value_coef",
                format!("{} must be finite and >= 0", self.value_coef),
            );
        }
        let s = &self.saver;
        if !(1..=1024).contains(&s.quantiles) {
            return bad(
                "saver.quantiles",
                format!("{} is not in 1..=1024", s.quantiles),
            );
        }
        if let Some(k) = s.kappa {
            if !(k.is_finite() && k > 0.0) {
                return bad("saver.kappa", format!("{k} must be > 0"));
            }
        }
        for (field, v) in [
            ("saver.lambda_mon", s.lambda_mon),
            ("saver.lambda_critic", s.lambda_critic),
            ("saver.mu_raw_penalty", s.mu_raw_penalty),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, format!("{v} must be finite and >= 0"));
            }
        }
        let p = &self.pretrain;
        if !(1..=65_536).contains(&p.batch_size) {
            return bad(
                "pretrain.batch_size",
                format!("{} is not in 1..=65536", p.batch_size),
            );
        }
        if p.eval_batches == 0 {
            return bad("pretrain.eval_batches", "must be >= 1".into());
        }
        Ok(())
    }

    /// Transitions per update in sync mode.
    pub fn batch_transitions(&self) -> u64 {
        self.actors as u64 * self.envs_per_actor as u64 * self.rollout as u64
    }

    /// Hash of the config (sha256 of its JSON), so peers can tell they agree.
    pub fn hash(&self) -> String {
        let json = serde_json::to_vec(self).unwrap_or_default();
        saver_proto::sha256_hex(&json)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_defaults_validate_and_bad_fields_are_named() {
        let env = EnvSpec::new(EnvKind::Angle, 4).unwrap();
        let ok = RunConfig::paper(env, Algo::Saver, 1000);
        ok.validate().unwrap();
        assert_eq!(ok.lr, 0.01);
        assert_eq!(ok.pretrain.lr, 0.001);
        assert_eq!(ok.batch_transitions(), 128);
        let mut c = ok.clone();
        c.gamma = 1.5;
        assert!(c.validate().unwrap_err().to_string().contains("gamma"));
        let mut c = ok.clone();
        c.lr = f64::NAN;
        assert!(c.validate().unwrap_err().to_string().contains("lr"));
        let mut c = ok;
        c.env.dim = 3;
        assert!(c.validate().unwrap_err().to_string().contains("even"));
    }
}
