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
    let agent = Agent::new(&l, config.head, with_value, &mut rng, &Device::Cpu).unwrap();
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
