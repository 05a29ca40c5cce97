//! SAVER (paper Section 4; docs/ALGORITHM.md §7): the agent is trained through the frozen PCPN with the QRRL
//! loss on vector advantages; a separate vector critic learns V(o, μ, log σ) ∈ R^d.
//!
//! L_a   = mean_{B·K·d} ρ_τ(Δp − PCPN(x, τ)) · Â_j        (agent only, via μ, log σ)
//! L_mon = λ_mon · 2K · mean_{B·K·K·d} Huber_1(relu(Q(τ_i) − Q(τ_k)))·1{τ_i<τ_k}
//! L_c   = λ_c · mean_{B·d} (V(x) − R)²                     (critic only)

pub(super) mod defaults;
mod env_return;
mod epochs;
pub(super) mod grad;
mod host_step;
mod obs_scale;
mod pcpn_tune;
pub mod signal;
mod stats;
mod step;
mod targets;

use crate::algo::{update_rows, Algorithm, GradPath, UpdateStats};
use crate::config::{DeltaTarget, RunConfig, SaverConfig};
use crate::env::{EnvLayout, Routing};
use crate::nets::{Agent, Critic, Pcpn};
use crate::optim::Optimizer;
use crate::returns::normalize_advantages;
use crate::rng::{rng_for, streams, uniform01, SaverRng};
use crate::rollout::Batch;
use crate::{checkpoint, Result};
use candle_core::{Device, Tensor};
use env_return::{EnvReturn, EnvRows, EnvTargets};
use grad::{host, PcpnGrad};
use obs_scale::ObsScale;
use pcpn_tune::PcpnTuner;
use saver_proto::NamedTensor;
use signal::{noise_rank_delta, predicted_delta, SignalBatch};
use std::borrow::Cow;
#[cfg(test)]
pub(super) use step::mu_raw_penalty;
use step::{Losses, StepRows};
use targets::Targets;

/// The update's statistics, and last the PCPN's loss on the batch when it keeps
/// learning ([`STATS`] without it).
const STATS_TUNED: &[&str] = &[
    "actor_loss",
    "mon_loss",
    "critic_loss",
    "mu_abs_max",
    "log_std_mean",
    "grad_norm",
    "pcpn_tune_loss",
];

/// The update's statistics with the PCPN frozen.
const STATS: &[&str] = STATS_TUNED.split_at(STATS_TUNED.len() - 1).0;

/// The env-return term's statistics, when the run has it (0 on a batch it skips).
const ENV_STATS: &[&str] = &["env_pg_loss", "env_pg_scale", "env_critic_loss"];

