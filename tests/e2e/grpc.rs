//! The learner and actors over real gRPC on 127.0.0.1:0, through the generated client.

use crate::{assert_tensors_in, temp_dir};
use saver_actor::grpc::GrpcLink;
use saver_actor::run_actor;
use saver_core::config::{Algo, PretrainConfig, RunConfig};
use saver_core::env::{EnvKind, EnvSpec};
use saver_core::link::{LearnerLink, Registration};
use saver_core::nets::Pcpn;
use saver_learner::grpc::{serve, LearnerService};
use saver_proto::weights_dir::WeightsDir;
use saver_proto::NamedTensor;
use saver_run::train::{follow, start_learner, train_with};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

fn checkpoint(path: &Path) -> Vec<NamedTensor> {
    saver_proto::decode(&std::fs::read(path).unwrap())
        .unwrap()
        .0
}

/// Runs `config` with its actors as gRPC clients of a learner served on 127.0.0.1:0
/// (writing its weights to `weights_dir` if given); also returns how many versions the
/// actors read from the learner's files.
/// An untrained frozen PCPN of `env` (the runs compared need the same one, not a good one).
fn untrained_pcpn(env: &EnvSpec) -> saver_core::nets::Pcpn {
    let dev = candle_core::Device::Cpu;
    saver_core::nets::Pcpn::random_frozen(&env.layout(), 0, candle_core::DType::F32, &dev).unwrap()
}

fn run_over_grpc(
    config: &RunConfig,
    out: &Path,
    pcpn: Option<Pcpn>,
    weights_dir: Option<WeightsDir>,
) -> (saver_learner::TrainerOutcome, u64) {
    let rt = tokio::runtime::Runtime::new().unwrap();
    let learner = start_learner(config, out, pcpn, Arc::new(AtomicBool::new(false)), 0).unwrap();
    let (service, _status) = LearnerService::new(learner.hub.clone(), weights_dir);
    let listener = rt
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server = rt.spawn(serve(service, listener, async {
        let _ = stop_rx.await;
    }));
    let actors: Vec<_> = (0..config.actors)
        .map(|i| {
            let url = url.clone();
            let n_envs = config.envs_per_actor;
            std::thread::spawn(move || {
                let mut link = GrpcLink::connect(&url).unwrap();
                let reg = Registration {
                    name: format!("grpc-{i}"),
                    session: 1000 + i as u64,
                    n_envs,
                };
                run_actor(&mut link, &reg, &AtomicBool::new(false)).unwrap();
                link.weights_read_from_files()
            })
        })
        .collect();
    let (_, outcome) = follow(learner, config, false, |_| {}).unwrap();
    let from_files = actors.into_iter().map(|a| a.join().unwrap()).sum();
    let _ = stop_tx.send(());
    rt.block_on(server).unwrap().unwrap();
    (outcome, from_files)
}

