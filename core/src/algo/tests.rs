//! Checks of the SAVER update against its formulas: the actor-loss gradient by finite
//! differences through the frozen PCPN, the PCPN left untouched, and the acting policy
//! equal to the training network.

use super::*;
use crate::config::{Algo, RunConfig};
use crate::env::{EnvKind, EnvLayout, EnvSpec};
use crate::link::PolicyWeights;
use crate::nets::{Agent, Pcpn, Policy};
use crate::rng::{rng_for, uniform01};
use crate::rollout::Batch;
use candle_core::{DType, Device, Tensor, Var};
use std::sync::Arc;

/// A custom env with the point mass's layout (p = entries 0-1, speeds 2-3, 2 actions),
/// every entry within ±`half`, max_change 0.2, and its goal at `goal_start` (a success
/// rule of radius 0.05) when given.
pub(super) fn plane_spec(half: f32, goal_start: Option<usize>) -> EnvSpec {
    let layout = EnvLayout {
        obs_dim: 6,
        continuous: 2,
        choices: 0,
        aligned_start: 0,
        aligned_dim: 2,
    };
    let bounds = crate::env::EnvBounds {
        obs_low: vec![-half; 6],
        obs_high: vec![half; 6],
        max_change: 0.2,
    };
    let rule = goal_start.map(|g| crate::env::SuccessRule {
        radius: 0.05,
        goal_start: Some(g),
    });
    EnvSpec::custom("plane", layout, bounds)
        .unwrap()
        .with_success(rule)
        .unwrap()
}

pub(super) fn random_pcpn(layout: &EnvLayout, dtype: DType) -> Pcpn {
    Pcpn::random_frozen(layout, 11, dtype, &Device::Cpu).unwrap()
}

pub(super) fn uniform(rng: &mut crate::rng::SaverRng, n: usize, lo: f32, hi: f32) -> Vec<f32> {
    uniform01(rng, n)
        .into_iter()
        .map(|u| lo + (hi - lo) * u)
        .collect()
}

/// A synthetic batch of `t` trajectories × `n` steps from seed `seed`: random rows,
/// actions within ±`action_bound`, the given `done` flags.
pub(super) fn random_batch(
    l: &EnvLayout,
    t: usize,
    n: usize,
    seed: u64,
    action_bound: f32,
    done: Vec<bool>,
) -> Batch {
    let mut rng = rng_for(seed, 0);
    let b = t * n;
    Batch {
        n_traj: t,
        n_steps: n,
        obs: uniform(&mut rng, b * l.obs_dim, -1.0, 1.0),
        last_obs: uniform(&mut rng, t * l.obs_dim, -1.0, 1.0),
        actions: uniform(&mut rng, b * l.action_dim(), -action_bound, action_bound),
        payload: gaussian_payload(l, b),
        state_delta: uniform(&mut rng, b * l.aligned_dim, -0.1, 0.1),
        vector_reward: uniform(&mut rng, b * l.aligned_dim, -0.1, 0.1),
        env_reward: vec![],
        done,
        timeouts: vec![],
        timeout_obs: vec![],
        steps: b as u64,
    }
}

/// A Gaussian behaviour policy's payload for `b` steps: μ = 0.1 in every mean entry,
/// log σ = −1 (the agent's initial σ).
pub(super) fn gaussian_payload(l: &EnvLayout, b: usize) -> Vec<f32> {
    let row: Vec<f32> = std::iter::repeat_n(0.1, l.mu_dim())
        .chain(std::iter::repeat_n(-1.0, l.log_std_dim()))
        .collect();
    row.repeat(b)
}

/// A synthetic batch of 2 trajectories × 3 steps.
fn small_batch(l: &EnvLayout) -> Batch {
    random_batch(
        l,
        2,
        3,
        5,
        1.0,
        vec![false, true, false, false, false, false],
    )
}