/// The SAVER learner state.
pub struct Saver {
    /// The agent (no value head).
    agent: Agent,
    /// The vector critic.
    critic: Critic,
    /// The frozen PCPN (plain tensors: no gradient ever reaches its weights), with the
    /// transposed weights of the hand-written backward pass.
    pcpn: PcpnGrad,
    /// Which agent-gradient implementation runs.
    path: GradPath,
    /// One optimiser over agent and critic variables.
    opt: Optimizer,
    /// The τ stream.
    rng: SaverRng,
    /// Env layout.
    layout: EnvLayout,
    /// Which part of an action moves which coordinate (per-coordinate V-trace).
    routing: Routing,
    /// γ.
    gamma: f32,
    /// Bootstrap at the step limit.
    bootstrap_timeout: bool,
    /// Loss constants.
    cfg: SaverConfig,
    /// The tanh bound of μ, if any (for the saturation diagnostic).
    mu_bound: Option<f64>,
    /// Device.
    dev: Device,
    /// The last rank statistics (saver/signal.rs).
    ranks: Vec<(&'static str, Vec<f32>)>,
    /// The PCPN's own training on the policy's steps (`saver.pcpn_tune_lr` > 0).
    tuner: Option<PcpnTuner>,
    /// Off-policy correction, when the run asks for it.
    vtrace: Option<super::Vtrace>,
    /// The env-return term (`saver.env_reward` > 0; env_return.rs).
    env: Option<EnvReturn>,
    /// In a run that goes on past success, the success box: a step that starts inside
    /// it has no vector advantage (its progress is only noise around the goal).
    at_goal: Option<crate::env::SuccessRule>,
    /// `saver.obs_norm`: how the agent and critics see the observations (the PCPN reads
    /// them raw); published with the weights.
    obs_norm: Option<ObsScale>,
}

/// SAVER's registration ([`crate::algo::entry`]).
pub(crate) const ENTRY: crate::algo::Entry = crate::algo::Entry {
    build: build_saver,
    policy: crate::algo::gaussian_policy,
    recommend: defaults::recommend,
    check: crate::algo::no_checks,
    flops: defaults::flops,
};

fn build_saver(config: &RunConfig, pcpn: Option<Pcpn>, dev: &Device) -> Result<Box<dyn Algorithm>> {
    let pcpn =
        pcpn.ok_or_else(|| crate::CoreError::Config("algo saver needs a pretrained PCPN".into()))?;
    Ok(Box::new(Saver::new(config, pcpn, dev)?))
}

impl Saver {
    /// A fresh agent and critic initialised from the run seed, around a frozen PCPN.
    pub fn new(config: &RunConfig, pcpn: Pcpn, dev: &Device) -> Result<Self> {
        let layout = config.env.layout();
        let mut rng = rng_for(config.seed, streams::INIT);
        let agent = Agent::new(&layout, config.head, &config.hidden, false, &mut rng, dev)?;
        let critic = Critic::new(&layout, &config.hidden, &mut rng, dev)?;
        let env = EnvReturn::of(config, &layout, &mut rng, dev)?;
        let mut vars = agent.params().vars.clone();
        vars.extend(critic.params().vars.clone());
        if let Some(e) = &env {
            vars.extend(e.params().vars.clone());
        }
        let batch = config.batch_transitions() as usize;
        let per_update = (config.saver.epochs * config.saver.minibatches(batch)) as u64;
        let opt = super::run_optimizer(vars, config, per_update)?;
        let tuner = (config.saver.pcpn_tune_lr > 0.0)
            .then(|| PcpnTuner::new(&pcpn, config.optimizer, config.saver.pcpn_tune_lr))
            .transpose()?;
        Ok(Self {
            agent,
            critic,
            pcpn: PcpnGrad::new(pcpn)?,
            path: GradPath::for_device(dev),
            opt,
            rng: rng_for(config.seed, streams::LEARNER),
            layout,
            routing: config.env.routing(),
            gamma: config.gamma as f32,
            bootstrap_timeout: config.bootstrap_timeout,
            cfg: config.saver.clone(),
            mu_bound: config.head.mu_bound,
            dev: dev.clone(),
            ranks: Vec::new(),
            tuner,
            vtrace: super::Vtrace::of(config).map(|v| super::Vtrace {
                lambda: config.saver.gae_lambda as f32,
                ..v
            }),
            env,
            at_goal: config
                .continue_past_success
                .then(|| config.env.success_rule())
                .flatten(),
            obs_norm: ObsScale::of(config.saver.obs_norm, &config.env),
        })
    }

    /// The frozen PCPN.
    pub fn pcpn(&self) -> &Pcpn {
        self.pcpn.pcpn()
    }
}

/// The networks a checkpoint holds: agent, vector critic and, with the env-return term,
/// its critic (fields apart, so that restoring may borrow the optimiser mutably).
fn nets<'a>(
    agent: &'a Agent,
    critic: &'a Critic,
    env: Option<&'a EnvReturn>,
) -> Vec<&'a crate::nets::ParamSet> {
    let mut nets = vec![agent.params(), critic.params()];
    nets.extend(env.map(EnvReturn::params));
    nets
}

/// Agent and critic over some rows, in the graph.
struct Forward {
    /// [N, o]: the rows' observations.
    obs: Tensor,
    /// [N, ·]: μ, its value before the bound, and log σ.
    mu: Tensor,
    raw: Tensor,
    log_std: Tensor,
    /// [N, o + M + L]: the PCPN's input [o, μ, log σ] as constants.
    x: Tensor,
    /// The critics' input: `x` with the observations as the agent reads them
    /// (normalised with `saver.obs_norm`, else `x` itself).
    xc: Tensor,
    /// [N, d]: V(x).
    value: Tensor,
}