#[test]
fn sync_over_grpc_equals_the_embedded_run_bit_for_bit() {
    // SAVER (with a fixed random PCPN) on angle d = 2 and A2C on select d = 3:
    // 4 actors, 20 updates each way; A2C's actors read the weights from the learner's
    // files, with a thread deleting them now and then (a reader that misses one asks
    // for the bytes), SAVER's take them over the stream. SAVER's episodes end at 30
    // steps and bootstrap there, so that timeouts and their observations cross the wire.
    let mut saver = RunConfig::paper(
        &EnvSpec::new(EnvKind::Angle, 2).unwrap(),
        Algo::Saver,
        20 * 4 * 8,
    );
    saver.max_episode_steps = 30;
    saver.bootstrap_timeout = true;
    let a2c = RunConfig::paper(
        &EnvSpec::new(EnvKind::Select, 3).unwrap(),
        Algo::A2c,
        20 * 4 * 8,
    );
    // QRRL on angle d = 2: its quantile policy's τ payload crosses the wire too.
    let qrrl = saver_core::algo::recommended(
        &EnvSpec::new(EnvKind::Angle, 2).unwrap(),
        Algo::Qrrl,
        20 * 4 * 8,
    );
    // PPO on angle d = 2: its old log-probabilities come from the payload the actors
    // send; 2 passes of 4 minibatches of 8 per update.
    let mut ppo = saver_core::algo::recommended(
        &EnvSpec::new(EnvKind::Angle, 2).unwrap(),
        Algo::Ppo,
        20 * 4 * 8,
    );
    ppo.rollout = 8;
    ppo.ppo.epochs = 2;
    ppo.ppo.minibatch_size = 8;
    for mut config in [saver, a2c, qrrl, ppo] {
        config.actors = 4;
        let pcpn = config.algo.has_pcpn().then(|| untrained_pcpn(&config.env));
        let dir = temp_dir(&format!("grpc-eq-{}", config.algo.name()));
        let embedded = train_with(
            &config,
            &dir.join("embedded"),
            pcpn.clone(),
            Arc::new(AtomicBool::new(false)),
            false,
        )
        .unwrap();
        let files = config.algo == Algo::A2c;
        let wdir = dir.join("weights");
        let done = Arc::new(AtomicBool::new(false));
        let deleter = files.then(|| {
            let (wdir, done) = (wdir.clone(), done.clone());
            std::thread::spawn(move || {
                let mut deleted = 0;
                while !done.load(std::sync::atomic::Ordering::Relaxed) {
                    std::thread::sleep(std::time::Duration::from_millis(7));
                    if let Ok(files) = std::fs::read_dir(&wdir) {
                        let f = files.flatten().find(|f| f.file_name() != "id");
                        deleted += f
                            .and_then(|f| std::fs::remove_file(f.path()).ok())
                            .is_some() as u32;
                    }
                }
                deleted
            })
        });
        let weights_dir = files.then(|| WeightsDir::create(&wdir).unwrap());
        let (remote, from_files) = run_over_grpc(&config, &dir.join("grpc"), pcpn, weights_dir);
        done.store(true, std::sync::atomic::Ordering::Relaxed);
        let deleted = deleter.map(|d| d.join().unwrap());
        assert_eq!((embedded.version, remote.version), (20, 20));
        if files {
            // 4 actors x 21 versions (0..=20) at most, less those deleted first.
            assert!(
                from_files > 0 && from_files <= 84,
                "{from_files} read, {deleted:?} deleted"
            );
            // The learner's weights thread removes it once it sees the end.
            let gone = (0..500).any(|_| {
                std::thread::sleep(std::time::Duration::from_millis(10));
                !wdir.exists()
            });
            assert!(gone, "the learner removes its weights directory");
        } else {
            assert_eq!(from_files, 0);
        }
        // Learner state only: the embedded run also saves its in-process actors.
        let learner_part = |p| -> Vec<_> {
            checkpoint(p)
                .into_iter()
                .filter(|t| !t.name.starts_with("actor."))
                .collect()
        };
        let (a, b) = (
            learner_part(&embedded.checkpoint),
            learner_part(&remote.checkpoint),
        );
        assert_eq!(a.len(), b.len());
        assert_tensors_in(&a, &b);
        std::fs::remove_dir_all(dir).ok();
    }
}

