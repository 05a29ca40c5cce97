//! The meeting point of actors and the trainer thread: registrations, the bounded
//! rollout queue and the newest published weights.

use crate::ledger::{EpisodeRules, Ledger};
use crate::warn::RateLimited;
use saver_core::config::RunConfig;
use saver_core::env::EnvLayout;
use saver_core::limits::RolloutLimits;
use saver_core::link::{ActorSettings, Assignment, LinkError, PolicyWeights, Registration};
use saver_core::rollout::Rollout;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// How long a registration over the network may go without opening its rollout
/// stream before it is forgotten (an actor opens it right after registering).
pub const REGISTRATION_LEASE: Duration = Duration::from_secs(10);
/// Registrations without a stream held at once; a newer one evicts the oldest, so a
/// flood of bare Registers costs bounded memory and never blocks a real actor.
pub const MAX_PENDING: usize = 256;
/// Most env instances one actor may register.
pub const MAX_ENVS: usize = 1024;
/// How often a learner that waits for actors says so.
const WAIT_REPORT: Duration = Duration::from_secs(10);

/// A registered actor.
#[derive(Debug)]
struct ActorInfo {
    /// Name it gave.
    name: String,
    /// Its session.
    session: u64,
    /// Env instances per rollout.
    n_envs: u32,
    /// Sequence number of its last accepted rollout (replays are refused).
    last_seq: Option<u64>,
    /// It holds its rollout stream (in-process actors always do): only such actors
    /// are waited for by rounds and counted as connected.
    attached: bool,
    /// When it registered.
    since: Instant,
    /// Its envs' running episodes as the learner counts them.
    ledger: Ledger,
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
    /// Ledgers of in-process actors resumed from a checkpoint, by id.
    resumed: BTreeMap<u32, Ledger>,
}

