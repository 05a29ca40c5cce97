//! What values a rollout of a run may hold: the env's bounds ([`EnvBounds`]) and the
//! policy head's (μ bound, log σ bounds), as data. The learner's edge holds every
//! rollout to them, so that a finite but absurd value (an observation of 1e10, a
//! vector reward of 1e18) never reaches an update.

use crate::config::RunConfig;
use crate::env::{EnvBounds, EnvLayout};
use crate::rollout::Rollout;
use crate::{CoreError, Result};

/// |μ| when the head leaves it unbounded (the paper's linear mean): far beyond any
/// mean a learning policy reaches (actions are clipped to [-1, 1]), far below what
/// overflows a squared error in f32.
pub const UNBOUNDED_MU: f32 = 1e6;
/// |log σ| when the head leaves it unbounded: σ from 2e-9 to 5e8.
pub const UNBOUNDED_LOG_STD: f32 = 20.0;
/// A sampled action lies within this many σ of its mean (a 16-σ draw has probability
/// below 1e-57).
pub const ACTION_SIGMAS: f32 = 16.0;

/// Rounding slack of a bound `b`: values up to `b·(1 + 1e-5) + 1e-6` pass.
fn slack(b: f32) -> f32 {
    b.abs() * 1e-5 + 1e-6
}

/// The ranges of one run's rollouts.
#[derive(Clone, Debug, PartialEq)]
pub struct RolloutLimits {
    /// The env's layout.
    pub layout: EnvLayout,
    /// The env's bounds.
    pub env: EnvBounds,
    /// Largest |μ| (continuous means and choice logits).
    pub mu_abs: f32,
    /// log σ range.
    pub log_std: (f32, f32),
}

impl RolloutLimits {
    /// The limits of `config`'s rollouts.
    pub fn for_run(config: &RunConfig) -> Self {
        let head = config.head;
        Self {
            layout: config.env.layout(),
            env: config.env.bounds(),
            mu_abs: head.mu_bound.map_or(UNBOUNDED_MU, |b| b as f32),
            log_std: head
                .log_std_bounds
                .map_or((-UNBOUNDED_LOG_STD, UNBOUNDED_LOG_STD), |(lo, hi)| {
                    (lo as f32, hi as f32)
                }),
        }
    }

