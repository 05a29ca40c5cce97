//! The learned action distribution of a run's policy: `samples` actions drawn at one
//! reset observation (the policy's own sampling, exploration included), a histogram
//! per continuous action dim (up to 4) in `action_histogram.png`, and the share of the
//! draws near each point of interest. Every `saver train` run writes it; for the
//! bandit env it shows whether both optimal actions (±0.75) are kept.

use crate::eval::load;
use crate::figures::{render, Picture};
use anyhow::Result;
use plotters::coord::Shift;
use plotters::prelude::*;
use saver_core::link::{ActorSettings, PolicyWeights};
use saver_core::rng::rng_for;
use std::path::Path;
use std::sync::Arc;

/// Bins over the drawn range.
const BINS: usize = 60;
/// Panels drawn at most.
const MAX_PANELS: usize = 4;

/// `samples` actions of the policy acting with `weights` at one reset observation of
/// its env (seeded by `seed`), [n][action_dim].
pub fn sample_actions(
    settings: &ActorSettings,
    weights: Arc<PolicyWeights>,
    samples: usize,
    seed: u64,
) -> Result<Vec<Vec<f32>>> {
    let mut policy = settings.policy.acting(weights)?;
    let mut env = settings.env.make(settings.max_episode_steps)?;
    let mut rng = rng_for(seed, 0);
    let mut obs = vec![0.0; settings.env.layout().obs_dim];
    env.reset(&mut rng, &mut obs);
    let (mut action, mut payload) = (Vec::new(), Vec::new());
    Ok((0..samples)
        .map(|_| {
            policy.act(&obs, &mut rng, &mut action, &mut payload);
            action.clone()
        })
        .collect())
}

/// The share of `xs` within `radius` of `at`.
pub fn share_near(xs: &[f32], at: f32, radius: f32) -> f64 {
    xs.iter().filter(|x| (*x - at).abs() <= radius).count() as f64 / xs.len().max(1) as f64
}

/// Draws the histograms of `actions` ([n][action_dim]) into `png` (PNG or SVG).
pub fn draw(actions: &[Vec<f32>], title: &str, png: &Path) -> Result<()> {
    let dims = actions.first().map_or(0, |a| a.len()).min(MAX_PANELS);
    if dims == 0 {
        return Ok(());
    }
    let size = (360 * dims as u32, 320);
    render(
        &Histograms {
            actions,
            dims,
            title,
        },
        size,
        png,
    )
}

/// One histogram panel per action dim.
struct Histograms<'a> {
    actions: &'a [Vec<f32>],
    dims: usize,
    title: &'a str,
}

impl Picture for Histograms<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<()>
    where
        DB::ErrorType: 'static,
    {
        panels(root, self.actions, self.dims, self.title)
    }
}

fn panels<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    actions: &[Vec<f32>],
    dims: usize,
    title: &str,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e}"))?;
    for (j, area) in root.split_evenly((1, dims)).iter().enumerate() {
        // The env clips to [-1, 1]; show a little beyond, and any mass further out in
        // the outer bins.
        let (lo, hi) = (-1.5f32, 1.5f32);
        let w = (hi - lo) / BINS as f32;
        let mut counts = vec![0usize; BINS];
        for a in actions {
            let b = ((a[j].clamp(lo, hi - 1e-6) - lo) / w) as usize;
            counts[b.min(BINS - 1)] += 1;
        }
        let top = counts.iter().copied().max().unwrap_or(1) as f32 / actions.len() as f32;
        let mut chart = ChartBuilder::on(area)
            .caption(format!("{title}: action {j}"), ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(30)
            .y_label_area_size(45)
            .build_cartesian_2d(lo..hi, 0f32..top * 1.1)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        chart
            .configure_mesh()
            .x_desc("action (clipped to [-1.5, 1.5])")
            .y_desc("share of draws")
            .label_style(("sans-serif", 12))
            .draw()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        chart
            .draw_series(counts.iter().enumerate().map(|(b, &c)| {
                let x0 = lo + b as f32 * w;
                Rectangle::new(
                    [(x0, 0.0), (x0 + w, c as f32 / actions.len() as f32)],
                    BLUE.mix(0.6).filled(),
                )
            }))
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    Ok(())
}

/// Writes `run`'s action histogram (4,000 draws) as `action_histogram.png` in it and
/// returns the draws; `None` for an env this build cannot make (a custom env, whose
/// actors run elsewhere).
pub fn write_for_run(run: &Path) -> Result<Option<Vec<Vec<f32>>>> {
    let (settings, weights) = load(run)?;
    if settings.env.kind().is_none() {
        return Ok(None);
    }
    let actions = sample_actions(&settings, weights, 4000, 0)?;
    let name = run.file_name().map_or_else(
        || run.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    );
    draw(&actions, &name, &run.join("action_histogram.png"))?;
    Ok(Some(actions))
}
