//! The run configuration: one validated type that every part of a run reads. Its serde
//! form is the run folder's config.toml (every setting explicit); flags and `--config`
//! files are its partial form ([`crate::settings`]). Defaults and where they differ from
//! the paper: docs/ALGORITHM.md.

mod head;
mod kinds;
mod ppo;
mod pretrain;
pub(crate) mod unbounded;

pub use head::HeadConfig;
pub use kinds::{Algo, DeltaTarget, Mode, OptimizerKind, SampleDistribution};
pub use ppo::PpoConfig;
pub use pretrain::{
    paper_lr, paper_pretrain_batches, preset_or_angle, PretrainConfig, PRETRAIN_EVAL_BATCHES,
};
pub(crate) use unbounded::{inf_is_none, neg_inf_is_none, zero_is_none};

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
    /// Weight of a penalty on the mean head's raw output beyond ±[`MU_RAW_LIMIT`]:
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
    /// Standalone QRRL: half-width s of the fixed base quantile function s·(2τ − 1)
    /// added to the policy network's output, so that the initial policy is U(−s, s)
    /// (the network starts near 0 everywhere, which would not explore). Not used by
    /// SAVER.
    #[serde(default)]
    pub qrrl_spread: f64,
    /// Standalone QRRL's vector variant: a vector critic V(o) ∈ R^d on the vector reward,
    /// and coordinate j's advantage weighs action dim j; only for envs whose actions
    /// are aligned with their coordinates ([`crate::env::EnvSpec::actions_aligned`]).
    #[serde(default)]
    pub qrrl_vector: bool,
    /// Where the actor loss takes its target from: the observed Δp (the paper) or the
    /// PCPN's prediction for the action taken (docs/ALGORITHM.md §7.1).
    #[serde(default)]
    pub target: DeltaTarget,
    /// Learning rate of the PCPN's own training on the policy's steps during the run
    /// (one pretraining step per update on the batch's [o, μ, log σ] → Δp;
    /// docs/ALGORITHM.md §7.1). 0: the PCPN stays frozen (the paper).
    #[serde(default)]
    pub pcpn_tune_lr: f64,
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

fn one() -> f64 {
    1.0
}

/// Hidden widths of the agent's trunk and of the critics by default: the paper's
/// (docs/ALGORITHM.md §3).
pub const PAPER_HIDDEN: [usize; 3] = [256, 128, 64];
/// Most hidden layers a run (or a weights file an actor reads) may have.
pub const MAX_HIDDEN_LAYERS: usize = 8;
/// Widest hidden layer a run may have.
pub const MAX_HIDDEN_WIDTH: usize = 4096;
/// Most values the agent's weights may hold: they travel to every actor in one
/// message of at most 64 MiB.
pub const MAX_AGENT_WEIGHTS: usize = 8 << 20;

fn paper_hidden() -> Vec<usize> {
    PAPER_HIDDEN.to_vec()
}

/// The widths of an MLP from `input` through the `hidden` layers to `output` (what
/// `mlp_flops` and the weights-size check take).
pub fn mlp_dims(input: usize, hidden: &[usize], output: usize) -> Vec<usize> {
    std::iter::once(input)
        .chain(hidden.iter().copied())
        .chain([output])
        .collect()
}

/// Where [`SaverConfig::mu_raw_penalty`] starts: tanh(2) = 0.964.
pub const MU_RAW_LIMIT: f64 = 2.0;

