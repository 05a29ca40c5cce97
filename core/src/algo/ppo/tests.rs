use super::*;
use crate::algo::tests::random_batch;
use crate::config::Algo;
use crate::env::{EnvKind, EnvSpec};
use rand::Rng;

/// PPO on angle d = 2 with `epochs` passes of minibatches of `size` and clip ε.
fn config(epochs: usize, size: usize, clip: f64) -> RunConfig {
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let mut c = crate::algo::recommended(&spec, Algo::Ppo, 1);
    c.ppo.epochs = epochs;
    c.ppo.minibatch_size = size;
    c.ppo.clip = clip;
    c.lr = 1e-3;
    crate::algo::validate(&c).unwrap();
    c
}

/// A batch of 4 trajectories × 16 steps whose payload is `ppo`'s own policy on it, as
/// a sync actor records it, and whose actions are drawn from that policy.
fn on_policy_batch(ppo: &Ppo, seed: u64) -> Batch {
    let l = ppo.layout;
    let mut batch = random_batch(&l, 4, 16, seed, 1.0, vec![false; 64]);
    let obs = Tensor::from_slice(&batch.obs, (64, l.obs_dim), &Device::Cpu).unwrap();
    let out = ppo.agent.forward(&obs).unwrap();
    let mu: Vec<Vec<f32>> = out.mu.to_vec2().unwrap();
    let ls: Vec<Vec<f32>> = out.log_std.to_vec2().unwrap();
    let mut rng = rng_for(seed, 77);
    batch.payload.clear();
    batch.actions.clear();
    for (m, s) in mu.iter().zip(&ls) {
        batch.payload.extend(m.iter().chain(s));
        for (mj, sj) in m.iter().zip(s) {
            batch
                .actions
                .push(mj + sj.exp() * crate::rng::normal(&mut rng));
        }
    }
    batch
}

/// mean |π(a|o)/π_old(a|o) − 1| over the batch's steps under `ppo`'s current policy.
fn mean_ratio_move(ppo: &Ppo, batch: &Batch) -> f32 {
    let l = ppo.layout;
    let obs = Tensor::from_slice(&batch.obs, (batch.len(), l.obs_dim), &Device::Cpu).unwrap();
    let shape = (batch.len(), l.action_dim());
    let actions = Tensor::from_slice(&batch.actions, shape, &Device::Cpu).unwrap();
    let out = ppo.agent.forward(&obs).unwrap();
    let logp: Vec<f32> = gaussian_log_prob(&l, &out.mu, &out.log_std, &actions)
        .unwrap()
        .to_vec1()
        .unwrap();
    let old = crate::algo::behaviour_log_probs(&l, batch, &Device::Cpu).unwrap();
    let sum: f32 = logp
        .iter()
        .zip(&old)
        .map(|(n, o)| ((n - o).exp() - 1.0).abs())
        .sum();
    sum / logp.len() as f32
}

/// The clip bounds how far one update moves the policy: 40 passes over one batch at
/// lr 1e-3 move the likelihood ratio by ~1.4 on the mean step with ε = 0.9, and with
/// ε = 0.02 by a small multiple of ε only (a step's gradient stops once its ratio
/// leaves [1 − ε, 1 + ε] on its advantage's side; what moves it further is the other
/// steps' gradients through the shared weights). Measured mean |ratio − 1|: ε = 0.9
/// 1.41, ε = 0.02 0.075; without the clip both would be the first.
#[test]
fn the_clip_bounds_how_far_an_update_moves_the_policy() {
    let mut moved = Vec::new();
    for clip in [0.9, 0.02] {
        let mut ppo = Ppo::new(&config(40, 64, clip), &Device::Cpu).unwrap();
        let batch = on_policy_batch(&ppo, 3);
        assert_eq!(mean_ratio_move(&ppo, &batch), 0.0);
        let stats = ppo.update(&batch).unwrap();
        assert_eq!(ppo.optimizer_steps(), 40);
        assert!(stats.get("clip_fraction").unwrap() > 0.0, "{stats:?}");
        moved.push(mean_ratio_move(&ppo, &batch));
    }
    eprintln!(
        "mean |ratio - 1| after 40 passes: eps 0.9 {} / eps 0.02 {}",
        moved[0], moved[1]
    );
    assert!(moved[0] > 0.7, "{moved:?}");
    assert!(moved[1] < 0.2, "{moved:?}");
}

