//! The trainer thread (docs/ALGORITHM.md §11): forms sync rounds (one rollout per registered actor at the
//! current version, batched in actor-id order), updates, publishes, logs, checkpoints.
//! It blocks on std primitives and never runs on an async runtime.

use crate::best::{Evaluator, PolicyFiles};
use crate::checkpoint::{save, ActorStates, Counters, RunState, CHECKPOINT_FILE};
use crate::metrics::MetricsRow;
use crate::sinks::{io_error, Sinks};
use crate::warn::RateLimited;
use crate::Hub;
use saver_core::algo::Algorithm;
use saver_core::config::Mode;
use saver_core::link::PolicyWeights;
use saver_core::rollout::{Batch, Rollout};
use saver_core::{CoreError, Result};
use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// What a finished trainer leaves behind.
#[derive(Debug)]
pub struct TrainerOutcome {
    /// Final weights version.
    pub version: u64,
    /// Env steps trained on.
    pub steps: u64,
    /// Wall seconds of training.
    pub wall_s: f64,
    /// Wall seconds of training in this process (`wall_s` less a resumed run's earlier
    /// processes).
    pub own_wall_s: f64,
    /// Seconds of `own_wall_s` in the algorithm's updates (the rest: waiting for
    /// rollouts, publishing weights, checkpoints).
    pub update_s: f64,
    /// The final checkpoint.
    pub checkpoint: PathBuf,
    /// metrics.csv.
    pub metrics: PathBuf,
    /// Mean length of the last 100 episodes at the end.
    pub mean_ep_len_100: Option<f64>,
    /// Rollouts dropped for carrying another version than the round's.
    pub stale_dropped: u64,
    /// Whether the run stopped early on request.
    pub interrupted: bool,
    /// Updates skipped because their batch made a loss or gradient non-finite.
    pub skipped: u64,
}

/// The running trainer thread.
pub struct TrainerHandle {
    /// The thread.
    pub join: JoinHandle<Result<TrainerOutcome>>,
}

/// How a trainer runs besides its algorithm and hub.
pub struct TrainerOptions {
    /// Run folder: metrics.csv and checkpoint.safetensors.
    pub run_dir: PathBuf,
    /// Metrics rows also go here (for a progress display).
    pub rows: Option<Sender<MetricsRow>>,
    /// Set to end the run early (with a checkpoint).
    pub stop: Arc<AtomicBool>,
    /// Write the checkpoint every this many updates too (0: only at the end).
    pub checkpoint_every: u64,
    /// Where the run starts: from zero, or where a resumed checkpoint left it (see
    /// [`crate::resume`]): counters, in-process actors, episode window.
    pub start: RunState,
    /// Evaluates the policy every `eval_every` updates and at the end, keeping
    /// best.safetensors ([`crate::best`]); `None`: no evaluation (a custom env, which
    /// only its actors can step).
    pub evaluator: Option<Evaluator>,
    /// Updates between evaluations.
    pub eval_every: u64,
}

impl TrainerOptions {
    /// A fresh run into `run_dir`: no periodic checkpoints, counters from zero.
    pub fn new(run_dir: PathBuf, stop: Arc<AtomicBool>) -> Self {
        Self {
            run_dir,
            rows: None,
            stop,
            checkpoint_every: 0,
            start: RunState::default(),
            evaluator: None,
            eval_every: 0,
        }
    }
}

/// Starts the trainer thread. Rows of metrics go to `run_dir/metrics.csv` (and to
/// `opts.rows`); `opts.stop` ends the run early with a checkpoint.
pub fn spawn_trainer(
    algo: Box<dyn Algorithm>,
    hub: Arc<Hub>,
    rx: Receiver<Rollout>,
    mut opts: TrainerOptions,
) -> std::io::Result<TrainerHandle> {
    let join = std::thread::Builder::new()
        .name("saver-trainer".into())
        .spawn(move || {
            let files = PolicyFiles::new(
                &opts.run_dir,
                saver_core::link::weights_metadata(hub.config()),
                opts.evaluator.take(),
            );
            let res = Trainer {
                algo,
                hub: hub.clone(),
                rx,
                stop: opts.stop.clone(),
                late: BTreeSet::new(),
                files,
            }
            .run(&opts);
            match &res {
                Ok(o) if o.interrupted => hub.close("the learner is stopping"),
                Ok(_) => hub.finish("training finished"),
                Err(e) => hub.close(&format!("learner failed: {e}")),
            }
            res
        })?;
    Ok(TrainerHandle { join })
}

