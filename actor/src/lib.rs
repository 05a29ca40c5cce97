//! saver-actor: steps N env instances with the newest policy and ships rollouts
//! through a [`LearnerLink`] (in-process or gRPC — the actor does not know which).

pub mod grpc;
pub mod remote;

use saver_core::config::{Mode, RunConfig};
use saver_core::env::{Env, EnvLayout};
use saver_core::link::{Assignment, LearnerLink, LinkError, Registration};
use saver_core::nets::{Action, Policy};
use saver_core::rng::{rng_for, streams, SaverRng};
use saver_core::rollout::{ActorState, Episode, Rollout};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// Errors of an actor.
#[derive(Debug, thiserror::Error)]
pub enum ActorError {
    /// The link failed (other than a normal close).
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The published weights do not fit the env.
    #[error(transparent)]
    Core(#[from] saver_core::CoreError),
}

/// What an actor did, for logs and tests.
#[derive(Debug, Default, Clone)]
pub struct ActorSummary {
    /// Rollouts the learner accepted.
    pub rollouts: u64,
    /// Env steps taken.
    pub steps: u64,
    /// Episodes finished.
    pub episodes: u64,
    /// Version of the first weights it acted with.
    pub first_version: u64,
    /// Why the link was lost before the run finished (`None`: finished or stopped);
    /// the caller may reconnect and register again.
    pub lost: Option<String>,
}

/// One actor: its envs, their current observations and episode counters.
pub struct Actor {
    /// Id from registration.
    id: u32,
    /// Session sent with every rollout.
    session: u64,
    /// The envs.
    envs: Vec<Box<dyn Env>>,
    /// Current observation per env.
    obs: Vec<Vec<f32>>,
    /// Steps and scalar return of the running episode per env.
    running: Vec<(u32, f32)>,
    /// Resets and action noise (seed + actor id stream).
    rng: SaverRng,
    /// Env layout.
    layout: EnvLayout,
    /// Rollout length n.
    n_steps: usize,
    /// Next sequence number.
    seq: u64,
}

impl Actor {
    /// An actor for an assignment, with `n_envs` fresh envs reset from its own stream.
    pub fn new(assignment: &Assignment, n_envs: usize) -> Self {
        let c: &RunConfig = &assignment.config;
        let layout = c.env.layout();
        let mut rng = rng_for(c.seed, streams::ACTOR_BASE + assignment.actor_id as u64);
        let mut envs = Vec::with_capacity(n_envs);
        let mut obs = Vec::with_capacity(n_envs);
        for _ in 0..n_envs {
            let mut env = c.env.make(c.max_episode_steps);
            let mut o = vec![0.0; layout.obs_dim];
            env.reset(&mut rng, &mut o);
            envs.push(env);
            obs.push(o);
        }
        Self {
            id: assignment.actor_id,
            session: assignment.session,
            envs,
            obs,
            running: vec![(0, 0.0); n_envs],
            rng,
            layout,
            n_steps: c.rollout as usize,
            seq: 0,
        }
    }

    /// Steps every env n times with `policy`; resets envs whose episode ends.
    pub fn collect(&mut self, policy: &mut Policy) -> Rollout {
        let (e, n, l) = (self.envs.len(), self.n_steps, self.layout);
        let mut r = Rollout {
            actor_id: self.id,
            session: self.session,
            seq: self.seq,
            policy_version: policy.version(),
            n_envs: e,
            n_steps: n,
            obs: Vec::with_capacity(e * (n + 1) * l.obs_dim),
            mu: Vec::with_capacity(e * n * l.mu_dim()),
            log_std: Vec::with_capacity(e * n * l.log_std_dim()),
            actions: Vec::with_capacity(e * n * l.action_dim()),
            state_delta: Vec::with_capacity(e * n * l.aligned_dim),
            vector_reward: Vec::with_capacity(e * n * l.aligned_dim),
            done: Vec::with_capacity(e * n),
            timeouts: Vec::new(),
            timeout_obs: Vec::new(),
            episodes: Vec::new(),
            actor_state: None,
        };
        self.seq += 1;
        let mut act = Action::default();
        // Env-major layout: all n steps of env 0, then env 1, … (envs are independent).
        for i in 0..e {
            for t in 0..n {
                r.obs.extend_from_slice(&self.obs[i]);
                policy.act(&self.obs[i], &mut self.rng, &mut act);
                let step = self.envs[i].step(&act.action, &mut self.obs[i]);
                r.mu.extend_from_slice(&act.mu);
                r.log_std.extend_from_slice(&act.log_std);
                r.actions.extend_from_slice(&act.action);
                r.state_delta.extend_from_slice(&step.state_delta);
                r.vector_reward.extend_from_slice(&step.vector_reward);
                r.done.push(step.done());
                let run = &mut self.running[i];
                run.0 += 1;
                run.1 += step.vector_reward.iter().sum::<f32>();
                if step.timeout {
                    r.timeouts.push((i * n + t) as u32);
                    r.timeout_obs.extend_from_slice(&self.obs[i]);
                }
                if step.done() {
                    r.episodes.push(Episode {
                        actor_id: self.id,
                        length: run.0,
                        success: step.success,
                        ret: run.1,
                        verified: true,
                    });
                    *run = (0, 0.0);
                    self.envs[i].reset(&mut self.rng, &mut self.obs[i]);
                }
            }
            r.obs.extend_from_slice(&self.obs[i]);
        }
        r.actor_state = Some(Arc::new(self.state()));
        r
    }

