//! Standalone QRRL's settings (`[qrrl]`; docs/ALGORITHM.md §14). Until 2026-12 they
//! sat in `[saver]` as `qrrl_spread` and `qrrl_vector`; such files still read
//! ([`super::upgrade`]).

use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// QRRL's [`QrrlConfig::spread`] by default: the initial policy is U(−1, 1), the env's
/// whole action range (with 0.637, the spread of the Gaussian's initial σ = e⁻¹, the
/// bandit's optima at ±0.75 lay outside it and seed 0 settled on the decoy;
/// docs/ALGORITHM.md §14).
pub const QRRL_SPREAD: f64 = 1.0;

/// Standalone QRRL's constants.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QrrlConfig {
    /// Half-width s of the fixed base quantile function s·(2τ − 1) added to the policy
    /// network's output, so that the initial policy is U(−s, s) (the network starts
    /// near 0 everywhere, which would not explore).
    pub spread: f64,
    /// The vector variant: a vector critic V(o) ∈ R^d on the vector reward, and
    /// coordinate j's advantage weighs action dim j; only for envs whose actions are
    /// aligned with their coordinates ([`crate::env::EnvSpec::actions_aligned`]).
    pub vector: bool,
}

impl Default for QrrlConfig {
    fn default() -> Self {
        Self {
            spread: QRRL_SPREAD,
            vector: false,
        }
    }
}

impl QrrlConfig {
    /// Checks every field; the message names it.
    pub fn validate(&self) -> Result<()> {
        if !(self.spread.is_finite() && self.spread >= 0.0) {
            return Err(CoreError::Config(format!(
                "qrrl.spread: {} must be finite and >= 0",
                self.spread
            )));
        }
        Ok(())
    }
}
