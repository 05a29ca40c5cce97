//! Environments with state aligned vector rewards (docs/ALGORITHM.md §2).
//!
//! An environment is described as data ([`EnvSpec`]: a name, its layout — observation
//! size, continuous action dims, an optional categorical choice, which observation
//! entries are the state-aligned part — and its bounds); the paper's three envs are
//! presets of it ([`EnvKind`]), and any [`Env`] of a spec's layout can act in it.
//! Vector reward `r = |p - g| - |p' - g|` element-wise; the scalar reward is its sum.

pub use angle::Angle;
pub use arm::{hand, wrap_angle, Arm};
pub use bandit::{bandit_reward, Bandit};
pub use layout::{EnvBounds, EnvLayout};
pub use point::Point;
pub use preset::{dim_help, EnvKind, Preset, Routing, PRESETS};
pub use select::Select;
pub use spec::EnvSpec;
pub use success::SuccessRule;

use crate::rng::SaverRng;
use crate::{CoreError, Result};

/// Rounding slack of a bound `b`: values up to `b·(1 + 1e-5) + 1e-6` pass (the env's
/// bounds, the policy head's, the success radius).
pub fn slack(b: f32) -> f32 {
    b.abs() * 1e-5 + 1e-6
}

/// Success radius: every aligned coordinate strictly within this of the goal.
pub const SUCCESS_RADIUS: f32 = 0.1;

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
    /// Where the state-aligned part should go (the goal g of the vector reward).
    fn goal(&self) -> Vec<f32>;
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

/// The state every cube env (angle, select, point, the bandit) is made of — the
/// position p (the state-aligned part and the whole observation), the goal, the step
/// count and its limit — with what they do alike; each env adds only its move.
pub(crate) struct Cube {
    /// Position p.
    pub(crate) pos: Vec<f32>,
    /// Goal g (the origin unless a test moves it).
    pub(crate) goal: Vec<f32>,
    /// Steps in this episode.
    pub(crate) steps: u32,
    /// Episode limit.
    pub(crate) max_steps: u32,
}

impl Cube {
    /// A d-cube at the origin with the goal at the origin.
    pub(crate) fn new(dim: usize, max_steps: u32) -> Self {
        Self {
            pos: vec![0.0; dim],
            goal: vec![0.0; dim],
            steps: 0,
            max_steps,
        }
    }

    /// Starts an episode from the current position: the step count to 0, `obs` = p.
    pub(crate) fn start(&mut self, obs: &mut [f32]) {
        self.steps = 0;
        obs.copy_from_slice(&self.pos);
    }

    /// Starts an episode at p ~ U(-1, 1)^d.
    pub(crate) fn start_uniform(&mut self, rng: &mut SaverRng, obs: &mut [f32]) {
        use rand::Rng;
        for p in &mut self.pos {
            *p = rng.random_range(-1.0f32..1.0);
        }
        self.start(obs);
    }

    /// One step: `mv` moves p, then the step is counted, `obs` = p' and the vector
    /// reward, success and timeout follow from p, p' and g ([`finish_step`]).
    pub(crate) fn advance(&mut self, obs: &mut [f32], mv: impl FnOnce(&mut [f32])) -> Step {
        let before = self.pos.clone();
        mv(&mut self.pos);
        self.steps += 1;
        obs.copy_from_slice(&self.pos);
        finish_step(&before, &self.pos, &self.goal, self.steps, self.max_steps)
    }
}

/// The [`Env`] methods a cube env gets from its [`Cube`] (a field `cube`): the step
/// count, the goal, and the snapshot and restore of its state. (Defined before the env
/// modules, which use it.)
macro_rules! cube_state {
    () => {
        fn steps(&self) -> u32 {
            self.cube.steps
        }

        fn goal(&self) -> Vec<f32> {
            self.cube.goal.clone()
        }

        fn snapshot(&self) -> Vec<f32> {
            super::snapshot_of(&self.cube.pos, &self.cube.goal, self.cube.steps)
        }

        fn restore(&mut self, state: &[f32]) -> crate::Result<()> {
            let c = &mut self.cube;
            super::restore_into(state, &mut c.pos, &mut c.goal, &mut c.steps)
        }
    };
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

mod angle;
mod arm;
mod bandit;
mod layout;
mod point;
mod preset;
mod select;
mod spec;
mod success;

#[cfg(test)]
mod tests;