/// Everything that defines a run. Its TOML form is the run folder's config.toml.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Algorithm.
    pub algo: Algo,
    /// Env steps (transitions) to train for.
    pub steps: u64,
    /// Base seed: weights, tau draws and actor streams derive from it.
    pub seed: u64,
    /// Number of actors (sync: the learner waits for this many before the first
    /// update; async: rollouts per update).
    pub actors: u32,
    /// Env instances per actor.
    #[serde(rename = "envs")]
    pub envs_per_actor: u32,
    /// Batch formation.
    pub mode: Mode,
    /// Async mode: largest accepted policy lag (versions behind the learner); `None`
    /// in sync mode, which has no lag.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_lag: Option<u64>,
    /// Rollout length n.
    pub rollout: u32,
    /// Discount γ.
    pub gamma: f64,
    /// Agent (and critic) learning rate.
    pub lr: f64,
    /// Optimiser.
    pub optimizer: OptimizerKind,
    /// Let the learning rate fall linearly from `lr` to zero over the run's updates
    /// (the paper: constant).
    pub lr_decay: bool,
    /// Clip the global gradient norm of each update to this (`None`, written inf: no
    /// clipping, the paper).
    #[serde(with = "inf_is_none")]
    pub grad_clip: Option<f64>,
    /// Episode step limit (hitting it is terminal, as in the paper's code).
    pub max_episode_steps: u32,
    /// At the step limit, bootstrap the return from the value of the observation
    /// reached, instead of treating the limit as terminal (the paper's code).
    pub bootstrap_timeout: bool,
    /// Ask the actors of a custom env with a success radius and the default progress
    /// reward to complete it at success: on the step that ends an episode inside the
    /// success box, coordinate j's reward also gets |p'_j − g_j| (the rest of its
    /// distance, capped at max_change), so a successful episode is credited the whole
    /// way to the goal (docs/ALGORITHM.md §7.1). Travels to the actors in
    /// RunSettings; a preset env's actors have nothing to complete. Off: the paper.
    #[serde(default)]
    pub complete_at_success: bool,
    /// Ask a custom env's actors to go on past success: an episode then ends only
    /// where the env ends it or at the step limit, so what the policy does at the goal
    /// (holding still, or paying control cost) is in its returns; success is ending
    /// inside the box. Travels in RunSettings; a preset's episodes end at success.
    /// Off: the paper (docs/ALGORITHM.md §7.2).
    #[serde(default)]
    pub continue_past_success: bool,
    /// A2C value-loss weight.
    pub value_coef: f64,
    /// Off-policy correction of rollouts acted by an older policy (async mode): V-trace
    /// critic targets and ratio-weighted advantages (docs/ALGORITHM.md §16). A2C and
    /// SAVER; off by default (a config.toml written before it reads as off).
    #[serde(default)]
    pub vtrace: bool,
    /// V-trace's ρ̄: the clip of the ratio π/μ that weighs each step's TD error and
    /// advantage.
    #[serde(default = "one")]
    pub rho_bar: f64,
    /// V-trace's c̄: the clip of the ratio that carries a later step's correction back.
    #[serde(default = "one")]
    pub c_bar: f64,
    /// The environment.
    pub env: EnvSpec,
    /// Bounds of the policy's μ and log σ (the paper: none).
    pub head: HeadConfig,
    /// Hidden widths of the agent's trunk and of each critic, ReLU after each (the
    /// paper's 256, 128, 64; a config.toml written before it reads as those).
    #[serde(default = "paper_hidden")]
    pub hidden: Vec<usize>,
    /// SAVER constants.
    pub saver: SaverConfig,
    /// PPO constants (a config.toml written before PPO existed reads as the defaults).
    #[serde(default)]
    pub ppo: PpoConfig,
    /// PCPN pretraining (SAVER).
    pub pretrain: PretrainConfig,
    /// SAVER: the weights sha256 of the PCPN this run uses. `None` before a PCPN is
    /// chosen; a run started with it set refuses any other PCPN.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pcpn_sha256: Option<String>,
}

/// QRRL's [`SaverConfig::qrrl_spread`] by default: the initial policy is U(−1, 1), the
/// env's whole action range (with 0.637, the spread of the Gaussian's initial σ = e⁻¹,
/// the bandit's optima at ±0.75 lay outside it and seed 0 settled on the decoy;
/// docs/ALGORITHM.md §14).
pub const QRRL_SPREAD: f64 = 1.0;
/// PCPN pretraining batches by default (the paper's: 100,000 for angle).
pub const RECOMMENDED_PRETRAIN_BATCHES: u64 = 5_000;
/// Async mode's policy lag unless set.
pub const DEFAULT_MAX_LAG: u64 = 4;

