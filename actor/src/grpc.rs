//! [`LearnerLink`] over gRPC: the actor's side of saver.proto. The actor stays a plain
//! blocking loop; a small tokio runtime inside the link drives the streams.

use saver_core::link::{
    ActorSettings, Assignment, LearnerLink, LinkError, PolicyWeights, Registration,
};
use saver_core::rollout::Rollout;
use saver_proto::pb;
use saver_proto::pb::learner_client::LearnerClient;
use saver_proto::weights_dir::{is_version_file, shares};
use saver_proto::{AddToken, ClientAccess};
use saver_proto::{ACKS_KEY, ACKS_REFUSALS, ACTOR_ID_KEY, SESSION_KEY};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, watch};
use tokio_stream::StreamExt;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

/// The generated Learner client with the token interceptor.
type Client = LearnerClient<InterceptedService<Channel, AddToken>>;

/// A connection to a learner.
pub struct GrpcLink {
    /// Drives the streams (one worker thread).
    rt: tokio::runtime::Runtime,
    /// The generated client (adds the token to every call).
    client: Client,
    /// Rollouts into the open StreamRollouts call.
    rollouts: Option<mpsc::Sender<pb::Rollout>>,
    /// Newest weights from WatchWeights, decoded.
    weights: Option<watch::Receiver<Option<Arc<PolicyWeights>>>>,
    /// Set when a stream ends: the error the next call fails with.
    closed: watch::Receiver<Option<LinkError>>,
    /// Its sender, handed to the stream tasks.
    closed_tx: watch::Sender<Option<LinkError>>,
    /// Read weights from the learner's weights directory when it is on this machine.
    shared_files: bool,
    /// Versions read from the learner's files (the rest came over the stream).
    from_files: Arc<AtomicU64>,
}

fn status_error(s: tonic::Status) -> LinkError {
    match s.code() {
        tonic::Code::InvalidArgument | tonic::Code::Unauthenticated => {
            LinkError::Rejected(s.message().to_string())
        }
        tonic::Code::FailedPrecondition => LinkError::Mismatch(s.message().to_string()),
        tonic::Code::ResourceExhausted => LinkError::TooLarge(s.message().to_string()),
        tonic::Code::OutOfRange => LinkError::Finished(s.message().to_string()),
        tonic::Code::Unavailable if s.metadata().contains_key(saver_proto::WAITING_KEY) => {
            LinkError::Waiting(s.message().to_string())
        }
        _ => LinkError::Closed(format!("{}: {}", s.code(), s.message())),
    }
}

/// Decodes a Weights message.
pub fn decode_weights(w: &pb::Weights) -> Result<PolicyWeights, LinkError> {
    let (tensors, _) = saver_proto::decode(&w.safetensors)
        .map_err(|e| LinkError::Rejected(format!("weights v{}: {e}", w.version)))?;
    Ok(PolicyWeights {
        version: w.version,
        tensors,
    })
}

/// Reads the file a Weights message names in the learner's weights directory; the
/// file must carry the announced version.
fn read_weights_file(dir: &Path, w: &pb::Weights) -> Result<PolicyWeights, String> {
    if !is_version_file(&w.file) {
        return Err(format!("{:?} is not a weights file name", w.file));
    }
    let path = dir.join(&w.file);
    let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let (tensors, meta) =
        saver_proto::decode(&bytes).map_err(|e| format!("{}: {e}", path.display()))?;
    let version = meta.get("version").and_then(|v| v.parse::<u64>().ok());
    if version != Some(w.version) {
        return Err(format!(
            "{} holds version {version:?}, not {}",
            path.display(),
            w.version
        ));
    }
    Ok(PolicyWeights {
        version: w.version,
        tensors,
    })
}

/// The weights a WatchWeights message stands for: read from the file it names in
/// `files` (counted in `from_files`), or decoded from its bytes; a named file that is
/// gone (this reader fell behind) or unreadable is asked for with GetWeights.
async fn resolve(
    w: pb::Weights,
    files: Option<&Path>,
    client: &mut Client,
    from_files: &AtomicU64,
) -> Result<PolicyWeights, LinkError> {
    let Some(dir) = files.filter(|_| !w.file.is_empty()) else {
        return decode_weights(&w);
    };
    match read_weights_file(dir, &w) {
        Ok(p) => {
            from_files.fetch_add(1, Ordering::Relaxed);
            Ok(p)
        }
        Err(e) => {
            tracing::debug!("weights file: {e}; asking for the bytes");
            let req = pb::WeightsRequest {
                min_version: w.version,
            };
            let bytes = client.get_weights(req).await.map_err(status_error)?;
            decode_weights(&bytes.into_inner())
        }
    }
}

