//! Rollouts (what an actor ships) and batches (what an update consumes).
//!
//! A rollout holds `n_envs` trajectories of `n_steps` steps; every array is row-major
//! with the env index first. A batch concatenates rollouts in actor-id order.

use crate::env::EnvLayout;
use crate::{CoreError, Result};
use std::sync::Arc;

/// An episode that finished inside a rollout.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Episode {
    /// Actor that ran it.
    pub actor_id: u32,
    /// Steps, counting the last one.
    pub length: u32,
    /// The goal was reached (not a timeout).
    pub success: bool,
    /// Undiscounted scalar return (sum of the vector reward components).
    pub ret: f32,
    /// The learner could check its length against the steps it counted (false for
    /// an episode that began before a gap in an actor's rollouts): only verified
    /// episodes enter the run's metrics.
    pub verified: bool,
}

/// n steps of E envs from one actor at one policy version.
#[derive(Clone, Debug, PartialEq)]
pub struct Rollout {
    /// Actor id from registration.
    pub actor_id: u32,
    /// Actor session (per process).
    pub session: u64,
    /// Per-actor sequence number, from 0.
    pub seq: u64,
    /// Version of the weights that chose the actions.
    pub policy_version: u64,
    /// E.
    pub n_envs: usize,
    /// n.
    pub n_steps: usize,
    /// [E, n+1, obs_dim]: observations o_0..o_n (o_n bootstraps the returns).
    pub obs: Vec<f32>,
    /// [E, n, payload width]: what the behaviour policy recorded per step, in the
    /// layout its family declares ([`crate::acting::PolicyFamily`]; the Gaussian's:
    /// μ then log σ).
    pub payload: Vec<f32>,
    /// [E, n, action_dim]: sampled actions (unclipped; the choice as a one-hot).
    pub actions: Vec<f32>,
    /// [E, n, d]: change of the state-aligned part.
    pub state_delta: Vec<f32>,
    /// [E, n, d]: vector rewards.
    pub vector_reward: Vec<f32>,
    /// [E, n]: the env's own scalar reward of each step, or empty when the env has
    /// none (the presets); SAVER's env-return term learns from it.
    pub env_reward: Vec<f32>,
    /// [E, n]: the episode ended at this step (success or timeout).
    pub done: Vec<bool>,
    /// Steps (indices into [E, n], ascending) whose episode ended at the step limit;
    /// empty from a peer that does not report them (every end is then terminal).
    pub timeouts: Vec<u32>,
    /// [timeouts, obs_dim]: the observation each of those steps reached (the envs
    /// are reset after it, so `obs` does not hold it): what a timeout bootstraps from.
    pub timeout_obs: Vec<f32>,
    /// Episodes that finished in this rollout.
    pub episodes: Vec<Episode>,
    /// The actor's state right after this rollout (in-process actors only; it never
    /// crosses the wire): what a checkpoint needs to resume the actor exactly.
    pub actor_state: Option<Arc<ActorState>>,
}

/// An actor between two rollouts: its envs, their current observations and running
/// episodes, the position of its random stream and its next sequence number.
#[derive(Clone, Debug, PartialEq)]
pub struct ActorState {
    /// [`crate::env::Env::snapshot`] of each env.
    pub envs: Vec<Vec<f32>>,
    /// Current observation of each env.
    pub obs: Vec<Vec<f32>>,
    /// Steps and scalar return of each env's running episode.
    pub running: Vec<(u32, f32)>,
    /// Word position of the actor's ChaCha8 stream.
    pub rng_word_pos: u128,
    /// Next sequence number.
    pub seq: u64,
}

impl ActorState {
    /// As one f32 tensor (a row per env: env state, observation, steps, return) and
    /// the two counters, for a checkpoint.
    pub fn to_rows(&self) -> (Vec<usize>, Vec<f32>) {
        let width =
            self.envs.first().map_or(0, Vec::len) + self.obs.first().map_or(0, Vec::len) + 2;
        let mut data = Vec::with_capacity(self.envs.len() * width);
        for ((e, o), (steps, ret)) in self.envs.iter().zip(&self.obs).zip(&self.running) {
            data.extend_from_slice(e);
            data.extend_from_slice(o);
            data.push(*steps as f32);
            data.push(*ret);
        }
        (vec![self.envs.len(), width], data)
    }

