//! The enumerations of a run's config: algorithm, batching mode, optimiser and the
//! pretraining sample distribution (clap's ValueEnum, so `--help` lists them).

use crate::optim::OptimizerConfig;
use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// The learning algorithm.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Algo {
    /// Vector rewards through the frozen PCPN with the QRRL loss.
    Saver,
    /// The scalar-reward A2C baseline.
    A2c,
    /// Standalone QRRL (paper Section 3): the policy is an implicit quantile network,
    /// any action distribution, multi-modal included; scalar reward, no PCPN.
    Qrrl,
    /// The PPO baseline (clipped surrogate, GAE(λ), epochs of minibatches): scalar
    /// reward, or a vector critic on the vector reward.
    Ppo,
}

impl Algo {
    /// Parses an algorithm's name ([`Algo::name`]).
    pub fn parse(s: &str) -> Result<Self> {
        <Self as clap::ValueEnum>::from_str(s, false).map_err(|_| {
            let names: Vec<_> = Self::all().iter().map(|a| a.name()).collect();
            CoreError::Config(format!(
                "algo: unknown algorithm {:?} (expected one of {})",
                crate::clip_text(s),
                names.join(", ")
            ))
        })
    }
    /// Every algorithm, in the order `--help` lists them.
    pub fn all() -> &'static [Self] {
        <Self as clap::ValueEnum>::value_variants()
    }
    /// The lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Saver => "saver",
            Self::A2c => "a2c",
            Self::Qrrl => "qrrl",
            Self::Ppo => "ppo",
        }
    }
    /// Whether it learns through a frozen PCPN (and so has pretraining settings that
    /// matter): SAVER only.
    pub fn has_pcpn(self) -> bool {
        self == Self::Saver
    }
}

/// How the learner forms batches.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// One rollout per registered actor at the current version, in actor-id order
    /// (exact on-policy A2C/SAVER, repeatable bit for bit).
    Sync,
    /// An update on every `actors` rollouts whose version lag is at most `max_lag`.
    Async,
}

impl Mode {
    /// The lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Sync => "sync",
            Self::Async => "async",
        }
    }
}

/// An optimiser with TensorFlow 1's constants (docs/ALGORITHM.md, optimisers).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum OptimizerKind {
    /// TF1 RMSProp (decay 0.9, ε 1e-10 inside the root, slots start at 1): the paper's.
    Rmsprop,
    /// TF1 Adam (β 0.9, 0.999, ε̂ 1e-8).
    Adam,
}

impl OptimizerKind {
    /// Its constants.
    pub fn tf1(self) -> OptimizerConfig {
        match self {
            Self::Rmsprop => OptimizerConfig::RMSPROP_TF1,
            Self::Adam => OptimizerConfig::ADAM_TF1,
        }
    }
    /// The lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Rmsprop => "rmsprop",
            Self::Adam => "adam",
        }
    }
}

/// Where SAVER's actor loss takes its target y from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum DeltaTarget {
    /// The observed Δp of the transition (the paper).
    #[default]
    Observed,
    /// The PCPN's median change for the action taken, at the policy's σ
    /// (docs/ALGORITHM.md §7.1, `algo::saver_signal`).
    Predicted,
    /// The PCPN's quantile at the rank of the step's own action noise along each
    /// coordinate's slope (`algo::saver_signal::noise_rank_delta`).
    Noise,
}

/// How SAVER's agent and critics see the observations (`saver.obs_norm`; the PCPN
/// always reads them raw, as it was pretrained).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ObsNorm {
    /// As the env gives them (the paper).
    #[default]
    Off,
    /// By their running mean and variance (SB3's `VecNormalize`, as `ppo.obs_norm`).
    Running,
    /// Mapped from the env's declared bounds to [−1, 1]: (o − (low + high)/2) / ((high −
    /// low)/2), fixed for the whole run.
    Bounds,
    /// The aligned entries (the position p, and the goal g where the env declares one)
    /// by their running mean and variance, every other entry raw: for an env whose p
    /// spreads far less than its other entries (Reacher-v5's fingertip offset), without
    /// blowing up entries that spread little under random actions (an inertial point's
    /// speed) as `running` does.
    Aligned,
    /// As `aligned` where, over the first batch, p's widest entry spreads less than a
    /// third of the widest entry outside p and g (the agent would read what it steers
    /// at a fraction of its other inputs' scale); raw otherwise. Decided once, logged
    /// and checkpointed. SAVER's default on a custom env.
    Auto,
}

/// Where PCPN pretraining samples come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum SampleDistribution {
    /// The paper's: an observation from the env's reset distribution, μ ~ U(-1, 1),
    /// σ ~ U(0, 1), one step with a ~ N(μ, σ²). Built-in envs only.
    Reset,
    /// Every step of random walks: from the env's reset, each step draws a fresh
    /// μ ~ U(-1, 1), σ ~ U(0, 1) and a ~ N(μ, σ²), and the walk goes on from where it
    /// lands until the env ends the episode. Real envs start in a narrow set of states
    /// (Reacher's joints within ±0.1 rad), so their one-step-from-reset samples would
    /// miss the states a policy reaches. Custom envs: actors stream these samples
    /// (saver.proto ProvideSamples).
    Walk,
}

impl SampleDistribution {
    /// The lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Reset => "reset",
            Self::Walk => "walk",
        }
    }

    /// The distribution an env's PCPN is pretrained on: a built-in env's own samples
    /// (reset), a custom env's streamed walks.
    pub fn for_env(env: &crate::env::EnvSpec) -> Self {
        match env.kind() {
            Some(_) => Self::Reset,
            None => Self::Walk,
        }
    }
}
