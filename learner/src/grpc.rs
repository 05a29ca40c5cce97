//! The `Learner` gRPC service over a [`Hub`]: the network edge of the same hub the
//! embedded run uses. Handlers only move bytes: blocking hub calls go to tokio's
//! blocking pool, updates stay on the trainer thread.

use crate::Hub;
use bytes::Bytes;
use saver_core::env::EnvSpec;
use saver_core::link::{LinkError, PolicyWeights, Registration};
use saver_core::rollout::Rollout;
use saver_core::CoreError;
use saver_proto::pb::learner_server::{Learner, LearnerServer};
use saver_proto::pb::{self, RolloutAck};
use saver_proto::weights_dir::WeightsDir;
use saver_proto::{Access, CheckToken};
use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::StreamExt;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status, Streaming};

/// One published version, encoded once and shared by every reader.
#[derive(Clone, Debug)]
pub struct EncodedWeights {
    /// Version.
    pub version: u64,
    /// safetensors bytes of the agent's tensors.
    pub bytes: Bytes,
    /// Its file in the weights directory, when the learner writes one.
    pub file: Option<String>,
}

/// Encodes weights as safetensors with `about` (what they are:
/// [`saver_core::link::weights_metadata`]) and their version in the metadata.
pub fn encode_weights(
    w: &PolicyWeights,
    about: &HashMap<String, String>,
) -> Result<EncodedWeights, saver_proto::CodecError> {
    let mut meta = about.clone();
    meta.insert("version".to_string(), w.version.to_string());
    Ok(EncodedWeights {
        version: w.version,
        bytes: Bytes::from(saver_proto::encode(&w.tensors, &meta)?),
        file: None,
    })
}

/// Encodes weights and, with a weights directory, writes them there too.
fn publishable(
    w: &PolicyWeights,
    about: &HashMap<String, String>,
    dir: &mut Option<WeightsDir>,
) -> Option<EncodedWeights> {
    let mut e = match encode_weights(w, about) {
        Ok(e) => e,
        Err(e) => {
            tracing::error!("encoding weights v{}: {e}", w.version);
            return None;
        }
    };
    if let Some(d) = dir {
        match d.write(e.version, &e.bytes) {
            Ok(name) => e.file = Some(name),
            // Readers then get the bytes over the stream, as off-host ones do.
            Err(err) => tracing::warn!(
                "writing weights v{} to {}: {err}",
                e.version,
                d.path().display()
            ),
        }
    }
    Some(e)
}

/// The Learner service.
#[derive(Clone)]
pub struct LearnerService {
    /// The hub it fronts.
    hub: Arc<Hub>,
    /// The newest encoded weights (`None` after the hub closed and the bridge ended).
    weights: watch::Receiver<EncodedWeights>,
    /// Extra status the trainer reports (steps, mean episode length, finished).
    status: watch::Receiver<TrainerStatus>,
    /// The token every call must carry and the TLS identity (none by default).
    access: Access,
    /// The weights directory (path, identity) that same-host actors may read.
    weights_dir: Option<(String, String)>,
}

/// What the trainer side tells the service for `Status`.
#[derive(Clone, Debug, Default)]
pub struct TrainerStatus {
    /// Env steps trained on.
    pub steps: u64,
    /// Mean of the last 100 episodes.
    pub mean_ep_len_100: Option<f64>,
    /// Rollouts dropped as stale.
    pub stale_dropped: u64,
    /// Updates skipped for a non-finite loss or gradient.
    pub skipped_updates: u64,
    /// Training is over.
    pub finished: bool,
}

use saver_proto::{ACKS_KEY, ACKS_REFUSALS, ACTOR_ID_KEY, SESSION_KEY};

fn actor_metadata(m: &tonic::metadata::MetadataMap) -> Option<(u32, u64)> {
    let get = |k: &str| m.get(k)?.to_str().ok()?.parse::<u64>().ok();
    Some((u32::try_from(get(ACTOR_ID_KEY)?).ok()?, get(SESSION_KEY)?))
}

