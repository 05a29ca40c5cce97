//! Observation normalisation, as Stable-Baselines3's `VecNormalize` does it: a running
//! mean and variance of every observation entry, and x = clip((o − mean)/√(var + 1e-8),
//! ±10) in front of the policy. The learner keeps the statistics (PPO's
//! `ppo.obs_norm`); they travel with the policy's weights as [`OBS_MEAN`] and
//! [`OBS_STD`], so every client that acts from the weights (the Rust actors, the
//! Python package, `saver eval`) normalises alike. Weights that scale some entries and
//! leave others raw (SAVER's `aligned` and `auto`) carry [`OBS_BOUND`] too: each entry's
//! own clip, +∞ for an entry read as it is, so a raw entry beyond ±10 is not cut.

use crate::{CoreError, Result};
use candle_core::{DType, Device, Tensor};
use saver_proto::NamedTensor;

/// The weights' tensor of the observation mean, [obs_dim].
pub const OBS_MEAN: &str = "agent.obs_mean";
/// The weights' tensor of √(var + 1e-8), [obs_dim].
pub const OBS_STD: &str = "agent.obs_std";
/// The weights' optional tensor of each entry's clip, [obs_dim], every value > 0 (+∞: not
/// clipped); without it every entry is clipped to ±[`OBS_CLIP`].
pub const OBS_BOUND: &str = "agent.obs_clip";
/// Normalised observations are clipped to ±this (SB3's `clip_obs`).
pub const OBS_CLIP: f32 = 10.0;
/// Added to the variance before the square root (SB3's `epsilon`).
const VAR_EPS: f64 = 1e-8;
/// The count the statistics start from (SB3's `RunningMeanStd(epsilon=1e-4)`), so the
/// first batch's moments take over almost entirely.
const COUNT0: f64 = 1e-4;

/// A running mean and variance per entry, merged batch by batch (Chan et al.'s
/// parallel formula, as SB3's `RunningMeanStd.update_from_moments`).
#[derive(Clone, Debug, PartialEq)]
pub struct RunningStats {
    /// Samples seen (starting at 1e-4).
    pub count: f64,
    /// Mean of each entry.
    pub mean: Vec<f64>,
    /// Population variance of each entry.
    pub var: Vec<f64>,
}

impl RunningStats {
    /// No samples yet: mean 0, variance 1 for `n` entries.
    pub fn new(n: usize) -> Self {
        Self {
            count: COUNT0,
            mean: vec![0.0; n],
            var: vec![1.0; n],
        }
    }

    /// Merges the rows of `rows` ([k, n] row-major, n = the entries) into the statistics.
    pub fn update(&mut self, rows: &[f32]) {
        let n = self.mean.len();
        let k = rows.len() / n.max(1);
        if k == 0 {
            return;
        }
        let kf = k as f64;
        for j in 0..n {
            let col = rows.iter().skip(j).step_by(n).map(|&v| v as f64);
            let batch_mean = col.clone().sum::<f64>() / kf;
            let batch_var = col.map(|v| (v - batch_mean).powi(2)).sum::<f64>() / kf;
            let total = self.count + kf;
            let delta = batch_mean - self.mean[j];
            let m2 =
                self.var[j] * self.count + batch_var * kf + delta * delta * self.count * kf / total;
            self.mean[j] += delta * kf / total;
            self.var[j] = m2 / total;
        }
        self.count += kf;
    }

    /// √(var + 1e-8) of each entry, in f32 (what [`normalize`] divides by).
    pub fn std(&self) -> Vec<f32> {
        self.var
            .iter()
            .map(|v| (v + VAR_EPS).sqrt() as f32)
            .collect()
    }

    /// The mean in f32.
    pub fn mean_f32(&self) -> Vec<f32> {
        self.mean.iter().map(|&m| m as f32).collect()
    }

    /// The two tensors the policy's weights carry.
    pub fn weights(&self) -> Vec<NamedTensor> {
        weights(self.mean_f32(), self.std(), None)
    }

    /// The checkpoint tensors `{prefix}.count`, `.mean`, `.var` (f64, so a resumed run
    /// goes on bit for bit).
    pub fn state(&self, prefix: &str) -> Result<Vec<(String, Tensor)>> {
        let f64s = |v: &[f64]| Tensor::from_slice(v, v.len(), &Device::Cpu);
        Ok(vec![
            (format!("{prefix}.count"), f64s(&[self.count])?),
            (format!("{prefix}.mean"), f64s(&self.mean)?),
            (format!("{prefix}.var"), f64s(&self.var)?),
        ])
    }

    /// The statistics of `n` entries that [`Self::state`] saved under `prefix`.
    pub fn restore(get: &dyn Fn(&str) -> Option<Tensor>, prefix: &str, n: usize) -> Result<Self> {
        let read = |name: &str| read_f64s(get, &format!("{prefix}.{name}"));
        let (count, mean, var) = (read("count")?, read("mean")?, read("var")?);
        if count.len() != 1 || mean.len() != n || var.len() != n {
            return Err(CoreError::Checkpoint(format!(
                "{prefix}: saved for {} entries, this run has {n}",
                mean.len()
            )));
        }
        Ok(Self {
            count: count[0],
            mean,
            var,
        })
    }
}

