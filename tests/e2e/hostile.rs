//! Hostile input at the learner's edge, over real gRPC: 100,000 malformed rollouts on
//! one stream, each refused with the right status code, no panic, and weights that no
//! refused rollout changed; then raw garbage at the port, after which it still serves.

use crate::{assert_tensors_in, temp_dir};
use rand::Rng;
use saver_actor::Actor;
use saver_core::config::{Algo, RunConfig};
use saver_core::env::{EnvKind, EnvSpec};
use saver_core::link::{ActorSettings, Assignment};
use saver_core::nets::Policy;
use saver_core::rng::rng_for;
use saver_proto::pb::learner_client::LearnerClient;
use saver_proto::{pb, ACKS_KEY, ACKS_REFUSALS, ACTOR_ID_KEY, SESSION_KEY};
use saver_run::train::start_learner;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use tokio_stream::StreamExt;
use tonic::Code;

const CASES: usize = 100_000;

/// The `k`-th float array of a rollout.
fn floats(r: &mut pb::Rollout, k: usize) -> &mut Vec<f32> {
    match k {
        0 => &mut r.obs,
        1 | 2 => &mut r.payload,
        3 => &mut r.actions,
        4 => &mut r.state_delta,
        _ => &mut r.vector_reward,
    }
}

/// One malformed copy of `base` (sequence numbers from 6 on; 5 was accepted) and the
/// code the learner must answer.
fn mutate(base: &pb::Rollout, i: usize, rng: &mut impl Rng) -> (pb::Rollout, Code) {
    let mut r = base.clone();
    r.seq = 6 + i as u64;
    // (A message over the size cap ends the stream: abuse::unreadable_or_oversized_….)
    let kind = rng.random_range(0..13);
    let code = match kind {
        0 => {
            // A shorter array (done included).
            let k = rng.random_range(0..7);
            if k == 6 {
                let n = rng.random_range(0..r.done.len());
                r.done.truncate(n);
            } else {
                let a = floats(&mut r, k);
                let n = rng.random_range(0..a.len());
                a.truncate(n);
            }
            Code::InvalidArgument
        }
        1 => {
            let a = floats(&mut r, rng.random_range(0..6));
            let extra = rng.random_range(1..100);
            a.extend(std::iter::repeat_n(0.5, extra));
            Code::InvalidArgument
        }
        2 => {
            let a = floats(&mut r, rng.random_range(0..6));
            let j = rng.random_range(0..a.len());
            a[j] = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY][rng.random_range(0..3)];
            Code::InvalidArgument
        }
        3 => {
            r.n_envs = [0, 2, 1024, u32::MAX][rng.random_range(0..4)];
            Code::InvalidArgument
        }
        4 => {
            r.n_steps = [0, 1, 7, 9, u32::MAX][rng.random_range(0..5)];
            Code::InvalidArgument
        }
        5 => {
            r.actor_id = rng.random_range(1..u32::MAX);
            Code::FailedPrecondition
        }
        6 => {
            r.session ^= rng.random_range(1..u64::MAX);
            Code::FailedPrecondition
        }
        7 => {
            r.seq = rng.random_range(0..=5);
            Code::FailedPrecondition
        }
        8 => {
            r.policy_version = rng.random_range(2..u64::MAX);
            Code::FailedPrecondition
        }
        9 => {
            let bad = [
                pb::Episode {
                    length: 0,
                    success: true,
                    ret: 1.0,
                },
                pb::Episode {
                    length: 5000,
                    success: false,
                    ret: 1.0,
                },
                pb::Episode {
                    length: 3,
                    success: true,
                    ret: f32::NAN,
                },
            ];
            r.episodes = vec![bad[rng.random_range(0..3)]];
            Code::InvalidArgument
        }
        10 => {
            let e = pb::Episode {
                length: 1,
                success: true,
                ret: 0.0,
            };
            r.episodes = vec![e; 9];
            Code::InvalidArgument
        }
        11 => {
            // A timeout at a step that ends no episode or past the rollout, repeated
            // indices, or a final observation of the wrong length or not finite
            // (every variant is malformed whether or not the base rollout has a done step).
            let obs_dim = r.obs.len() / 9;
            match rng.random_range(0..4) {
                0 => r.timeouts = vec![rng.random_range(0..8)],
                1 => r.timeouts = vec![rng.random_range(8..u32::MAX)],
                2 => r.timeout_obs = vec![0.5; rng.random_range(1..3 * obs_dim)],
                _ => {
                    r.done[3] = true;
                    r.timeouts = vec![3];
                    r.timeout_obs = vec![f32::NAN; obs_dim];
                }
            }
            Code::InvalidArgument
        }
        12 => {
            // Issue 35's forged successes: every step ends a one-step episode flagged
            // as a success, lengths and returns consistent, but from p = (0.9, 0.9) a
            // step of Δp = (−0.05, −0.05) reaches (0.85, 0.85), far outside the goal's
            // radius 0.1 around the origin.
            let n = r.done.len();
            r.obs = vec![0.9; r.obs.len()];
            r.state_delta = vec![-0.05; r.state_delta.len()];
            r.vector_reward = vec![0.05; r.vector_reward.len()];
            r.done = vec![true; n];
            (r.timeouts, r.timeout_obs) = (vec![], vec![]);
            let forged = pb::Episode {
                length: 1,
                success: true,
                ret: 0.1,
            };
            r.episodes = vec![forged; n];
            Code::InvalidArgument
        }
        _ => unreachable!("kinds are 0..13"),
    };
    (r, code)
}

