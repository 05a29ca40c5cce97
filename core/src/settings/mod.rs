//! Flags and `--config` files: the partial form of [`RunConfig`], one clap + serde
//! definition whose fields carry RunConfig's names (nested tables included), so a
//! config.toml a run wrote reads back as settings, and settings lay over any config.
//!
//! Resolution: the defaults of the chosen env and algorithm (the paper's with
//! `faithful`), then the `--config` file, then the flags; each layer a TOML table laid
//! over the one below ([`overlay`]), read back as a RunConfig and validated.

use crate::config::{
    Algo, DeltaTarget, Mode, ObsNorm, OptimizerKind, PretrainConfig, RunConfig, SampleDistribution,
    DEFAULT_MAX_LAG,
};
use crate::env::{EnvBounds, EnvKind, EnvLayout, EnvSpec, SuccessRule};
use crate::{CoreError, Result};
use clap::Args;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

mod help;
pub use help::help;

/// Env of a run with no `--env`.
pub const DEFAULT_ENV: EnvKind = EnvKind::Angle;
/// Algorithm with no `--algo`: A2C trains the default run in ~15 s; SAVER needs a
/// PCPN first.
pub const DEFAULT_ALGO: Algo = Algo::A2c;
/// Length of a run in env steps with no `--steps`.
pub const DEFAULT_STEPS: u64 = 1_000_000;

/// The environment: `[env]` in a file.
#[derive(Args, Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct EnvSettings {
    /// Environment preset [default: angle]
    #[arg(id = "env", long = "env", value_name = "ENV", value_enum)]
    pub kind: Option<EnvKind>,
    /// State dimension d: the help lists every preset's (from the table).
    #[arg(long, help = crate::env::dim_help())]
    pub dim: Option<usize>,
    /// A custom env's name (config files only; with `layout` and `bounds`).
    #[arg(skip)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// A custom env's layout.
    #[arg(skip)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layout: Option<EnvLayout>,
    /// A custom env's bounds.
    #[arg(skip)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bounds: Option<EnvBounds>,
    /// A custom env's success rule (optional: without it the env's own word is taken).
    #[arg(skip)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub success: Option<SuccessRule>,
}

impl EnvSettings {
    /// The env these settings name: a custom env when they give its name, else a
    /// preset (angle, d = 4 by default).
    pub fn spec(&self) -> Result<EnvSpec> {
        if let Some(name) = &self.name {
            if self.kind.is_some() {
                return Err(config_err(format!(
                    "env: {name:?} is a custom env; it takes no preset kind"
                )));
            }
            let (Some(layout), Some(bounds)) = (self.layout, self.bounds.clone()) else {
                return Err(config_err(format!(
                    "env {name:?}: a custom env needs its layout and bounds"
                )));
            };
            let spec = EnvSpec::custom(name, layout, bounds)?.with_success(self.success)?;
            if self.dim.is_some_and(|d| d != spec.dim()) {
                return Err(config_err(format!(
                    "env {name:?}: dim is its layout's aligned_dim, {}",
                    spec.dim()
                )));
            }
            return Ok(spec);
        }
        let kind = self.kind.unwrap_or(DEFAULT_ENV);
        let dim = self.dim.unwrap_or(kind.preset().default_dim);
        EnvSpec::new(kind, dim)
    }
}

