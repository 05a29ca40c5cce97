//! Standalone QRRL (paper Section 3, loss (2); docs/ALGORITHM.md §14): the policy is an
//! implicit quantile network a_j = Q_θ(τ_j, o) (nets/quantile_policy.rs), trained by
//! quantile regression of its own quantiles onto the actions it took, weighted by the
//! advantage, beside a scalar critic V(o):
//!
//! L_a   = mean_{B·K·A} ρ_τ'(a_j − Q_j(τ', o)) · Â         (K fresh τ' per (dim, step))
//! L_mon = λ_mon · 2K · mean_{B·K·K·A} Huber_1(relu(Q(τ_i) − Q(τ_k)))·1{τ_i<τ_k}
//! L_c   = λ_c · mean_B (V(o) − R)²,  Â = R − V(o) (R: n-step return of the summed reward)
//!
//! The vector variant (`qrrl.vector`, for envs whose action dim j moves coordinate
//! j): V(o) ∈ R^d on the vector reward, and Â_j weighs action dim j.
//!
//! Q is the network's output plus a fixed base quantile function s·(2τ − 1)
//! (`qrrl.spread`), so the initial policy is U(−s, s) rather than a point. A
//! positive advantage pulls the quantile function toward the action (more likely), a
//! negative one pushes it away. Its constants (K, κ, λ_mon, λ_c, advantage
//! normalisation) are the `saver` section's.

use super::qnet_grad::quantile_net_grads;
use super::saver::grad::weighted_quantile_losses;
use super::UpdateStats;
use super::{batch_returns, check_finite, tau_tensors, update_rows, Algorithm, GradPath};
use crate::config::{RunConfig, SaverConfig};
use crate::env::EnvLayout;
use crate::nets::{base_quantiles, Critic, ParamSet, Pcpn, QuantileFamily, QUANTILE_PREFIX};
use crate::optim::Optimizer;
use crate::returns::normalize_advantages;
use crate::rng::{rng_for, streams, uniform01, SaverRng};
use crate::rollout::Batch;
use crate::{checkpoint, Result};
use candle_core::{Device, Tensor};
use saver_proto::NamedTensor;
use std::sync::Arc;

const STATS: &[&str] = &[
    "actor_loss",
    "mon_loss",
    "critic_loss",
    "action_abs_max",
    "grad_norm",
];

/// The QRRL learner state.
pub struct Qrrl {
    /// The quantile policy network (variables `agent.q.*`).
    net: Pcpn,
    /// Its variables.
    net_params: ParamSet,
    /// The scalar critic V(o).
    critic: Critic,
    /// One optimiser over policy and critic variables.
    opt: Optimizer,
    /// The τ' stream.
    rng: SaverRng,
    /// Env layout.
    layout: EnvLayout,
    /// γ.
    gamma: f32,
    /// Bootstrap at the step limit.
    bootstrap_timeout: bool,
    /// Loss constants (SAVER's quantile loss and monotonic penalty).
    cfg: SaverConfig,
    /// s of the base quantile function s·(2τ − 1) (`qrrl.spread`).
    spread: f64,
    /// Which gradient implementation runs.
    path: GradPath,
    /// Threads of the fused blocks (0: one per core).
    threads: usize,
    /// Device.
    dev: Device,
}

/// QRRL's registration ([`super::entry`]).
/// Standalone QRRL's learning rate by default (with Adam; docs/ALGORITHM.md §14).
pub const RECOMMENDED_QRRL_LR: f64 = 1e-3;
pub(crate) const ENTRY: super::Entry = super::Entry {
    build: build_qrrl,
    policy: quantile_policy,
    recommend,
    check,
    flops,
};

/// TF1 Adam at [`RECOMMENDED_QRRL_LR`]. Advantages stay raw: normalised, the noise of
/// equally good actions is scaled up and drifts the bandit's two modes into one (2 of
/// 5 seeds against 0 of 5 raw; docs/ALGORITHM.md §14).
fn recommend(c: &mut RunConfig) {
    c.optimizer = crate::config::OptimizerKind::Adam;
    c.lr = RECOMMENDED_QRRL_LR;
}

