//! `saver diagnose pcpn`: how well a frozen PCPN's input gradient — the only signal
//! SAVER's agent gets (docs/ALGORITHM.md §7) — matches the true one, on the angle env,
//! whose dynamics are known in closed form.
//!
//! For S random inputs (p ~ U(-1, 1)^d, μ ~ U(-1, 1)^d, σ ~ U(σ_lo, σ_hi)^d) and the τ
//! grid τ_m = (m + ½)/M:
//!
//! ```text
//! PCPN    J[j, i] = ∂Q_j(τ_m | p, μ, log σ)/∂μ_i and ∂/∂log σ_i        (candle autograd)
//! truth   the τ_m-quantile of Δp_j over N draws a = μ + σ·ε (the same ε for every
//!         perturbation), differentiated by central differences of step h; in the angle
//!         env Δp_j depends only on the action pair of j, so every other entry is 0
//! ```
//!
//! Reported per PCPN (sums over inputs, τ and coordinates): the in-pair cosine and
//! relative error of J against the truth, and the cross-pair ratio ‖J_cross‖/‖J_in,true‖
//! (the share of a coordinate's gradient that comes from action entries that cannot
//! move it). SAVER sums the advantage-weighted J over all d coordinates, so cross
//! entries turn the advantages of the other d − 2 coordinates into noise on each μ_i.

pub use crate::pcpn_gradients::{
    pcpn_jacobians, random_input, true_jacobians, Agreement, Input, Jacobians,
};
use anyhow::{bail, Context, Result};
use candle_core::Device;
use clap::{Args, Subcommand};
use saver_core::env::EnvKind;
use saver_core::rng::{normal, rng_for};
use std::path::PathBuf;

/// `saver diagnose` subcommands.
#[derive(Args, Clone, Debug)]
pub struct DiagnoseArgs {
    /// What to diagnose.
    #[command(subcommand)]
    pub what: Diagnose,
}

/// What `saver diagnose` looks at.
#[derive(Subcommand, Clone, Debug)]
pub enum Diagnose {
    /// Compare angle PCPNs' input gradients (dQ/dμ, dQ/dlog σ) with the true ones.
    Pcpn(PcpnArgs),
}

