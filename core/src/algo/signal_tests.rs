//! The predicted target and the signal statistics (saver_signal.rs): the predicted
//! target makes SAVER's update blind to an error in the observed change, the observed
//! one does not, and the statistics tell the two cases apart.

use super::saver_signal::{predicted_delta, rank_stats, SignalBatch};
use super::tests::{random_batch, random_pcpn, uniform};
use super::*;
use crate::config::{Algo, DeltaTarget, RunConfig};
use crate::env::{EnvKind, EnvSpec};
use crate::rng::rng_for;
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
    config.saver.target = DeltaTarget::Predicted;
    let err = crate::algo::validate(&config).unwrap_err().to_string();
    assert!(err.contains("saver.target"), "{err}");
}
