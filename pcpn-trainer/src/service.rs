//! The `PcpnStore` gRPC service: lists the store, streams a PCPN file in chunks with
//! its hashes, and pretrains one on request (once per env spec and pretraining
//! settings, never silently again).

use crate::samples::SampleHub;
use crate::store::{check_pcpn_bytes, PcpnStore};
use crate::train::pretrain_pcpn;
use bytes::Bytes;
use saver_core::config::PretrainConfig;
use saver_core::env::EnvSpec;
use saver_proto::pb::pcpn_store_server::{PcpnStore as PcpnStoreApi, PcpnStoreServer};
use saver_proto::pb::{self, PcpnChunk};
use saver_proto::{Access, CheckToken, ClientAccess};
use std::path::PathBuf;
use std::sync::Arc;
use tokio::sync::Mutex;
use tokio_stream::wrappers::ReceiverStream;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status};

/// Bytes per streamed chunk.
pub const CHUNK_BYTES: usize = 1 << 20;

/// The service over a store folder.
#[derive(Clone)]
pub struct PcpnService {
    /// The store.
    store: PcpnStore,
    /// Its folder (for listing).
    dir: PathBuf,
    /// One pretraining at a time (a second request for the same spec then finds the file).
    pretraining: Arc<Mutex<()>>,
    /// The token every call must carry and the TLS identity (none by default).
    access: Access,
    /// Custom envs' samples, streamed by their actors.
    samples: Arc<SampleHub>,
    /// How far the pretraining in progress is.
    tracker: crate::progress::Tracker,
}

/// The info message of a PCPN file's bytes (checked as a whole: spec, settings, hash).
pub fn info_of(bytes: &[u8]) -> Result<pb::PcpnInfo, Status> {
    let spec = crate::store::spec_of(bytes)
        .ok_or_else(|| Status::data_loss("a stored file has no env_spec"))?;
    // Checked (spec, settings, hash) without building the network.
    let (_, info) = check_pcpn_bytes(bytes, std::path::Path::new("stored"), &spec)
        .map_err(|e| Status::data_loss(e.to_string()))?;
    Ok(pb::PcpnInfo {
        env: Some((&spec).into()),
        settings: Some((&info.pretrain).into()),
        weights_sha256: info.weights_sha256,
        file_sha256: saver_proto::sha256_hex(bytes),
        size: bytes.len() as u64,
        metadata: info.meta,
    })
}

/// The env spec and pretraining settings a request names (both required).
fn wanted(
    env: Option<&pb::EnvSpec>,
    settings: Option<&pb::PretrainSettings>,
) -> Result<(EnvSpec, PretrainConfig), Status> {
    let invalid = |e: saver_core::CoreError| Status::invalid_argument(e.to_string());
    let env = env.ok_or_else(|| Status::invalid_argument("env is required"))?;
    let settings = settings
        .ok_or_else(|| Status::invalid_argument("settings (PretrainSettings) are required"))?;
    Ok((
        EnvSpec::try_from(env).map_err(invalid)?.dynamics(),
        PretrainConfig::try_from(settings).map_err(invalid)?,
    ))
}

impl PcpnService {
    /// A service over the store in `dir`.
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        let dir = dir.into();
        Self {
            store: PcpnStore::new(&dir),
            dir,
            pretraining: Arc::new(Mutex::new(())),
            access: Access::default(),
            samples: Arc::default(),
            tracker: Default::default(),
        }
    }

    /// How far the pretraining in progress is (None when none is).
    pub fn progress(&self) -> Option<pb::PretrainProgress> {
        self.tracker.progress(&self.samples)
    }

    /// Ends a pretraining that waits for samples, now and from now on (the store
    /// stops).
    pub fn cancel(&self) {
        self.samples.cancel();
    }

    /// A pretraining from streamed samples fails when none arrive for `deadline`.
    pub fn with_sample_deadline(mut self, deadline: std::time::Duration) -> Self {
        self.samples = Arc::new(SampleHub::with_deadline(deadline));
        self
    }

    /// The tonic server with the message size limits set.
    pub fn into_server(self) -> InterceptedService<PcpnStoreServer<Self>, CheckToken> {
        let check = self.access.check.clone();
        let server = PcpnStoreServer::new(self)
            .max_decoding_message_size(saver_proto::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(saver_proto::MAX_MESSAGE_BYTES);
        InterceptedService::new(server, check)
    }

    /// Requires `access`'s token on every call and serves TLS when it has a
    /// certificate.
    pub fn with_access(mut self, access: Access) -> Self {
        self.access = access;
        self
    }

    /// The stored file for `spec` and `p` with its info, if present; a file there that
    /// holds another PCPN (renamed, or of other settings) is refused.
    async fn stored(
        &self,
        spec: &EnvSpec,
        p: &PretrainConfig,
    ) -> Result<Option<(Vec<u8>, pb::PcpnInfo)>, Status> {
        let path = self.store.path_for(spec, p);
        let bytes = match tokio::fs::read(&path).await {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Status::internal(format!("reading the store: {e}"))),
        };
        let info = info_of(&bytes)?;
        let found = info.env.as_ref().and_then(|e| EnvSpec::try_from(e).ok());
        let settings = info
            .settings
            .as_ref()
            .and_then(|s| PretrainConfig::try_from(s).ok());
        if found.as_ref() != Some(spec) || settings != Some(*p) {
            return Err(Status::failed_precondition(format!(
                "the stored file for {spec} with {p:?} holds a PCPN for {} pretrained with {:?}",
                found.map_or_else(|| "an unknown env".into(), |s| s.to_string()),
                settings
            )));
        }
        Ok(Some((bytes, info)))
    }
}