/// `saver diagnose pcpn` flags.
#[derive(Args, Clone, Debug)]
pub struct PcpnArgs {
    /// PCPN files (safetensors, from `saver pretrain`), angle env of any d.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Random inputs (p, μ, σ) per PCPN.
    #[arg(long, default_value_t = 64)]
    pub inputs: usize,
    /// Quantile levels τ_m = (m + 0.5)/M.
    #[arg(long, default_value_t = 9)]
    pub taus: usize,
    /// Monte Carlo draws per input for the true quantiles.
    #[arg(long, default_value_t = 20_000)]
    pub draws: usize,
    /// Central-difference step (in μ and in log σ).
    #[arg(long, default_value_t = 0.02)]
    pub step: f32,
    /// σ of the inputs ~ U(lo, hi): the pretraining's (0, 1) by default; trained
    /// policies sit near 0.1-0.3.
    #[arg(long, value_delimiter = ',', default_value = "0.05,1")]
    pub sigma: Vec<f32>,
    /// Seed of the inputs and draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Print JSON (one object per PCPN) instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// What one PCPN's diagnosis found.
#[derive(Debug, serde::Serialize)]
pub struct Report {
    pub file: String,
    pub d: usize,
    pub batches: u64,
    pub held_out_loss: String,
    pub mu_cosine: f64,
    pub mu_relative_error: f64,
    pub mu_cross_ratio: f64,
    pub log_std_cosine: f64,
    pub log_std_relative_error: f64,
    pub log_std_cross_ratio: f64,
    /// Mean |Q_pcpn − Q_true| over inputs, τ and coordinates.
    pub quantile_mae: f64,
    /// Mean |Q_true(τ) − Q_true(½)|: the scale the error compares with.
    pub quantile_spread: f64,
}

/// Diagnoses one PCPN file.
pub fn diagnose_file(file: &std::path::Path, args: &PcpnArgs) -> Result<Report> {
    let bytes = std::fs::read(file).with_context(|| format!("reading {}", file.display()))?;
    let spec = saver_pcpn_trainer::store::spec_of(&bytes)
        .with_context(|| format!("{} names no env spec: not a PCPN file", file.display()))?;
    if spec.kind() != Some(EnvKind::Angle) {
        bail!(
            "{} models {spec}; the true gradients are known only for angle",
            file.display()
        );
    }
    let (pcpn, info) =
        saver_pcpn_trainer::store::load_pcpn_bytes(&bytes, file, &spec, &Device::Cpu)?;
    let [lo, hi] = args.sigma[..] else {
        bail!("--sigma takes two values, lo,hi");
    };
    if !(0.0 < lo && lo < hi) {
        bail!("--sigma {lo},{hi}: need 0 < lo < hi");
    }
    let d = pcpn.dim();
    let taus: Vec<f32> = (0..args.taus)
        .map(|m| (m as f32 + 0.5) / args.taus as f32)
        .collect();
    let with_median: Vec<f32> = taus.iter().copied().chain([0.5]).collect();
    let mut rng = rng_for(args.seed, 0);
    let (mut mu, mut ls) = (Agreement::default(), Agreement::default());
    let (mut mae, mut spread, mut n) = (0.0f64, 0.0f64, 0usize);
    for _ in 0..args.inputs {
        let input = random_input(d, (lo, hi), &mut rng);
        let eps: Vec<f32> = (0..args.draws * d).map(|_| normal(&mut rng)).collect();
        // The median rides along as one more τ level: the same sorted draws.
        let mut truth = true_jacobians(&input, &with_median, &eps, args.step);
        let median = truth.q.pop().unwrap_or_default();
        truth.mu.pop();
        truth.log_std.pop();
        let got = pcpn_jacobians(&pcpn, &input, &taus)?;
        mu.add(&got.mu, &truth.mu);
        ls.add(&got.log_std, &truth.log_std);
        for (gm, tm) in got.q.iter().zip(&truth.q) {
            for (j, (&a, &b)) in gm.iter().zip(tm).enumerate() {
                mae += (a - b).abs() as f64;
                spread += (b - median[j]).abs() as f64;
                n += 1;
            }
        }
    }
    Ok(Report {
        file: file.display().to_string(),
        d,
        batches: info.pretrain.batches,
        held_out_loss: info
            .meta
            .get("held_out_loss")
            .cloned()
            .unwrap_or_else(|| "?".into()),
        mu_cosine: mu.cosine(),
        mu_relative_error: mu.relative_error(),
        mu_cross_ratio: mu.cross_ratio(),
        log_std_cosine: ls.cosine(),
        log_std_relative_error: ls.relative_error(),
        log_std_cross_ratio: ls.cross_ratio(),
        quantile_mae: mae / n as f64,
        quantile_spread: spread / n as f64,
    })
}

/// Runs `saver diagnose`.
pub fn run(args: DiagnoseArgs) -> Result<()> {
    let Diagnose::Pcpn(a) = args.what;
    if a.inputs == 0 || a.taus == 0 || a.draws < 2 || a.step.is_nan() || a.step <= 0.0 {
        bail!("--inputs, --taus must be at least 1, --draws at least 2, --step above 0");
    }
    if !a.json {
        crate::out!(
            "PCPN input gradients against the angle env's true ones ({} inputs, {} τ levels, \
             {} draws, σ ~ U({}, {})):",
            a.inputs,
            a.taus,
            a.draws,
            a.sigma.first().unwrap_or(&0.0),
            a.sigma.get(1).unwrap_or(&0.0)
        );
        crate::out!(
            "{:>3} {:>8} {:>9} | {:>7} {:>8} {:>8} | {:>7} {:>8} {:>8} | {:>9} {:>9}  file",
            "d",
            "batches",
            "held-out",
            "μ cos",
            "μ relerr",
            "μ cross",
            "lσ cos",
            "lσ rel",
            "lσ cross",
            "Q MAE",
            "Q spread"
        );
    }
    for f in &a.files {
        let r = diagnose_file(f, &a)?;
        if a.json {
            crate::out!("{}", serde_json::to_string(&r)?);
        } else {
            crate::out!(
                "{:>3} {:>8} {:>9} | {:>7.3} {:>8.3} {:>8.3} | {:>7.3} {:>8.3} {:>8.3} | {:>9.5} {:>9.5}  {}",
                r.d,
                r.batches,
                r.held_out_loss.chars().take(9).collect::<String>(),
                r.mu_cosine,
                r.mu_relative_error,
                r.mu_cross_ratio,
                r.log_std_cosine,
                r.log_std_relative_error,
                r.log_std_cross_ratio,
                r.quantile_mae,
                r.quantile_spread,
                r.file
            );
        }
    }
    Ok(())
}