/// The first minibatch step sees the behaviour policy itself: ratio 1 on every step,
/// so the KL estimate and the clipped share are 0 and the surrogate is −mean Â = 0
/// under normalised advantages.
#[test]
fn one_step_on_policy_starts_at_ratio_one() {
    let mut ppo = Ppo::new(&config(1, 64, 0.2), &Device::Cpu).unwrap();
    let batch = on_policy_batch(&ppo, 4);
    let s = ppo.update(&batch).unwrap();
    assert_eq!(s.get("approx_kl"), Some(0.0));
    assert_eq!(s.get("clip_fraction"), Some(0.0));
    assert!(s.get("policy_loss").unwrap().abs() < 1e-6, "{s:?}");
    assert_eq!(ppo.optimizer_steps(), 1);
}

fn values(tensors: Vec<(String, Tensor)>) -> Vec<(String, Vec<f32>)> {
    tensors
        .into_iter()
        .map(|(n, t)| (n, t.flatten_all().unwrap().to_vec1().unwrap()))
        .collect()
}

/// A return too large for f32's square makes a later minibatch's value loss infinite:
/// the update fails and leaves weights, optimiser slots, step count and shuffle stream
/// as they were (the steps it had taken are put back), and the next batch goes on.
#[test]
fn a_non_finite_minibatch_puts_the_whole_update_back() {
    // 64 steps in 64 minibatches of one: only the step with the huge reward fails,
    // after the steps shuffled before it.
    let mut ppo = Ppo::new(&config(2, 1, 0.2), &Device::Cpu).unwrap();
    let good = on_policy_batch(&ppo, 5);
    let mut bad = good.clone();
    // Step 0 of trajectory 1: only its own return is huge (GAE looks forward).
    bad.vector_reward[16 * 2] = 3e19;
    let before = ppo.save_state().unwrap();
    let e = ppo.update(&bad).unwrap_err();
    assert!(matches!(e, crate::CoreError::NonFinite(_)), "{e}");
    let after = ppo.save_state().unwrap();
    assert_eq!(values(before.tensors), values(after.tensors));
    assert_eq!(before.numbers, after.numbers);
    ppo.update(&good).unwrap();
    assert_eq!(ppo.optimizer_steps(), 128);
}

/// A run resumed after 2 updates makes the next 2 exactly as the run that went on
/// (weights, Adam slots, step count and the shuffle stream are in the state).
#[test]
fn a_resumed_ppo_goes_on_to_the_bit() {
    let cfg = config(3, 16, 0.2);
    let mut a = Ppo::new(&cfg, &Device::Cpu).unwrap();
    let batches: Vec<_> = (0..4).map(|s| on_policy_batch(&a, 20 + s)).collect();
    a.update(&batches[0]).unwrap();
    a.update(&batches[1]).unwrap();
    let saved = a.save_state().unwrap();
    let mut b = Ppo::new(&cfg, &Device::Cpu).unwrap();
    b.restore_state(&|n| saved.get(n), &saved.numbers).unwrap();
    for batch in &batches[2..] {
        assert_eq!(
            a.update(batch).unwrap().values,
            b.update(batch).unwrap().values
        );
    }
    assert_eq!(
        values(a.save_state().unwrap().tensors),
        values(b.save_state().unwrap().tensors)
    );
}