/// SAVER's agent-side loss (L_a + L_mon) in f64 at (μ, log σ), fixed everything else.
struct Fixture {
    pcpn: Pcpn,
    obs: Tensor,
    state_delta: Tensor,
    advantage: Tensor,
    tau: Tensor,
    cos: Tensor,
    cfg: crate::config::SaverConfig,
}

impl Fixture {
    fn new(spec: EnvSpec, kappa: Option<f64>) -> (Self, Vec<f64>, Vec<f64>) {
        let l = spec.layout();
        let (b, k, d) = (3, 4, l.aligned_dim);
        let dev = Device::Cpu;
        let mut rng = rng_for(21, 0);
        let f64t = |v: Vec<f32>, shape: &[usize]| {
            Tensor::from_vec(v, shape, &dev)
                .unwrap()
                .to_dtype(DType::F64)
                .unwrap()
        };
        let taus = uniform01(&mut rng, d * b * k);
        let (tau, cos) = tau_tensors(&taus, d, b, k, &dev).unwrap();
        let fx = Self {
            pcpn: random_pcpn(&l, DType::F64),
            obs: f64t(uniform(&mut rng, b * l.obs_dim, -1.0, 1.0), &[b, l.obs_dim]),
            state_delta: f64t(uniform(&mut rng, b * d, -0.1, 0.1), &[b, d]),
            advantage: f64t(uniform(&mut rng, b * d, -1.0, 1.0), &[b, d]),
            tau: tau.to_dtype(DType::F64).unwrap(),
            cos: cos.to_dtype(DType::F64).unwrap(),
            cfg: loss_config(k, kappa),
        };
        let mu: Vec<f64> = uniform(&mut rng, b * l.mu_dim(), -1.0, 1.0)
            .into_iter()
            .map(f64::from)
            .collect();
        let ls: Vec<f64> = uniform(&mut rng, b * l.log_std_dim(), -2.0, 0.0)
            .into_iter()
            .map(f64::from)
            .collect();
        (fx, mu, ls)
    }

    fn loss(&self, mu: &Tensor, ls: &Tensor) -> Tensor {
        let l = saver_actor_losses(
            &self.pcpn,
            &self.obs,
            mu,
            ls,
            &self.state_delta,
            &self.advantage,
            &self.tau,
            &self.cos,
            &self.cfg,
        )
        .unwrap();
        (l.actor + l.mon).unwrap()
    }

    fn value(&self, mu: &[f64], ls: &[f64]) -> f64 {
        let b = self.obs.dim(0).unwrap();
        let mu = Tensor::from_slice(mu, (b, mu.len() / b), &Device::Cpu).unwrap();
        let ls = Tensor::from_slice(ls, (b, ls.len() / b), &Device::Cpu).unwrap();
        self.loss(&mu, &ls).to_scalar::<f64>().unwrap()
    }
}

/// Central differences (h = 1e-6, f64) against candle's autograd for every entry of μ
/// and log σ: the gradient reaches the agent's outputs through the frozen PCPN.
fn check_gradient(spec: EnvSpec, kappa: Option<f64>) {
    let (fx, mu, ls) = Fixture::new(spec.clone(), kappa);
    let b = fx.obs.dim(0).unwrap();
    let mu_v = Var::from_slice(&mu, (b, mu.len() / b), &Device::Cpu).unwrap();
    let ls_v = Var::from_slice(&ls, (b, ls.len() / b), &Device::Cpu).unwrap();
    let grads = fx
        .loss(mu_v.as_tensor(), ls_v.as_tensor())
        .backward()
        .unwrap();
    let g_mu: Vec<f64> = grads
        .get(mu_v.as_tensor())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    let g_ls: Vec<f64> = grads
        .get(ls_v.as_tensor())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    let h = 1e-6;
    let mut worst = 0.0f64;
    let scale = g_mu.iter().chain(&g_ls).fold(0.0f64, |m, g| m.max(g.abs()));
    assert!(scale > 1e-6, "gradient vanishes: {g_mu:?} {g_ls:?}");
    for (which, base, auto) in [(0, &mu, &g_mu), (1, &ls, &g_ls)] {
        for i in 0..base.len() {
            let (mut up, mut down) = (base.clone(), base.clone());
            up[i] += h;
            down[i] -= h;
            let fd = if which == 0 {
                (fx.value(&up, &ls) - fx.value(&down, &ls)) / (2.0 * h)
            } else {
                (fx.value(&mu, &up) - fx.value(&mu, &down)) / (2.0 * h)
            };
            worst = worst.max((fd - auto[i]).abs() / scale);
        }
    }
    assert!(
        worst < 1e-5,
        "{spec}: worst relative gradient error {worst:e}"
    );
}

