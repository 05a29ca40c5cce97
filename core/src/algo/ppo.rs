//! PPO (Schulman et al. 2017; docs/ALGORITHM.md §15): per batch, GAE(λ) advantages from a
//! separate critic, then `epochs` passes of random minibatches of `minibatch_size`, each one
//! optimiser step on
//!
//!   L = −mean min(ρ·Â, clip(ρ, 1 − ε, 1 + ε)·Â) + c_v·mean (V − R)² − β·mean H(π),
//!
//! ρ = π(a|o)/π_old(a|o), π_old the behaviour policy the actor recorded (μ, log σ in the
//! rollout's payload), Â the minibatch's advantages (normalised with `ppo.adv_norm`),
//! R = A + V_old. With `ppo.value_clip` the squared error is the larger of the plain one
//! and the one of V_old + clip(V − V_old, ±clip). With `ppo.vector` the critic is
//! V(o) ∈ R^d on the vector reward, GAE runs per coordinate and Â is the sum over them.

use super::{
    batch_gae, check_finite, policy_diagnostics, update_rows, Algorithm, GradPath, UpdateStats,
};
use crate::config::{PpoConfig, RunConfig};
use crate::env::EnvLayout;
use crate::nets::{gaussian_log_prob, Agent, Critic};
use crate::optim::{HostState, Optimizer};
use crate::returns::normalize_advantages;
use crate::rng::{rng_for, streams, SaverRng};
use crate::rollout::Batch;
use crate::{checkpoint, Result};
use candle_core::backprop::GradStore;
use candle_core::{Device, Tensor};
use minibatch::{Minibatch, Totals};
use normalize::Normalizers;
use rand::seq::SliceRandom;
use saver_proto::NamedTensor;

const STATS: &[&str] = &[
    "policy_loss",
    "value_loss",
    "entropy",
    "approx_kl",
    "clip_fraction",
    "explained_variance",
    "mu_abs_max",
    "log_std_mean",
    "grad_norm",
];

/// The PPO learner state.
pub struct Ppo {
    /// The Gaussian agent (no value head).
    agent: Agent,
    /// V(o) ∈ R^c: c = 1, or d with `ppo.vector`.
    critic: Critic,
    /// One optimiser over agent and critic variables.
    opt: Optimizer,
    /// The minibatch shuffles.
    rng: SaverRng,
    /// Env layout.
    layout: EnvLayout,
    /// Critic outputs.
    c: usize,
    /// γ.
    gamma: f32,
    /// Value-loss weight.
    value_coef: f64,
    /// Bootstrap at the step limit.
    bootstrap_timeout: bool,
    /// PPO's constants.
    cfg: PpoConfig,
    /// Which gradient implementation runs.
    path: GradPath,
    /// Threads of the hand-written step (0: one per core): from 2 on, the critic's part
    /// of each minibatch runs beside the agent's, and the optimiser steps half of the
    /// variables on a second thread (the same bits).
    threads: usize,
    /// Device.
    dev: Device,
    /// The observation and reward normalisers (`ppo.obs_norm`, `ppo.reward_norm`) and
    /// the reward learnt from (normalize.rs).
    norm: Normalizers,
}

/// PPO's learning rate (Adam; Stable-Baselines3's).
pub const RECOMMENDED_PPO_LR: f64 = 3e-4;
/// PPO's rollout length on a custom env: Stable-Baselines3's `n_steps`, 2,048 steps per
/// env and update (on Reacher-v5, 8 envs, seed 0, 1 M steps: return -5.4 and success
/// 1.00 with it, against -19.2 and 0.34 with 128, whose 1,024-step batches let σ
/// collapse to the floor and each update's KL grow past 0.5; results/README.md, "PPO").
pub const RECOMMENDED_PPO_ROLLOUT: u32 = 2048;
/// PPO's rollout length on a preset: 16 actors make 2,048-step batches (angle d = 4,
/// seed 0, 1 M steps: mean length 11.8 with 128, 20.5 with 2,048, whose 32,768-step
/// batches give 31 updates in the run).
pub const PRESET_PPO_ROLLOUT: u32 = 128;
/// PPO's gradient-norm clip (Stable-Baselines3's `max_grad_norm`).
pub const RECOMMENDED_PPO_GRAD_CLIP: f64 = 0.5;
/// PPO's registration ([`super::entry`]).
pub(crate) const ENTRY: super::Entry = super::Entry {
    build: build_ppo,
    policy: super::gaussian_policy,
    recommend,
    check,
    flops,
};

