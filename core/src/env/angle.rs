//! `angle` (paper Fig. 3): for each pair k = 0, 2, …: step s = 0.1·a[k], angle
//! φ = (a[k+1] + 1)·π/2; Δ[k] = s·sin φ, Δ[k+1] = s·cos φ; p' = clip(p + Δ, -1, 1).

use super::{Cube, Env, EnvLayout, Step};
use crate::rng::SaverRng;
use std::f32::consts::PI;

/// The d-cube with pairwise (step, angle) actions; goal at the origin by default.
pub struct Angle {
    /// Position, goal, steps and limit (1000 in the paper).
    cube: Cube,
}

impl Angle {
    /// Its layout at dimension d: the observation is p, a (step, angle) pair of action entries per two coordinates.
    pub const fn layout_at(d: usize) -> EnvLayout {
        EnvLayout::cube(d, d, 0)
    }

    /// A d-cube (d even) with the goal at the origin.
    pub fn new(dim: usize, max_steps: u32) -> Self {
        Self {
            cube: Cube::new(dim, max_steps),
        }
    }

    /// Puts the agent at `pos` (tests and diagnostics).
    pub fn set_position(&mut self, pos: &[f32]) {
        self.cube.pos.copy_from_slice(pos);
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
        Self::layout_at(self.cube.pos.len())
    }

    fn reset(&mut self, rng: &mut SaverRng, obs: &mut [f32]) {
        self.cube.start_uniform(rng, obs);
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Step {
        self.cube.advance(obs, |pos| {
            for (p, dp) in pos.iter_mut().zip(Self::delta(action)) {
                *p = (*p + dp).clamp(-1.0, 1.0);
            }
        })
    }

    cube_state!();
}
