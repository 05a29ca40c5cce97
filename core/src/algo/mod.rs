//! The learner's algorithms behind one trait, so the learner loop, checkpoints and
//! weight publishing do not care which one runs (and a third, standalone QRRL, fits).

mod a2c;
mod fused;
mod saver;
mod saver_grad;

pub use a2c::A2c;
pub use fused::{pcpn_threads, set_pcpn_threads};
pub use saver::{saver_actor_losses, tau_tensors, GradPath, Saver, SaverLosses};
pub use saver_grad::{policy_grads, InputGrad, PcpnGrad};

use crate::config::{Algo, RunConfig};
use crate::nets::Pcpn;
use crate::rollout::Batch;
use crate::{CoreError, Result};
use candle_core::{Device, Tensor};
use saver_proto::NamedTensor;

/// Losses and diagnostics of one update, in the order of [`Algorithm::stat_names`].
#[derive(Clone, Debug, PartialEq)]
pub struct UpdateStats {
    /// Values, one per name.
    pub values: Vec<f32>,
}

/// A learning algorithm: updates from batches and exposes its state.
pub trait Algorithm: Send {
    /// Names of the values in [`UpdateStats`] (CSV columns).
    fn stat_names(&self) -> &'static [&'static str];
    /// One update from a batch. [`CoreError::NonFinite`] when the batch makes a loss
    /// or gradient non-finite: then nothing changed (weights, optimiser slots and step
    /// count are as before) and the caller may go on with the next batch.
    fn update(&mut self, batch: &Batch) -> Result<UpdateStats>;
    /// The agent's weights (`agent.*`), what actors need.
    fn policy_tensors(&self) -> Result<Vec<NamedTensor>>;
    /// Everything a checkpoint needs: every trainable tensor and the optimiser slots.
    fn state_tensors(&self) -> Result<Vec<(String, Tensor)>>;
    /// Optimiser steps taken.
    fn optimizer_steps(&self) -> u64;
    /// Position of the learner's random stream (SAVER's tau draws), for checkpoints.
    fn rng_word_pos(&self) -> Option<u128> {
        None
    }
    /// Restores [`Algorithm::rng_word_pos`].
    fn set_rng_word_pos(&mut self, _pos: u128) {}
    /// Restores what [`Algorithm::state_tensors`] saved.
    fn load_state(
        &mut self,
        get: &dyn Fn(&str) -> Option<Tensor>,
        optimizer_steps: u64,
    ) -> Result<()>;
}

/// Builds the configured algorithm; SAVER needs its frozen PCPN.
pub fn build(config: &RunConfig, pcpn: Option<Pcpn>, dev: &Device) -> Result<Box<dyn Algorithm>> {
    match config.algo {
        Algo::A2c => Ok(Box::new(A2c::new(config, dev)?)),
        Algo::Saver => {
            let pcpn =
                pcpn.ok_or_else(|| CoreError::Config("algo saver needs a pretrained PCPN".into()))?;
            Ok(Box::new(Saver::new(config, pcpn, dev)?))
        }
    }
}

/// Diagnostics both algorithms report: max |μ| over the batch and mean log σ.
pub(crate) fn policy_diagnostics(mu: &Tensor, log_std: &Tensor) -> Result<(f32, f32)> {
    let mu_abs_max = mu.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
    let log_std_mean = log_std.mean_all()?.to_scalar::<f32>()?;
    Ok((mu_abs_max, log_std_mean))
}

/// A tensor [rows, cols] from a row-major slice.
pub(crate) fn matrix(data: &[f32], rows: usize, cols: usize, dev: &Device) -> Result<Tensor> {
    Ok(Tensor::from_slice(data, (rows, cols), dev)?)
}

/// The rows an update evaluates its networks at: the batch's observations, the last
/// observation of each trajectory and, when the run bootstraps at timeouts, the final
/// observation of each timeout; with the count of the last kind.
pub(crate) fn update_rows(
    batch: &crate::rollout::Batch,
    bootstrap_timeout: bool,
    obs_dim: usize,
    dev: &Device,
) -> Result<(Tensor, usize)> {
    let mut rows = vec![
        matrix(&batch.obs, batch.len(), obs_dim, dev)?,
        matrix(&batch.last_obs, batch.n_traj, obs_dim, dev)?,
    ];
    let k = if bootstrap_timeout {
        batch.timeouts.len()
    } else {
        0
    };
    if k > 0 {
        rows.push(matrix(&batch.timeout_obs, k, obs_dim, dev)?);
    }
    Ok((Tensor::cat(&rows, 0)?, k))
}

/// The `ends` of [`crate::returns::n_step_returns`] from the values of all update rows
/// ([`update_rows`], [rows, c]): none without bootstrapped timeouts.
pub(crate) fn timeout_ends(
    batch: &crate::rollout::Batch,
    values: &Tensor,
    k: usize,
    c: usize,
) -> Result<Option<Vec<f32>>> {
    if k == 0 {
        return Ok(None);
    }
    let v = values
        .narrow(0, batch.len() + batch.n_traj, k)?
        .flatten_all()?
        .to_vec1::<f32>()?;
    Ok(Some(batch.timeout_ends(&v, c)))
}

/// A non-finite loss is [`CoreError::NonFinite`]: the update is skipped before it
/// changes anything.
pub(crate) fn check_finite(name: &str, v: f32) -> Result<f32> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(CoreError::NonFinite(format!("{name} is {v}")))
    }
}

#[cfg(test)]
mod tests;
