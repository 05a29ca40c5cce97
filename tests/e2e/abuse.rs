//! The defect classes a hostile client found (issue 15), one test each: extreme
//! values, another actor's session, bare registrations, unreadable messages, forged
//! episodes, oversized messages, and a run killed after its checkpoint.

use crate::faults::small;
use crate::hostile::{learner_with, one_actor_learner, open_stream, register, register_and_roll};
use crate::temp_dir;
use saver_actor::grpc::GrpcLink;
use saver_actor::remote::{run_remote, RemoteActor};
use saver_actor::{run_actor, Actor};
use saver_core::link::{ActorSettings, Assignment, Registration};
use saver_core::nets::Policy;
use saver_core::rollout::{Batch, Rollout};
use saver_core::CoreError;
use saver_learner::InProcessLink;
use saver_proto::pb::learner_client::LearnerClient;
use saver_proto::{pb, ACTOR_ID_KEY, SESSION_KEY};
use saver_run::train::{start_learner, train_with};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio_stream::StreamExt;
use tonic::Code;

/// The first ack (or the status that ended the stream) after sending `r`.
async fn answer(
    tx: &tokio::sync::mpsc::Sender<pb::Rollout>,
    acks: &mut tonic::Streaming<pb::RolloutAck>,
    r: pb::Rollout,
) -> Result<pb::RolloutAck, tonic::Status> {
    tx.send(r).await.unwrap();
    acks.next().await.expect("an answer")
}

