//! The distributed roles of the one `saver` binary: `learner`, `actor`,
//! `pcpn-trainer`, and the clients `weights` and `healthcheck`. They run the same
//! learner and actor code as `saver train`, with gRPC between them.

use crate::config::RunArgs;
use crate::pretrain::obtain_pcpn;
use crate::train::{default_run_dir, follow, report, start_learner};
use anyhow::{bail, Context, Result};
use clap::Args;
use saver_actor::grpc::{decode_weights, GrpcLink};
use saver_actor::run_actor;
use saver_core::config::Algo;
use saver_core::link::Registration;
use saver_learner::grpc::{LearnerService, TrainerStatus};
use saver_pcpn_trainer::service::{fetch, PcpnService};
use saver_pcpn_trainer::{load_pcpn_bytes, PcpnStore};
use saver_proto::pb;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")
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

/// `saver learner` flags.
#[derive(Args, Clone, Debug)]
pub struct LearnerArgs {
    /// The run's settings (as for `saver train`; --actors is the sync round size).
    #[command(flatten)]
    pub run: RunArgs,
    /// Address to serve the Learner service on.
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,
    /// SAVER's PCPN: a pcpn-trainer URL (http://host:port) or a file; default: the
    /// local store in --pcpn-dir.
    #[arg(long)]
    pub pcpn: Option<String>,
    /// Local PCPN store (when --pcpn is not given).
    #[arg(long, default_value = "pcpn-cache")]
    pub pcpn_dir: PathBuf,
    /// Run folder (default: runs/<env>-<algo>-seed<seed>-<time>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Exit when training is done instead of serving the final weights until stopped.
    #[arg(long)]
    pub exit_when_done: bool,
}

/// Runs `saver learner`.
pub fn learner(args: LearnerArgs) -> Result<()> {
    let config = args.run.resolve()?;
    let out = args.out.clone().unwrap_or_else(|| default_run_dir(&config));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    std::fs::write(out.join("config.toml"), crate::config::to_toml(&config))?;
    let rt = runtime()?;
    let pcpn = match (config.algo, args.pcpn.as_deref()) {
        (Algo::A2c, _) => None,
        (Algo::Saver, Some(url)) if url.starts_with("http://") || url.starts_with("https://") => {
            let bytes = rt
                .block_on(fetch(url, &config))
                .map_err(|s| anyhow::anyhow!("{}: {}", s.code(), s.message()))?;
            let shown = PathBuf::from(format!("{url} ({})", config.env));
            let (pcpn, info) = load_pcpn_bytes(&bytes, &shown, &config.env, &saver_core::device())
                .map_err(|e| anyhow::anyhow!("FAILED_PRECONDITION: {e}"))?;
            eprintln!("PCPN from {url}: weights sha256 {}", info.weights_sha256);
            Some(pcpn)
        }
        (Algo::Saver, file) => {
            let store = PcpnStore::new(&args.pcpn_dir);
            Some(obtain_pcpn(&config, &store, file.map(Path::new))?.0)
        }
    };
    let stop = Arc::new(AtomicBool::new(false));
    let learner = start_learner(&config, &out, pcpn, stop.clone())?;
    let (service, status) = LearnerService::new(learner.hub.clone());
    let listener = rt.block_on(bind(args.listen))?;
    let addr = listener.local_addr()?;
    eprintln!(
        "learner for {} {} ({} mode, {} actors per round) serving on {addr}; run folder {}",
        config.algo.name(),
        config.env,
        config.mode.name(),
        config.actors,
        out.display()
    );
    let (done_tx, done_rx) = tokio::sync::watch::channel(false);
    let exit_when_done = args.exit_when_done;
    let server = rt.spawn(saver_learner::grpc::serve(service, listener, async move {
        let mut done = done_rx;
        tokio::select! {
            _ = terminated() => {}
            _ = async { while !(exit_when_done && *done.borrow_and_update()) {
                if done.changed().await.is_err() { break; } } } => {}
        }
    }));
    // Ctrl-C / SIGTERM also stop the trainer (it writes its checkpoint).
    let flag = stop.clone();
    rt.spawn(async move {
        terminated().await;
        flag.store(true, Ordering::SeqCst);
    });
    let (_, outcome) = follow(learner, &config, true, |row| {
        status.send_replace(TrainerStatus {
            steps: row.steps,
            mean_ep_len_100: row.mean_ep_len_100,
            stale_dropped: row.stale_dropped,
            finished: false,
        });
    })?;
    status.send_modify(|s| s.finished = true);
    crate::plot::plot_runs(std::slice::from_ref(&out), &out.join("learning_curve.png"))?;
    report(&config, &outcome, &out);
    if !exit_when_done && !stop.load(Ordering::SeqCst) {
        eprintln!("training finished; still serving the final weights on {addr} (Ctrl-C to stop)");
    }
    let _ = done_tx.send(true);
    rt.block_on(server)?.context("serving")?;
    Ok(())
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
    /// Name in the learner's logs (default: actor-<process id>).
    #[arg(long)]
    pub name: Option<String>,
    /// Keep trying to reach the learner for this many seconds at start-up.
    #[arg(long, default_value_t = 120)]
    pub connect_timeout: u64,
}