/// The hand-written step gives the same bits on one thread and with the critic's part
/// on a second (two updates of a vector critic with value clipping: the weights, Adam
/// slots and stats all equal).
#[test]
fn one_thread_and_two_give_the_same_bits() {
    let mut cfg = config(2, 16, 0.2);
    cfg.ppo.vector = true;
    cfg.ppo.value_clip = Some(0.1);
    let run = |threads: usize| {
        let mut ppo = Ppo::new(&cfg, &Device::Cpu).unwrap();
        ppo.set_threads(threads);
        let stats: Vec<_> = (0..2)
            .map(|s| {
                let batch = on_policy_batch(&ppo, 40 + s);
                ppo.update(&batch).unwrap().values
            })
            .collect();
        (stats, values(ppo.save_state().unwrap().tensors))
    };
    let one = run(1);
    assert!(one.0[1]
        .iter()
        .any(|(k, v)| *k == "policy_loss" && *v != 0.0));
    assert_eq!(one, run(2));
}

/// The vector variant's critic has one output per coordinate; its update runs on the
/// vector reward (a reward on coordinate 1 alone moves its value, not coordinate 0's).
#[test]
fn the_vector_critic_learns_each_coordinate_apart() {
    let mut cfg = config(5, 32, 0.2);
    cfg.ppo.vector = true;
    let mut ppo = Ppo::new(&cfg, &Device::Cpu).unwrap();
    assert_eq!(ppo.c, 2);
    let mut batch = on_policy_batch(&ppo, 6);
    for r in batch.vector_reward.chunks_exact_mut(2) {
        r[0] = 0.0;
        r[1] = 1.0;
    }
    let obs = Tensor::from_slice(&batch.obs, (64, ppo.layout.obs_dim), &Device::Cpu).unwrap();
    let v0: Vec<Vec<f32>> = ppo.critic.forward(&obs).unwrap().to_vec2().unwrap();
    for _ in 0..10 {
        ppo.update(&batch).unwrap();
    }
    let v1: Vec<Vec<f32>> = ppo.critic.forward(&obs).unwrap().to_vec2().unwrap();
    let mean = |v: &[Vec<f32>], j: usize| v.iter().map(|r| r[j]).sum::<f32>() / 64.0;
    let (d0, d1) = (mean(&v1, 0) - mean(&v0, 0), mean(&v1, 1) - mean(&v0, 1));
    eprintln!("mean value moved: coordinate 0 {d0}, coordinate 1 {d1}");
    // Returns of a reward of 1 per step over ≤ 16 steps at γ = 0.99 plus bootstrap: ≥ 1.
    assert!(d1 > 0.5 && d0.abs() < 0.25 * d1, "{d0} {d1}");
}

/// Every variable's gradient of one minibatch step by `path`, with the step's totals.
/// The fast path's buffers first hold another step's, of the minibatch `before`: what
/// a step leaves in them must not reach the next one.
fn step_grads(
    ppo: &Ppo,
    mb: &Minibatch,
    before: &Minibatch,
    path: GradPath,
) -> (Vec<(String, Vec<f32>)>, Totals) {
    let mut totals = Totals::default();
    let mut vars = ppo.agent.params().vars.clone();
    vars.extend(ppo.critic.params().vars.clone());
    let g = match path {
        GradPath::Fast => {
            let (nets, h) = (ppo.fast_nets(), ppo.opt.host_state().unwrap());
            let mut scratch = fast::Scratch::default();
            fast::step_grads(
                &nets,
                &h,
                before,
                false,
                &mut Totals::default(),
                &mut scratch,
            )
            .unwrap();
            let grads = fast::step_grads(&nets, &h, mb, false, &mut totals, &mut scratch).unwrap();
            assert_eq!(grads.len(), vars.len(), "one gradient per variable");
            vars.iter()
                .map(|(name, v)| {
                    let (_, g) = grads
                        .iter()
                        .find(|(id, _)| *id == v.as_tensor().id())
                        .unwrap_or_else(|| panic!("no gradient for {name}"));
                    (name.clone(), g.to_vec())
                })
                .collect()
        }
        GradPath::Reference => {
            let grads = ppo.reference_grads(mb, &mut totals).unwrap();
            vars.iter()
                .map(|(name, v)| {
                    let g = grads
                        .get(v.as_tensor())
                        .unwrap_or_else(|| panic!("no gradient for {name}"));
                    (name.clone(), g.flatten_all().unwrap().to_vec1().unwrap())
                })
                .collect()
        }
    };
    (g, totals)
}