#[test]
fn saver_actor_gradient_matches_finite_differences_for_every_layout() {
    check_gradient(EnvSpec::new(EnvKind::Angle, 4).unwrap(), None);
    check_gradient(EnvSpec::new(EnvKind::Select, 3).unwrap(), None);
    check_gradient(EnvSpec::new(EnvKind::Arm, 2).unwrap(), Some(0.01));
}

#[test]
fn saver_update_leaves_the_pcpn_bit_identical_and_moves_agent_and_critic() {
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let config = RunConfig::paper(&spec, Algo::Saver, 1);
    let pcpn = random_pcpn(&spec.layout(), DType::F32);
    let values = |t: Vec<(String, Tensor)>| -> Vec<(String, Vec<f32>)> {
        t.into_iter()
            .map(|(n, x)| (n, x.flatten_all().unwrap().to_vec1().unwrap()))
            .collect()
    };
    let before = values(pcpn.tensors().unwrap());
    let mut saver = Saver::new(&config, pcpn, &Device::Cpu).unwrap();
    let state0 = values(saver.save_state().unwrap().tensors);
    for _ in 0..3 {
        saver.update(&small_batch(&spec.layout())).unwrap();
    }
    for ((n, a), (_, b)) in before.iter().zip(values(saver.pcpn().tensors().unwrap())) {
        assert!(
            a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
            "{n} changed"
        );
    }
    // Agent and critic did move (TF1 RMSProp moves every weight with a gradient).
    let state1 = values(saver.save_state().unwrap().tensors);
    for prefix in ["agent.mu.w", "critic.out.w"] {
        let get = |s: &[(String, Vec<f32>)]| s.iter().find(|(n, _)| n == prefix).unwrap().1.clone();
        assert_ne!(get(&state0), get(&state1), "{prefix} did not move");
    }
}

/// The actor's host forward equals the learner's network, at the paper's widths and at
/// others (the actor reads the widths from the weights).
#[test]
fn acting_policy_equals_the_training_network() {
    let bounded = crate::nets::HeadConfig {
        mu_bound: Some(1.0),
        log_std_bounds: Some((-3.0, -0.5)),
        ..crate::nets::HeadConfig::FAITHFUL
    };
    let paper = &crate::config::PAPER_HIDDEN[..];
    for (spec, head, hidden) in [
        (
            EnvSpec::new(EnvKind::Angle, 4).unwrap(),
            crate::nets::HeadConfig::FAITHFUL,
            paper,
        ),
        (EnvSpec::new(EnvKind::Select, 5).unwrap(), bounded, paper),
        (EnvSpec::new(EnvKind::Arm, 2).unwrap(), bounded, paper),
        (EnvSpec::new(EnvKind::Angle, 6).unwrap(), bounded, &[64, 64]),
        (EnvSpec::new(EnvKind::Select, 2).unwrap(), bounded, &[7]),
        (
            EnvSpec::new(EnvKind::Arm, 2).unwrap(),
            bounded,
            &[32, 5, 16, 9],
        ),
    ] {
        let l = spec.layout();
        let agent = Agent::new(&l, head, hidden, true, &mut rng_for(3, 1), &Device::Cpu).unwrap();
        let weights = PolicyWeights {
            version: 7,
            tensors: crate::checkpoint::to_named_all(&agent.params().tensors().unwrap()).unwrap(),
        };
        let mut policy = Policy::new(Arc::new(weights), l, head).unwrap();
        let obs = uniform(&mut rng_for(4, 0), 5 * l.obs_dim, -1.0, 1.0);
        let want = agent
            .forward(&Tensor::from_slice(&obs, (5, l.obs_dim), &Device::Cpu).unwrap())
            .unwrap()
            .mu
            .to_vec2::<f32>()
            .unwrap();
        let mut mu = Vec::new();
        for (row, w) in obs.chunks(l.obs_dim).zip(want) {
            policy.mean(row, &mut mu);
            for (a, b) in mu.iter().zip(&w) {
                assert!((a - b).abs() < 1e-5, "{spec}: {mu:?} vs {w:?}");
            }
        }
    }
}

