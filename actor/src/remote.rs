//! An actor for a learner across the network: registers, acts, and when the learner is
//! lost (restart, cut link) reconnects with jittered backoff and registers again,
//! until the run finishes or the learner stays away too long.

use crate::grpc::GrpcLink;
use crate::{run_actor_with, ActorError, ActorSummary};
use saver_core::link::{LinkError, Registration};
use saver_proto::ClientAccess;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Who to act for, and how.
#[derive(Clone)]
pub struct RemoteActor {
    /// The learner's URL.
    pub learner: String,
    /// Name in the learner's logs.
    pub name: String,
    /// Env instances stepped per rollout.
    pub envs: u32,
    /// Give up after this long without reaching the learner.
    pub give_up: Duration,
    /// Read the weights from the learner's weights directory when it is readable here.
    pub shared_weights: bool,
    /// Token and TLS.
    pub access: ClientAccess,
    /// Added to every env step (an actor slower than the rest; zero: none).
    pub step_delay: Duration,
}

/// Why a remote actor stopped before the run finished.
#[derive(Debug, thiserror::Error)]
pub enum RemoteError {
    /// Acting failed in a way reconnecting cannot mend.
    #[error("{name} at {learner}: {source}")]
    Actor {
        /// The actor.
        name: String,
        /// The learner.
        learner: String,
        /// What failed.
        source: Box<ActorError>,
    },
    /// The learner was unreachable for longer than `give_up`.
    #[error("{name}: no learner at {learner} for {secs} s ({why}); giving up")]
    GaveUp {
        /// The actor.
        name: String,
        /// The learner.
        learner: String,
        /// Seconds waited.
        secs: u64,
        /// The last failure.
        why: String,
    },
}

/// Delay before reconnect attempt `n` (0, 1, …): 100 ms doubling up to 5 s, times a
/// random factor in [0.5, 1) so that actors cut off together do not return together.
pub fn backoff(n: u32) -> Duration {
    let base = 0.1 * 2f64.powi(n.min(6) as i32);
    Duration::from_secs_f64(base.min(5.0) * rand::random_range(0.5..1.0))
}

/// Acts for `a.learner` until the run finishes (or `stop` is set: then a lost link is
/// not reconnected); the totals over every connection that ended without an error.
pub fn run_remote(a: &RemoteActor, stop: &AtomicBool) -> Result<ActorSummary, RemoteError> {
    let mut total = ActorSummary::default();
    let mut attempt = 0u32;
    let mut last_contact = Instant::now();
    let mut said_waiting: Option<Instant> = None;
    loop {
        let reg = Registration {
            name: a.name.clone(),
            session: rand::random(),
            n_envs: a.envs,
        };
        let outcome = GrpcLink::connect_with(&a.learner, &a.access)
            .map(|l| l.with_shared_files(a.shared_weights))
            .map_err(ActorError::from)
            .and_then(|mut link| {
                let make = |s: &saver_core::link::ActorSettings| {
                    let env = crate::preset_env(s)?;
                    Ok(if a.step_delay.is_zero() {
                        env
                    } else {
                        Box::new(crate::slow::SlowEnv {
                            inner: env,
                            delay: a.step_delay,
                        }) as Box<dyn saver_core::env::Env>
                    })
                };
                run_actor_with(&mut link, &reg, stop, &Default::default(), &make)
            });
        let why = match outcome {
            Ok(s) => {
                total.rollouts += s.rollouts;
                total.steps += s.steps;
                total.episodes += s.episodes;
                if s.rollouts > 0 {
                    attempt = 0;
                    last_contact = Instant::now();
                }
                match s.lost {
                    None => return Ok(total),
                    Some(why) => why,
                }
            }
            Err(ActorError::Link(LinkError::Finished(_))) => return Ok(total),
            Err(ActorError::Link(LinkError::Closed(why))) => why,
            Err(ActorError::Link(LinkError::Waiting(why))) => {
                // Up and waiting for its PCPN: no deadline; its progress every 10 s.
                last_contact = Instant::now();
                if said_waiting.is_none_or(|t| t.elapsed() >= Duration::from_secs(10)) {
                    eprintln!("{}: the learner at {} {why}", a.name, a.learner);
                    said_waiting = Some(Instant::now());
                }
                if stop.load(Ordering::Relaxed) {
                    return Ok(total);
                }
                std::thread::sleep(Duration::from_secs(2));
                continue;
            }
            Err(source) => {
                return Err(RemoteError::Actor {
                    name: a.name.clone(),
                    learner: a.learner.clone(),
                    source: Box::new(source),
                })
            }
        };
        if stop.load(Ordering::Relaxed) {
            // Asked to stop: no reconnecting to a learner that went away meanwhile.
            return Ok(total);
        }
        if last_contact.elapsed() > a.give_up {
            return Err(RemoteError::GaveUp {
                name: a.name.clone(),
                learner: a.learner.clone(),
                secs: a.give_up.as_secs(),
                why: why.to_string(),
            });
        }
        let wait = backoff(attempt);
        attempt += 1;
        tracing::warn!("{}: {why}; reconnecting in {wait:?}", a.name);
        std::thread::sleep(wait);
    }
}