#[test]
fn an_actor_reports_each_timeout_with_the_observation_it_reached() {
    // Angle d = 16 with a 3-step limit: one env over 8 steps times out at steps 2 and
    // 5 (success in 3 steps from a uniform start has probability ~1e-16). The envs are
    // reset after a timeout, so the observation reached is the one before the step plus
    // its state change, not the next row of `obs`. The rollout survives the wire.
    let mut config = RunConfig::paper(&EnvSpec::new(EnvKind::Angle, 16).unwrap(), Algo::A2c, 1);
    config.max_episode_steps = 3;
    let dev = candle_core::Device::Cpu;
    let tensors = saver_core::algo::build(&config, None, &dev)
        .unwrap()
        .policy_tensors()
        .unwrap();
    let weights = Arc::new(saver_core::link::PolicyWeights {
        version: 0,
        tensors,
    });
    let layout = config.env.layout();
    let mut policy = saver_core::nets::Policy::new(weights, layout, config.head).unwrap();
    let assignment = saver_core::link::Assignment {
        actor_id: 0,
        session: 1,
        settings: saver_core::link::ActorSettings::of(&config),
    };
    let r = saver_actor::Actor::new(&assignment, 1)
        .unwrap()
        .collect(&mut policy);
    r.validate(&layout, assignment.settings.policy.payload_width())
        .unwrap();
    assert_eq!(r.timeouts, vec![2, 5]);
    let d = layout.obs_dim;
    for (k, &t) in r.timeouts.iter().enumerate() {
        let t = t as usize;
        let reached = &r.timeout_obs[k * d..(k + 1) * d];
        let before = &r.obs[t * d..(t + 1) * d];
        let change = &r.state_delta[t * d..(t + 1) * d];
        for j in 0..d {
            assert!((reached[j] - (before[j] + change[j])).abs() < 1e-6);
        }
        assert_ne!(reached, &r.obs[(t + 1) * d..(t + 2) * d], "the reset row");
    }
    let back = saver_core::rollout::Rollout::try_from(saver_proto::pb::Rollout::from(&r)).unwrap();
    assert_eq!(
        (back.timeouts, back.timeout_obs),
        (r.timeouts.clone(), r.timeout_obs.clone())
    );
}

#[test]
fn a_late_actor_starts_from_the_newest_weights_and_joins_the_rounds() {
    let mut config = RunConfig::paper(
        &EnvSpec::new(EnvKind::Angle, 2).unwrap(),
        Algo::A2c,
        60 * 3 * 8,
    );
    config.actors = 2;
    let dir = temp_dir("late");
    let rt = tokio::runtime::Runtime::new().unwrap();
    let learner = start_learner(&config, &dir, None, Arc::new(AtomicBool::new(false)), 0).unwrap();
    let hub = learner.hub.clone();
    let url =
        saver_run::services::serve_hub_on_loopback(&rt, hub.clone(), Default::default(), None)
            .unwrap();
    let spawn_actor = |i: u64| {
        let url = url.clone();
        std::thread::spawn(move || {
            let mut link = GrpcLink::connect(&url).unwrap();
            let reg = Registration {
                name: format!("a{i}"),
                session: i,
                n_envs: 1,
            };
            run_actor(&mut link, &reg, &AtomicBool::new(false)).unwrap()
        })
    };
    let early: Vec<_> = (0..2).map(spawn_actor).collect();
    // A probe registers, gets the newest weights and leaves: its closed stream takes it
    // out of the rounds again.
    let v = hub.wait_weights(10).unwrap().version;
    let mut link = GrpcLink::connect(&url).unwrap();
    let reg = Registration {
        name: "probe".into(),
        session: 99,
        n_envs: 1,
    };
    assert_eq!(link.register(&reg).unwrap().actor_id, 2);
    let first = link.weights(0).unwrap();
    assert!(
        first.version >= v,
        "a late actor got version {} < {v}",
        first.version
    );
    drop(link);
    let v = hub.wait_weights(v + 5).unwrap().version;
    let late = spawn_actor(3);
    let (_, outcome) = follow(learner, &config, false, |_| {}).unwrap();
    for a in early {
        a.join().unwrap();
    }
    let late = late.join().unwrap();
    assert!(
        late.first_version >= v,
        "the late actor started from version {}",
        late.first_version
    );
    assert!(late.rollouts > 0, "the late actor never contributed");
    assert!(outcome.steps >= config.steps);
    std::fs::remove_dir_all(dir).ok();
}

