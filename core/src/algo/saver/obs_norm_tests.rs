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

/// Fresh weights carry mean 0 and std √(1 + 1e-8) = 1 in f32, so the first update reads
/// the raw observations (all within ±10 here) and takes the step of a run without the
/// option, bit for bit. The weights then carry the batch's moments (entry 0 is shifted
/// by 3 and entry 1 spread ×5 so that they matter), the second update reads the
/// observations normalised by them and so differs from the run without, and a
/// checkpoint gives a fresh learner the same statistics (one without them is refused).
#[test]
fn the_statistics_the_actors_acted_with_are_the_ones_the_update_reads() {
    let (mut on, mut batch) = saver(ObsNorm::Running);
    let (mut off, _) = saver(ObsNorm::Off);
    let o = on.layout.obs_dim;
    for row in batch.obs.chunks_exact_mut(o) {
        row[0] += 3.0;
        row[1] *= 5.0;
    }
    assert!(batch.obs.iter().all(|v| v.abs() < 10.0));
    let start = on.policy_tensors().unwrap();
    assert_eq!(find(&start, OBS_MEAN), Some(vec![0.0; o]));
    assert_eq!(find(&start, OBS_STD), Some(vec![1.0; o]));
    assert_eq!(find(&off.policy_tensors().unwrap(), OBS_MEAN), None);
    on.update(&batch).unwrap();
    off.update(&batch).unwrap();
    assert_eq!(agent_bits(&on), agent_bits(&off));
    let after = on.policy_tensors().unwrap();
    let (mean, std) = (
        find(&after, OBS_MEAN).unwrap(),
        find(&after, OBS_STD).unwrap(),
    );
    for j in 0..o {
        let col: Vec<f64> = batch
            .obs
            .iter()
            .skip(j)
            .step_by(o)
            .map(|&v| v as f64)
            .collect();
        let m = col.iter().sum::<f64>() / col.len() as f64;
        let s = (col.iter().map(|x| (x - m).powi(2)).sum::<f64>() / col.len() as f64).sqrt();
        // The starting count (1e-4 at mean 0, variance 1) pulls each by ~1e-4 / 24.
        assert!(
            (mean[j] as f64 - m).abs() < 1e-3 * m.abs().max(1.0),
            "{mean:?} vs {m}"
        );
        assert!(
            (std[j] as f64 - s).abs() < 1e-3 * s.max(0.1),
            "{std:?} vs {s}"
        );
    }
    assert!((mean[0] - 3.0).abs() < 1.0, "{mean:?}");
    on.update(&batch).unwrap();
    off.update(&batch).unwrap();
    assert_ne!(agent_bits(&on), agent_bits(&off));
    let saved = on.save_state().unwrap();
    let (mut fresh, _) = saver(ObsNorm::Running);
    fresh
        .restore_state(&|name: &str| saved.get(name), &saved.numbers)
        .unwrap();
    let weights = |s: &Saver| {
        let t = s.policy_tensors().unwrap();
        (find(&t, OBS_MEAN), find(&t, OBS_STD))
    };
    assert_eq!(weights(&fresh), weights(&on));
    // A checkpoint without them (a run without the option) is refused by name.
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