struct Trainer {
    algo: Box<dyn Algorithm>,
    hub: Arc<Hub>,
    rx: Receiver<Rollout>,
    stop: Arc<AtomicBool>,
    /// Sync mode: actors that missed a round's deadline; rounds stop waiting for them
    /// until they send again.
    late: BTreeSet<u32>,
    /// policy.safetensors, best.safetensors and eval.csv.
    files: PolicyFiles,
}

/// The rollouts of one update and their policy lag.
struct Round {
    /// In batch order.
    rollouts: Vec<Rollout>,
    /// Mean versions behind the learner.
    lag_mean: f64,
    /// Largest lag.
    lag_max: u64,
}

impl Trainer {
    fn run(mut self, opts: &TrainerOptions) -> Result<TrainerOutcome> {
        let run_dir = &opts.run_dir;
        std::fs::create_dir_all(run_dir).map_err(|e| io_error("creating run folder", e))?;
        let RunState {
            counters: mut c,
            // Sync mode: the actors' states after the last round, saved with the
            // weights they lead to, so that a resumed run continues exactly.
            mut actors,
            mut window,
        } = opts.start.clone();
        let resumed = c != Counters::default();
        let config = self.hub.config().clone();
        let mut sinks = Sinks::open(
            run_dir,
            self.algo.stat_names(),
            resumed,
            &config,
            opts.rows.clone(),
        )?;
        let wait = self
            .hub
            .wait_for_actors(config.actors as usize, resumed, &self.stop);
        let mut skipped = 0u64;
        let skip_warning = RateLimited::default();
        let checkpoint = run_dir.join(CHECKPOINT_FILE);
        let save_to = |algo: &dyn Algorithm, c: &Counters, actors: &ActorStates, w: &_| {
            save(&checkpoint, algo, c, actors, w, &config)
        };
        let mut stale_dropped = 0u64;
        let mut interrupted = wait.is_err();
        let start = Instant::now();
        let mut update_s = 0.0;
        // Training time before this process: rates go on across a resume.
        let wall_before = c.wall_ms as f64 / 1000.0;
        while !interrupted && c.steps < config.steps {
            let Some(Round {
                rollouts: round,
                lag_mean,
                lag_max,
            }) = self.collect_round(c.version, &mut stale_dropped)
            else {
                interrupted = true;
                break;
            };
            let episodes: Vec<_> = round
                .iter()
                .flat_map(|r| r.episodes.iter().copied())
                .collect();
            let batch = Batch::from_rollouts(&round, &config.env.layout())?;
            // A batch whose loss or gradient is not finite changed nothing: it is
            // skipped, and the same weights go out as the next version (sync actors
            // wait for one).
            let update_start = std::time::Instant::now();
            let updated = self.algo.update(&batch);
            let took = update_start.elapsed().as_secs_f64();
            update_s += took;
            ::metrics::histogram!("saver_update_seconds").record(took);
            let stats = match updated {
                Ok(stats) => Some(stats),
                Err(CoreError::NonFinite(why)) => {
                    skipped += 1;
                    let ids: Vec<u32> = round.iter().map(|r| r.actor_id).collect();
                    skip_warning.warn(|| {
                        format!(
                            "update {} skipped ({skipped} so far): {why}; the batch came from \
                             actors {ids:?}; the weights stay as they were",
                            c.version + 1
                        )
                    });
                    None
                }
                Err(e) => return Err(e),
            };
            c.version += 1;
            if config.mode == Mode::Sync {
                actors = round
                    .iter()
                    .filter_map(|r| Some((r.actor_id, r.actor_state.as_deref()?.clone())))
                    .collect();
            }
            window.extend(&episodes);
            c.episodes += episodes.len() as u64;
            let wall_s = wall_before + start.elapsed().as_secs_f64();
            c.wall_ms = (wall_s * 1000.0).round() as u64;
            if let Some(stats) = stats {
                c.steps += batch.steps;
                let row = MetricsRow {
                    steps: c.steps,
                    updates: c.version,
                    wall_s,
                    steps_per_s: c.steps as f64 / wall_s.max(1e-9),
                    mean_ep_len_100: window.mean_all(),
                    mean_ep_len_100_actor0: window.mean_actor0(),
                    episodes: c.episodes,
                    lag_mean,
                    lag_max,
                    stale_dropped,
                    skipped_updates: skipped,
                    stats: sinks.columns(&stats),
                };
                sinks.write(row, &stats, &episodes, self.hub.counts())?;
            }
            // Finite: the optimiser never writes a non-finite value.
            self.hub.publish(Arc::new(PolicyWeights {
                version: c.version,
                tensors: self.algo.policy_tensors()?,
            }));
            if opts.checkpoint_every > 0 && c.version.is_multiple_of(opts.checkpoint_every) {
                save_to(self.algo.as_ref(), &c, &actors, &window)?;
                // The newest weights beside it, for any client.
                self.files.save_newest(&self.hub.latest())?;
            }
            if opts.eval_every > 0 && c.version.is_multiple_of(opts.eval_every) {
                self.files.evaluate(c.steps, self.hub.latest())?;
            }
        }
        let own_wall_s = start.elapsed().as_secs_f64();
        c.wall_ms = ((wall_before + own_wall_s) * 1000.0).round() as u64;
        save_to(self.algo.as_ref(), &c, &actors, &window)?;
        self.files.save_newest(&self.hub.latest())?;
        if c.version > 0 {
            self.files.evaluate(c.steps, self.hub.latest())?;
        }
        Ok(TrainerOutcome {
            version: c.version,
            steps: c.steps,
            wall_s: c.wall_ms as f64 / 1000.0,
            own_wall_s,
            update_s,
            checkpoint,
            metrics: run_dir.join("metrics.csv"),
            mean_ep_len_100: window.mean_all(),
            stale_dropped,
            interrupted,
            skipped,
        })
    }