const SESSION: u64 = 0x5eed;

/// Registers a client with the learner at `url` and makes one real rollout (seq 5) of
/// that actor stepping the env with the current weights.
pub async fn register_and_roll(
    url: &str,
    hub: &saver_learner::Hub,
    config: &RunConfig,
) -> (LearnerClient<tonic::transport::Channel>, pb::Rollout) {
    let (client, assignment) = register(url, config).await;
    let mut actor = Actor::new(&assignment, 1).unwrap();
    let mut policy = Policy::new(hub.latest(), config.env.layout(), config.head).unwrap();
    let mut good = actor.collect(&mut policy);
    good.seq = 5;
    (client, pb::Rollout::from(&good))
}

/// Registers a client with one env at the learner at `url`; returns the client and
/// its assignment (the learner's session included).
pub async fn register(
    url: &str,
    config: &RunConfig,
) -> (LearnerClient<tonic::transport::Channel>, Assignment) {
    let mut client = LearnerClient::connect(url.to_string())
        .await
        .unwrap()
        .max_encoding_message_size(saver_proto::MAX_MESSAGE_BYTES);
    let reply = client
        .register(pb::RegisterRequest {
            name: "fuzz".into(),
            session: SESSION,
            n_envs: 1,
            env: None,
        })
        .await
        .unwrap()
        .into_inner();
    let assignment = Assignment {
        actor_id: reply.actor_id,
        session: reply.session,
        settings: ActorSettings::try_from(reply.settings.as_ref().unwrap()).unwrap(),
    };
    // The reply's fields say what the run's config says.
    let (s, want) = (&assignment.settings, ActorSettings::of(config));
    assert_eq!(
        (
            s.algo,
            s.mode,
            s.rollout,
            s.seed,
            s.max_episode_steps,
            &s.env
        ),
        (
            want.algo,
            want.mode,
            want.rollout,
            want.seed,
            want.max_episode_steps,
            &want.env
        )
    );
    assert_eq!(s.policy.params(), want.policy.params());
    assert_eq!(s.policy.payload_width(), want.policy.payload_width());
    (client, assignment)
}

