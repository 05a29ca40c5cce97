//! PPO's settings (`[ppo]`; docs/ALGORITHM.md §15). The defaults are Stable-Baselines3's
//! (clip 0.2, GAE λ 0.95, 10 epochs of minibatches of 64 steps, no value clipping, no
//! entropy bonus, advantages normalised per minibatch).

use super::zero_is_none;
use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// PPO's constants.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PpoConfig {
    /// Passes over each batch.
    pub epochs: usize,
    /// Steps per minibatch: each pass cuts the batch, shuffled anew, into
    /// ⌈B / minibatch_size⌉ minibatches of (nearly) equal size.
    pub minibatch_size: usize,
    /// ε of the clipped surrogate: the ratio π/π_old counts within [1 − ε, 1 + ε].
    pub clip: f64,
    /// λ of GAE(λ) (1: the n-step return inside the rollout, as A2C).
    pub gae_lambda: f64,
    /// Clip the value's move from its value at the batch's start to ±this (`None`,
    /// written 0: unclipped).
    #[serde(with = "zero_is_none")]
    pub value_clip: Option<f64>,
    /// Weight of the policy's entropy bonus.
    pub entropy_coef: f64,
    /// Centre each minibatch's advantages and divide them by their standard deviation.
    pub adv_norm: bool,
    /// A vector critic V(o) ∈ R^d on the vector reward, GAE per coordinate, and the
    /// step's advantage the sum over coordinates (instead of one critic on the summed
    /// reward).
    pub vector: bool,
    /// Normalise observations by a running mean and variance (SB3's `VecNormalize`,
    /// which RL Zoo's tuned settings use): the statistics travel with the weights
    /// (`nets::obs_norm`). A config.toml written before it reads as off.
    #[serde(default)]
    pub obs_norm: bool,
    /// Scale rewards by a running standard deviation of the discounted return (SB3's
    /// `VecNormalize(norm_reward=True)`), clipped to ±10.
    #[serde(default)]
    pub reward_norm: bool,
    /// Learn from the env's own scalar reward (what a Python actor sends beside the
    /// progress reward; Reacher's is −distance − control cost) instead of the progress
    /// reward's sum. A batch without it is refused.
    #[serde(default)]
    pub env_reward: bool,
}

impl Default for PpoConfig {
    fn default() -> Self {
        Self {
            epochs: 10,
            minibatch_size: 64,
            clip: 0.2,
            gae_lambda: 0.95,
            value_clip: None,
            entropy_coef: 0.0,
            adv_norm: true,
            vector: false,
            obs_norm: false,
            reward_norm: false,
            env_reward: false,
        }
    }
}

impl PpoConfig {
    /// The critic's outputs in `layout`: d with `vector`, else 1.
    pub fn critic_values(&self, layout: &crate::env::EnvLayout) -> usize {
        if self.vector {
            layout.aligned_dim
        } else {
            1
        }
    }

    /// Minibatches per pass over a batch of `b` steps.
    pub fn minibatches(&self, b: usize) -> usize {
        b.div_ceil(self.minibatch_size).max(1)
    }

    /// Checks every field; the message names it.
    pub fn validate(&self) -> Result<()> {
        let bad = |field: &str, why: String| Err(CoreError::Config(format!("ppo.{field}: {why}")));
        if !(1..=1000).contains(&self.epochs) {
            return bad("epochs", format!("{} is not in 1..=1000", self.epochs));
        }
        if !(1..=1 << 20).contains(&self.minibatch_size) {
            return bad(
                "minibatch_size",
                format!("{} is not in 1..=1048576", self.minibatch_size),
            );
        }
        if !(self.clip.is_finite() && self.clip > 0.0 && self.clip < 1.0) {
            return bad("clip", format!("{} is not in (0, 1)", self.clip));
        }
        if !(0.0..=1.0).contains(&self.gae_lambda) {
            return bad(
                "gae_lambda",
                format!("{} is not in [0, 1]", self.gae_lambda),
            );
        }
        if let Some(v) = self.value_clip {
            if !(v.is_finite() && v > 0.0) {
                return bad("value_clip", format!("{v} must be > 0 (0: unclipped)"));
            }
        }
        if self.env_reward && self.vector {
            return bad(
                "env_reward",
                "the env's reward is one number a step; a vector critic (ppo.vector) learns \
                 the vector reward"
                    .into(),
            );
        }
        if !(self.entropy_coef.is_finite() && self.entropy_coef >= 0.0) {
            return bad(
                "entropy_coef",
                format!("{} must be finite and >= 0", self.entropy_coef),
            );
        }
        Ok(())
    }
}