/// PCPN pretraining: `[pretrain]` in a file.
#[derive(Args, Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PretrainSettings {
    #[arg(id = "pretrain_optimizer", value_name = "OPTIMIZER", long = "pretrain-optimizer", value_enum, help = help("Pretraining optimiser (TF1 constants)", "pretrain.optimizer"))]
    pub optimizer: Option<OptimizerKind>,
    #[arg(id = "pretrain_lr", value_name = "LR", long = "pretrain-lr", allow_hyphen_values = true, help = help("Pretraining learning rate", "pretrain.lr"))]
    pub lr: Option<f64>,
    #[arg(id = "pretrain_batches", value_name = "N", long = "pretrain-batches", visible_alias = "batches", help = help("Pretraining batches (fresh samples each)", "pretrain.batches"))]
    pub batches: Option<u64>,
    #[arg(id = "pretrain_batch_size", value_name = "N", long = "pretrain-batch-size", help = help("Transitions per pretraining batch", "pretrain.batch_size"))]
    pub batch_size: Option<usize>,
    #[arg(id = "pretrain_quantiles", value_name = "K", long = "pretrain-quantiles", help = help("τ samples per pretraining transition", "pretrain.quantiles"))]
    pub quantiles: Option<usize>,
    #[arg(id = "pretrain_seed", value_name = "SEED", long = "pretrain-seed", help = help("Seed of the PCPN's weights, samples and τ draws (apart from --seed, so runs of an env share a PCPN)", "pretrain.seed"))]
    pub seed: Option<u64>,
    #[arg(id = "pretrain_samples", value_name = "SAMPLES", long = "pretrain-samples", value_enum, help = help("Pretraining sample distribution", "pretrain.samples"))]
    pub samples: Option<SampleDistribution>,
    #[arg(id = "pretrain_walk_samples", value_name = "N", long = "pretrain-walk-samples", help = help("A custom env's distinct streamed transitions, each batch drawn from them (0: fresh ones for every batch row)", "pretrain.walk_samples"))]
    pub walk_samples: Option<u64>,
}

/// The policy head's bounds: `[head]` in a file.
#[derive(Args, Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HeadSettings {
    #[arg(long, allow_hyphen_values = true, help = help("Bound the policy mean: μ = bound·tanh(raw); inf: unbounded linear μ", "head.mu_bound"))]
    pub mu_bound: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("Lower clamp of log σ (-inf: none)", "head.log_std_min"))]
    pub log_std_min: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("Upper clamp of log σ (inf: none)", "head.log_std_max"))]
    pub log_std_max: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("log σ before the first update", "head.log_std_init"))]
    pub log_std_init: Option<f64>,
}