/// Every algorithm builds its networks at the run's `hidden` widths: the published
/// agent has one `agent.l{i}` per width, of that width, and an update is finite and
/// moves it.
#[test]
fn every_algorithm_trains_at_other_hidden_widths() {
    let spec = EnvSpec::new(EnvKind::Point, 3).unwrap();
    let l = spec.layout();
    for algo in [Algo::A2c, Algo::Saver, Algo::Ppo, Algo::Qrrl] {
        let mut config = recommended(&spec, algo, 1);
        config.hidden = vec![16, 8];
        validate(&config).unwrap();
        let pcpn = algo.has_pcpn().then(|| random_pcpn(&l, DType::F32));
        let mut a = build(&config, pcpn, &Device::Cpu).unwrap();
        let before = a.policy_tensors().unwrap();
        if algo != Algo::Qrrl {
            // (QRRL's policy is the PCPN-shaped quantile net; its critic has the widths.)
            let width = |name: &str| {
                before
                    .iter()
                    .find(|t| t.name == name)
                    .map(|t| t.shape.clone())
            };
            assert_eq!(width("agent.l0.w"), Some(vec![l.obs_dim, 16]), "{algo:?}");
            assert_eq!(width("agent.l1.w"), Some(vec![16, 8]), "{algo:?}");
            assert_eq!(width("agent.l2.w"), None, "{algo:?}");
        }
        let stats = a.update(&small_batch(&l)).unwrap();
        assert!(stats.values.iter().all(|(_, v)| v.is_finite()), "{algo:?}");
        assert_ne!(before, a.policy_tensors().unwrap(), "{algo:?}");
    }
}

/// Weights an actor cannot read as a Gaussian MLP are refused with the reason: nine
/// hidden layers, none, a weight that is not a matrix, a chain whose shapes break.
#[test]
fn acting_policy_refuses_weights_of_no_mlp() {
    let l = EnvSpec::new(EnvKind::Point, 2).unwrap().layout();
    let head = crate::nets::HeadConfig::IN_PCPN_DOMAIN;
    let agent = |hidden: &[usize]| {
        let a = Agent::new(&l, head, hidden, false, &mut rng_for(3, 1), &Device::Cpu).unwrap();
        crate::checkpoint::to_named_all(&a.params().tensors().unwrap()).unwrap()
    };
    let refused = |tensors: Vec<saver_proto::NamedTensor>| {
        let w = PolicyWeights {
            version: 1,
            tensors,
        };
        match Policy::new(Arc::new(w), l, head) {
            Ok(_) => panic!("accepted"),
            Err(e) => e.to_string(),
        }
    };
    assert!(refused(agent(&[3; 9])).contains("more than 8 hidden layers"));
    let mut none = agent(&[4]);
    none.retain(|t| !t.name.starts_with("agent.l0"));
    assert!(refused(none).contains("lack agent.l0.w"));
    let mut cube = agent(&[4]);
    let l0 = cube.iter_mut().find(|t| t.name == "agent.l0.w").unwrap();
    l0.shape = vec![l.obs_dim, 2, 2];
    assert!(refused(cube).contains("not [in, out]"));
    let mut broken = agent(&[4, 5]);
    let l1 = broken.iter_mut().find(|t| t.name == "agent.l1.w").unwrap();
    l1.shape = vec![5, 4]; // 20 values still, but 4 wide into a 5-wide layer
    assert!(refused(broken).contains("agent.l1.w"));
}

