//! One optimiser step of SAVER's update: the critic's loss, the actor loss and monotonic
//! penalty through the frozen PCPN (fast path or autograd reference), and the saturation wall.

use super::env_return::{EnvReturn, EnvRows};
use super::grad::{policy_grads, saver_actor_losses, surrogate, OutputLeaves};
use super::{Forward, Saver};
use crate::algo::{check_finite, matrix};
use crate::algo::{tau_tensors, GradPath};
use crate::config::MU_RAW_LIMIT;
use crate::rng::uniform01;
use crate::Result;
use candle_core::Tensor;

/// `w · Σ_j mean_b relu(|raw_bj| − MU_RAW_LIMIT)²` over raw means [B, mu_dim], the sum
/// over `entries` only unless empty: a wall that keeps a tanh-bounded mean where tanh
/// still passes gradient back.
pub fn mu_raw_penalty(raw: &Tensor, w: f64, entries: &[usize]) -> Result<Tensor> {
    let raw = if entries.is_empty() {
        raw.clone()
    } else {
        let idx: Vec<u32> = entries.iter().map(|&e| e as u32).collect();
        raw.index_select(&Tensor::new(idx.as_slice(), raw.device())?, 1)?
    };
    let over = (raw.abs()? - MU_RAW_LIMIT)?.relu()?;
    Ok((over.sqr()?.sum_all()? * (w / raw.dim(0)? as f64))?)
}

/// What one optimiser step trains on: some rows' forward, critic targets [N, d], Δp
/// targets and advantages.
pub(super) struct StepRows<'a> {
    pub(super) fwd: &'a Forward,
    pub(super) returns: Tensor,
    pub(super) target: &'a [f32],
    pub(super) adv: &'a [f32],
    /// The env-return term's rows, when it learns from this batch.
    pub(super) env: Option<EnvRows>,
}

/// The agent's loss on some rows: L_a and L_mon, the tensor whose gradient trains the
/// agent, (fast path) dL/dμ per row, and when asked d(L_a + L_mon)/d(μ, log σ).
struct AgentLoss {
    actor: f32,
    mon: f32,
    loss: Tensor,
    dmu: Option<Vec<f32>>,
    grads: Option<(Tensor, Tensor)>,
}

/// One optimiser step's loss, checked and not yet applied.
pub(super) struct StepLoss {
    loss: Tensor,
    losses: Losses,
    dmu: Option<Vec<f32>>,
}

/// An update's losses as reported (the mean over its optimiser steps).
#[derive(Clone, Copy, Default)]
pub(super) struct Losses {
    pub(super) actor: f32,
    pub(super) mon: f32,
    pub(super) critic: f32,
    pub(super) grad_norm: f32,
    /// The env-return term's unit L_r, its scale c and L_V_r (0 where it does not run).
    pub(super) env_pg: f32,
    pub(super) env_scale: f32,
    pub(super) env_critic: f32,
}

impl Losses {
    /// The mean of several steps' losses (summed in f64).
    pub(super) fn mean(all: &[Losses]) -> Self {
        let mean = |f: fn(&Losses) -> f32| {
            (all.iter().map(|l| f(l) as f64).sum::<f64>() / all.len().max(1) as f64) as f32
        };
        Self {
            actor: mean(|l| l.actor),
            mon: mean(|l| l.mon),
            critic: mean(|l| l.critic),
            grad_norm: mean(|l| l.grad_norm),
            env_pg: mean(|l| l.env_pg),
            env_scale: mean(|l| l.env_scale),
            env_critic: mean(|l| l.env_critic),
        }
    }
}

impl Saver {
    /// The loss of one optimiser step on `rows`: the critic's loss, SAVER's actor loss
    /// and monotonic penalty and the saturation wall, checked before any step (a
    /// non-finite one changes nothing).
    pub(super) fn step_loss(&mut self, rows: &StepRows) -> Result<StepLoss> {
        let f = rows.fwd;
        let (n, d, k) = (f.obs.dim(0)?, self.layout.aligned_dim, self.cfg.quantiles);
        let critic_loss =
            ((&f.value - &rows.returns)?.sqr()?.mean_all()? * self.cfg.lambda_critic)?;
        let taus = uniform01(&mut self.rng, d * n * k);
        let env = self.env.as_ref().zip(rows.env.as_ref());
        let a = self.agent_loss(rows, &taus, env.is_some())?;
        let (mut env_pg, mut env_scale, mut env_critic) = (0.0, 0.0, 0.0);
        let agent = match (env, &a.grads) {
            (Some((term, env_rows)), Some((g_mu, g_ls))) => {
                // The env term's push on μ and log σ, scaled to w times the PCPN's.
                let e = EnvReturn::policy_grads(&self.layout, &f.mu, &f.log_std, env_rows)?;
                let c = term.scale([g_mu, g_ls], [&e.plain.0, &e.plain.1])? as f64;
                let push = surrogate(&f.mu, &f.log_std, &(e.push.0 * c)?, &(e.push.1 * c)?)?;
                let v_r = term.critic_loss(&f.xc, env_rows, self.cfg.lambda_critic)?;
                env_pg = check_finite("env_pg_loss", e.loss)?;
                env_scale = check_finite("env_pg_scale", c as f32)?;
                env_critic = check_finite("env_critic_loss", v_r.to_scalar::<f32>()?)?;
                ((a.loss + push)? + v_r)?
            }
            _ => a.loss,
        };
        let loss = self.with_penalty((agent + &critic_loss)?, &f.raw)?;
        let losses = Losses {
            actor: check_finite("actor_loss", a.actor)?,
            mon: check_finite("mon_loss", a.mon)?,
            critic: check_finite("critic_loss", critic_loss.to_scalar::<f32>()?)?,
            grad_norm: 0.0,
            env_pg,
            env_scale,
            env_critic,
        };
        Ok(StepLoss {
            loss,
            losses,
            dmu: a.dmu,
        })
    }

