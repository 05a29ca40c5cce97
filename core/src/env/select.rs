//! `select` (paper Fig. 4): action = [step, one-hot of d]; step = 0.1·clip(a[0]); the
//! chosen coordinate moves by step, clipped to [-1, 1]; the others stay.

use super::{Cube, Env, EnvLayout, Step};
use crate::rng::SaverRng;

/// The d-cube where the agent picks one dimension and a step.
pub struct Select {
    /// Position, goal, steps and limit.
    cube: Cube,
}

impl Select {
    /// Its layout at dimension d: the observation is p, one step entry and a choice of d coordinates.
    pub const fn layout_at(d: usize) -> EnvLayout {
        EnvLayout::cube(d, 1, d)
    }

    /// A d-cube with the goal at the origin.
    pub fn new(dim: usize, max_steps: u32) -> Self {
        Self {
            cube: Cube::new(dim, max_steps),
        }
    }

    /// Puts the agent at `pos` (tests and diagnostics).
    pub fn set_position(&mut self, pos: &[f32]) {
        self.cube.pos.copy_from_slice(pos);
    }
}

/// Index of the largest entry (the first on ties).
pub(crate) fn argmax(xs: &[f32]) -> usize {
    let mut best = 0;
    for (i, &x) in xs.iter().enumerate() {
        if x > xs[best] {
            best = i;
        }
    }
    best
}

impl Env for Select {
    fn layout(&self) -> EnvLayout {
        Self::layout_at(self.cube.pos.len())
    }

    fn reset(&mut self, rng: &mut SaverRng, obs: &mut [f32]) {
        self.cube.start_uniform(rng, obs);
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Step {
        let step = 0.1 * action[0].clamp(-1.0, 1.0);
        let j = argmax(&action[1..]);
        self.cube
            .advance(obs, |pos| pos[j] = (pos[j] + step).clamp(-1.0, 1.0))
    }

    cube_state!();
}