/// An async run of `config` (2 in-process actors) into `dir` while a third actor acts
/// on version 0 and hands its rollout in only once the learner is at version `late`.
fn run_with_a_late_rollout(
    config: &RunConfig,
    dir: &Path,
    late: u64,
) -> saver_learner::TrainerOutcome {
    let learner = start_learner(config, dir, None, Arc::new(AtomicBool::new(false)), 0).unwrap();
    let hub = learner.hub.clone();
    let mut slow = saver_learner::InProcessLink::new(hub.clone());
    let reg = |i: u64| Registration {
        name: format!("a{i}"),
        session: i,
        n_envs: 1,
    };
    let assignment = slow.register(&reg(9)).unwrap();
    let v0 = slow.weights(0).unwrap();
    assert_eq!(v0.version, 0);
    let mut policy = saver_core::nets::Policy::new(v0, config.env.layout(), config.head).unwrap();
    let old = saver_actor::Actor::new(&assignment, 1)
        .unwrap()
        .collect(&mut policy);
    let actors: Vec<_> = (0..2)
        .map(|i| {
            let mut link = saver_learner::InProcessLink::new(hub.clone());
            let r = reg(i);
            std::thread::spawn(move || run_actor(&mut link, &r, &AtomicBool::new(false)).unwrap())
        })
        .collect();
    hub.wait_weights(late).unwrap();
    slow.push(old).expect("the learner is still training");
    let (_, o) = follow(learner, config, false, |_| {}).unwrap();
    for a in actors {
        a.join().unwrap();
    }
    o
}

/// The paper's A2C on angle d = 2 in async mode: 2 actors of 8-step rollouts, `updates`
/// updates' worth of steps, lag at most `max_lag`.
fn async_a2c(updates: u64, max_lag: u64) -> RunConfig {
    let mut config = RunConfig::paper(
        &EnvSpec::new(EnvKind::Angle, 2).unwrap(),
        Algo::A2c,
        updates * 2 * 8,
    );
    config.actors = 2;
    config.mode = saver_core::config::Mode::Async;
    config.max_lag = Some(max_lag);
    config
}

/// metrics.csv's column `name`, parsed.
fn metrics_column<T: std::str::FromStr>(o: &saver_learner::TrainerOutcome, name: &str) -> Vec<T>
where
    T::Err: std::fmt::Debug,
{
    let csv = std::fs::read_to_string(&o.metrics).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let col = header.iter().position(|h| *h == name).unwrap();
    csv.lines()
        .skip(1)
        .map(|l| l.split(',').nth(col).unwrap().parse().unwrap())
        .collect()
}

#[test]
fn async_mode_drops_rollouts_older_than_max_lag() {
    // Async, 2 rollouts per update, max_lag 0: two actors train; a third acts on
    // version 0 and hands its rollout in only once the learner is at version 2. It must
    // be dropped as stale, and no update may use a rollout older than max_lag.
    let config = async_a2c(400, 0);
    let dir = temp_dir("async");
    let o = run_with_a_late_rollout(&config, &dir, 2);
    assert!(
        o.stale_dropped >= 1,
        "the version-0 rollout was not dropped"
    );
    let lags: Vec<u64> = metrics_column(&o, "lag_max");
    assert!(
        lags.iter().all(|&l| l == 0),
        "an update used a rollout older than max_lag: {lags:?}"
    );
    std::fs::remove_dir_all(dir).ok();
}

