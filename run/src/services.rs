//! The distributed roles of the one `saver` binary: `learner`, `actor` and
//! `pcpn-trainer` (the small clients are in `clients.rs`). They run the same learner
//! and actor code as `saver train`, with gRPC between them.

use crate::access::{client_tls, ClientArgs, ServerAccess};
use crate::pretrain::{pcpn_for_run, record};
use crate::train::{default_run_dir, follow, report, start_learner};
use anyhow::{Context, Result};
use clap::Args;
use saver_actor::remote::{run_remote, RemoteActor};
use saver_core::config::RunConfig;
use saver_core::nets::Pcpn;
use saver_core::settings::RunSettings;
use saver_learner::grpc::{LearnerService, TrainerStatus};
use saver_learner::waiting::{serve_waiting, Waiting, WaitingLearner};
use saver_learner::TrainerOutcome;
use saver_pcpn_trainer::service::{fetch, PcpnService};
use saver_pcpn_trainer::{load_pcpn_bytes, PcpnStore};
use saver_proto::weights_dir::WeightsDir;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

pub(crate) fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// Serves the Learner service over `hub` (with `access`, and writing the weights to
/// `weights_dir` if given) on 127.0.0.1:0 on `rt`, for as long as the runtime lives;
/// returns its URL (`saver bench` and the tests).
pub fn serve_hub_on_loopback(
    rt: &tokio::runtime::Runtime,
    hub: Arc<saver_learner::Hub>,
    access: saver_proto::Access,
    weights_dir: Option<WeightsDir>,
) -> Result<String> {
    let (service, _status) = LearnerService::new(hub, weights_dir);
    let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
    let url = format!("http://{}", listener.local_addr()?);
    rt.spawn(saver_learner::grpc::serve(
        service.with_access(access),
        listener,
        std::future::pending(),
    ));
    Ok(url)
}

async fn bind(addr: SocketAddr) -> Result<tokio::net::TcpListener> {
    tokio::net::TcpListener::bind(addr)
        .await
        .with_context(|| format!("listening on {addr}"))
}

/// Resolves on Ctrl-C or SIGTERM.
async fn terminated() {
    #[cfg(unix)]
    {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(s) => s,
                Err(_) => return std::future::pending().await,
            };
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    let _ = tokio::signal::ctrl_c().await;
}

/// A flag that turns true on Ctrl-C or SIGTERM, for every part of a service that
/// stops on it (wait with [`quit`]).
fn quit_on_signal(rt: &tokio::runtime::Runtime) -> tokio::sync::watch::Receiver<bool> {
    let (tx, rx) = tokio::sync::watch::channel(false);
    rt.spawn(async move {
        terminated().await;
        let _ = tx.send(true);
    });
    rx
}

/// Resolves once `rx` (from [`quit_on_signal`]) turned true.
async fn quit(mut rx: tokio::sync::watch::Receiver<bool>) {
    let _ = rx.wait_for(|q| *q).await;
}

