//! What values a rollout of a run may hold: the env's bounds ([`EnvBounds`]) and what
//! the behaviour policy's family accepts of its payload and actions, as data. The learner's edge holds every
//! rollout to them, so that a finite but absurd value (an observation of 1e10, a
//! vector reward of 1e18) never reaches an update.

use crate::acting::PolicyFamily;
use crate::env::{EnvBounds, EnvLayout};
use crate::rollout::Rollout;
use crate::{CoreError, Result};
use std::sync::Arc;

/// The largest env reward a rollout may carry for one step (its square and its sums
/// over an episode stay far inside f32).
pub const MAX_ENV_REWARD: f32 = 1e9;

/// The ranges of one run's rollouts.
#[derive(Clone, Debug)]
pub struct RolloutLimits {
    /// The env's layout.
    pub layout: EnvLayout,
    /// The env's bounds.
    pub env: EnvBounds,
    /// The behaviour policy's family: it checks payloads and actions.
    pub policy: Arc<dyn PolicyFamily>,
}

impl RolloutLimits {
    /// The limits of rollouts of `env` (with `layout`) acted by `policy`.
    pub fn new(layout: EnvLayout, env: EnvBounds, policy: Arc<dyn PolicyFamily>) -> Self {
        Self {
            layout,
            env,
            policy,
        }
    }

    /// Checks every value of `r` (whose shapes [`Rollout::validate`] checked) against
    /// the limits; the error names the first value outside them.
    pub fn check(&self, r: &Rollout) -> Result<()> {
        let out = |name: &str, i: usize, v: f32, what: String| {
            Err(CoreError::Data(format!(
                "rollout {name}[{i}] = {v} is outside {what}"
            )))
        };
        for (name, obs) in [("obs", &r.obs), ("timeout_obs", &r.timeout_obs)] {
            if let Some((i, k)) = self.env.obs_outside(obs) {
                let (lo, hi) = (self.env.obs_low[k], self.env.obs_high[k]);
                return out(
                    name,
                    i,
                    obs[i],
                    format!("the env's range [{lo}, {hi}] of entry {k}"),
                );
            }
        }
        for (name, data) in [
            ("state_delta", &r.state_delta),
            ("vector_reward", &r.vector_reward),
        ] {
            if let Some(i) = self.env.change_beyond(data) {
                return out(
                    name,
                    i,
                    data[i],
                    format!("+-{} (the env's largest step)", self.env.max_change),
                );
            }
        }
        if let Some(i) = r.env_reward.iter().position(|x| x.abs() > MAX_ENV_REWARD) {
            return out(
                "env_reward",
                i,
                r.env_reward[i],
                format!("+-{MAX_ENV_REWARD:e} (the largest env reward a step may carry)"),
            );
        }
        self.policy
            .check(&r.payload, &r.actions, r.n_envs * r.n_steps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Algo, RunConfig};
    use crate::env::{EnvKind, EnvSpec};
    use crate::nets::{Gaussian, UNBOUNDED_MU};

    fn limits_of(config: &RunConfig) -> RolloutLimits {
        let layout = config.env.layout();
        let policy = Arc::new(Gaussian {
            layout,
            head: config.head,
        });
        RolloutLimits::new(layout, config.env.bounds(), policy)
    }

    /// One step of angle d = 2 with values inside every limit.
    fn one_step() -> Rollout {
        Rollout {
            actor_id: 0,
            session: 1,
            seq: 0,
            policy_version: 0,
            n_envs: 1,
            n_steps: 1,
            obs: vec![0.5, -1.0, 0.5, -0.9],
            // μ = [0.9, -0.2], log σ = [-1, 0].
            payload: vec![0.9, -0.2, -1.0, 0.0],
            actions: vec![0.9 + 3.0 * (-1.0f32).exp(), 2.0],
            state_delta: vec![0.0, 0.1],
            vector_reward: vec![0.0, 0.1],
            env_reward: vec![],
            done: vec![false],
            timeouts: vec![],
            timeout_obs: vec![],
            episodes: vec![],
            actor_state: None,
        }
    }

    #[test]
    fn values_outside_the_env_or_the_head_are_refused_with_their_place() {
        let mut config =
            RunConfig::paper(&EnvSpec::new(EnvKind::Angle, 2).unwrap(), Algo::Saver, 0);
        config.head = crate::nets::HeadConfig::IN_PCPN_DOMAIN;
        let limits = limits_of(&config);
        let good = one_step();
        limits.check(&good).unwrap();
        limits
            .check(&Rollout {
                env_reward: vec![-1e9],
                ..good.clone()
            })
            .unwrap();
        type Break = fn(&mut Rollout);
        let cases: [(Break, &str); 9] = [
            (|r| r.obs[2] = 1e10, "obs[2]"),
            // The env's own reward, where sent: any sign and size up to 1e9 a step.
            (|r| r.env_reward = vec![-2e9], "env_reward[0]"),
            (|r| r.obs[1] = -1.01, "obs[1]"),
            (|r| r.vector_reward[1] = 1e18, "vector_reward[1]"),
            (|r| r.state_delta[0] = -0.11, "state_delta[0]"),
            // The head bounds μ by 1 (tanh) and log σ to [-4.6, 0].
            (|r| r.payload[0] = 1.5, "mu[0]"),
            (|r| r.payload[3] = 0.5, "log_std[1]"),
            // 17 σ from the mean (σ = e^-1 = 0.368): 0.9 + 6.25 = 7.15.
            (|r| r.actions[0] = 7.15, "actions[0]"),
            (|r| r.actions[1] = 1e10, "actions[1]"),
        ];
        for (bad, place) in cases {
            let mut r = good.clone();
            bad(&mut r);
            let e = limits.check(&r).unwrap_err().to_string();
            assert!(e.contains(place), "{place}: {e}");
        }
        // A timeout's final observation is held to the same range.
        let mut r = good.clone();
        r.timeout_obs = vec![0.0, f32::MAX];
        assert!(limits
            .check(&r)
            .unwrap_err()
            .to_string()
            .contains("timeout_obs[1]"));
    }

    #[test]
    fn the_paper_head_allows_wide_but_not_absurd_means_and_the_choice_is_a_one_hot() {
        let config = RunConfig::paper(&EnvSpec::new(EnvKind::Select, 3).unwrap(), Algo::A2c, 0);
        let limits = limits_of(&config);
        assert_eq!(
            Gaussian {
                layout: config.env.layout(),
                head: config.head
            }
            .mu_abs(),
            UNBOUNDED_MU
        );
        let mut r = Rollout {
            obs: vec![0.0; 6],
            // μ = [50, 1, -30, 2] (a mean and three logits), log σ = [0].
            payload: vec![50.0, 1.0, -30.0, 2.0, 0.0],
            actions: vec![52.0, 0.0, 0.0, 1.0],
            state_delta: vec![0.0, 0.0, 0.05],
            vector_reward: vec![0.0, 0.0, 0.05],
            env_reward: vec![],
            ..one_step()
        };
        limits.check(&r).unwrap();
        r.actions[1] = 1.0;
        assert!(limits
            .check(&r)
            .unwrap_err()
            .to_string()
            .contains("one-hot"));
        r.actions[1] = 0.0;
        r.payload[0] = 2e6;
        r.actions[0] = 2e6;
        assert!(limits.check(&r).unwrap_err().to_string().contains("mu[0]"));
    }
}