/// Async with V-trace and a deliberately slow actor: two actors train A2C; a third
/// acts on version 0 and hands its rollout in at version 20 or later (max_lag 150, so
/// that a busy machine that runs the trainer ahead before the push does not drop it
/// as stale). The update that takes it reports a lag of at least 20 and ratios π/μ
/// away from 1; every update of current rollouts alone reports ratios of 1 (the
/// actors' payload is the learner's own policy at that version, to rounding). At a lag
/// of 5 the slow batch's largest ratio was 1.011 against the 0.01 this asserts, and a
/// loaded machine once took it under; 20 updates move the policy ~4x as far.
#[test]
fn vtrace_weighs_a_slow_actors_rollout_by_its_ratios() {
    let mut config = async_a2c(200, 150);
    config.vtrace = true;
    // A rate at which 20 updates move the policy visibly.
    config.lr = 3e-3;
    saver_core::algo::validate(&config).unwrap();
    let dir = temp_dir("async-vtrace");
    let o = run_with_a_late_rollout(&config, &dir, 20);
    let lags: Vec<u64> = metrics_column(&o, "lag_max");
    let means: Vec<f32> = metrics_column(&o, "vtrace_ratio_mean");
    let maxes: Vec<f32> = metrics_column(&o, "vtrace_ratio_max");
    let clipped: Vec<f32> = metrics_column(&o, "vtrace_clipped");
    let mut slow_rows = 0;
    for (((l, m), x), c) in lags.iter().zip(&means).zip(&maxes).zip(&clipped) {
        if *l >= 20 {
            slow_rows += 1;
            assert!(
                (x - 1.0).abs() > 0.01 || (m - 1.0).abs() > 0.01,
                "{l} {m} {x}"
            );
        } else if *l == 0 {
            assert!(
                (m - 1.0).abs() < 1e-3 && (x - 1.0).abs() < 1e-2,
                "{l} {m} {x}"
            );
            // Rounding apart, not clipped.
            assert_eq!(*c, 0.0, "{l} {m} {x}");
        }
    }
    assert!(slow_rows >= 1, "the slow rollout was not used");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn the_store_refuses_a_pcpn_for_another_env_spec_with_failed_precondition() {
    use saver_pcpn_trainer::service::{fetch, serve as serve_store, PcpnService};
    let dir = temp_dir("precondition");
    let store = saver_pcpn_trainer::PcpnStore::new(dir.join("store"));
    // A d = 2 PCPN saved under the d = 4 file name.
    let d2 = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let d4 = EnvSpec::new(EnvKind::Angle, 4).unwrap();
    let p = untrained_pcpn(&d2);
    let tensors = saver_core::checkpoint::to_named_all(&p.tensors().unwrap()).unwrap();
    let settings = PretrainConfig::recommended(EnvKind::Angle);
    let info = store
        .save(&d2, &settings, &tensors, Default::default())
        .unwrap();
    std::fs::rename(&info.path, store.path_for(&d4, &settings)).unwrap();

    let rt = tokio::runtime::Runtime::new().unwrap();
    let listener = rt
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    rt.spawn(serve_store(
        PcpnService::new(dir.join("store")),
        listener,
        std::future::pending(),
    ));
    let err = rt
        .block_on(fetch(
            &url,
            &d4,
            &settings,
            &saver_proto::ClientAccess::default(),
        ))
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::FailedPrecondition, "{err}");
    assert!(err.message().contains("angle-d2"), "{err}");
    std::fs::remove_dir_all(dir).ok();
}

/// The slow env steps exactly as the env it wraps (the same observations, rewards
/// and ends from the same start).
#[test]
fn a_slow_env_steps_as_the_env_it_wraps() {
    use saver_actor::slow::SlowEnv;
    use saver_core::env::Env;
    use saver_core::rng::rng_for;
    use std::time::Duration;
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let mut plain = spec.make(20).unwrap();
    let mut slow = SlowEnv {
        inner: spec.make(20).unwrap(),
        delay: Duration::from_micros(10),
    };
    let l = plain.layout();
    let (mut a, mut b) = (vec![0.0; l.obs_dim], vec![0.0; l.obs_dim]);
    plain.reset(&mut rng_for(3, 0), &mut a);
    slow.reset(&mut rng_for(3, 0), &mut b);
    assert_eq!(a, b);
    for t in 0..25 {
        let action = [0.3, (t as f32 * 0.7).sin()];
        let (sa, sb) = (plain.step(&action, &mut a), slow.step(&action, &mut b));
        assert_eq!((sa, &a), (sb, &b));
        assert_eq!(plain.snapshot(), slow.snapshot());
    }
}