/// `saver learner` flags.
#[derive(Args, Clone, Debug)]
pub struct LearnerArgs {
    /// The run's settings (as for `saver train`; --actors is the sync round size).
    #[command(flatten)]
    pub run: RunSettings,
    /// Address to serve the Learner service on.
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,
    /// SAVER's PCPN: a pcpn-trainer URL (http://host:port) or a file; default: the
    /// local store in --pcpn-dir.
    #[arg(long)]
    pub pcpn: Option<String>,
    /// CA certificate (PEM) of an https:// --pcpn store.
    #[arg(long, value_name = "FILE")]
    pub pcpn_ca: Option<PathBuf>,
    /// Local PCPN store (when --pcpn is not given).
    #[arg(long, default_value = "pcpn-cache")]
    pub pcpn_dir: PathBuf,
    /// Run folder (default: runs/<env>-<algo>-seed<seed>-<time>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Exit when training is done instead of serving the final weights until stopped.
    #[arg(long)]
    pub exit_when_done: bool,
    /// Sync mode: seconds a round waits for each actor before it goes ahead without
    /// the late ones (they rejoin with their next rollout).
    #[arg(long, default_value_t = 10.0, value_parser = positive_secs)]
    pub round_timeout: f64,
    /// Write the checkpoint (atomically) every this many updates, besides at the end
    /// and on Ctrl-C or SIGTERM; 0: only then. A restart with the same --out resumes.
    #[arg(long, default_value_t = 100)]
    pub checkpoint_every: u64,
    /// Also write each version's weights here, so that actors on this machine read one
    /// file instead of each receiving the bytes over its socket (default: a folder in
    /// /dev/shm, i.e. memory, removed at exit; "none": stream the bytes to everyone).
    /// Actors elsewhere, or that cannot read it, get the bytes as before.
    #[arg(long, value_name = "DIR")]
    pub weights_dir: Option<String>,
    /// Serve Prometheus metrics (text format, any path) on this address: steps,
    /// version, actors, rollouts accepted and refused by reason, update and broadcast
    /// latency, losses, episode length. The gRPC port's rule holds: its token
    /// (scrapers send `Authorization: Bearer <token>`) and TLS, and a non-loopback
    /// address needs one of them (or --insecure).
    #[arg(long, value_name = "ADDR")]
    pub metrics: Option<SocketAddr>,
    /// Token and --insecure.
    #[command(flatten)]
    pub access: ServerAccess,
}

/// Serves Prometheus metrics on `addr` (if given) on `rt` under the server's `access`
/// rule, and says where.
fn metrics_on(
    rt: &tokio::runtime::Runtime,
    addr: Option<SocketAddr>,
    access: &ServerAccess,
) -> Result<()> {
    if let Some(addr) = addr {
        let access = access.metrics(addr)?;
        let scheme = access.scheme();
        let bound = crate::prometheus::serve_metrics(rt, addr, access)?;
        eprintln!("Prometheus metrics at {scheme}://{bound}/metrics");
    }
    Ok(())
}

/// The learner's weights directory as `--weights-dir` asks.
fn weights_dir(arg: Option<&str>) -> Result<Option<WeightsDir>> {
    let path = match arg {
        Some("none") => return Ok(None),
        Some(p) => PathBuf::from(p),
        None => match WeightsDir::default_path() {
            Some(p) => p,
            None => return Ok(None),
        },
    };
    let dir = WeightsDir::create(&path)
        .with_context(|| format!("creating the weights directory {}", path.display()))?;
    Ok(Some(dir))
}

pub(crate) fn positive_secs(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 && v < 1e6 => Ok(v),
        _ => Err(format!("{s:?} is not a number of seconds in (0, 1e6)")),
    }
}

/// Runs `saver learner`.
pub fn learner(args: LearnerArgs) -> Result<()> {
    let mut config = args.run.resolve()?;
    let check = args.access.check(args.listen)?;
    let pcpn_access = saver_proto::ClientAccess {
        token: args.access.token.client()?,
        tls: args.pcpn_ca.as_deref().map(client_tls).transpose()?,
    };
    let out = args.out.clone().unwrap_or_else(|| default_run_dir(&config));
    // A folder of another run is refused before anything is fetched or written.
    let saved = saver_learner::checkpoint::check_settings(&out, &config)
        .with_context(|| format!("resuming from {}", out.display()))?;
    crate::pretrain::pin_saved(&mut config, saved);
    let rt = runtime()?;
    metrics_on(&rt, args.metrics, &args.access)?;
    let listener = rt.block_on(bind(args.listen))?;
    let quit_rx = quit_on_signal(&rt);
    let (pcpn, listener) = if config.algo.has_pcpn() {
        // The port answers at once: Status says what the learner waits for, actors
        // are told to keep waiting. The trained service takes the port over after.
        let std = listener.into_std()?;
        let (ours, theirs) = (std.try_clone()?, std);
        let _in_rt = rt.enter();
        let listener = tokio::net::TcpListener::from_std(ours)?;
        let first = Waiting {
            algo: config.algo.name().into(),
            env: config.env.to_string(),
            mode: config.mode.name().into(),
            what: "the PCPN".into(),
            pretrain: None,
        };
        let pcpn = while_waiting(&rt, first, &check, theirs, quit_rx.clone(), |about| {
            obtain_for_learner(&rt, &mut config, &args, &pcpn_access, about)
        })?;
        (pcpn, listener)
    } else {
        (None, listener)
    };
    let opts = LearnerOptions {
        out,
        round_timeout: Duration::from_secs_f64(args.round_timeout),
        checkpoint_every: args.checkpoint_every,
        weights_dir: weights_dir(args.weights_dir.as_deref())?,
        exit_when_done: args.exit_when_done,
        access: check,
    };
    let out = opts.out.clone();
    let outcome = serve_learner(&rt, &config, pcpn, opts, listener, quit(quit_rx))?;
    report(&config, &outcome, &out);
    Ok(())
}