/// Shared state between ingress and the trainer.
pub struct Hub {
    /// The run config.
    config: RunConfig,
    /// What actors are told of it.
    settings: ActorSettings,
    /// Env layout (rollouts are checked against it).
    layout: EnvLayout,
    /// The values a rollout may hold.
    limits: RolloutLimits,
    /// Refused rollouts, logged a few at a time.
    refusals: RateLimited,
    /// What every rollout's episodes and positions must agree with.
    rules: EpisodeRules,
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

/// The reason label of a refusal (its google.rpc code, lower case).
pub fn reason(e: &LinkError) -> &'static str {
    match e {
        LinkError::Rejected(_) => "invalid_argument",
        LinkError::Mismatch(_) => "failed_precondition",
        LinkError::TooLarge(_) => "resource_exhausted",
        LinkError::Closed(_) | LinkError::Finished(_) | LinkError::Waiting(_) => "unavailable",
    }
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
            settings: ActorSettings::of(&config),
            layout: config.env.layout(),
            limits: RolloutLimits::new(
                config.env.layout(),
                config.env.bounds(),
                saver_core::algo::policy_family(&config),
            ),
            refusals: RateLimited::default(),
            rules: EpisodeRules {
                max_len: config.max_episode_steps,
                layout: config.env.layout(),
                success: config.env.success_rule(),
                continue_past_success: config.continue_past_success,
            },
            config,
            state: Mutex::new(State {
                actors: BTreeMap::new(),
                next_id: 0,
                weights: Arc::new(initial),
                closed: None,
                resumed: BTreeMap::new(),
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

    /// In-process actors resumed from a checkpoint: their next sequence numbers and
    /// running episodes, so that their episode reports are checked as if the run had
    /// never stopped.
    pub fn resume_actors(&self, actors: &crate::ActorStates) {
        self.lock().resumed = actors
            .iter()
            .map(|(&id, a)| (id, Ledger::resumed(a.seq, &a.running)))
            .collect();
    }

    /// Registers an in-process actor (it is connected from the start): ids are dense
    /// and handed out in arrival order; the session is the learner's secret for it.
    pub fn register(&self, reg: &Registration) -> Result<Assignment, LinkError> {
        self.admit(reg, true)
    }

    /// Registers an actor over the network: it counts once its rollout stream claims
    /// the registration ([`Hub::attach`]); until then it is pending, and forgotten
    /// after [`REGISTRATION_LEASE`] or when [`MAX_PENDING`] newer ones wait.
    pub fn register_remote(&self, reg: &Registration) -> Result<Assignment, LinkError> {
        self.admit(reg, false)
    }

    fn admit(&self, reg: &Registration, attached: bool) -> Result<Assignment, LinkError> {
        if reg.n_envs == 0 || reg.n_envs as usize > MAX_ENVS {
            return Err(LinkError::Rejected(format!(
                "env count {} is not in 1..={MAX_ENVS}",
                reg.n_envs
            )));
        }
        let mut s = self.lock();
        if let Some(why) = &s.closed {
            return Err(why.clone());
        }
        Self::expire(&mut s);
        if !attached && Self::count_pending(&s) >= MAX_PENDING {
            // Ids ascend with time: the first pending one is the oldest.
            if let Some(oldest) = s
                .actors
                .iter()
                .find(|(_, a)| !a.attached)
                .map(|(&id, _)| id)
            {
                s.actors.remove(&oldest);
            }
        }
        let actor_id = s.next_id;
        s.next_id = s.next_id.checked_add(1).ok_or_else(|| {
            LinkError::TooLarge("this learner has handed out every actor id".into())
        })?;
        let session = loop {
            // A secret from the OS-seeded CSPRNG: no other client can guess it.
            let x: u64 = rand::random();
            if x != 0 {
                break x;
            }
        };
        let ledger = s
            .resumed
            .remove(&actor_id)
            .filter(|l| l.n_envs() == reg.n_envs as usize)
            .unwrap_or_else(|| Ledger::fresh(reg.n_envs as usize));
        s.actors.insert(
            actor_id,
            ActorInfo {
                name: reg.name.clone(),
                session,
                n_envs: reg.n_envs,
                last_seq: None,
                attached,
                since: Instant::now(),
                ledger,
            },
        );
        drop(s);
        self.changed.notify_all();
        tracing::debug!(actor_id, name = %reg.name, "actor registered");
        Ok(Assignment {
            actor_id,
            session,
            settings: self.settings.clone(),
        })
    }

    /// The env count of registration (`actor_id`, `session`), if it exists.
    pub fn registered_envs(&self, actor_id: u32, session: u64) -> Option<usize> {
        let s = self.lock();
        let a = s.actors.get(&actor_id).filter(|a| a.session == session)?;
        Some(a.n_envs as usize)
    }

    /// Forgets registrations whose stream never came within the lease.
    fn expire(s: &mut State) {
        s.actors
            .retain(|_, a| a.attached || a.since.elapsed() < REGISTRATION_LEASE);
    }

    /// A rollout stream claims the registration (`actor_id`, `session`): from now on
    /// the actor counts in rounds, until the stream ends ([`Hub::unregister`]). A
    /// registration is claimed once; an unknown or expired one, or a wrong session, is
    /// refused without saying more.
    pub fn attach(&self, actor_id: u32, session: u64) -> Result<String, LinkError> {
        let mut s = self.lock();
        if let Some(why) = &s.closed {
            return Err(why.clone());
        }
        Self::expire(&mut s);
        let name = match s.actors.get_mut(&actor_id) {
            Some(a) if a.session == session && !a.attached => {
                a.attached = true;
                a.name.clone()
            }
            Some(a) if a.session == session => {
                return Err(LinkError::Mismatch(format!(
                    "actor {actor_id} already has a rollout stream"
                )))
            }
            _ => {
                return Err(LinkError::Mismatch(format!(
                    "actor {actor_id} is not registered with that session (expired or \
                     never registered): register again"
                )))
            }
        };
        drop(s);
        self.changed.notify_all();
        tracing::info!(actor_id, name = %name, "actor joined");
        Ok(name)
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
            tracing::info!(actor_id, "actor left (its rollout stream ended)");
        }
        drop(s);
        self.changed.notify_all();
    }

    /// Ids of the connected actors (in-process, or holding their rollout stream).
    pub fn actors(&self) -> BTreeSet<u32> {
        let mut s = self.lock();
        Self::expire(&mut s);
        s.actors
            .iter()
            .filter(|(_, a)| a.attached)
            .map(|(&id, _)| id)
            .collect()
    }

    /// The session of connected actor `actor_id` (its rollout stream attached), if any.
    pub fn session_of(&self, actor_id: u32) -> Option<u64> {
        let s = self.lock();
        let a = s.actors.get(&actor_id).filter(|a| a.attached)?;
        Some(a.session)
    }

    /// Registrations still waiting for their rollout stream.
    pub fn pending(&self) -> usize {
        let mut s = self.lock();
        Self::expire(&mut s);
        Self::count_pending(&s)
    }

    /// The counts the Prometheus gauges show at an update (one look at the state: the
    /// actors attached and those still waiting for their stream).
    pub fn counts(&self) -> crate::metrics::HubCounts {
        let mut s = self.lock();
        Self::expire(&mut s);
        let pending = Self::count_pending(&s);
        crate::metrics::HubCounts {
            streaming: s.actors.len() - pending,
            pending,
            accepted: self.stats.accepted.load(Ordering::Relaxed),
            rejected: self.stats.rejected.load(Ordering::Relaxed),
        }
    }

    fn count_pending(s: &State) -> usize {
        s.actors.values().filter(|a| !a.attached).count()
    }

    /// Blocks until at least `n` actors are connected, the hub closes or `stop` is set,
    /// saying every few seconds what it waits for. With `go_ahead`, after a round
    /// deadline with at least one actor it goes on with those it has (a learner
    /// restarted with fewer actors back than it had).
    pub fn wait_for_actors(
        &self,
        n: usize,
        go_ahead: bool,
        stop: &AtomicBool,
    ) -> Result<(), LinkError> {
        let start = Instant::now();
        let mut said = start;
        let mut s = self.lock();
        loop {
            if let Some(why) = &s.closed {
                return Err(why.clone());
            }
            if stop.load(Ordering::Relaxed) {
                return Err(LinkError::Closed("the learner is stopping".into()));
            }
            Self::expire(&mut s);
            let waiting = Self::count_pending(&s);
            let have = s.actors.len() - waiting;
            if have >= n {
                return Ok(());
            }
            if go_ahead && have > 0 && start.elapsed() >= self.round_timeout() {
                tracing::warn!(
                    "going ahead with {have} of {n} actors after the round deadline \
                     ({:?}); more may join at any time",
                    self.round_timeout()
                );
                return Ok(());
            }
            if said.elapsed() >= WAIT_REPORT {
                said = Instant::now();
                tracing::info!(
                    "waiting for actors: {have} of {n} connected ({waiting} registered \
                     without a rollout stream yet), {:.0} s so far",
                    start.elapsed().as_secs_f64()
                );
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
        let (ledger, verified) = match self.check(&rollout) {
            Ok(v) => v,
            Err(e) => {
                // A closed learner is not a refusal of the rollout: not counted or logged.
                if !matches!(e, LinkError::Closed(_) | LinkError::Finished(_)) {
                    self.refused(Some(rollout.actor_id), reason(&e), &e);
                }
                return Err(e);
            }
        };
        let (id, seq) = (rollout.actor_id, rollout.seq);
        let mut rollout = rollout;
        for (e, v) in rollout.episodes.iter_mut().zip(&verified) {
            e.verified = *v;
        }
        match self.queue.try_send(rollout) {
            Ok(()) => {
                self.stats.accepted.fetch_add(1, Ordering::Relaxed);
                ::metrics::counter!("saver_rollouts_accepted_total").increment(1);
                // Rollouts waiting for the trainer (it takes them off: trainer.rs).
                ::metrics::gauge!("saver_rollout_queue").increment(1.0);
                if let Some(a) = self.lock().actors.get_mut(&id) {
                    a.last_seq = Some(seq);
                    a.ledger = ledger;
                }
                Ok(None)
            }
            Err(TrySendError::Disconnected(_)) => {
                Err(LinkError::Closed("the trainer has stopped".into()))
            }
            Err(TrySendError::Full(back)) => Ok(Some(back)),
        }
    }

    /// Counts a refused rollout (or stream: `actor` when it named one) and logs it,
    /// a few lines at a time.
    pub fn refused(&self, actor: Option<u32>, reason: &'static str, why: &dyn std::fmt::Display) {
        self.stats.rejected.fetch_add(1, Ordering::Relaxed);
        ::metrics::counter!("saver_rollouts_rejected_total", "reason" => reason).increment(1);
        self.refusals.warn(|| match actor {
            Some(id) => format!("rollout of actor {id} refused: {why}"),
            None => format!("rollout refused: {why}"),
        });
    }

    /// Everything a rollout must satisfy before it is queued: it comes from a
    /// registered actor and session, in sequence, at a published version, with the
    /// run's shapes, values in the env's and head's ranges, and episode reports that
    /// agree with the steps the learner counted. Returns the actor's ledger after it
    /// and which episodes were verified.
    fn check(&self, r: &Rollout) -> Result<(Ledger, Vec<bool>), LinkError> {
        let mismatch = |why: String| Err(LinkError::Mismatch(why));
        let ledger = {
            let s = self.lock();
            if let Some(e) = &s.closed {
                return Err(e.clone());
            }
            // Neither text names the registered session: it is that actor's secret.
            let Some(a) = s.actors.get(&r.actor_id).filter(|a| a.session == r.session) else {
                return mismatch(format!(
                    "actor {} is not registered with that session: register again",
                    r.actor_id
                ));
            };
            if let Some(last) = a.last_seq.filter(|&last| r.seq <= last) {
                return mismatch(format!(
                    "actor {} sent sequence number {} after {last} (a replay)",
                    r.actor_id, r.seq
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
            a.ledger.clone()
        };
        if r.n_steps != self.config.rollout as usize {
            return Err(LinkError::Rejected(format!(
                "rollout has {} steps, this run uses {}",
                r.n_steps, self.config.rollout
            )));
        }
        let rejected = |e: saver_core::CoreError| LinkError::Rejected(e.to_string());
        r.validate(&self.layout, self.settings.policy.payload_width())
            .map_err(rejected)?;
        self.limits.check(r).map_err(rejected)?;
        ledger.check(r, &self.rules).map_err(rejected)
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
