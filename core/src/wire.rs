//! Conversions between the wire messages of saver.proto and the domain types. A
//! rollout becomes a domain [`Rollout`] only here, with every length checked against
//! its declared sizes (the learner then checks it against the env layout).

use crate::config::PretrainConfig;
use crate::env::{EnvKind, EnvLayout, EnvSpec};
use crate::rollout::{Episode, Rollout};
use crate::{CoreError, Result};
use saver_proto::pb;

/// Largest rollout (values over all arrays) a peer may send: far above any real one
/// (1024 envs × 64 steps × a d = 64 layout), far below what would hurt the learner.
pub const MAX_ROLLOUT_VALUES: usize = 8 << 20;

impl From<&EnvLayout> for pb::EnvLayout {
    fn from(l: &EnvLayout) -> Self {
        Self {
            obs_dim: l.obs_dim as u32,
            continuous: l.continuous as u32,
            choices: l.choices as u32,
            aligned_start: l.aligned_start as u32,
            aligned_dim: l.aligned_dim as u32,
        }
    }
}

impl From<&EnvSpec> for pb::EnvSpec {
    fn from(s: &EnvSpec) -> Self {
        Self {
            kind: s.kind.name().to_string(),
            dim: s.dim as u32,
            layout: Some((&s.layout()).into()),
        }
    }
}

impl TryFrom<&pb::EnvSpec> for EnvSpec {
    type Error = CoreError;
    fn try_from(s: &pb::EnvSpec) -> Result<Self> {
        EnvSpec::new(EnvKind::parse(&s.kind)?, s.dim as usize)
    }
}

impl From<&PretrainConfig> for pb::PretrainSettings {
    fn from(p: &PretrainConfig) -> Self {
        Self {
            optimizer: p.optimizer.name().to_string(),
            lr: p.lr,
            batches: p.batches,
            batch_size: p.batch_size as u32,
            quantiles: p.quantiles as u32,
            seed: p.seed,
            samples: p.samples.name().to_string(),
        }
    }
}

impl TryFrom<&pb::PretrainSettings> for PretrainConfig {
    type Error = CoreError;
    /// Every field is required (no zero means "a default"); the result is validated.
    fn try_from(s: &pb::PretrainSettings) -> Result<Self> {
        let named = |field: &str, value: &str, expected: &str| {
            CoreError::Config(format!(
                "pretrain.{field}: {value:?} is not one of {expected}"
            ))
        };
        let p = Self {
            optimizer: clap::ValueEnum::from_str(&s.optimizer, false)
                .map_err(|_| named("optimizer", &s.optimizer, "rmsprop, adam"))?,
            lr: s.lr,
            batches: s.batches,
            batch_size: s.batch_size as usize,
            quantiles: s.quantiles as usize,
            seed: s.seed,
            samples: clap::ValueEnum::from_str(&s.samples, false)
                .map_err(|_| named("samples", &s.samples, "reset"))?,
        };
        p.validate()?;
        Ok(p)
    }
}

impl From<&Rollout> for pb::Rollout {
    fn from(r: &Rollout) -> Self {
        Self {
            actor_id: r.actor_id,
            session: r.session,
            seq: r.seq,
            policy_version: r.policy_version,
            n_envs: r.n_envs as u32,
            n_steps: r.n_steps as u32,
            obs: r.obs.clone(),
            mu: r.mu.clone(),
            log_std: r.log_std.clone(),
            actions: r.actions.clone(),
            state_delta: r.state_delta.clone(),
            vector_reward: r.vector_reward.clone(),
            done: r.done.clone(),
            timeouts: r.timeouts.clone(),
            timeout_obs: r.timeout_obs.clone(),
            episodes: r
                .episodes
                .iter()
                .map(|e| pb::Episode {
                    length: e.length,
                    success: e.success,
                    ret: e.ret,
                })
                .collect(),
        }
    }
}

impl TryFrom<pb::Rollout> for Rollout {
    type Error = CoreError;
    /// Checks sizes only; [`Rollout::validate`] checks shapes and values.
    fn try_from(r: pb::Rollout) -> Result<Self> {
        let total = r.obs.len()
            + r.mu.len()
            + r.log_std.len()
            + r.actions.len()
            + r.state_delta.len()
            + r.vector_reward.len()
            + r.done.len()
            + r.timeouts.len()
            + r.timeout_obs.len();
        if total > MAX_ROLLOUT_VALUES {
            return Err(CoreError::TooLarge(format!(
                "rollout carries {total} values, more than the {MAX_ROLLOUT_VALUES} allowed"
            )));
        }
        let steps = r.n_envs as u64 * r.n_steps as u64;
        if r.episodes.len() as u64 > steps {
            return Err(CoreError::Data(format!(
                "rollout reports {} finished episodes in {steps} env steps",
                r.episodes.len()
            )));
        }
        let actor_id = r.actor_id;
        Ok(Self {
            actor_id,
            session: r.session,
            seq: r.seq,
            policy_version: r.policy_version,
            n_envs: r.n_envs as usize,
            n_steps: r.n_steps as usize,
            obs: r.obs,
            mu: r.mu,
            log_std: r.log_std,
            actions: r.actions,
            state_delta: r.state_delta,
            vector_reward: r.vector_reward,
            done: r.done,
            timeouts: r.timeouts,
            timeout_obs: r.timeout_obs,
            actor_state: None,
            episodes: r
                .episodes
                .into_iter()
                .map(|e| Episode {
                    actor_id,
                    length: e.length,
                    success: e.success,
                    ret: e.ret,
                    verified: true,
                })
                .collect(),
        })
    }
}