#[test]
fn a2c_update_is_finite_and_changes_the_agent() {
    let spec = EnvSpec::new(EnvKind::Select, 3).unwrap();
    let config = RunConfig::paper(&spec, Algo::A2c, 1);
    let mut a2c = A2c::new(&config, &Device::Cpu).unwrap();
    let before = a2c.policy_tensors().unwrap();
    let stats = a2c.update(&small_batch(&spec.layout())).unwrap();
    assert!(stats.values.iter().all(|(_, v)| v.is_finite()));
    assert_ne!(before, a2c.policy_tensors().unwrap());
}

/// With bootstrapping at timeouts A2C's value loss is c_v·mean((V − R)²) with the
/// timeout step's return r + γ·V(final observation); without it, or with no timeout in
/// the batch, the step is terminal. The values come from the same agent built by hand.
#[test]
fn a2c_bootstraps_at_a_timeout_from_the_observation_reached() {
    use crate::nets::HeadConfig;
    use crate::returns::n_step_returns;
    use crate::rng::streams;
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let l = spec.layout();
    let mut batch = small_batch(&l); // trajectory 0 ends at its step 1
    batch.timeouts = vec![1];
    batch.timeout_obs = vec![0.9, -0.8];
    let value_loss = |bootstrap: bool, batch: &crate::rollout::Batch| {
        let mut config = RunConfig::paper(&spec, Algo::A2c, 1);
        config.bootstrap_timeout = bootstrap;
        let mut a2c = A2c::new(&config, &Device::Cpu).unwrap();
        a2c.update(batch).unwrap().get("value_loss").unwrap()
    };
    let mut rng = rng_for(0, streams::INIT);
    let hidden = crate::config::PAPER_HIDDEN;
    let agent = Agent::new(
        &l,
        HeadConfig::FAITHFUL,
        &hidden,
        true,
        &mut rng,
        &Device::Cpu,
    )
    .unwrap();
    let v = |rows: &[f32]| -> Vec<f32> {
        let x = Tensor::from_slice(rows, (rows.len() / 2, 2), &Device::Cpu).unwrap();
        agent.forward(&x).unwrap().value.unwrap().to_vec1().unwrap()
    };
    let (values, last, reached) = (v(&batch.obs), v(&batch.last_obs), v(&batch.timeout_obs));
    let rewards = batch.scalar_reward();
    let expected = |ends: Option<&[f32]>| {
        let r = n_step_returns(&rewards, &batch.done, &last, ends, 3, 1, 0.99);
        0.5 * values
            .iter()
            .zip(&r)
            .map(|(v, r)| (v - r).powi(2))
            .sum::<f32>()
            / 6.0
    };
    let with = expected(Some(&[0., reached[0], 0., 0., 0., 0.]));
    let without = expected(None);
    assert!(
        (with - without).abs() > 1e-4,
        "{with} vs {without}: the case tells nothing"
    );
    let close = |a: f32, b: f32| (a - b).abs() <= 1e-6 * b.abs().max(1.0);
    assert!(close(value_loss(true, &batch), with));
    assert!(close(value_loss(false, &batch), without));
    batch.timeouts.clear();
    batch.timeout_obs.clear();
    assert!(close(value_loss(true, &batch), without));
}