impl Forward {
    /// The first `n` rows.
    fn narrow(&self, n: usize) -> Result<Self> {
        let first = |t: &Tensor| t.narrow(0, 0, n);
        Ok(Self {
            obs: first(&self.obs)?,
            mu: first(&self.mu)?,
            raw: first(&self.raw)?,
            log_std: first(&self.log_std)?,
            x: first(&self.x)?,
            xc: first(&self.xc)?,
            value: first(&self.value)?,
        })
    }
}

/// A batch's quantities at its update's start.
struct Start<'a> {
    /// Agent and critic over the B steps.
    fwd: Forward,
    /// [B, d]: the critic's targets R, V(x) on the host, the advantages as trained on
    /// (normalised with `saver.adv_norm`).
    returns_host: Vec<f32>,
    value_host: Vec<f32>,
    adv_host: Vec<f32>,
    /// [B, d]: the actor loss's Δp (`saver.target`).
    target: Cow<'a, [f32]>,
    /// μ and log σ of the steps on the host.
    mu_host: Vec<f32>,
    log_std_host: Vec<f32>,
    /// V-trace's statistics, when it runs.
    vtrace_stats: Vec<(&'static str, f32)>,
    /// The env-return term's targets, when it learns from this batch.
    env: Option<EnvTargets>,
}

impl Saver {
    /// Agent and critic over the observations `obs`.
    fn forward(&self, obs: Tensor) -> Result<Forward> {
        let seen = match &self.obs_norm {
            Some(s) => Some(s.normalize(&obs)?),
            None => None,
        };
        let out = self.agent.forward(seen.as_ref().unwrap_or(&obs))?;
        // The critic sees the policy's outputs as constants: its loss trains it alone.
        let with_policy = |o: &Tensor| -> Result<Tensor> {
            Ok(Tensor::cat(&[o, &out.mu, &out.log_std], 1)?.detach())
        };
        let x = with_policy(&obs)?;
        let xc = match &seen {
            Some(o) => with_policy(o)?,
            None => x.clone(),
        };
        let value = self.critic.forward(&xc)?;
        Ok(Forward {
            obs,
            mu: out.mu,
            raw: out.mu_raw,
            log_std: out.log_std,
            x,
            xc,
            value,
        })
    }