impl GrpcLink {
    /// Connects to `url` (e.g. `http://127.0.0.1:50051`) without a token.
    pub fn connect(url: &str) -> Result<Self, LinkError> {
        Self::connect_with(url, &ClientAccess::default())
    }

    /// Connects to `url` with `access`'s token (on every call) and TLS settings.
    pub fn connect_with(url: &str, access: &ClientAccess) -> Result<Self, LinkError> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| LinkError::Closed(format!("starting the link runtime: {e}")))?;
        let endpoint = access
            .endpoint(url)
            .map_err(|e| LinkError::Rejected(format!("learner address {url:?}: {e}")))?;
        let channel = rt
            .block_on(endpoint.connect())
            .map_err(|e| LinkError::Closed(format!("connecting to {url}: {e}")))?;
        let client = LearnerClient::with_interceptor(channel, access.token.clone())
            .max_decoding_message_size(saver_proto::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(saver_proto::MAX_MESSAGE_BYTES);
        let (closed_tx, closed) = watch::channel(None);
        Ok(Self {
            rt,
            client,
            rollouts: None,
            weights: None,
            closed,
            closed_tx,
            shared_files: true,
            from_files: Arc::default(),
        })
    }

    /// How many versions this link read from the learner's files.
    pub fn weights_read_from_files(&self) -> u64 {
        self.from_files.load(Ordering::Relaxed)
    }

    /// Whether to read the weights from the learner's files when they are reachable
    /// (on by default; off: every version comes over the stream).
    pub fn with_shared_files(mut self, on: bool) -> Self {
        self.shared_files = on;
        self
    }

    fn closed_reason(&self) -> Option<LinkError> {
        self.closed.borrow().clone()
    }

    /// The newest weights once they reach `min_version`, or when `wait` (if any) has
    /// passed, whichever comes first.
    fn wait_weights(
        &mut self,
        min_version: u64,
        wait: Option<Duration>,
    ) -> Result<Arc<PolicyWeights>, LinkError> {
        let mut rx = self
            .weights
            .clone()
            .ok_or_else(|| LinkError::Rejected("register first".into()))?;
        let mut closed = self.closed.clone();
        let deadline = wait.map(|w| tokio::time::Instant::now() + w);
        self.rt.block_on(async move {
            loop {
                let newest = rx.borrow_and_update().clone();
                if let Some(w) = &newest {
                    let late = deadline.is_some_and(|d| tokio::time::Instant::now() >= d);
                    if w.version >= min_version || late {
                        return Ok(w.clone());
                    }
                }
                if let Some(e) = closed.borrow().clone() {
                    return Err(e);
                }
                let until = async {
                    match deadline {
                        // With no weights at all yet there is nothing to fall back on.
                        Some(d) if newest.is_some() => tokio::time::sleep_until(d).await,
                        _ => std::future::pending().await,
                    }
                };
                tokio::select! {
                    r = rx.changed() => if r.is_err() {
                        return Err(LinkError::Closed("weights stream ended".into()));
                    },
                    _ = closed.changed() => {}
                    _ = until => {}
                }
            }
        })
    }

    /// Opens the rollout and weight streams (after registration); with `files`, the
    /// weights come as names of files in that directory.
    fn open_streams(
        &mut self,
        actor_id: u32,
        session: u64,
        files: Option<PathBuf>,
    ) -> Result<(), LinkError> {
        let mut client = self.client.clone();
        let (tx, rx) = mpsc::channel::<pb::Rollout>(4);
        let closed = self.closed_tx.clone();
        let mut req = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(rx));
        let md = req.metadata_mut();
        md.insert(ACTOR_ID_KEY, actor_id.into());
        md.insert(SESSION_KEY, session.into());
        // Acceptances would only wake this process; refusals are logged.
        md.insert(
            ACKS_KEY,
            tonic::metadata::MetadataValue::from_static(ACKS_REFUSALS),
        );
        let acks = self
            .rt
            .block_on(client.stream_rollouts(req))
            .map_err(status_error)?
            .into_inner();
        self.rt.spawn(async move {
            let mut acks = acks;
            while let Some(a) = acks.next().await {
                match a {
                    // The learner no longer knows this registration (it expired, the
                    // learner restarted, or the rollout looked like a replay): the
                    // link is lost, and the actor registers again.
                    Ok(a) if !a.accepted && a.code == tonic::Code::FailedPrecondition as i32 => {
                        let _ = closed.send(Some(LinkError::Closed(format!(
                            "rollout {} refused: {}; registering again",
                            a.seq, a.error
                        ))));
                        return;
                    }
                    Ok(a) if !a.accepted => {
                        tracing::warn!("rollout {} rejected: {}", a.seq, a.error)
                    }
                    Ok(_) => {}
                    Err(s) if s.code() == tonic::Code::FailedPrecondition => {
                        let _ = closed.send(Some(LinkError::Closed(format!(
                            "the learner ended the rollout stream: {}; registering again",
                            s.message()
                        ))));
                        return;
                    }
                    Err(s) => {
                        let _ = closed.send(Some(status_error(s)));
                        return;
                    }
                }
            }
            let _ = closed.send(Some(LinkError::Closed(
                "the learner closed the rollout stream".into(),
            )));
        });
        let stream = self
            .rt
            .block_on(client.watch_weights(pb::WatchRequest {
                by_file: files.is_some(),
            }))
            .map_err(status_error)?
            .into_inner();
        let (wtx, wrx) = watch::channel(None);
        let closed = self.closed_tx.clone();
        let from_files = self.from_files.clone();
        self.rt.spawn(async move {
            let mut stream = stream;
            while let Some(w) = stream.next().await {
                let got = match w {
                    Ok(w) => resolve(w, files.as_deref(), &mut client, &from_files).await,
                    Err(s) => Err(status_error(s)),
                };
                match got {
                    Ok(w) => {
                        if wtx.send(Some(Arc::new(w))).is_err() {
                            return;
                        }
                    }
                    Err(e) => {
                        let _ = closed.send(Some(e));
                        return;
                    }
                }
            }
            let _ = closed.send(Some(LinkError::Closed(
                "the learner ended the weights stream".into(),
            )));
        });
        self.rollouts = Some(tx);
        self.weights = Some(wrx);
        Ok(())
    }
}

