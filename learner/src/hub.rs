//! The meeting point of actors and the trainer thread: registrations, the bounded
//! rollout queue and the newest published weights.

use saver_core::config::RunConfig;
use saver_core::env::EnvLayout;
use saver_core::link::{Assignment, LinkError, PolicyWeights, Registration};
use saver_core::rollout::Rollout;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

/// A registered actor.
#[derive(Clone, Debug)]
pub struct ActorInfo {
    /// Name it gave.
    pub name: String,
    /// Its session.
    pub session: u64,
    /// Env instances per rollout.
    pub n_envs: u32,
    /// Sequence number of its last accepted rollout (replays are refused).
    pub last_seq: Option<u64>,
}

/// Counters of the hub, for logs and metrics.
#[derive(Debug, Default)]
pub struct HubStats {
    /// Rollouts accepted into the queue.
    pub accepted: AtomicU64,
    /// Rollouts refused at the edge (bad shape, unknown actor, closed).
    pub rejected: AtomicU64,
    /// Times a sync round went ahead without an actor that missed its deadline.
    pub late: AtomicU64,
}

struct State {
    /// Registered actors by id.
    actors: BTreeMap<u32, ActorInfo>,
    /// Next id to hand out.
    next_id: u32,
    /// Newest weights.
    weights: Arc<PolicyWeights>,
    /// Set when the run is over or the learner stops: every waiter returns this.
    closed: Option<LinkError>,
}

/// Shared state between ingress and the trainer.
pub struct Hub {
    /// The run config handed to actors.
    config: RunConfig,
    /// Its hash.
    config_hash: String,
    /// Env layout (rollouts are checked against it).
    layout: EnvLayout,
    /// Registrations, weights, closed flag.
    state: Mutex<State>,
    /// Signalled on every publish, registration and close.
    changed: Condvar,
    /// Ingress side of the bounded rollout queue.
    queue: SyncSender<Rollout>,
    /// Sync mode: how long a round waits for a registered actor (milliseconds).
    round_timeout_ms: AtomicU64,
    /// Counters.
    pub stats: HubStats,
}

/// How long a sync round waits for a registered actor unless told otherwise.
pub const DEFAULT_ROUND_TIMEOUT: Duration = Duration::from_secs(10);

