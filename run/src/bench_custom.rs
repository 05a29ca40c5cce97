//! The custom-env half of `saver bench`: SAVER's update at a custom env's defaults on
//! Reacher-v5's shape (10 observations, 2 torques, d = 2; 8 envs × 64 steps with the
//! env's own reward), beside the defaults before 2026-12-08 (K = 32, the PCPN's step on
//! every row), whose ratio is what the newer ones save.

use anyhow::Result;
use candle_core::Device;
use saver_core::algo::{build, Algorithm};
use saver_core::config::{Algo, RunConfig};
use saver_core::env::{EnvBounds, EnvLayout, EnvSpec};
use saver_core::nets::Pcpn;
use saver_core::rollout::Batch;

/// Reacher-v5's shape as a custom env: p (the fingertip) at entries 8-9.
fn reacher_shape() -> Result<EnvSpec> {
    let layout = EnvLayout {
        obs_dim: 10,
        continuous: 2,
        choices: 0,
        aligned_start: 8,
        aligned_dim: 2,
    };
    let bounds = EnvBounds {
        obs_low: vec![-1.0; 10],
        obs_high: vec![1.0; 10],
        max_change: 0.2,
    };
    Ok(EnvSpec::custom("reacher-shape", layout, bounds)?)
}

/// Seconds per update of SAVER at `config` on `batch` (a random PCPN).
fn seconds_per_update(config: &RunConfig, batch: &Batch, seconds: f64) -> Result<f64> {
    let dev = Device::Cpu;
    let pcpn = Pcpn::random_frozen(&config.env.layout(), 0, candle_core::DType::F32, &dev)?;
    let mut a: Box<dyn Algorithm> = build(config, Some(pcpn), &dev)?;
    a.set_threads(crate::pcpn_threads());
    crate::bench::time(seconds, || {
        a.update(batch)?;
        Ok(())
    })
}

/// Prints SAVER's update at a custom env's defaults and at the older ones.
pub fn custom_env_updates(seconds: f64) -> Result<()> {
    let spec = reacher_shape()?;
    let config = saver_core::algo::recommended(&spec, Algo::Saver, 1);
    let l = spec.layout();
    // The shape of a default custom-env batch: 8 envs × the rollout, with the env's
    // reward (which turns the env-return term on).
    let mut batch = crate::bench::synthetic_batch(&l, 8, config.rollout as usize, 0);
    batch.env_reward = (0..batch.len()).map(|i| -0.01 * (i % 7) as f32).collect();
    let mut before = config.clone();
    (before.saver.quantiles, before.saver.pcpn_tune_rows) = (32, 0);
    crate::out!(
        "\nSAVER at a custom env's defaults, Reacher-v5's shape ({} × {} steps, K = {}, the PCPN's \
         step on {} rows; PCPN blocks on the default threads):",
        batch.n_traj,
        batch.n_steps,
        config.saver.quantiles,
        config.saver.pcpn_tune_rows
    );
    let now = seconds_per_update(&config, &batch, seconds)?;
    let old = seconds_per_update(&before, &batch, seconds)?;
    crate::out!(
        "  {:.1} ms/update ({:.0} steps/s); with K = 32 and every row (the defaults before 2026-12-08, on this step) \
         {:.1} ms: {:.2}x",
        now * 1e3,
        batch.len() as f64 / now,
        old * 1e3,
        old / now
    );
    Ok(())
}
