//! Off-policy correction of rollouts acted by an older policy (docs/ALGORITHM.md §16):
//! the ratios π/μ of the batch's actions, from the behaviour policy's payload, and the
//! V-trace critic targets and advantages A2C and SAVER learn from under `--vtrace`.

use super::{behaviour_log_probs, bootstrap_and_ends};
use crate::config::RunConfig;
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
    /// for a learner whose policy gives the batch's actions log-probabilities `log_pi`,
    /// with `values` V at [`update_rows`]' rows ([rows, c]; `n_ends` timeouts), and the
    /// ratio statistics ([`VTRACE_STATS`]).
    #[allow(clippy::too_many_arguments)]
    pub fn targets(
        self,
        batch: &Batch,
        layout: &crate::env::EnvLayout,
        rewards: &[f32],
        values: &Tensor,
        n_ends: usize,
        c: usize,
        gamma: f32,
        log_pi: &[f32],
    ) -> Result<Corrected> {
        let b = batch.len();
        let log_mu = behaviour_log_probs(layout, batch, values.device())?;
        let ratio: Vec<f32> = log_pi
            .iter()
            .zip(&log_mu)
            .map(|(p, m)| (p - m).exp())
            .collect();
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

#[cfg(test)]
mod tests;