impl RunConfig {
    /// The paper's settings for an env and algorithm, for `steps` steps.
    pub fn paper(env: &EnvSpec, algo: Algo, steps: u64) -> Self {
        Self {
            env: env.clone(),
            algo,
            steps,
            seed: 0,
            actors: 16,
            mode: Mode::Sync,
            max_lag: None,
            envs_per_actor: 1,
            rollout: 8,
            gamma: 0.99,
            lr: paper_lr(preset_or_angle(env), algo),
            optimizer: OptimizerKind::Rmsprop,
            lr_decay: false,
            grad_clip: None,
            head: HeadConfig::FAITHFUL,
            hidden: paper_hidden(),
            // The paper's envs stop at 1000; the bandit is one step long.
            max_episode_steps: env
                .kind()
                .and_then(|k| k.fixed_episode_steps())
                .unwrap_or(1000),
            bootstrap_timeout: false,
            complete_at_success: false,
            continue_past_success: false,
            value_coef: 0.5,
            vtrace: false,
            rho_bar: 1.0,
            c_bar: 1.0,
            saver: SaverConfig {
                quantiles: 32,
                kappa: None,
                lambda_mon: 1.0,
                lambda_critic: 0.5,
                adv_norm: false,
                adv_norm_joint: false,
                mu_raw_penalty: 0.0,
                mu_raw_penalty_entries: Vec::new(),
                qrrl_spread: QRRL_SPREAD,
                qrrl_vector: false,
                target: DeltaTarget::Observed,
                pcpn_tune_lr: 0.0,
                epochs: 1,
                minibatch_size: 0,
                gae_lambda: 1.0,
                target_kl: 0.0,
                env_reward: 0.0,
            },
            ppo: PpoConfig::default(),
            pretrain: PretrainConfig::paper(preset_or_angle(env)).for_env(env),
            pcpn_sha256: None,
        }
    }

