//! Off-policy correction of rollouts acted by an older policy (docs/ALGORITHM.md §16):
//! the ratios π/μ of the batch's actions, from the behaviour policy's payload, and the
//! V-trace critic targets and advantages A2C and SAVER learn from under `--vtrace`.

use super::{behaviour_log_probs, behaviour_payload_width, bootstrap_and_ends};
use crate::config::RunConfig;
use crate::env::{EnvLayout, Routing};
use crate::rollout::Batch;
use crate::Result;
use candle_core::Tensor;

/// V-trace's clips (docs/ALGORITHM.md §16), for a run that corrects its rollouts.
#[derive(Clone, Copy, Debug)]
pub struct Vtrace {
    /// ρ̄.
    pub rho_bar: f32,
    /// c̄.
    pub c_bar: f32,
    /// λ, the traces' decay on top of c̄: c_t = λ·min(c̄, π/μ) (IMPALA's Remark 2; 1 but
    /// in SAVER with `saver.gae_lambda`).
    pub lambda: f32,
}

/// What an update learns from under V-trace.
pub struct Corrected {
    /// [B, c]: the critic's targets v_t.
    pub targets: Vec<f32>,
    /// [B, c]: the policy's advantages ρ_t·(r_t + γ·v_next − V(o_t)).
    pub advantages: Vec<f32>,
    /// The ratio statistics, by [`VTRACE_STATS`] name.
    pub stats: Vec<(&'static str, f32)>,
}

/// How far above ρ̄ a ratio must be to count in `vtrace_clipped`.
const CLIP_TOLERANCE: f32 = 1e-4;

/// The metrics.csv columns V-trace adds: the mean and largest ratio π/μ of the batch's
/// steps and the share of steps whose ratio ρ̄ clips (by more than 1e-4 of ρ̄).
pub const VTRACE_STATS: [&str; 3] = ["vtrace_ratio_mean", "vtrace_ratio_max", "vtrace_clipped"];

impl Vtrace {
    /// A run's V-trace, when it asks for one.
    pub fn of(config: &RunConfig) -> Option<Self> {
        config.vtrace.then_some(Self {
            rho_bar: config.rho_bar as f32,
            c_bar: config.c_bar as f32,
            lambda: 1.0,
        })
    }

