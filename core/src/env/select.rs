//! `select` (paper Fig. 4): action = [step, one-hot of d]; step = 0.1·clip(a[0]); the
//! chosen coordinate moves by step, clipped to [-1, 1]; the others stay.

use super::{finish_step, Env, EnvLayout, Step};
use crate::rng::SaverRng;
use rand::Rng;

/// The d-cube where the agent picks one dimension and a step.
pub struct Select {
    /// Position p in [-1, 1]^d.
    pos: Vec<f32>,
    /// Goal g.
    goal: Vec<f32>,
    /// Steps in this episode.
    steps: u32,
    /// Episode limit.
    max_steps: u32,
}

impl Select {
    /// A d-cube with the goal at the origin.
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
        super::EnvKind::Select.layout(self.pos.len())
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
        let step = 0.1 * action[0].clamp(-1.0, 1.0);
        let j = argmax(&action[1..]);
        self.pos[j] = (self.pos[j] + step).clamp(-1.0, 1.0);
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