/// Not in the paper: Stable-Baselines3's PPO settings, with the bounded head (μ = tanh,
/// log σ in [-4.6, 0]) and bootstrapped timeouts.
fn recommend(c: &mut RunConfig) {
    c.optimizer = crate::config::OptimizerKind::Adam;
    c.lr = RECOMMENDED_PPO_LR;
    c.rollout = match c.env.kind() {
        Some(_) => PRESET_PPO_ROLLOUT,
        None => RECOMMENDED_PPO_ROLLOUT,
    };
    c.grad_clip = Some(RECOMMENDED_PPO_GRAD_CLIP);
    c.head = crate::config::HeadConfig::IN_PCPN_DOMAIN;
    c.bootstrap_timeout = true;
}

/// Its surrogate already corrects for the acting policy.
fn check(c: &RunConfig) -> Result<()> {
    super::refuse_vtrace(
        c,
        "already weighs each step by π/π_old of the policy that acted",
    )
}

/// The critic's values on every row, then each epoch trains agent and critic on every
/// step once, then one agent forward for the diagnostics.
fn flops(config: &RunConfig, b: usize, t: usize) -> f64 {
    let l = config.env.layout();
    let h = &config.hidden;
    let agent = super::mlp_flops(b, &super::mlp_dims(l.obs_dim, h, l.mu_dim()));
    let critic_dims = super::mlp_dims(l.obs_dim, h, config.ppo.critic_values(&l));
    let critic = |n| super::mlp_flops(n, &critic_dims);
    critic(b + t) + config.ppo.epochs as f64 * 3.0 * (agent + critic(b)) + agent
}

fn build_ppo(
    config: &RunConfig,
    _pcpn: Option<crate::nets::Pcpn>,
    dev: &Device,
) -> Result<Box<dyn Algorithm>> {
    Ok(Box::new(Ppo::new(config, dev)?))
}

impl Ppo {
    /// A fresh agent and critic initialised from the run seed.
    pub fn new(config: &RunConfig, dev: &Device) -> Result<Self> {
        let layout = config.env.layout();
        let mut rng = rng_for(config.seed, streams::INIT);
        let agent = Agent::new(&layout, config.head, &config.hidden, false, &mut rng, dev)?;
        let c = config.ppo.critic_values(&layout);
        let critic = Critic::with_sizes(layout.obs_dim, c, &config.hidden, &mut rng, dev)?;
        let mut vars = agent.params().vars.clone();
        vars.extend(critic.params().vars.clone());
        let batch = config.batch_transitions() as usize;
        let per_update = (config.ppo.epochs * config.ppo.minibatches(batch)) as u64;
        let opt = super::run_optimizer(vars, config, per_update)?;
        Ok(Self {
            agent,
            critic,
            opt,
            rng: rng_for(config.seed, streams::LEARNER),
            layout,
            c,
            gamma: config.gamma as f32,
            value_coef: config.value_coef,
            bootstrap_timeout: config.bootstrap_timeout,
            cfg: config.ppo.clone(),
            path: GradPath::for_device(dev),
            threads: 0,
            dev: dev.clone(),
            norm: Normalizers::new(&config.ppo, layout.obs_dim, config.gamma),
        })
    }