    /// Checks every field; the message names the field. What an algorithm refuses on
    /// top ([`crate::algo::Entry::check`]) is checked by [`crate::algo::validate`],
    /// which calls this first: use that one.
    pub fn check_fields(&self) -> Result<()> {
        let bad = |field: &str, why: String| Err(CoreError::Config(format!("{field}: {why}")));
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
        match (self.mode, self.max_lag) {
            (Mode::Sync, Some(_)) => {
                return bad(
                    "max_lag",
                    "sync mode uses every rollout at the current version; a policy lag \
                     applies to --mode async only"
                        .into(),
                )
            }
            (Mode::Async, None) => return bad("max_lag", "async mode needs one".into()),
            _ => {}
        }
        if !(1..=10_000).contains(&self.rollout) {
            return bad("rollout", format!("{} is not in 1..=10000", self.rollout));
        }
        if !(self.gamma > 0.0 && self.gamma <= 1.0) {
            return bad("gamma", format!("{} is not in (0, 1]", self.gamma));
        }
        if !(self.lr.is_finite() && self.lr > 0.0 && self.lr < 10.0) {
            return bad(
                "lr",
                format!("{} is not a learning rate in (0, 10)", self.lr),
            );
        }
        if let Some(c) = self.grad_clip {
            if !(c.is_finite() && c > 0.0) {
                return bad("grad_clip", format!("{c} must be > 0 (inf: no clipping)"));
            }
        }
        if let Some(b) = self.head.mu_bound {
            if !(b.is_finite() && b > 0.0) {
                return bad("head.mu_bound", format!("{b} must be > 0 (inf: unbounded)"));
            }
        }
        if let Some((lo, hi)) = self.head.log_std_bounds {
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return bad(
                    "head.log_std_min, head.log_std_max",
                    format!("[{lo}, {hi}] is not an interval (-inf and inf: unbounded)"),
                );
            }
        }
        self.check_hidden()?;
        if self.max_episode_steps == 0 {
            return bad("max_episode_steps", "must be >= 1".into());
        }
        if self.complete_at_success && self.env.kind().is_some() {
            return bad(
                "complete_at_success",
                format!(
                    "the preset env {} has its own reward; only a custom env's actors \
                     complete the progress reward at success",
                    self.env.name()
                ),
            );
        }
        if self.continue_past_success && self.env.kind().is_some() {
            return bad(
                "continue_past_success",
                format!(
                    "the preset env {} ends its episodes at success; only a custom env's \
                     actors go on past it",
                    self.env.name()
                ),
            );
        }
        if !(self.value_coef.is_finite() && self.value_coef >= 0.0) {
            return bad(
                "value_coef",
                format!("{} must be finite and >= 0", self.value_coef),
            );
        }
        for (field, v) in [("rho_bar", self.rho_bar), ("c_bar", self.c_bar)] {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, format!("{v} must be finite and > 0"));
            }
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
                return bad("saver.kappa", format!("{k} must be >= 0 (0: plain loss)"));
            }
        }
        for (field, v) in [
            ("saver.lambda_mon", s.lambda_mon),
            ("saver.lambda_critic", s.lambda_critic),
            ("saver.mu_raw_penalty", s.mu_raw_penalty),
            ("saver.qrrl_spread", s.qrrl_spread),
            ("saver.pcpn_tune_lr", s.pcpn_tune_lr),
            ("saver.env_reward", s.env_reward),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, format!("{v} must be finite and >= 0"));
            }
        }
        if !(0.0..=1.0).contains(&s.gae_lambda) {
            return bad(
                "saver.gae_lambda",
                format!("{} is not in [0, 1]", s.gae_lambda),
            );
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
        if s.target != DeltaTarget::Observed && self.env.layout().choices > 0 {
            return bad(
                "saver.target",
                "predicted and noise need an env without a categorical choice (its action \
                 noise has no rank along the position change); use observed"
                    .into(),
            );
        }
        if !s.mu_raw_penalty_entries.is_empty() {
            let n = self.env.layout().mu_dim();
            let field = "saver.mu_raw_penalty_entries";
            if s.mu_raw_penalty == 0.0 {
                return bad(field, "set without saver.mu_raw_penalty (> 0)".into());
            }
            if let Some(e) = s.mu_raw_penalty_entries.iter().find(|&&e| e >= n) {
                return bad(
                    field,
                    format!("entry {e}: {} has {n} mean entries (0..{n})", self.env),
                );
            }
            let unique: std::collections::BTreeSet<_> = s.mu_raw_penalty_entries.iter().collect();
            if unique.len() != s.mu_raw_penalty_entries.len() {
                return bad(field, "an entry is listed twice".into());
            }
        }
        self.ppo.validate()?;
        self.pretrain.validate()?;
        self.pretrain.check_env(&self.env)?;
        if let Some(n) = self.env.kind().and_then(|k| k.fixed_episode_steps()) {
            if self.max_episode_steps != n {
                return bad(
                    "max_episode_steps",
                    format!(
                        "{}'s episodes are {n} step(s) long; got {}",
                        self.env.name(),
                        self.max_episode_steps
                    ),
                );
            }
        }
        if self.saver.qrrl_vector && !(self.algo == Algo::Qrrl && self.env.actions_aligned()) {
            return bad(
                "saver.qrrl_vector",
                format!(
                    "the vector variant is standalone QRRL's, on an env whose action dim j \
                     moves coordinate j (point, bandit); this is {} on {}",
                    self.algo.name(),
                    self.env
                ),
            );
        }
        if !self.algo.has_pcpn() && self.pcpn_sha256.is_some() {
            return bad(
                "pcpn_sha256",
                format!("{} runs use no PCPN", self.algo.name()),
            );
        }
        Ok(())
    }

    /// Transitions per update in sync mode.
    pub fn batch_transitions(&self) -> u64 {
        self.actors as u64 * self.envs_per_actor as u64 * self.rollout as u64
    }

    /// Async mode's policy lag (0 in sync mode, where every rollout is current).
    pub fn lag_limit(&self) -> u64 {
        self.max_lag.unwrap_or(0)
    }

    /// `hidden`: 1 to [`MAX_HIDDEN_LAYERS`] widths in 1..=[`MAX_HIDDEN_WIDTH`], and an
    /// agent whose weights fit one weights message.
    fn check_hidden(&self) -> Result<()> {
        let bad = |why: String| Err(CoreError::Config(format!("hidden: {why}")));
        let h = &self.hidden;
        if !(1..=MAX_HIDDEN_LAYERS).contains(&h.len()) {
            return bad(format!(
                "{h:?} has {} layers; give 1 to {MAX_HIDDEN_LAYERS} widths",
                h.len()
            ));
        }
        if let Some(w) = h.iter().find(|w| !(1..=MAX_HIDDEN_WIDTH).contains(*w)) {
            return bad(format!("width {w} is not in 1..={MAX_HIDDEN_WIDTH}"));
        }
        let l = self.env.layout();
        let dims = mlp_dims(
            l.obs_dim.max(l.pcpn_input_dim()),
            h,
            l.mu_dim().max(l.aligned_dim) + 1,
        );
        let weights: usize = dims.windows(2).map(|w| (w[0] + 1) * w[1]).sum();
        if weights > MAX_AGENT_WEIGHTS {
            return bad(format!(
                "{h:?} makes a network of {weights} weights in this env, over the \
                 {MAX_AGENT_WEIGHTS} that fit one weights message"
            ));
        }
        Ok(())
    }

    /// Hash of the config (sha256 of its JSON), so peers can tell they agree.
    pub fn hash(&self) -> String {
        let json = serde_json::to_vec(self).unwrap_or_default();
        saver_proto::sha256_hex(&json)
    }

    /// The config as the TOML of config.toml, every setting listed.
    pub fn to_toml(&self) -> String {
        let body = toml::to_string(self).unwrap_or_default();
        format!(
            "# Every setting of this run; `saver train --config <this file>` repeats it.\n\
             # inf (grad_clip, head.*) means no bound; saver.kappa = 0 the plain quantile loss.\n\
             {body}"
        )
    }
}