/// The hand-written step (fast.rs) gives candle autograd's gradients on every variable
/// and the same losses, to f32 rounding, in each branch: ratios spread over [0.5, 2]
/// around a clip of 0.2 (the share of clipped steps is checked to be between 10 % and
/// 90 %, so both sides of min() and of the clamp are taken), advantages of both signs,
/// value clipping on a vector critic (old values moved off the returns so that both
/// sides of max() are taken), the entropy bonus, and the unbounded head.
#[test]
fn the_fast_step_gives_candle_autograds_gradients() {
    for (value_clip, vector, bounded) in [
        (None, false, true),
        (Some(0.1), true, true),
        (Some(0.1), false, false),
    ] {
        let mut cfg = config(1, 64, 0.2);
        cfg.ppo.value_clip = value_clip;
        cfg.ppo.vector = vector;
        cfg.ppo.entropy_coef = 0.01;
        if !bounded {
            cfg.head = crate::config::HeadConfig::FAITHFUL;
        }
        let mut ppo = Ppo::new(&cfg, &Device::Cpu).unwrap();
        let batch = on_policy_batch(&ppo, 9);
        let (advantage, returns, values) = ppo.advantages(&batch).unwrap();
        let mut rng = rng_for(9, 78);
        let old_logp: Vec<f32> =
            crate::algo::behaviour_log_probs(&ppo.layout, &batch, &Device::Cpu)
                .unwrap()
                .iter()
                .map(|l| l + 0.7 * (2.0 * rng.random::<f32>() - 1.0))
                .collect();
        let values = values
            .iter()
            .map(|v| v + 0.3 * (2.0 * rng.random::<f32>() - 1.0))
            .collect();
        let host = Host {
            old_logp,
            advantage,
            returns,
            values,
            explained_variance: 0.0,
        };
        let idx: Vec<usize> = (0..64).collect();
        let mb = ppo.minibatch(&idx, &batch, &host);
        // 40 other steps, in another order: buffers of another size and content.
        let other: Vec<usize> = (24..64).rev().collect();
        let before = ppo.minibatch(&other, &batch, &host);
        let (want, t_ref) = step_grads(&ppo, &mb, &before, GradPath::Reference);
        let (got, t_fast) = step_grads(&ppo, &mb, &before, GradPath::Fast);
        assert!(
            t_ref.clip_fraction > 0.1 && t_ref.clip_fraction < 0.9,
            "{}",
            t_ref.clip_fraction
        );
        for (a, b) in [
            (t_ref.policy_loss, t_fast.policy_loss),
            (t_ref.value_loss, t_fast.value_loss),
            (t_ref.entropy, t_fast.entropy),
            (t_ref.approx_kl, t_fast.approx_kl),
            (t_ref.clip_fraction, t_fast.clip_fraction),
        ] {
            assert!((a - b).abs() <= 1e-5 * (1.0 + a.abs()), "{a} {b}");
        }
        for ((name, w), (_, g)) in want.iter().zip(&got) {
            let scale = w.iter().fold(0.0f32, |m, x| m.max(x.abs()));
            assert!(scale > 0.0, "{name}: no gradient");
            let err = w
                .iter()
                .zip(g)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(
                err <= 1e-4 * scale,
                "{name} ({value_clip:?}, {vector}, {bounded}): {err} of {scale}"
            );
        }
    }
}