#[test]
fn extreme_finite_values_are_refused_and_a_poisoned_batch_changes_nothing() {
    let (config, dir, rt, _learner, hub, url) = one_actor_learner("extreme");
    rt.block_on(async {
        let (mut client, base) = register_and_roll(&url, &hub, &config).await;
        let (tx, mut acks) = open_stream(&mut client, &base, false).await;
        let obs_dim = config.env.layout().obs_dim;
        type Break = fn(&mut pb::Rollout, usize);
        let cases: [(Break, &str); 6] = [
            (|r, _| r.obs[0] = 1e10, "obs[0]"),
            (|r, _| r.actions[1] = 1e10, "actions[1]"),
            (|r, _| r.vector_reward[0] = 1e18, "vector_reward[0]"),
            // The env's own reward: optional, but one per step and within +-1e9.
            (
                |r, _| r.env_reward = vec![0.0; 3],
                "env_reward has 3 values",
            ),
            (
                |r, _| {
                    r.env_reward = vec![-1.0; r.done.len()];
                    r.env_reward[2] = 2e9;
                },
                "env_reward[2]",
            ),
            (
                |r, obs_dim| {
                    // A timeout at step 3 whose final observation is near f32::MAX.
                    let before = r.done[..3].iter().filter(|&&d| d).count();
                    if !r.done[3] {
                        r.done[3] = true;
                        let ep = pb::Episode {
                            length: 1000,
                            success: false,
                            ret: 0.0,
                        };
                        r.episodes.insert(before, ep);
                    }
                    r.timeouts = vec![3];
                    r.timeout_obs = vec![f32::MAX; obs_dim];
                },
                "timeout_obs[0]",
            ),
        ];
        for (i, (bad, place)) in cases.into_iter().enumerate() {
            let mut r = base.clone();
            r.seq = 10 + i as u64;
            bad(&mut r, obs_dim);
            let ack = answer(&tx, &mut acks, r).await.unwrap();
            assert!(!ack.accepted, "{place}");
            assert_eq!(Code::from(ack.code), Code::InvalidArgument, "{}", ack.error);
            assert!(ack.error.contains(place), "{place}: {}", ack.error);
        }
        // The genuine rollout still trains (while its stream is open the actor counts).
        assert!(answer(&tx, &mut acks, base).await.unwrap().accepted);
        let h = hub.clone();
        let v = tokio::task::spawn_blocking(move || h.wait_weights(1).unwrap().version);
        assert_eq!(v.await.unwrap(), 1);
    });
    hub.close("test over");

    // Whatever gets past the edge (here: straight to the algorithm), a batch that
    // makes the loss non-finite is skipped: same weights, same optimiser step count;
    // the next good batch trains.
    let dev = candle_core::Device::Cpu;
    let mut algo = saver_core::algo::build(&config, None, &dev).unwrap();
    let layout = config.env.layout();
    let weights = Arc::new(saver_core::link::PolicyWeights {
        version: 0,
        tensors: algo.policy_tensors().unwrap(),
    });
    let assignment = Assignment {
        actor_id: 0,
        session: 1,
        settings: ActorSettings::of(&config),
    };
    let mut policy = Policy::new(weights.clone(), layout, config.head).unwrap();
    let good: Rollout = Actor::new(&assignment, 1).unwrap().collect(&mut policy);
    let mut poisoned = good.clone();
    poisoned.obs.iter_mut().for_each(|x| *x = 1e30);
    poisoned.vector_reward.iter_mut().for_each(|x| *x = 3e38);
    let batch = Batch::from_rollouts(&[poisoned], &layout).unwrap();
    let e = algo.update(&batch).unwrap_err();
    assert!(matches!(e, CoreError::NonFinite(_)), "{e}");
    assert_eq!(algo.optimizer_steps(), 0);
    crate::assert_tensors_in(&algo.policy_tensors().unwrap(), &weights.tensors);
    algo.update(&Batch::from_rollouts(&[good], &layout).unwrap())
        .unwrap();
    assert_eq!(algo.optimizer_steps(), 1);
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_session_is_a_secret_that_only_its_stream_can_use() {
    let (config, dir, rt, _learner, hub, url) = one_actor_learner("session");
    rt.block_on(async {
        let (mut a, base) = register_and_roll(&url, &hub, &config).await;
        // Another client registers and opens its own stream ...
        let (mut b, reg_b) = register(&url, &config).await;
        assert_ne!(reg_b.session, base.session);
        let mut own = base.clone();
        own.actor_id = reg_b.actor_id;
        own.session = reg_b.session;
        let (tx_b, mut acks_b) = open_stream(&mut b, &own, false).await;
        // ... and sends rollouts as actor A: with a guessed session and the largest
        // sequence number (the lock-out attack), and with A's id alone.
        for session in [base.session ^ 1, 0] {
            let mut forged = base.clone();
            forged.session = session;
            forged.seq = u64::MAX;
            let ack = answer(&tx_b, &mut acks_b, forged).await.unwrap();
            assert!(!ack.accepted);
            assert_eq!(Code::from(ack.code), Code::FailedPrecondition);
            // The refusal names no session: not A's (hex or decimal), not B's.
            for secret in [base.session, reg_b.session] {
                assert!(
                    !ack.error.contains(&format!("{secret:x}"))
                        && !ack.error.contains(&secret.to_string()),
                    "{}",
                    ack.error
                );
            }
        }
        // A stream that names A's registration with a wrong session is refused.
        let mut wrong = base.clone();
        wrong.session ^= 0xff;
        let mut req = tonic::Request::new(tokio_stream::iter(Vec::<pb::Rollout>::new()));
        req.metadata_mut()
            .insert(ACTOR_ID_KEY, wrong.actor_id.into());
        req.metadata_mut().insert(SESSION_KEY, wrong.session.into());
        let e = b.stream_rollouts(req).await.unwrap_err();
        assert_eq!(e.code(), Code::FailedPrecondition);
        // A's own stream: its rollout is accepted (nothing locked it out), and a
        // second stream for the same registration is refused.
        let (tx_a, mut acks_a) = open_stream(&mut a, &base, false).await;
        let mut req = tonic::Request::new(tokio_stream::iter(Vec::<pb::Rollout>::new()));
        req.metadata_mut()
            .insert(ACTOR_ID_KEY, base.actor_id.into());
        req.metadata_mut().insert(SESSION_KEY, base.session.into());
        let e = b.stream_rollouts(req).await.unwrap_err();
        assert_eq!(e.code(), Code::FailedPrecondition, "{e}");
        assert!(answer(&tx_a, &mut acks_a, base).await.unwrap().accepted);
    });
    hub.close("test over");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn bare_registrations_neither_stall_rounds_nor_pile_up() {
    // Rounds wait up to 60 s for a connected actor: a round that waited for a bare
    // registration would show as a late actor.
    let (_config, dir, rt, _learner, hub, url) = one_actor_learner("bare");
    hub.set_round_timeout(Duration::from_secs(60));
    let status = rt.block_on(async {
        let mut c = LearnerClient::connect(url.clone()).await.unwrap();
        for i in 0..1000u64 {
            let r = pb::RegisterRequest {
                name: "flood".into(),
                session: i,
                n_envs: 1,
                env: None,
            };
            c.register(r).await.unwrap();
        }
        c.status(pb::StatusRequest {}).await.unwrap().into_inner()
    });
    assert_eq!(status.actors, 0);
    assert_eq!(status.pending as usize, saver_learner::MAX_PENDING);
    // A real actor over gRPC trains on at once.
    let stop = Arc::new(AtomicBool::new(false));
    let (u, s) = (url.clone(), stop.clone());
    let actor = std::thread::spawn(move || {
        let mut link = GrpcLink::connect(&u).unwrap();
        let reg = Registration {
            name: "real".into(),
            session: 7,
            n_envs: 1,
        };
        run_actor(&mut link, &reg, &s).unwrap()
    });
    assert!(hub.wait_weights(5).unwrap().version >= 5);
    assert_eq!(hub.stats.late.load(Ordering::Relaxed), 0);
    assert_eq!(hub.actors().len(), 1);
    stop.store(true, Ordering::Relaxed);
    hub.close("test over");
    actor.join().unwrap();
    std::fs::remove_dir_all(dir).ok();
}

/// A message on the Rollout stream whose field 7 (obs, floats) is a varint.
#[derive(Clone, PartialEq, prost::Message)]
struct NotARollout {
    #[prost(uint64, tag = "7")]
    obs: u64,
}

#[test]
fn unreadable_or_oversized_messages_end_the_stream_with_their_status() {
    let (config, dir, rt, _learner, hub, url) = one_actor_learner("unreadable");
    rt.block_on(async {
        // Over this stream's limit (one env of angle d = 2: a few KiB), far below the
        // server's 64 MiB: a million empty episodes, 2 MiB on the wire.
        let (mut client, base) = register_and_roll(&url, &hub, &config).await;
        let (tx, mut acks) = open_stream(&mut client, &base, false).await;
        let mut big = base.clone();
        big.episodes = vec![pb::Episode::default(); 1 << 20];
        let e = answer(&tx, &mut acks, big).await.unwrap_err();
        assert_eq!(e.code(), Code::ResourceExhausted, "{e}");
        assert!(acks.next().await.is_none(), "the stream ended");

        // Bytes that do not decode as a Rollout.
        let channel = tonic::transport::Endpoint::from_shared(url.clone())
            .unwrap()
            .connect()
            .await
            .unwrap();
        let mut grpc = tonic::client::Grpc::new(channel);
        grpc.ready().await.unwrap();
        let codec = tonic_prost::ProstCodec::<NotARollout, pb::RolloutAck>::default();
        let path = tonic::codegen::http::uri::PathAndQuery::from_static(
            "/saver.v1.Learner/StreamRollouts",
        );
        let req = tonic::Request::new(tokio_stream::iter(vec![NotARollout { obs: 5 }]));
        let mut answers = grpc.streaming(req, path, codec).await.unwrap().into_inner();
        let e = answers.next().await.unwrap().unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{e}");
    });
    assert_eq!(hub.stats.rejected.load(Ordering::Relaxed), 2);
    assert_eq!(hub.stats.accepted.load(Ordering::Relaxed), 0);
    hub.close("test over");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn episode_reports_must_match_the_steps_the_learner_counted() {
    // Episodes of at most 3 steps: a rollout of 8 ends two (timeouts at steps 2, 5).
    let (config, dir, rt, _learner, hub, url) = learner_with("forged", |c| {
        c.max_episode_steps = 3;
    });
    rt.block_on(async {
        let (mut client, assignment) = register(&url, &config).await;
        let mut policy = Policy::new(hub.latest(), config.env.layout(), config.head).unwrap();
        let first = pb::Rollout::from(&Actor::new(&assignment, 1).unwrap().collect(&mut policy));
        assert_eq!(first.seq, 0);
        assert_eq!(first.episodes.len(), 2);
        let (tx, mut acks) = open_stream(&mut client, &first, false).await;
        let forgeries: [fn(&mut pb::Rollout); 4] = [
            |r| r.episodes[0].length = 1,
            |r| {
                r.episodes.pop();
            },
            |r| r.episodes.push(r.episodes[0]),
            |r| r.episodes[1].success = true,
        ];
        for forge in forgeries {
            let mut r = first.clone();
            forge(&mut r);
            let ack = answer(&tx, &mut acks, r).await.unwrap();
            assert!(!ack.accepted);
            assert_eq!(Code::from(ack.code), Code::InvalidArgument, "{}", ack.error);
        }
        assert!(answer(&tx, &mut acks, first).await.unwrap().accepted);
    });
    hub.close("test over");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_run_killed_after_its_checkpoint_resumes_cleanly() {
    let first = small(2, 10);
    let mut longer = first.clone();
    longer.steps *= 2;
    let dir = temp_dir("killed");
    let stop = Arc::new(AtomicBool::new(false));
    train_with(&first, &dir, None, stop.clone(), false).unwrap();
    let ckpt = dir.join("checkpoint.safetensors");
    let at_ten = std::fs::read(&ckpt).unwrap();
    // On to 20 updates; then "killed" with the checkpoint of update 10 the last one
    // written, and a temporary file a killed writer left.
    train_with(&longer, &dir, None, stop.clone(), false).unwrap();
    std::fs::write(&ckpt, &at_ten).unwrap();
    let stale = dir.join(".checkpoint.safetensors.tmp-4000000");
    std::fs::write(&stale, b"half").unwrap();

    // A restart with other settings is refused and changes nothing.
    let config_toml = std::fs::read(dir.join("config.toml")).unwrap();
    let mut other = longer.clone();
    other.seed += 1;
    let err = start_learner(&other, &dir, None, stop.clone(), 0)
        .err()
        .unwrap();
    assert!(format!("{err:#}").contains("another folder"), "{err:#}");
    assert_eq!(std::fs::read(dir.join("config.toml")).unwrap(), config_toml);
    assert!(stale.exists());

    // The restart with one of its two actors back: it goes ahead after the round
    // deadline, versions continue above 20 (the newest published: the checkpoint's
    // weights are served as 21, not as a second 20), the temporary is gone and
    // metrics.csv holds no row twice.
    let learner = start_learner(&longer, &dir, None, stop.clone(), 0).unwrap();
    assert_eq!(learner.start.steps, first.steps);
    assert_eq!(learner.hub.latest().version, 21);
    assert!(!stale.exists());
    learner.hub.set_round_timeout(Duration::from_millis(200));
    let mut link = InProcessLink::new(learner.hub.clone());
    let hub = learner.hub.clone();
    let actor = std::thread::spawn(move || {
        let reg = Registration {
            name: "back".into(),
            session: 0,
            n_envs: 1,
        };
        run_actor(&mut link, &reg, &AtomicBool::new(false)).unwrap()
    });
    let (_, outcome) = saver_run::train::follow(learner, &longer, false, |_| {}).unwrap();
    hub.close("test over");
    actor.join().unwrap();
    assert_eq!(outcome.steps, longer.steps);
    let csv = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
    let rows: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').take(3).map(|v| v.parse().unwrap()).collect())
        .collect();
    let versions: Vec<u64> = rows.iter().map(|r| r[1] as u64).collect();
    assert_eq!(&versions[..10], &(1..=10).collect::<Vec<_>>()[..]);
    assert_eq!(versions[10], 22, "{versions:?}");
    for w in rows.windows(2) {
        assert!(
            w[1][0] > w[0][0] && w[1][1] > w[0][1],
            "steps and versions ascend"
        );
        assert!(w[1][2] >= w[0][2], "wall_s goes on across the restart");
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_link_that_the_learner_forgets_registers_again() {
    // An actor whose registration the learner no longer knows (here: the learner
    // forgot it, as after a lease or a lock-out) loses its link, and `saver actor`'s
    // loop (`run_remote`) registers again under a new session, instead of sending
    // refused rollouts for ever or giving up, and the run trains on its rollouts.
    let (_config, dir, _rt, _learner, hub, url) = one_actor_learner("forgotten");
    let remote = RemoteActor {
        learner: url,
        name: "a".into(),
        envs: 1,
        give_up: Duration::from_secs(60),
        shared_weights: false,
        access: Default::default(),
        step_delay: Duration::ZERO,
    };
    let stop = Arc::new(AtomicBool::new(false));
    let actor = {
        let stop = stop.clone();
        std::thread::spawn(move || run_remote(&remote, &stop))
    };
    // The connected actor's (id, session), once one other than `not` is attached.
    let connected = |not: Option<u64>| {
        let deadline = std::time::Instant::now() + Duration::from_secs(60);
        loop {
            let found = hub
                .actors()
                .into_iter()
                .find_map(|id| Some((id, hub.session_of(id)?)))
                .filter(|&(_, s)| Some(s) != not);
            if let Some(found) = found {
                return found;
            }
            assert!(
                std::time::Instant::now() < deadline,
                "no actor (re)attached"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    };
    let trains = |min: u64| {
        let v = hub
            .wait_weights_for(min, Duration::from_secs(60))
            .unwrap()
            .version;
        assert!(
            v >= min,
            "no update past version {} on this registration",
            min - 1
        );
        v
    };
    let (id, first) = connected(None);
    trains(2);
    hub.unregister(id, first);
    let after_forget = hub.latest().version;
    let (_, second) = connected(Some(first));
    assert_ne!(second, first);
    trains(after_forget + 3);
    stop.store(true, Ordering::SeqCst);
    hub.close("test over");
    // Stopped, it does not reconnect to the closed learner (it did, until `give_up`).
    actor.join().unwrap().expect("the actor ends cleanly");
    std::fs::remove_dir_all(dir).ok();
}