/// The env's actions must suit a quantile policy; V-trace has no ratio to take.
fn check(c: &RunConfig) -> Result<()> {
    crate::config::check_quantile_policy(c.env.layout(), c.qrrl.spread)?;
    if c.qrrl.vector && !c.env.actions_aligned() {
        return Err(crate::CoreError::Config(format!(
            "qrrl.vector: the vector variant pairs action dim j with coordinate j, on an \
             env whose action dim j moves coordinate j (point, bandit); {} is not one",
            c.env
        )));
    }
    super::refuse_vtrace(
        c,
        "acts with a quantile policy, whose actions have no density to take a ratio of",
    )
}

/// The quantile policy is trained (3× its layers) over the actions' dims, beside the
/// critic.
fn flops(config: &RunConfig, b: usize, t: usize) -> f64 {
    let (l, k) = (&config.env.layout(), config.saver.quantiles);
    let critic = 3.0 * super::mlp_flops(b + t, &super::mlp_dims(l.obs_dim, &config.hidden, 1));
    let (policy, embed) = super::quantile_net_flops(b, k, l.obs_dim, l.continuous);
    critic + 3.0 * policy + 2.0 * embed
}

fn build_qrrl(config: &RunConfig, _pcpn: Option<Pcpn>, dev: &Device) -> Result<Box<dyn Algorithm>> {
    Ok(Box::new(Qrrl::new(config, dev)?))
}

fn quantile_policy(config: &RunConfig) -> Arc<dyn crate::acting::PolicyFamily> {
    // `RunConfig::validate` refuses QRRL on a layout with a choice, so this holds.
    Arc::new(QuantileFamily {
        layout: config.env.layout(),
        spread: config.qrrl.spread,
    })
}

impl Qrrl {
    /// A fresh policy and critic initialised from the run seed.
    pub fn new(config: &RunConfig, dev: &Device) -> Result<Self> {
        let layout = config.env.layout();
        QuantileFamily::new(layout, config.qrrl.spread)?;
        let mut rng = rng_for(config.seed, streams::INIT);
        let mut net_params = ParamSet::default();
        let net = Pcpn::init_net(
            QUANTILE_PREFIX,
            layout.obs_dim,
            layout.continuous,
            &mut rng,
            dev,
            &mut net_params,
        )?;
        let values = if config.qrrl.vector {
            layout.aligned_dim
        } else {
            1
        };
        let critic = Critic::with_sizes(layout.obs_dim, values, &config.hidden, &mut rng, dev)?;
        let mut vars = net_params.vars.clone();
        vars.extend(critic.params().vars.clone());
        Ok(Self {
            net,
            net_params,
            critic,
            opt: super::run_optimizer(vars, config, 1)?,
            rng: rng_for(config.seed, streams::LEARNER),
            layout,
            gamma: config.gamma as f32,
            bootstrap_timeout: config.bootstrap_timeout,
            cfg: config.saver.clone(),
            spread: config.qrrl.spread,
            path: GradPath::for_device(dev),
            threads: 0,
            dev: dev.clone(),
        })
    }
}

/// The two policy-side loss terms through candle autograd: the reference the fused
/// path is held to. `obs` [B, O], `actions` [B, A], `advantage` [B, 1] (one per step)
/// or [B, A] (the vector variant: one per action dim), `taus` [A, B, K].
pub fn qrrl_actor_losses(
    net: &Pcpn,
    obs: &Tensor,
    actions: &Tensor,
    advantage: &Tensor,
    taus: &[f32],
    cfg: &SaverConfig,
    spread: f64,
) -> Result<(Tensor, Tensor)> {
    let (b, a) = actions.dims2()?;
    let k = taus.len() / (a * b);
    let (tau, cos) = tau_tensors(taus, a, b, k, obs.device())?;
    // Q = network + the base quantile function s·(2τ − 1).
    let base = base_quantiles(&tau, spread)?;
    let q = (net.forward(obs, &cos)? + base)?; // [A, B, K]
    let l = weighted_quantile_losses(&q, actions, advantage, &tau, cfg)?;
    Ok((l.actor, l.mon))
}