/// A stream's claim on a registration: made by [`Hub::attach`] (a quick lock, so on
/// the runtime like [`Hub::try_submit`]), released when the stream's task ends,
/// however it ends.
struct Leave {
    hub: Arc<Hub>,
    id: u32,
    session: u64,
}

impl Leave {
    fn attach(hub: &Arc<Hub>, (id, session): (u32, u64)) -> Result<Self, LinkError> {
        hub.attach(id, session)?;
        Ok(Self {
            hub: hub.clone(),
            id,
            session,
        })
    }
}

impl Drop for Leave {
    fn drop(&mut self) {
        self.hub.unregister(self.id, self.session);
    }
}

fn link_status(e: LinkError) -> Status {
    let cut = |why: String| saver_proto::clip_chars(&why, saver_proto::MAX_STATUS_CHARS);
    match e {
        LinkError::Closed(why) | LinkError::Waiting(why) => Status::unavailable(cut(why)),
        LinkError::Finished(why) => Status::out_of_range(cut(why)),
        LinkError::Rejected(why) => Status::invalid_argument(cut(why)),
        LinkError::Mismatch(why) => Status::failed_precondition(cut(why)),
        LinkError::TooLarge(why) => Status::resource_exhausted(cut(why)),
    }
}

/// Queues a rollout without leaving the runtime; only a full queue (the trainer is
/// behind) waits on the blocking pool.
async fn submit(hub: &Arc<Hub>, r: Rollout) -> Result<(), LinkError> {
    match hub.try_submit(r) {
        Ok(Some(back)) => {
            let h = hub.clone();
            blocking(move || h.submit(back))
                .await
                .unwrap_or_else(|s| Err(LinkError::Closed(s.message().to_string())))
        }
        Ok(None) => Ok(()),
        Err(e) => Err(e),
    }
}

/// The status that ends a rollout stream whose next message could not be read:
/// RESOURCE_EXHAUSTED over the size limit, INVALID_ARGUMENT when it does not decode;
/// `None` when the client went away (nothing to answer).
fn inbound_error(s: &Status) -> Option<Status> {
    let m = s.message();
    if s.code() == tonic::Code::ResourceExhausted {
        Some(s.clone())
    } else if s.code() == tonic::Code::OutOfRange {
        // tonic's own limit (the server-wide MAX_MESSAGE_BYTES).
        Some(Status::resource_exhausted(format!(
            "rollout message over the size limit: {m}"
        )))
    } else if s.code() == tonic::Code::Internal && m.contains("decode") {
        Some(Status::invalid_argument(format!(
            "rollout message does not decode as saver.v1.Rollout: {m}"
        )))
    } else {
        None
    }
}

async fn blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Result<T, Status> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| Status::internal(format!("learner task failed: {e}")))
}

impl LearnerService {
    /// A service for `hub`. Starts the thread that encodes each new version once and
    /// publishes it to every watcher (and, with `weights_dir`, writes it there for
    /// same-host actors); returns the status sender the trainer side feeds.
    pub fn new(
        hub: Arc<Hub>,
        weights_dir: Option<WeightsDir>,
    ) -> (Self, watch::Sender<TrainerStatus>) {
        let mut dir = weights_dir;
        let shared = dir
            .as_ref()
            .map(|d| (d.path().display().to_string(), d.id().to_string()));
        let about = saver_core::link::weights_metadata(hub.config());
        let first = publishable(&hub.latest(), &about, &mut dir).unwrap_or(EncodedWeights {
            version: 0,
            bytes: Bytes::new(),
            file: None,
        });
        let (tx, rx) = watch::channel(first);
        let bridge_hub = hub.clone();
        std::thread::Builder::new()
            .name("saver-weights-bridge".into())
            .spawn(move || {
                let mut next = 1;
                while let Ok(w) = bridge_hub.wait_weights(next) {
                    let start = std::time::Instant::now();
                    let published = publishable(&w, &about, &mut dir);
                    ::metrics::histogram!("saver_weights_broadcast_seconds")
                        .record(start.elapsed().as_secs_f64());
                    if let Some(e) = published {
                        if tx.send(e).is_err() {
                            break;
                        }
                    }
                    next = w.version + 1;
                }
                // Publish the very last version too (the hub may close right after it).
                // This thread is the only sender, so no one else can have sent it.
                let last = bridge_hub.latest();
                if last.version > tx.borrow().version {
                    if let Some(e) = publishable(&last, &about, &mut dir) {
                        let _ = tx.send(e);
                    }
                }
                // `dir` drops here and removes its files: a reader that misses the
                // last one asks GetWeights, which still serves it.
            })
            .expect("spawning a thread");
        let (status_tx, status_rx) = watch::channel(TrainerStatus::default());
        (
            Self {
                hub,
                weights: rx,
                status: status_rx,
                access: Access::default(),
                weights_dir: shared,
            },
            status_tx,
        )
    }