    /// Inverse of [`ActorState::to_rows`] for envs whose snapshot has `env_len`
    /// numbers and observations `obs_len`.
    pub fn from_rows(
        shape: &[usize],
        data: &[f32],
        env_len: usize,
        obs_len: usize,
        rng_word_pos: u128,
        seq: u64,
    ) -> Result<Self> {
        let width = env_len + obs_len + 2;
        if shape.len() != 2 || shape[1] != width || data.len() != shape[0] * width {
            return Err(CoreError::Checkpoint(format!(
                "an actor state of shape {shape:?} does not fit rows of {width}"
            )));
        }
        let mut s = Self {
            envs: Vec::new(),
            obs: Vec::new(),
            running: Vec::new(),
            rng_word_pos,
            seq,
        };
        for row in data.chunks_exact(width) {
            s.envs.push(row[..env_len].to_vec());
            s.obs.push(row[env_len..env_len + obs_len].to_vec());
            s.running.push((row[width - 2] as u32, row[width - 1]));
        }
        Ok(s)
    }
}

impl Rollout {
    /// Checks every array against the layout and the payload width, and that all
    /// numbers are finite.
    pub fn validate(&self, layout: &EnvLayout, payload_width: usize) -> Result<()> {
        let (e, n) = (self.n_envs, self.n_steps);
        if e == 0 || n == 0 {
            return Err(CoreError::Data(format!(
                "rollout has {e} envs and {n} steps; both must be >= 1"
            )));
        }
        let mut arrays: Vec<(&str, &[f32], usize)> = vec![
            ("obs", &self.obs, e * (n + 1) * layout.obs_dim),
            ("payload", &self.payload, e * n * payload_width),
            ("actions", &self.actions, e * n * layout.action_dim()),
            ("state_delta", &self.state_delta, e * n * layout.aligned_dim),
            (
                "vector_reward",
                &self.vector_reward,
                e * n * layout.aligned_dim,
            ),
        ];
        // The env's own reward is optional: checked like the rest where it is sent.
        if !self.env_reward.is_empty() {
            arrays.push(("env_reward", &self.env_reward, e * n));
        }
        for (name, data, want) in arrays {
            if data.len() != want {
                return Err(CoreError::Data(format!(
                    "rollout {name} has {} values, expected {want} for {e} envs x {n} steps",
                    data.len()
                )));
            }
            if let Some(i) = data.iter().position(|x| !x.is_finite()) {
                return Err(CoreError::Data(format!(
                    "rollout {name}[{i}] is {} (not finite)",
                    data[i]
                )));
            }
        }
        if self.done.len() != e * n {
            return Err(CoreError::Data(format!(
                "rollout done has {} entries, expected {}",
                self.done.len(),
                e * n
            )));
        }
        let ends = self.done.iter().filter(|&&d| d).count();
        if ends != self.episodes.len() {
            return Err(CoreError::Data(format!(
                "rollout has {ends} done flags and {} episodes: each done flag carries \
                 exactly one episode, in the order of the flags",
                self.episodes.len()
            )));
        }
        if let Some(i) = self.episodes.iter().position(|e| !e.ret.is_finite()) {
            return Err(CoreError::Data(format!(
                "rollout episodes[{i}] has return {} (not finite)",
                self.episodes[i].ret
            )));
        }
        self.validate_timeouts(layout.obs_dim)
    }

    fn validate_timeouts(&self, obs_dim: usize) -> Result<()> {
        let mut prev = None;
        for (k, &i) in self.timeouts.iter().enumerate() {
            if !self.done.get(i as usize).copied().unwrap_or(false) || prev >= Some(i) {
                return Err(CoreError::Data(format!(
                    "rollout timeouts[{k}] = {i} is not a step that ends an episode, after \
                     the one before"
                )));
            }
            prev = Some(i);
        }
        let want = self.timeouts.len() * obs_dim;
        if self.timeout_obs.len() != want {
            return Err(CoreError::Data(format!(
                "rollout timeout_obs has {} values, expected {want} for {} timeouts",
                self.timeout_obs.len(),
                self.timeouts.len()
            )));
        }
        if self.timeout_obs.iter().any(|x| !x.is_finite()) {
            return Err(CoreError::Data("rollout timeout_obs is not finite".into()));
        }
        Ok(())
    }
}

