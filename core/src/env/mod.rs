//! Environments with state aligned vector rewards (docs/ALGORITHM.md §2).
//!
//! An environment is described on the wire as data ([`EnvLayout`]: observation size,
//! continuous action dims, an optional categorical choice, which observation entries are
//! the state-aligned part); the paper's three envs are presets ([`EnvSpec`]) of it.
//! Vector reward `r = |p - g| - |p' - g|` element-wise; the scalar reward is its sum.

mod angle;
mod arm;
mod select;

pub use angle::Angle;
pub use arm::{hand, wrap_angle, Arm};
pub use select::Select;

use crate::rng::SaverRng;
use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};
use std::fmt;

/// Success radius: every aligned coordinate strictly within this of the goal.
pub const SUCCESS_RADIUS: f32 = 0.1;

/// The paper's environment presets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum EnvKind {
    /// Pairwise (step, angle) moves in a d-cube, d even (paper Fig. 3).
    Angle,
    /// Choose one dimension and a step in a d-cube (paper Fig. 4).
    Select,
    /// Two-joint robot arm reaching a goal (paper Fig. 5).
    Arm,
}

impl EnvKind {
    /// Parses `angle`, `select` or `arm`.
    pub fn parse(s: &str) -> Result<Self> {
        <Self as clap::ValueEnum>::from_str(s, false).map_err(|_| {
            CoreError::Config(format!(
                "env: unknown environment {s:?} (expected angle, select or arm)"
            ))
        })
    }

    /// The lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Angle => "angle",
            Self::Select => "select",
            Self::Arm => "arm",
        }
    }
}

/// Which environment and its dimension: the identity of the dynamics that a PCPN models.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct EnvSpec {
    /// The preset.
    pub kind: EnvKind,
    /// Number of state-aligned dimensions d (always 2 for the arm).
    pub dim: usize,
}

impl fmt::Display for EnvSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}-d{}", self.kind.name(), self.dim)
    }
}

impl EnvSpec {
    /// Validates the dimension for the kind.
    pub fn new(kind: EnvKind, dim: usize) -> Result<Self> {
        match kind {
            EnvKind::Angle if dim == 0 || !dim.is_multiple_of(2) => Err(CoreError::Config(
                format!("dim: angle needs an even dimension >= 2, got {dim}"),
            )),
            EnvKind::Select if dim == 0 => Err(CoreError::Config(
                "dim: select needs a dimension >= 1, got 0".into(),
            )),
            EnvKind::Arm if dim != 2 => Err(CoreError::Config(format!(
                "dim: the arm's hand moves in 2 dimensions, got dim {dim}"
            ))),
            _ if dim > 1024 => Err(CoreError::Config(format!(
                "dim: {dim} is larger than the supported 1024"
            ))),
            _ => Ok(Self { kind, dim }),
        }
    }

    /// The data layout of this preset.
    pub fn layout(&self) -> EnvLayout {
        let d = self.dim;
        match self.kind {
            EnvKind::Angle => EnvLayout {
                obs_dim: d,
                continuous: d,
                choices: 0,
                aligned_start: 0,
                aligned_dim: d,
            },
            EnvKind::Select => EnvLayout {
                obs_dim: d,
                continuous: 1,
                choices: d,
                aligned_start: 0,
                aligned_dim: d,
            },
            EnvKind::Arm => EnvLayout {
                obs_dim: 6,
                continuous: 2,
                choices: 0,
                aligned_start: 4,
                aligned_dim: 2,
            },
        }
    }

    /// What this preset's observations and steps can hold (the learner refuses
    /// rollouts outside it).
    pub fn bounds(&self) -> EnvBounds {
        let d = self.dim;
        match self.kind {
            // Positions stay in the cube; a step moves each coordinate by at most
            // 0.1 (angle: 0.1·|sin φ|, 0.1·|cos φ|; select: 0.1 on one coordinate).
            EnvKind::Angle | EnvKind::Select => EnvBounds {
                obs_low: vec![-1.0; d],
                obs_high: vec![1.0; d],
                max_change: 0.1,
            },
            // obs = [goal in [-1, 1]^2, angles in [-π, π), hand in [-2, 2]^2]. Each
            // joint turns by at most 0.02π per step; the hand moves by at most its
            // lever arm times that: 2·0.02π (joint 1) + 1·0.02π (joint 2) < 0.19.
            EnvKind::Arm => {
                let pi = std::f32::consts::PI;
                EnvBounds {
                    obs_low: vec![-1.0, -1.0, -pi, -pi, -2.0, -2.0],
                    obs_high: vec![1.0, 1.0, pi, pi, 2.0, 2.0],
                    max_change: 0.19,
                }
            }
        }
    }

