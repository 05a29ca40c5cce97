//! `saver train`: the embedded run. One process holds the PCPN, the learner's trainer
//! thread and the actors (threads over the in-process link); the same learner and actor
//! code serve the distributed roles.

use crate::config::TrainArgs;
use crate::plot::plot_runs;
use crate::pretrain::pcpn_for_run;
use crate::progress::Progress;
use anyhow::{anyhow, Context, Result};
use saver_actor::run_actor_from;
use saver_core::config::RunConfig;
use saver_core::link::{PolicyWeights, Registration};
use saver_core::nets::Pcpn;
use saver_learner::{
    spawn_trainer, ActorStates, Counters, Hub, InProcessLink, MetricsRow, TrainerHandle,
    TrainerOptions, TrainerOutcome,
};
use saver_pcpn_trainer::PcpnStore;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{SystemTime, UNIX_EPOCH};

/// Runs `saver train` from flags.
pub fn run(args: TrainArgs) -> Result<()> {
    let mut config = args.run.resolve()?;
    // An env this build cannot step fails before the run folder is made (its actors
    // would fail at once and end the run).
    config.env.make(config.max_episode_steps)?;
    let out = args.out.clone().unwrap_or_else(|| default_run_dir(&config));
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    // A second Ctrl-C while the checkpoint is written falls through to the default.
    let _ = ctrlc::set_handler(move || {
        if flag.swap(true, Ordering::SeqCst) {
            std::process::exit(130);
        }
        eprintln!("\nstopping: finishing the current update and writing a checkpoint…");
    });
    let outcome = train(
        &mut config,
        &out,
        &args.pcpn_dir,
        args.pcpn.as_deref(),
        stop,
        true,
    )?;
    report(&config, &outcome, &out);
    Ok(())
}

/// runs/<env>-<algo>-seed<seed>-<unix time>.
pub fn default_run_dir(c: &RunConfig) -> PathBuf {
    let t = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    PathBuf::from("runs").join(format!("{}-{}-seed{}-{t}", c.env, c.algo.name(), c.seed))
}

/// Trains per `config` into `out` (SAVER: with the PCPN of `pcpn_file`, or of the
/// store in `pcpn_dir`, recorded in `config`); `show` draws progress on stderr.
pub fn train(
    config: &mut RunConfig,
    out: &Path,
    pcpn_dir: &Path,
    pcpn_file: Option<&Path>,
    stop: Arc<AtomicBool>,
    show: bool,
) -> Result<TrainerOutcome> {
    // Refuse a folder of another run before anything else (a PCPN's pretraining
    // included); start_learner checks again and only then writes into it.
    let saved = saver_learner::checkpoint::check_settings(out, config)
        .with_context(|| format!("resuming from {}", out.display()))?;
    let pcpn = {
        crate::pretrain::pin_saved(config, saved);
        pcpn_for_run(config, &PcpnStore::new(pcpn_dir), pcpn_file)?
    };
    let outcome = train_with(config, out, pcpn, stop, show)?;
    let png = out.join("learning_curve.png");
    plot_runs(&[out.to_path_buf()], &png).context("drawing the learning curve")?;
    let actions = crate::histogram::write_for_run(out).context("drawing the action histogram")?;
    let actions = actions.unwrap_or_default();
    if show && !actions.is_empty() && config.env.kind() == Some(saver_core::env::EnvKind::Bandit) {
        let a: Vec<f32> = actions.iter().map(|a| a[0]).collect();
        let near = |at: f32| 100.0 * crate::histogram::share_near(&a, at, 0.1);
        let reward = a
            .iter()
            .map(|&x| saver_core::env::bandit_reward(x) as f64)
            .sum::<f64>()
            / a.len().max(1) as f64;
        crate::out!(
            "learned actions (4,000 draws): {:.1} % within 0.1 of -0.75, {:.1} % of +0.75, \
             {:.1} % of the decoy 0; mean reward {reward:.3}",
            near(-0.75),
            near(0.75),
            near(0.0)
        );
    }
    Ok(outcome)
}

/// A learner started in this process: the hub actors talk to, the trainer thread and
/// its metrics rows.
pub struct LocalLearner {
    /// What actors (in-process or through the gRPC service) talk to.
    pub hub: Arc<Hub>,
    /// The trainer thread.
    pub trainer: TrainerHandle,
    /// One row per update.
    pub rows: mpsc::Receiver<MetricsRow>,
    /// Counters it started from (non-zero when resumed).
    pub start: Counters,
    /// In-process actors saved in the resumed checkpoint, by id.
    pub actors: Arc<ActorStates>,
}

