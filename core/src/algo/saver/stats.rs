//! The statistics of a SAVER update: its losses, the policy's, and the per-dimension and
//! signal statistics of the batch at the update's start.

use super::signal::{rank_stats, snr_stats, SignalBatch, SIGNAL_EVERY};
use super::step::Losses;
use super::{Saver, Start};
use crate::algo::{policy_diagnostics, UpdateStats};
use crate::rollout::Batch;
use crate::Result;

impl Saver {
    /// The update's statistics: its losses, the policy's and the per-dimension ones of
    /// the batch at its start, and the signal's (`dmu`: dL/dμ per row, fast path).
    pub(super) fn finish(
        &mut self,
        batch: &Batch,
        s: Start,
        dmu: Option<Vec<f32>>,
        l: Losses,
        tune_loss: Option<f32>,
    ) -> Result<UpdateStats> {
        let d = self.layout.aligned_dim;
        let (mu_abs_max, log_std_mean) = policy_diagnostics(&s.fwd.mu, &s.fwd.log_std)?;
        let signal = SignalBatch::of(
            batch,
            &s.mu_host,
            &s.log_std_host,
            &s.adv_host,
            dmu.as_deref(),
        );
        let mut per_dim = crate::algo::per_dim::per_dim_stats(
            &s.returns_host,
            &s.value_host,
            &batch.vector_reward,
            &s.mu_host,
            &s.log_std_host,
            d,
            self.mu_bound,
        );
        // The rank statistics cost PCPN passes: made on this learner's first update (a
        // resumed run's per_dim.csv keeps its columns) and every SIGNAL_EVERY-th
        // optimiser step, the last ones repeated in between.
        if self.ranks.is_empty() || self.opt.steps().is_multiple_of(SIGNAL_EVERY) {
            self.ranks = rank_stats(self.pcpn.pcpn(), &self.layout, &signal, &self.dev)?;
        }
        per_dim.extend(self.ranks.iter().cloned());
        per_dim.extend(snr_stats(&self.layout, &signal));
        let mut values = vec![
            ("actor_loss", l.actor),
            ("mon_loss", l.mon),
            ("critic_loss", l.critic),
            ("mu_abs_max", mu_abs_max),
            ("log_std_mean", log_std_mean),
            ("grad_norm", l.grad_norm),
        ];
        values.extend(tune_loss.map(|l| ("pcpn_tune_loss", l)));
        values.extend(s.vtrace_stats);
        if self.env.is_some() {
            values.extend([
                ("env_pg_loss", l.env_pg),
                ("env_pg_scale", l.env_scale),
                ("env_critic_loss", l.env_critic),
            ]);
        }
        Ok(UpdateStats { values, per_dim })
    }
}
