//! `saver.obs_norm`: the agent and critics read normalised observations, the PCPN raw
//! ones, and the statistics travel with the weights and the checkpoint.

use crate::algo::tests::{plane_spec, random_batch, random_pcpn};
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

/// The plane (`plane_spec`) with entries within ±5 and its goal at `goal_start`.
fn plane(goal_start: Option<usize>) -> EnvSpec {
    plane_spec(5.0, goal_start)
}

/// SAVER on the plane with its goal at entries 4-5, reading the observations as `norm`.
fn plane_saver(norm: ObsNorm) -> Saver {
    let spec = plane(Some(4));
    let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
    config.saver.obs_norm = norm;
    Saver::new(
        &config,
        random_pcpn(&spec.layout(), DType::F32),
        &Device::Cpu,
    )
    .unwrap()
}

/// `aligned`: the position and the declared goal are scaled by their running moments,
/// every other entry travels as mean 0, scale 1 (read raw), while all entries' moments
/// are kept (the checkpoint holds the same statistics as `running`'s). Entries are
/// shifted and spread apart per column so that a wrong index shows: column j of the
/// batch is U(−1, 1)·(j + 1) + j, so its mean is ≈ j and its std ≈ (j + 1)/√3.
#[test]
fn aligned_scales_the_position_and_goal_alone() {
    use crate::algo::saver::obs_scale::aligned_entries;
    assert_eq!(aligned_entries(&plane(Some(4))), vec![0, 1, 4, 5]);
    // No goal in the observation (Reacher-v5: p is already relative to the target).
    assert_eq!(aligned_entries(&plane(None)), vec![0, 1]);
    // A goal that overlaps p adds nothing twice.
    assert_eq!(aligned_entries(&plane(Some(1))), vec![0, 1, 2]);
    let l = plane(Some(4)).layout();
    let mut s = plane_saver(ObsNorm::Aligned);
    let mut batch = random_batch(&l, 8, 64, 3, 1.0, vec![false; 512]);
    for row in batch.obs.chunks_exact_mut(6) {
        for (j, v) in row.iter_mut().enumerate() {
            *v = *v * (j + 1) as f32 + j as f32;
        }
    }
    s.update(&batch).unwrap();
    let t = s.policy_tensors().unwrap();
    let (mean, std) = (find(&t, OBS_MEAN).unwrap(), find(&t, OBS_STD).unwrap());
    for j in 0..6 {
        if [2, 3].contains(&j) {
            assert_eq!((mean[j], std[j]), (0.0, 1.0), "{j}");
            continue;
        }
        // 512 draws: the sample mean is within 4 standard errors of j.
        let (m, sd) = (j as f32, (j + 1) as f32 / 3f32.sqrt());
        assert!(
            (mean[j] - m).abs() < 4.0 * sd / 512f32.sqrt(),
            "{j}: {mean:?}"
        );
        assert!((std[j] - sd).abs() < 0.1 * sd, "{j}: {std:?}");
    }
    let saved = s.save_state().unwrap();
    let stored_mean = saved.get("saver.obs_norm.mean").unwrap();
    let stored: Vec<f64> = stored_mean.to_vec1().unwrap();
    assert!((stored[2] - 2.0).abs() < 0.3, "{stored:?}");
}

/// `auto`'s rule on spreads measured under random actions (`saver-actor check`, seed
/// 0): Reacher-v5's fingertip offset (entries 8-9) spreads 0.134 at most against its
/// second joint cosine's 0.75, a share of 0.179 < 1/3; the point mass's p (0.52) is
/// 6.5 times its speeds' 0.08, so not narrow; nothing outside p and g, or others that
/// never move, leave it raw.
#[test]
fn auto_calls_p_narrow_only_under_a_third_of_the_widest_other_entry() {
    use crate::algo::saver::obs_scale::narrow_position;
    let reacher = [
        0.681, 0.75, 0.624, 0.64, 0.0694, 0.105, 0.674, 0.712, 0.13, 0.134,
    ];
    let (ratio, k) = narrow_position(&reacher, &[8, 9], &[8, 9]).unwrap();
    assert_eq!(k, 1);
    assert!((ratio - 0.134 / 0.75).abs() < 1e-6, "{ratio}");
    let pointmass = [0.52, 0.52, 0.08, 0.07, 0.54, 0.55];
    assert_eq!(narrow_position(&pointmass, &[0, 1], &[0, 1, 4, 5]), None);
    // The same spreads with the speeds 10 times wider: 0.52 / 0.8 = 0.65, still not.
    let fast = [0.52, 0.52, 0.8, 0.7, 0.54, 0.55];
    assert_eq!(narrow_position(&fast, &[0, 1], &[0, 1, 4, 5]), None);
    // ... and 20 times wider: 0.52 / 1.6 = 0.325 < 1/3, narrow (against entry 2).
    let faster = [0.52, 0.52, 1.6, 1.4, 0.54, 0.55];
    assert_eq!(
        narrow_position(&faster, &[0, 1], &[0, 1, 4, 5]).map(|(_, k)| k),
        Some(2)
    );
    assert_eq!(narrow_position(&[0.1, 0.5], &[0, 1], &[0, 1]), None);
    assert_eq!(narrow_position(&[0.1, 0.0], &[0], &[0]), None);
}

