//! Conversions between the wire messages of saver.proto and the domain types. A
//! rollout becomes a domain [`Rollout`] only here, with every length checked against
//! its declared sizes (the learner then checks it against the env layout).

use crate::config::{Algo, PretrainConfig};
use crate::env::{EnvBounds, EnvKind, EnvLayout, EnvSpec, SuccessRule};
use crate::link::ActorSettings;
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
        let b = s.bounds();
        // A preset's rule is its kind's: only a custom env's travels.
        let rule = s.declared_success();
        Self {
            kind: s.name().to_string(),
            dim: s.dim() as u32,
            layout: Some((&s.layout()).into()),
            bounds: Some(pb::EnvBounds {
                obs_low: b.obs_low,
                obs_high: b.obs_high,
                max_change: b.max_change,
            }),
            success_radius: rule.map_or(0.0, |r| r.radius),
            goal_start: rule.and_then(|r| r.goal_start.map(|g| g as u32)),
        }
    }
}

impl From<&ActorSettings> for pb::RunSettings {
    fn from(s: &ActorSettings) -> Self {
        Self {
            algo: s.algo.name().to_string(),
            mode: s.mode.name().to_string(),
            rollout: s.rollout,
            seed: s.seed,
            max_episode_steps: s.max_episode_steps,
            complete_at_success: s.complete_at_success,
            continue_past_success: s.continue_past_success,
            env: Some((&s.env).into()),
            policy: Some(pb::PolicySpec {
                family: s.policy.name().to_string(),
                payload_width: s.policy.payload_width() as u32,
                payload_layout: s.policy.payload_layout(),
                params: s.policy.params().into_iter().collect(),
            }),
        }
    }
}

impl TryFrom<&pb::RunSettings> for ActorSettings {
    type Error = CoreError;
    /// Every field checked: a preset env of this build, a known policy family whose
    /// payload width agrees.
    fn try_from(s: &pb::RunSettings) -> Result<Self> {
        let bad = |why: String| CoreError::Config(format!("the learner's settings: {why}"));
        let env = EnvSpec::try_from(s.env.as_ref().ok_or_else(|| bad("no env".into()))?)?;
        let p = s.policy.as_ref().ok_or_else(|| bad("no policy".into()))?;
        let params = p.params.iter().map(|(k, v)| (k.clone(), *v)).collect();
        let policy = crate::nets::family_from_wire(&p.family, env.layout(), &params)?;
        if policy.payload_width() != p.payload_width as usize {
            return Err(bad(format!(
                "payload width {} where {} has {}",
                p.payload_width,
                p.family,
                policy.payload_width()
            )));
        }
        let mode = clap::ValueEnum::from_str(&s.mode, false)
            .map_err(|_| bad(format!("mode {:?}", s.mode)))?;
        if s.rollout == 0 || s.max_episode_steps == 0 {
            return Err(bad("rollout and max_episode_steps must be >= 1".into()));
        }
        Ok(Self {
            algo: Algo::parse(&s.algo)?,
            mode,
            rollout: s.rollout,
            seed: s.seed,
            max_episode_steps: s.max_episode_steps,
            complete_at_success: s.complete_at_success,
            continue_past_success: s.continue_past_success,
            env,
            policy,
        })
    }
}

impl From<&pb::EnvLayout> for EnvLayout {
    fn from(l: &pb::EnvLayout) -> Self {
        Self {
            obs_dim: l.obs_dim as usize,
            continuous: l.continuous as usize,
            choices: l.choices as usize,
            aligned_start: l.aligned_start as usize,
            aligned_dim: l.aligned_dim as usize,
        }
    }
}

