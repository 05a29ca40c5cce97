//! The predicted target and the signal statistics (signal.rs): the predicted
//! target makes SAVER's update blind to an error in the observed change, the observed
//! one does not, and the statistics tell the two cases apart.

use super::signal::{noise_ranks, normal_cdf, predicted_delta, rank_stats, SignalBatch};
use crate::algo::tests::{random_batch, random_pcpn, uniform};
use crate::algo::*;
use crate::config::{Algo, DeltaTarget, RunConfig};
use crate::env::{EnvKind, EnvSpec};
use crate::rng::rng_for;
use crate::rollout::Batch;
use candle_core::{DType, Device};

/// A batch of 8 trajectories × 8 steps of random rows, some actions beyond ±1.
fn batch(spec: &EnvSpec) -> Batch {
    random_batch(
        &spec.layout(),
        8,
        8,
        7,
        1.2,
        (0..64).map(|i| i % 13 == 12).collect(),
    )
}

fn agent_after_one_update(config: &RunConfig, batch: &Batch) -> Vec<f32> {
    let pcpn = random_pcpn(&config.env.layout(), DType::F32);
    let mut saver = Saver::new(config, pcpn, &Device::Cpu).unwrap();
    saver.update(batch).unwrap();
    let state = saver.save_state().unwrap();
    let mu_w = state
        .tensors
        .iter()
        .find(|(n, _)| n == "agent.mu.w")
        .unwrap();
    mu_w.1.flatten_all().unwrap().to_vec1().unwrap()
}

/// An error in the observed Δp (a drift the PCPN got wrong, here +0.05 on every
/// coordinate) moves the observed-target update and leaves the predicted-target update
/// bit for bit where it was: only the action taken and the PCPN define its target.
#[test]
fn the_predicted_target_does_not_see_an_error_in_the_observed_change() {
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let clean = batch(&spec);
    let mut shifted = clean.clone();
    shifted.state_delta.iter_mut().for_each(|v| *v += 0.05);
    let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
    config.saver.target = DeltaTarget::Observed;
    assert_ne!(
        agent_after_one_update(&config, &clean),
        agent_after_one_update(&config, &shifted)
    );
    config.saver.target = DeltaTarget::Predicted;
    assert_eq!(
        agent_after_one_update(&config, &clean),
        agent_after_one_update(&config, &shifted)
    );
    // The noise-rank target depends on the actions' noise and the PCPN alone too, and
    // its update differs from the predicted target's.
    let predicted = agent_after_one_update(&config, &clean);
    config.saver.target = DeltaTarget::Noise;
    let noise = agent_after_one_update(&config, &clean);
    assert_eq!(noise, agent_after_one_update(&config, &shifted));
    assert_ne!(noise, predicted);
}

/// Φ at a few points (tables: Φ(1) = 0.841345, Φ(−1.96) = 0.024998, Φ(3) = 0.998650).
#[test]
fn normal_cdf_matches_the_tables() {
    for (z, want) in [
        (0.0, 0.5),
        (1.0, 0.841_345),
        (-1.96, 0.024_998),
        (3.0, 0.998_650),
    ] {
        assert!(
            (normal_cdf(z) - want).abs() < 2e-6,
            "{z}: {}",
            normal_cdf(z)
        );
    }
}

