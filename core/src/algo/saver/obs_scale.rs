//! How SAVER's agent and critics see the observations (`saver.obs_norm`;
//! docs/ALGORITHM.md §7.1): raw, by running statistics (as PPO's `ppo.obs_norm`) of
//! every entry or of the aligned ones alone, or by the env's declared bounds. The PCPN
//! reads them raw. The mean and scale travel with
//! the policy's weights as `agent.obs_mean` / `agent.obs_std`, so every client that acts
//! from them (the Rust actors, the Python package, `saver eval`) does the same.

use crate::config::ObsNorm;
use crate::env::EnvSpec;
use crate::nets::obs_norm::{normalize_tensor, weights, RunningStats};
use crate::Result;
use candle_core::Tensor;
use saver_proto::NamedTensor;

/// The checkpoint prefix of the running statistics.
const STATE: &str = "saver.obs_norm";

pub(super) enum ObsScale {
    /// The running mean and variance of the observations seen so far: an update reads
    /// the statistics the actors acted with, and the batch joins them after it. With
    /// `only`, the entries it does not hold read raw (mean 0, scale 1).
    Running {
        stats: RunningStats,
        only: Option<Vec<usize>>,
    },
    /// (o − (low + high)/2) / ((high − low)/2) from the env's declared bounds (1 where
    /// an entry's range is empty), fixed for the run.
    Bounds { mean: Vec<f32>, std: Vec<f32> },
}

impl ObsScale {
    /// The scale `kind` asks for on `env`; none for `Off`.
    pub(super) fn of(kind: ObsNorm, env: &EnvSpec) -> Option<Self> {
        let bounds = env.bounds();
        let running = |only| Self::Running {
            stats: RunningStats::new(bounds.obs_low.len()),
            only,
        };
        match kind {
            ObsNorm::Off => None,
            ObsNorm::Running => Some(running(None)),
            ObsNorm::Aligned => Some(running(Some(aligned_entries(env)))),
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

    fn mean_std(&self) -> (Vec<f32>, Vec<f32>) {
        match self {
            Self::Running { stats, only: None } => (stats.mean_f32(), stats.std()),
            Self::Running {
                stats,
                only: Some(only),
            } => {
                let n = stats.mean.len();
                let (mut mean, mut std) = (vec![0.0; n], vec![1.0; n]);
                let (m, s) = (stats.mean_f32(), stats.std());
                for &j in only {
                    (mean[j], std[j]) = (m[j], s[j]);
                }
                (mean, std)
            }
            Self::Bounds { mean, std } => (mean.clone(), std.clone()),
        }
    }

    /// `obs` [N, obs_dim] as the agent reads it.
    pub(super) fn normalize(&self, obs: &Tensor) -> Result<Tensor> {
        let (mean, std) = self.mean_std();
        normalize_tensor(obs, &mean, &std)
    }

    /// After an update: the batch's raw observations join the running statistics.
    pub(super) fn learn(&mut self, obs: &[f32]) {
        if let Self::Running { stats, .. } = self {
            stats.update(obs);
        }
    }

    /// The tensors the policy's weights carry.
    pub(super) fn weights(&self) -> Vec<NamedTensor> {
        let (mean, std) = self.mean_std();
        weights(mean, std)
    }

    /// The checkpoint's tensors (the running statistics; the bounds come from the config).
    pub(super) fn state(&self) -> Result<Vec<(String, Tensor)>> {
        match self {
            Self::Running { stats, .. } => stats.state(STATE),
            Self::Bounds { .. } => Ok(Vec::new()),
        }
    }

    /// Takes the running statistics back from a checkpoint.
    pub(super) fn restore(&mut self, get: &dyn Fn(&str) -> Option<Tensor>) -> Result<()> {
        if let Self::Running { stats, .. } = self {
            *stats = RunningStats::restore(get, STATE, stats.mean.len())?;
        }
        Ok(())
    }
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
