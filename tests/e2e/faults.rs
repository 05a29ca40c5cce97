//! Access and faults: the token on every call, sync rounds that do not wait for a
//! silent actor, and a learner that resumes from its checkpoint.

use crate::{assert_tensors_in, temp_dir};
use saver_actor::grpc::GrpcLink;
use saver_actor::run_actor;
use saver_core::config::{Algo, RunConfig};
use saver_core::env::{EnvKind, EnvSpec};
use saver_core::link::{LearnerLink, LinkError, Registration};
use saver_learner::InProcessLink;
use saver_proto::pb::learner_client::LearnerClient;
use saver_proto::{pb, Access, AddToken, CheckToken, ClientAccess};
use saver_run::train::{start_learner, train_with};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// A2C on angle d = 2 for `updates` sync updates of `actors` actors.
pub fn small(actors: u32, updates: u64) -> RunConfig {
    let mut c = RunConfig::paper(&EnvSpec::new(EnvKind::Angle, 2).unwrap(), Algo::A2c, 0);
    c.actors = actors;
    c.steps = updates * actors as u64 * c.envs_per_actor as u64 * c.rollout as u64;
    c
}

#[test]
fn every_learner_call_needs_the_token() {
    let config = small(1, 1000);
    let dir = temp_dir("token");
    let rt = tokio::runtime::Runtime::new().unwrap();
    let learner = start_learner(&config, &dir, None, Arc::new(AtomicBool::new(false)), 0).unwrap();
    let access = Access::token(CheckToken::new(Some("tok-1")).unwrap());
    let url =
        saver_run::services::serve_hub_on_loopback(&rt, learner.hub.clone(), access, None).unwrap();

    let status_with = |token: Option<&str>| {
        rt.block_on(async {
            let channel = saver_proto::endpoint(&url)
                .unwrap()
                .connect()
                .await
                .unwrap();
            let mut c = LearnerClient::with_interceptor(channel, AddToken::new(token).unwrap());
            c.status(pb::StatusRequest {}).await.map(|r| r.into_inner())
        })
    };
    for bad in [None, Some("tok-2"), Some("tok-")] {
        let e = status_with(bad).unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated, "token {bad:?}");
    }
    assert_eq!(status_with(Some("tok-1")).unwrap().actors, 0);

    // An actor without the token is refused at registration, and nothing registers.
    let reg = Registration {
        name: "intruder".into(),
        session: 7,
        n_envs: 1,
    };
    let mut link = GrpcLink::connect(&url).unwrap();
    match link.register(&reg) {
        Err(LinkError::Rejected(why)) => assert!(why.contains("token"), "{why}"),
        other => panic!("expected a refusal, got {other:?}"),
    }
    let mut link = GrpcLink::connect_with(
        &url,
        &ClientAccess {
            token: AddToken::new(Some("tok-1")).unwrap(),
            tls: None,
        },
    )
    .unwrap();
    assert_eq!(link.register(&reg).unwrap().actor_id, 0);
    assert_eq!(learner.hub.actors().len(), 1);
    learner.hub.close("test over");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_sync_round_goes_ahead_without_a_silent_actor() {
    let config = small(2, 30);
    let dir = temp_dir("silent");
    let learner = start_learner(&config, &dir, None, Arc::new(AtomicBool::new(false)), 0).unwrap();
    let hub = learner.hub.clone();
    hub.set_round_timeout(Duration::from_secs(1));
    // Registers and never sends: the first round waits 1 s for it, later ones not.
    let silent = Registration {
        name: "silent".into(),
        session: 1,
        n_envs: 1,
    };
    assert_eq!(hub.register(&silent).unwrap().actor_id, 0);
    let actors: Vec<_> = (0..2u64)
        .map(|i| {
            let mut link = InProcessLink::new(hub.clone());
            std::thread::spawn(move || {
                let reg = Registration {
                    name: format!("a{i}"),
                    session: 10 + i,
                    n_envs: 1,
                };
                run_actor(&mut link, &reg, &AtomicBool::new(false)).unwrap()
            })
        })
        .collect();
    let (_, outcome) = saver_run::train::follow(learner, &config, false, |_| {}).unwrap();
    for a in actors {
        // One per version; the last may land before the learner says it is done.
        let sent = a.join().unwrap().rollouts;
        assert!((30..=31).contains(&sent), "{sent} rollouts");
    }
    assert_eq!(outcome.version, 30);
    assert!(!outcome.interrupted);
    assert_eq!(hub.stats.late.load(Ordering::Relaxed), 1);
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_restarted_learner_resumes_from_its_checkpoint() {
    let first = small(2, 20);
    let dir = temp_dir("resume");
    let stop = Arc::new(AtomicBool::new(false));
    let o1 = train_with(&first, &dir, None, stop.clone(), false).unwrap();
    assert_eq!(o1.version, 20);
    let saved = saver_core::checkpoint::load(&dir.join("checkpoint.safetensors")).unwrap();

    // Restarted with more steps: the first published weights are the checkpoint's.
    let mut longer = first.clone();
    longer.steps *= 2;
    let learner = start_learner(&longer, &dir, None, stop.clone(), 0).unwrap();
    assert_eq!(learner.start.version, 20);
    assert_eq!(learner.start.steps, first.steps);
    let w = learner.hub.latest();
    assert_eq!(w.version, 20);
    assert_tensors_in(&w.tensors, &saved.tensors);
    learner.hub.close("restart");
    let o = learner.trainer.join.join().unwrap().unwrap();
    assert!(o.interrupted);

    // Trains on to the new length; metrics.csv continues the same rows.
    let o2 = train_with(&longer, &dir, None, stop, false).unwrap();
    assert_eq!((o2.version, o2.steps), (40, longer.steps));
    let csv = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
    let updates: Vec<u64> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(1).unwrap().parse().unwrap())
        .collect();
    assert_eq!(updates, (1..=40).collect::<Vec<_>>());

    // Other settings are refused, not mixed into this run.
    let mut other = longer.clone();
    other.seed += 1;
    let err = start_learner(&other, &dir, None, Arc::new(AtomicBool::new(false)), 0)
        .err()
        .expect("a checkpoint of another seed must be refused");
    assert!(format!("{err:#}").contains("other settings"), "{err:#}");
    std::fs::remove_dir_all(dir).ok();
}