/// Opens StreamRollouts as `base`'s actor (asking for refusals only if `refusals`).
pub async fn open_stream(
    client: &mut LearnerClient<tonic::transport::Channel>,
    base: &pb::Rollout,
    refusals: bool,
) -> (
    tokio::sync::mpsc::Sender<pb::Rollout>,
    tonic::Streaming<pb::RolloutAck>,
) {
    let (tx, rx) = tokio::sync::mpsc::channel::<pb::Rollout>(64);
    let mut req = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(rx));
    let md = req.metadata_mut();
    md.insert(ACTOR_ID_KEY, base.actor_id.into());
    md.insert(SESSION_KEY, base.session.into());
    if refusals {
        md.insert(ACKS_KEY, ACKS_REFUSALS.parse().unwrap());
    }
    (tx, client.stream_rollouts(req).await.unwrap().into_inner())
}

/// A learner served on 127.0.0.1:0: its config, output dir, runtime, handle (kept
/// alive by the caller), hub and URL.
pub type Served = (
    RunConfig,
    std::path::PathBuf,
    tokio::runtime::Runtime,
    saver_run::train::LocalLearner,
    Arc<saver_learner::Hub>,
    String,
);

/// A [`Served`] learner: A2C, angle d = 2, sync, one actor.
pub fn one_actor_learner(name: &str) -> Served {
    learner_with(name, |_| {})
}

/// [`one_actor_learner`] with `change` applied to its config.
pub fn learner_with(name: &str, change: impl FnOnce(&mut RunConfig)) -> Served {
    let mut config = RunConfig::paper(&EnvSpec::new(EnvKind::Angle, 2).unwrap(), Algo::A2c, 0);
    config.actors = 1;
    config.steps = 1_000_000;
    change(&mut config);
    let dir = temp_dir(name);
    let rt = tokio::runtime::Runtime::new().unwrap();
    let learner = start_learner(&config, &dir, None, Arc::new(AtomicBool::new(false)), 0).unwrap();
    let hub = learner.hub.clone();
    let url =
        saver_run::services::serve_hub_on_loopback(&rt, hub.clone(), Default::default(), None)
            .unwrap();
    (config, dir, rt, learner, hub, url)
}