/// The noise ranks follow the noise: mirroring every action about its mean (a → 2μ − a)
/// mirrors each rank (τ* → 1 − τ*), an action at its mean has rank ½, and a step whose
/// noise moves coordinate j up under the PCPN (its slopes' direction) ranks above ½.
#[test]
fn noise_ranks_follow_the_action_noise() {
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let l = spec.layout();
    let pcpn = random_pcpn(&l, DType::F32);
    let b = batch(&spec);
    let rows = b.len();
    let mut rng = rng_for(9, 2);
    let mu = uniform(&mut rng, rows * l.mu_dim(), -0.8, 0.8);
    let log_std = vec![-1.0f32; rows * l.log_std_dim()];
    let advantage = vec![0.0f32; rows * l.aligned_dim];
    let mirrored: Vec<f32> = b
        .actions
        .iter()
        .zip(&mu)
        .map(|(a, m)| 2.0 * m - a)
        .collect();
    let ranks = |actions: &[f32]| {
        let s = SignalBatch {
            obs: &b.obs,
            mu: &mu,
            log_std: &log_std,
            actions,
            state_delta: &b.state_delta,
            advantage: &advantage,
            dmu: None,
        };
        let x = s
            .inputs(&l, &(0..rows).collect::<Vec<_>>(), false, &Device::Cpu)
            .unwrap();
        noise_ranks(&pcpn, &l, &s, &x).unwrap()
    };
    let (r, m) = (ranks(&b.actions), ranks(&mirrored));
    let mut spread = 0.0f32;
    for (x, y) in r.iter().zip(&m) {
        assert!((x + y - 1.0).abs() < 1e-5, "{x} {y}");
        spread = spread.max((x - 0.5).abs());
    }
    assert!(spread > 0.3, "the ranks hardly move: {spread}");
    assert!(ranks(&mu).iter().all(|&x| (x - 0.5).abs() < 1e-6));
}

/// With the observed change equal to the prediction, the observed and predicted ranks
/// agree (correlation 1) and the PCPN's error is 0; with a large error added to every
/// row, the ranks no longer follow the action (correlation below 0.5) and the error
/// ratio exceeds 1.
#[test]
fn signal_stats_tell_an_exact_pcpn_from_one_whose_error_swamps_the_action() {
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let l = spec.layout();
    let pcpn = random_pcpn(&l, DType::F32);
    let mut b = batch(&spec);
    let rows = b.len();
    let dev = Device::Cpu;
    let mut rng = rng_for(9, 1);
    let mu = uniform(&mut rng, rows * l.mu_dim(), -1.0, 1.0);
    let log_std = vec![-1.0f32; rows * l.log_std_dim()];
    let advantage = uniform(&mut rng, rows * l.aligned_dim, -1.0, 1.0);
    fn signal<'a>(
        b: &'a Batch,
        mu: &'a [f32],
        log_std: &'a [f32],
        advantage: &'a [f32],
    ) -> SignalBatch<'a> {
        SignalBatch {
            obs: &b.obs,
            mu,
            log_std,
            actions: &b.actions,
            state_delta: &b.state_delta,
            advantage,
            dmu: None,
        }
    }
    b.state_delta =
        predicted_delta(&pcpn, &l, &signal(&b, &mu, &log_std, &advantage), &dev).unwrap();
    let stats =
        |b: &Batch| rank_stats(&pcpn, &l, &signal(b, &mu, &log_std, &advantage), &dev).unwrap();
    let get =
        |s: &[(&str, Vec<f32>)], name: &str| s.iter().find(|(n, _)| *n == name).unwrap().1.clone();
    let exact = stats(&b);
    for j in 0..l.aligned_dim {
        assert!(
            (get(&exact, "rank_corr")[j] - 1.0).abs() < 1e-6,
            "{exact:?}"
        );
        assert_eq!(get(&exact, "err_ratio")[j], 0.0, "{exact:?}");
    }
    let spread = b.state_delta.iter().fold(0f32, |m, v| m.max(v.abs()));
    let noise = uniform(
        &mut rng,
        b.state_delta.len(),
        -100.0 * spread,
        100.0 * spread,
    );
    b.state_delta
        .iter_mut()
        .zip(noise)
        .for_each(|(v, e)| *v += e);
    let swamped = stats(&b);
    for j in 0..l.aligned_dim {
        assert!(get(&swamped, "rank_corr")[j] < 0.5, "{swamped:?}");
        assert!(get(&swamped, "err_ratio")[j] > 1.0, "{swamped:?}");
    }
}

#[test]
fn the_predicted_target_is_refused_for_an_env_with_a_choice() {
    let spec = EnvSpec::new(EnvKind::Select, 2).unwrap();
    let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
    for target in [DeltaTarget::Predicted, DeltaTarget::Noise] {
        config.saver.target = target;
        let err = crate::algo::validate(&config).unwrap_err().to_string();
        assert!(err.contains("saver.target"), "{err}");
    }
}
