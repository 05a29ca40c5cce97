//! What the algorithms share: checkpoint helpers, the update's rows and return
//! recursions, minibatch gathers, behaviour log-probabilities, the optimiser a config
//! asks for, FLOP counts and τ's embedding. It names no algorithm: every arrow goes
//! from an algorithm to here.

use super::algorithm::{AlgoState, OPTIMIZER_STEPS, RNG_WORD_POS};
use crate::acting::PolicyFamily;
use crate::config::RunConfig;
use crate::embedding::{cosine_embedding, EMBED_DIM};
use crate::nets::Gaussian;
use crate::optim::Optimizer;
use crate::rollout::Batch;
use crate::{CoreError, Result};
use candle_core::{Device, Tensor};
use std::collections::BTreeMap;
use std::sync::Arc;

/// The checkpointed state of networks `nets` trained by `opt`, and the position of the
/// random stream `rng` where the update draws from one.
pub(crate) fn nets_state(
    nets: &[&crate::nets::ParamSet],
    opt: &Optimizer,
    rng: Option<&crate::rng::SaverRng>,
) -> Result<AlgoState> {
    let mut tensors = Vec::new();
    for n in nets {
        tensors.extend(n.tensors()?);
    }
    let mut state = AlgoState::with_optimizer(tensors, opt);
    if let Some(rng) = rng {
        state
            .numbers
            .insert(RNG_WORD_POS.to_string(), rng.get_word_pos());
    }
    Ok(state)
}

/// Restores what [`nets_state`] saved.
pub(crate) fn restore_nets(
    nets: &[&crate::nets::ParamSet],
    opt: &mut Optimizer,
    rng: Option<&mut crate::rng::SaverRng>,
    get: &dyn Fn(&str) -> Option<Tensor>,
    numbers: &BTreeMap<String, u128>,
) -> Result<()> {
    for n in nets {
        n.load(get)?;
    }
    restore_optimizer(opt, get, numbers)?;
    if let Some(rng) = rng {
        rng.set_word_pos(saved_number(numbers, RNG_WORD_POS)?);
    }
    Ok(())
}

/// Restores `opt` (slots and step count) from a saved state.
pub(crate) fn restore_optimizer(
    opt: &mut Optimizer,
    get: &dyn Fn(&str) -> Option<Tensor>,
    numbers: &BTreeMap<String, u128>,
) -> Result<()> {
    opt.restore(get, saved_number(numbers, OPTIMIZER_STEPS)? as u64)
}

/// The number `key` of a saved state.
pub(crate) fn saved_number(numbers: &BTreeMap<String, u128>, key: &str) -> Result<u128> {
    numbers
        .get(key)
        .copied()
        .ok_or_else(|| CoreError::Checkpoint(format!("the saved state has no {key}")))
}

/// An algorithm's [`Entry::check`] with nothing of its own to refuse.
pub(crate) fn no_checks(_: &RunConfig) -> Result<()> {
    Ok(())
}

/// The refusal of `--vtrace` by an algorithm it does not correct, and `why`.
pub(crate) fn refuse_vtrace(config: &RunConfig, why: &str) -> Result<()> {
    if !config.vtrace {
        return Ok(());
    }
    Err(CoreError::Config(format!(
        "vtrace: V-trace corrects A2C and SAVER; {} {why}",
        config.algo.name()
    )))
}

/// FLOPs of the dense layers `dims` (in, hidden..., out) on `rows` rows, forward only.
pub fn mlp_flops(rows: usize, dims: &[usize]) -> f64 {
    dims.windows(2)
        .map(|w| 2.0 * (rows * w[0] * w[1]) as f64)
        .sum()
}