    /// The rollouts of the next update; `None` when asked to stop or when every sender
    /// is gone. Sync: one from each registered actor at `version`, in actor-id order;
    /// an actor that misses the round deadline is left out (and not waited for again
    /// until it sends). Async: the next `actors` rollouts whose lag is at most
    /// `max_lag`, ordered by (actor id, sequence number).
    fn collect_round(&mut self, version: u64, stale: &mut u64) -> Option<Round> {
        let config = self.hub.config();
        let (mode, want, max_lag) = (config.mode, config.actors as usize, config.lag_limit());
        let timeout = self.hub.round_timeout();
        let mut deadline = Instant::now() + timeout;
        let mut pending: BTreeMap<(u32, u64), Rollout> = BTreeMap::new();
        loop {
            let complete = match mode {
                Mode::Sync => {
                    let live = self.hub.actors();
                    self.late.retain(|id| live.contains(id));
                    let missing: Vec<u32> = live
                        .iter()
                        .filter(|id| !self.late.contains(id) && !pending.contains_key(&(**id, 0)))
                        .copied()
                        .collect();
                    let expired = Instant::now() >= deadline;
                    if expired && !pending.is_empty() && !missing.is_empty() {
                        tracing::warn!(
                            version,
                            ?missing,
                            "sync round deadline ({timeout:?}) passed: going ahead without \
                             these actors until they send again"
                        );
                        self.hub
                            .stats
                            .late
                            .fetch_add(missing.len() as u64, Ordering::Relaxed);
                        self.late.extend(&missing);
                    } else if expired && pending.is_empty() {
                        if live.is_empty() {
                            tracing::warn!(version, "every actor is gone; waiting for actors");
                        } else {
                            tracing::warn!(version, actors = live.len(), "no rollout yet");
                        }
                        deadline = Instant::now() + timeout;
                    }
                    !pending.is_empty() && (missing.is_empty() || expired)
                }
                Mode::Async => pending.len() >= want,
            };
            if complete {
                let rollouts: Vec<Rollout> = pending.into_values().collect();
                let lags: Vec<u64> = rollouts
                    .iter()
                    .map(|r| version - r.policy_version)
                    .collect();
                return Some(Round {
                    lag_mean: lags.iter().sum::<u64>() as f64 / lags.len() as f64,
                    lag_max: lags.into_iter().max().unwrap_or(0),
                    rollouts,
                });
            }
            if self.stop.load(Ordering::Relaxed) || self.hub.is_closed() {
                return None;
            }
            match self.rx.recv_timeout(Duration::from_millis(50)) {
                Ok(r) => {
                    ::metrics::gauge!("saver_rollout_queue").decrement(1.0);
                    if self.late.remove(&r.actor_id) {
                        tracing::info!(actor = r.actor_id, "late actor is back");
                    }
                    let fresh = match mode {
                        Mode::Sync => r.policy_version == version,
                        Mode::Async => {
                            r.policy_version <= version && version - r.policy_version <= max_lag
                        }
                    };
                    if !fresh {
                        *stale += 1;
                        tracing::debug!(
                            actor = r.actor_id,
                            v = r.policy_version,
                            version,
                            "stale rollout dropped"
                        );
                        continue;
                    }
                    let key = match mode {
                        Mode::Sync => (r.actor_id, 0),
                        Mode::Async => (r.actor_id, r.seq),
                    };
                    if pending.insert(key, r).is_some() {
                        *stale += 1;
                    }
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => return None,
            }
        }
    }
}
