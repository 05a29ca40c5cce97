//! The Learner service of a learner that is up but not training yet: it waits for its
//! PCPN (fetched from a pcpn-trainer, which may first gather samples and pretrain,
//! or pretrained here). Status says what it waits for and how far that is; every
//! other call is answered UNAVAILABLE with the same words and the trailer
//! [`WAITING_KEY`], so that actors know to keep waiting (no deadline) instead of
//! taking the learner for gone.

use saver_proto::pb::learner_server::{Learner, LearnerServer};
use saver_proto::pb::{self, RolloutAck};
use saver_proto::{Access, WAITING_KEY};
use tokio::sync::watch;
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::MetadataMap;
use tonic::{Request, Response, Status, Streaming};

/// What the learner waits for.
#[derive(Clone, Debug, Default)]
pub struct Waiting {
    /// The run's algorithm, env and mode (as Status names them).
    pub algo: String,
    /// Env.
    pub env: String,
    /// Mode.
    pub mode: String,
    /// What it waits for and how far that is, in one line.
    pub what: String,
    /// The PCPN's pretraining, when the store says how far it is.
    pub pretrain: Option<pb::PretrainProgress>,
}

/// The waiting learner's service.
#[derive(Clone)]
pub struct WaitingLearner {
    about: watch::Receiver<Waiting>,
    access: Access,
}

impl WaitingLearner {
    /// A service that says what `about` holds, under `access`'s token and TLS.
    pub fn new(about: watch::Receiver<Waiting>, access: Access) -> Self {
        Self { about, access }
    }

    fn refused(&self) -> Status {
        let mut md = MetadataMap::new();
        md.insert(WAITING_KEY, "pcpn".parse().expect("an ASCII value"));
        let what = self.about.borrow().what.clone();
        Status::with_metadata(
            tonic::Code::Unavailable,
            saver_proto::clip_chars(
                &format!("waits before it serves: {what}"),
                saver_proto::MAX_STATUS_CHARS,
            ),
            md,
        )
    }
}

#[tonic::async_trait]
impl Learner for WaitingLearner {
    async fn register(
        &self,
        _req: Request<pb::RegisterRequest>,
    ) -> Result<Response<pb::RegisterReply>, Status> {
        Err(self.refused())
    }

    type StreamRolloutsStream = ReceiverStream<Result<RolloutAck, Status>>;

    async fn stream_rollouts(
        &self,
        _req: Request<Streaming<pb::Rollout>>,
    ) -> Result<Response<Self::StreamRolloutsStream>, Status> {
        Err(self.refused())
    }

    type WatchWeightsStream = ReceiverStream<Result<pb::Weights, Status>>;

    async fn watch_weights(
        &self,
        _req: Request<pb::WatchRequest>,
    ) -> Result<Response<Self::WatchWeightsStream>, Status> {
        Err(self.refused())
    }

    async fn get_weights(
        &self,
        _req: Request<pb::WeightsRequest>,
    ) -> Result<Response<pb::Weights>, Status> {
        Err(self.refused())
    }

    async fn status(
        &self,
        _req: Request<pb::StatusRequest>,
    ) -> Result<Response<pb::StatusReply>, Status> {
        let w = self.about.borrow().clone();
        Ok(Response::new(pb::StatusReply {
            algo: w.algo,
            env: w.env,
            mode: w.mode,
            mean_ep_len_100: f64::NAN,
            waiting: w.what,
            pretrain: w.pretrain,
            ..Default::default()
        }))
    }
}

/// Serves the waiting learner (and grpc.health.v1) on `listener` until `shutdown`.
pub async fn serve_waiting(
    service: WaitingLearner,
    listener: tokio::net::TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send,
) -> Result<(), tonic::transport::Error> {
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<LearnerServer<WaitingLearner>>().await;
    let incoming = service.access.incoming(listener);
    let (mut router, check) = (service.access.server()?, service.access.check.clone());
    router
        .add_service(health_service)
        .add_service(crate::grpc::learner_server(service, check))
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await
}