/// What the quantile-network policy (QRRL's) can act in: continuous action dims only
/// (a categorical choice is no quantile of anything) and a finite spread s ≥ 0 of its
/// base quantile function. `nets::QuantileFamily::new` holds its family to it.
pub fn check_quantile_policy(layout: crate::env::EnvLayout, spread: f64) -> Result<()> {
    if layout.choices > 0 || layout.continuous == 0 {
        return Err(CoreError::Config(format!(
            "algo qrrl: the quantile policy acts in continuous action dims only; this env \
             has {} continuous dims and a choice of {}",
            layout.continuous, layout.choices
        )));
    }
    if !(spread.is_finite() && spread >= 0.0) {
        return Err(CoreError::Config(format!(
            "quantile-mlp policy: spread {spread} must be finite and >= 0"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::env::EnvKind;

    /// Every hand-written list of algorithms or presets names each row of the tables
    /// (a new algorithm or preset must appear in each): the wire's comments, which no
    /// code can build, and the texts built from the tables.
    #[test]
    fn every_list_names_every_algorithm_and_preset() {
        let proto = include_str!("../../../proto/saver.proto");
        let line = |field: &str| {
            proto
                .lines()
                .find(|l| l.trim_start().starts_with(field))
                .unwrap_or_else(|| panic!("saver.proto has no {field}"))
                .to_string()
        };
        let algo_line = line("string algo = 1;");
        let env_comment = line("// An environment: its name");
        let parse_err = Algo::parse("nope").unwrap_err().to_string();
        let env_err = EnvKind::parse("nope").unwrap_err().to_string();
        let dim_help = crate::env::dim_help();
        for a in Algo::all() {
            let quoted = format!("\"{}\"", a.name());
            assert!(algo_line.contains(&quoted), "{algo_line} lacks {quoted}");
            assert!(
                parse_err.contains(a.name()),
                "{parse_err} lacks {}",
                a.name()
            );
        }
        assert_eq!(
            Algo::all().len(),
            4,
            "a new algorithm: check the lists above"
        );
        for p in crate::env::PRESETS.iter() {
            let quoted = format!("\"{}\"", p.name);
            assert!(
                env_comment.contains(&quoted),
                "{env_comment} lacks {quoted}"
            );
            assert!(env_err.contains(p.name), "{env_err} lacks {}", p.name);
            assert!(dim_help.contains(p.name), "{dim_help} lacks {}", p.name);
        }
    }

    #[test]
    fn paper_defaults_validate_and_bad_fields_are_named() {
        let env = EnvSpec::new(EnvKind::Angle, 4).unwrap();
        let ok = RunConfig::paper(&env, Algo::Saver, 1000);
        crate::algo::validate(&ok).unwrap();
        assert_eq!(ok.lr, 0.01);
        assert_eq!(ok.pretrain.lr, 0.001);
        assert_eq!(ok.batch_transitions(), 128);
        let mut c = ok.clone();
        c.gamma = 1.5;
        assert!(crate::algo::validate(&c)
            .unwrap_err()
            .to_string()
            .contains("gamma"));
        let mut c = ok.clone();
        c.lr = f64::NAN;
        assert!(crate::algo::validate(&c)
            .unwrap_err()
            .to_string()
            .contains("lr"));
        let mut c = ok.clone();
        c.max_lag = Some(2);
        assert!(crate::algo::validate(&c)
            .unwrap_err()
            .to_string()
            .contains("max_lag"));
        let mut c = crate::algo::recommended(&env, Algo::Saver, 1000);
        c.saver.mu_raw_penalty_entries = vec![1, 3];
        assert!(crate::algo::validate(&c)
            .unwrap_err()
            .to_string()
            .contains("without"));
        c.saver.mu_raw_penalty = 0.1;
        crate::algo::validate(&c).unwrap();
        c.saver.mu_raw_penalty_entries = vec![1, 4];
        let e = crate::algo::validate(&c).unwrap_err().to_string();
        assert!(e.contains("entry 4: angle-d4 has 4 mean entries"), "{e}");
        c.saver.mu_raw_penalty_entries = vec![3, 3];
        assert!(crate::algo::validate(&c)
            .unwrap_err()
            .to_string()
            .contains("twice"));
        let mut c = ok.clone();
        for bad in [1.5, -0.1, f64::NAN] {
            c.saver.gae_lambda = bad;
            let e = crate::algo::validate(&c).unwrap_err().to_string();
            assert!(
                e.contains("saver.gae_lambda") && e.contains("not in [0, 1]"),
                "{e}"
            );
        }
        c.saver.gae_lambda = 0.0;
        crate::algo::validate(&c).unwrap();
        for bad in [-0.1, f64::NAN, f64::INFINITY] {
            c.saver.target_kl = bad;
            let e = crate::algo::validate(&c).unwrap_err().to_string();
            assert!(e.contains("saver.target_kl") && e.contains(">= 0"), "{e}");
        }
        c.saver.target_kl = 0.01;
        let e = crate::algo::validate(&c).unwrap_err().to_string();
        assert!(e.contains("nothing to stop"), "{e}");
        c.saver.epochs = 4;
        crate::algo::validate(&c).unwrap();
        (c.saver.target_kl, c.saver.epochs) = (0.0, 1);
        c.saver.epochs = 0;
        let e = crate::algo::validate(&c).unwrap_err().to_string();
        assert!(
            e.contains("saver.epochs") && e.contains("0 is not in 1..=1000"),
            "{e}"
        );
        (c.saver.epochs, c.saver.minibatch_size) = (4, 1 << 21);
        let e = crate::algo::validate(&c).unwrap_err().to_string();
        assert!(e.contains("saver.minibatch_size"), "{e}");
        // 128 steps in minibatches of 50: 3 of them (42, 43 and 43 steps).
        c.saver.minibatch_size = 50;
        crate::algo::validate(&c).unwrap();
        assert_eq!(
            (c.saver.minibatches(128), c.saver.one_step(128)),
            (3, false)
        );
        (c.saver.epochs, c.saver.minibatch_size) = (1, 128);
        assert!(c.saver.one_step(128));
        assert!(EnvSpec::new(EnvKind::Angle, 3)
            .unwrap_err()
            .to_string()
            .contains("even"));
    }

    /// Every field survives TOML and JSON, the unbounded ones (inf, κ = 0) included.
    #[test]
    fn toml_and_json_forms_read_back_equal() {
        let env = EnvSpec::new(EnvKind::Select, 5).unwrap();
        let faithful = RunConfig::paper(&env, Algo::Saver, 1000);
        let mut bounded = crate::algo::recommended(&env, Algo::Saver, 1000);
        bounded.saver.kappa = Some(0.01);
        bounded.grad_clip = Some(0.5);
        bounded.mode = Mode::Async;
        bounded.max_lag = Some(3);
        bounded.pcpn_sha256 = Some("ab".repeat(32));
        (bounded.saver.epochs, bounded.saver.minibatch_size) = (4, 256);
        for c in [faithful, bounded] {
            let text = c.to_toml();
            let back: RunConfig = toml::from_str(&text).unwrap();
            assert_eq!(back, c, "{text}");
            let json: RunConfig = serde_json::from_slice(&serde_json::to_vec(&c).unwrap()).unwrap();
            assert_eq!(json, c);
        }
    }
}