/// Runs `obtain` (the learner's PCPN) while a [`WaitingLearner`] serves `listener`:
/// Status says what `obtain` reports through its sender, every other call is answered
/// "waiting" so that actors keep waiting. Ctrl-C or SIGTERM meanwhile ends the process
/// (nothing is trained or written before the PCPN is in hand).
fn while_waiting<T>(
    rt: &tokio::runtime::Runtime,
    first: Waiting,
    access: &saver_proto::Access,
    listener: std::net::TcpListener,
    quit_rx: tokio::sync::watch::Receiver<bool>,
    obtain: impl FnOnce(&tokio::sync::watch::Sender<Waiting>) -> Result<T>,
) -> Result<T> {
    let (about, about_rx) = tokio::sync::watch::channel(first);
    let waiting = Arc::new(AtomicBool::new(true));
    let flag = waiting.clone();
    rt.spawn(async move {
        quit(quit_rx).await;
        if flag.load(Ordering::SeqCst) {
            eprintln!("learner: stopped while waiting for its PCPN (nothing trained or written)");
            std::process::exit(130);
        }
    });
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = {
        let _in_rt = rt.enter();
        let listener = tokio::net::TcpListener::from_std(listener)?;
        rt.spawn(serve_waiting(
            WaitingLearner::new(about_rx, access.clone()),
            listener,
            async move {
                let _ = stopped.await;
            },
        ))
    };
    let out = obtain(&about);
    waiting.store(false, Ordering::SeqCst);
    let _ = stop.send(());
    rt.block_on(server)?
        .context("serving while waiting for the PCPN")?;
    out
}

