//! The registry: each [`Algo`] to its [`Entry`], and what the rest of the system asks
//! of "the run's algorithm" (build it, its defaults, its checks, its policy, its FLOPs).
//! Adding an algorithm is its files and one line in [`entry`]; nothing else here
//! names one.

use super::algorithm::{Algorithm, Entry};
use super::{a2c, ppo, qrrl, saver};
use crate::acting::PolicyFamily;
use crate::config::{preset_or_angle, Algo, PretrainConfig, RunConfig};
use crate::env::EnvSpec;
use crate::nets::Pcpn;
use crate::Result;
use candle_core::Device;
use std::sync::Arc;

/// The algorithms. Adding one: its files (an [`Algorithm`] and, unless it acts with an
/// existing family, a [`PolicyFamily`]), a variant of [`Algo`], and one line here.
pub fn entry(algo: Algo) -> Entry {
    match algo {
        Algo::A2c => a2c::ENTRY,
        Algo::Saver => saver::ENTRY,
        Algo::Qrrl => qrrl::ENTRY,
        Algo::Ppo => ppo::ENTRY,
    }
}

/// The default settings of `algo` on `env` for `steps` steps: the paper's, with the
/// recommended pretraining, and the algorithm's own defaults ([`Entry::recommend`]).
pub fn recommended(env: &EnvSpec, algo: Algo, steps: u64) -> RunConfig {
    let mut c = RunConfig::paper(env, algo, steps);
    c.pretrain = PretrainConfig::recommended(preset_or_angle(env)).for_env(env);
    (entry(algo).recommend)(&mut c);
    c
}

/// Checks every field of `config` ([`RunConfig::check_fields`]) and what its algorithm
/// refuses ([`Entry::check`]); the message names the field.
pub fn validate(config: &RunConfig) -> Result<()> {
    config.check_fields()?;
    (entry(config.algo).check)(config)
}

/// FLOPs of one update of `config`'s algorithm on `b` steps of `t` trajectories
/// ([`Entry::flops`]).
pub fn update_flops(config: &RunConfig, b: usize, t: usize) -> f64 {
    (entry(config.algo).flops)(config, b, t)
}

/// Builds the configured algorithm; SAVER needs its frozen PCPN.
pub fn build(config: &RunConfig, pcpn: Option<Pcpn>, dev: &Device) -> Result<Box<dyn Algorithm>> {
    (entry(config.algo).build)(config, pcpn, dev)
}

/// The behaviour policy of `config`'s actors.
pub fn policy_family(config: &RunConfig) -> Arc<dyn PolicyFamily> {
    (entry(config.algo).policy)(config)
}
