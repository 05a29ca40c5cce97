//! Flags and config files become one validated [`RunConfig`], here and nowhere else.
//! Precedence: flags over the `--config` TOML file over the defaults (the paper's
//! settings for the chosen env and algorithm; see the README for the embedded default).

use anyhow::{bail, Context, Result};
use clap::Args;
use saver_core::config::{Algo, Mode, RunConfig};
use saver_core::env::{EnvKind, EnvSpec};
use saver_core::optim::OptimizerConfig;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// Default env of `saver train` with no flags: learns visibly in ~5 minutes on 2 cores.
pub const DEFAULT_ENV: &str = "angle";
/// Default dimension.
pub const DEFAULT_DIM: usize = 4;
/// Default algorithm: A2C trains the default run in ~30 s; SAVER needs a PCPN first.
pub const DEFAULT_ALGO: &str = "a2c";
/// Default length of a run in env steps.
pub const DEFAULT_STEPS: u64 = 1_000_000;

/// Settings shared by every command that defines a run.
#[derive(Args, Clone, Debug, Default)]
pub struct RunArgs {
    /// TOML file with any of the settings below (flags win over it).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Environment: angle, select or arm.
    #[arg(long)]
    pub env: Option<String>,
    /// State dimension d (angle: even; arm: 2).
    #[arg(long)]
    pub dim: Option<usize>,
    /// Algorithm: saver or a2c.
    #[arg(long)]
    pub algo: Option<String>,
    /// Start from the paper's published settings for every field (SAVER: TF1 RMSProp
    /// at lr 0.01, unbounded μ and log σ, no advantage normalisation, the paper's
    /// pretraining length) instead of the defaults that make SAVER learn.
    #[arg(long)]
    pub faithful: bool,
    /// Env steps (transitions) to train for.
    #[arg(long)]
    pub steps: Option<u64>,
    /// Base seed of every random stream.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Number of actors.
    #[arg(long)]
    pub actors: Option<u32>,
    /// Env instances per actor.
    #[arg(long)]
    pub envs: Option<u32>,
    /// Batching: sync (one rollout per actor per version) or async.
    #[arg(long)]
    pub mode: Option<String>,
    /// Async mode: largest policy lag accepted.
    #[arg(long)]
    pub max_lag: Option<u64>,
    /// Rollout length n.
    #[arg(long)]
    pub rollout: Option<u32>,
    /// Learning rate (default: the paper's for env and algorithm).
    #[arg(long)]
    pub lr: Option<f64>,
    /// Discount γ.
    #[arg(long)]
    pub gamma: Option<f64>,
    /// Optimizer: rmsprop (TF1, the paper's) or adam (TF1).
    #[arg(long)]
    pub optimizer: Option<String>,
    /// Episode step limit.
    #[arg(long)]
    pub max_episode_steps: Option<u32>,
    /// SAVER: quantile copies K per transition.
    #[arg(long)]
    pub quantiles: Option<usize>,
    /// SAVER: κ of the Huber quantile loss (default: the plain quantile loss).
    #[arg(long)]
    pub kappa: Option<f64>,
    /// SAVER: weight of the monotonic penalty.
    #[arg(long)]
    pub lambda_mon: Option<f64>,
    /// PCPN pretraining batches (default: the paper's for the env).
    #[arg(long)]
    pub pretrain_batches: Option<u64>,
    /// PCPN pretraining learning rate (default: 0.1 × the SAVER rate).
    #[arg(long)]
    pub pretrain_lr: Option<f64>,
    /// Bound the policy mean: μ = bound·tanh(raw) (default: unbounded, as the paper).
    #[arg(long)]
    pub mu_bound: Option<f64>,
    /// Lower clamp of log σ (needs --log-std-max too).
    #[arg(long, requires = "log_std_max")]
    pub log_std_min: Option<f64>,
    /// Upper clamp of log σ (needs --log-std-min too).
    #[arg(long, requires = "log_std_min")]
    pub log_std_max: Option<f64>,
    /// SAVER: normalise the vector advantage per dimension over each batch.
    #[arg(long)]
    pub adv_norm: Option<bool>,
    /// SAVER: with --adv-norm, one standard deviation over every dimension instead of
    /// one per dimension.
    #[arg(long)]
    pub adv_norm_joint: Option<bool>,
    /// Clip each update's global gradient norm to this.
    #[arg(long)]
    pub grad_clip: Option<f64>,
    /// Let the learning rate fall linearly to zero over the run's updates.
    #[arg(long)]
    pub lr_decay: Option<bool>,
    /// At the episode step limit, bootstrap the return from the value of the state
    /// reached (the paper: the limit is terminal).
    #[arg(long)]
    pub bootstrap_timeout: Option<bool>,
    /// SAVER: weight of the penalty on the mean head's raw output beyond ±2 (keeps
    /// tanh(raw) out of saturation; 0: off).
    #[arg(long)]
    pub mu_raw_penalty: Option<f64>,
}

