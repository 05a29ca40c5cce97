//! A2C (docs/ALGORITHM.md §8): loss = mean(−log π(a|o)·A) + c_v·mean((V − R)²), A = R − V (no gradient),
//! scalar reward = sum of the vector reward, shared trunk, entropy β = 0.

use super::vtrace::shared_log_ratios;
use super::{
    batch_returns, check_finite, matrix, policy_diagnostics, update_rows, Algorithm, UpdateStats,
};
use crate::config::RunConfig;
use crate::env::EnvLayout;
use crate::nets::{gaussian_log_prob, Agent};
use crate::optim::Optimizer;
use crate::rng::{rng_for, streams};
use crate::rollout::Batch;
use crate::{checkpoint, Result};
use candle_core::{Device, Tensor};
use saver_proto::NamedTensor;

const STATS: &[&str] = &[
    "policy_loss",
    "value_loss",
    "mu_abs_max",
    "log_std_mean",
    "grad_norm",
];

/// The A2C learner state.
pub struct A2c {
    /// Agent with value head.
    agent: Agent,
    /// Its optimiser.
    opt: Optimizer,
    /// Env layout.
    layout: EnvLayout,
    /// γ.
    gamma: f32,
    /// Value-loss weight.
    value_coef: f64,
    /// Bootstrap at the step limit.
    bootstrap_timeout: bool,
    /// Off-policy correction, when the run asks for it.
    vtrace: Option<super::Vtrace>,
    /// Device of the tensors.
    dev: Device,
}

/// A2C's registration ([`super::entry`]).
/// A2C's learning rate on a custom env (with the bounded head; `recommended`).
pub const RECOMMENDED_CUSTOM_A2C_LR: f64 = 1e-3;
pub(crate) const ENTRY: super::Entry = super::Entry {
    build: build_a2c,
    policy: super::gaussian_policy,
    recommend,
    check: super::no_checks,
    flops,
};

/// A2C keeps the paper's settings on the paper's envs; on a custom env (for which the
/// paper has none) it takes SAVER's bounded head and 1e-3: on Reacher-v5 the paper's
/// linear mean ran to |μ| ≈ 250 (clipped actions, bang-bang) and did not learn in 1 M
/// steps (final distance 0.160 → 0.163), the bounded head at 1e-3 did (0.177 → 0.136;
/// results/README.md).
fn recommend(c: &mut RunConfig) {
    if c.env.kind().is_none() {
        c.head = crate::config::HeadConfig::IN_PCPN_DOMAIN;
        c.lr = RECOMMENDED_CUSTOM_A2C_LR;
    }
}

/// The shared trunk with the mean and value heads, trained.
fn flops(config: &RunConfig, b: usize, t: usize) -> f64 {
    let l = config.env.layout();
    let dims = super::mlp_dims(l.obs_dim, &config.hidden, l.mu_dim() + 1);
    3.0 * super::mlp_flops(b + t, &dims)
}

fn build_a2c(
    config: &RunConfig,
    _pcpn: Option<crate::nets::Pcpn>,
    dev: &Device,
) -> Result<Box<dyn Algorithm>> {
    Ok(Box::new(A2c::new(config, dev)?))
}

impl A2c {
    /// A fresh agent initialised from the run seed.
    pub fn new(config: &RunConfig, dev: &Device) -> Result<Self> {
        let layout = config.env.layout();
        let mut rng = rng_for(config.seed, streams::INIT);
        let agent = Agent::new(&layout, config.head, &config.hidden, true, &mut rng, dev)?;
        let opt = super::run_optimizer(agent.params().vars.clone(), config, 1)?;
        Ok(Self {
            agent,
            opt,
            layout,
            gamma: config.gamma as f32,
            value_coef: config.value_coef,
            bootstrap_timeout: config.bootstrap_timeout,
            vtrace: super::Vtrace::of(config),
            dev: dev.clone(),
        })
    }
}

impl Algorithm for A2c {
    fn stat_names(&self) -> Vec<&'static str> {
        let mut names = STATS.to_vec();
        if self.vtrace.is_some() {
            names.extend(super::VTRACE_STATS);
        }
        names
    }

    fn update(&mut self, batch: &Batch) -> Result<UpdateStats> {
        let (b, o) = (batch.len(), self.layout.obs_dim);
        let (rows, k) = update_rows(batch, self.bootstrap_timeout, o, &self.dev)?;
        let out = self.agent.forward(&rows)?;
        let value_all = out.value.expect("A2C agent has a value head");
        let value = value_all.narrow(0, 0, b)?; // [B]
        let mu = out.mu.narrow(0, 0, b)?;
        let log_std = out.log_std.narrow(0, 0, b)?;
        let actions = matrix(&batch.actions, b, self.layout.action_dim(), &self.dev)?;
        let logp = gaussian_log_prob(&self.layout, &mu, &log_std, &actions)?;
        let rewards = batch.scalar_reward();
        let mut extra = Vec::new();
        let (returns, advantage) = match self.vtrace {
            None => {
                let returns = batch_returns(batch, &rewards, &value_all, k, 1, self.gamma)?;
                let returns = Tensor::from_vec(returns, b, &self.dev)?;
                let advantage = (&returns - &value)?.detach();
                (returns, advantage)
            }
            Some(vt) => {
                let log_pi = logp.detach().to_vec1::<f32>()?;
                let log_ratio = shared_log_ratios(&self.layout, batch, &log_pi, &self.dev)?;
                let values = value_all.detach().unsqueeze(1)?;
                let corrected =
                    vt.targets(batch, &rewards, &values, k, 1, self.gamma, &log_ratio)?;
                extra = corrected.stats;
                (
                    Tensor::from_vec(corrected.targets, b, &self.dev)?,
                    Tensor::from_vec(corrected.advantages, b, &self.dev)?,
                )
            }
        };
        let policy_loss = (logp * advantage)?.mean_all()?.neg()?;
        let value_loss = ((value - returns)?.sqr()?.mean_all()? * self.value_coef)?;
        let loss = (&policy_loss + &value_loss)?;
        // Checked before the step: a non-finite loss changes nothing.
        let policy_loss = check_finite("policy_loss", policy_loss.to_scalar::<f32>()?)?;
        let value_loss_v = check_finite("value_loss", value_loss.to_scalar::<f32>()?)?;
        let grads = loss.backward()?;
        let grad_norm = self.opt.step(&grads)? as f32;
        let (mu_abs_max, log_std_mean) = policy_diagnostics(&mu, &log_std)?;
        let mut values = vec![
            ("policy_loss", policy_loss),
            ("value_loss", value_loss_v),
            ("mu_abs_max", mu_abs_max),
            ("log_std_mean", log_std_mean),
            ("grad_norm", grad_norm),
        ];
        values.extend(extra);
        Ok(UpdateStats {
            values,
            per_dim: Vec::new(),
        })
    }

    fn policy_tensors(&self) -> Result<Vec<NamedTensor>> {
        checkpoint::to_named_all(&self.agent.params().tensors()?)
    }

    fn optimizer_steps(&self) -> u64 {
        self.opt.steps()
    }

    fn save_state(&self) -> Result<super::AlgoState> {
        super::nets_state(&[self.agent.params()], &self.opt, None)
    }

    fn restore_state(
        &mut self,
        get: &dyn Fn(&str) -> Option<Tensor>,
        numbers: &std::collections::BTreeMap<String, u128>,
    ) -> Result<()> {
        super::restore_nets(&[self.agent.params()], &mut self.opt, None, get, numbers)
    }
}