/// FLOPs of a PCPN-shaped quantile net's forward on `b` rows of `input` entries with
/// K = `k` quantiles for each of its `n` outputs: (the dense layers, the cosine
/// embedding's product with the chunks, one multiply per row and feature). SAVER's
/// frozen PCPN, QRRL's quantile policy and pretraining weigh them differently.
pub fn quantile_net_flops(b: usize, k: usize, input: usize, n: usize) -> (f64, f64) {
    use crate::nets::{PCPN_CHUNK, PCPN_HEAD_HIDDEN, PCPN_HIDDEN};
    let shared = mlp_flops(b, &[input, PCPN_HIDDEN, n * PCPN_CHUNK]);
    let heads = n as f64 * mlp_flops(b * k, &[PCPN_CHUNK, PCPN_HEAD_HIDDEN, 1]);
    (shared + heads, (b * k * n * PCPN_CHUNK) as f64)
}

/// The Gaussian MLP policy with the run's head (A2C and SAVER act with it).
pub(crate) fn gaussian_policy(config: &RunConfig) -> Arc<dyn PolicyFamily> {
    Arc::new(Gaussian {
        layout: config.env.layout(),
        head: config.head,
    })
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
fn timeout_ends(
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

/// What every return recursion reads from V at [`update_rows`]' rows (`values`,
/// [rows] or [rows, c]) besides the steps' own values: each trajectory's bootstrap
/// V(o_n) ([T, c]) and the `ends` of [`crate::returns::n_step_returns`] (`n_ends`
/// timeouts).
pub(crate) fn bootstrap_and_ends(
    batch: &crate::rollout::Batch,
    values: &Tensor,
    n_ends: usize,
    c: usize,
) -> Result<(Vec<f32>, Option<Vec<f32>>)> {
    let bootstrap = values
        .narrow(0, batch.len(), batch.n_traj)?
        .flatten_all()?
        .to_vec1::<f32>()?;
    Ok((bootstrap, timeout_ends(batch, values, n_ends, c)?))
}

/// The n-step returns of `rewards` ([B, c]: the summed reward with c = 1, the vector
/// reward with c = d) for every algorithm, bootstrapped from `values`: V at
/// [`update_rows`]' rows ([rows] or [rows, c]); `n_ends` timeouts at their end.
pub(crate) fn batch_returns(
    batch: &crate::rollout::Batch,
    rewards: &[f32],
    values: &Tensor,
    n_ends: usize,
    c: usize,
    gamma: f32,
) -> Result<Vec<f32>> {
    let (bootstrap, ends) = bootstrap_and_ends(batch, values, n_ends, c)?;
    Ok(crate::returns::n_step_returns(
        rewards,
        &batch.done,
        &bootstrap,
        ends.as_deref(),
        batch.n_steps,
        c,
        gamma,
    ))
}

/// GAE(λ) advantages of `rewards` ([B, c]) and the critic's targets A + V, for PPO and
/// SAVER's `saver.gae_lambda`: `values` is V(o_t) of the B steps on the host ([B, c]),
/// `v_all` V at [`update_rows`]' rows ([rows] or [rows, c]; `n_ends` timeouts at their
/// end).
pub(crate) fn batch_gae(
    batch: &crate::rollout::Batch,
    rewards: &[f32],
    values: &[f32],
    v_all: &Tensor,
    n_ends: usize,
    gamma: f32,
    lambda: f32,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let c = rewards.len() / batch.len().max(1);
    let (bootstrap, ends) = bootstrap_and_ends(batch, v_all, n_ends, c)?;
    let adv = crate::returns::gae(
        rewards,
        values,
        &batch.done,
        &bootstrap,
        ends.as_deref(),
        batch.n_steps,
        c,
        gamma,
        lambda,
    );
    let returns = adv.iter().zip(values).map(|(a, v)| a + v).collect();
    Ok((adv, returns))
}

/// The advantages and critic targets of `rewards` ([B, c]) by λ: GAE(λ) below 1, and
/// at λ = 1 the n-step recursion itself (GAE(1) is the same sum in another order,
/// equal only to rounding), A = R − V; `values` V(o_t) of the B steps on the host,
/// `v_all` V at [`update_rows`]' rows (`n_ends` timeouts at their end).
pub(crate) fn lambda_targets(
    batch: &crate::rollout::Batch,
    rewards: &[f32],
    values: &[f32],
    v_all: &Tensor,
    n_ends: usize,
    gamma: f32,
    lambda: f32,
) -> Result<(Vec<f32>, Vec<f32>)> {
    if lambda < 1.0 {
        return batch_gae(batch, rewards, values, v_all, n_ends, gamma, lambda);
    }
    let c = rewards.len() / batch.len().max(1);
    let r = batch_returns(batch, rewards, v_all, n_ends, c, gamma)?;
    let adv = r.iter().zip(values).map(|(r, v)| r - v).collect();
    Ok((adv, r))
}

/// The rows `idx` of `data` ([rows, w], row-major), in that order: a minibatch's.
pub(crate) fn gather_rows(data: &[f32], idx: &[usize], w: usize) -> Vec<f32> {
    idx.iter()
        .flat_map(|&i| data[i * w..(i + 1) * w].iter().copied())
        .collect()
}

/// The width of a step's payload under the Gaussian behaviour policy that acted (its μ
/// then its log σ), once the batch is checked to hold exactly that a step.
pub(crate) fn behaviour_payload_width(
    layout: &crate::env::EnvLayout,
    batch: &Batch,
) -> Result<usize> {
    let (b, width) = (batch.len(), layout.mu_dim() + layout.log_std_dim());
    if batch.payload.len() != b * width {
        return Err(CoreError::Data(format!(
            "the Gaussian behaviour policy's payload is μ then log σ, {width} values a step; \
             the batch has {} values for {b} steps",
            batch.payload.len()
        )));
    }
    Ok(width)
}

/// log μ(a|o) of every step under the Gaussian behaviour policy that acted, from the
/// (μ, log σ) its actor recorded in the payload (PPO's π_old, V-trace's μ).
pub(crate) fn behaviour_log_probs(
    layout: &crate::env::EnvLayout,
    batch: &Batch,
    dev: &Device,
) -> Result<Vec<f32>> {
    let b = batch.len();
    let (m, s) = (layout.mu_dim(), layout.log_std_dim());
    let width = behaviour_payload_width(layout, batch)?;
    let payload = Tensor::from_slice(&batch.payload, (b, width), dev)?;
    let actions = Tensor::from_slice(&batch.actions, (b, layout.action_dim()), dev)?;
    let logp = crate::nets::gaussian_log_prob(
        layout,
        &payload.narrow(1, 0, m)?,
        &payload.narrow(1, m, s)?,
        &actions,
    )?;
    Ok(logp.to_vec1::<f32>()?)
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

/// The optimiser a run's config asks for over `vars`: its kind, learning rate,
/// gradient clip and, with `lr_decay`, a rate that falls linearly to zero over the
/// run's updates, of `steps_per_update` optimiser steps each (beside the registry, so
/// that optim.rs knows no config).
pub(crate) fn run_optimizer(
    vars: Vec<(String, candle_core::Var)>,
    config: &RunConfig,
    steps_per_update: u64,
) -> Result<crate::optim::Optimizer> {
    let opt = crate::optim::Optimizer::with_clip(
        vars,
        config.optimizer.tf1(),
        config.lr,
        config.grad_clip,
    )?;
    Ok(if config.lr_decay {
        opt.decaying_over(config.steps.div_ceil(config.batch_transitions()) * steps_per_update)
    } else {
        opt
    })
}

/// τ [d, B, K] and its cosine embedding [d, B, K, 128] as tensors.
pub fn tau_tensors(
    taus: &[f32],
    d: usize,
    b: usize,
    k: usize,
    dev: &Device,
) -> Result<(Tensor, Tensor)> {
    let cos = cosine_embedding(taus, EMBED_DIM);
    Ok((
        Tensor::from_slice(taus, (d, b, k), dev)?,
        Tensor::from_vec(cos, (d, b, k, EMBED_DIM), dev)?,
    ))
}