/// The same settings as a TOML file; unknown keys are errors.
#[derive(Deserialize, Default, Debug)]
#[serde(deny_unknown_fields)]
struct FileConfig {
    env: Option<String>,
    dim: Option<usize>,
    algo: Option<String>,
    faithful: Option<bool>,
    steps: Option<u64>,
    seed: Option<u64>,
    actors: Option<u32>,
    envs: Option<u32>,
    mode: Option<String>,
    max_lag: Option<u64>,
    rollout: Option<u32>,
    lr: Option<f64>,
    gamma: Option<f64>,
    optimizer: Option<String>,
    max_episode_steps: Option<u32>,
    quantiles: Option<usize>,
    kappa: Option<f64>,
    lambda_mon: Option<f64>,
    pretrain_batches: Option<u64>,
    pretrain_lr: Option<f64>,
    mu_bound: Option<f64>,
    log_std_min: Option<f64>,
    log_std_max: Option<f64>,
    adv_norm: Option<bool>,
    adv_norm_joint: Option<bool>,
    grad_clip: Option<f64>,
    lr_decay: Option<bool>,
    bootstrap_timeout: Option<bool>,
    mu_raw_penalty: Option<f64>,
}

/// `saver train` flags.
#[derive(Args, Clone, Debug)]
pub struct TrainArgs {
    /// The run's settings.
    #[command(flatten)]
    pub run: RunArgs,
    /// Run folder (default: runs/<env>-<algo>-seed<seed>-<unix time>).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Folder of cached PCPNs, one per env spec.
    #[arg(long, value_name = "DIR", default_value = "pcpn-cache")]
    pub pcpn_dir: PathBuf,
    /// Use this PCPN file (refused if it was pretrained for another env spec).
    #[arg(long, value_name = "FILE")]
    pub pcpn: Option<PathBuf>,
}

fn parse_optimizer(s: &str) -> Result<OptimizerConfig> {
    match s {
        "rmsprop" => Ok(OptimizerConfig::RMSPROP_TF1),
        "adam" => Ok(OptimizerConfig::ADAM_TF1),
        other => bail!("optimizer: unknown optimizer {other:?} (expected rmsprop or adam)"),
    }
}

fn read_file(path: &Path) -> Result<FileConfig> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading config file {}", path.display()))?;
    toml::from_str(&text).with_context(|| format!("config file {}", path.display()))
}

impl RunArgs {
    /// Resolves flags, file and defaults into a validated config.
    pub fn resolve(&self) -> Result<RunConfig> {
        let f = match &self.config {
            Some(p) => read_file(p)?,
            None => FileConfig::default(),
        };
        macro_rules! pick {
            ($name:ident) => {
                self.$name.clone().or(f.$name.clone())
            };
        }
        let kind = EnvKind::parse(&pick!(env).unwrap_or_else(|| DEFAULT_ENV.into()))?;
        let default_dim = if kind == EnvKind::Arm { 2 } else { DEFAULT_DIM };
        let dim = pick!(dim).unwrap_or(default_dim);
        let env = EnvSpec::new(kind, dim)?;
        let algo = Algo::parse(&pick!(algo).unwrap_or_else(|| DEFAULT_ALGO.into()))?;
        let steps = pick!(steps).unwrap_or(DEFAULT_STEPS);
        let mut c = if self.faithful || f.faithful.unwrap_or(false) {
            RunConfig::paper(env, algo, steps)
        } else {
            RunConfig::recommended(env, algo, steps)
        };
        if let Some(v) = pick!(seed) {
            c.seed = v;
        }
        if let Some(v) = pick!(actors) {
            c.actors = v;
        }
        if let Some(v) = pick!(envs) {
            c.envs_per_actor = v;
        }
        if let Some(v) = pick!(mode) {
            c.mode = Mode::parse(&v)?;
        }
        if let Some(v) = pick!(max_lag) {
            c.max_lag = v;
        }
        if let Some(v) = pick!(rollout) {
            c.rollout = v;
        }
        if let Some(v) = pick!(lr) {
            c.lr = v;
        }
        if let Some(v) = pick!(gamma) {
            c.gamma = v;
        }
        if let Some(v) = pick!(optimizer) {
            c.optimizer = parse_optimizer(&v)?;
        }
        if let Some(v) = pick!(max_episode_steps) {
            c.max_episode_steps = v;
        }
        if let Some(v) = pick!(quantiles) {
            c.saver.quantiles = v;
        }
        if let Some(v) = pick!(kappa) {
            c.saver.kappa = Some(v);
        }
        if let Some(v) = pick!(lambda_mon) {
            c.saver.lambda_mon = v;
        }
        if let Some(v) = pick!(pretrain_batches) {
            c.pretrain.batches = v;
        }
        if let Some(v) = pick!(pretrain_lr) {
            c.pretrain.lr = v;
        }
        if let Some(v) = pick!(mu_bound) {
            c.head.mu_bound = Some(v);
        }
        match (pick!(log_std_min), pick!(log_std_max)) {
            (Some(lo), Some(hi)) => c.head.log_std_bounds = Some((lo, hi)),
            (None, None) => {}
            _ => bail!("log_std_min and log_std_max: set both or neither"),
        }
        if let Some(v) = pick!(adv_norm) {
            c.saver.adv_norm = v;
        }
        if let Some(v) = pick!(adv_norm_joint) {
            c.saver.adv_norm_joint = v;
        }
        if let Some(v) = pick!(grad_clip) {
            c.grad_clip = Some(v);
        }
        if let Some(v) = pick!(lr_decay) {
            c.lr_decay = v;
        }
        if let Some(v) = pick!(bootstrap_timeout) {
            c.bootstrap_timeout = v;
        }
        if let Some(v) = pick!(mu_raw_penalty) {
            c.saver.mu_raw_penalty = v;
        }
        c.validate()?;
        Ok(c)
    }
}