/// The weights' [`OBS_MEAN`] and [`OBS_STD`] of a mean and scale, and [`OBS_BOUND`]
/// where the entries' clips differ from ±[`OBS_CLIP`].
pub fn weights(mean: Vec<f32>, std: Vec<f32>, bound: Option<Vec<f32>>) -> Vec<NamedTensor> {
    let n = mean.len();
    let named = |name: &str, data| NamedTensor {
        name: name.into(),
        shape: vec![n],
        data,
    };
    let mut t = vec![named(OBS_MEAN, mean), named(OBS_STD, std)];
    t.extend(bound.map(|b| named(OBS_BOUND, b)));
    t
}

/// `obs` [k, n] normalised on its device as [`normalize`] does on the host.
pub fn normalize_tensor(
    obs: &Tensor,
    mean: &[f32],
    std: &[f32],
    bound: Option<&[f32]>,
) -> Result<Tensor> {
    let (n, dev) = (mean.len(), obs.device());
    let mean = Tensor::from_slice(mean, (1, n), dev)?;
    let std = Tensor::from_slice(std, (1, n), dev)?;
    let x = obs.broadcast_sub(&mean)?.broadcast_div(&std)?;
    Ok(match bound {
        None => x.clamp(-OBS_CLIP, OBS_CLIP)?,
        Some(b) => {
            let hi = Tensor::from_slice(b, (1, n), dev)?;
            x.broadcast_minimum(&hi)?.broadcast_maximum(&hi.neg()?)?
        }
    })
}

/// The saved tensor `name` as f64s; a clear error where the state has none.
pub fn read_f64s(get: &dyn Fn(&str) -> Option<Tensor>, name: &str) -> Result<Vec<f64>> {
    let t =
        get(name).ok_or_else(|| CoreError::Checkpoint(format!("the saved state has no {name}")))?;
    Ok(t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?)
}

/// Normalises observations `obs` ([k, n] row-major) in place: clip((o − mean)/std, ±b),
/// b each entry's `bound` (±10 without).
pub fn normalize(obs: &mut [f32], mean: &[f32], std: &[f32], bound: Option<&[f32]>) {
    let n = mean.len();
    for row in obs.chunks_exact_mut(n.max(1)) {
        for (j, ((o, &m), &s)) in row.iter_mut().zip(mean).zip(std).enumerate() {
            let b = bound.map_or(OBS_CLIP, |b| b[j]);
            *o = ((*o - m) / s).clamp(-b, b);
        }
    }
}

/// Where a policy's weights hold the observation normaliser: the indices of
/// [`OBS_MEAN`], [`OBS_STD`] and, where present, [`OBS_BOUND`].
#[derive(Clone, Copy, Debug)]
pub(crate) struct ObsNormAt {
    pub mean: usize,
    pub std: usize,
    pub bound: Option<usize>,
}