/// Runs `saver actor`.
pub fn actor(args: ActorArgs) -> Result<()> {
    let name = args
        .name
        .clone()
        .unwrap_or_else(|| format!("actor-{}", std::process::id()));
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(args.connect_timeout);
    let mut link = loop {
        match GrpcLink::connect(&args.learner) {
            Ok(l) => break l,
            Err(e) if std::time::Instant::now() < deadline => {
                tracing::info!("{e}; retrying");
                std::thread::sleep(std::time::Duration::from_millis(500));
            }
            Err(e) => return Err(e.into()),
        }
    };
    let reg = Registration {
        name: name.clone(),
        session: rand::random(),
        n_envs: args.envs,
    };
    let stop = AtomicBool::new(false);
    let summary = run_actor(&mut link, &reg, &stop)?;
    eprintln!(
        "{name}: learner done; {} rollouts, {} env steps, {} episodes",
        summary.rollouts, summary.steps, summary.episodes
    );
    Ok(())
}

/// `saver weights` flags.
#[derive(Args, Clone, Debug)]
pub struct WeightsArgs {
    /// The learner's URL.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    pub learner: String,
    /// Write the weights (safetensors) here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Wait for at least this version.
    #[arg(long, default_value_t = 0)]
    pub min_version: u64,
}

/// Runs `saver weights`.
pub fn weights(args: WeightsArgs) -> Result<()> {
    let rt = runtime()?;
    let reply = rt.block_on(async {
        let mut client = pb::learner_client::LearnerClient::connect(args.learner.clone())
            .await
            .with_context(|| format!("connecting to {}", args.learner))?
            .max_decoding_message_size(saver_proto::MAX_MESSAGE_BYTES);
        let w = client
            .get_weights(pb::WeightsRequest {
                min_version: args.min_version,
            })
            .await
            .map_err(|s| anyhow::anyhow!("{}: {}", s.code(), s.message()))?;
        anyhow::Ok(w.into_inner())
    })?;
    let decoded = decode_weights(&reply)?;
    println!("version {}", decoded.version);
    for t in &decoded.tensors {
        println!("{:<16} {:?}", t.name, t.shape);
    }
    if let Some(path) = &args.out {
        saver_core::checkpoint::write_atomic(path, &reply.safetensors)?;
        println!("weights written to {}", path.display());
    }
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
}

/// Runs `saver pcpn-trainer`.
pub fn pcpn_trainer(args: PcpnTrainerArgs) -> Result<()> {
    let rt = runtime()?;
    let listener = rt.block_on(bind(args.listen))?;
    eprintln!(
        "pcpn-trainer serving the store {} on {}",
        args.store.display(),
        listener.local_addr()?
    );
    rt.block_on(saver_pcpn_trainer::service::serve(
        PcpnService::new(&args.store),
        listener,
        terminated(),
    ))?;
    Ok(())
}

/// `saver healthcheck` flags.
#[derive(Args, Clone, Debug)]
pub struct HealthArgs {
    /// The server's URL.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    pub addr: String,
}

/// Runs `saver healthcheck`: exit 0 when the server reports SERVING (grpc.health.v1).
pub fn healthcheck(args: HealthArgs) -> Result<()> {
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;
    let rt = runtime()?;
    let status = rt.block_on(async {
        let channel = tonic::transport::Channel::from_shared(args.addr.clone())
            .with_context(|| format!("server address {:?}", args.addr))?
            .connect()
            .await
            .with_context(|| format!("connecting to {}", args.addr))?;
        let mut client = HealthClient::new(channel);
        let r = client
            .check(HealthCheckRequest {
                service: String::new(),
            })
            .await
            .map_err(|s| anyhow::anyhow!("{}: {}", s.code(), s.message()))?;
        anyhow::Ok(r.into_inner().status)
    })?;
    if status != tonic_health::pb::health_check_response::ServingStatus::Serving as i32 {
        bail!("{} is not serving (status {status})", args.addr);
    }
    println!("{}: SERVING", args.addr);
    Ok(())
}