/// SAVER's loss: `[saver]` in a file.
#[derive(Args, Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SaverSettings {
    #[arg(long, help = help("SAVER: τ samples K per transition", "saver.quantiles"))]
    pub quantiles: Option<usize>,
    #[arg(long, allow_hyphen_values = true, help = help("SAVER: κ of the Huber quantile loss (0: the plain quantile loss)", "saver.kappa"))]
    pub kappa: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("SAVER: weight of the monotonic penalty", "saver.lambda_mon"))]
    pub lambda_mon: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("SAVER: weight of the vector critic's squared error", "saver.lambda_critic"))]
    pub lambda_critic: Option<f64>,
    #[arg(long, help = help("SAVER: centre the vector advantage per dimension over each batch and scale it", "saver.adv_norm"))]
    pub adv_norm: Option<bool>,
    #[arg(long, help = help("SAVER: with --adv-norm, one standard deviation over every dimension instead of one per dimension", "saver.adv_norm_joint"))]
    pub adv_norm_joint: Option<bool>,
    #[arg(long, allow_hyphen_values = true, help = help("SAVER: weight of the penalty on the mean head's raw output beyond ±2 (0: off)", "saver.mu_raw_penalty"))]
    pub mu_raw_penalty: Option<f64>,
    #[arg(long, value_delimiter = ',', value_name = "ENTRIES", help = help("SAVER: the mean entries (0-based, comma-separated) --mu-raw-penalty applies to, none given: all; on angle 1,3,5,... are the angles", "saver.mu_raw_penalty_entries"))]
    pub mu_raw_penalty_entries: Option<Vec<usize>>,
    #[arg(long = "saver-target", value_enum, help = help("SAVER: the actor loss's target: the observed position change (the paper), the PCPN's prediction for the action taken, or the PCPN's quantile at the rank of the action's own noise (noise; both for envs where one step's change is mostly velocity)", "saver.target"))]
    #[serde(rename = "target")]
    pub saver_target: Option<DeltaTarget>,
    #[arg(long, allow_hyphen_values = true, help = help("SAVER: learning rate of the PCPN's own training on the policy's steps during the run (one step per update; 0: frozen, the paper)", "saver.pcpn_tune_lr"))]
    pub pcpn_tune_lr: Option<f64>,
    #[arg(long, value_name = "N", help = help("SAVER: rows of each batch, drawn at random, that the PCPN's training step of --pcpn-tune-lr reads (0: every row)", "saver.pcpn_tune_rows"))]
    pub pcpn_tune_rows: Option<usize>,
    #[arg(id = "saver_epochs", value_name = "N", long = "saver-epochs", help = help("SAVER: passes over each batch, each in shuffled minibatches of --saver-minibatch-size steps (one optimiser step each)", "saver.epochs"))]
    #[serde(rename = "epochs")]
    pub saver_epochs: Option<usize>,
    #[arg(id = "saver_minibatch_size", value_name = "N", long = "saver-minibatch-size", help = help("SAVER: steps per minibatch of --saver-epochs (0: the whole batch)", "saver.minibatch_size"))]
    #[serde(rename = "minibatch_size")]
    pub saver_minibatch_size: Option<usize>,
    #[arg(id = "saver_gae_lambda", value_name = "LAMBDA", long = "saver-gae-lambda", allow_hyphen_values = true, help = help("SAVER: λ of GAE(λ) on the vector critic, per coordinate (1: the rollout's n-step returns, the paper)", "saver.gae_lambda"))]
    #[serde(rename = "gae_lambda")]
    pub saver_gae_lambda: Option<f64>,
    #[arg(id = "saver_env_gae_lambda", value_name = "LAMBDA", long = "saver-env-gae-lambda", allow_hyphen_values = true, help = help("SAVER: λ of GAE(λ) on the env-return term's scalar critic (1: the rollout's n-step returns)", "saver.env_gae_lambda"))]
    #[serde(rename = "env_gae_lambda")]
    pub saver_env_gae_lambda: Option<f64>,
    #[arg(id = "saver_target_kl", value_name = "KL", long = "saver-target-kl", help = help("SAVER: stop --saver-epochs' passes over a batch once a minibatch's approximate KL to the behaviour policy is above this (0: off)", "saver.target_kl"))]
    #[serde(rename = "target_kl")]
    pub saver_target_kl: Option<f64>,
    #[arg(id = "saver_env_reward", value_name = "W", long = "saver-env-reward", allow_hyphen_values = true, help = help("SAVER: weight of the env-return term, a scalar critic and policy gradient on the env's own reward where the actors send one that is not the progress reward (0: off, the paper)", "saver.env_reward"))]
    #[serde(rename = "env_reward")]
    pub saver_env_reward: Option<f64>,
    #[arg(id = "saver_env_clip", value_name = "EPS", long = "saver-env-clip", help = help("SAVER: ε of PPO's clip on the env-return term's policy gradient, the ratio taken to the policy that acted (it bites over --saver-epochs' passes and minibatches, and on lagged async batches; 0: off)", "saver.env_clip"))]
    #[serde(rename = "env_clip")]
    pub saver_env_clip: Option<f64>,
    #[arg(id = "saver_obs_norm", value_name = "MODE", long = "saver-obs-norm", value_enum, help = help("SAVER: how the agent and critics see the observations: raw (off), by their running mean and variance (running), the aligned position and goal entries alone by theirs (aligned; auto: so where the first batch finds the position spread under a third of the widest other entry, else raw), or mapped from the env's declared bounds to [-1, 1] (bounds); the mean and scale travel with the weights, the PCPN reads them raw", "saver.obs_norm"))]
    #[serde(rename = "obs_norm")]
    pub saver_obs_norm: Option<ObsNorm>,
}