impl LearnerLink for GrpcLink {
    fn register(&mut self, reg: &Registration) -> Result<Assignment, LinkError> {
        let mut client = self.client.clone();
        let reply = self
            .rt
            .block_on(client.register(pb::RegisterRequest {
                name: reg.name.clone(),
                session: reg.session,
                n_envs: reg.n_envs,
                env: None,
            }))
            .map_err(status_error)?
            .into_inner();
        let settings = reply
            .settings
            .as_ref()
            .ok_or_else(|| LinkError::Rejected("the learner's reply has no run settings".into()))
            .and_then(|s| {
                ActorSettings::try_from(s).map_err(|e| LinkError::Rejected(e.to_string()))
            })?;
        let files = (self.shared_files && !reply.weights_dir.is_empty())
            .then(|| PathBuf::from(&reply.weights_dir))
            .filter(|dir| shares(dir, &reply.weights_dir_id));
        if let Some(dir) = &files {
            tracing::info!(
                "reading weights from the learner's files in {}",
                dir.display()
            );
        }
        self.open_streams(reply.actor_id, reply.session, files)
            .map_err(|e| match e {
                // The registration expired before the stream opened: try again.
                LinkError::Mismatch(why) => LinkError::Closed(why),
                e => e,
            })?;
        Ok(Assignment {
            actor_id: reply.actor_id,
            session: reply.session,
            settings,
        })
    }

    fn weights(&mut self, min_version: u64) -> Result<Arc<PolicyWeights>, LinkError> {
        self.wait_weights(min_version, None)
    }

    fn weights_within(
        &mut self,
        min_version: u64,
        wait: Duration,
    ) -> Result<Arc<PolicyWeights>, LinkError> {
        self.wait_weights(min_version, Some(wait))
    }

    fn push(&mut self, rollout: Rollout) -> Result<(), LinkError> {
        if let Some(e) = self.closed_reason() {
            return Err(e);
        }
        let tx = self
            .rollouts
            .clone()
            .ok_or_else(|| LinkError::Rejected("register first".into()))?;
        let msg = pb::Rollout::from(&rollout);
        self.rt
            .block_on(tx.send(msg))
            .map_err(|_| LinkError::Closed("the rollout stream is closed".into()))
    }
}
