//! The `PcpnStore` gRPC service: lists the store, streams a PCPN file in chunks with
//! its hashes, and pretrains one on request (once per env spec, never silently again).

use crate::store::{spec_of, PcpnStore};
use crate::train::pretrain_pcpn;
use bytes::Bytes;
use saver_core::config::{Algo, RunConfig};
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
}

/// The info message of a PCPN file's bytes.
pub fn info_of(bytes: &[u8]) -> Result<pb::PcpnInfo, Status> {
    let (_, meta) = saver_proto::decode(bytes).map_err(|e| Status::data_loss(e.to_string()))?;
    let spec = spec_of(bytes).ok_or_else(|| Status::data_loss("a stored file has no env_spec"))?;
    Ok(pb::PcpnInfo {
        env: Some((&spec).into()),
        weights_sha256: meta.get("weights_sha256").cloned().unwrap_or_default(),
        file_sha256: saver_proto::sha256_hex(bytes),
        size: bytes.len() as u64,
        metadata: meta,
    })
}

fn spec_from(req: Option<&pb::EnvSpec>) -> Result<EnvSpec, Status> {
    let s = req.ok_or_else(|| Status::invalid_argument("env is required"))?;
    EnvSpec::try_from(s).map_err(|e| Status::invalid_argument(e.to_string()))
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
        }
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

    async fn read(&self, spec: &EnvSpec) -> Result<Option<Vec<u8>>, Status> {
        match tokio::fs::read(self.store.path_for(spec)).await {
            Ok(b) => Ok(Some(b)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(Status::internal(format!("reading the store: {e}"))),
        }
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
        let spec = spec_from(req.get_ref().env.as_ref())?;
        let bytes = self.read(&spec).await?.ok_or_else(|| {
            Status::not_found(format!(
                "no PCPN for {spec} in the store; ask Pretrain first"
            ))
        })?;
        let info = info_of(&bytes)?;
        let stored = spec_of(&bytes);
        if stored != Some(spec) {
            return Err(Status::failed_precondition(format!(
                "the stored file for {spec} was pretrained for {}",
                stored
                    .map(|s| s.to_string())
                    .unwrap_or_else(|| "an unknown env".into())
            )));
        }
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
        let spec = spec_from(r.env.as_ref())?;
        let _one_at_a_time = self.pretraining.lock().await;
        if let Some(bytes) = self.read(&spec).await? {
            return Ok(Response::new(pb::PretrainReply {
                info: Some(info_of(&bytes)?),
                already_present: true,
            }));
        }
        let mut config = RunConfig::paper(spec, Algo::Saver, 1);
        config.seed = r.seed;
        if r.batches > 0 {
            config.pretrain.batches = r.batches;
        }
        if r.lr > 0.0 {
            config.pretrain.lr = r.lr;
        }
        config
            .validate()
            .map_err(|e| Status::invalid_argument(e.to_string()))?;
        let store = self.store.clone();
        let saved = tokio::task::spawn_blocking(move || -> Result<PathBuf, String> {
            let dev = saver_core::device();
            let every = (config.pretrain.batches / 20).max(1);
            let report = pretrain_pcpn(&config, &dev, &mut |p| {
                if p.batch % every == 0 {
                    tracing::info!(
                        "pretraining {spec}: batch {}/{} loss {:.4}",
                        p.batch,
                        p.batches,
                        p.loss
                    );
                }
            })
            .map_err(|e| e.to_string())?;
            let info = store
                .save(&spec, &report.tensors, report.meta)
                .map_err(|e| e.to_string())?;
            Ok(info.path)
        })
        .await
        .map_err(|e| Status::internal(e.to_string()))?
        .map_err(Status::aborted)?;
        let bytes = tokio::fs::read(&saved)
            .await
            .map_err(|e| Status::internal(format!("reading {}: {e}", saved.display())))?;
        tracing::info!("PCPN for {spec} stored in {}", saved.display());
        Ok(Response::new(pb::PretrainReply {
            info: Some(info_of(&bytes)?),
            already_present: false,
        }))
    }
}

/// Serves PcpnStore (and grpc.health.v1) on `listener` until `shutdown`.
pub async fn serve(
    service: PcpnService,
    listener: tokio::net::TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send,
) -> Result<(), tonic::transport::Error> {
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<PcpnStoreServer<PcpnService>>().await;
    let incoming = service.access.incoming(listener);
    service
        .access
        .server()?
        .add_service(health_service)
        .add_service(service.into_server())
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await
}

/// Fetches the PCPN of `config.env` from a store at `url` (asking it to pretrain one
/// with `config`'s pretraining settings if it has none); returns the file's bytes after
/// checking their length and sha256.
pub async fn fetch(
    url: &str,
    config: &RunConfig,
    access: &ClientAccess,
) -> Result<Vec<u8>, Status> {
    let spec = &config.env;
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
    client
        .pretrain(pb::PretrainRequest {
            env: env.clone(),
            batches: config.pretrain.batches,
            seed: config.seed,
            lr: config.pretrain.lr,
        })
        .await?;
    let mut stream = client.get(pb::GetPcpnRequest { env }).await?.into_inner();
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
