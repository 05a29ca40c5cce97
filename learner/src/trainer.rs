//! The trainer thread: forms sync rounds (one rollout per registered actor at the
//! current version, batched in actor-id order), updates, publishes, logs, checkpoints.
//! It blocks on std primitives and never runs on an async runtime.

use crate::metrics::{EpisodeWindow, MetricsCsv, MetricsRow};
use crate::Hub;
use saver_core::algo::Algorithm;
use saver_core::checkpoint;
use saver_core::config::Mode;
use saver_core::link::PolicyWeights;
use saver_core::rollout::{Batch, Rollout};
use saver_core::{CoreError, Result};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
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
}

/// The running trainer thread.
pub struct TrainerHandle {
    /// The thread.
    pub join: JoinHandle<Result<TrainerOutcome>>,
}

/// Starts the trainer thread. Rows of metrics go to `rows` (for a progress display) as
/// well as to `run_dir/metrics.csv`; `stop` ends the run early with a checkpoint.
pub fn spawn_trainer(
    algo: Box<dyn Algorithm>,
    hub: Arc<Hub>,
    rx: Receiver<Rollout>,
    run_dir: PathBuf,
    rows: Option<Sender<MetricsRow>>,
    stop: Arc<AtomicBool>,
) -> std::io::Result<TrainerHandle> {
    let join = std::thread::Builder::new()
        .name("saver-trainer".into())
        .spawn(move || {
            let res = Trainer {
                algo,
                hub: hub.clone(),
                rx,
                stop,
            }
            .run(&run_dir, rows);
            match &res {
                Ok(_) => hub.close("training finished"),
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

/// Counters saved in checkpoints.
struct Counters {
    version: u64,
    steps: u64,
    episodes: u64,
}

impl Trainer {
    fn run(mut self, run_dir: &Path, rows: Option<Sender<MetricsRow>>) -> Result<TrainerOutcome> {
        let io = |what: &str, e: std::io::Error| CoreError::Checkpoint(format!("{what}: {e}"));
        std::fs::create_dir_all(run_dir).map_err(|e| io("creating run folder", e))?;
        let metrics_path = run_dir.join("metrics.csv");
        let mut csv = MetricsCsv::create(&metrics_path, self.algo.stat_names())
            .map_err(|e| io("creating metrics.csv", e))?;
        let config = self.hub.config().clone();
        let wait = self.hub.wait_for_actors(config.actors as usize);
        let mut window = EpisodeWindow::default();
        let mut c = Counters {
            version: 0,
            steps: 0,
            episodes: 0,
        };
        let mut stale_dropped = 0u64;
        let mut interrupted = wait.is_err();
        let start = Instant::now();
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
            let stats = self.algo.update(&batch)?;
            c.version += 1;
            c.steps += batch.steps;
            self.hub.publish(Arc::new(PolicyWeights {
                version: c.version,
                tensors: self.algo.policy_tensors()?,
            }));
            window.extend(&episodes);
            c.episodes = window.total;
            let wall_s = start.elapsed().as_secs_f64();
            let row = MetricsRow {
                steps: c.steps,
                updates: c.version,
                wall_s,
                steps_per_s: c.steps as f64 / wall_s.max(1e-9),
                mean_ep_len_100: window.mean_all(),
                mean_ep_len_100_actor0: window.mean_actor0(),
                episodes: window.total,
                lag_mean,
                lag_max,
                stale_dropped,
                stats: stats.values,
            };
            csv.write(&row).map_err(|e| io("writing metrics.csv", e))?;
            if let Some(tx) = &rows {
                let _ = tx.send(row);
            }
        }
        let checkpoint = run_dir.join("checkpoint.safetensors");
        self.save_checkpoint(&checkpoint, &c, &config)?;
        Ok(TrainerOutcome {
            version: c.version,
            steps: c.steps,
            wall_s: start.elapsed().as_secs_f64(),
            checkpoint,
            metrics: metrics_path,
            mean_ep_len_100: window.mean_all(),
            stale_dropped,
            interrupted,
        })
    }

    /// The rollouts of the next update; `None` when asked to stop or when every sender
    /// is gone. Sync: one from each registered actor at `version`, in actor-id order.
    /// Async: the next `actors` rollouts whose lag is at most `max_lag`, ordered by
    /// (actor id, sequence number).
    fn collect_round(&mut self, version: u64, stale: &mut u64) -> Option<Round> {
        let config = self.hub.config();
        let (mode, want, max_lag) = (config.mode, config.actors as usize, config.max_lag);
        let mut pending: BTreeMap<(u32, u64), Rollout> = BTreeMap::new();
        loop {
            let expected = match mode {
                Mode::Sync => self.hub.actors().len(),
                Mode::Async => want,
            };
            if expected > 0 && pending.len() >= expected {
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

    fn save_checkpoint(
        &self,
        path: &Path,
        c: &Counters,
        config: &saver_core::config::RunConfig,
    ) -> Result<()> {
        let tensors = checkpoint::to_named_all(&self.algo.state_tensors()?)?;
        let meta = HashMap::from([
            (
                "format".to_string(),
                "saver-learner-checkpoint/1".to_string(),
            ),
            ("version".to_string(), c.version.to_string()),
            ("steps".to_string(), c.steps.to_string()),
            ("episodes".to_string(), c.episodes.to_string()),
            (
                "optimizer_steps".to_string(),
                self.algo.optimizer_steps().to_string(),
            ),
            (
                "config".to_string(),
                serde_json::to_string(config).unwrap_or_default(),
            ),
            ("config_hash".to_string(), config.hash()),
        ]);
        checkpoint::save(path, &tensors, &meta)?;
        Ok(())
    }
}