/// Builds the algorithm around `pcpn` (SAVER) or none (A2C), resumes it from `out`'s
/// checkpoint when there is one of the same settings, publishes the first version and
/// starts the trainer thread writing into `out` (a checkpoint every `checkpoint_every`
/// updates too, when it is not 0). Nothing in `out` changes before the run is
/// accepted; then config.toml is written, temporaries of a killed run are removed, and
/// metrics.csv loses the rows written after the checkpoint. Versions go on above every
/// version the killed run published, so no client sees a number twice.
pub fn start_learner(
    config: &RunConfig,
    out: &Path,
    pcpn: Option<Pcpn>,
    stop: Arc<AtomicBool>,
    checkpoint_every: u64,
) -> Result<LocalLearner> {
    let config = &with_pcpn_recorded(config, pcpn.as_ref())?;
    let dev = saver_core::device();
    let mut algo = saver_core::algo::build(config, pcpn, &dev)?;
    algo.set_threads(crate::pcpn_threads());
    let resumed = saver_learner::resume(out, config, algo.as_mut())
        .with_context(|| format!("resuming from {}", out.display()))?;
    std::fs::create_dir_all(out)
        .with_context(|| format!("creating run folder {}", out.display()))?;
    std::fs::write(out.join("config.toml"), config.to_toml()).context("writing config.toml")?;
    saver_core::checkpoint::remove_stale_temporaries(out);
    let mut state = resumed.unwrap_or_default();
    let start = &mut state.counters;
    if *start != Counters::default() {
        let csv = out.join("metrics.csv");
        let (dropped, newest) = saver_learner::metrics::truncate_after(&csv, start.steps)
            .with_context(|| format!("reading {}", csv.display()))?;
        let per_dim = out.join("per_dim.csv");
        saver_learner::metrics::truncate_after(&per_dim, start.steps)
            .with_context(|| format!("reading {}", per_dim.display()))?;
        eprintln!(
            "resuming {} from its checkpoint: version {}, {} steps, {} episodes{}",
            out.display(),
            start.version,
            start.steps,
            start.episodes,
            if dropped > 0 {
                format!(
                    "; {dropped} rows of metrics.csv written after it were dropped, and \
                     versions continue from {} (the last one published was {newest})",
                    newest + 1
                )
            } else {
                String::new()
            }
        );
        // The first version served is above every one published before: the
        // checkpoint's weights are not those the killed learner published as `newest`.
        if dropped > 0 {
            start.version = start.version.max(newest + 1);
        }
    }
    let initial = PolicyWeights {
        version: start.version,
        tensors: algo.policy_tensors()?,
    };
    let start = *start;
    let (hub, rx) = Hub::new(config.clone(), initial, 2 * config.actors as usize);
    hub.resume_actors(&state.actors);
    let actors = Arc::new(state.actors.clone());
    let (row_tx, rows) = mpsc::channel::<MetricsRow>();
    let opts = TrainerOptions {
        rows: Some(row_tx),
        checkpoint_every,
        start: state,
        evaluator: crate::eval::learner_evaluator(config),
        eval_every: crate::eval::LEARNER_EVAL_EVERY,
        ..TrainerOptions::new(out.to_path_buf(), stop)
    };
    let trainer = spawn_trainer(algo, hub.clone(), rx, opts)?;
    Ok(LocalLearner {
        hub,
        trainer,
        rows,
        start,
        actors,
    })
}

/// `config` with the weights sha256 of `pcpn` recorded (refused when it names another).
fn with_pcpn_recorded(config: &RunConfig, pcpn: Option<&Pcpn>) -> Result<RunConfig> {
    let mut c = config.clone();
    if let Some(p) = pcpn {
        let sha = saver_pcpn_trainer::weights_sha256(&saver_core::checkpoint::to_named_all(
            &p.tensors()?,
        )?);
        if c.pcpn_sha256.as_ref().is_some_and(|want| *want != sha) {
            anyhow::bail!(
                "the run names the PCPN {} but was given {sha}",
                c.pcpn_sha256.unwrap_or_default()
            );
        }
        c.pcpn_sha256 = Some(sha);
    }
    Ok(c)
}

/// Follows the metrics rows until training ends, showing progress when `show`, and
/// handing each row to `each`; then joins the trainer.
pub fn follow(
    learner: LocalLearner,
    config: &RunConfig,
    show: bool,
    mut each: impl FnMut(&MetricsRow),
) -> Result<(Arc<Hub>, TrainerOutcome)> {
    let label = format!("{} {}", config.algo.name(), config.env);
    let mut progress = show.then(|| Progress::new(&label, config.steps, "steps"));
    for row in learner.rows {
        if let Some(p) = progress.as_mut() {
            let len = row
                .mean_ep_len_100
                .map(|m| format!("{m:.0}"))
                .unwrap_or_else(|| "-".into());
            p.update(
                row.steps,
                &format!("mean ep len {len} | update {}", row.updates),
            );
        }
        each(&row);
    }
    if let Some(p) = &progress {
        p.finish();
    }
    let outcome = learner
        .trainer
        .join
        .join()
        .map_err(|_| anyhow!("the trainer thread panicked"))??;
    Ok((learner.hub, outcome))
}

