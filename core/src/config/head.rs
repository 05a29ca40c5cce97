//! The policy head's bounds ([`HeadConfig`], `[head]` in a config): how the agent's raw
//! outputs become the action distribution's parameters, with its own checks. The
//! networks (nets/agent.rs, nets/policy.rs) read it.

use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// How the agent's raw outputs become the action distribution's parameters. Written
/// as `mu_bound`, `log_std_min`, `log_std_max`, with inf (-inf) for no bound.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "HeadRepr", into = "HeadRepr")]
pub struct HeadConfig {
    /// μ = bound·tanh(raw) when set (keeps μ where the PCPN was pretrained: [-1, 1]);
    /// `None`: the paper's unbounded linear mean.
    pub mu_bound: Option<f64>,
    /// log σ clamped into [min, max] when set (σ ~ U(0, 1) in pretraining means
    /// log σ ≤ 0); `None`: unbounded, as in the paper.
    pub log_std_bounds: Option<(f64, f64)>,
}

impl HeadConfig {
    /// Checks both bounds; the message names the field.
    pub fn validate(&self) -> Result<()> {
        let bad = |field: &str, why: String| Err(CoreError::Config(format!("{field}: {why}")));
        if let Some(b) = self.mu_bound {
            if !(b.is_finite() && b > 0.0) {
                return bad("head.mu_bound", format!("{b} must be > 0 (inf: unbounded)"));
            }
        }
        if let Some((lo, hi)) = self.log_std_bounds {
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return bad(
                    "head.log_std_min, head.log_std_max",
                    format!("[{lo}, {hi}] is not an interval (-inf and inf: unbounded)"),
                );
            }
        }
        Ok(())
    }
}

/// The written form of [`HeadConfig`].
#[derive(Clone, Copy, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct HeadRepr {
    /// `inf`: unbounded.
    #[serde(with = "super::inf_is_none")]
    mu_bound: Option<f64>,
    /// `-inf` (with `log_std_max` inf): unbounded.
    #[serde(with = "super::neg_inf_is_none")]
    log_std_min: Option<f64>,
    /// `inf` (with `log_std_min` -inf): unbounded.
    #[serde(with = "super::inf_is_none")]
    log_std_max: Option<f64>,
}

impl From<HeadRepr> for HeadConfig {
    /// One open side of the log σ interval is kept as an infinite bound, which
    /// validation refuses with the field's name.
    fn from(r: HeadRepr) -> Self {
        let log_std_bounds = match (r.log_std_min, r.log_std_max) {
            (None, None) => None,
            (lo, hi) => Some((lo.unwrap_or(f64::NEG_INFINITY), hi.unwrap_or(f64::INFINITY))),
        };
        Self {
            mu_bound: r.mu_bound,
            log_std_bounds,
        }
    }
}

impl From<HeadConfig> for HeadRepr {
    fn from(h: HeadConfig) -> Self {
        Self {
            mu_bound: h.mu_bound,
            log_std_min: h.log_std_bounds.map(|b| b.0),
            log_std_max: h.log_std_bounds.map(|b| b.1),
        }
    }
}

impl HeadConfig {
    /// The paper's head: linear μ, free log σ.
    pub const FAITHFUL: Self = Self {
        mu_bound: None,
        log_std_bounds: None,
    };
    /// μ in [-1, 1] (tanh) and log σ in [-4.6, 0] (σ in [0.01, 1]): the ranges the
    /// PCPN's pretraining samples cover.
    pub const IN_PCPN_DOMAIN: Self = Self {
        mu_bound: Some(1.0),
        log_std_bounds: Some((-4.6, 0.0)),
    };

    /// Applies the bound to one raw mean.
    pub fn mu(&self, raw: f32) -> f32 {
        match self.mu_bound {
            Some(b) => b as f32 * raw.tanh(),
            None => raw,
        }
    }

    /// Applies the clamp to one log σ.
    pub fn log_std(&self, raw: f32) -> f32 {
        match self.log_std_bounds {
            Some((lo, hi)) => raw.clamp(lo as f32, hi as f32),
            None => raw,
        }
    }
}
