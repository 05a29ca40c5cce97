//! How SAVER's agent and critics see the observations (`saver.obs_norm`;
//! docs/ALGORITHM.md §7.1): raw, by running statistics (as PPO's `ppo.obs_norm`) of
//! every entry or of the aligned ones alone (always, or where the first batch finds p
//! narrow), or by the env's declared bounds. The PCPN reads them raw. The mean and
//! scale travel with the policy's weights as `agent.obs_mean` / `agent.obs_std`, so
//! every client that acts from them (the Rust actors, the Python package, `saver
//! eval`) does the same.

use crate::config::ObsNorm;
use crate::env::EnvSpec;
use crate::nets::obs_norm::{normalize_tensor, read_f64s, weights, RunningStats, OBS_CLIP};
use crate::Result;
use candle_core::Tensor;
use saver_proto::NamedTensor;

/// The checkpoint prefix of the running statistics.
const STATE: &str = "saver.obs_norm";
/// The checkpoint tensor of `auto`'s choice: −1 not yet made, 0 raw, 1 p and g scaled.
const AUTO_STATE: &str = "saver.obs_norm.auto";
/// `auto` scales p and g where p's widest entry spreads less than this share of the
/// widest entry outside p and g over the first batch (`saver-actor check`'s note uses
/// the same share): Reacher-v5's fingertip offset spreads ~0.2 of its joint cosines,
/// the point masses' p 2.5-7 times their speeds, reach3's p as much as its gripper
/// (results/env-return/README.md, "where the observation scale acts").
pub const NARROW_POSITION: f32 = 1.0 / 3.0;

pub(super) enum ObsScale {
    /// The running mean and variance of the observations seen so far: an update reads
    /// the statistics the actors acted with, and the batch joins them after it. The
    /// entries they do not scale read raw (mean 0, scale 1).
    Running { stats: RunningStats, scaled: Scaled },
    /// (o − (low + high)/2) / ((high − low)/2) from the env's declared bounds (1 where
    /// an entry's range is empty), fixed for the run.
    Bounds { mean: Vec<f32>, std: Vec<f32> },
}

/// Which entries running statistics scale.
#[derive(Clone, Debug, PartialEq)]
pub(super) enum Scaled {
    /// Every entry (`running`).
    All,
    /// These entries (`aligned`: p, then g).
    Only(Vec<usize>),
    /// `auto`: p's entries, p's and g's, and the choice the first batch made (none
    /// before it: every entry raw until then, and after it where p is not narrow).
    Auto {
        p: Vec<usize>,
        entries: Vec<usize>,
        chosen: Option<bool>,
    },
}

impl ObsScale {
    /// The scale `kind` asks for on `env`; none for `Off`.
    pub(super) fn of(kind: ObsNorm, env: &EnvSpec) -> Option<Self> {
        let bounds = env.bounds();
        let running = |scaled| Self::Running {
            stats: RunningStats::new(bounds.obs_low.len()),
            scaled,
        };
        let l = env.layout();
        match kind {
            ObsNorm::Off => None,
            ObsNorm::Running => Some(running(Scaled::All)),
            ObsNorm::Aligned => Some(running(Scaled::Only(aligned_entries(env)))),
            ObsNorm::Auto => Some(running(Scaled::Auto {
                p: (l.aligned_start..l.aligned_start + l.aligned_dim).collect(),
                entries: aligned_entries(env),
                chosen: None,
            })),
            ObsNorm::Bounds => {
                let pairs = bounds.obs_low.iter().zip(&bounds.obs_high);
                let (mean, std) = pairs
                    .map(|(&lo, &hi)| {
                        let half = (hi as f64 - lo as f64) / 2.0;
                        let mid = (lo as f64 + hi as f64) / 2.0;
                        (mid as f32, if half > 0.0 { half as f32 } else { 1.0 })
                    })
                    .unzip();
                Some(Self::Bounds { mean, std })
            }
        }
    }

    /// The mean, the scale and, where some entries are read raw, each entry's clip (±10
    /// where scaled, none where raw, so a raw entry reads exactly as under `off`).
    pub(super) fn mean_std(&self) -> (Vec<f32>, Vec<f32>, Option<Vec<f32>>) {
        let (stats, scaled) = match self {
            Self::Bounds { mean, std } => return (mean.clone(), std.clone(), None),
            Self::Running { stats, scaled } => (stats, scaled),
        };
        let only: &[usize] = match scaled {
            Scaled::All => return (stats.mean_f32(), stats.std(), None),
            Scaled::Only(e) => e,
            Scaled::Auto {
                entries,
                chosen: Some(true),
                ..
            } => entries,
            Scaled::Auto { .. } => &[],
        };
        let n = stats.mean.len();
        let (mut mean, mut std, mut bound) = (vec![0.0; n], vec![1.0; n], vec![f32::INFINITY; n]);
        let (m, s) = (stats.mean_f32(), stats.std());
        for &j in only {
            (mean[j], std[j], bound[j]) = (m[j], s[j], OBS_CLIP);
        }
        (mean, std, Some(bound))
    }