    /// The per-step advantages (summed over the critic's outputs), the returns
    /// R = A + V_old ([B, c]) and V_old ([B, c]).
    fn advantages(&mut self, batch: &Batch) -> Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
        let (b, c) = (batch.len(), self.c);
        let (rows, k) = update_rows(
            batch,
            self.bootstrap_timeout,
            self.layout.obs_dim,
            &self.dev,
        )?;
        let v_all = self.critic.forward(&rows)?.detach(); // [B + T + k, c]
        let values = v_all.narrow(0, 0, b)?.flatten_all()?.to_vec1::<f32>()?;
        let rewards = self.norm.rewards(batch, c)?;
        let lambda = self.cfg.gae_lambda as f32;
        let (adv, returns) = batch_gae(batch, &rewards, &values, &v_all, k, self.gamma, lambda)?;
        let step_adv = adv.chunks_exact(c).map(|a| a.iter().sum()).collect();
        Ok((step_adv, returns, values))
    }

    /// Whether the minibatch steps are the hand-written ones (fast.rs), stepped by the
    /// optimiser on the host.
    fn fast(&self) -> bool {
        self.path == GradPath::Fast && self.layout.choices == 0
    }

    /// One minibatch's optimiser step; its losses are checked before the step. With
    /// `host` (the fast path) the step reads and changes the optimiser's host state.
    fn step(
        &mut self,
        mb: &Minibatch,
        host: Option<(&mut HostState, &mut fast::Scratch)>,
        parallel: bool,
        totals: &mut Totals,
    ) -> Result<()> {
        totals.grad_norm += match host {
            Some((h, scratch)) => {
                let nets = self.fast_nets();
                let grads = fast::step_grads(&nets, h, mb, parallel, totals, scratch)?;
                self.opt
                    .step_host_on(h, &grads, if parallel { 2 } else { 1 })?
            }
            None => {
                let grads = self.reference_grads(mb, totals)?;
                self.opt.step(&grads)?
            }
        };
        totals.steps += 1;
        Ok(())
    }

    /// The pool of the hand-written steps' threads when there are two or more; none
    /// (one thread, the same bits) on the reference path or when the OS refuses threads.
    fn step_pool(&self) -> Option<rayon::ThreadPool> {
        let threads = super::fused::threads_for(self.threads);
        if !self.fast() || threads < 2 {
            return None;
        }
        crate::optim::pool_of_two("PPO's")
    }

    /// The networks as the hand-written step takes them.
    fn fast_nets(&self) -> fast::Nets<'_> {
        fast::Nets {
            agent: self.agent.layers(),
            log_std: self.agent.log_std_var(),
            critic: self.critic.layers().iter().collect(),
            head: self.agent.head(),
            cfg: &self.cfg,
            value_coef: self.value_coef,
            c: self.c,
        }
    }

    /// The step's losses and gradients through candle's graph (the reference the fast
    /// path is tested against; the only path for layouts with a choice and off the CPU).
    fn reference_grads(&self, mb: &Minibatch, totals: &mut Totals) -> Result<GradStore> {
        let (n, c, dev) = (mb.n, self.c, &self.dev);
        let obs = Tensor::from_slice(&mb.obs, (n, self.layout.obs_dim), dev)?;
        let actions = Tensor::from_slice(&mb.actions, (n, self.layout.action_dim()), dev)?;
        let old_logp = Tensor::from_slice(&mb.old_logp, n, dev)?;
        let advantage = Tensor::from_slice(&mb.advantage, n, dev)?;
        let returns = Tensor::from_slice(&mb.returns, (n, c), dev)?;
        let out = self.agent.forward(&obs)?;
        let logp = gaussian_log_prob(&self.layout, &out.mu, &out.log_std, &actions)?;
        let log_ratio = (logp - &old_logp)?;
        let ratio = log_ratio.exp()?;
        let eps = self.cfg.clip;
        let unclipped = (&ratio * &advantage)?;
        let clipped = (ratio.clamp(1.0 - eps, 1.0 + eps)? * &advantage)?;
        let policy_loss = unclipped.minimum(&clipped)?.mean_all()?.neg()?;
        let v = self.critic.forward(&obs)?;
        let err = (&v - &returns)?.sqr()?;
        let err = match self.cfg.value_clip {
            Some(vc) => {
                let old_value = Tensor::from_slice(&mb.old_value, (n, c), dev)?;
                let moved = (&v - &old_value)?.clamp(-vc, vc)?;
                let clipped_err = ((&old_value + moved)? - &returns)?.sqr()?;
                err.maximum(&clipped_err)?
            }
            None => err,
        };
        let value_loss = err.mean_all()?;
        let entropy = self.entropy(&out.mu, &out.log_std)?;
        let loss = ((&policy_loss + (&value_loss * self.value_coef)?)?
            - (&entropy * self.cfg.entropy_coef)?)?;
        let pl = check_finite("policy_loss", policy_loss.to_scalar::<f32>()?)?;
        let vl = check_finite("value_loss", value_loss.to_scalar::<f32>()?)?;
        check_finite("loss", loss.to_scalar::<f32>()?)?;
        let grads = loss.backward()?;
        // Diagnostics (cleanrl's): KL(π_old‖π) ≈ mean((ρ − 1) − log ρ), and the share of
        // steps whose ratio the clip bounds.
        let kl = ((&ratio - 1.0)? - &log_ratio)?.mean_all()?;
        let outside = (ratio - 1.0)?
            .abs()?
            .gt(eps)?
            .to_dtype(candle_core::DType::F32)?;
        totals.policy_loss += pl as f64;
        totals.value_loss += vl as f64;
        totals.entropy += entropy.to_scalar::<f32>()? as f64;
        totals.approx_kl += kl.to_scalar::<f32>()? as f64;
        totals.clip_fraction += outside.mean_all()?.to_scalar::<f32>()? as f64;
        Ok(grads)
    }

    /// The mean entropy of the policy over rows: Σ_c (log σ_c + ½·ln(2πe)) for the
    /// continuous dims, plus the categorical choice's −Σ p·log p.
    fn entropy(&self, mu: &Tensor, log_std: &Tensor) -> Result<Tensor> {
        let half_log_2pi_e = 0.5 * (1.0 + (2.0 * std::f64::consts::PI).ln());
        let c = self.layout.continuous;
        let mut h = (log_std.sum(1)? + c as f64 * half_log_2pi_e)?;
        if self.layout.choices > 0 {
            let logits = mu.narrow(1, c, self.layout.choices)?;
            let log_p = candle_nn::ops::log_softmax(&logits, candle_core::D::Minus1)?;
            h = (h - (log_p.exp()? * log_p)?.sum(1)?)?;
        }
        Ok(h.mean_all()?)
    }

    /// The minibatch of steps `idx`.
    fn minibatch(&self, idx: &[usize], batch: &Batch, host: &Host) -> Minibatch {
        let (o, a, c) = (self.layout.obs_dim, self.layout.action_dim(), self.c);
        let rows = |data: &[f32], w: usize| super::gather_rows(data, idx, w);
        let n = idx.len();
        let mut adv = rows(&host.advantage, 1);
        if self.cfg.adv_norm {
            normalize_advantages(&mut adv, 1, false);
        }
        Minibatch {
            n,
            obs: rows(&batch.obs, o),
            actions: rows(&batch.actions, a),
            old_logp: rows(&host.old_logp, 1),
            advantage: adv,
            returns: rows(&host.returns, c),
            old_value: rows(&host.values, c),
        }
    }

    /// The update's body; on an error the caller puts the state back.
    fn epochs(&mut self, batch: &Batch) -> Result<UpdateStats> {
        let b = batch.len();
        let (advantage, returns, values) = self.advantages(batch)?;
        let host = Host {
            old_logp: super::behaviour_log_probs(&self.layout, batch, &self.dev)?,
            explained_variance: explained_variance(&returns, &values),
            advantage,
            returns,
            values,
        };
        let m = self.cfg.minibatches(b);
        let mut order: Vec<usize> = (0..b).collect();
        let mut totals = Totals::default();
        // The fast path's steps read and write the optimiser's host copy of the weights
        // and slots, committed once after the passes (dropped on an error).
        let mut opt_host = self.fast().then(|| self.opt.host_state()).transpose()?;
        let mut scratch = fast::Scratch::default();
        let pool = self.step_pool();
        // Two-way hand-offs exactly when there is a pool to take them.
        let parallel = pool.is_some();
        let mut passes = || -> Result<()> {
            for _ in 0..self.cfg.epochs {
                order.shuffle(&mut self.rng);
                for j in 0..m {
                    // Minibatch j holds steps [j·B/m, (j+1)·B/m) of the shuffled order.
                    let idx = &order[j * b / m..(j + 1) * b / m];
                    let mb = self.minibatch(idx, batch, &host);
                    let host = opt_host.as_mut().map(|h| (h, &mut scratch));
                    self.step(&mb, host, parallel, &mut totals)?;
                }
            }
            Ok(())
        };
        // With two threads or more, the hand-written steps run on a pool of two made
        // for this update: each step hands its halves to the pool's threads instead of
        // spawning one (~23 µs a spawn here, two a step of ~0.5 ms).
        match pool {
            Some(pool) => pool.install(passes)?,
            None => passes()?,
        }
        if let Some(h) = opt_host {
            self.opt.commit_host(h)?;
        }
        let obs = Tensor::from_slice(&batch.obs, (b, self.layout.obs_dim), &self.dev)?;
        let out = self.agent.forward(&obs)?;
        let (mu_abs_max, log_std_mean) = policy_diagnostics(&out.mu, &out.log_std)?;
        let n = totals.steps.max(1) as f64;
        Ok(UpdateStats {
            values: vec![
                ("policy_loss", (totals.policy_loss / n) as f32),
                ("value_loss", (totals.value_loss / n) as f32),
                ("entropy", (totals.entropy / n) as f32),
                ("approx_kl", (totals.approx_kl / n) as f32),
                ("clip_fraction", (totals.clip_fraction / n) as f32),
                ("explained_variance", host.explained_variance),
                ("mu_abs_max", mu_abs_max),
                ("log_std_mean", log_std_mean),
                ("grad_norm", (totals.grad_norm / n) as f32),
            ],
            per_dim: Vec::new(),
        })
    }
}