/// Transitions of several rollouts, trajectory-major, ready for an update.
#[derive(Clone, Debug)]
pub struct Batch {
    /// Number of trajectories T (sum of the rollouts' envs).
    pub n_traj: usize,
    /// Steps per trajectory n.
    pub n_steps: usize,
    /// [T·n, obs_dim]: o_t.
    pub obs: Vec<f32>,
    /// [T, obs_dim]: o_n of each trajectory.
    pub last_obs: Vec<f32>,
    /// [T·n, action_dim].
    pub actions: Vec<f32>,
    /// [T·n, payload width]: what the behaviour policy recorded per step
    /// ([`Rollout::payload`]; PPO's old log-probabilities come from it).
    pub payload: Vec<f32>,
    /// [T·n, d].
    pub state_delta: Vec<f32>,
    /// [T·n, d].
    pub vector_reward: Vec<f32>,
    /// [T·n]: the env's own scalar reward, or empty unless every rollout of the batch
    /// carries one.
    pub env_reward: Vec<f32>,
    /// [T·n].
    pub done: Vec<bool>,
    /// Transitions (indices into T·n, ascending) whose episode hit the step limit.
    pub timeouts: Vec<usize>,
    /// [timeouts, obs_dim]: the final observation of each.
    pub timeout_obs: Vec<f32>,
    /// Total env steps in the batch (T·n).
    pub steps: u64,
}

impl Batch {
    /// Concatenates rollouts in the given order (callers sort by actor id). All must
    /// have the same n and match `layout` (validate them first).
    pub fn from_rollouts(rollouts: &[Rollout], layout: &EnvLayout) -> Result<Self> {
        let Some(first) = rollouts.first() else {
            return Err(CoreError::Data("a batch needs at least one rollout".into()));
        };
        let n = first.n_steps;
        let o = layout.obs_dim;
        let mut b = Batch {
            n_traj: 0,
            n_steps: n,
            obs: vec![],
            last_obs: vec![],
            actions: vec![],
            payload: vec![],
            state_delta: vec![],
            vector_reward: vec![],
            env_reward: vec![],
            done: vec![],
            timeouts: vec![],
            timeout_obs: vec![],
            steps: 0,
        };
        for r in rollouts {
            if r.n_steps != n {
                return Err(CoreError::Data(format!(
                    "rollouts of {} and {n} steps cannot share a batch",
                    r.n_steps
                )));
            }
            for e in 0..r.n_envs {
                let traj = &r.obs[e * (n + 1) * o..(e + 1) * (n + 1) * o];
                b.obs.extend_from_slice(&traj[..n * o]);
                b.last_obs.extend_from_slice(&traj[n * o..]);
            }
            b.actions.extend_from_slice(&r.actions);
            b.payload.extend_from_slice(&r.payload);
            b.state_delta.extend_from_slice(&r.state_delta);
            b.vector_reward.extend_from_slice(&r.vector_reward);
            b.env_reward.extend_from_slice(&r.env_reward);
            b.done.extend_from_slice(&r.done);
            let offset = b.n_traj * n;
            b.timeouts
                .extend(r.timeouts.iter().map(|&i| offset + i as usize));
            b.timeout_obs.extend_from_slice(&r.timeout_obs);
            b.n_traj += r.n_envs;
        }
        b.steps = (b.n_traj * n) as u64;
        if rollouts.iter().any(|r| r.env_reward.is_empty()) {
            b.env_reward.clear();
        }
        Ok(b)
    }

    /// Number of transitions B = T·n.
    pub fn len(&self) -> usize {
        self.n_traj * self.n_steps
    }

    /// True when the batch holds no transitions.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The `ends` of [`crate::returns::n_step_returns`] ([T·n, c]): `values` ([timeouts,
    /// c], the value of each timeout's final observation) at the timeouts, 0 elsewhere.
    pub fn timeout_ends(&self, values: &[f32], c: usize) -> Vec<f32> {
        let mut ends = vec![0.0; self.len() * c];
        for (&i, v) in self.timeouts.iter().zip(values.chunks_exact(c)) {
            ends[i * c..(i + 1) * c].copy_from_slice(v);
        }
        ends
    }

    /// The scalar reward of each transition: the sum of its vector reward.
    pub fn scalar_reward(&self) -> Vec<f32> {
        let d = self.vector_reward.len() / self.len().max(1);
        self.vector_reward
            .chunks_exact(d.max(1))
            .map(|r| r.iter().sum())
            .collect()
    }
}