/// The learner's PCPN: from a pcpn-trainer (saying how far its pretraining is every
/// 10 s, here and through `about`), or from a file or the local store.
fn obtain_for_learner(
    rt: &tokio::runtime::Runtime,
    config: &mut RunConfig,
    args: &LearnerArgs,
    pcpn_access: &saver_proto::ClientAccess,
    about: &tokio::sync::watch::Sender<Waiting>,
) -> Result<Option<Pcpn>> {
    let Some(url) = args
        .pcpn
        .as_deref()
        .filter(|u| u.starts_with("http://") || u.starts_with("https://"))
    else {
        about.send_modify(|w| {
            w.what = "the PCPN, pretrained here (the learner's log shows how far)".into()
        });
        return pcpn_for_run(
            config,
            &PcpnStore::new(&args.pcpn_dir),
            args.pcpn.as_deref().map(Path::new),
        );
    };
    eprintln!(
        "waiting for the PCPN of {} from {url} (the store pretrains it first if it has none: \
         {}); serving starts once it is in hand",
        config.env, config.pretrain
    );
    let bytes = rt
        .block_on(async {
            reach_store(url, pcpn_access, about).await?;
            // One channel for every Progress call (connected on first use, again
            // after a failure).
            let mut progress = pcpn_access.endpoint(url).ok().map(|e| {
                saver_proto::pb::pcpn_store_client::PcpnStoreClient::with_interceptor(
                    e.connect_lazy(),
                    pcpn_access.token.clone(),
                )
            });
            let work = fetch(url, &config.env, &config.pretrain, pcpn_access);
            tokio::pin!(work);
            let mut tick = tokio::time::interval(saver_pcpn_trainer::samples::SAY_EVERY);
            let start = std::time::Instant::now();
            loop {
                tokio::select! {
                    out = &mut work => return out,
                    _ = tick.tick() => {
                        let p = store_progress(progress.as_mut()).await;
                        let what = match &p {
                            Ok(Some(p)) => format!("the PCPN from {url}: {}", p.line),
                            Ok(None) => format!("the PCPN from {url} (no pretraining in progress there: \
                                                 it is being sent, or another pretraining goes first)"),
                            Err(e) => format!("the PCPN from {url} (its Progress: {})", e.message()),
                        };
                        if start.elapsed() > Duration::from_secs(1) {
                            eprintln!("still waiting for {what} ({:.0} s)", start.elapsed().as_secs_f64());
                        }
                        about.send_modify(|w| {
                            w.what = what;
                            w.pretrain = p.ok().flatten();
                        });
                    }
                }
            }
        })
        .map_err(|s| {
            let hint = if s.code() == tonic::Code::Unavailable {
                format!(
                    " (is a pcpn-trainer running at {url}? Start one with `saver pcpn-trainer \
                     --listen HOST:PORT`, or leave out --pcpn to pretrain here)"
                )
            } else {
                String::new()
            };
            anyhow::anyhow!("{}: {}{hint}", s.code(), s.message())
        })?;
    let shown = PathBuf::from(format!("{url} ({})", config.env));
    let (pcpn, info) = load_pcpn_bytes(&bytes, &shown, &config.env, &saver_core::device())
        .map_err(|e| anyhow::anyhow!("FAILED_PRECONDITION: {e}"))?;
    eprintln!("PCPN from {url}: weights sha256 {}", info.weights_sha256);
    // A pinned run (resumed, or named in its config) refuses other weights.
    record(config, &info)?;
    Ok(Some(pcpn))
}

/// How long a learner retries a pcpn-trainer it cannot reach (started beside it, the
/// store may come up a moment later).
const STORE_RETRY: Duration = Duration::from_secs(60);