    /// A fresh environment instance with the default goal.
    pub fn make(&self, max_steps: u32) -> Box<dyn Env> {
        match self.kind {
            EnvKind::Angle => Box::new(Angle::new(self.dim, max_steps)),
            EnvKind::Select => Box::new(Select::new(self.dim, max_steps)),
            EnvKind::Arm => Box::new(Arm::new(max_steps)),
        }
    }
}

/// An environment described as data, so that any actor can speak it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
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
#[derive(Clone, Debug, PartialEq)]
pub struct EnvBounds {
    /// Smallest value of each observation entry.
    pub obs_low: Vec<f32>,
    /// Largest value of each observation entry.
    pub obs_high: Vec<f32>,
    /// Largest |p' - p| of one aligned coordinate in one step.
    pub max_change: f32,
}

/// The result of one environment step.
#[derive(Clone, Debug, PartialEq)]
pub struct Step {
    /// Change of the state-aligned part, p' - p (before any reset).
    pub state_delta: Vec<f32>,
    /// Vector reward |p - g| - |p' - g|, one component per aligned dim.
    pub vector_reward: Vec<f32>,
    /// The goal was reached on this step (strict L-infinity < 0.1).
    pub success: bool,
    /// The step limit was hit on this step without success.
    pub timeout: bool,
}

impl Step {
    /// The episode ended on this step (success or timeout).
    pub fn done(&self) -> bool {
        self.success || self.timeout
    }
}

/// An environment instance. Actions are clipped to [-1, 1] inside `step`.
pub trait Env: Send {
    /// The layout of observations and actions.
    fn layout(&self) -> EnvLayout;
    /// Starts an episode; writes the first observation.
    fn reset(&mut self, rng: &mut SaverRng, obs: &mut [f32]);
    /// Applies `action` (layout: continuous values, then a one-hot of the choice);
    /// writes the next observation (not reset on `done`: the caller resets).
    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Step;
    /// Steps taken in the current episode.
    fn steps(&self) -> u32;
    /// The whole state (position or angles, goal, step count) as numbers, for
    /// checkpoints of a run's actors.
    fn snapshot(&self) -> Vec<f32>;
    /// Restores [`Env::snapshot`]; refuses a state of another length.
    fn restore(&mut self, state: &[f32]) -> Result<()>;
}

/// [`Env::snapshot`] of an env made of a position, a goal and a step count.
pub(crate) fn snapshot_of(pos: &[f32], goal: &[f32], steps: u32) -> Vec<f32> {
    let mut s = Vec::with_capacity(pos.len() + goal.len() + 1);
    s.extend_from_slice(pos);
    s.extend_from_slice(goal);
    // Exact: step counts stay far below 2^24.
    s.push(steps as f32);
    s
}

/// [`Env::restore`] of an env made of a position, a goal and a step count.
pub(crate) fn restore_into(
    state: &[f32],
    pos: &mut [f32],
    goal: &mut [f32],
    steps: &mut u32,
) -> Result<()> {
    let (n, m) = (pos.len(), goal.len());
    let last = state.get(n + m).copied().unwrap_or(-1.0);
    if state.len() != n + m + 1 || !(0.0..16_777_216.0).contains(&last) || last.fract() != 0.0 {
        return Err(CoreError::Checkpoint(format!(
            "an env state of {} numbers does not fit this env ({} expected)",
            state.len(),
            n + m + 1
        )));
    }
    pos.copy_from_slice(&state[..n]);
    goal.copy_from_slice(&state[n..n + m]);
    *steps = last as u32;
    Ok(())
}

/// Shared bookkeeping of the cube environments and the arm: the vector reward, strict
/// success and the step limit, from the aligned state before and after a step.
pub(crate) fn finish_step(
    before: &[f32],
    after: &[f32],
    goal: &[f32],
    steps: u32,
    max_steps: u32,
) -> Step {
    let mut state_delta = Vec::with_capacity(after.len());
    let mut vector_reward = Vec::with_capacity(after.len());
    let mut worst = 0.0f32;
    for ((&p, &q), &g) in before.iter().zip(after).zip(goal) {
        state_delta.push(q - p);
        vector_reward.push((p - g).abs() - (q - g).abs());
        worst = worst.max((q - g).abs());
    }
    let success = worst < SUCCESS_RADIUS;
    Step {
        state_delta,
        vector_reward,
        success,
        timeout: !success && steps >= max_steps,
    }
}

#[cfg(test)]
mod tests;