/// SAVER uses a timeout's final observation only with bootstrapping on: its critic
/// loss (2nd stat) changes with the option on a batch with a timeout, and with the
/// option on a batch without timeouts everything equals the run without it, bit for bit.
#[test]
fn saver_bootstraps_at_a_timeout_only_when_asked() {
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let l = spec.layout();
    let mut batch = small_batch(&l);
    batch.timeouts = vec![1];
    batch.timeout_obs = vec![0.9, -0.8];
    let stats = |bootstrap: bool, batch: &crate::rollout::Batch| {
        let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
        config.bootstrap_timeout = bootstrap;
        let pcpn = random_pcpn(&l, DType::F32);
        let mut saver = Saver::new(&config, pcpn, &Device::Cpu).unwrap();
        saver.update(batch).unwrap()
    };
    let (off, on) = (stats(false, &batch), stats(true, &batch));
    let critic = |s: &super::UpdateStats| s.get("critic_loss").unwrap();
    assert!(
        (critic(&on) - critic(&off)).abs() > 1e-6 * critic(&off).abs(),
        "{on:?} vs {off:?}"
    );
    batch.timeouts.clear();
    batch.timeout_obs.clear();
    assert_eq!(stats(true, &batch), off);
}

/// The fast path's dL/dμ and dL/dlog σ equal candle autograd's through the reference
/// graph, within 1e-5 of the gradient's scale, on random inputs at the real sizes
/// (B = 128, K = 32) for every env layout, with the plain and the Huber quantile loss,
/// and at B = 13 (one full block of 8 transitions and a partial one). The fused blocks
/// give the same bits on 1 and 3 threads.
#[test]
fn fast_saver_gradient_equals_the_autograd_reference() {
    let cases = [
        (EnvSpec::new(EnvKind::Angle, 4).unwrap(), None, 128),
        (EnvSpec::new(EnvKind::Select, 3).unwrap(), None, 13),
        (EnvSpec::new(EnvKind::Arm, 2).unwrap(), Some(0.01), 128),
        (EnvSpec::new(EnvKind::Angle, 16).unwrap(), Some(0.01), 128),
    ];
    for (spec, kappa, b) in cases {
        let l = spec.layout();
        let (k, d) = (32, l.aligned_dim);
        let dev = Device::Cpu;
        let mut rng = rng_for(31, d as u64);
        let cfg = loss_config(k, kappa);
        let pcpn = random_pcpn(&l, DType::F32);
        let obs = uniform(&mut rng, b * l.obs_dim, -1.0, 1.0);
        let mu = uniform(&mut rng, b * l.mu_dim(), -1.0, 1.0);
        let ls = uniform(&mut rng, b * l.log_std_dim(), -2.0, 0.0);
        let delta = uniform(&mut rng, b * d, -0.1, 0.1);
        let adv = uniform(&mut rng, b * d, -1.0, 1.0);
        let taus = uniform01(&mut rng, d * b * k);
        let (tau, cos) = tau_tensors(&taus, d, b, k, &dev).unwrap();
        let t = |v: &[f32], c: usize| Tensor::from_slice(v, (b, c), &dev).unwrap();

        let mu_v = Var::from_slice(&mu, (b, l.mu_dim()), &dev).unwrap();
        let ls_v = Var::from_slice(&ls, (b, l.log_std_dim()), &dev).unwrap();
        let reference = saver_actor_losses(
            &pcpn,
            &t(&obs, l.obs_dim),
            mu_v.as_tensor(),
            ls_v.as_tensor(),
            &t(&delta, d),
            &t(&adv, d),
            &tau,
            &cos,
            &cfg,
        )
        .unwrap();
        let grads = (&reference.actor + &reference.mon)
            .unwrap()
            .backward()
            .unwrap();
        let flat = |x: &Tensor| -> Vec<f32> { x.flatten_all().unwrap().to_vec1().unwrap() };
        let want: Vec<f32> = [
            flat(grads.get(mu_v.as_tensor()).unwrap()),
            flat(grads.get(ls_v.as_tensor()).unwrap()),
        ]
        .concat();

        let mut fast = PcpnGrad::new(pcpn).unwrap();
        let x = Tensor::cat(
            &[
                t(&obs, l.obs_dim),
                t(&mu, l.mu_dim()),
                t(&ls, l.log_std_dim()),
            ],
            1,
        )
        .unwrap();
        fast.set_threads(1);
        let g = fast.input_grad(&x, &delta, &adv, &taus, &cfg).unwrap();
        fast.set_threads(3);
        let g3 = fast.input_grad(&x, &delta, &adv, &taus, &cfg).unwrap();
        assert_eq!(flat(&g3.dx), flat(&g.dx), "{spec}: 3 threads differ from 1");
        assert_eq!(
            (g3.actor_loss.to_bits(), g3.mon_loss.to_bits()),
            (g.actor_loss.to_bits(), g.mon_loss.to_bits())
        );
        let (dmu, dls) = policy_grads(&g.dx, l.obs_dim, l.mu_dim()).unwrap();
        let got: Vec<f32> = [flat(&dmu), flat(&dls)].concat();

        let (scale, worst) = super::test_util::scale_and_worst(&got, &want);
        assert!(
            scale > 0.0 && worst <= 1e-5 * scale,
            "{spec} κ={kappa:?}: error {worst:e} at scale {scale:e}"
        );
        let (ra, rm) = (
            reference.actor.to_scalar::<f32>().unwrap(),
            reference.mon.to_scalar::<f32>().unwrap(),
        );
        assert!(
            (g.actor_loss - ra).abs() <= 1e-5 * ra.abs().max(1e-3),
            "{spec}: L_a {} vs {ra}",
            g.actor_loss
        );
        assert!(
            (g.mon_loss - rm).abs() <= 1e-5 * rm.abs().max(1e-3),
            "{spec}: L_mon {} vs {rm}",
            g.mon_loss
        );
    }
}