/// Waits until the store at `url` accepts a connection, for up to [`STORE_RETRY`]
/// (saying so once); then UNAVAILABLE with the last error.
async fn reach_store(
    url: &str,
    access: &saver_proto::ClientAccess,
    about: &tokio::sync::watch::Sender<Waiting>,
) -> Result<(), tonic::Status> {
    let start = std::time::Instant::now();
    let mut said = false;
    loop {
        let err = match access.endpoint(url) {
            Ok(e) => match e.connect().await {
                Ok(_) => return Ok(()),
                Err(e) => e.to_string(),
            },
            // A malformed URL does not mend: fetch says what is wrong with it.
            Err(_) => return Ok(()),
        };
        if start.elapsed() >= STORE_RETRY {
            return Err(tonic::Status::unavailable(format!(
                "the PCPN store {url}: {err} (for {} s)",
                STORE_RETRY.as_secs()
            )));
        }
        if !said {
            eprintln!(
                "no pcpn-trainer answers at {url} yet ({err}); retrying for up to {} s",
                STORE_RETRY.as_secs()
            );
            about.send_modify(|w| w.what = format!("a pcpn-trainer to answer at {url}"));
            said = true;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

/// The store's client for Progress calls (its token attached).
type StoreClient = saver_proto::pb::pcpn_store_client::PcpnStoreClient<
    tonic::service::interceptor::InterceptedService<
        tonic::transport::Channel,
        saver_proto::AddToken,
    >,
>;

/// How far the store is with its pretraining (None: none in progress).
async fn store_progress(
    client: Option<&mut StoreClient>,
) -> Result<Option<saver_proto::pb::PretrainProgress>, tonic::Status> {
    let client = client.ok_or_else(|| tonic::Status::unavailable("no endpoint"))?;
    let r = client.progress(saver_proto::pb::ProgressRequest {}).await?;
    Ok(r.into_inner().pretraining.into_iter().next())
}

/// How a served learner runs besides its config.
pub struct LearnerOptions {
    /// Run folder (resumed when it holds a checkpoint of the same settings).
    pub out: PathBuf,
    /// Sync mode: how long a round waits for each actor.
    pub round_timeout: Duration,
    /// Checkpoint every this many updates (0: only at the end and on shutdown).
    pub checkpoint_every: u64,
    /// Where each version's weights are also written for actors on this machine.
    pub weights_dir: Option<WeightsDir>,
    /// Stop serving when training is done instead of waiting for `shutdown`.
    pub exit_when_done: bool,
    /// Token and TLS of the service.
    pub access: saver_proto::Access,
}

/// Trains per `config` (SAVER around `pcpn`) while serving the Learner service on
/// `listener`, until training is done, then (unless `exit_when_done`) serves the
/// final weights until `shutdown`; `shutdown` before the end stops training after the
/// current update with a checkpoint. The trainer runs on its own thread, the service
/// on `rt`.
pub fn serve_learner(
    rt: &tokio::runtime::Runtime,
    config: &RunConfig,
    pcpn: Option<Pcpn>,
    opts: LearnerOptions,
    listener: tokio::net::TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<TrainerOutcome> {
    let stop = Arc::new(AtomicBool::new(false));
    let learner = start_learner(config, &opts.out, pcpn, stop.clone(), opts.checkpoint_every)?;
    learner.hub.set_round_timeout(opts.round_timeout);
    let shared = opts
        .weights_dir
        .as_ref()
        .map(|d| (d.path().display().to_string(), d.remover()));
    let (service, status) = LearnerService::new(learner.hub.clone(), opts.weights_dir);
    let service = service.with_access(opts.access);
    let addr = listener.local_addr()?;
    eprintln!(
        "learner for {} {} ({} mode, {} actors per round) serving on {addr}; run folder {}",
        config.algo.name(),
        config.env,
        config.mode.name(),
        config.actors,
        opts.out.display()
    );
    if let Some((path, _)) = &shared {
        eprintln!("weights also go to {path}, read there by actors that share it");
    }
    // `shutdown` stops the trainer (it writes its checkpoint) and the server.
    let (quit_tx, quit_rx) = tokio::sync::watch::channel(false);
    let flag = stop.clone();
    rt.spawn(async move {
        shutdown.await;
        flag.store(true, Ordering::SeqCst);
        let _ = quit_tx.send(true);
    });
    let (done_tx, done_rx) = tokio::sync::watch::channel(false);
    let exit_when_done = opts.exit_when_done;
    let server = rt.spawn(saver_learner::grpc::serve(service, listener, async move {
        let (mut quit, mut done) = (quit_rx, done_rx);
        tokio::select! {
            _ = quit.wait_for(|q| *q) => {}
            _ = done.wait_for(|d| exit_when_done && *d) => {}
        }
    }));
    let (_, outcome) = follow(learner, config, true, |row| {
        status.send_replace(TrainerStatus {
            steps: row.steps,
            mean_ep_len_100: row.mean_ep_len_100,
            stale_dropped: row.stale_dropped,
            skipped_updates: row.skipped_updates,
            finished: false,
        });
    })?;
    status.send_modify(|s| s.finished = true);
    crate::plot::plot_runs(
        std::slice::from_ref(&opts.out),
        &opts.out.join("learning_curve.png"),
    )?;
    if !exit_when_done && !stop.load(Ordering::SeqCst) {
        eprintln!("training finished; still serving the final weights on {addr} (Ctrl-C to stop)");
    }
    let _ = done_tx.send(true);
    let served = rt.block_on(server);
    if let Some((_, remover)) = shared {
        remover.remove();
    }
    served?.context("serving")?;
    Ok(outcome)
}

/// `saver actor` flags.
#[derive(Args, Clone, Debug)]
pub struct ActorArgs {
    /// The learner's URL.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    pub learner: String,
    /// Env instances stepped per rollout.
    #[arg(long, default_value_t = 1)]
    pub envs: u32,
    /// Name in the learner's logs (default: actor-<host name>-<process id>).
    #[arg(long)]
    pub name: Option<String>,
    /// Give up after this many seconds without reaching the learner (at start-up or
    /// after losing it); until then reconnect with jittered backoff.
    #[arg(long, default_value_t = 600)]
    pub connect_timeout: u64,
    /// Always take the weights over the stream, even when the learner's weights
    /// directory is readable here.
    #[arg(long)]
    pub no_shared_weights: bool,
    /// Sleep this many microseconds after every env step: an actor slower than the
    /// rest, as on a slower machine (to measure async mode and --vtrace)
    #[arg(long, value_name = "MICROSECONDS", default_value_t = 0)]
    pub step_delay_us: u64,
    /// The learner's token and CA.
    #[command(flatten)]
    pub access: ClientArgs,
}

/// `actor-<host>-<process id>` (`actor-<process id>` where the host has no name):
/// containers all run as process 1, so their host names (in a swarm or compose, the
/// container's) tell them apart.
fn default_actor_name() -> String {
    let host = std::fs::read_to_string("/etc/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty() && h.len() <= 64);
    match host {
        Some(h) => format!("actor-{h}-{}", std::process::id()),
        None => format!("actor-{}", std::process::id()),
    }
}

/// Runs `saver actor` ([`run_remote`]).
pub fn actor(args: ActorArgs) -> Result<()> {
    let a = RemoteActor {
        learner: args.learner.clone(),
        name: args.name.clone().unwrap_or_else(default_actor_name),
        envs: args.envs,
        give_up: Duration::from_secs(args.connect_timeout),
        shared_weights: !args.no_shared_weights,
        access: args.access.access()?,
        step_delay: Duration::from_micros(args.step_delay_us),
    };
    let total = run_remote(&a, &AtomicBool::new(false))?;
    eprintln!(
        "{}: run finished; {} rollouts, {} env steps, {} episodes",
        a.name, total.rollouts, total.steps, total.episodes
    );
    Ok(())
}

/// `saver pcpn-trainer` flags.
#[derive(Args, Clone, Debug)]
pub struct PcpnTrainerArgs {
    /// Address to serve the PcpnStore service on.
    #[arg(long, default_value = "127.0.0.1:50052")]
    pub listen: SocketAddr,
    /// The store folder.
    #[arg(long, default_value = "pcpn-cache")]
    pub store: PathBuf,
    /// Serve Prometheus metrics (pretraining progress) on this address.
    #[arg(long, value_name = "ADDR")]
    pub metrics: Option<SocketAddr>,
    /// A custom env's pretraining fails (saying what it waited for) when its actors
    /// stream no samples for this many seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 1800.0, value_parser = positive_secs)]
    pub pretrain_deadline: f64,
    /// Token and --insecure.
    #[command(flatten)]
    pub access: ServerAccess,
}

/// Runs `saver pcpn-trainer`.
pub fn pcpn_trainer(args: PcpnTrainerArgs) -> Result<()> {
    let check = args.access.check(args.listen)?;
    let rt = runtime()?;
    metrics_on(&rt, args.metrics, &args.access)?;
    let listener = rt.block_on(bind(args.listen))?;
    eprintln!(
        "pcpn-trainer serving the store {} on {}",
        args.store.display(),
        listener.local_addr()?
    );
    // A signal stops the server; a pretraining still training then (nothing of it is
    // stored) is given up with the runtime after a short grace.
    let quit_rx = quit_on_signal(&rt);
    let served = rt.block_on(async {
        let server = saver_pcpn_trainer::service::serve(
            PcpnService::new(&args.store)
                .with_access(check)
                .with_sample_deadline(std::time::Duration::from_secs_f64(args.pretrain_deadline)),
            listener,
            quit(quit_rx.clone()),
        );
        tokio::select! {
            r = server => r.map_err(anyhow::Error::from),
            _ = async { quit(quit_rx).await; tokio::time::sleep(Duration::from_secs(3)).await } => {
                eprintln!("pcpn-trainer: stopped during a pretraining (nothing of it is stored)");
                Ok(())
            }
        }
    });
    rt.shutdown_timeout(Duration::from_millis(500));
    served?;
    eprintln!("pcpn-trainer: stopped");
    Ok(())
}