#[test]
fn a_stream_that_asks_for_refusals_only_hears_of_nothing_else() {
    // A good rollout, a malformed one (a NaN observation), then the sender closes: the
    // only message on the ack stream is the refusal of the second, and the first did
    // reach the trainer (version 1).
    let (config, dir, rt, _learner, hub, url) = one_actor_learner("refusals");
    let acks: Vec<pb::RolloutAck> = rt.block_on(async {
        let (mut client, base) = register_and_roll(&url, &hub, &config).await;
        let (tx, mut acks) = open_stream(&mut client, &base, true).await;
        let mut bad = base.clone();
        bad.seq = 6;
        bad.obs[0] = f32::NAN;
        tx.send(base).await.unwrap();
        tx.send(bad).await.unwrap();
        let mut got = vec![acks.next().await.unwrap().unwrap()];
        // The actor counts while its stream is open: the good rollout trains first.
        let h = hub.clone();
        let v = tokio::task::spawn_blocking(move || h.wait_weights(1).unwrap().version);
        assert_eq!(v.await.unwrap(), 1);
        drop(tx);
        while let Some(a) = acks.next().await {
            got.push(a.unwrap());
        }
        got
    });
    assert_eq!(acks.len(), 1, "{acks:?}");
    assert_eq!((acks[0].seq, acks[0].accepted), (6, false));
    assert_eq!(Code::from(acks[0].code), Code::InvalidArgument);
    assert_eq!(hub.stats.accepted.load(Ordering::Relaxed), 1);
    hub.close("test over");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_hundred_thousand_hostile_rollouts_are_refused_and_change_nothing() {
    let (config, dir, rt, _learner, hub, url) = one_actor_learner("hostile");

    let (refused, weights_after_one) = rt.block_on(async {
        let (mut client, base) = register_and_roll(&url, &hub, &config).await;
        let (tx, mut acks) = open_stream(&mut client, &base, false).await;
        tx.send(base.clone()).await.unwrap();
        let ack = acks.next().await.unwrap().unwrap();
        assert!(ack.accepted, "{}", ack.error);
        let after_one = hub.wait_weights(1).unwrap();

        let mut expected = Vec::with_capacity(CASES);
        let mut rng = rng_for(7, 0);
        let cases: Vec<pb::Rollout> = (0..CASES)
            .map(|i| {
                let (r, code) = mutate(&base, i, &mut rng);
                expected.push((r.seq, code));
                r
            })
            .collect();
        let sender = tokio::spawn(async move {
            for r in cases {
                tx.send(r).await.unwrap();
            }
        });
        let mut refused = 0usize;
        for (seq, code) in expected {
            let ack = acks.next().await.expect("an ack per rollout").unwrap();
            assert_eq!(ack.seq, seq);
            assert!(!ack.accepted, "seq {seq} was accepted");
            assert_eq!(Code::from(ack.code), code, "seq {seq}: {}", ack.error);
            assert!(!ack.error.is_empty());
            refused += 1;
        }
        sender.await.unwrap();
        (refused, after_one)
    });
    assert_eq!(refused, CASES);

    // Raw garbage at the port (random bytes, an HTTP/1.1 request, a cut-off HTTP/2
    // preface): each connection is dropped, the learner keeps serving.
    let addr = url.trim_start_matches("http://").to_string();
    let mut junk = rng_for(8, 0);
    let payloads: Vec<Vec<u8>> = vec![
        (0..1 << 20).map(|_| junk.random::<u8>()).collect(),
        b"GET / HTTP/1.1\r\nHost: x\r\n\r\n".to_vec(),
        b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n\x00\x00\xff\x01".to_vec(),
    ];
    for p in payloads {
        use std::io::{Read, Write};
        let mut s = std::net::TcpStream::connect(&addr).unwrap();
        s.set_read_timeout(Some(std::time::Duration::from_secs(10)))
            .unwrap();
        let _ = s.write_all(&p);
        let _ = s.shutdown(std::net::Shutdown::Write);
        let mut sink = Vec::new();
        let _ = s.read_to_end(&mut sink);
    }
    let status = rt.block_on(async {
        let mut c = LearnerClient::connect(url.clone()).await.unwrap();
        c.status(pb::StatusRequest {}).await.unwrap().into_inner()
    });
    assert_eq!(status.version, 1);
    assert_eq!(hub.stats.accepted.load(Ordering::Relaxed), 1);
    assert_eq!(hub.stats.rejected.load(Ordering::Relaxed), CASES as u64);
    // Nothing refused reached the trainer: still version 1, the same tensors.
    let now = hub.latest();
    assert_eq!(now.version, 1);
    assert_tensors_in(&now.tensors, &weights_after_one.tensors);
    hub.close("test over");
    std::fs::remove_dir_all(dir).ok();
}

/// A Register whose env name is 1 MiB is refused with a reason that fits in a
/// status (the name cut to 64 characters and "…"); a 1 MiB actor name is cut too, and
/// the registration goes through.
#[test]
fn a_one_mebibyte_name_gets_a_short_refusal() {
    let (config, dir, rt, _learner, hub, url) = one_actor_learner("huge-name");
    let huge = "n".repeat(1 << 20);
    let (refusal, accepted) = rt.block_on(async {
        let mut client = LearnerClient::connect(url.clone())
            .await
            .unwrap()
            .max_encoding_message_size(saver_proto::MAX_MESSAGE_BYTES);
        let mut env = pb::EnvSpec::from(&config.env);
        env.kind = huge.clone();
        let refusal = client
            .register(pb::RegisterRequest {
                name: "huge-env".into(),
                session: SESSION,
                n_envs: 1,
                env: Some(env),
            })
            .await
            .unwrap_err();
        let accepted = client
            .register(pb::RegisterRequest {
                name: huge.clone(),
                session: SESSION,
                n_envs: 1,
                env: None,
            })
            .await;
        (refusal, accepted)
    });
    assert_eq!(refusal.code(), Code::InvalidArgument, "{refusal:?}");
    let m = refusal.message();
    assert!(
        m.len() < 400 && m.contains(&format!("{}…", &huge[..64])),
        "{m}"
    );
    assert!(accepted.is_ok(), "{accepted:?}");
    hub.close("test over");
    std::fs::remove_dir_all(dir).ok();
}
