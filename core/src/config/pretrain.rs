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
    /// Walk samples only (custom envs): the distinct transitions the actors stream;
    /// each batch draws its rows from them at random, with replacement. 0: every row
    /// of every batch is a fresh streamed transition (batches x batch_size of them).
    /// Left out of a file (and of the store's key) when 0, so the keys of every PCPN
    /// pretrained before the field existed stay the same.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub walk_samples: u64,
}

fn is_zero(v: &u64) -> bool {
    *v == 0
}

/// The streamed transitions a custom env's PCPN is pretrained from by default
/// (`pretrain.walk_samples`): the held-out loss on Reacher-v5 and the point mass stops
/// improving below this many (results/pcpn-samples/README.md; bench/pcpn_samples.py),
/// a tenth of the 640,000 fresh ones that 5,000 batches of 128 would read.
pub const DEFAULT_WALK_SAMPLES: u64 = 65_536;

/// Held-out batches of the pretraining report (fresh samples, fixed τ stream).
pub const PRETRAIN_EVAL_BATCHES: usize = 16;

/// The paper's learning rate for an env and algorithm (docs/ALGORITHM.md §12; the
/// preset's row, [`crate::env::PRESETS`]). The paper does not run standalone QRRL; its
/// "paper" settings are A2C's (the same actor-critic loop, optimiser and rate), and so
/// are PPO's.
pub fn paper_lr(kind: EnvKind, algo: Algo) -> f64 {
    // The paper ran SAVER and A2C: an algorithm with a PCPN takes SAVER's column, any
    // other A2C's, so a new algorithm needs no line here.
    let p = kind.preset();
    if algo.has_pcpn() {
        p.paper_saver_lr
    } else {
        p.paper_a2c_lr
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
            walk_samples: 0,
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
    /// from [`DEFAULT_WALK_SAMPLES`] streamed walk transitions).
    pub fn for_env(self, env: &EnvSpec) -> Self {
        let samples = SampleDistribution::for_env(env);
        Self {
            samples,
            walk_samples: match samples {
                SampleDistribution::Walk => DEFAULT_WALK_SAMPLES,
                SampleDistribution::Reset => 0,
            },
            ..self
        }
    }

    /// Streamed transitions a pretraining with these settings reads (walk samples):
    /// the held-out ones, then `walk_samples` (or one per row of every batch).
    pub fn streamed_total(&self) -> u64 {
        let held = (PRETRAIN_EVAL_BATCHES * self.batch_size) as u64;
        held + match self.walk_samples {
            0 => self.batches * self.batch_size as u64,
            n => n,
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
        if self.walk_samples != 0 && self.samples == SampleDistribution::Reset {
            return bad(
                "walk_samples",
                format!(
                    "{}: only walk samples (a custom env's, streamed by its actors) are \
                     gathered in a fixed number; a built-in env draws fresh samples for \
                     every batch (set 0)",
                    self.walk_samples
                ),
            );
        }
        if self.walk_samples > 100_000_000
            || (1..self.batch_size as u64).contains(&self.walk_samples)
        {
            return bad(
                "walk_samples",
                format!(
                    "{} is not 0 (fresh samples) or in {}..=1e8 (at least one batch)",
                    self.walk_samples, self.batch_size
                ),
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
            PretrainConfig {
                samples: SampleDistribution::Walk,
                ..p
            },
            PretrainConfig {
                samples: SampleDistribution::Walk,
                walk_samples: 65_536,
                ..p
            },
        ];
        for o in others {
            assert_ne!(o.key(&env), k, "{o:?}");
        }
        assert_ne!(p.key(&EnvSpec::new(EnvKind::Angle, 2).unwrap()), k);
        // A PCPN pretrained before walk_samples existed keeps its key: the field is
        // not serialised at 0. (The key of the committed angle-d4 PCPN's settings.)
        let json = serde_json::to_string(&p).unwrap();
        assert!(!json.contains("walk_samples"), "{json}");
    }

    /// walk_samples: refused for reset samples and below one batch; the streamed
    /// total is the held-out rows plus the walk samples (or one per batch row).
    #[test]
    fn walk_samples_set_how_many_transitions_are_streamed() {
        let p = PretrainConfig::recommended(EnvKind::Angle);
        let e = PretrainConfig {
            walk_samples: 1000,
            ..p
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("pretrain.walk_samples") && e.contains("fresh samples"),
            "{e}"
        );
        let w = PretrainConfig {
            samples: SampleDistribution::Walk,
            ..p
        };
        // 16 held-out batches of 128 = 2,048, plus 5,000 x 128 = 640,000.
        assert_eq!(w.streamed_total(), 2_048 + 640_000);
        assert_eq!(
            PretrainConfig {
                walk_samples: 65_536,
                ..w
            }
            .streamed_total(),
            2_048 + 65_536
        );
        let e = PretrainConfig {
            walk_samples: 100,
            ..w
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(e.contains("in 128..=1e8"), "{e}");
        assert!(PretrainConfig {
            walk_samples: 128,
            ..w
        }
        .validate()
        .is_ok());
    }
}
