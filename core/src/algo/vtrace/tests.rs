use crate::algo::tests::{random_batch, random_pcpn};
use crate::algo::{A2c, Algorithm, Saver};
use crate::config::{Algo, RunConfig};
use crate::env::{EnvKind, EnvSpec};
use crate::nets::Agent;
use crate::rng::{rng_for, streams};
use crate::rollout::Batch;
use candle_core::{DType, Device, Tensor};

/// A batch of 4 trajectories × 8 steps on `spec` whose payload is the policy of a fresh
/// learner of `config` (its agent rebuilt from the same seed and stream), its means
/// moved by `shift`: 0 is on-policy, as a sync actor records it.
fn batch(config: &RunConfig, shift: f32) -> Batch {
    let l = config.env.layout();
    let mut rng = rng_for(config.seed, streams::INIT);
    let with_value = config.algo == Algo::A2c;
    let agent = Agent::new(
        &l,
        config.head,
        &config.hidden,
        with_value,
        &mut rng,
        &Device::Cpu,
    )
    .unwrap();
    let done = (0..32).map(|i| i % 11 == 10).collect();
    let mut b = random_batch(&l, 4, 8, 9, 0.8, done);
    let obs = Tensor::from_slice(&b.obs, (32, l.obs_dim), &Device::Cpu).unwrap();
    let out = agent.forward(&obs).unwrap();
    let mu: Vec<Vec<f32>> = out.mu.to_vec2().unwrap();
    let ls: Vec<Vec<f32>> = out.log_std.to_vec2().unwrap();
    b.payload = mu
        .iter()
        .zip(&ls)
        .flat_map(|(m, s)| m.iter().map(|x| x + shift).chain(s.iter().copied()))
        .collect();
    b
}

fn learner(config: &RunConfig) -> Box<dyn Algorithm> {
    match config.algo {
        Algo::A2c => Box::new(A2c::new(config, &Device::Cpu).unwrap()),
        _ => Box::new(
            Saver::new(
                config,
                random_pcpn(&config.env.layout(), DType::F32),
                &Device::Cpu,
            )
            .unwrap(),
        ),
    }
}

fn weights(a: &dyn Algorithm) -> Vec<f32> {
    a.save_state()
        .unwrap()
        .tensors
        .iter()
        .filter(|(n, _)| !n.starts_with("opt."))
        .flat_map(|(_, t)| t.flatten_all().unwrap().to_vec1::<f32>().unwrap())
        .collect()
}

/// On-policy (the payload is the learner's own policy) every ratio is 1 and V-trace is
/// the plain update up to rounding (its targets sum the same terms in another order);
/// off-policy (the behaviour means moved by 0.3) the ratios spread, ρ̄ = 1 clips some,
/// and the update differs. A2C on angle d = 2 and SAVER on select d = 3.
#[test]
fn vtrace_is_the_plain_update_on_policy_and_corrects_off_policy() {
    let a2c = RunConfig::paper(&EnvSpec::new(EnvKind::Angle, 2).unwrap(), Algo::A2c, 1);
    let saver =
        crate::algo::recommended(&EnvSpec::new(EnvKind::Select, 3).unwrap(), Algo::Saver, 1);
    for plain in [a2c, saver] {
        let corrected = RunConfig {
            vtrace: true,
            ..plain.clone()
        };
        crate::algo::validate(&corrected).unwrap();
        let (on, off) = (batch(&plain, 0.0), batch(&plain, 0.3));
        let mut p = learner(&plain);
        let mut c = learner(&corrected);
        assert!(c.stat_names().ends_with(&super::VTRACE_STATS));
        p.update(&on).unwrap();
        let s = c.update(&on).unwrap();
        assert_eq!(s.get("vtrace_ratio_mean"), Some(1.0), "{:?}", plain.algo);
        assert_eq!(s.get("vtrace_ratio_max"), Some(1.0));
        assert_eq!(s.get("vtrace_clipped"), Some(0.0));
        let (wp, wc) = (weights(p.as_ref()), weights(c.as_ref()));
        let worst = wp
            .iter()
            .zip(&wc)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(
            worst < 1e-5,
            "{:?}: on-policy V-trace moved a weight by {worst}",
            plain.algo
        );
        // Off-policy: one update from the same start on the shifted batch.
        let (mut p, mut c) = (learner(&plain), learner(&corrected));
        let w0 = weights(p.as_ref());
        p.update(&off).unwrap();
        let s = c.update(&off).unwrap();
        let (mean, max, clipped) = (
            s.get("vtrace_ratio_mean").unwrap(),
            s.get("vtrace_ratio_max").unwrap(),
            s.get("vtrace_clipped").unwrap(),
        );
        eprintln!(
            "{:?} off-policy: ratio mean {mean} max {max} clipped {clipped}",
            plain.algo
        );
        assert!(max > 1.0 && clipped > 0.0 && clipped < 1.0, "{s:?}");
        // The two updates' steps from the same weights differ by a good share of a step.
        let (wp, wc) = (weights(p.as_ref()), weights(c.as_ref()));
        let norm = |x: &mut dyn Iterator<Item = f32>| x.map(|v| v * v).sum::<f32>().sqrt();
        let step = norm(&mut wp.iter().zip(&w0).map(|(a, b)| a - b));
        let apart = norm(&mut wp.iter().zip(&wc).map(|(a, b)| a - b));
        eprintln!("{:?} off-policy: steps {step} apart by {apart}", plain.algo);
        assert!(
            apart > 0.1 * step,
            "{:?}: the correction changed little",
            plain.algo
        );
    }
}