#[test]
fn mu_raw_penalty_is_a_quadratic_wall_beyond_the_limit() {
    // raw = [[3, -0.5], [-2.5, 1]], limit 2: over = [[1, 0], [0.5, 0]];
    // w = 0.1, B = 2: 0.1 · (1 + 0.25) / 2 = 0.0625.
    // d/draw = 2·w·over·sign(raw)/B = [[0.1, 0], [-0.05, 0]].
    // On entry 0 alone the same; on entry 1 alone (-0.5 and 1, inside ±2) 0 and no
    // gradient anywhere.
    let raw = Var::from_slice(&[3f32, -0.5, -2.5, 1.0], (2, 2), &Device::Cpu).unwrap();
    for (entries, want_p, want_g) in [
        (vec![], 0.0625, [0.1f32, 0.0, -0.05, 0.0]),
        (vec![0], 0.0625, [0.1, 0.0, -0.05, 0.0]),
        (vec![1], 0.0, [0.0; 4]),
    ] {
        let p = super::saver::mu_raw_penalty(raw.as_tensor(), 0.1, &entries).unwrap();
        assert!(
            (p.to_scalar::<f32>().unwrap() - want_p).abs() < 1e-7,
            "{entries:?}"
        );
        let grads = p.backward().unwrap();
        let g: Vec<f32> = match grads.get(raw.as_tensor()) {
            Some(g) => g.flatten_all().unwrap().to_vec1().unwrap(),
            None => vec![0.0; 4],
        };
        for (got, want) in g.iter().zip(want_g) {
            assert!((got - want).abs() < 1e-7, "{entries:?}: {g:?}");
        }
    }
}

/// SAVER's loss constants as the paper has them, with K = `k` and Huber κ = `kappa`.
fn loss_config(k: usize, kappa: Option<f64>) -> crate::config::SaverConfig {
    crate::config::SaverConfig {
        quantiles: k,
        kappa,
        lambda_mon: 1.0,
        lambda_critic: 0.5,
        adv_norm: false,
        adv_norm_joint: false,
        mu_raw_penalty: 0.0,
        mu_raw_penalty_entries: Vec::new(),
        target: crate::config::DeltaTarget::Observed,
        pcpn_tune_lr: 0.0,
        pcpn_tune_rows: 0,
        epochs: 1,
        minibatch_size: 0,
        gae_lambda: 1.0,
        env_gae_lambda: 1.0,
        target_kl: 0.0,
        env_reward: 0.0,
        env_clip: 0.0,
        obs_norm: crate::config::ObsNorm::Off,
    }
}
