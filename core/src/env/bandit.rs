//! `bandit`: a one-step continuous bandit with two separated optimal actions and a
//! broad decoy, where a unimodal (Gaussian) policy gets stuck and a quantile policy
//! need not (standalone QRRL's multi-modality check; docs/ALGORITHM.md §14).
//!
//! R(a) = max(0.5·exp(−a²/(2·0.25²)), exp(−(|a| − 0.75)²/(2·0.05²))), a clipped to
//! [-1, 1]: a wide peak of 0.5 at a = 0 and narrow peaks of 1.0 at a = ±0.75. As a
//! state-aligned env: the position starts at p = 1 with the goal at 0 and the step
//! moves it to p' = 1 − R(a), so the vector reward |p| − |p'| is R(a); success is
//! R(a) > 0.9 (|p'| < 0.1), and every episode ends after its one step.

use super::{Cube, Env, EnvLayout, Step};
use crate::rng::SaverRng;

/// The reward of action `a` (clipped to [-1, 1]).
pub fn bandit_reward(a: f32) -> f32 {
    let a = a.clamp(-1.0, 1.0);
    let wide = 0.5 * (-(a * a) / (2.0 * 0.25 * 0.25)).exp();
    let narrow = (-((a.abs() - 0.75).powi(2)) / (2.0 * 0.05 * 0.05)).exp();
    wide.max(narrow)
}

/// The bandit; its state is the position p and the step count.
pub struct Bandit {
    /// Position (1 at reset), goal (the origin), steps (0 or 1) and the limit: 1
    /// ([`super::EnvKind::fixed_episode_steps`]; runs are held to it).
    cube: Cube,
}

impl Bandit {
    /// Its layout: p in one coordinate, one continuous action.
    pub const LAYOUT: EnvLayout = EnvLayout::cube(1, 1, 0);

    /// A fresh bandit with the step limit `max_steps` (1 in every valid run).
    pub fn new(max_steps: u32) -> Self {
        let mut cube = Cube::new(1, max_steps);
        cube.pos[0] = 1.0;
        Self { cube }
    }
}

impl Env for Bandit {
    fn layout(&self) -> EnvLayout {
        Self::LAYOUT
    }

    fn reset(&mut self, _rng: &mut SaverRng, obs: &mut [f32]) {
        self.cube.pos[0] = 1.0;
        self.cube.start(obs);
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Step {
        self.cube
            .advance(obs, |pos| pos[0] = 1.0 - bandit_reward(action[0]))
    }

    cube_state!();
}

#[cfg(test)]
mod tests {
    use super::*;

    /// By hand: R(0) = 0.5, R(±0.75) = 1, R(0.375) = max(0.5·e^-1.125, e^-28.1)
    /// = 0.16232, R(2) = R(1) = max(0.5·e^-8, e^-12.5) = 0.000168; the vector reward is
    /// R and the episode ends after one step, a success only near ±0.75.
    #[test]
    fn bandit_by_hand() {
        assert!((bandit_reward(0.0) - 0.5).abs() < 1e-6);
        assert!((bandit_reward(0.75) - 1.0).abs() < 1e-6);
        assert!((bandit_reward(-0.75) - 1.0).abs() < 1e-6);
        assert!((bandit_reward(0.375) - 0.162_32).abs() < 1e-5);
        assert!((bandit_reward(2.0) - 0.000_167_7).abs() < 1e-6);
        let mut b = Bandit::new(1);
        let mut obs = [0.0];
        b.reset(&mut crate::rng::rng_for(0, 0), &mut obs);
        assert_eq!(obs, [1.0]);
        let s = b.step(&[-0.75], &mut obs);
        assert!(s.success && s.done() && (s.vector_reward[0] - 1.0).abs() < 1e-6);
        b.reset(&mut crate::rng::rng_for(0, 0), &mut obs);
        let s = b.step(&[0.0], &mut obs);
        assert!(!s.success && s.timeout && (s.vector_reward[0] - 0.5).abs() < 1e-6);
    }
}