/// PPO and QRRL refuse V-trace with the reason.
#[test]
fn vtrace_is_refused_where_it_does_not_apply() {
    let env = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    for (algo, why) in [(Algo::Ppo, "π/π_old"), (Algo::Qrrl, "no density")] {
        let mut c = crate::algo::recommended(&env, algo, 1);
        c.vtrace = true;
        let e = crate::algo::validate(&c).unwrap_err().to_string();
        assert!(e.contains("vtrace") && e.contains(why), "{e}");
    }
}

/// A one-step batch on `layout` with action `a` and the behaviour's payload `then`.
fn one_step(layout: &crate::env::EnvLayout, a: &[f32], then: &[f32]) -> Batch {
    let mut b = random_batch(layout, 1, 1, 1, 0.8, vec![false]);
    b.actions = a.to_vec();
    b.payload = then.to_vec();
    b
}

/// Per-coordinate log ratios by hand. The behaviour is μ = 0, σ = 1 (logits 0) and the
/// step taken a_0 = 0.5, so the step's factor is log N(0.5; 0.5, 1) − log N(0.5; 0, 1)
/// = 0.125.
/// - select d = 3, choice 1, the learner's logits (ln 3, 0, ln 2): p' = (1/2, 1/6, 1/3)
///   against 1/3 each. Chosen coordinate 1: 0.125 + ln((1/6)/(1/3)) = 0.125 − ln 2 =
///   −0.5681472; coordinate 0: ln((1 − 1/2)/(2/3)) = ln 0.75 = −0.2876821; coordinate 2:
///   ln((2/3)/(2/3)) = 0. Shared: −0.5681472 for all three.
/// - angle d = 4, a = (0.5, 0, 0, 1), the learner's μ' = (0.5, 0, 0, 0) and log σ' =
///   (0, 0, ln 2, 0): factors 0.125, 0, −ln 2 (a = 0 under σ' = 2: −ln 2 + 0) and 0.
///   Pairs: (0.125, 0.125, −0.6931472, −0.6931472); own entry: (0.125, 0, −0.6931472,
///   0); shared: −0.5681472.
#[test]
fn per_coordinate_ratios_by_hand() {
    use super::coordinate_log_ratios;
    use crate::env::Routing;
    let close = |got: Vec<f32>, want: &[f32], what: &str| {
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{what}: {got:?} against {want:?}");
        }
        assert_eq!(got.len(), want.len(), "{what}");
    };
    let select = EnvSpec::new(EnvKind::Select, 3).unwrap().layout();
    let b = one_step(&select, &[0.5, 0., 1., 0.], &[0., 0., 0., 0., 0.]);
    let mu = [0.5, 3f32.ln(), 0., 2f32.ln()];
    let got = |r| coordinate_log_ratios(r, &select, &b, &mu, &[0.]).unwrap();
    close(
        got(Routing::Choice),
        &[-0.2876821, -0.5681472, 0.],
        "choice",
    );
    close(got(Routing::Shared), &[-0.5681472; 3], "select shared");
    let angle = EnvSpec::new(EnvKind::Angle, 4).unwrap().layout();
    let b = one_step(&angle, &[0.5, 0., 0., 1.], &[0.; 8]);
    let (mu, ls) = ([0.5, 0., 0., 0.], [0., 0., 2f32.ln(), 0.]);
    let got = |r| coordinate_log_ratios(r, &angle, &b, &mu, &ls).unwrap();
    let ln2 = std::f32::consts::LN_2;
    close(got(Routing::Pairs), &[0.125, 0.125, -ln2, -ln2], "pairs");
    close(got(Routing::Own), &[0.125, 0., -ln2, 0.], "own");
    close(got(Routing::Shared), &[0.125 - ln2; 4], "angle shared");
    // A routing that does not fit the layout is an error, not a panic.
    let e = coordinate_log_ratios(Routing::Choice, &angle, &b, &mu, &ls).unwrap_err();
    assert!(e.to_string().contains("does not fit"), "{e}");
}

/// The shared routing's ratio is the learner's `shared_log_ratios` (candle's log-prob of
/// the whole action against the payload's), on random select and angle batches.
#[test]
fn the_shared_routing_is_the_whole_actions_ratio() {
    use super::{coordinate_log_ratios, shared_log_ratios};
    for spec in [
        EnvSpec::new(EnvKind::Select, 3).unwrap(),
        EnvSpec::new(EnvKind::Angle, 4).unwrap(),
    ] {
        let config = crate::algo::recommended(&spec, Algo::Saver, 1);
        let (l, b) = (spec.layout(), batch(&config, 0.3));
        let (m, c) = (l.mu_dim(), l.continuous);
        let rows = b.len();
        let now = batch(&config, 0.0).payload;
        let (mu, ls): (Vec<f32>, Vec<f32>) = (
            now.chunks(m + c).flat_map(|r| r[..m].to_vec()).collect(),
            now.chunks(m + c).flat_map(|r| r[m..].to_vec()).collect(),
        );
        let t = |v: &[f32], w| Tensor::from_slice(v, (rows, w), &Device::Cpu).unwrap();
        let actions = t(&b.actions, l.action_dim());
        let log_pi = crate::nets::gaussian_log_prob(&l, &t(&mu, m), &t(&ls, c), &actions)
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let want = shared_log_ratios(&l, &b, &log_pi, &Device::Cpu).unwrap();
        let got = coordinate_log_ratios(crate::env::Routing::Shared, &l, &b, &mu, &ls).unwrap();
        let d = l.aligned_dim;
        for (i, w) in want.iter().enumerate() {
            for g in &got[i * d..(i + 1) * d] {
                assert!(
                    (g - w).abs() < 1e-4 * w.abs().max(1.0),
                    "{spec:?} step {i}: {g} against {w}"
                );
            }
        }
        assert!(
            want.iter().any(|w| w.abs() > 0.1),
            "the batch is off-policy"
        );
    }
}
