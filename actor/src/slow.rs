//! An env that takes longer per step than it needs: what an actor on a slower machine,
//! or with a costlier simulator, looks like to the learner (`saver actor
//! --step-delay-us`; how async mode and V-trace are measured, results/README.md).

use saver_core::env::{Env, EnvLayout, Step};
use saver_core::rng::SaverRng;
use std::time::Duration;

/// `inner`, sleeping `delay` after each step.
pub struct SlowEnv {
    /// The env that does the work.
    pub inner: Box<dyn Env>,
    /// Added to every step.
    pub delay: Duration,
}

impl Env for SlowEnv {
    fn layout(&self) -> EnvLayout {
        self.inner.layout()
    }
    fn reset(&mut self, rng: &mut SaverRng, obs: &mut [f32]) {
        self.inner.reset(rng, obs)
    }
    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Step {
        let step = self.inner.step(action, obs);
        std::thread::sleep(self.delay);
        step
    }
    fn steps(&self) -> u32 {
        self.inner.steps()
    }
    fn goal(&self) -> Vec<f32> {
        self.inner.goal()
    }
    fn snapshot(&self) -> Vec<f32> {
        self.inner.snapshot()
    }
    fn restore(&mut self, state: &[f32]) -> saver_core::Result<()> {
        self.inner.restore(state)
    }
}