impl Algorithm for Qrrl {
    fn set_grad_path(&mut self, path: GradPath) {
        self.path = path;
    }

    fn stat_names(&self) -> Vec<&'static str> {
        STATS.to_vec()
    }

    fn update(&mut self, batch: &Batch) -> Result<UpdateStats> {
        let (b, o, a) = (batch.len(), self.layout.obs_dim, self.layout.continuous);
        let k = self.cfg.quantiles;
        let (obs_all, n_ends) = update_rows(batch, self.bootstrap_timeout, o, &self.dev)?;
        let v_all = self.critic.forward(&obs_all)?; // [B+T(+timeouts), c]
        let value = v_all.narrow(0, 0, b)?;
        // c = 1: the summed reward; the vector variant: one return per coordinate.
        let c = v_all.dim(1)?;
        let rewards = if c == 1 {
            batch.scalar_reward()
        } else {
            batch.vector_reward.clone()
        };
        let returns = batch_returns(batch, &rewards, &v_all, n_ends, c, self.gamma)?;
        let returns = Tensor::from_vec(returns, (b, c), &self.dev)?;
        let mut adv: Vec<f32> = (&returns - &value)?.flatten_all()?.to_vec1()?; // [B, c]
        if self.cfg.adv_norm {
            normalize_advantages(&mut adv, c, self.cfg.adv_norm_joint);
        }
        let critic_loss = ((value - &returns)?.sqr()?.mean_all()? * self.cfg.lambda_critic)?;
        let obs = obs_all.narrow(0, 0, b)?.detach();
        let taus = uniform01(&mut self.rng, a * b * k);
        let (actor, mon, grads) = match self.path {
            GradPath::Fast => {
                // Each step's advantage weighs every action dim of it; the vector
                // variant's advantage of coordinate j weighs action dim j.
                let weight: Vec<f32> = if c == 1 {
                    adv.iter()
                        .flat_map(|&v| std::iter::repeat_n(v, a))
                        .collect()
                } else {
                    adv.clone()
                };
                let g = quantile_net_grads(
                    &self.net,
                    &obs,
                    &batch.actions,
                    &weight,
                    &taus,
                    (&self.cfg).into(),
                    self.spread as f32,
                    self.threads,
                    Some(&critic_loss),
                )?;
                (g.quantile_loss, g.mon_loss, g.grads)
            }
            GradPath::Reference => {
                let actions = Tensor::from_slice(&batch.actions, (b, a), &self.dev)?;
                let adv_t = Tensor::from_slice(&adv, (b, c), &self.dev)?;
                let (actor, mon) = qrrl_actor_losses(
                    &self.net,
                    &obs,
                    &actions,
                    &adv_t,
                    &taus,
                    &self.cfg,
                    self.spread,
                )?;
                let (av, mv) = (actor.to_scalar::<f32>()?, mon.to_scalar::<f32>()?);
                (av, mv, ((actor + mon)? + &critic_loss)?.backward()?)
            }
        };
        // Checked before the step: a non-finite loss changes nothing.
        let actor = check_finite("actor_loss", actor)?;
        let mon = check_finite("mon_loss", mon)?;
        let critic = check_finite("critic_loss", critic_loss.to_scalar::<f32>()?)?;
        let grad_norm = self.opt.step(&grads)? as f32;
        let action_abs_max = batch.actions.iter().fold(0f32, |m, v| m.max(v.abs()));
        Ok(UpdateStats {
            values: vec![
                ("actor_loss", actor),
                ("mon_loss", mon),
                ("critic_loss", critic),
                ("action_abs_max", action_abs_max),
                ("grad_norm", grad_norm),
            ],
            per_dim: Vec::new(),
        })
    }

    fn policy_tensors(&self) -> Result<Vec<NamedTensor>> {
        checkpoint::to_named_all(&self.net.tensors()?)
    }

    fn optimizer_steps(&self) -> u64 {
        self.opt.steps()
    }

    fn set_threads(&mut self, n: usize) {
        self.threads = n;
    }

    fn save_state(&self) -> Result<super::AlgoState> {
        let nets = [&self.net_params, self.critic.params()];
        super::nets_state(&nets, &self.opt, Some(&self.rng))
    }

    fn restore_state(
        &mut self,
        get: &dyn Fn(&str) -> Option<Tensor>,
        numbers: &std::collections::BTreeMap<String, u128>,
    ) -> Result<()> {
        let nets = [&self.net_params, self.critic.params()];
        super::restore_nets(&nets, &mut self.opt, Some(&mut self.rng), get, numbers)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::test_util::{grad_of, scale_and_worst};
    use crate::config::Algo;
    use crate::env::{EnvKind, EnvSpec};

    /// The fused path's losses and every policy gradient equal candle autograd's
    /// through [`qrrl_actor_losses`] (monotonic penalty on, the base quantile function
    /// on, 21 steps: two full blocks and a partial one), within 1e-4 of each tensor's
    /// largest entry (f32 sums in another order), with one advantage per step and with
    /// the vector variant's one per action dim.
    #[test]
    fn fast_qrrl_gradients_equal_autograd() {
        check_qrrl_gradients(false);
        check_qrrl_gradients(true);
    }

    fn check_qrrl_gradients(vector: bool) {
        let spec = EnvSpec::new(EnvKind::Angle, 4).unwrap();
        let config = crate::algo::recommended(&spec, Algo::Qrrl, 1);
        let (cfg, spread) = (config.saver, config.qrrl.spread);
        let (b, o, a, k) = (21, 4, 4, cfg.quantiles);
        let dev = Device::Cpu;
        let mut params = ParamSet::default();
        let net =
            Pcpn::init_net(QUANTILE_PREFIX, o, a, &mut rng_for(2, 0), &dev, &mut params).unwrap();
        let mut rng = rng_for(3, 0);
        let u = |rng: &mut SaverRng, n: usize, s: f32| -> Vec<f32> {
            uniform01(rng, n)
                .iter()
                .map(|x| s * (2.0 * x - 1.0))
                .collect()
        };
        let obs = u(&mut rng, b * o, 1.0);
        let actions = u(&mut rng, b * a, 1.5);
        let c = if vector { a } else { 1 };
        let adv = u(&mut rng, b * c, 1.0);
        let taus = uniform01(&mut rng, a * b * k);
        let obs_t = Tensor::from_slice(&obs, (b, o), &dev).unwrap();
        let (actor, mon) = qrrl_actor_losses(
            &net,
            &obs_t,
            &Tensor::from_slice(&actions, (b, a), &dev).unwrap(),
            &Tensor::from_slice(&adv, (b, c), &dev).unwrap(),
            &taus,
            &cfg,
            spread,
        )
        .unwrap();
        let (want_a, want_m) = (
            actor.to_scalar::<f32>().unwrap(),
            mon.to_scalar::<f32>().unwrap(),
        );
        assert!(want_m > 0.0, "the penalty is active in this fixture");
        let want = (actor + mon).unwrap().backward().unwrap();
        let weight: Vec<f32> = if vector {
            adv.clone()
        } else {
            adv.iter().flat_map(|&v| [v; 4]).collect()
        };
        let got = quantile_net_grads(
            &net,
            &obs_t,
            &actions,
            &weight,
            &taus,
            (&cfg).into(),
            spread as f32,
            1,
            None,
        )
        .unwrap();
        assert!((got.quantile_loss - want_a).abs() <= 1e-5 * want_a.abs().max(1e-3));
        assert!((got.mon_loss - want_m).abs() <= 1e-5 * want_m.abs().max(1e-3));
        for (name, var) in &params.vars {
            let (scale, diff) = scale_and_worst(&grad_of(&got.grads, var), &grad_of(&want, var));
            assert!(
                scale > 0.0 && diff <= 1e-4 * scale,
                "vector {vector}, {name}: max |fast - autograd| {diff}, max |autograd| {scale}"
            );
        }
    }
}
