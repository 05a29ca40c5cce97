//! The service half of `saver bench`, as ratios measured in one run:
//! - 16 actor processes over loopback gRPC against the embedded run (env steps/s);
//! - the learner's ingress alone: rollouts accepted per second with no updates;
//! - weight-broadcast latency to 16 WatchWeights subscribers (p50 / p99).

use crate::services::serve_hub_on_loopback;
use crate::train::{follow, start_learner, train_with};
use anyhow::{Context, Result};
use saver_core::config::{Algo, RunConfig};
use saver_core::env::{EnvKind, EnvSpec};
use saver_core::link::PolicyWeights;
use saver_core::rollout::Rollout;
use saver_learner::Hub;
use saver_proto::pb;
use saver_proto::pb::learner_client::LearnerClient;
use saver_proto::weights_dir::WeightsDir;
use std::collections::HashMap;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?)
}

/// Env steps/s of the embedded run, and of the same run with 16 actor processes that
/// take the weights over their sockets, then from the learner's files in /dev/shm
/// (angle d = 4, sync mode; SAVER with a random PCPN). The files row is absent where
/// there is no /dev/shm.
pub fn processes_vs_embedded(algo: Algo, updates: u64) -> Result<(f64, f64, Option<f64>)> {
    let spec = EnvSpec::new(EnvKind::Angle, 4)?;
    let mut config = saver_core::algo::recommended(&spec, algo, 0);
    config.steps = updates * config.batch_transitions();
    let dir = std::env::temp_dir().join(format!(
        "saver-bench-svc-{}-{}",
        algo.name(),
        std::process::id()
    ));
    let pcpn = algo
        .has_pcpn()
        .then(|| {
            let cpu = candle_core::Device::Cpu;
            saver_core::nets::Pcpn::random_frozen(&spec.layout(), 0, candle_core::DType::F32, &cpu)
        })
        .transpose()?;
    let emb = train_with(
        &config,
        &dir.join("embedded"),
        pcpn.clone(),
        Arc::new(AtomicBool::new(false)),
        false,
    )?;
    let bytes = over_processes(&config, &dir.join("bytes"), pcpn.clone(), None)?;
    let files = match WeightsDir::default_path() {
        Some(p) => Some(over_processes(
            &config,
            &dir.join("files"),
            pcpn,
            Some(WeightsDir::create(&p)?),
        )?),
        None => None,
    };
    std::fs::remove_dir_all(&dir).ok();
    // Every clock starts once all actors have registered (the trainer's own clock).
    Ok((emb.steps as f64 / emb.wall_s, bytes, files))
}

/// Env steps/s of `config` with its actors as `saver actor` processes.
fn over_processes(
    config: &RunConfig,
    out: &std::path::Path,
    pcpn: Option<saver_core::nets::Pcpn>,
    weights_dir: Option<WeightsDir>,
) -> Result<f64> {
    let rt = runtime()?;
    let stop = Arc::new(AtomicBool::new(false));
    let learner = start_learner(config, out, pcpn, stop, 0)?;
    let url = serve_hub_on_loopback(&rt, learner.hub.clone(), Default::default(), weights_dir)?;
    let exe = std::env::current_exe().context("finding the saver binary")?;
    let mut actors = Vec::new();
    for _ in 0..config.actors {
        actors.push(
            Command::new(&exe)
                .args(["actor", "--learner", &url])
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .context("starting an actor process")?,
        );
    }
    let (_, remote) = follow(learner, config, false, |_| {})?;
    for mut a in actors {
        let _ = a.wait();
    }
    Ok(remote.steps as f64 / remote.wall_s)
}