impl TryFrom<&pb::EnvSpec> for EnvSpec {
    type Error = CoreError;
    /// A preset's name with its dimension (a layout and bounds sent along must be the
    /// preset's), or any other name with its layout and bounds (a custom env).
    fn try_from(s: &pb::EnvSpec) -> Result<Self> {
        let bounds = s.bounds.as_ref().map(|b| EnvBounds {
            obs_low: b.obs_low.clone(),
            obs_high: b.obs_high.clone(),
            max_change: b.max_change,
        });
        let layout = s.layout.as_ref().map(EnvLayout::from);
        match EnvKind::parse(&s.kind) {
            Ok(kind) => {
                let spec = EnvSpec::new(kind, s.dim as usize)?;
                if layout.is_some_and(|l| l != spec.layout())
                    || bounds.is_some_and(|b| b != spec.bounds())
                {
                    return Err(CoreError::Config(format!(
                        "env {spec}: the layout or bounds sent are not the preset's"
                    )));
                }
                Ok(spec)
            }
            Err(_) => {
                let (Some(layout), Some(bounds)) = (layout, bounds) else {
                    return Err(CoreError::Config(format!(
                        "env {:?} is no preset: send its layout and bounds",
                        crate::clip_text(&s.kind)
                    )));
                };
                let success = match (s.success_radius, s.goal_start) {
                    (0.0, None) => None,
                    (radius, goal_start) => Some(SuccessRule {
                        radius,
                        goal_start: goal_start.map(|g| g as usize),
                    }),
                };
                let spec = EnvSpec::custom(&s.kind, layout, bounds)?.with_success(success)?;
                if spec.dim() != s.dim as usize {
                    return Err(CoreError::Config(format!(
                        "env {:?}: dim {} is not the layout's aligned_dim {}",
                        s.kind,
                        s.dim,
                        spec.dim()
                    )));
                }
                Ok(spec)
            }
        }
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
            walk_samples: p.walk_samples,
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
                .map_err(|_| named("samples", &s.samples, "reset, walk"))?,
            walk_samples: s.walk_samples,
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
            payload: r.payload.clone(),
            actions: r.actions.clone(),
            state_delta: r.state_delta.clone(),
            vector_reward: r.vector_reward.clone(),
            env_reward: r.env_reward.clone(),
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
            + r.payload.len()
            + r.actions.len()
            + r.state_delta.len()
            + r.vector_reward.len()
            + r.env_reward.len()
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
            payload: r.payload,
            actions: r.actions,
            state_delta: r.state_delta,
            vector_reward: r.vector_reward,
            env_reward: r.env_reward,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// An env crosses the wire as data: a preset by name (its layout and bounds must
    /// be the preset's), a user's env by name, layout and bounds; the run settings
    /// with it, the policy family and its parameters included.
    #[test]
    fn envs_and_run_settings_cross_the_wire_as_data() {
        let angle = EnvSpec::new(EnvKind::Angle, 4).unwrap();
        let custom = EnvSpec::custom(
            "reach",
            EnvLayout {
                obs_dim: 4,
                continuous: 2,
                choices: 0,
                aligned_start: 2,
                aligned_dim: 2,
            },
            EnvBounds {
                obs_low: vec![-1.0; 4],
                obs_high: vec![1.0; 4],
                max_change: 0.05,
            },
        )
        .unwrap();
        let with_goal = custom
            .clone()
            .with_success(Some(SuccessRule {
                radius: 0.05,
                goal_start: Some(0),
            }))
            .unwrap();
        for spec in [&angle, &custom, &with_goal] {
            let back = EnvSpec::try_from(&pb::EnvSpec::from(spec)).unwrap();
            assert_eq!(&back, spec);
        }
        let mut forged = pb::EnvSpec::from(&angle);
        forged.bounds.as_mut().unwrap().max_change = 5.0;
        let e = EnvSpec::try_from(&forged).unwrap_err().to_string();
        assert!(e.contains("not the preset's"), "{e}");
        let mut bare = pb::EnvSpec::from(&custom);
        bare.layout = None;
        assert!(EnvSpec::try_from(&bare).is_err());

        let config = crate::algo::recommended(&custom, Algo::Saver, 1);
        let s = ActorSettings::of(&config);
        let back = ActorSettings::try_from(&pb::RunSettings::from(&s)).unwrap();
        assert_eq!(back.env, custom);
        assert_eq!(back.policy.params(), s.policy.params());
        assert_eq!(back.policy.params()["mu_bound"], 1.0);
        assert_eq!((back.rollout, back.seed), (s.rollout, s.seed));
    }
}