    /// The critic's targets, the advantages and the actor loss's Δp of `batch`, from
    /// one forward of agent and critic over its rows and bootstrap rows.
    fn start<'a>(&self, batch: &'a Batch) -> Result<Start<'a>> {
        let (b, o, d) = (batch.len(), self.layout.obs_dim, self.layout.aligned_dim);
        let (obs_all, n_ends) = update_rows(batch, self.bootstrap_timeout, o, &self.dev)?;
        let all = self.forward(obs_all)?;
        let v_all = &all.value; // [B+T, d]
        let env = match &self.env {
            Some(e) if EnvReturn::applies(batch) => {
                let lambda = self.cfg.env_gae_lambda as f32;
                Some(e.targets(batch, &e.value(&all.xc)?, n_ends, self.gamma, lambda)?)
            }
            _ => None,
        };
        let fwd = all.narrow(b)?;
        let value_host: Vec<f32> = fwd.value.flatten_all()?.to_vec1()?;
        let (mu_host, log_std_host) = (host(&fwd.mu)?, host(&fwd.log_std)?);
        let Targets {
            returns: returns_host,
            advantages: mut adv_host,
            vtrace_stats,
        } = self.targets(
            batch,
            &fwd,
            (&mu_host, &log_std_host),
            v_all,
            &value_host,
            n_ends,
        )?;
        if self.cfg.adv_norm {
            normalize_advantages(&mut adv_host, d, self.cfg.adv_norm_joint);
        }
        // Past success, a step at the goal learns only from the env's reward: its
        // progress is noise around the goal. Where the env term does not run on this
        // batch (no env reward, or one equal to the progress) the progress is all there
        // is, and it stays.
        if let (Some(rule), Some(_)) = (&self.at_goal, &env) {
            let (o, a0) = (self.layout.obs_dim, self.layout.aligned_start);
            for (row, adv) in batch.obs.chunks_exact(o).zip(adv_host.chunks_exact_mut(d)) {
                if rule.distance(row, &row[a0..a0 + d]) < rule.radius {
                    adv.fill(0.0);
                }
            }
        }
        let target = match self.cfg.target {
            DeltaTarget::Observed => Cow::Borrowed(batch.state_delta.as_slice()),
            target => {
                let signal = SignalBatch::of(batch, &mu_host, &log_std_host, &adv_host, None);
                let make = match target {
                    DeltaTarget::Predicted => predicted_delta,
                    _ => noise_rank_delta,
                };
                Cow::Owned(make(self.pcpn.pcpn(), &self.layout, &signal, &self.dev)?)
            }
        };
        Ok(Start {
            fwd,
            returns_host,
            value_host,
            adv_host,
            target,
            mu_host,
            log_std_host,
            vtrace_stats,
            env,
        })
    }

    /// The PCPN's loss and gradient on the batch's steps (inputs `x`), when it learns.
    fn tune_grads(
        &mut self,
        x: &Tensor,
        batch: &Batch,
    ) -> Result<Option<(f32, candle_core::backprop::GradStore)>> {
        let Some(t) = &self.tuner else {
            return Ok(None);
        };
        let (b, d, k) = (batch.len(), self.layout.aligned_dim, self.cfg.quantiles);
        let rows = self.cfg.pcpn_tune_rows;
        if rows == 0 || rows >= b {
            let taus = uniform01(&mut self.rng, d * b * k);
            return Ok(Some(t.grads(x, &batch.state_delta, &taus)?));
        }
        // `rows` distinct rows, in batch order.
        let mut idx = rand::seq::index::sample(&mut self.rng, b, rows).into_vec();
        idx.sort_unstable();
        let at: Vec<u32> = idx.iter().map(|&i| i as u32).collect();
        let x = x.index_select(&Tensor::from_vec(at, rows, &self.dev)?, 0)?;
        let delta = crate::algo::gather_rows(&batch.state_delta, &idx, d);
        let taus = uniform01(&mut self.rng, d * rows * k);
        Ok(Some(t.grads(&x, &delta, &taus)?))
    }

    /// Applies the PCPN's step; its loss.
    fn apply_tune(
        &mut self,
        tune: Option<(f32, candle_core::backprop::GradStore)>,
    ) -> Result<Option<f32>> {
        match (&mut self.tuner, tune) {
            (Some(t), Some((l, g))) => {
                t.apply(&g)?;
                self.pcpn = self.pcpn.refreshed(t.frozen()?)?;
                Ok(Some(l))
            }
            _ => Ok(None),
        }
    }

    /// The paper's update: one optimiser step on the whole batch.
    fn update_one_step(&mut self, batch: &Batch) -> Result<UpdateStats> {
        let s = self.start(batch)?;
        let (b, d) = (batch.len(), self.layout.aligned_dim);
        let behaviour = self.behaviour(batch, &s)?;
        let rows = StepRows {
            fwd: &s.fwd,
            returns: Tensor::from_slice(&s.returns_host, (b, d), &self.dev)?,
            target: &s.target,
            adv: &s.adv_host,
            env: self.env_rows(&s, batch, None, behaviour.as_deref())?,
        };
        let step = self.step_loss(&rows)?;
        // The PCPN's step on this batch, computed before anything changes.
        let tune = self.tune_grads(&s.fwd.x, batch)?;
        let (losses, dmu) = self.take_step(step)?;
        let tune_loss = self.apply_tune(tune)?;
        self.finish(batch, s, dmu, losses, tune_loss)
    }

    /// The batch's log μ(a|o) under the policy that acted, where this update needs it:
    /// for the KL stop of `saver.target_kl` where the update makes several steps, or for
    /// the env term's clip where that term learns from the batch.
    fn behaviour(&self, batch: &Batch, s: &Start) -> Result<Option<Vec<f32>>> {
        let clip = s.env.is_some() && self.env.as_ref().is_some_and(EnvReturn::clips);
        let kl_stop = self.cfg.target_kl > 0.0 && !self.cfg.one_step(batch.len());
        (clip || kl_stop)
            .then(|| super::behaviour_log_probs(&self.layout, batch, &self.dev))
            .transpose()
    }

    /// The env term's rows `idx` (all with `None`) of the batch, where it learns from it.
    fn env_rows(
        &self,
        s: &Start,
        batch: &Batch,
        idx: Option<&[usize]>,
        behaviour: Option<&[f32]>,
    ) -> Result<Option<EnvRows>> {
        let a = self.layout.action_dim();
        match (&self.env, &s.env) {
            (Some(term), Some(t)) => Ok(Some(term.rows(t, batch, idx, behaviour, a, &self.dev)?)),
            _ => Ok(None),
        }
    }
}

