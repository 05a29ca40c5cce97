//! `point` (the paper's Figure 1(a)): an agent moving freely in the d-cube, each action
//! dim moving its own coordinate: p' = clip(p + 0.1·clip(a, −1, 1), −1, 1), reset
//! p ~ U(−1, 1)^d, goal 0. Its actions are aligned with its state-aligned coordinates,
//! so a vector advantage can be applied to each action dim directly (standalone QRRL's
//! vector variant, docs/ALGORITHM.md §14); for SAVER and A2C it is one more cube.

use super::{Cube, Env, EnvLayout, Step};
use crate::rng::SaverRng;

/// The d-cube with one action dim per coordinate; goal at the origin. The same state,
/// reset and bookkeeping as [`super::Angle`]'s cube ([`Cube`]); only the move differs.
pub struct Point {
    /// Position, goal, steps and limit.
    cube: Cube,
}

impl Point {
    /// Its layout at dimension d: the observation is p, one action entry per coordinate.
    pub const fn layout_at(d: usize) -> EnvLayout {
        EnvLayout::cube(d, d, 0)
    }

    /// A d-cube with the goal at the origin.
    pub fn new(dim: usize, max_steps: u32) -> Self {
        Self {
            cube: Cube::new(dim, max_steps),
        }
    }
}

impl Env for Point {
    fn layout(&self) -> EnvLayout {
        Self::layout_at(self.cube.pos.len())
    }

    fn reset(&mut self, rng: &mut SaverRng, obs: &mut [f32]) {
        self.cube.start_uniform(rng, obs);
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Step {
        self.cube.advance(obs, |pos| {
            for (p, &a) in pos.iter_mut().zip(action) {
                *p = (*p + 0.1 * a.clamp(-1.0, 1.0)).clamp(-1.0, 1.0);
            }
        })
    }

    cube_state!();
}

#[cfg(test)]
mod tests {
    use super::*;

    /// By hand: from p = (0.5, −0.95), a = (−1, −3) moves by (−0.1, −0.1 clipped at the
    /// wall): p' = (0.4, −1); vector reward |p| − |p'| = (0.1, −0.05).
    #[test]
    fn point_by_hand() {
        let mut r = Point::new(2, 1000);
        r.restore(&[0.5, -0.95, 0.0, 0.0, 0.0]).unwrap();
        let mut obs = [0.0; 2];
        let s = r.step(&[-1.0, -3.0], &mut obs);
        assert!((obs[0] - 0.4).abs() < 1e-6 && obs[1] == -1.0, "{obs:?}");
        assert!((s.vector_reward[0] - 0.1).abs() < 1e-6);
        assert!((s.vector_reward[1] + 0.05).abs() < 1e-6);
    }
}
