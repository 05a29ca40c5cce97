//! When an episode succeeds, as data the learner can check a client's claim against:
//! every state-aligned coordinate of the position a step reached strictly within
//! `radius` of the goal, the goal being the origin or observation entries.
//! (docs/ALGORITHM.md §2, rule 4; a custom env declares it, or has none when its own
//! `terminated` is the success.)

use super::slack;
use serde::{Deserialize, Serialize};

/// Success: `max_j |p'_j − g_j| < radius`, with `g` the `dim` observation entries from
/// `goal_start` of the observation the step started from (`None`: g = 0).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SuccessRule {
    /// The success radius (finite, > 0).
    pub radius: f32,
    /// First observation entry of the goal; `None`: the goal is the origin (p is
    /// already relative to it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub goal_start: Option<usize>,
}

impl SuccessRule {
    /// The goal's coordinate `j` for a step from observation `obs`.
    pub fn goal(&self, obs: &[f32], j: usize) -> f32 {
        self.goal_start.map_or(0.0, |g| obs[g + j])
    }

    /// How far `next` (the aligned position a step from `obs` reached) is from the
    /// goal: `max_j |p'_j − g_j|`.
    pub fn distance(&self, obs: &[f32], next: &[f32]) -> f32 {
        next.iter()
            .enumerate()
            .map(|(j, &q)| (q - self.goal(obs, j)).abs())
            .fold(0.0, f32::max)
    }

    /// Whether a client's success flag can be true for a step from `obs` to the
    /// aligned position `next`: within the radius up to rounding `tolerance` (the
    /// client may have computed in another precision).
    pub fn may_succeed(&self, obs: &[f32], next: &[f32], tolerance: f32) -> bool {
        self.distance(obs, next) < self.radius + slack(self.radius) + tolerance
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// By hand: obs = [g = (0.5, -0.5), p = (0.45, -0.3)], the step reaches
    /// p' = (0.52, -0.45): |0.52 − 0.5| = 0.02, |−0.45 + 0.5| = 0.05, so the distance is
    /// 0.05: a success for radius 0.1, not for 0.04; with the goal at the origin the
    /// distance is 0.52.
    #[test]
    fn distance_to_a_goal_in_the_observation_or_the_origin() {
        let obs = [0.5, -0.5, 0.45, -0.3];
        let next = [0.52, -0.45];
        let in_obs = SuccessRule {
            radius: 0.1,
            goal_start: Some(0),
        };
        assert!((in_obs.distance(&obs, &next) - 0.05).abs() < 1e-6);
        assert!(in_obs.may_succeed(&obs, &next, 0.0));
        let tight = SuccessRule {
            radius: 0.04,
            ..in_obs
        };
        assert!(!tight.may_succeed(&obs, &next, 0.0));
        // 0.04 + slack + 0.011 > 0.05: a tolerance that covers the gap lets it pass.
        assert!(tight.may_succeed(&obs, &next, 0.011));
        let origin = SuccessRule {
            radius: 0.1,
            goal_start: None,
        };
        assert!((origin.distance(&obs, &next) - 0.52).abs() < 1e-6);
        assert!(!origin.may_succeed(&obs, &next, 0.0));
    }
}