    /// Checks every value of `r` (whose shapes [`Rollout::validate`] checked) against
    /// the limits; the error names the first value outside them.
    pub fn check(&self, r: &Rollout) -> Result<()> {
        let l = &self.layout;
        let out = |name: &str, i: usize, v: f32, what: String| {
            Err(CoreError::Data(format!(
                "rollout {name}[{i}] = {v} is outside {what}"
            )))
        };
        let obs_in = |name: &str, obs: &[f32]| -> Result<()> {
            for (i, &v) in obs.iter().enumerate() {
                let k = i % l.obs_dim;
                let (lo, hi) = (self.env.obs_low[k], self.env.obs_high[k]);
                if v < lo - slack(lo) || v > hi + slack(hi) {
                    return out(
                        name,
                        i,
                        v,
                        format!("the env's range [{lo}, {hi}] of entry {k}"),
                    );
                }
            }
            Ok(())
        };
        obs_in("obs", &r.obs)?;
        obs_in("timeout_obs", &r.timeout_obs)?;
        let change = self.env.max_change + slack(self.env.max_change);
        for (name, data) in [
            ("state_delta", &r.state_delta),
            ("vector_reward", &r.vector_reward),
        ] {
            if let Some(i) = data.iter().position(|v| v.abs() > change) {
                return out(
                    name,
                    i,
                    data[i],
                    format!("+-{} (the env's largest step)", self.env.max_change),
                );
            }
        }
        let mu_abs = self.mu_abs + slack(self.mu_abs);
        if let Some(i) = r.mu.iter().position(|v| v.abs() > mu_abs) {
            return out("mu", i, r.mu[i], format!("the head's +-{}", self.mu_abs));
        }
        let (lo, hi) = self.log_std;
        if let Some(i) = r
            .log_std
            .iter()
            .position(|&v| v < lo - slack(lo) || v > hi + slack(hi))
        {
            return out(
                "log_std",
                i,
                r.log_std[i],
                format!("the head's [{lo}, {hi}]"),
            );
        }
        // Continuous actions within ACTION_SIGMAS σ of their mean; the choice a one-hot.
        let (c, a_dim) = (l.continuous, l.action_dim());
        for (s, a) in r.actions.chunks_exact(a_dim.max(1)).enumerate() {
            for (j, &aj) in a[..c].iter().enumerate() {
                let mu = r.mu[s * l.mu_dim() + j];
                let sigma = r.log_std[s * c + j].exp();
                let far = ACTION_SIGMAS * sigma + slack(mu);
                if (aj - mu).abs() > far {
                    return out(
                        "actions",
                        s * a_dim + j,
                        aj,
                        format!("{ACTION_SIGMAS} sigma of its mean {mu} (sigma {sigma})"),
                    );
                }
            }
            let choice = &a[c..];
            if !choice.is_empty()
                && (choice.iter().any(|&v| v != 0.0 && v != 1.0)
                    || choice.iter().filter(|&&v| v == 1.0).count() != 1)
            {
                return Err(CoreError::Data(format!(
                    "rollout actions of step {s}: the choice {choice:?} is not a one-hot"
                )));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Algo, RunConfig};
    use crate::env::{EnvKind, EnvSpec};

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
            mu: vec![0.9, -0.2],
            log_std: vec![-1.0, 0.0],
            actions: vec![0.9 + 3.0 * (-1.0f32).exp(), 2.0],
            state_delta: vec![0.0, 0.1],
            vector_reward: vec![0.0, 0.1],
            done: vec![false],
            timeouts: vec![],
            timeout_obs: vec![],
            episodes: vec![],
            actor_state: None,
        }
    }

    #[test]
    fn values_outside_the_env_or_the_head_are_refused_with_their_place() {
        let mut config = RunConfig::paper(EnvSpec::new(EnvKind::Angle, 2).unwrap(), Algo::Saver, 0);
        config.head = crate::nets::HeadConfig::IN_PCPN_DOMAIN;
        let limits = RolloutLimits::for_run(&config);
        let good = one_step();
        limits.check(&good).unwrap();
        type Break = fn(&mut Rollout);
        let cases: [(Break, &str); 8] = [
            (|r| r.obs[2] = 1e10, "obs[2]"),
            (|r| r.obs[1] = -1.01, "obs[1]"),
            (|r| r.vector_reward[1] = 1e18, "vector_reward[1]"),
            (|r| r.state_delta[0] = -0.11, "state_delta[0]"),
            // The head bounds μ by 1 (tanh) and log σ to [-4.6, 0].
            (|r| r.mu[0] = 1.5, "mu[0]"),
            (|r| r.log_std[1] = 0.5, "log_std[1]"),
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
        let config = RunConfig::paper(EnvSpec::new(EnvKind::Select, 3).unwrap(), Algo::A2c, 0);
        let limits = RolloutLimits::for_run(&config);
        assert_eq!(limits.mu_abs, UNBOUNDED_MU);
        let mut r = Rollout {
            obs: vec![0.0; 6],
            mu: vec![50.0, 1.0, -30.0, 2.0],
            log_std: vec![0.0],
            actions: vec![52.0, 0.0, 0.0, 1.0],
            state_delta: vec![0.0, 0.0, 0.05],
            vector_reward: vec![0.0, 0.0, 0.05],
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
        r.mu[0] = 2e6;
        r.actions[0] = 2e6;
        assert!(limits.check(&r).unwrap_err().to_string().contains("mu[0]"));
    }
}