    /// Requires `access`'s token on every call and serves TLS when it has a
    /// certificate.
    pub fn with_access(mut self, access: Access) -> Self {
        self.access = access;
        self
    }

    /// The tonic server for this service: message size limits set, token checked.
    pub fn into_server(self) -> InterceptedService<LearnerServer<Self>, CheckToken> {
        let check = self.access.check.clone();
        learner_server(self, check)
    }

    fn weights_reply(w: &EncodedWeights) -> pb::Weights {
        pb::Weights {
            version: w.version,
            safetensors: w.bytes.clone(),
            file: String::new(),
        }
    }

    /// The reply to a watcher: the file's name when it asked for one and there is one.
    fn watch_reply(w: &EncodedWeights, by_file: bool) -> pb::Weights {
        match &w.file {
            Some(name) if by_file => pb::Weights {
                version: w.version,
                safetensors: Bytes::new(),
                file: name.clone(),
            },
            _ => Self::weights_reply(w),
        }
    }
}

#[tonic::async_trait]
impl Learner for LearnerService {
    async fn register(
        &self,
        req: Request<pb::RegisterRequest>,
    ) -> Result<Response<pb::RegisterReply>, Status> {
        let r = req.into_inner();
        if let Some(env) = &r.env {
            check_actor_env(env, &self.hub.config().env)?;
        }
        let hub = self.hub.clone();
        let reg = Registration {
            name: saver_proto::clip_text(&r.name),
            session: r.session,
            n_envs: r.n_envs,
        };
        let a = blocking(move || hub.register_remote(&reg))
            .await?
            .map_err(link_status)?;
        let (weights_dir, weights_dir_id) = self.weights_dir.clone().unwrap_or_default();
        Ok(Response::new(pb::RegisterReply {
            actor_id: a.actor_id,
            settings: Some((&a.settings).into()),
            weights_dir,
            weights_dir_id,
            session: a.session,
        }))
    }

    type StreamRolloutsStream = ReceiverStream<Result<RolloutAck, Status>>;

