//! The run configuration: one validated type that every part of a run reads. Its serde
//! form is the run folder's config.toml (every setting explicit); flags and `--config`
//! files are its partial form ([`crate::settings`]). Defaults and where they differ from
//! the paper: docs/ALGORITHM.md.

mod head;
mod kinds;
mod ppo;
mod pretrain;
mod qrrl;
mod saver;
pub(crate) mod unbounded;
pub mod upgrade;

pub use head::{HeadConfig, LOG_STD_INIT};
pub use kinds::{Algo, DeltaTarget, Mode, ObsNorm, OptimizerKind, SampleDistribution};
pub use ppo::PpoConfig;
pub use pretrain::{
    paper_lr, paper_pretrain_batches, preset_or_angle, PretrainConfig, PRETRAIN_EVAL_BATCHES,
};
pub use qrrl::{QrrlConfig, QRRL_SPREAD};
pub use saver::SaverConfig;
pub(crate) use unbounded::{inf_is_none, neg_inf_is_none, zero_is_none};

use crate::env::EnvSpec;
use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

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
    /// Standalone QRRL's settings (a config.toml written when they sat in `[saver]`
    /// reads into this section: [`upgrade`]).
    #[serde(default)]
    pub qrrl: QrrlConfig,
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
                target: DeltaTarget::Observed,
                pcpn_tune_lr: 0.0,
                pcpn_tune_rows: 0,
                epochs: 1,
                minibatch_size: 0,
                gae_lambda: 1.0,
                env_gae_lambda: 1.0,
                target_kl: 0.0,
                env_reward: 0.0,
                env_clip: 0.0,
                obs_norm: crate::config::ObsNorm::Off,
            },
            qrrl: QrrlConfig::default(),
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
        self.head.validate()?;
        self.check_hidden()?;
        if self.max_episode_steps == 0 {
            return bad("max_episode_steps", "must be >= 1".into());
        }
        // What only a custom env's actors do; a preset has its own reward and episodes.
        for (asked, field, why) in [
            (
                self.complete_at_success,
                "complete_at_success",
                "has its own reward; only a custom env's actors complete the progress \
                 reward at success",
            ),
            (
                self.continue_past_success,
                "continue_past_success",
                "ends its episodes at success; only a custom env's actors go on past it",
            ),
        ] {
            if asked && self.env.kind().is_some() {
                return bad(field, format!("the preset env {} {why}", self.env.name()));
            }
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
        self.saver.validate(&self.env)?;
        self.qrrl.validate()?;
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
        if self.qrrl.vector && self.algo != Algo::Qrrl {
            return bad(
                "qrrl.vector",
                format!(
                    "the vector variant is standalone QRRL's; this is {}",
                    self.algo.name()
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
        for (field, bad) in [
            ("gae_lambda", 1.5),
            ("gae_lambda", -0.1),
            ("gae_lambda", f64::NAN),
            ("env_gae_lambda", 1.5),
            ("env_gae_lambda", f64::NAN),
        ] {
            let mut c = ok.clone();
            match field {
                "gae_lambda" => c.saver.gae_lambda = bad,
                _ => c.saver.env_gae_lambda = bad,
            }
            let e = crate::algo::validate(&c).unwrap_err().to_string();
            // "saver.gae_lambda" is not a part of "saver.env_gae_lambda".
            let named = format!("saver.{field}");
            assert!(e.contains(&named) && e.contains("not in [0, 1]"), "{e}");
        }
        (c.saver.gae_lambda, c.saver.env_gae_lambda) = (0.0, 0.0);
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
        for bad in [-0.1, 1.0, f64::NAN, f64::INFINITY] {
            c.saver.env_clip = bad;
            let e = crate::algo::validate(&c).unwrap_err().to_string();
            assert!(
                e.contains("saver.env_clip") && e.contains("not in [0, 1)"),
                "{e}"
            );
        }
        c.saver.env_clip = 0.2;
        crate::algo::validate(&c).unwrap();
        c.saver.env_clip = 0.0;
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