#[tonic::async_trait]
impl PcpnStoreApi for PcpnService {
    async fn list(
        &self,
        _req: Request<pb::ListRequest>,
    ) -> Result<Response<pb::ListReply>, Status> {
        let mut pcpns = Vec::new();
        let mut entries = match tokio::fs::read_dir(&self.dir).await {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok(Response::new(pb::ListReply { pcpns }))
            }
            Err(e) => return Err(Status::internal(format!("listing the store: {e}"))),
        };
        while let Ok(Some(entry)) = entries.next_entry().await {
            let name = entry.file_name().to_string_lossy().into_owned();
            if !(name.starts_with("pcpn-") && name.ends_with(".safetensors")) {
                continue;
            }
            match tokio::fs::read(entry.path()).await.map(|b| info_of(&b)) {
                Ok(Ok(info)) => pcpns.push(info),
                Ok(Err(e)) => tracing::warn!("{name}: {}", e.message()),
                Err(e) => tracing::warn!("{name}: {e}"),
            }
        }
        pcpns.sort_by(|a, b| a.file_sha256.cmp(&b.file_sha256));
        Ok(Response::new(pb::ListReply { pcpns }))
    }

    type GetStream = ReceiverStream<Result<PcpnChunk, Status>>;

    async fn get(
        &self,
        req: Request<pb::GetPcpnRequest>,
    ) -> Result<Response<Self::GetStream>, Status> {
        let r = req.get_ref();
        let (spec, p) = wanted(r.env.as_ref(), r.settings.as_ref())?;
        let (bytes, info) = self.stored(&spec, &p).await?.ok_or_else(|| {
            Status::not_found(format!(
                "no PCPN for {spec} pretrained with {p:?} in the store; ask Pretrain first"
            ))
        })?;
        let bytes = Bytes::from(bytes);
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            let mut info = Some(info);
            for (i, chunk) in bytes.chunks(CHUNK_BYTES).enumerate() {
                let msg = PcpnChunk {
                    info: info.take(),
                    offset: (i * CHUNK_BYTES) as u64,
                    data: bytes.slice_ref(chunk),
                };
                if tx.send(Ok(msg)).await.is_err() {
                    return;
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn pretrain(
        &self,
        req: Request<pb::PretrainRequest>,
    ) -> Result<Response<pb::PretrainReply>, Status> {
        let r = req.into_inner();
        let (spec, p) = wanted(r.env.as_ref(), r.settings.as_ref())?;
        // Held by the pretraining itself, not by this call: a caller that goes away
        // leaves it running, and the next request for the same PCPN waits for it and
        // then finds the file instead of starting another.
        let one_at_a_time = self.pretraining.clone().lock_owned().await;
        if let Some((_, info)) = self.stored(&spec, &p).await? {
            return Ok(Response::new(pb::PretrainReply {
                info: Some(info),
                already_present: true,
            }));
        }
        let store = self.store.clone();
        let shown = spec.to_string();
        let samples = self.samples.clone();
        if spec.kind().is_none() {
            tracing::info!(
                "pretraining {spec} from samples its actors stream ({} providers connected)",
                samples.providers_of(&spec)
            );
        }
        let tracker = self.tracker.clone();
        tracker.begin(&spec, p.batches);
        let saved = tokio::task::spawn_blocking(move || -> Result<PathBuf, String> {
            let _one_at_a_time = one_at_a_time;
            let dev = saver_core::device();
            let env = spec.to_string();
            let report = pretrain_pcpn(&spec, &p, &dev, Some(&samples), &mut |b| {
                metrics::gauge!("saver_pretrain_batches_done", "env" => env.clone())
                    .set(b.batch as f64);
                metrics::gauge!("saver_pretrain_batches", "env" => env.clone())
                    .set(b.batches as f64);
                metrics::gauge!("saver_pretrain_loss", "env" => env.clone()).set(b.loss as f64);
                tracker.batch(b.batch, b.loss);
            });
            tracker.end();
            let report = report.map_err(|e| e.to_string())?;
            let info = store
                .save(&spec, &p, &report.tensors, report.meta)
                .map_err(|e| e.to_string())?;
            Ok(info.path)
        })
        .await
        .map_err(|e| Status::internal(e.to_string()))?
        .map_err(Status::aborted)?;
        let bytes = tokio::fs::read(&saved)
            .await
            .map_err(|e| Status::internal(format!("reading {}: {e}", saved.display())))?;
        tracing::info!("PCPN for {shown} stored in {}", saved.display());
        Ok(Response::new(pb::PretrainReply {
            info: Some(info_of(&bytes)?),
            already_present: false,
        }))
    }

    async fn progress(
        &self,
        _req: Request<pb::ProgressRequest>,
    ) -> Result<Response<pb::ProgressReply>, Status> {
        Ok(Response::new(pb::ProgressReply {
            pretraining: self.progress().into_iter().collect(),
        }))
    }

    type ProvideSamplesStream = ReceiverStream<Result<pb::SampleDemand, Status>>;

    async fn provide_samples(
        &self,
        req: Request<tonic::Streaming<pb::SampleBatch>>,
    ) -> Result<Response<Self::ProvideSamplesStream>, Status> {
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(crate::samples::provide(
            self.samples.clone(),
            req.into_inner(),
            tx,
        ));
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

/// Serves PcpnStore (and grpc.health.v1) on `listener` until `shutdown`, saying how
/// far a pretraining is every 10 s. At `shutdown` a pretraining that waits for samples
/// ends at once (its caller is told the store stops); one that trains is left to the
/// caller's runtime to drop (nothing of it is stored).
pub async fn serve(
    service: PcpnService,
    listener: tokio::net::TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send,
) -> Result<(), tonic::transport::Error> {
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<PcpnStoreServer<PcpnService>>().await;
    let incoming = service.access.incoming(listener);
    let reporter = tokio::spawn({
        let service = service.clone();
        async move {
            let mut tick = tokio::time::interval(crate::samples::SAY_EVERY);
            tick.tick().await;
            loop {
                tick.tick().await;
                if let Some(p) = service.progress() {
                    tracing::info!("{}", p.line);
                }
            }
        }
    });
    let stopping = service.clone();
    let served = service
        .access
        .server()?
        .add_service(health_service)
        .add_service(service.into_server())
        .serve_with_incoming_shutdown(incoming, async move {
            shutdown.await;
            stopping.cancel();
        })
        .await;
    reporter.abort();
    served
}

/// Fetches the PCPN of `spec` pretrained with `p` from a store at `url` (asking it to
/// pretrain one if it has none); returns the file's bytes after checking their length
/// and sha256.
pub async fn fetch(
    url: &str,
    spec: &EnvSpec,
    p: &PretrainConfig,
    access: &ClientAccess,
) -> Result<Vec<u8>, Status> {
    use saver_proto::pb::pcpn_store_client::PcpnStoreClient;
    use tokio_stream::StreamExt;
    let unavailable =
        |e: &dyn std::fmt::Display| Status::unavailable(format!("the PCPN store {url}: {e}"));
    let channel = access
        .endpoint(url)
        .map_err(|e| unavailable(&e))?
        .connect()
        .await
        .map_err(|e| unavailable(&e))?;
    let mut client = PcpnStoreClient::with_interceptor(channel, access.token.clone())
        .max_decoding_message_size(saver_proto::MAX_MESSAGE_BYTES);
    let env = Some(pb::EnvSpec::from(spec));
    let settings = Some(pb::PretrainSettings::from(p));
    client
        .pretrain(pb::PretrainRequest {
            env: env.clone(),
            settings: settings.clone(),
        })
        .await?;
    let mut stream = client
        .get(pb::GetPcpnRequest { env, settings })
        .await?
        .into_inner();
    let mut bytes = Vec::new();
    let mut info: Option<pb::PcpnInfo> = None;
    while let Some(chunk) = stream.next().await {
        let chunk = chunk?;
        if chunk.offset != bytes.len() as u64 {
            return Err(Status::data_loss("PCPN chunks arrived out of order"));
        }
        if info.is_none() {
            info = chunk.info;
        }
        bytes.extend_from_slice(&chunk.data);
    }
    let info = info.ok_or_else(|| Status::data_loss("the PCPN stream carried no info"))?;
    let actual = saver_proto::sha256_hex(&bytes);
    if bytes.len() as u64 != info.size || actual != info.file_sha256 {
        return Err(Status::data_loss(format!(
            "PCPN file from {url}: {} bytes with sha256 {actual}, announced {} bytes with {}",
            bytes.len(),
            info.size,
            info.file_sha256
        )));
    }
    Ok(bytes)
}
