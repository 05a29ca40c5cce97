//! `saver act`: a trained policy as a filter — observations in, actions out, one JSON
//! line each — for any program that would rather pipe than link (and the check that
//! another implementation of a policy family acts as this one does).

use anyhow::{bail, Context, Result};
use clap::Args;
use saver_core::rng::rng_for;
use std::io::{BufRead, Write};
use std::path::PathBuf;

/// `saver act` flags.
#[derive(Args, Clone, Debug)]
pub struct ActArgs {
    /// A run folder (its checkpoint) or a weights file (from `saver weights --save`,
    /// a learner's weights directory, or GetWeights).
    pub source: PathBuf,
    /// Seed of the sampled actions.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Runs `saver act`: reads one observation per line from stdin (a JSON array of
/// numbers) and writes per line `{"action": [...], "payload": [...], "mean_action":
/// [...]}`: a sampled action, what the policy recorded for it (gaussian-mlp: μ then
/// log σ; quantile-mlp: τ) and the deterministic action.
pub fn run(args: ActArgs) -> Result<()> {
    let (settings, weights) = crate::eval::load(&args.source)?;
    let layout = settings.env.layout();
    let mut policy = settings.policy.acting(weights)?;
    let mut rng = rng_for(args.seed, saver_core::rng::streams::EVAL);
    let (mut action, mut payload, mut mean) = (Vec::new(), Vec::new(), Vec::new());
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    for (i, line) in std::io::stdin().lock().lines().enumerate() {
        let line = line.context("reading stdin")?;
        if line.trim().is_empty() {
            continue;
        }
        let obs: Vec<f32> = serde_json::from_str(&line)
            .with_context(|| format!("line {}: not a JSON array of numbers", i + 1))?;
        if obs.len() != layout.obs_dim || obs.iter().any(|v| !v.is_finite()) {
            bail!(
                "line {}: {} values where {} takes {} finite ones",
                i + 1,
                obs.len(),
                settings.env,
                layout.obs_dim
            );
        }
        policy.act(&obs, &mut rng, &mut action, &mut payload);
        policy.act_deterministic(&obs, &mut mean);
        let row = serde_json::json!({"action": action, "payload": payload, "mean_action": mean});
        if writeln!(out, "{row}").is_err() {
            return Ok(()); // the reader went away
        }
    }
    Ok(())
}