/// The batch's per-step numbers on the host.
struct Host {
    /// [B]: log π_old(a|o).
    old_logp: Vec<f32>,
    /// [B]: advantage (summed over the critic's outputs).
    advantage: Vec<f32>,
    /// [B, c]: R = A + V_old.
    returns: Vec<f32>,
    /// [B, c]: V_old.
    values: Vec<f32>,
    /// 1 − Var(R − V)/Var(R) over every entry.
    explained_variance: f32,
}

/// 1 − Var(R − V)/Var(R): how much of the returns' spread the critic explains (1 all,
/// 0 none, below 0 worse than their mean); 0 where the returns do not vary.
fn explained_variance(returns: &[f32], values: &[f32]) -> f32 {
    let var_r = variance(returns.iter().map(|&r| r as f64));
    if var_r == 0.0 {
        return 0.0;
    }
    let var_e = variance(returns.iter().zip(values).map(|(&r, &v)| (r - v) as f64));
    (1.0 - var_e / var_r) as f32
}

/// The population variance of `xs`, in f64.
fn variance(xs: impl Iterator<Item = f64>) -> f64 {
    let v: Vec<f64> = xs.collect();
    let n = v.len().max(1) as f64;
    let mean = v.iter().sum::<f64>() / n;
    v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n
}