impl Hub {
    /// A hub with initial weights; returns the trainer's end of the rollout queue.
    /// `queue_depth` bounds the rollouts waiting for the trainer (back-pressure).
    pub fn new(
        config: RunConfig,
        initial: PolicyWeights,
        queue_depth: usize,
    ) -> (Arc<Self>, Receiver<Rollout>) {
        let (tx, rx) = mpsc::sync_channel(queue_depth.max(1));
        let hub = Arc::new(Self {
            config_hash: config.hash(),
            layout: config.env.layout(),
            config,
            state: Mutex::new(State {
                actors: BTreeMap::new(),
                next_id: 0,
                weights: Arc::new(initial),
                closed: None,
            }),
            changed: Condvar::new(),
            queue: tx,
            round_timeout_ms: AtomicU64::new(DEFAULT_ROUND_TIMEOUT.as_millis() as u64),
            stats: HubStats::default(),
        });
        (hub, rx)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panic elsewhere while holding the lock leaves plain data behind; keep going.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The run config.
    pub fn config(&self) -> &RunConfig {
        &self.config
    }

    /// Sync mode: a round waits this long for each registered actor, then goes ahead
    /// with the rollouts it has and leaves the late actors out until they send again.
    pub fn set_round_timeout(&self, timeout: Duration) {
        let ms = u64::try_from(timeout.as_millis())
            .unwrap_or(u64::MAX)
            .max(1);
        self.round_timeout_ms.store(ms, Ordering::Relaxed);
    }

    /// The sync round deadline.
    pub fn round_timeout(&self) -> Duration {
        Duration::from_millis(self.round_timeout_ms.load(Ordering::Relaxed))
    }

    /// Registers an actor: ids are dense and handed out in arrival order.
    pub fn register(&self, reg: &Registration) -> Result<Assignment, LinkError> {
        if reg.n_envs == 0 || reg.n_envs > 1024 {
            return Err(LinkError::Rejected(format!(
                "env count {} is not in 1..=1024",
                reg.n_envs
            )));
        }
        let mut s = self.lock();
        if let Some(why) = &s.closed {
            return Err(why.clone());
        }
        let actor_id = s.next_id;
        s.next_id += 1;
        s.actors.insert(
            actor_id,
            ActorInfo {
                name: reg.name.clone(),
                session: reg.session,
                n_envs: reg.n_envs,
                last_seq: None,
            },
        );
        drop(s);
        self.changed.notify_all();
        tracing::debug!(actor_id, name = %reg.name, "actor registered");
        Ok(Assignment {
            actor_id,
            config: self.config.clone(),
            config_hash: self.config_hash.clone(),
        })
    }

    /// Forgets an actor whose connection closed (only if `session` still matches, so
    /// a newer registration under the same id is kept); sync rounds stop waiting for it.
    pub fn unregister(&self, actor_id: u32, session: u64) {
        let mut s = self.lock();
        if s.actors
            .get(&actor_id)
            .is_some_and(|a| a.session == session)
        {
            s.actors.remove(&actor_id);
            tracing::info!(actor_id, "actor left");
        }
        drop(s);
        self.changed.notify_all();
    }

    /// Registered actors, by id.
    pub fn actors(&self) -> BTreeMap<u32, ActorInfo> {
        self.lock().actors.clone()
    }

    /// Blocks until at least `n` actors are registered, the hub closes or `stop` is set.
    pub fn wait_for_actors(&self, n: usize, stop: &AtomicBool) -> Result<(), LinkError> {
        let mut s = self.lock();
        loop {
            if let Some(why) = &s.closed {
                return Err(why.clone());
            }
            if stop.load(Ordering::Relaxed) {
                return Err(LinkError::Closed("the learner is stopping".into()));
            }
            if s.actors.len() >= n {
                return Ok(());
            }
            s = self
                .changed
                .wait_timeout(s, Duration::from_millis(50))
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    /// Validates a rollout at the edge and queues it for the trainer, waiting while
    /// the queue is full (back-pressure).
    pub fn submit(&self, rollout: Rollout) -> Result<(), LinkError> {
        let mut item = rollout;
        loop {
            match self.try_submit(item)? {
                None => return Ok(()),
                Some(back) => {
                    item = back;
                    let s = self.lock();
                    if let Some(why) = &s.closed {
                        return Err(why.clone());
                    }
                    let _ = self
                        .changed
                        .wait_timeout(s, Duration::from_millis(2))
                        .unwrap_or_else(|e| e.into_inner());
                }
            }
        }
    }

    /// Validates a rollout and queues it without waiting: `Ok(None)` when queued,
    /// `Ok(Some(rollout))` back when the queue is full. Async callers use it and only
    /// fall back to the blocking [`Hub::submit`] when the trainer is behind.
    pub fn try_submit(&self, rollout: Rollout) -> Result<Option<Rollout>, LinkError> {
        if let Err(e) = self.check(&rollout) {
            // A closed learner is not a refusal of the rollout: not counted or logged.
            if !matches!(e, LinkError::Closed(_) | LinkError::Finished(_)) {
                self.stats.rejected.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(
                    actor = rollout.actor_id,
                    seq = rollout.seq,
                    "rollout refused: {e}"
                );
            }
            return Err(e);
        }
        let (id, seq) = (rollout.actor_id, rollout.seq);
        match self.queue.try_send(rollout) {
            Ok(()) => {
                self.stats.accepted.fetch_add(1, Ordering::Relaxed);
                if let Some(a) = self.lock().actors.get_mut(&id) {
                    a.last_seq = Some(seq);
                }
                Ok(None)
            }
            Err(TrySendError::Disconnected(_)) => {
                Err(LinkError::Closed("the trainer has stopped".into()))
            }
            Err(TrySendError::Full(back)) => Ok(Some(back)),
        }
    }

    /// Everything a rollout must satisfy before it is queued: it comes from a
    /// registered actor and session, in sequence, at a published version, with the
    /// run's shapes and finite values.
    fn check(&self, r: &Rollout) -> Result<(), LinkError> {
        let mismatch = |why: String| Err(LinkError::Mismatch(why));
        {
            let s = self.lock();
            if let Some(e) = &s.closed {
                return Err(e.clone());
            }
            let Some(a) = s.actors.get(&r.actor_id) else {
                return mismatch(format!("unknown actor id {}", r.actor_id));
            };
            if a.session != r.session {
                return mismatch(format!(
                    "actor {} sent session {:x}, registered as {:x}",
                    r.actor_id, r.session, a.session
                ));
            }
            if a.last_seq.is_some_and(|last| r.seq <= last) {
                return mismatch(format!(
                    "actor {} sent sequence number {} after {} (a replay)",
                    r.actor_id,
                    r.seq,
                    a.last_seq.unwrap_or(0)
                ));
            }
            if r.policy_version > s.weights.version {
                return mismatch(format!(
                    "policy version {} is newer than the learner's {}",
                    r.policy_version, s.weights.version
                ));
            }
            if a.n_envs as usize != r.n_envs {
                return Err(LinkError::Rejected(format!(
                    "actor {} registered {} envs but sent {}",
                    r.actor_id, a.n_envs, r.n_envs
                )));
            }
        }
        if r.n_steps != self.config.rollout as usize {
            return Err(LinkError::Rejected(format!(
                "rollout has {} steps, this run uses {}",
                r.n_steps, self.config.rollout
            )));
        }
        r.validate(&self.layout)
            .map_err(|e| LinkError::Rejected(e.to_string()))?;
        let max_len = self.config.max_episode_steps;
        if let Some(e) = r.episodes.iter().find(|e| {
            e.actor_id != r.actor_id || e.length == 0 || e.length > max_len || !e.ret.is_finite()
        }) {
            return Err(LinkError::Rejected(format!(
                "episode report {e:?} is impossible (actor {}, lengths 1..={max_len}, finite return)",
                r.actor_id
            )));
        }
        Ok(())
    }

    /// The newest weights.
    pub fn latest(&self) -> Arc<PolicyWeights> {
        self.lock().weights.clone()
    }

    /// Blocks until weights of at least `min_version` exist; returns the newest.
    pub fn wait_weights(&self, min_version: u64) -> Result<Arc<PolicyWeights>, LinkError> {
        self.wait_weights_until(min_version, None)
    }

    /// Like [`Hub::wait_weights`], but waits at most `wait`; then returns the newest.
    pub fn wait_weights_for(
        &self,
        min_version: u64,
        wait: Duration,
    ) -> Result<Arc<PolicyWeights>, LinkError> {
        self.wait_weights_until(min_version, Some(std::time::Instant::now() + wait))
    }

    fn wait_weights_until(
        &self,
        min_version: u64,
        deadline: Option<std::time::Instant>,
    ) -> Result<Arc<PolicyWeights>, LinkError> {
        let mut s = self.lock();
        loop {
            if s.weights.version >= min_version {
                return Ok(s.weights.clone());
            }
            if let Some(why) = &s.closed {
                return Err(why.clone());
            }
            s = match deadline {
                None => self.changed.wait(s).unwrap_or_else(|e| e.into_inner()),
                Some(d) => {
                    let now = std::time::Instant::now();
                    if now >= d {
                        return Ok(s.weights.clone());
                    }
                    self.changed
                        .wait_timeout(s, d - now)
                        .unwrap_or_else(|e| e.into_inner())
                        .0
                }
            };
        }
    }

    /// Publishes a new version: one shared buffer for every reader.
    pub fn publish(&self, weights: Arc<PolicyWeights>) {
        self.lock().weights = weights;
        self.changed.notify_all();
    }

    /// Stops serving (the learner stops or failed): every waiting or future call
    /// returns `Closed(why)`, which tells actors to reconnect later.
    pub fn close(&self, why: &str) {
        self.end(LinkError::Closed(why.to_string()));
    }

    /// Ends the run for good (every step trained): calls return `Finished(why)`, which
    /// tells actors to stop.
    pub fn finish(&self, why: &str) {
        self.end(LinkError::Finished(why.to_string()));
    }

    fn end(&self, e: LinkError) {
        let mut s = self.lock();
        if s.closed.is_none() {
            s.closed = Some(e);
        }
        drop(s);
        self.changed.notify_all();
    }

    /// Why the hub closed, if it did.
    pub fn closed_reason(&self) -> Option<LinkError> {
        self.lock().closed.clone()
    }

    /// Whether the hub is closed.
    pub fn is_closed(&self) -> bool {
        self.lock().closed.is_some()
    }
}