    async fn stream_rollouts(
        &self,
        req: Request<Streaming<pb::Rollout>>,
    ) -> Result<Response<Self::StreamRolloutsStream>, Status> {
        // The actor names its registration in metadata: the stream claims it (the
        // actor counts in rounds from now on) and leaves the rounds when it closes. A
        // client that names none claims it with its first rollout.
        let owner = actor_metadata(req.metadata());
        let mut leave = owner
            .map(|o| Leave::attach(&self.hub, o))
            .transpose()
            .map_err(link_status)?;
        let refusals_only =
            req.metadata().get(ACKS_KEY).and_then(|v| v.to_str().ok()) == Some(ACKS_REFUSALS);
        let mut inbound = req.into_inner();
        let (tx, rx) = mpsc::channel(32);
        let hub = self.hub.clone();
        tokio::spawn(async move {
            while let Some(msg) = inbound.next().await {
                let owner = leave.as_ref().map(|l| (l.id, l.session));
                let msg = match msg {
                    Ok(m) => m,
                    Err(status) => {
                        // A message that is too large or undecodable ends the stream
                        // with the status that says so (counted and logged); a client
                        // that went away just ends it.
                        if let Some(s) = inbound_error(&status) {
                            let code = match s.code() {
                                tonic::Code::ResourceExhausted => "resource_exhausted",
                                _ => "invalid_argument",
                            };
                            hub.refused(owner.map(|o| o.0), code, &s);
                            let _ = tx.send(Err(s)).await;
                        } else {
                            tracing::debug!("rollout stream ended: {status}");
                        }
                        break;
                    }
                };
                let seq = msg.seq;
                // Refusals before the hub's checks are counted here; the hub counts its own.
                let outcome = match (owner, Rollout::try_from(msg)) {
                    (_, Err(e)) => Err(match e {
                        CoreError::TooLarge(why) => LinkError::TooLarge(why),
                        e => LinkError::Rejected(e.to_string()),
                    }),
                    (Some((id, session)), Ok(r)) if (r.actor_id, r.session) != (id, session) => {
                        Err(LinkError::Mismatch(format!(
                            "this stream belongs to actor {id}; a rollout of actor {} with \
                             another session is refused",
                            r.actor_id
                        )))
                    }
                    (Some(_), Ok(r)) => Ok(r),
                    // The first rollout of an unnamed stream claims its registration.
                    (None, Ok(r)) => Leave::attach(&hub, (r.actor_id, r.session)).map(|l| {
                        leave = Some(l);
                        r
                    }),
                };
                let outcome = match outcome {
                    Ok(r) => submit(&hub, r).await,
                    Err(e) => {
                        if !matches!(e, LinkError::Closed(_) | LinkError::Finished(_)) {
                            hub.refused(owner.map(|o| o.0), crate::hub::reason(&e), &e);
                        }
                        Err(e)
                    }
                };
                let reply = match outcome {
                    Ok(()) if refusals_only => continue,
                    Ok(()) => RolloutAck {
                        seq,
                        accepted: true,
                        error: String::new(),
                        code: 0,
                    },
                    Err(e @ (LinkError::Closed(_) | LinkError::Finished(_))) => {
                        let _ = tx.send(Err(link_status(e))).await;
                        break;
                    }
                    Err(e) => {
                        let status = link_status(e);
                        RolloutAck {
                            seq,
                            accepted: false,
                            error: status.message().to_string(),
                            code: status.code() as i32,
                        }
                    }
                };
                if tx.send(Ok(reply)).await.is_err() {
                    break;
                }
            }
            // The claim ends with the stream.
            drop(leave);
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    type WatchWeightsStream = ReceiverStream<Result<pb::Weights, Status>>;

    async fn watch_weights(
        &self,
        req: Request<pb::WatchRequest>,
    ) -> Result<Response<Self::WatchWeightsStream>, Status> {
        let by_file = req.into_inner().by_file;
        let mut rx = self.weights.clone();
        let (tx, out) = mpsc::channel(1);
        let hub = self.hub.clone();
        // A new watcher starts from the hub's newest version: on a loaded machine the
        // bridge thread can be several versions behind it, so wait for the bridge.
        let newest = hub.latest().version;
        tokio::spawn(async move {
            // An error means the bridge has ended; the loop then sends its last
            // version and says why the run closed.
            let _ = rx.wait_for(|w| w.version >= newest).await;
            loop {
                // The newest version only: a slow reader skips what it missed.
                let reply = Self::watch_reply(&rx.borrow_and_update(), by_file);
                if tx.send(Ok(reply)).await.is_err() {
                    break;
                }
                if rx.changed().await.is_err() {
                    // The run ended: say how (finished, or the learner is stopping).
                    let why = hub
                        .closed_reason()
                        .unwrap_or_else(|| LinkError::Closed("the learner stopped".into()));
                    let _ = tx.send(Err(link_status(why))).await;
                    break;
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(out)))
    }

    async fn get_weights(
        &self,
        req: Request<pb::WeightsRequest>,
    ) -> Result<Response<pb::Weights>, Status> {
        let min = req.into_inner().min_version;
        let mut rx = self.weights.clone();
        loop {
            {
                let w = rx.borrow_and_update();
                if w.version >= min {
                    return Ok(Response::new(Self::weights_reply(&w)));
                }
            }
            if rx.changed().await.is_err() {
                let w = rx.borrow();
                return Err(Status::failed_precondition(format!(
                    "training ended at version {}; version {min} will not exist",
                    w.version
                )));
            }
        }
    }

    async fn status(
        &self,
        _req: Request<pb::StatusRequest>,
    ) -> Result<Response<pb::StatusReply>, Status> {
        let c = self.hub.config();
        let s = self.status.borrow().clone();
        Ok(Response::new(pb::StatusReply {
            version: self.weights.borrow().version,
            steps: s.steps,
            actors: self.hub.actors().len() as u32,
            pending: self.hub.pending() as u32,
            skipped_updates: s.skipped_updates,
            mode: c.mode.name().to_string(),
            env: c.env.to_string(),
            algo: c.algo.name().to_string(),
            accepted: self.hub.stats.accepted.load(Ordering::Relaxed),
            rejected: self.hub.stats.rejected.load(Ordering::Relaxed),
            stale_dropped: s.stale_dropped,
            mean_ep_len_100: s.mean_ep_len_100.unwrap_or(f64::NAN),
            finished: s.finished,
            ..Default::default()
        }))
    }
}

/// The tonic server of a Learner implementation (the training one, or the one that
/// answers while the learner waits): message size limits set, `check`'s token checked.
pub fn learner_server<S: Learner>(
    service: S,
    check: CheckToken,
) -> InterceptedService<LearnerServer<S>, CheckToken> {
    let server = LearnerServer::new(service)
        .max_decoding_message_size(saver_proto::MAX_MESSAGE_BYTES)
        .max_encoding_message_size(saver_proto::MAX_MESSAGE_BYTES);
    InterceptedService::new(server, check)
}

/// Serves the Learner service (and grpc.health.v1) on `listener` until `shutdown`.
pub async fn serve(
    service: LearnerService,
    listener: tokio::net::TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send,
) -> Result<(), tonic::transport::Error> {
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<LearnerServer<LearnerService>>().await;
    let limit = crate::size_limit::RolloutSizeLimit::new(service.hub.clone());
    let incoming = service.access.incoming(listener);
    service
        .access
        .server()?
        .layer(limit)
        .add_service(health_service)
        .add_service(service.into_server())
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await
}

/// Refuses an actor whose declared env is not the run's, saying what differs. A
/// success rule only one side declares is no difference (the run's, if any, is the
/// one the learner checks episodes by); two that differ are.
fn check_actor_env(env: &pb::EnvSpec, run: &EnvSpec) -> Result<(), Status> {
    let theirs = EnvSpec::try_from(env).map_err(|e| {
        Status::invalid_argument(format!("the env this actor declares is not valid: {e}"))
    })?;
    if theirs.dynamics() == run.dynamics() {
        return match (theirs.success_rule(), run.success_rule()) {
            (Some(a), Some(b)) if a != b => Err(Status::invalid_argument(format!(
                "this actor's env {theirs} is the run's, but its success rule {a:?} is not \
                 the run's {b:?}"
            ))),
            _ => Ok(()),
        };
    }
    let (a, b) = (theirs.layout(), run.layout());
    let why = if theirs.name() != run.name() {
        format!(
            "its name is {:?}, the run's {:?}",
            theirs.name(),
            run.name()
        )
    } else if a != b {
        format!("its layout is {a:?}, the run's {b:?}")
    } else {
        let (a, b) = (theirs.bounds(), run.bounds());
        match (0..a.obs_low.len())
            .find(|&k| a.obs_low[k] != b.obs_low[k] || a.obs_high[k] != b.obs_high[k])
        {
            Some(k) => format!(
                "observation entry {k} has bounds [{}, {}], the run's [{}, {}]",
                a.obs_low[k], a.obs_high[k], b.obs_low[k], b.obs_high[k]
            ),
            None => format!(
                "its max_change is {}, the run's {}",
                a.max_change, b.max_change
            ),
        }
    };
    Err(Status::invalid_argument(format!(
        "this actor's env {theirs} is not the run's env {run}: {why}"
    )))
}