/// The resolved config as TOML in the flat form `--config` reads back.
pub fn to_toml(c: &RunConfig) -> String {
    let opt = match c.optimizer {
        OptimizerConfig::Rmsprop { .. } => "rmsprop",
        OptimizerConfig::Adam { .. } => "adam",
    };
    let mut s = format!(
        "# Resolved settings of this run; `saver train --config <this file>` repeats it.\n\
         # Every setting is listed, on the paper's settings as the base.\n\
         faithful = true\n\
         env = \"{}\"\ndim = {}\nalgo = \"{}\"\nsteps = {}\nseed = {}\nactors = {}\nenvs = {}\n\
         mode = \"{}\"\nmax_lag = {}\n\
         rollout = {}\nlr = {:?}\ngamma = {:?}\noptimizer = \"{opt}\"\nmax_episode_steps = {}\n\
         quantiles = {}\nlambda_mon = {:?}\npretrain_batches = {}\npretrain_lr = {:?}\n",
        c.env.kind.name(),
        c.env.dim,
        c.algo.name(),
        c.steps,
        c.seed,
        c.actors,
        c.envs_per_actor,
        c.mode.name(),
        c.max_lag,
        c.rollout,
        c.lr,
        c.gamma,
        c.max_episode_steps,
        c.saver.quantiles,
        c.saver.lambda_mon,
        c.pretrain.batches,
        c.pretrain.lr,
    );
    if let Some(k) = c.saver.kappa {
        s.push_str(&format!("kappa = {k:?}\n"));
    }
    if let Some(b) = c.head.mu_bound {
        s.push_str(&format!("mu_bound = {b:?}\n"));
    }
    if let Some((lo, hi)) = c.head.log_std_bounds {
        s.push_str(&format!("log_std_min = {lo:?}\nlog_std_max = {hi:?}\n"));
    }
    s.push_str(&format!("adv_norm = {}\n", c.saver.adv_norm));
    s.push_str(&format!("adv_norm_joint = {}\n", c.saver.adv_norm_joint));
    if let Some(g) = c.grad_clip {
        s.push_str(&format!("grad_clip = {g:?}\n"));
    }
    s.push_str(&format!("lr_decay = {}\n", c.lr_decay));
    s.push_str(&format!("bootstrap_timeout = {}\n", c.bootstrap_timeout));
    s.push_str(&format!("mu_raw_penalty = {:?}\n", c.saver.mu_raw_penalty));
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn written_config_reads_back_identically() {
        let args = RunArgs {
            env: Some("select".into()),
            dim: Some(5),
            algo: Some("saver".into()),
            kappa: Some(0.01),
            optimizer: Some("adam".into()),
            seed: Some(9),
            mu_bound: Some(1.0),
            log_std_min: Some(-4.0),
            log_std_max: Some(0.0),
            adv_norm: Some(true),
            adv_norm_joint: Some(true),
            grad_clip: Some(0.5),
            lr_decay: Some(true),
            bootstrap_timeout: Some(true),
            mu_raw_penalty: Some(0.5),
            ..Default::default()
        };
        let c = args.resolve().unwrap();
        let dir = std::env::temp_dir().join(format!("saver-cfg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("run.toml");
        std::fs::write(&p, to_toml(&c)).unwrap();
        let back = RunArgs {
            config: Some(p),
            ..Default::default()
        }
        .resolve()
        .unwrap();
        assert_eq!(back, c);
        std::fs::remove_dir_all(dir).ok();
    }
}