    /// `obs` [N, obs_dim] as the agent reads it.
    pub(super) fn normalize(&self, obs: &Tensor) -> Result<Tensor> {
        let (mean, std, bound) = self.mean_std();
        normalize_tensor(obs, &mean, &std, bound.as_deref())
    }

    /// After an update: the batch's raw observations join the running statistics, and
    /// `auto`'s first batch makes its choice.
    pub(super) fn learn(&mut self, obs: &[f32]) {
        let Self::Running { stats, scaled } = self else {
            return;
        };
        stats.update(obs);
        if let Scaled::Auto {
            p,
            entries,
            chosen: chosen @ None,
        } = scaled
        {
            let std = stats.std();
            let narrow = narrow_position(&std, p, entries);
            *chosen = Some(narrow.is_some());
            match narrow {
                Some((ratio, k)) => tracing::info!(
                    "saver.obs_norm auto: over the first batch p spreads {ratio:.2} of entry \
                     {k}'s {:.3}: the agent and critics read p (and the goal, where the \
                     env declares one) by their running statistics (as `aligned`), every \
                     other entry raw",
                    std[k]
                ),
                None => tracing::info!(
                    "saver.obs_norm auto: over the first batch p spreads at least \
                     {NARROW_POSITION:.2} of every other entry: the agent and critics read \
                     the observations raw"
                ),
            }
        }
    }

    /// The tensors the policy's weights carry.
    pub(super) fn weights(&self) -> Vec<NamedTensor> {
        let (mean, std, bound) = self.mean_std();
        weights(mean, std, bound)
    }

    /// The checkpoint's tensors (the running statistics and `auto`'s choice; the
    /// bounds come from the config).
    pub(super) fn state(&self) -> Result<Vec<(String, Tensor)>> {
        let Self::Running { stats, scaled } = self else {
            return Ok(Vec::new());
        };
        let mut t = stats.state(STATE)?;
        if let Scaled::Auto { chosen, .. } = scaled {
            let code = chosen.map_or(-1.0, |c| c as u8 as f64);
            t.push((
                AUTO_STATE.into(),
                Tensor::from_slice(&[code], 1, &candle_core::Device::Cpu)?,
            ));
        }
        Ok(t)
    }

    /// Takes the running statistics and `auto`'s choice back from a checkpoint.
    pub(super) fn restore(&mut self, get: &dyn Fn(&str) -> Option<Tensor>) -> Result<()> {
        let Self::Running { stats, scaled } = self else {
            return Ok(());
        };
        *stats = RunningStats::restore(get, STATE, stats.mean.len())?;
        if let Scaled::Auto { chosen, .. } = scaled {
            *chosen = match read_f64s(get, AUTO_STATE)?.as_slice() {
                [c] if *c == -1.0 => None,
                [c] if *c == 0.0 || *c == 1.0 => Some(*c == 1.0),
                other => {
                    return Err(crate::CoreError::Checkpoint(format!(
                        "{AUTO_STATE} is {other:?}, not one of −1, 0, 1"
                    )))
                }
            };
        }
        Ok(())
    }
}

/// Whether p is narrow beside the other entries of spreads `std`: p's widest entry
/// under [`NARROW_POSITION`] of the widest entry outside `entries` (p and g). Some
/// with that share and the widest other entry; None where p is not narrow or no entry
/// lies outside p and g.
pub(super) fn narrow_position(std: &[f32], p: &[usize], entries: &[usize]) -> Option<(f32, usize)> {
    let widest_p = p.iter().map(|&j| std[j]).fold(0.0f32, f32::max);
    let k = (0..std.len())
        .filter(|j| !entries.contains(j))
        .max_by(|&a, &b| std[a].total_cmp(&std[b]))?;
    let ratio = widest_p / std[k];
    (std[k] > 0.0 && ratio < NARROW_POSITION).then_some((ratio, k))
}

/// The observation entries `saver.obs_norm = aligned` scales: the aligned position p,
/// then the goal g where the env's success rule places it in the observation.
pub(super) fn aligned_entries(env: &EnvSpec) -> Vec<usize> {
    let l = env.layout();
    let goal = env.success_rule().and_then(|r| r.goal_start);
    let mut entries: Vec<usize> = (l.aligned_start..l.aligned_start + l.aligned_dim).collect();
    for g in goal.map(|g| g..g + l.aligned_dim).into_iter().flatten() {
        if !entries.contains(&g) {
            entries.push(g);
        }
    }
    entries
}
