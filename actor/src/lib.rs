//! saver-actor: steps N env instances with the newest policy and ships rollouts
//! through a [`LearnerLink`] (in-process or gRPC — the actor does not know which).

pub mod grpc;
pub mod remote;
pub mod slow;

use saver_core::acting::ActingPolicy;
use saver_core::config::Mode;
use saver_core::env::{Env, EnvLayout};
use saver_core::link::{ActorSettings, Assignment, LearnerLink, LinkError, Registration};
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
    /// Payload values per step.
    payload_width: usize,
    /// Rollout length n.
    n_steps: usize,
    /// Next sequence number.
    seq: u64,
}

/// Makes one env for a run (any [`Env`] whose layout is the run's).
pub type EnvMaker<'a> = &'a dyn Fn(&ActorSettings) -> Result<Box<dyn Env>, saver_core::CoreError>;

/// The built-in preset the run names.
pub fn preset_env(s: &ActorSettings) -> Result<Box<dyn Env>, saver_core::CoreError> {
    s.env.make(s.max_episode_steps)
}

impl Actor {
    /// An actor for an assignment, with `n_envs` fresh preset envs reset from its own
    /// stream (refused for a custom env, whose actors bring it: [`Actor::with_envs`]).
    pub fn new(assignment: &Assignment, n_envs: usize) -> Result<Self, saver_core::CoreError> {
        let envs = (0..n_envs)
            .map(|_| preset_env(&assignment.settings))
            .collect::<Result<_, _>>()?;
        Self::with_envs(assignment, envs)
    }

    /// An actor for an assignment over the given envs (refused when one's layout is
    /// not the run's), each reset from the actor's own stream.
    pub fn with_envs(
        assignment: &Assignment,
        mut envs: Vec<Box<dyn Env>>,
    ) -> Result<Self, saver_core::CoreError> {
        let s = &assignment.settings;
        let layout = s.env.layout();
        if let Some(bad) = envs.iter().find(|e| e.layout() != layout) {
            return Err(saver_core::CoreError::Config(format!(
                "an env of layout {:?} cannot act in {} (layout {layout:?})",
                bad.layout(),
                s.env
            )));
        }
        let mut rng = rng_for(s.seed, streams::ACTOR_BASE + assignment.actor_id as u64);
        let mut obs = Vec::with_capacity(envs.len());
        for env in envs.iter_mut() {
            let mut o = vec![0.0; layout.obs_dim];
            env.reset(&mut rng, &mut o);
            obs.push(o);
        }
        let n_envs = envs.len();
        Ok(Self {
            id: assignment.actor_id,
            session: assignment.session,
            envs,
            obs,
            running: vec![(0, 0.0); n_envs],
            rng,
            layout,
            payload_width: s.policy.payload_width(),
            n_steps: s.rollout as usize,
            seq: 0,
        })
    }

    /// Steps every env n times with `policy`; resets envs whose episode ends.
    pub fn collect(&mut self, policy: &mut dyn ActingPolicy) -> Rollout {
        let (e, n, l) = (self.envs.len(), self.n_steps, self.layout);
        let mut r = Rollout {
            actor_id: self.id,
            session: self.session,
            seq: self.seq,
            policy_version: policy.version(),
            n_envs: e,
            n_steps: n,
            obs: Vec::with_capacity(e * (n + 1) * l.obs_dim),
            payload: Vec::with_capacity(e * n * self.payload_width),
            actions: Vec::with_capacity(e * n * l.action_dim()),
            state_delta: Vec::with_capacity(e * n * l.aligned_dim),
            vector_reward: Vec::with_capacity(e * n * l.aligned_dim),
            env_reward: vec![],
            done: Vec::with_capacity(e * n),
            timeouts: Vec::new(),
            timeout_obs: Vec::new(),
            episodes: Vec::new(),
            actor_state: None,
        };
        self.seq += 1;
        let (mut action, mut payload) = (Vec::new(), Vec::new());
        // Env-major layout: all n steps of env 0, then env 1, … (envs are independent).
        for i in 0..e {
            for t in 0..n {
                r.obs.extend_from_slice(&self.obs[i]);
                policy.act(&self.obs[i], &mut self.rng, &mut action, &mut payload);
                let step = self.envs[i].step(&action, &mut self.obs[i]);
                r.payload.extend_from_slice(&payload);
                r.actions.extend_from_slice(&action);
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
    run_actor_with(link, reg, stop, saved, &preset_env)
}

/// [`run_actor_from`] over envs that `make_env` makes for the run (a user's own
/// environment, say), `reg.n_envs` of them.
pub fn run_actor_with(
    link: &mut dyn LearnerLink,
    reg: &Registration,
    stop: &AtomicBool,
    saved: &BTreeMap<u32, ActorState>,
    make_env: EnvMaker<'_>,
) -> Result<ActorSummary, ActorError> {
    let assignment = link.register(reg)?;
    let envs = (0..reg.n_envs)
        .map(|_| make_env(&assignment.settings))
        .collect::<Result<Vec<_>, _>>()?;
    let mut actor = Actor::with_envs(&assignment, envs)?;
    if let Some(s) = saved.get(&assignment.actor_id) {
        actor.restore(s)?;
    }
    let mut summary = ActorSummary::default();
    let mut want = 0u64;
    let mut pace = Pace::default();
    while !stop.load(Ordering::Relaxed) {
        let got = match assignment.settings.mode {
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
        let mut policy = assignment.settings.policy.acting(weights)?;
        let rollout = actor.collect(policy.as_mut());
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
