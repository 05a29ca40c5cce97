//! `saver.obs_norm`: the agent and critics read normalised observations, the PCPN raw
//! ones, and the statistics travel with the weights and the checkpoint.

use crate::algo::tests::{random_batch, random_pcpn};
use crate::algo::{Algorithm, Saver};
use crate::config::{Algo, ObsNorm};
use crate::env::{EnvKind, EnvSpec};
use crate::nets::obs_norm::{OBS_MEAN, OBS_STD};
use crate::rollout::Batch;
use candle_core::{DType, Device};
use saver_proto::NamedTensor;

fn saver(obs_norm: ObsNorm) -> (Saver, Batch) {
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
    config.saver.obs_norm = obs_norm;
    let pcpn = random_pcpn(&spec.layout(), DType::F32);
    let batch = random_batch(&spec.layout(), 4, 6, 9, 1.0, vec![false; 24]);
    (Saver::new(&config, pcpn, &Device::Cpu).unwrap(), batch)
}

fn find(t: &[NamedTensor], name: &str) -> Option<Vec<f32>> {
    t.iter().find(|x| x.name == name).map(|x| x.data.clone())
}

fn agent_bits(s: &Saver) -> Vec<u32> {
    let mut bits = Vec::new();
    for t in s.policy_tensors().unwrap() {
        if t.name.starts_with("agent.obs_") {
            continue;
        }
        bits.extend(t.data.iter().map(|v| v.to_bits()));
    }
    bits
}

/// The running statistics start from the declared range (mean its midpoint, variance
/// its half-width squared, counted as `PRIOR_COUNT` observations), so the first update
/// reads what the fixed `bounds` scale reads and takes its step, bit for bit. The batch
/// (entry 0 shifted by 3, entry 1 spread ×5) then joins them by Chan's formula, which
/// the weights carry; the second update reads them and so differs from `bounds`'; a
/// checkpoint gives a fresh learner the same statistics and one without them is refused.
#[test]
fn the_statistics_the_actors_acted_with_are_the_ones_the_update_reads() {
    let (mut on, mut batch) = saver(ObsNorm::Running);
    let (mut fixed, _) = saver(ObsNorm::Bounds);
    let (off, _) = saver(ObsNorm::Off);
    let o = on.layout.obs_dim;
    for row in batch.obs.chunks_exact_mut(o) {
        row[0] += 3.0;
        row[1] *= 5.0;
    }
    let carried = |s: &Saver| {
        let t = s.policy_tensors().unwrap();
        (find(&t, OBS_MEAN).unwrap(), find(&t, OBS_STD).unwrap())
    };
    assert_eq!(carried(&on), carried(&fixed));
    assert_eq!(find(&off.policy_tensors().unwrap(), OBS_MEAN), None);
    on.update(&batch).unwrap();
    fixed.update(&batch).unwrap();
    assert_eq!(agent_bits(&on), agent_bits(&fixed));
    let (mean, std) = carried(&on);
    let bounds = EnvSpec::new(EnvKind::Angle, 2).unwrap().bounds();
    let n0 = super::obs_scale::PRIOR_COUNT;
    for j in 0..o {
        let (lo, hi) = (bounds.obs_low[j] as f64, bounds.obs_high[j] as f64);
        let (mid, half) = ((lo + hi) / 2.0, (hi - lo) / 2.0);
        let col: Vec<f64> = batch
            .obs
            .iter()
            .skip(j)
            .step_by(o)
            .map(|&v| v as f64)
            .collect();
        let n = col.len() as f64;
        let m = col.iter().sum::<f64>() / n;
        let v = col.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n;
        let total = n0 + n;
        let want_mean = (n0 * mid + n * m) / total;
        let want_var = (n0 * half * half + n * v + (m - mid).powi(2) * n0 * n / total) / total;
        assert!(
            (mean[j] as f64 - want_mean).abs() < 1e-6,
            "{mean:?} vs {want_mean}"
        );
        let want_std = (want_var + 1e-8).sqrt();
        assert!(
            (std[j] as f64 - want_std).abs() < 1e-6,
            "{std:?} vs {want_std}"
        );
    }
    // Entry 0's mean moved by 24·3/10,024 ≈ 0.007 from its midpoint.
    assert!(mean[0] > 0.005, "{mean:?}");
    on.update(&batch).unwrap();
    fixed.update(&batch).unwrap();
    assert_ne!(agent_bits(&on), agent_bits(&fixed));
    let saved = on.save_state().unwrap();
    let (mut fresh, _) = saver(ObsNorm::Running);
    fresh
        .restore_state(&|name: &str| saved.get(name), &saved.numbers)
        .unwrap();
    assert_eq!(carried(&fresh), carried(&on));
    let plain = off.save_state().unwrap();
    let (mut strict, _) = saver(ObsNorm::Running);
    let err = strict
        .restore_state(&|name: &str| plain.get(name), &plain.numbers)
        .unwrap_err()
        .to_string();
    assert!(err.contains("saver.obs_norm"), "{err}");
}

/// `bounds`: the weights carry the declared range's midpoints and half-widths (on angle
/// d = 2, [−1, 1] for the position and goal entries: mean 0, scale 1, and the angles'
/// own ranges), the same after an update, and the checkpoint holds nothing of them.
#[test]
fn the_bounds_scale_is_the_declared_range_for_the_whole_run() {
    let (mut s, batch) = saver(ObsNorm::Bounds);
    let bounds = EnvSpec::new(EnvKind::Angle, 2).unwrap().bounds();
    let pairs = bounds.obs_low.iter().zip(&bounds.obs_high);
    let mean: Vec<f32> = pairs.clone().map(|(l, h)| (l + h) / 2.0).collect();
    let std: Vec<f32> = pairs.map(|(l, h)| (h - l) / 2.0).collect();
    let carried = |s: &Saver| {
        let t = s.policy_tensors().unwrap();
        (find(&t, OBS_MEAN).unwrap(), find(&t, OBS_STD).unwrap())
    };
    assert_eq!(carried(&s), (mean.clone(), std.clone()));
    s.update(&batch).unwrap();
    assert_eq!(carried(&s), (mean, std));
    let state = s.save_state().unwrap();
    assert!(state
        .tensors
        .iter()
        .all(|(n, _)| !n.starts_with("saver.obs_norm")));
}