impl Algorithm for Saver {
    fn set_grad_path(&mut self, path: GradPath) {
        self.path = path;
    }

    fn stat_names(&self) -> Vec<&'static str> {
        let mut names = if self.tuner.is_some() {
            STATS_TUNED.to_vec()
        } else {
            STATS.to_vec()
        };
        if self.vtrace.is_some() {
            names.extend(super::VTRACE_STATS);
        }
        if self.env.is_some() {
            names.extend(ENV_STATS);
        }
        names
    }

    fn update(&mut self, batch: &Batch) -> Result<UpdateStats> {
        let stats = if self.cfg.one_step(batch.len()) {
            self.update_one_step(batch)?
        } else {
            self.update_epochs(batch)?
        };
        // With `saver.obs_norm` the update read the statistics the actors acted with;
        // the batch joins them for the weights published next.
        if let Some(s) = &mut self.obs_norm {
            s.learn(&batch.obs);
        }
        Ok(stats)
    }

    fn policy_tensors(&self) -> Result<Vec<NamedTensor>> {
        let mut t = checkpoint::to_named_all(&self.agent.params().tensors()?)?;
        t.extend(
            self.obs_norm
                .as_ref()
                .map(|s| s.weights())
                .unwrap_or_default(),
        );
        Ok(t)
    }

    fn optimizer_steps(&self) -> u64 {
        self.opt.steps()
    }

    fn set_threads(&mut self, n: usize) {
        self.pcpn.set_threads(n);
        if let Some(t) = &mut self.tuner {
            t.set_threads(n);
        }
    }

    fn save_state(&self) -> Result<super::AlgoState> {
        let nets = nets(&self.agent, &self.critic, self.env.as_ref());
        let mut state = super::nets_state(&nets, &self.opt, Some(&self.rng))?;
        if let Some(t) = &self.tuner {
            t.save(&mut state)?;
        }
        if let Some(e) = &self.env {
            state.tensors.push(e.state(&self.dev)?);
        }
        if let Some(s) = &self.obs_norm {
            state.tensors.extend(s.state()?);
        }
        Ok(state)
    }

    fn restore_state(
        &mut self,
        get: &dyn Fn(&str) -> Option<Tensor>,
        numbers: &std::collections::BTreeMap<String, u128>,
    ) -> Result<()> {
        let nets = nets(&self.agent, &self.critic, self.env.as_ref());
        super::restore_nets(&nets, &mut self.opt, Some(&mut self.rng), get, numbers)?;
        if let Some(e) = &self.env {
            e.restore(get)?;
        }
        if let Some(s) = &mut self.obs_norm {
            s.restore(get)?;
        }
        if let Some(t) = &mut self.tuner {
            t.restore(get, numbers)?;
            self.pcpn = self.pcpn.refreshed(t.frozen()?)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod obs_norm_tests;
#[cfg(test)]
mod signal_tests;