/// The embedded run proper, around a given PCPN (SAVER) or none (A2C): learner
/// thread, actor threads over the in-process link, progress from the metrics rows.
pub fn train_with(
    config: &RunConfig,
    out: &Path,
    pcpn: Option<Pcpn>,
    stop: Arc<AtomicBool>,
    show: bool,
) -> Result<TrainerOutcome> {
    let learner = start_learner(config, out, pcpn, stop.clone(), 0)?;
    let mut actors = Vec::new();
    for i in 0..config.actors {
        let mut link = InProcessLink::new(learner.hub.clone());
        let stop = stop.clone();
        let saved = learner.actors.clone();
        let reg = Registration {
            name: format!("embedded-{i}"),
            session: rand::random(),
            n_envs: config.envs_per_actor,
        };
        let hub = learner.hub.clone();
        actors.push(
            std::thread::Builder::new()
                .name(format!("saver-actor-{i}"))
                .spawn(move || {
                    // The embedded actors are alike: one that fails (a bad checkpoint,
                    // an env it cannot make) ends the run instead of leaving the
                    // others to wait for it.
                    let r = run_actor_from(&mut link, &reg, &stop, &saved);
                    if let Err(e) = &r {
                        hub.close(&format!("actor {i} failed: {e}"));
                    }
                    r
                })?,
        );
    }
    let (hub, outcome) = follow(learner, config, show, |_| {})?;
    hub.close("run over");
    let mut failed = None;
    for (i, a) in actors.into_iter().enumerate() {
        match a.join() {
            Ok(Ok(_)) => {}
            Ok(Err(e)) => {
                failed.get_or_insert(anyhow::anyhow!("actor {i} failed: {e}"));
            }
            Err(_) => {
                failed.get_or_insert(anyhow::anyhow!("actor {i} panicked"));
            }
        }
    }
    match failed {
        Some(e) => Err(e.context(format!(
            "the run stopped at step {} (its checkpoint is in {})",
            outcome.steps,
            out.display()
        ))),
        None => Ok(outcome),
    }
}

/// Where this process's training time went: the updates' share, the rest waiting for
/// rollouts (the actors' env steps and transfers), publishing weights and checkpoints.
fn time_split(o: &TrainerOutcome) -> String {
    let share = 100.0 * o.update_s / o.own_wall_s.max(1e-9);
    format!(
        "The learner's updates took {:.1} s of {:.1} s ({share:.0} %); the rest it waited for \
         rollouts, published weights and saved checkpoints",
        o.update_s, o.own_wall_s
    )
}

/// Prints the run's summary and where its outputs went.
pub fn report(config: &RunConfig, o: &TrainerOutcome, out: &Path) {
    let len = o
        .mean_ep_len_100
        .map(|m| format!("{m:.1}"))
        .unwrap_or_else(|| "n/a (no episode finished)".into());
    crate::out!(
        "{} {}: {} steps, {} updates in {:.1} s of training ({:.0} steps/s){}; mean episode length (last 100): {len}",
        config.algo.name(),
        config.env,
        o.steps,
        o.version,
        o.wall_s,
        o.steps as f64 / o.wall_s.max(1e-9),
        if o.interrupted { ", stopped early" } else { "" }
    );
    crate::out!("{}", time_split(o));
    crate::out!("Outputs in {}:", out.display());
    crate::out!("  config      {}", out.join("config.toml").display());
    crate::out!("  metrics     {}", o.metrics.display());
    crate::out!("  plot        {}", out.join("learning_curve.png").display());
    let histogram = out.join("action_histogram.png");
    if histogram.exists() {
        crate::out!("  actions     {}", histogram.display());
    }
    crate::out!("  checkpoint  {}", o.checkpoint.display());
    let policy = out.join(saver_learner::best::POLICY_FILE);
    match config.env.kind() {
        Some(_) => crate::out!(
            "  policy      {} (any client: saver eval, saver_actor.Policy.load)",
            policy.display()
        ),
        None => crate::out!(
            "  policy      {} (play it: {}; saver_actor.Policy.load)",
            policy.display(),
            crate::eval::enjoy_command(&policy)
        ),
    }
    let best = out.join(saver_learner::best::BEST_FILE);
    if best.exists() {
        crate::out!(
            "  best        {} (by deterministic evaluation; every one in {})",
            best.display(),
            out.join(saver_learner::best::EVAL_CSV).display()
        );
    }
}
