//! The policy head's bounds ([`HeadConfig`], `[head]` in a config): how the agent's raw
//! outputs become the action distribution's parameters, with its own checks. The
//! networks (nets/agent.rs, nets/policy.rs) read it.

use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// The trainable log σ's value before the first update, unless `head.log_std_init`
/// sets another.
pub const LOG_STD_INIT: f64 = -1.0;

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
    /// The trainable log σ's value before the first update (−1 by default,
    /// [`LOG_STD_INIT`]); the clamp applies to it as to any other.
    pub log_std_init: f64,
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
        if !(self.log_std_init.is_finite() && self.log_std_init.abs() <= 20.0) {
            return bad(
                "head.log_std_init",
                format!("{} is not in [-20, 20]", self.log_std_init),
            );
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
    /// Absent in files written before it: the default −1.
    #[serde(default = "default_log_std_init")]
    log_std_init: f64,
}

fn default_log_std_init() -> f64 {
    LOG_STD_INIT
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
            log_std_init: r.log_std_init,
        }
    }
}

impl From<HeadConfig> for HeadRepr {
    fn from(h: HeadConfig) -> Self {
        Self {
            mu_bound: h.mu_bound,
            log_std_min: h.log_std_bounds.map(|b| b.0),
            log_std_max: h.log_std_bounds.map(|b| b.1),
            log_std_init: h.log_std_init,
        }
    }
}

impl HeadConfig {
    /// The paper's head: linear μ, free log σ.
    pub const FAITHFUL: Self = Self {
        mu_bound: None,
        log_std_bounds: None,
        log_std_init: LOG_STD_INIT,
    };
    /// μ in [-1, 1] (tanh) and log σ in [-4.6, 0] (σ in [0.01, 1]): the ranges the
    /// PCPN's pretraining samples cover.
    pub const IN_PCPN_DOMAIN: Self = Self {
        mu_bound: Some(1.0),
        log_std_bounds: Some((-4.6, 0.0)),
        log_std_init: LOG_STD_INIT,
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::env::{EnvKind, EnvSpec};
    use candle_core::{Device, Tensor};

    /// `head.log_std_init` is the fresh agent's log σ, under the clamp like any other:
    /// −0.8 within [−1.6, 0] stays −0.8, −2 comes out at the floor −1.6, and the
    /// default is −1; a non-finite or far-off value is refused by its name.
    #[test]
    fn the_fresh_agents_log_std_is_the_heads_initial_one() {
        let layout = EnvSpec::new(EnvKind::Angle, 2).unwrap().layout();
        let fresh = |init: f64| {
            let head = HeadConfig {
                mu_bound: Some(1.0),
                log_std_bounds: Some((-1.6, 0.0)),
                log_std_init: init,
            };
            head.validate().unwrap();
            let mut rng = crate::rng::rng_for(7, 0);
            let agent = crate::nets::Agent::new(&layout, head, &[8], false, &mut rng, &Device::Cpu)
                .unwrap();
            let obs =
                Tensor::zeros((3, layout.obs_dim), candle_core::DType::F32, &Device::Cpu).unwrap();
            let log_std = agent
                .forward(&obs)
                .unwrap()
                .log_std
                .to_vec2::<f32>()
                .unwrap();
            assert_eq!(log_std.len(), 3);
            log_std.into_iter().flatten().collect::<Vec<f32>>()
        };
        assert!(fresh(-0.8).iter().all(|&l| l == -0.8), "{:?}", fresh(-0.8));
        assert!(fresh(-2.0).iter().all(|&l| l == -1.6), "{:?}", fresh(-2.0));
        assert!(fresh(LOG_STD_INIT).iter().all(|&l| l == -1.0));
        for bad in [f64::NAN, f64::INFINITY, 25.0] {
            let head = HeadConfig {
                log_std_init: bad,
                ..HeadConfig::IN_PCPN_DOMAIN
            };
            let e = head.validate().unwrap_err().to_string();
            assert!(e.contains("head.log_std_init"), "{e}");
        }
    }
}