/// Standalone QRRL's settings: `[qrrl]` in a file (a file of an earlier version with
/// them in `[saver]` is read too: [`crate::config::upgrade`]).
#[derive(Args, Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct QrrlSettings {
    #[arg(id = "qrrl_spread", value_name = "S", long = "qrrl-spread", allow_hyphen_values = true, help = help("QRRL: half-width s of the base quantile function s·(2τ − 1) added to the policy's output (its initial policy is U(−s, s))", "qrrl.spread"))]
    pub spread: Option<f64>,
    #[arg(id = "qrrl_vector", value_name = "BOOL", long = "qrrl-vector", help = help("QRRL: vector critic and per-coordinate advantages on each aligned action dim (envs point, bandit)", "qrrl.vector"))]
    pub vector: Option<bool>,
}

/// PPO's constants: `[ppo]` in a file.
#[derive(Args, Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PpoSettings {
    #[arg(id = "ppo_epochs", value_name = "N", long = "ppo-epochs", help = help("PPO: passes over each batch", "ppo.epochs"))]
    pub epochs: Option<usize>,
    #[arg(id = "ppo_minibatch_size", value_name = "N", long = "ppo-minibatch-size", help = help("PPO: steps per minibatch", "ppo.minibatch_size"))]
    pub minibatch_size: Option<usize>,
    #[arg(id = "ppo_clip", value_name = "EPS", long = "ppo-clip", allow_hyphen_values = true, help = help("PPO: ε of the clipped surrogate", "ppo.clip"))]
    pub clip: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("PPO: λ of GAE(λ)", "ppo.gae_lambda"))]
    pub gae_lambda: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("PPO: clip the value's move from its value at the batch's start (0: unclipped)", "ppo.value_clip"))]
    pub value_clip: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("PPO: weight of the entropy bonus", "ppo.entropy_coef"))]
    pub entropy_coef: Option<f64>,
    #[arg(id = "ppo_adv_norm", value_name = "BOOL", long = "ppo-adv-norm", help = help("PPO: normalise each minibatch's advantages", "ppo.adv_norm"))]
    pub adv_norm: Option<bool>,
    #[arg(id = "ppo_vector", value_name = "BOOL", long = "ppo-vector", help = help("PPO: a vector critic on the vector reward, GAE per coordinate, the advantage their sum", "ppo.vector"))]
    pub vector: Option<bool>,
    #[arg(id = "ppo_obs_norm", value_name = "BOOL", long = "ppo-obs-norm", help = help("PPO: normalise observations by a running mean and variance, carried in the weights (SB3's VecNormalize)", "ppo.obs_norm"))]
    pub obs_norm: Option<bool>,
    #[arg(id = "ppo_reward_norm", value_name = "BOOL", long = "ppo-reward-norm", help = help("PPO: scale rewards by a running std of the discounted return, clipped to ±10 (SB3's VecNormalize)", "ppo.reward_norm"))]
    pub reward_norm: Option<bool>,
    #[arg(id = "ppo_env_reward", value_name = "BOOL", long = "ppo-env-reward", help = help("PPO: learn from the env's own reward (a Python actor's env) instead of the progress reward", "ppo.env_reward"))]
    pub env_reward: Option<bool>,
}

