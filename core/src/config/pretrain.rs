//! PCPN pretraining settings (docs/ALGORITHM.md §9) and the paper's rates per env.

use super::{Algo, OptimizerKind, SampleDistribution, RECOMMENDED_PRETRAIN_BATCHES};
use crate::env::{EnvKind, EnvSpec};
use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// PCPN pretraining settings: everything that decides the PCPN's weights. A PCPN is
/// stored and found by its env spec and these (the same settings give the same
/// weights, bit for bit, from every entry point).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PretrainConfig {
    /// Optimiser.
    pub optimizer: OptimizerKind,
    /// Learning rate (paper: 0.1 × the agent's).
    pub lr: f64,
    /// Number of fresh batches.
    pub batches: u64,
    /// Transitions per batch.
    pub batch_size: usize,
    /// K: τ samples per transition.
    pub quantiles: usize,
    /// Seed of the weights, the samples and the τ draws (apart from the run's seed, so
    /// that every run of an env shares one PCPN, as the paper intends).
    pub seed: u64,
    /// The sample distribution.
    pub samples: SampleDistribution,
}

/// Held-out batches of the pretraining report (fresh samples, fixed τ stream).
pub const PRETRAIN_EVAL_BATCHES: usize = 16;

/// The paper's learning rate for an env and algorithm (docs/ALGORITHM.md §12; the
/// preset's row, [`crate::env::PRESETS`]). The paper does not run standalone QRRL; its
/// "paper" settings are A2C's (the same actor-critic loop, optimiser and rate), and so
/// are PPO's.
pub fn paper_lr(kind: EnvKind, algo: Algo) -> f64 {
    let p = kind.preset();
    match algo {
        Algo::Saver => p.paper_saver_lr,
        Algo::A2c | Algo::Qrrl | Algo::Ppo => p.paper_a2c_lr,
    }
}

/// The preset whose paper settings an env takes: its own, or angle's for a custom env
/// (the paper has none for it).
pub fn preset_or_angle(env: &EnvSpec) -> EnvKind {
    env.kind().unwrap_or(EnvKind::Angle)
}

/// The paper's number of pretraining batches for an env (the preset's row).
pub fn paper_pretrain_batches(kind: EnvKind) -> u64 {
    kind.preset().paper_pretrain_batches
}

/// "5000 batches x 128, K 32, rmsprop lr 0.001, seed 0, reset samples": what a PCPN's
/// pretraining was, in one line (`saver pretrain`, `saver repro`'s manifest).
impl std::fmt::Display for PretrainConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} batches x {}, K {}, {} lr {}, seed {}, {} samples",
            self.batches,
            self.batch_size,
            self.quantiles,
            self.optimizer.name(),
            self.lr,
            self.seed,
            self.samples.name()
        )
    }
}

impl PretrainConfig {
    /// The paper's: TF1 RMSProp at 0.1 × the paper's SAVER rate, the paper's number of
    /// batches of 128, K = 32.
    pub fn paper(kind: EnvKind) -> Self {
        Self {
            optimizer: OptimizerKind::Rmsprop,
            lr: 0.1 * paper_lr(kind, Algo::Saver),
            batches: paper_pretrain_batches(kind),
            batch_size: 128,
            quantiles: 32,
            seed: 0,
            samples: SampleDistribution::Reset,
        }
    }

    /// The default: the paper's but 5,000 batches (the held-out loss settles by
    /// ~1,000; results/README.md). The committed angle-d4 PCPN was made with these.
    pub fn recommended(kind: EnvKind) -> Self {
        Self {
            batches: RECOMMENDED_PRETRAIN_BATCHES,
            ..Self::paper(kind)
        }
    }

    /// These settings for `env`: its sample distribution (a custom env's PCPN learns
    /// from streamed walks).
    pub fn for_env(self, env: &EnvSpec) -> Self {
        Self {
            samples: SampleDistribution::for_env(env),
            ..self
        }
    }

    /// Refuses a sample distribution `env` cannot give: reset samples come from a
    /// built-in env, walks from a custom env's actors.
    pub fn check_env(&self, env: &EnvSpec) -> Result<()> {
        let want = SampleDistribution::for_env(env);
        if self.samples != want {
            return Err(CoreError::Config(format!(
                "pretrain.samples: {env} takes {:?} samples, not {:?} ({})",
                want.name(),
                self.samples.name(),
                match want {
                    SampleDistribution::Reset => "a built-in env samples itself",
                    SampleDistribution::Walk => "a custom env's actors stream random walks",
                }
            )));
        }
        Ok(())
    }

    /// Checks every field; the message names the field.
    pub fn validate(&self) -> Result<()> {
        let bad =
            |field: &str, why: String| Err(CoreError::Config(format!("pretrain.{field}: {why}")));
        if !(self.lr.is_finite() && self.lr > 0.0 && self.lr < 10.0) {
            return bad(
                "lr",
                format!("{} is not a learning rate in (0, 10)", self.lr),
            );
        }
        if !(1..=100_000_000).contains(&self.batches) {
            return bad("batches", format!("{} is not in 1..=1e8", self.batches));
        }
        if !(1..=65_536).contains(&self.batch_size) {
            return bad(
                "batch_size",
                format!("{} is not in 1..=65536", self.batch_size),
            );
        }
        if !(1..=1024).contains(&self.quantiles) {
            return bad(
                "quantiles",
                format!("{} is not in 1..=1024", self.quantiles),
            );
        }
        Ok(())
    }

    /// The identity of the PCPN these settings make for `spec`: a short hash of both
    /// (of the env's dynamics: a custom env's success rule is no part of it), for file
    /// names (the full settings are in the file's metadata).
    pub fn key(&self, spec: &EnvSpec) -> String {
        let json = serde_json::to_vec(&(spec.dynamics(), self)).unwrap_or_default();
        saver_proto::sha256_hex(&json)[..12].to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::env::EnvKind;

    /// The same env and settings give the same key; any setting changes it.
    #[test]
    fn pretrain_key_covers_every_setting() {
        let env = EnvSpec::new(EnvKind::Angle, 4).unwrap();
        let p = PretrainConfig::recommended(EnvKind::Angle);
        let k = p.key(&env);
        assert_eq!(k.len(), 12);
        assert_eq!(k, PretrainConfig::recommended(EnvKind::Angle).key(&env));
        let others = [
            PretrainConfig { lr: 0.002, ..p },
            PretrainConfig { batches: 5001, ..p },
            PretrainConfig { seed: 1, ..p },
            PretrainConfig {
                optimizer: OptimizerKind::Adam,
                ..p
            },
            PretrainConfig { quantiles: 16, ..p },
            PretrainConfig {
                batch_size: 64,
                ..p
            },
        ];
        for o in others {
            assert_ne!(o.key(&env), k, "{o:?}");
        }
        assert_ne!(p.key(&EnvSpec::new(EnvKind::Angle, 2).unwrap()), k);
    }
}