impl Algorithm for Ppo {
    fn stat_names(&self) -> Vec<&'static str> {
        STATS.to_vec()
    }

    /// Several optimiser steps: a non-finite loss in a later one puts back the
    /// weights, optimiser slots, step count and shuffle stream of the update's start.
    fn update(&mut self, batch: &Batch) -> Result<UpdateStats> {
        let before = self.save_state()?;
        // With `ppo.obs_norm`, the update reads what the actors' policy read.
        let normalized = self.norm.observations(batch);
        let result = self.epochs(normalized.as_ref().unwrap_or(batch));
        match &result {
            Err(_) => self.restore_state(&|name| before.get(name), &before.numbers)?,
            Ok(_) => self.norm.learn_observations(batch),
        }
        result
    }

    fn policy_tensors(&self) -> Result<Vec<NamedTensor>> {
        let mut t = checkpoint::to_named_all(&self.agent.params().tensors()?)?;
        t.extend(self.norm.weights());
        Ok(t)
    }

    fn optimizer_steps(&self) -> u64 {
        self.opt.steps()
    }

    fn set_grad_path(&mut self, path: GradPath) {
        self.path = path;
    }

    fn set_threads(&mut self, n: usize) {
        self.threads = n;
    }

    fn save_state(&self) -> Result<super::AlgoState> {
        let nets = [self.agent.params(), self.critic.params()];
        let mut state = super::nets_state(&nets, &self.opt, Some(&self.rng))?;
        state.tensors.extend(self.norm.state()?);
        Ok(state)
    }

    fn restore_state(
        &mut self,
        get: &dyn Fn(&str) -> Option<Tensor>,
        numbers: &std::collections::BTreeMap<String, u128>,
    ) -> Result<()> {
        let nets = [self.agent.params(), self.critic.params()];
        super::restore_nets(&nets, &mut self.opt, Some(&mut self.rng), get, numbers)?;
        self.norm.restore(get)
    }
}

mod fast;
mod minibatch;
mod normalize;
#[cfg(test)]
mod tests;