/// Every setting of a run, each optional: flags, or a `--config` file (the same names
/// as TOML keys; unknown keys are errors).
#[derive(Args, Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RunSettings {
    /// TOML file with any of these settings (a run's config.toml repeats that run;
    /// flags win over it)
    #[arg(long, value_name = "FILE")]
    #[serde(skip)]
    pub config: Option<PathBuf>,
    /// Start from the paper's published settings for every field (SAVER: TF1 RMSProp
    /// at the paper's rate, unbounded μ and log σ, raw advantages, a PCPN pretrained
    /// the paper's number of batches) instead of the defaults that make SAVER learn
    #[arg(long)]
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub faithful: bool,
    /// Algorithm [default: a2c]
    #[arg(long, value_enum)]
    pub algo: Option<Algo>,
    #[arg(long, help = help("Env steps (transitions) to train for", "steps"))]
    pub steps: Option<u64>,
    #[arg(long, help = help("Base seed of every random stream of the run", "seed"))]
    pub seed: Option<u64>,
    #[arg(long, help = help("Actors (sync: rollouts per update)", "actors"))]
    pub actors: Option<u32>,
    #[arg(long, help = help("Env instances per actor", "envs"))]
    pub envs: Option<u32>,
    #[arg(long, value_enum, help = help("Batching: one rollout per actor per version (sync) or any recent rollouts (async)", "mode"))]
    pub mode: Option<Mode>,
    /// Async mode: the largest policy lag accepted (refused in sync mode) [default: 4]
    #[arg(long)]
    pub max_lag: Option<u64>,
    #[arg(long, help = help("Rollout length n", "rollout"))]
    pub rollout: Option<u32>,
    #[arg(long, allow_hyphen_values = true, help = help("Discount γ", "gamma"))]
    pub gamma: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("Learning rate", "lr"))]
    pub lr: Option<f64>,
    #[arg(long, value_enum, help = help("Optimiser (TF1 constants)", "optimizer"))]
    pub optimizer: Option<OptimizerKind>,
    #[arg(long, help = help("Let the learning rate fall linearly to zero over the run", "lr_decay"))]
    pub lr_decay: Option<bool>,
    #[arg(long, allow_hyphen_values = true, help = help("Clip each update's global gradient norm to this (inf: no clipping)", "grad_clip"))]
    pub grad_clip: Option<f64>,
    #[arg(long, help = help("Episode step limit", "max_episode_steps"))]
    pub max_episode_steps: Option<u32>,
    #[arg(long, help = help("At the step limit, bootstrap the return from the value of the state reached (the paper: the limit is terminal)", "bootstrap_timeout"))]
    pub bootstrap_timeout: Option<bool>,
    #[arg(long, help = help("Custom env: the actors credit a step that ends inside the success box with each coordinate's remaining distance |p' − g| (the default progress reward only)", "complete_at_success"))]
    pub complete_at_success: Option<bool>,
    #[arg(long, help = help("Custom env: the actors go on past success until the env ends the episode or the step limit (success: ending inside the box), so the policy learns what to do at the goal", "continue_past_success"))]
    pub continue_past_success: Option<bool>,
    #[arg(long, allow_hyphen_values = true, help = help("A2C: weight of the value loss", "value_coef"))]
    pub value_coef: Option<f64>,
    #[arg(long, help = help("Correct rollouts acted by an older policy (async) with V-trace targets and ratio-weighted advantages (A2C, SAVER)", "vtrace"))]
    pub vtrace: Option<bool>,
    #[arg(long, allow_hyphen_values = true, help = help("V-trace: clip ρ̄ of the ratio that weighs each step's TD error and advantage", "rho_bar"))]
    pub rho_bar: Option<f64>,
    #[arg(long, allow_hyphen_values = true, help = help("V-trace: clip c̄ of the ratio that carries later corrections back", "c_bar"))]
    pub c_bar: Option<f64>,
    #[arg(long, value_delimiter = ',', value_name = "WIDTHS", help = help("Hidden layer widths of the policy's trunk and of the critic, e.g. 64,64", "hidden"))]
    pub hidden: Option<Vec<usize>>,
    /// The environment.
    #[command(flatten)]
    #[serde(default)]
    pub env: EnvSettings,
    /// The policy head.
    #[command(flatten)]
    #[serde(default)]
    pub head: HeadSettings,
    /// SAVER's loss.
    #[command(flatten)]
    #[serde(default)]
    pub saver: SaverSettings,
    /// Standalone QRRL's settings.
    #[command(flatten)]
    #[serde(default)]
    pub qrrl: QrrlSettings,
    /// PPO's constants.
    #[command(flatten)]
    #[serde(default)]
    pub ppo: PpoSettings,
    /// PCPN pretraining.
    #[command(flatten)]
    #[serde(default)]
    pub pretrain: PretrainSettings,
    /// SAVER: use only the PCPN with this weights sha256 (a run's config.toml names
    /// the one it used)
    #[arg(long, value_name = "SHA256")]
    pub pcpn_sha256: Option<String>,
}

