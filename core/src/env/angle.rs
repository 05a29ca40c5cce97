//! `angle` (paper Fig. 3): for each pair k = 0, 2, …: step s = 0.1·a[k], angle
//! φ = (a[k+1] + 1)·π/2; Δ[k] = s·sin φ, Δ[k+1] = s·cos φ; p' = clip(p + Δ, -1, 1).

use super::{finish_step, Env, EnvLayout, Step};
use crate::rng::SaverRng;
use rand::Rng;
use std::f32::consts::PI;

/// The d-cube with pairwise (step, angle) actions; goal at the origin by default.
pub struct Angle {
    /// Position p in [-1, 1]^d.
    pub(super) pos: Vec<f32>,
    /// Goal g (the task parameter).
    pub(super) goal: Vec<f32>,
    /// Steps in this episode.
    pub(super) steps: u32,
    /// Episode limit (1000 in the paper).
    pub(super) max_steps: u32,
}

impl Angle {
    /// A d-cube (d even) with the goal at the origin.
    pub fn new(dim: usize, max_steps: u32) -> Self {
        Self {
            pos: vec![0.0; dim],
            goal: vec![0.0; dim],
            steps: 0,
            max_steps,
        }
    }

    /// Puts the agent at `pos` (tests and diagnostics).
    pub fn set_position(&mut self, pos: &[f32]) {
        self.pos.copy_from_slice(pos);
    }

    /// The position change of `action` at `pos`, before clipping to the cube.
    pub fn delta(action: &[f32]) -> Vec<f32> {
        let mut delta = vec![0.0; action.len()];
        for k in (0..action.len()).step_by(2) {
            let s = 0.1 * action[k].clamp(-1.0, 1.0);
            let phi = (action[k + 1].clamp(-1.0, 1.0) + 1.0) * PI / 2.0;
            delta[k] = s * phi.sin();
            delta[k + 1] = s * phi.cos();
        }
        delta
    }
}

impl Env for Angle {
    fn layout(&self) -> EnvLayout {
        super::EnvKind::Angle.layout(self.pos.len())
    }

    fn reset(&mut self, rng: &mut SaverRng, obs: &mut [f32]) {
        for p in &mut self.pos {
            *p = rng.random_range(-1.0f32..1.0);
        }
        self.steps = 0;
        obs.copy_from_slice(&self.pos);
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Step {
        let before = self.pos.clone();
        for (p, dp) in self.pos.iter_mut().zip(Self::delta(action)) {
            *p = (*p + dp).clamp(-1.0, 1.0);
        }
        self.steps += 1;
        obs.copy_from_slice(&self.pos);
        finish_step(&before, &self.pos, &self.goal, self.steps, self.max_steps)
    }

    fn steps(&self) -> u32 {
        self.steps
    }

    fn goal(&self) -> Vec<f32> {
        self.goal.clone()
    }

    fn snapshot(&self) -> Vec<f32> {
        super::snapshot_of(&self.pos, &self.goal, self.steps)
    }

    fn restore(&mut self, state: &[f32]) -> crate::Result<()> {
        super::restore_into(state, &mut self.pos, &mut self.goal, &mut self.steps)
    }
}