    /// The critic targets and policy advantages ([B, c] each) of `rewards` ([B, c])
    /// for ratios whose logs are `log_ratio`: one a step ([B], [`shared_log_ratios`])
    /// or one a step and coordinate ([B, c], [`coordinate_log_ratios`]), with
    /// `values` V at [`update_rows`]' rows ([rows, c]; `n_ends` timeouts), and the
    /// ratio statistics ([`VTRACE_STATS`]) over them all.
    #[allow(clippy::too_many_arguments)]
    pub fn targets(
        self,
        batch: &Batch,
        rewards: &[f32],
        values: &Tensor,
        n_ends: usize,
        c: usize,
        gamma: f32,
        log_ratio: &[f32],
    ) -> Result<Corrected> {
        let b = batch.len();
        let ratio: Vec<f32> = log_ratio.iter().map(|l| l.exp()).collect();
        let rho: Vec<f32> = ratio.iter().map(|r| r.min(self.rho_bar)).collect();
        let cs: Vec<f32> = ratio
            .iter()
            .map(|r| self.lambda * r.min(self.c_bar))
            .collect();
        let v = values.narrow(0, 0, b)?.flatten_all()?.to_vec1::<f32>()?;
        let (bootstrap, ends) = bootstrap_and_ends(batch, values, n_ends, c)?;
        let (targets, adv) = crate::returns::vtrace(
            rewards,
            &v,
            &batch.done,
            &bootstrap,
            ends.as_deref(),
            &rho,
            &cs,
            batch.n_steps,
            c,
            gamma,
        );
        let n = ratio.len().max(1) as f64;
        let mean = ratio.iter().map(|&r| r as f64).sum::<f64>() / n;
        let max = ratio.iter().copied().fold(0.0f32, f32::max);
        // A ratio above ρ̄ by rounding alone (the actor's forward pass against the
        // learner's, ~1e-6 apart on a current rollout) is not counted as clipped.
        let clipped = ratio
            .iter()
            .filter(|&&r| r > self.rho_bar * (1.0 + CLIP_TOLERANCE))
            .count() as f64
            / n;
        let stats = VTRACE_STATS
            .into_iter()
            .zip([mean as f32, max, clipped as f32])
            .collect();
        Ok(Corrected {
            targets,
            advantages: adv,
            stats,
        })
    }
}

/// log π/μ of each step's whole action ([B]), for a learner whose policy gives the
/// batch's actions log-probabilities `log_pi`: the one ratio of A2C, and of SAVER where
/// the env does not say which part of an action moves which coordinate.
pub fn shared_log_ratios(
    layout: &EnvLayout,
    batch: &Batch,
    log_pi: &[f32],
    dev: &candle_core::Device,
) -> Result<Vec<f32>> {
    let log_mu = behaviour_log_probs(layout, batch, dev)?;
    Ok(log_pi.iter().zip(&log_mu).map(|(p, m)| p - m).collect())
}

/// log π/μ of what coordinate j saw of each step's action ([B, d], docs/ALGORITHM.md
/// §16): the factors of the action that move coordinate j under `routing`, the
/// learner's policy (`mu` [B, continuous + choices], `log_std` [B, continuous], host)
/// against the behaviour's payload.
/// - `Own`: continuous entry j's Gaussian factor;
/// - `Pairs`: the pair's two entries' factors, for both of its coordinates;
/// - `Choice`: where j was chosen, the step's factor times p'_j / p_j; where not,
///   (1 − p'_j) / (1 − p_j), the odds that j stays where it is;
/// - `Shared`: the whole action's, the same for every j.
///
/// With every factor 1 (on-policy) every ratio is exactly 1. Sums in f64.
pub fn coordinate_log_ratios(
    routing: Routing,
    layout: &EnvLayout,
    batch: &Batch,
    mu: &[f32],
    log_std: &[f32],
) -> Result<Vec<f32>> {
    let (b, c, k, d) = (
        batch.len(),
        layout.continuous,
        layout.choices,
        layout.aligned_dim,
    );
    let (m, a_dim) = (layout.mu_dim(), layout.action_dim());
    let width = behaviour_payload_width(layout, batch)?;
    if mu.len() != b * m || log_std.len() != b * c {
        return Err(crate::CoreError::Data(format!(
            "per-coordinate ratios need the learner's μ ({m}) and log σ ({c}) for each of \
             the {b} steps; got {} and {}",
            mu.len(),
            log_std.len()
        )));
    }
    if !routing.fits(layout) {
        return Err(crate::CoreError::Data(format!(
            "routing {routing:?} does not fit a layout of {c} continuous entries, {k} choices \
             and {d} coordinates"
        )));
    }
    let mut out = vec![0f32; b * d];
    let mut gauss = vec![0f64; c];
    for i in 0..b {
        let a = &batch.actions[i * a_dim..(i + 1) * a_dim];
        let then = &batch.payload[i * width..(i + 1) * width];
        let (mu_now, ls_now) = (&mu[i * m..(i + 1) * m], &log_std[i * c..(i + 1) * c]);
        // log N(a; μ', σ') − log N(a; μ, σ) per continuous entry.
        for (e, g) in gauss.iter_mut().enumerate() {
            let half_z2 = |mean: f32, ls: f32| {
                let z = (a[e] as f64 - mean as f64) / (ls as f64).exp();
                0.5 * z * z + ls as f64
            };
            *g = half_z2(then[e], then[m + e]) - half_z2(mu_now[e], ls_now[e]);
        }
        let (p_now, p_then) = (softmax(&mu_now[c..]), softmax(&then[c..m]));
        let pick = (0..k).find(|&j| a[c + j] > 0.5);
        let choice = pick.map_or(0.0, |j| p_now[j].ln() - p_then[j].ln());
        let whole = gauss.iter().sum::<f64>() + choice;
        let row = &mut out[i * d..(i + 1) * d];
        for (j, r) in row.iter_mut().enumerate() {
            *r = match routing {
                Routing::Shared => whole,
                Routing::Own => gauss[j],
                Routing::Pairs => gauss[j & !1] + gauss[j | 1],
                Routing::Choice if pick == Some(j) => whole,
                Routing::Choice => (-p_now[j]).ln_1p() - (-p_then[j]).ln_1p(),
            } as f32;
        }
    }
    Ok(out)
}

/// softmax of `logits` in f64.
fn softmax(logits: &[f32]) -> Vec<f64> {
    let max = logits
        .iter()
        .fold(f64::NEG_INFINITY, |m, &l| m.max(l as f64));
    let e: Vec<f64> = logits.iter().map(|&l| (l as f64 - max).exp()).collect();
    let total: f64 = e.iter().sum();
    e.into_iter().map(|x| x / total).collect()
}

#[cfg(test)]
mod tests;