/// Where a policy's weights hold [`OBS_MEAN`] and [`OBS_STD`] when it carries both
/// (each [obs_dim], the std finite and > 0), and [`OBS_BOUND`] where it carries one
/// ([obs_dim], each > 0, +∞ allowed); `None` when it carries neither mean nor std.
pub(crate) fn find_in(
    weights: &crate::acting::PolicyWeights,
    obs_dim: usize,
) -> Result<Option<ObsNormAt>> {
    let at = |name: &str| weights.tensors.iter().position(|t| t.name == name);
    match (at(OBS_MEAN), at(OBS_STD)) {
        (None, None) if at(OBS_BOUND).is_some() => Err(CoreError::Checkpoint(format!(
            "weights hold {OBS_BOUND} without {OBS_MEAN} and {OBS_STD}"
        ))),
        (None, None) => Ok(None),
        (Some(_), Some(_)) => {
            let m = super::weight_index(weights, OBS_MEAN, &[obs_dim])?;
            let s = super::weight_index(weights, OBS_STD, &[obs_dim])?;
            let finite = weights.tensors[m].data.iter().all(|v| v.is_finite());
            if !finite
                || weights.tensors[s]
                    .data
                    .iter()
                    .any(|&v| !(v.is_finite() && v > 0.0))
            {
                return Err(CoreError::Checkpoint(format!(
                    "weights {OBS_MEAN} must be finite and {OBS_STD} finite and > 0"
                )));
            }
            let bound = match at(OBS_BOUND) {
                None => None,
                Some(_) => {
                    let b = super::weight_index(weights, OBS_BOUND, &[obs_dim])?;
                    if weights.tensors[b]
                        .data
                        .iter()
                        .any(|&v| v.is_nan() || v <= 0.0)
                    {
                        return Err(CoreError::Checkpoint(format!(
                            "weights {OBS_BOUND} must be > 0 in every entry (+inf: not clipped)"
                        )));
                    }
                    Some(b)
                }
            };
            Ok(Some(ObsNormAt {
                mean: m,
                std: s,
                bound,
            }))
        }
        _ => Err(CoreError::Checkpoint(format!(
            "weights hold one of {OBS_MEAN} and {OBS_STD} without the other"
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two batches merged equal one batch of all their rows (the population moments
    /// of the rows, up to the 1e-4 starting count).
    #[test]
    fn merged_batches_give_the_moments_of_all_rows() {
        // Entry 0: 1, 2, 3, 4, 5, 6 (mean 3.5, population variance 35/12 = 2.9167);
        // entry 1: 10 each (mean 10, variance 0).
        let rows = [
            1.0, 10.0, 2.0, 10.0, 3.0, 10.0, 4.0, 10.0, 5.0, 10.0, 6.0, 10.0,
        ];
        let mut s = RunningStats::new(2);
        s.update(&rows[..4]);
        s.update(&rows[4..]);
        assert!((s.count - 6.0001).abs() < 1e-12);
        // The starting count 1e-4 at mean 0, variance 1 pulls each moment by ~1e-4/6.
        assert!((s.mean[0] - 3.5).abs() < 1e-3, "{:?}", s.mean);
        assert!((s.var[0] - 35.0 / 12.0).abs() < 1e-3, "{:?}", s.var);
        // Entry 1 has no spread of its own; its variance is the starting count's pull:
        // (1e-4·1 + 10²·1e-4·6/6.0001)/6.0001 = 1.68328e-3.
        assert!((s.mean[1] - 10.0).abs() < 1e-3, "{s:?}");
        assert!((s.var[1] - 1.68328e-3).abs() < 1e-7, "{s:?}");
        let mut obs = [3.5f32, 10.0, 100.0, -100.0];
        normalize(&mut obs, &s.mean_f32(), &s.std(), None);
        assert!(obs[0].abs() < 1e-3, "{obs:?}");
        // Entry 1's variance is ~2e-3 (the starting count's pull): 90/√2e-3 is far
        // beyond the clip, as is (100 − 3.5)/1.71 = 56.5.
        assert_eq!(obs[2], OBS_CLIP);
        assert_eq!(obs[3], -OBS_CLIP);
        // An empty batch changes nothing.
        let before = s.clone();
        s.update(&[]);
        assert_eq!(s, before);
    }

    /// [`OBS_BOUND`] clips each entry at its own bound: +∞ passes a raw entry through
    /// whole (100 stays 100), 10 cuts as without the tensor, and the tensor form on a
    /// device does the same as the host's.
    #[test]
    fn each_entry_is_clipped_at_its_own_bound() {
        // Entries: (100 − 0)/1 = 100 unclipped; (−100 − 0)/1 at bound 10 = −10;
        // (3 − 1)/0.5 = 4 at bound 2.5 = 2.5.
        let (mean, std, bound) = (
            [0.0f32, 0.0, 1.0],
            [1.0f32, 1.0, 0.5],
            [f32::INFINITY, 10.0, 2.5],
        );
        let rows = [100.0f32, -100.0, 3.0, -7.0, 5.0, -1.0];
        let mut host = rows;
        normalize(&mut host, &mean, &std, Some(&bound));
        // Second row: −7 within +∞; 5 within 10; (−1 − 1)/0.5 = −4 at 2.5 = −2.5.
        assert_eq!(host, [100.0, -10.0, 2.5, -7.0, 5.0, -2.5]);
        let t = Tensor::from_slice(&rows, (2, 3), &Device::Cpu).unwrap();
        let dev = normalize_tensor(&t, &mean, &std, Some(&bound)).unwrap();
        assert_eq!(dev.flatten_all().unwrap().to_vec1::<f32>().unwrap(), host);
        let mut plain = rows;
        normalize(&mut plain, &mean, &std, None);
        assert_eq!(plain, [10.0, -10.0, 4.0, -7.0, 5.0, -4.0]);
    }

    /// A client refuses a bound that is not > 0 (0, negative, NaN) and one without the
    /// mean and scale; +∞ is a bound.
    #[test]
    fn weights_with_a_bad_bound_are_refused() {
        let with = |tensors| crate::acting::PolicyWeights {
            version: 0,
            tensors,
        };
        let ok = with(weights(
            vec![0.0; 2],
            vec![1.0; 2],
            Some(vec![f32::INFINITY, 10.0]),
        ));
        let at = find_in(&ok, 2).unwrap().unwrap();
        assert_eq!(ok.tensors[at.bound.unwrap()].name, OBS_BOUND);
        for bad in [0.0, -1.0, f32::NAN] {
            let w = with(weights(vec![0.0; 2], vec![1.0; 2], Some(vec![1.0, bad])));
            let e = find_in(&w, 2).unwrap_err().to_string();
            assert!(e.contains("must be > 0"), "{e}");
        }
        let alone = with(weights(vec![0.0; 2], vec![1.0; 2], Some(vec![1.0; 2]))[2..].to_vec());
        let e = find_in(&alone, 2).unwrap_err().to_string();
        assert!(e.contains("without"), "{e}");
        let short = with(weights(vec![0.0; 2], vec![1.0; 2], Some(vec![1.0])));
        assert!(find_in(&short, 2).is_err());
    }
}