/// `auto` on the plane's layout: fresh weights read raw; the first batch decides once.
/// With p spread 0.1× and the other entries 1× (column j is U(−1, 1)·scale + j), p's
/// std ≈ 0.058 against 0.58: the weights then carry the moments of p and g (entries
/// 0, 1, 4, 5) and raw for the speeds, as `aligned`'s do; with p wide they stay raw,
/// and a later batch with p narrow does not change that. The checkpoint keeps the
/// choice; one without it (an `aligned` run's) is refused by name.
#[test]
fn auto_reads_p_and_g_scaled_only_where_the_first_batch_finds_p_narrow() {
    let spec = plane(Some(4));
    let l = spec.layout();
    let batch = |p_scale: f32| {
        let mut b = random_batch(&l, 8, 64, 3, 1.0, vec![false; 512]);
        for row in b.obs.chunks_exact_mut(6) {
            for (j, v) in row.iter_mut().enumerate() {
                *v = *v * if j < 2 { p_scale } else { 1.0 } + j as f32;
            }
        }
        b
    };
    let carried = |s: &Saver| {
        let t = s.policy_tensors().unwrap();
        (find(&t, OBS_MEAN).unwrap(), find(&t, OBS_STD).unwrap())
    };
    let raw = (vec![0.0; 6], vec![1.0; 6]);
    let mut narrow = plane_saver(ObsNorm::Auto);
    assert_eq!(carried(&narrow), raw);
    narrow.update(&batch(0.1)).unwrap();
    let (mean, std) = carried(&narrow);
    let mut aligned = plane_saver(ObsNorm::Aligned);
    aligned.update(&batch(0.1)).unwrap();
    assert_eq!((mean.clone(), std.clone()), carried(&aligned));
    assert!((std[0] - 0.1 / 3f32.sqrt()).abs() < 0.01, "{std:?}");
    assert!((mean[4] - 4.0).abs() < 0.2, "{mean:?}");
    assert_eq!((mean[2], std[2]), (0.0, 1.0));
    let mut wide = plane_saver(ObsNorm::Auto);
    wide.update(&batch(1.0)).unwrap();
    wide.update(&batch(0.1)).unwrap();
    assert_eq!(carried(&wide), raw);
    for s in [&narrow, &wide] {
        let saved = s.save_state().unwrap();
        let mut fresh = plane_saver(ObsNorm::Auto);
        fresh
            .restore_state(&|name: &str| saved.get(name), &saved.numbers)
            .unwrap();
        assert_eq!(carried(&fresh), carried(s));
    }
    let plain = aligned.save_state().unwrap();
    let err = plane_saver(ObsNorm::Auto)
        .restore_state(&|name: &str| plain.get(name), &plain.numbers)
        .unwrap_err()
        .to_string();
    assert!(err.contains("saver.obs_norm.auto"), "{err}");
}

/// An entry `aligned` and `auto` read raw is read exactly as under `off`, however large:
/// on the plane with its speeds (entries 2, 3) near 50, far past the ±10 clip, `auto`
/// with p wide takes `off`'s updates bit for bit, its weights clip no entry (+∞ in
/// `agent.obs_clip`) and an acting policy built from them gives `off`'s μ on such an
/// observation. `aligned` clips p and g (±10) and passes the speeds (+∞).
#[test]
fn raw_entries_are_not_clipped() {
    use crate::nets::obs_norm::{OBS_BOUND, OBS_CLIP};
    let spec = plane(Some(4));
    let l = spec.layout();
    // Column j: U(−1, 1) + 50 for the speeds (spread 0.58, as p's), j elsewhere.
    let mut batch = random_batch(&l, 8, 64, 3, 1.0, vec![false; 512]);
    for row in batch.obs.chunks_exact_mut(6) {
        for (j, v) in row.iter_mut().enumerate() {
            *v += if [2, 3].contains(&j) { 50.0 } else { j as f32 };
        }
    }
    let (mut auto, mut off, mut aligned) = (
        plane_saver(ObsNorm::Auto),
        plane_saver(ObsNorm::Off),
        plane_saver(ObsNorm::Aligned),
    );
    for _ in 0..2 {
        for s in [&mut auto, &mut off, &mut aligned] {
            s.update(&batch).unwrap();
        }
    }
    assert!(
        agent_bits(&auto) == agent_bits(&off),
        "auto with p wide updates otherwise than off"
    );
    let t = auto.policy_tensors().unwrap();
    assert_eq!(find(&t, OBS_BOUND), Some(vec![f32::INFINITY; 6]));
    let bound = find(&aligned.policy_tensors().unwrap(), OBS_BOUND).unwrap();
    let inf = f32::INFINITY;
    assert_eq!(bound, [OBS_CLIP, OBS_CLIP, inf, inf, OBS_CLIP, OBS_CLIP]);
    let head = crate::algo::recommended(&spec, Algo::Saver, 1).head;
    let policy = |s: &Saver| {
        let w = crate::acting::PolicyWeights {
            version: 1,
            tensors: s.policy_tensors().unwrap(),
        };
        crate::nets::Policy::new(std::sync::Arc::new(w), l, head).unwrap()
    };
    let obs = [0.3, -0.2, 55.0, -48.0, 4.0, 5.0];
    let (mut a, mut b) = (Vec::new(), Vec::new());
    policy(&auto).mean(&obs, &mut a);
    policy(&off).mean(&obs, &mut b);
    assert_eq!(a, b);
}
