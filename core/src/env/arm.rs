//! `arm` (paper Fig. 5): two joints, links of length 1, angles from the +y axis;
//! hand = Σ_j (sin Θ_j, cos Θ_j) with Θ_j the cumulative angle;
//! θ ← wrap(θ + 0.02·π·clip(a)) into [-π, π). obs = [goal(2), angles(2), hand(2)].

use super::{finish_step, Env, EnvLayout, Step};
use crate::rng::SaverRng;
use rand::Rng;
use std::f32::consts::PI;

/// The two-joint arm; the hand is the state-aligned part.
pub struct Arm {
    /// Joint angles θ in [-π, π).
    angles: [f32; 2],
    /// Goal for the hand, in [-1, 1]^2.
    goal: [f32; 2],
    /// Steps in this episode.
    steps: u32,
    /// Episode limit.
    max_steps: u32,
}

/// Wraps an angle into [-π, π).
pub fn wrap_angle(x: f32) -> f32 {
    let two_pi = 2.0 * PI;
    let y = (x + PI).rem_euclid(two_pi) - PI;
    // rem_euclid can round up to exactly 2π; keep the interval half-open.
    if y >= PI {
        y - two_pi
    } else {
        y
    }
}

/// Hand position of joint angles θ.
pub fn hand(angles: [f32; 2]) -> [f32; 2] {
    let t1 = angles[0];
    let t2 = angles[0] + angles[1];
    [t1.sin() + t2.sin(), t1.cos() + t2.cos()]
}

impl Arm {
    /// Its layout: obs = [goal (2), joint angles (2), hand (2)]; the hand is the
    /// aligned part.
    pub const LAYOUT: EnvLayout = EnvLayout {
        obs_dim: 6,
        continuous: 2,
        choices: 0,
        aligned_start: 4,
        aligned_dim: 2,
    };

    /// An arm with both angles 0 and the goal at the origin until the first reset.
    pub fn new(max_steps: u32) -> Self {
        Self {
            angles: [0.0; 2],
            goal: [0.0; 2],
            steps: 0,
            max_steps,
        }
    }

    /// Sets the joint angles and the goal (tests and diagnostics).
    pub fn set_state(&mut self, angles: [f32; 2], goal: [f32; 2]) {
        self.angles = angles;
        self.goal = goal;
    }

    fn write_obs(&self, obs: &mut [f32]) {
        let h = hand(self.angles);
        obs.copy_from_slice(&[
            self.goal[0],
            self.goal[1],
            self.angles[0],
            self.angles[1],
            h[0],
            h[1],
        ]);
    }
}

impl Env for Arm {
    fn layout(&self) -> EnvLayout {
        Self::LAYOUT
    }

    fn reset(&mut self, rng: &mut SaverRng, obs: &mut [f32]) {
        self.goal = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
        self.angles = [rng.random_range(-PI..PI), rng.random_range(-PI..PI)];
        self.steps = 0;
        self.write_obs(obs);
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Step {
        let before = hand(self.angles);
        for (theta, &a) in self.angles.iter_mut().zip(action) {
            *theta = wrap_angle(*theta + 0.02 * PI * a.clamp(-1.0, 1.0));
        }
        self.steps += 1;
        self.write_obs(obs);
        finish_step(
            &before,
            &hand(self.angles),
            &self.goal,
            self.steps,
            self.max_steps,
        )
    }

    fn steps(&self) -> u32 {
        self.steps
    }

    fn goal(&self) -> Vec<f32> {
        self.goal.to_vec()
    }

    fn snapshot(&self) -> Vec<f32> {
        super::snapshot_of(&self.angles, &self.goal, self.steps)
    }

    fn restore(&mut self, state: &[f32]) -> crate::Result<()> {
        super::restore_into(state, &mut self.angles, &mut self.goal, &mut self.steps)
    }
}
