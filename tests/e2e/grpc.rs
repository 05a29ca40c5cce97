//! The learner and actors over real gRPC on 127.0.0.1:0, through the generated client.

use crate::temp_dir;
use saver::bench::random_pcpn;
use saver::train::{follow, start_learner, train_with};
use saver_actor::grpc::GrpcLink;
use saver_actor::run_actor;
use saver_core::config::{Algo, RunConfig};
use saver_core::env::{EnvKind, EnvSpec};
use saver_core::link::Registration;
use saver_core::nets::Pcpn;
use saver_learner::grpc::{serve, LearnerService};
use saver_proto::NamedTensor;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

fn checkpoint(path: &Path) -> Vec<NamedTensor> {
    saver_proto::decode(&std::fs::read(path).unwrap())
        .unwrap()
        .0
}

fn assert_bit_identical(a: &[NamedTensor], b: &[NamedTensor]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert_eq!((&x.name, &x.shape), (&y.name, &y.shape));
        assert!(
            x.data
                .iter()
                .zip(&y.data)
                .all(|(p, q)| p.to_bits() == q.to_bits()),
            "{} differs",
            x.name
        );
    }
}

/// Runs `config` with its actors as gRPC clients of a learner served on 127.0.0.1:0.
fn run_over_grpc(
    config: &RunConfig,
    out: &Path,
    pcpn: Option<Pcpn>,
) -> saver_learner::TrainerOutcome {
    let rt = tokio::runtime::Runtime::new().unwrap();
    let learner = start_learner(config, out, pcpn, Arc::new(AtomicBool::new(false))).unwrap();
    let (service, _status) = LearnerService::new(learner.hub.clone());
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
                run_actor(&mut link, &reg, &AtomicBool::new(false)).unwrap()
            })
        })
        .collect();
    let (_, outcome) = follow(learner, config, false, |_| {}).unwrap();
    for a in actors {
        a.join().unwrap();
    }
    let _ = stop_tx.send(());
    rt.block_on(server).unwrap().unwrap();
    outcome
}

#[test]
fn sync_over_grpc_equals_the_embedded_run_bit_for_bit() {
    // SAVER (with a fixed random PCPN) on angle d = 2 and A2C on select d = 3:
    // 4 actors, 20 updates each way.
    let saver = RunConfig::paper(
        EnvSpec::new(EnvKind::Angle, 2).unwrap(),
        Algo::Saver,
        20 * 4 * 8,
    );
    let a2c = RunConfig::paper(
        EnvSpec::new(EnvKind::Select, 3).unwrap(),
        Algo::A2c,
        20 * 4 * 8,
    );
    for mut config in [saver, a2c] {
        config.actors = 4;
        let pcpn = (config.algo == Algo::Saver)
            .then(|| random_pcpn(&config.env, &candle_core::Device::Cpu).unwrap());
        let dir = temp_dir(&format!("grpc-eq-{}", config.algo.name()));
        let embedded = train_with(
            &config,
            &dir.join("embedded"),
            pcpn.clone(),
            Arc::new(AtomicBool::new(false)),
            false,
        )
        .unwrap();
        let remote = run_over_grpc(&config, &dir.join("grpc"), pcpn);
        assert_eq!((embedded.version, remote.version), (20, 20));
        assert_bit_identical(
            &checkpoint(&embedded.checkpoint),
            &checkpoint(&remote.checkpoint),
        );
        std::fs::remove_dir_all(dir).ok();
    }
}