/// Transitions per second the learner's gRPC ingress accepts with no updates: 16
/// streams send valid rollouts for `seconds`; a thread drains the queue.
pub fn ingress(seconds: f64) -> Result<f64> {
    let mut config = RunConfig::paper(&EnvSpec::new(EnvKind::Angle, 4)?, Algo::A2c, u64::MAX);
    config.mode = saver_core::config::Mode::Async;
    let layout = config.env.layout();
    let (hub, rx) = Hub::new(
        config.clone(),
        PolicyWeights {
            version: 0,
            tensors: vec![],
        },
        64,
    );
    let drained = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let d = drained.clone();
    std::thread::spawn(move || {
        for r in rx {
            d.fetch_add((r.n_envs * r.n_steps) as u64, Ordering::Relaxed);
        }
    });
    let rt = runtime()?;
    let url = serve_hub_on_loopback(&rt, hub.clone(), Default::default(), None)?;
    let n = config.rollout as usize;
    let deadline = Instant::now() + Duration::from_secs_f64(seconds);
    let tasks: Vec<_> = (0..16u32)
        .map(|i| {
            let url = url.clone();
            rt.spawn(async move {
                let mut client = LearnerClient::connect(url).await?;
                let reg = client
                    .register(pb::RegisterRequest {
                        name: format!("bench-{i}"),
                        session: i as u64,
                        n_envs: 1,
                        env: None,
                    })
                    .await?
                    .into_inner();
                let template = Rollout {
                    actor_id: reg.actor_id,
                    // The learner's secret for this registration, not the client's number.
                    session: reg.session,
                    seq: 0,
                    policy_version: 0,
                    n_envs: 1,
                    n_steps: n,
                    obs: vec![0.1; (n + 1) * layout.obs_dim],
                    // The Gaussian's payload per step: μ = 0, log σ = -1.
                    payload: (0..n)
                        .flat_map(|_| {
                            let mu = std::iter::repeat_n(0.0, layout.mu_dim());
                            mu.chain(std::iter::repeat_n(-1.0, layout.log_std_dim()))
                        })
                        .collect(),
                    actions: vec![0.2; n * layout.action_dim()],
                    // Standing still: each step's p + Δp is the next p, as the learner checks.
                    state_delta: vec![0.0; n * layout.aligned_dim],
                    vector_reward: vec![0.0; n * layout.aligned_dim],
                    env_reward: vec![],
                    done: vec![false; n],
                    timeouts: vec![],
                    timeout_obs: vec![],
                    episodes: vec![],
                    actor_state: None,
                };
                let msg = pb::Rollout::from(&template);
                let (tx, rxs) = tokio::sync::mpsc::channel(64);
                let mut req = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(rxs));
                let md = req.metadata_mut();
                md.insert(saver_proto::ACTOR_ID_KEY, reg.actor_id.into());
                md.insert(saver_proto::SESSION_KEY, reg.session.into());
                let mut acks = client.stream_rollouts(req).await?.into_inner();
                let sender = tokio::spawn(async move {
                    let mut seq = 0;
                    while Instant::now() < deadline {
                        let mut m = msg.clone();
                        m.seq = seq;
                        seq += 1;
                        if tx.send(m).await.is_err() {
                            break;
                        }
                    }
                });
                while let Some(a) = tokio_stream::StreamExt::next(&mut acks).await {
                    if a.is_err() || Instant::now() >= deadline {
                        break;
                    }
                }
                sender.abort();
                anyhow::Ok(())
            })
        })
        .collect();
    // Count from one second in (connections warm) to the deadline.
    std::thread::sleep(Duration::from_secs(1).min(Duration::from_secs_f64(seconds / 4.0)));
    let (t0, c0) = (Instant::now(), drained.load(Ordering::Relaxed));
    while Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    let end = (Instant::now(), drained.load(Ordering::Relaxed));
    hub.close("bench over");
    for t in tasks {
        let _ = rt.block_on(t);
    }
    Ok((end.1 - c0) as f64 / (end.0 - t0).as_secs_f64().max(1e-9))
}

/// Latency from publishing a version to its arrival at each of 16 WatchWeights
/// subscribers, over `versions` publications of the paper's angle-d4 agent.
pub fn broadcast_latency(versions: u64) -> Result<(f64, f64)> {
    let config = RunConfig::paper(&EnvSpec::new(EnvKind::Angle, 4)?, Algo::A2c, 1);
    let dev = candle_core::Device::Cpu;
    let tensors = saver_core::algo::build(&config, None, &dev)?.policy_tensors()?;
    let (hub, _rx) = Hub::new(
        config,
        PolicyWeights {
            version: 0,
            tensors: tensors.clone(),
        },
        4,
    );
    let rt = runtime()?;
    let url = serve_hub_on_loopback(&rt, hub.clone(), Default::default(), None)?;
    let published: Arc<Mutex<HashMap<u64, Instant>>> = Arc::default();
    let samples: Arc<Mutex<Vec<f64>>> = Arc::default();
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    for _ in 0..16 {
        let (url, published, samples, ready) = (
            url.clone(),
            published.clone(),
            samples.clone(),
            ready_tx.clone(),
        );
        rt.spawn(async move {
            let mut client = LearnerClient::connect(url)
                .await?
                .max_decoding_message_size(saver_proto::MAX_MESSAGE_BYTES);
            let mut stream = client
                .watch_weights(pb::WatchRequest { by_file: false })
                .await?
                .into_inner();
            let _ = ready.send(());
            while let Some(Ok(w)) = tokio_stream::StreamExt::next(&mut stream).await {
                let now = Instant::now();
                let sent = published
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .get(&w.version)
                    .copied();
                if let Some(t) = sent {
                    samples
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .push((now - t).as_secs_f64() * 1e3);
                }
            }
            anyhow::Ok(())
        });
    }
    for _ in 0..16 {
        ready_rx.recv_timeout(Duration::from_secs(10))?;
    }
    std::thread::sleep(Duration::from_millis(200));
    for v in 1..=versions {
        published
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(v, Instant::now());
        hub.publish(Arc::new(PolicyWeights {
            version: v,
            tensors: tensors.clone(),
        }));
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_millis(200));
    hub.close("bench over");
    let mut s = samples.lock().unwrap_or_else(|e| e.into_inner()).clone();
    anyhow::ensure!(!s.is_empty(), "no weights arrived");
    s.sort_by(f64::total_cmp);
    let pct = |p: f64| s[((s.len() - 1) as f64 * p).round() as usize];
    Ok((pct(0.5), pct(0.99)))
}