/// The fast path serves layouts without a choice; select's categorical choice takes the
/// reference (its update runs and moves the weights).
#[test]
fn a_layout_with_a_choice_takes_the_reference_step() {
    let spec = EnvSpec::new(EnvKind::Select, 4).unwrap();
    let mut cfg = crate::algo::recommended(&spec, Algo::Ppo, 1);
    cfg.ppo.epochs = 1;
    cfg.ppo.minibatch_size = 32;
    let mut ppo = Ppo::new(&cfg, &Device::Cpu).unwrap();
    assert!(ppo.layout.choices > 0);
    let l = ppo.layout;
    let batch = random_batch(&l, 4, 16, 3, 1.0, vec![false; 64]);
    let before = values(ppo.save_state().unwrap().tensors);
    ppo.update(&batch).unwrap();
    assert_ne!(before, values(ppo.save_state().unwrap().tensors));
}

/// `ppo.reward_norm` scales as SB3's VecNormalize does over its envs, step by step.
/// The numbers: SB3's RunningMeanStd and `VecNormalize.step_wait` in numpy on the same
/// rewards (2 trajectories × 3 steps, γ 0.9, trajectory 0's episode ending at step 1):
/// scaled [[2.49953, -2.54471, 0.75376], [0.49991, 0.50894, -0.90451]], and after
/// them mean 0.183664, var 0.440024, count 6.0001, returns [0.5, -0.078].
#[test]
fn reward_norm_scales_as_vecnormalize() {
    let mut c = config(1, 8, 0.2);
    c.ppo.reward_norm = true;
    c.gamma = 0.9;
    crate::algo::validate(&c).unwrap();
    let l = c.env.layout();
    let done = vec![false, true, false, false, false, false];
    let mut batch = random_batch(&l, 2, 3, 5, 1.0, done);
    let r = [1.0f32, -2.0, 0.5, 0.2, 0.4, -0.6];
    // The scalar reward is the vector reward's sum: put it all in coordinate 0.
    batch.vector_reward = r.iter().flat_map(|&v| [v, 0.0]).collect();
    let mut n = Normalizers::new(&c.ppo, l.obs_dim, c.gamma);
    let got = n.rewards(&batch, 1).unwrap();
    let want = [
        2.499531, -2.544706, 0.753758, 0.4999063, 0.5089412, -0.9045096,
    ];
    for (g, w) in got.iter().zip(want) {
        assert!((g - w).abs() < 1e-5, "{got:?} against {want:?}");
    }
    let state = n.state().unwrap();
    let value = |name: &str| -> Vec<f64> {
        let t = &state.iter().find(|(k, _)| k == name).unwrap().1;
        t.to_vec1().unwrap()
    };
    assert!((value("ppo.reward_norm.mean")[0] - 0.1836636).abs() < 1e-6);
    assert!((value("ppo.reward_norm.var")[0] - 0.4400238).abs() < 1e-6);
    assert!((value("ppo.reward_norm.count")[0] - 6.0001).abs() < 1e-9);
    let returns = value("ppo.reward_norm.returns");
    assert!((returns[0] - 0.5).abs() < 1e-6 && (returns[1] + 0.078).abs() < 1e-6);
    // Restored into fresh normalisers, the next batch scales the same.
    let mut again = Normalizers::new(&c.ppo, l.obs_dim, c.gamma);
    again
        .restore(&|name| {
            state
                .iter()
                .find(|(k, _)| k == name)
                .map(|(_, t)| t.clone())
        })
        .unwrap();
    assert_eq!(
        again.rewards(&batch, 1).unwrap(),
        n.rewards(&batch, 1).unwrap()
    );
}

/// `ppo.env_reward` learns from the env's own reward, and refuses a batch without one.
#[test]
fn env_reward_is_the_batchs_or_refused() {
    let mut c = config(1, 8, 0.2);
    c.ppo.env_reward = true;
    crate::algo::validate(&c).unwrap();
    let l = c.env.layout();
    let mut batch = random_batch(&l, 2, 3, 5, 1.0, vec![false; 6]);
    let mut n = Normalizers::new(&c.ppo, l.obs_dim, c.gamma);
    let err = n.rewards(&batch, 1).unwrap_err().to_string();
    assert!(err.contains("no env reward"), "{err}");
    batch.env_reward = vec![-0.5, -0.25, 0.0, 1.0, 2.0, 3.0];
    assert_eq!(n.rewards(&batch, 1).unwrap(), batch.env_reward);
    c.ppo.vector = true;
    let err = crate::algo::validate(&c).unwrap_err().to_string();
    assert!(err.contains("ppo.env_reward"), "{err}");
}

