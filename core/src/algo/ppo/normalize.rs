//! PPO's normalisers, as Stable-Baselines3's `VecNormalize` (which RL Zoo's tuned
//! settings use; docs/ALGORITHM.md §15):
//!
//! - `ppo.obs_norm`: the update reads observations normalised by the running statistics
//!   of the weights it published last (they travel in the weights, `nets::obs_norm`):
//!   in sync mode exactly those the batch's actors acted with, in async mode those or a
//!   few versions newer; it merges the batch's raw observations into them after a
//!   successful update;
//! - `ppo.reward_norm`: per trajectory, R ← γ·R + r (0 again after a step that ends an
//!   episode); at each step the trajectories' R update a running variance, and the
//!   step's reward becomes clip(r / √(var + 1e-8), ±10);
//! - `ppo.env_reward`: the env's own reward instead of the progress reward's sum.
//!
//! Their state is part of the checkpoint, so a resumed run goes on exactly.

use crate::config::PpoConfig;
use crate::nets::obs_norm::{normalize, read_f64s, RunningStats};
use crate::rollout::Batch;
use crate::{CoreError, Result};
use candle_core::{Device, Tensor};
use saver_proto::NamedTensor;

/// Scaled rewards are clipped to ±this (SB3's `clip_reward`).
const REWARD_CLIP: f64 = 10.0;

/// The discounted-return scale of `ppo.reward_norm`.
#[derive(Clone, Debug)]
struct ReturnScale {
    /// Running variance of R.
    stats: RunningStats,
    /// R of each trajectory so far (the batch's trajectory t; sync mode keeps each
    /// actor env at one index).
    returns: Vec<f64>,
}

/// PPO's normalisers; each `None` when off.
#[derive(Clone, Debug)]
pub(super) struct Normalizers {
    obs: Option<RunningStats>,
    reward: Option<ReturnScale>,
    env_reward: bool,
    gamma: f64,
}

impl Normalizers {
    /// The normalisers `cfg` asks for, fresh.
    pub(super) fn new(cfg: &PpoConfig, obs_dim: usize, gamma: f64) -> Self {
        Self {
            obs: cfg.obs_norm.then(|| RunningStats::new(obs_dim)),
            reward: cfg.reward_norm.then(|| ReturnScale {
                stats: RunningStats::new(1),
                returns: Vec::new(),
            }),
            env_reward: cfg.env_reward,
            gamma,
        }
    }

    /// `batch` with its observations (steps, last and timeout ones) normalised by the
    /// statistics its actors acted with; `None` without `ppo.obs_norm`.
    pub(super) fn observations(&self, batch: &Batch) -> Option<Batch> {
        let s = self.obs.as_ref()?;
        let (mean, std) = (s.mean_f32(), s.std());
        let mut b = batch.clone();
        for rows in [&mut b.obs, &mut b.last_obs, &mut b.timeout_obs] {
            normalize(rows, &mean, &std, None);
        }
        Some(b)
    }

    /// Merges the raw observations of `batch` into the statistics (after an update
    /// that used the old ones).
    pub(super) fn learn_observations(&mut self, batch: &Batch) {
        if let Some(s) = &mut self.obs {
            s.update(&batch.obs);
        }
    }

    /// The rewards PPO learns from, [B, c]: the progress reward (summed with c = 1,
    /// per coordinate with c = d) or the env's own (c = 1), scaled with
    /// `ppo.reward_norm` (which moves its statistics).
    pub(super) fn rewards(&mut self, batch: &Batch, c: usize) -> Result<Vec<f32>> {
        let mut r = if self.env_reward {
            if batch.env_reward.len() != batch.len() {
                return Err(CoreError::Data(
                    "ppo.env_reward: the batch carries no env reward (a preset's actors send \
                     none; a Python actor sends its env's)"
                        .into(),
                ));
            }
            batch.env_reward.clone()
        } else if c == 1 {
            batch.scalar_reward()
        } else {
            batch.vector_reward.clone()
        };
        if let Some(scale) = &mut self.reward {
            scale.apply(batch, &mut r, c, self.gamma);
        }
        Ok(r)
    }

    /// The tensors actors need beside the agent's ([`crate::nets::obs_norm::OBS_MEAN`]
    /// and `OBS_STD`), none without `ppo.obs_norm`.
    pub(super) fn weights(&self) -> Vec<NamedTensor> {
        self.obs.as_ref().map(|s| s.weights()).unwrap_or_default()
    }

    /// Their checkpointed state (f64, so a resumed run goes on bit for bit).
    pub(super) fn state(&self) -> Result<Vec<(String, Tensor)>> {
        let mut out = Vec::new();
        if let Some(s) = &self.obs {
            out.extend(s.state("ppo.obs_norm")?);
        }
        if let Some(r) = &self.reward {
            out.extend(r.stats.state("ppo.reward_norm")?);
            let returns = Tensor::from_slice(&r.returns, r.returns.len(), &Device::Cpu)?;
            out.push(("ppo.reward_norm.returns".into(), returns));
        }
        Ok(out)
    }

    /// Restores what [`Normalizers::state`] saved.
    pub(super) fn restore(&mut self, get: &dyn Fn(&str) -> Option<Tensor>) -> Result<()> {
        if let Some(s) = &mut self.obs {
            *s = RunningStats::restore(get, "ppo.obs_norm", s.mean.len())?;
        }
        if let Some(r) = &mut self.reward {
            r.stats = RunningStats::restore(get, "ppo.reward_norm", 1)?;
            r.returns = read_f64s(get, "ppo.reward_norm.returns")?;
        }
        Ok(())
    }
}

impl ReturnScale {
    /// Scales `rewards` ([B, c], trajectory-major) step by step, as SB3 does over its
    /// envs: each step's R of every trajectory updates the variance first.
    fn apply(&mut self, batch: &Batch, rewards: &mut [f32], c: usize, gamma: f64) {
        let (t, n) = (batch.n_traj, batch.n_steps);
        if self.returns.len() != t {
            // Another number of trajectories (async batches, a resumed run with other
            // actors): the returns start again.
            self.returns = vec![0.0; t];
        }
        let mut step_returns = vec![0f32; t];
        for k in 0..n {
            for (traj, r) in self.returns.iter_mut().enumerate() {
                let i = traj * n + k;
                let summed: f64 = rewards[i * c..(i + 1) * c].iter().map(|&v| v as f64).sum();
                *r = *r * gamma + summed;
                step_returns[traj] = *r as f32;
            }
            self.stats.update(&step_returns);
            let std = (self.stats.var[0] + 1e-8).sqrt();
            for traj in 0..t {
                let i = traj * n + k;
                for v in &mut rewards[i * c..(i + 1) * c] {
                    *v = (*v as f64 / std).clamp(-REWARD_CLIP, REWARD_CLIP) as f32;
                }
                if batch.done[i] {
                    self.returns[traj] = 0.0;
                }
            }
        }
    }
}