    /// Its state between rollouts (for the learner's checkpoint).
    pub fn state(&self) -> ActorState {
        ActorState {
            envs: self.envs.iter().map(|e| e.snapshot()).collect(),
            obs: self.obs.clone(),
            running: self.running.clone(),
            rng_word_pos: self.rng.get_word_pos(),
            seq: self.seq,
        }
    }

    /// Puts the actor back into a saved state (same env count).
    pub fn restore(&mut self, s: &ActorState) -> Result<(), saver_core::CoreError> {
        let n = self.envs.len();
        if s.envs.len() != n || s.obs.len() != n || s.running.len() != n {
            return Err(saver_core::CoreError::Checkpoint(format!(
                "a saved actor with {} envs cannot resume one with {n}",
                s.envs.len()
            )));
        }
        for (env, state) in self.envs.iter_mut().zip(&s.envs) {
            env.restore(state)?;
        }
        if s.obs.iter().any(|o| o.len() != self.layout.obs_dim) {
            return Err(saver_core::CoreError::Checkpoint(
                "a saved observation has the wrong length".into(),
            ));
        }
        self.obs = s.obs.clone();
        self.running = s.running.clone();
        self.rng.set_word_pos(s.rng_word_pos);
        self.seq = s.seq;
        Ok(())
    }
}

/// Registers through `link` and acts until the run finishes, the link is lost
/// ([`ActorSummary::lost`]) or `stop` is set.
/// Sync mode: after each rollout the actor waits for the next version; async mode: it
/// goes on with the newest weights it has.
pub fn run_actor(
    link: &mut dyn LearnerLink,
    reg: &Registration,
    stop: &AtomicBool,
) -> Result<ActorSummary, ActorError> {
    run_actor_from(link, reg, stop, &BTreeMap::new())
}

/// [`run_actor`] for a resumed run: an actor whose id has a state in `saved` (from
/// the learner's checkpoint) continues from it instead of starting its envs afresh.
pub fn run_actor_from(
    link: &mut dyn LearnerLink,
    reg: &Registration,
    stop: &AtomicBool,
    saved: &BTreeMap<u32, ActorState>,
) -> Result<ActorSummary, ActorError> {
    let assignment = link.register(reg)?;
    let layout = assignment.config.env.layout();
    let mut actor = Actor::new(&assignment, reg.n_envs as usize);
    if let Some(s) = saved.get(&assignment.actor_id) {
        actor.restore(s)?;
    }
    let mut summary = ActorSummary::default();
    let mut want = 0u64;
    let mut pace = Pace::default();
    while !stop.load(Ordering::Relaxed) {
        let got = match assignment.config.mode {
            Mode::Sync => link.weights(want),
            Mode::Async if summary.rollouts == 0 => link.weights(0),
            Mode::Async => link.weights_within(want, pace.wait()),
        };
        let weights = match got {
            Ok(w) => w,
            Err(LinkError::Finished(_)) => break,
            Err(LinkError::Closed(why)) => {
                summary.lost = Some(why);
                break;
            }
            Err(e) => return Err(e.into()),
        };
        if summary.rollouts == 0 {
            summary.first_version = weights.version;
        }
        pace.saw(weights.version);
        let mut policy = Policy::new(weights, layout, assignment.config.head)?;
        let rollout = actor.collect(&mut policy);
        summary.steps += (rollout.n_envs * rollout.n_steps) as u64;
        summary.episodes += rollout.episodes.len() as u64;
        match link.push(rollout) {
            Ok(()) => summary.rollouts += 1,
            Err(LinkError::Finished(_)) => break,
            Err(LinkError::Closed(why)) => {
                summary.lost = Some(why);
                break;
            }
            Err(e) => return Err(e.into()),
        }
        want = policy.version() + 1;
    }
    Ok(summary)
}

/// Async mode: how long an actor waits for a newer version before it acts again with
/// the one it has: about two of the learner's update intervals as the actor sees
/// them, so that a fast learner gets about one rollout per actor and version (not a
/// flood of rollouts that go stale in the queue) and a slow one is not waited for.
struct Pace {
    /// Smoothed seconds between versions.
    interval: f64,
    /// Last version seen, and when it first arrived.
    last: Option<(u64, std::time::Instant)>,
}

impl Default for Pace {
    fn default() -> Self {
        Self {
            interval: 0.01,
            last: None,
        }
    }
}

impl Pace {
    fn saw(&mut self, version: u64) {
        let now = std::time::Instant::now();
        match self.last {
            Some((v, at)) if version > v => {
                let per = now.duration_since(at).as_secs_f64() / (version - v) as f64;
                self.interval = 0.8 * self.interval + 0.2 * per;
                self.last = Some((version, now));
            }
            Some(_) => {}
            None => self.last = Some((version, now)),
        }
    }

    fn wait(&self) -> std::time::Duration {
        std::time::Duration::from_secs_f64((2.0 * self.interval).clamp(0.002, 0.5))
    }
}