/// With `ppo.obs_norm` the weights carry the statistics of the observations seen so
/// far, the update reads observations normalised by those the actors acted with, the
/// acting policy normalises by them, and a checkpoint carries them on exactly.
#[test]
fn obs_norm_travels_with_the_weights_and_the_checkpoint() {
    let mut c = config(2, 16, 0.2);
    c.ppo.obs_norm = true;
    crate::algo::validate(&c).unwrap();
    let mut ppo = Ppo::new(&c, &Device::Cpu).unwrap();
    let find =
        |t: &[NamedTensor], name: &str| t.iter().find(|x| x.name == name).unwrap().data.clone();
    let start = ppo.policy_tensors().unwrap();
    assert_eq!(find(&start, crate::nets::obs_norm::OBS_MEAN), vec![0.0; 2]);
    // Shift and scale the observations so that normalising matters: entry 0 around 3,
    // entry 1 spread ×5.
    let mut batch = on_policy_batch(&ppo, 1);
    for row in batch.obs.chunks_exact_mut(2) {
        row[0] += 3.0;
        row[1] *= 5.0;
    }
    ppo.update(&batch).unwrap();
    let after = ppo.policy_tensors().unwrap();
    let (mean, std) = (
        find(&after, crate::nets::obs_norm::OBS_MEAN),
        find(&after, crate::nets::obs_norm::OBS_STD),
    );
    let col = |j: usize| {
        batch
            .obs
            .iter()
            .skip(j)
            .step_by(2)
            .map(|&v| v as f64)
            .collect::<Vec<_>>()
    };
    for j in 0..2 {
        let v = col(j);
        let m = v.iter().sum::<f64>() / v.len() as f64;
        let s = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
        assert!(
            (mean[j] as f64 - m).abs() < 1e-3 * m.abs().max(1.0),
            "{mean:?} against {m}"
        );
        assert!((std[j] as f64 - s).abs() < 1e-3 * s, "{std:?} against {s}");
    }
    // The acting policy's mean is the agent's on the normalised observation.
    let weights = std::sync::Arc::new(crate::link::PolicyWeights {
        version: 1,
        tensors: after.clone(),
    });
    let mut policy = crate::nets::Policy::new(weights, ppo.layout, c.head).unwrap();
    let o = [2.5f32, -4.0];
    let mut got = Vec::new();
    policy.mean(&o, &mut got);
    let normed: Vec<f32> = o
        .iter()
        .zip(&mean)
        .zip(&std)
        .map(|((o, m), s)| (o - m) / s)
        .collect();
    let out = ppo
        .agent
        .forward(&Tensor::from_slice(&normed, (1, 2), &Device::Cpu).unwrap())
        .unwrap();
    let want: Vec<f32> = out.mu.flatten_all().unwrap().to_vec1().unwrap();
    for (g, w) in got.iter().zip(&want) {
        assert!((g - w).abs() < 1e-5, "{got:?} against {want:?}");
    }
    // Resumed from its state, a run takes the next update exactly as one that went on.
    let saved = ppo.save_state().unwrap();
    let mut resumed = Ppo::new(&c, &Device::Cpu).unwrap();
    resumed
        .restore_state(&|n| saved.get(n), &saved.numbers)
        .unwrap();
    let next = on_policy_batch(&ppo, 2);
    ppo.update(&next).unwrap();
    resumed.update(&next).unwrap();
    assert_eq!(
        ppo.policy_tensors().unwrap(),
        resumed.policy_tensors().unwrap()
    );
}