    /// The optimiser step on a checked loss; its losses with the gradient norm, and
    /// (fast path) dL/dμ per row.
    pub(super) fn take_step(&mut self, s: StepLoss) -> Result<(Losses, Option<Vec<f32>>)> {
        let grads = s.loss.backward()?;
        let grad_norm = self.opt.step(&grads)? as f32;
        Ok((
            Losses {
                grad_norm,
                ..s.losses
            },
            s.dmu,
        ))
    }

    /// SAVER's actor loss and monotonic penalty on `rows` with τ `taus` [d·N·K]; with
    /// `want_grads` also their gradient with respect to μ and log σ (the reference path
    /// then trains through that gradient as the fast path does, the same step).
    fn agent_loss(&self, rows: &StepRows, taus: &[f32], want_grads: bool) -> Result<AgentLoss> {
        let f = rows.fwd;
        let (b, d, k) = (f.obs.dim(0)?, self.layout.aligned_dim, self.cfg.quantiles);
        match self.path {
            GradPath::Fast => {
                // dL/dμ and dL/dlog σ by hand, then the surrogate Σ μ·dμ + Σ log σ·dlog σ
                // carries them into the agent through autograd.
                let g = self
                    .pcpn
                    .input_grad(&f.x, rows.target, rows.adv, taus, &self.cfg)?;
                let (dmu, dls) = policy_grads(&g.dx, self.layout.obs_dim, self.layout.mu_dim())?;
                let dmu_host = dmu.flatten_all()?.to_vec1::<f32>()?;
                let loss = surrogate(&f.mu, &f.log_std, &dmu, &dls)?;
                Ok(AgentLoss {
                    actor: g.actor_loss,
                    mon: g.mon_loss,
                    loss,
                    dmu: Some(dmu_host),
                    grads: want_grads.then_some((dmu, dls)),
                })
            }
            GradPath::Reference => {
                let (tau, cos) = tau_tensors(taus, d, b, k, &self.dev)?;
                // With `want_grads` the losses run on detached copies of μ and log σ,
                // and their gradient there carries them into the agent.
                let leaves = want_grads
                    .then(|| OutputLeaves::of(&f.mu, &f.log_std))
                    .transpose()?;
                let (mu, log_std) = match &leaves {
                    Some(at) => (at.mu.as_tensor(), at.log_std.as_tensor()),
                    None => (&f.mu, &f.log_std),
                };
                let l = saver_actor_losses(
                    self.pcpn.pcpn(),
                    &f.obs,
                    mu,
                    log_std,
                    &matrix(rows.target, b, d, &self.dev)?,
                    &Tensor::from_slice(rows.adv, (b, d), &self.dev)?,
                    &tau,
                    &cos,
                    &self.cfg,
                )?;
                let (actor, mon) = (l.actor.to_scalar::<f32>()?, l.mon.to_scalar::<f32>()?);
                let total = (l.actor + l.mon)?;
                let Some(at) = leaves else {
                    return Ok(AgentLoss {
                        actor,
                        mon,
                        loss: total,
                        dmu: None,
                        grads: None,
                    });
                };
                let (g_mu, g_ls) = at.grads(&total)?;
                let loss = surrogate(&f.mu, &f.log_std, &g_mu, &g_ls)?;
                Ok(AgentLoss {
                    actor,
                    mon,
                    loss,
                    dmu: None,
                    grads: Some((g_mu, g_ls)),
                })
            }
        }
    }

    /// `loss` plus the saturation wall on the raw means `raw`, when it is on.
    fn with_penalty(&self, loss: Tensor, raw: &Tensor) -> Result<Tensor> {
        if self.cfg.mu_raw_penalty == 0.0 {
            return Ok(loss);
        }
        let (w, entries) = (self.cfg.mu_raw_penalty, &self.cfg.mu_raw_penalty_entries);
        Ok((loss + mu_raw_penalty(raw, w, entries)?)?)
    }
}