fn config_err(why: impl std::fmt::Display) -> CoreError {
    CoreError::Config(why.to_string())
}

/// Lays `top` over `base`: every key of `top` replaces `base`'s, tables key by key.
pub fn overlay(base: &mut toml::Table, top: toml::Table) {
    for (k, v) in top {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(t)) => overlay(b, t),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

fn table_of<T: Serialize>(v: &T) -> Result<toml::Table> {
    toml::Table::try_from(v).map_err(config_err)
}

/// A config's settings by their dotted config.toml names (`head.log_std_min`), each
/// value as the file writes it (strings without quotes): what `--help` shows as a
/// default and `saver plot` compares to name what a run changed.
pub fn dotted(c: &RunConfig) -> std::collections::BTreeMap<String, String> {
    fn walk(prefix: &str, t: &toml::Table, out: &mut std::collections::BTreeMap<String, String>) {
        for (k, v) in t {
            let name = if prefix.is_empty() {
                k.clone()
            } else {
                format!("{prefix}.{k}")
            };
            match v {
                toml::Value::Table(t) => walk(&name, t, out),
                toml::Value::String(s) => {
                    out.insert(name, s.clone());
                }
                v => {
                    out.insert(name, v.to_string());
                }
            }
        }
    }
    let mut out = std::collections::BTreeMap::new();
    walk("", &table_of(c).unwrap_or_default(), &mut out);
    out
}

impl RunSettings {
    /// Reads a `--config` file.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| config_err(format!("reading config file {}: {e}", path.display())))?;
        let bad = |e: String| config_err(format!("config file {}: {e}", path.display()));
        let mut top: toml::Table = toml::from_str(&text).map_err(|e| bad(e.to_string()))?;
        crate::config::upgrade::upgrade_toml(&mut top);
        toml::Value::Table(top)
            .try_into()
            .map_err(|e: toml::de::Error| bad(e.to_string()))
    }

    /// Flags over the `--config` file over the defaults, validated.
    pub fn resolve(&self) -> Result<RunConfig> {
        let file = match &self.config {
            Some(p) => Self::read(p)?,
            None => Self::default(),
        };
        if let (Some(f), Some(a)) = (file.algo, self.algo) {
            if f != a {
                return Err(config_err(format!(
                    "--algo {}: the config file {} holds {} settings (its learning rate, \
                     optimiser and head would apply unchanged); drop --algo to repeat that \
                     run, or leave out --config to start from {}'s defaults",
                    a.name(),
                    self.config.as_deref().unwrap_or(Path::new("")).display(),
                    f.name(),
                    a.name()
                )));
            }
        }
        let mut top = table_of(&file)?;
        if self.mode == Some(Mode::Sync) && self.max_lag.is_none() {
            // A file of an async run switched to sync by flag: its lag no longer applies.
            top.remove("max_lag");
        }
        overlay(&mut top, table_of(self)?);
        let merged: RunSettings = toml::Value::Table(top.clone())
            .try_into()
            .map_err(config_err)?;
        let env = merged.env.spec()?;
        let algo = merged.algo.unwrap_or(DEFAULT_ALGO);
        let steps = merged.steps.unwrap_or(DEFAULT_STEPS);
        let base = if self.faithful || file.faithful {
            RunConfig::paper(&env, algo, steps)
        } else {
            crate::algo::recommended(&env, algo, steps)
        };
        let mut table = table_of(&base)?;
        top.remove("faithful");
        // The base holds the env as resolved above.
        top.remove("env");
        overlay(&mut table, top);
        if merged.mode == Some(Mode::Async) && merged.max_lag.is_none() {
            table.insert(
                "max_lag".into(),
                toml::Value::Integer(DEFAULT_MAX_LAG as i64),
            );
        }
        let config: RunConfig = toml::Value::Table(table).try_into().map_err(config_err)?;
        crate::algo::validate(&config)?;
        Ok(config)
    }

    /// The env and pretraining settings alone (what `saver pretrain` uses).
    pub fn resolve_pretrain(&self) -> Result<(EnvSpec, PretrainConfig)> {
        let c = RunSettings {
            algo: Some(Algo::Saver),
            ..self.clone()
        }
        .resolve()?;
        Ok((c.env, c.pretrain))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("saver-settings-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    /// A written config.toml reads back as settings that resolve to the same config,
    /// on any base: the faithful SAVER's unbounded head and an A2C base included.
    #[test]
    fn written_config_resolves_back_equal() {
        let env = EnvSpec::new(EnvKind::Select, 5).unwrap();
        let mut bounded = crate::algo::recommended(&env, Algo::Saver, 1000);
        bounded.saver.kappa = Some(0.01);
        bounded.seed = 9;
        bounded.grad_clip = Some(0.5);
        bounded.mode = Mode::Async;
        bounded.max_lag = Some(2);
        bounded.pretrain.seed = 4;
        // A user's env, written as name, layout and bounds.
        let layout = EnvLayout {
            obs_dim: 3,
            continuous: 1,
            choices: 2,
            aligned_start: 1,
            aligned_dim: 2,
        };
        let bounds = EnvBounds {
            obs_low: vec![-1.0, -0.5, -0.5],
            obs_high: vec![1.0, 0.5, 0.5],
            max_change: 0.02,
        };
        let custom = EnvSpec::custom("maze", layout, bounds).unwrap();
        let custom = crate::algo::recommended(&custom, Algo::Saver, 1000);
        for c in [bounded, RunConfig::paper(&env, Algo::Saver, 1000), custom] {
            let p = temp("run.toml");
            std::fs::write(&p, c.to_toml()).unwrap();
            let back = RunSettings {
                config: Some(p.clone()),
                ..Default::default()
            }
            .resolve()
            .unwrap();
            assert_eq!(back, c);
            std::fs::remove_file(p).ok();
        }
    }

    /// `hidden` from a file, a flag over it, the paper's widths without either, and
    /// the refusals (each names the field): no layer, a zero width, nine layers, a
    /// network over the weights message ([4096, 4096, 4096]: two 4097 × 4096 layers
    /// ≈ 33.6 M > 8.39 M values; [2048, 2048]: one 2049 × 2048 ≈ 4.2 M, which fits).
    #[test]
    fn hidden_widths_resolve_and_bad_ones_are_refused() {
        let p = temp("hidden.toml");
        std::fs::write(&p, "algo = \"ppo\"\nhidden = [32]\n").unwrap();
        let file = RunSettings {
            config: Some(p.clone()),
            ..Default::default()
        };
        assert_eq!(file.resolve().unwrap().hidden, [32]);
        let flag = |h: Vec<usize>| RunSettings {
            hidden: Some(h),
            ..file.clone()
        };
        assert_eq!(flag(vec![64, 64]).resolve().unwrap().hidden, [64, 64]);
        assert_eq!(
            RunSettings::default().resolve().unwrap().hidden,
            crate::config::PAPER_HIDDEN
        );
        assert_eq!(
            flag(vec![2048, 2048]).resolve().unwrap().hidden,
            [2048, 2048]
        );
        for bad in [vec![], vec![64, 0], vec![8; 9], vec![4096, 4096, 4096]] {
            let e = flag(bad.clone()).resolve().unwrap_err().to_string();
            assert!(e.contains("hidden"), "{bad:?}: {e}");
        }
        std::fs::remove_file(p).ok();
    }

    /// Flags win over the file; the file over the defaults; unbounded values by name.
    #[test]
    fn flags_over_file_over_defaults() {
        let p = temp("partial.toml");
        std::fs::write(&p, "algo = \"saver\"\nlr = 0.5\n[head]\nmu_bound = inf\n").unwrap();
        let s = RunSettings {
            config: Some(p.clone()),
            lr: Some(0.25),
            head: HeadSettings {
                log_std_min: Some(-3.0),
                log_std_max: Some(f64::INFINITY),
                ..Default::default()
            },
            ..Default::default()
        };
        let c = s.resolve();
        // An open upper side of the clamp is named, not silently dropped.
        assert!(c.unwrap_err().to_string().contains("log_std"));
        let s = RunSettings {
            head: HeadSettings {
                log_std_min: Some(-3.0),
                log_std_max: Some(-1.0),
                ..Default::default()
            },
            ..s
        };
        let c = s.resolve().unwrap();
        assert_eq!(c.algo, Algo::Saver);
        assert_eq!(c.lr, 0.25);
        assert_eq!(c.head.mu_bound, None);
        assert_eq!(c.head.log_std_bounds, Some((-3.0, -1.0)));
        // The rest is SAVER's default.
        assert!(c.saver.adv_norm_joint);
        assert_eq!(c.optimizer, OptimizerKind::Adam);
        std::fs::remove_file(p).ok();
    }

    #[test]
    fn impossible_combinations_and_unknown_keys_are_refused() {
        let lag = RunSettings {
            max_lag: Some(3),
            ..Default::default()
        };
        assert!(lag.resolve().unwrap_err().to_string().contains("max_lag"));
        let async_default = RunSettings {
            mode: Some(Mode::Async),
            ..Default::default()
        };
        let async_run = async_default.resolve().unwrap();
        assert_eq!(async_run.max_lag, Some(DEFAULT_MAX_LAG));
        // An async run's file with --mode sync: a sync run, its lag dropped.
        let p = temp("async.toml");
        std::fs::write(&p, async_run.to_toml()).unwrap();
        let sync = RunSettings {
            config: Some(p.clone()),
            mode: Some(Mode::Sync),
            ..Default::default()
        }
        .resolve()
        .unwrap();
        assert_eq!((sync.mode, sync.max_lag), (Mode::Sync, None));
        std::fs::remove_file(p).ok();
        let p = temp("unknown.toml");
        std::fs::write(&p, "[saver]\nquantile = 3\n").unwrap();
        let e = RunSettings::read(&p).unwrap_err().to_string();
        assert!(e.contains("quantile"), "{e}");
        std::fs::write(&p, "algo = \"a2c\"\n").unwrap();
        let e = RunSettings {
            config: Some(p.clone()),
            algo: Some(Algo::Saver),
            ..Default::default()
        }
        .resolve()
        .unwrap_err()
        .to_string();
        assert!(e.contains("a2c settings"), "{e}");
        std::fs::remove_file(p).ok();
    }

    /// `--faithful` selects the paper's pretraining, so it never shares a PCPN with
    /// the default.
    #[test]
    fn faithful_pretraining_has_its_own_key() {
        let d = RunSettings::default().resolve_pretrain().unwrap();
        let f = RunSettings {
            faithful: true,
            ..Default::default()
        }
        .resolve_pretrain()
        .unwrap();
        assert_eq!(d.1.batches, 5_000);
        assert_eq!(f.1.batches, 100_000);
        assert_ne!(d.1.key(&d.0), f.1.key(&f.0));
    }

    /// Every flag has its own id (a flattened field of the same name as another would
    /// silently feed both) and clap's own checks pass.
    #[test]
    fn flags_are_well_formed() {
        use clap::{Args, Command};
        RunSettings::augment_args(Command::new("train")).debug_assert();
        let m = RunSettings::augment_args(Command::new("train"))
            .try_get_matches_from([
                "train",
                "--lr",
                "0.5",
                "--pretrain-lr",
                "0.25",
                "--log-std-min",
                "-4.6",
                "--log-std-max",
                "-inf",
            ])
            .unwrap();
        let s = <RunSettings as clap::FromArgMatches>::from_arg_matches(&m).unwrap();
        assert_eq!(s.lr, Some(0.5));
        assert_eq!(s.pretrain.lr, Some(0.25));
        assert_eq!(s.head.log_std_min, Some(-4.6));
        assert_eq!(s.head.log_std_max, Some(f64::NEG_INFINITY));
    }
}
