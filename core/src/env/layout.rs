//! What an env looks like to the networks ([`EnvLayout`]: observation size, action
//! dims, where the state-aligned part sits) and the values it can produce
//! ([`EnvBounds`]); presets and custom specs both describe themselves with these.

use super::slack;
use serde::{Deserialize, Serialize};

/// An environment described as data, so that any actor can speak it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnvLayout {
    /// Observation length.
    pub obs_dim: usize,
    /// Gaussian action dims: the agent outputs one mean and one log-std per dim.
    pub continuous: usize,
    /// Size of the categorical choice (0: none). The agent outputs that many logits.
    pub choices: usize,
    /// First observation entry of the state-aligned part.
    pub aligned_start: usize,
    /// d: number of state-aligned entries (and of vector reward components).
    pub aligned_dim: usize,
}

impl EnvLayout {
    /// A d-cube's layout: the observation is p (all of it aligned), `continuous`
    /// action entries and a choice of `choices`.
    pub const fn cube(d: usize, continuous: usize, choices: usize) -> Self {
        Self {
            obs_dim: d,
            continuous,
            choices,
            aligned_start: 0,
            aligned_dim: d,
        }
    }
    /// Length of the agent's mean output: continuous means, then the choice logits.
    pub fn mu_dim(&self) -> usize {
        self.continuous + self.choices
    }
    /// Length of the trainable log-std vector.
    pub fn log_std_dim(&self) -> usize {
        self.continuous
    }
    /// Length of a stored action: continuous values then a one-hot of the choice.
    pub fn action_dim(&self) -> usize {
        self.continuous + self.choices
    }
    /// Input width of the PCPN and of the vector critic: [obs, mu, log sigma].
    pub fn pcpn_input_dim(&self) -> usize {
        self.obs_dim + self.mu_dim() + self.log_std_dim()
    }
}

/// The values an environment can produce, as data: the bounds of each observation
/// entry and the largest change of a state-aligned coordinate in one step (which
/// bounds the vector reward too: ||p - g| - |p' - g|| <= |p' - p|).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnvBounds {
    /// Smallest value of each observation entry.
    pub obs_low: Vec<f32>,
    /// Largest value of each observation entry.
    pub obs_high: Vec<f32>,
    /// Largest |p' - p| of one aligned coordinate in one step.
    pub max_change: f32,
}

impl EnvBounds {
    /// The first value of `obs` (observations back to back) outside its entry's range,
    /// as (index in `obs`, entry); rounding slack passes, NaN does not.
    pub fn obs_outside(&self, obs: &[f32]) -> Option<(usize, usize)> {
        let n = self.obs_low.len();
        obs.iter().enumerate().find_map(|(i, &v)| {
            let k = i % n;
            let (lo, hi) = (self.obs_low[k], self.obs_high[k]);
            (!(v >= lo - slack(lo) && v <= hi + slack(hi))).then_some((i, k))
        })
    }

    /// The index of the first of `changes` (aligned changes or vector rewards) beyond
    /// ±max_change; rounding slack passes, NaN does not.
    pub fn change_beyond(&self, changes: &[f32]) -> Option<usize> {
        let limit = self.max_change + slack(self.max_change);
        changes.iter().position(|v| v.is_nan() || v.abs() > limit)
    }
}
