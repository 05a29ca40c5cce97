//! The small clients of the `saver` binary: `weights` (fetch and list a learner's
//! weights), `status` (what a learner is doing) and `healthcheck` (grpc.health.v1, for
//! container healthchecks where no shell or curl exists).

use crate::access::{client_tls, ClientArgs};
use crate::services::runtime;
use anyhow::{bail, Context, Result};
use clap::Args;
use saver_actor::grpc::decode_weights;
use saver_proto::pb;
use saver_proto::pb::learner_client::LearnerClient;
use saver_proto::{AddToken, ClientAccess};
use std::path::PathBuf;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

/// Where a learner is and how to prove we may talk to it.
#[derive(Args, Clone, Debug)]
pub struct LearnerAddr {
    /// The learner's URL.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    pub learner: String,
    /// The learner's token and CA.
    #[command(flatten)]
    pub access: ClientArgs,
}

type Client = LearnerClient<InterceptedService<Channel, AddToken>>;

impl LearnerAddr {
    async fn connect(&self) -> Result<Client> {
        let access = self.access.access()?;
        let channel = access
            .endpoint(&self.learner)
            .with_context(|| format!("learner address {:?}", self.learner))?
            .connect()
            .await
            .with_context(|| format!("connecting to {}", self.learner))?;
        Ok(LearnerClient::with_interceptor(channel, access.token)
            .max_decoding_message_size(saver_proto::MAX_MESSAGE_BYTES))
    }
}

fn status_error(s: tonic::Status) -> anyhow::Error {
    anyhow::anyhow!("{:?}: {}", s.code(), s.message())
}

/// `saver weights` flags.
#[derive(Args, Clone, Debug)]
pub struct WeightsArgs {
    /// The learner.
    #[command(flatten)]
    pub addr: LearnerAddr,
    /// Write the weights (safetensors) here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Wait for at least this version.
    #[arg(long, default_value_t = 0)]
    pub min_version: u64,
}

/// Runs `saver weights`.
pub fn weights(args: WeightsArgs) -> Result<()> {
    let reply = runtime()?.block_on(async {
        let mut client = args.addr.connect().await?;
        let w = client
            .get_weights(pb::WeightsRequest {
                min_version: args.min_version,
            })
            .await
            .map_err(status_error)?;
        anyhow::Ok(w.into_inner())
    })?;
    let decoded = decode_weights(&reply)?;
    crate::out!("version {}", decoded.version);
    for t in &decoded.tensors {
        crate::out!("{:<16} {:?}", t.name, t.shape);
    }
    if let Some(path) = &args.out {
        saver_core::checkpoint::write_atomic(path, &reply.safetensors)?;
        crate::out!("weights written to {}", path.display());
    }
    Ok(())
}

/// `saver status` flags.
#[derive(Args, Clone, Debug)]
pub struct StatusArgs {
    /// The learner.
    #[command(flatten)]
    pub addr: LearnerAddr,
    /// One JSON object per answer (mean_ep_len_100 null before the first episode).
    #[arg(long)]
    pub json: bool,
    /// Ask again every SECONDS until the run is finished (or Ctrl-C); a learner that
    /// does not answer yet (still starting, fetching or pretraining its PCPN) is said
    /// so and asked again.
    #[arg(long, value_name = "SECONDS", value_parser = crate::services::positive_secs)]
    pub watch: Option<f64>,
}

/// Runs `saver status`: one `key value` line per field of the learner's Status (or a
/// JSON object with `--json`), once or, with `--watch`, until the run is finished.
pub fn status(args: StatusArgs) -> Result<()> {
    let rt = runtime()?;
    let ask = || {
        rt.block_on(async {
            let mut client = args.addr.connect().await?;
            let r = client
                .status(pb::StatusRequest {})
                .await
                .map_err(status_error)?;
            anyhow::Ok(r.into_inner())
        })
    };
    let Some(every) = args.watch else {
        let s = ask().map_err(|e| not_answering(&args.addr.learner, e))?;
        print_status(&s, args.json);
        return Ok(());
    };
    loop {
        match ask() {
            Ok(s) => {
                print_status(&s, args.json);
                if s.finished {
                    return Ok(());
                }
            }
            Err(e) => eprintln!("{:#}", not_answering(&args.addr.learner, e)),
        }
        std::thread::sleep(std::time::Duration::from_secs_f64(every));
    }
}

/// A failed Status call, with what it may mean.
fn not_answering(url: &str, e: anyhow::Error) -> anyhow::Error {
    e.context(format!(
        "no Status answer from the learner at {url} (is `saver learner` running there? \
         while it waits for its PCPN it answers Status with what it waits for)"
    ))
}

fn print_status(s: &pb::StatusReply, json: bool) {
    use serde_json::Value;
    // One list of fields for both forms (mean_ep_len_100: JSON null before the first
    // episode, NaN in text).
    let pretrain = s.pretrain.as_ref().map(|p| {
        serde_json::json!({
            "phase": p.phase,
            "samples_received": p.samples_received,
            "samples_total": p.samples_total,
            "providers": p.providers,
            "batches_done": p.batches_done,
            "batches": p.batches,
            "seconds": p.seconds,
            "eta_seconds": p.eta_seconds,
        })
    });
    let fields: [(&str, Value); 15] = [
        ("algo", s.algo.clone().into()),
        ("env", s.env.clone().into()),
        ("mode", s.mode.clone().into()),
        ("version", s.version.into()),
        ("steps", s.steps.into()),
        ("actors", s.actors.into()),
        ("pending", s.pending.into()),
        ("accepted", s.accepted.into()),
        ("rejected", s.rejected.into()),
        ("stale_dropped", s.stale_dropped.into()),
        ("skipped_updates", s.skipped_updates.into()),
        ("mean_ep_len_100", s.mean_ep_len_100.into()),
        ("finished", s.finished.into()),
        ("waiting", s.waiting.clone().into()),
        ("pretrain", pretrain.unwrap_or(Value::Null)),
    ];
    if json {
        let map: serde_json::Map<String, Value> = fields
            .into_iter()
            .map(|(k, v)| (k.to_string(), v))
            .collect();
        crate::out!("{}", Value::Object(map));
        return;
    }
    for (k, v) in fields {
        match v {
            // Empty while the learner trains; the pretraining's progress is in `waiting`.
            Value::String(t) if t.is_empty() && k == "waiting" => {}
            Value::Null if k == "pretrain" => {}
            Value::Object(_) => {}
            Value::String(t) => crate::out!("{k} {t}"),
            Value::Null => crate::out!("{k} NaN"),
            v => crate::out!("{k} {v}"),
        }
    }
}

/// `saver healthcheck` flags.
#[derive(Args, Clone, Debug)]
pub struct HealthArgs {
    /// The server's URL.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    pub addr: String,
    /// CA certificate (PEM) of an https:// server.
    #[arg(long, value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
}

/// Runs `saver healthcheck`: exit 0 when the server reports SERVING (grpc.health.v1,
/// which needs no token).
pub fn healthcheck(args: HealthArgs) -> Result<()> {
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;
    let status = runtime()?.block_on(async {
        let access = ClientAccess {
            tls: args.tls_ca.as_deref().map(client_tls).transpose()?,
            ..ClientAccess::default()
        };
        let channel = access
            .endpoint(&args.addr)
            .with_context(|| format!("server address {:?}", args.addr))?
            .connect()
            .await
            .with_context(|| format!("connecting to {}", args.addr))?;
        let r = HealthClient::new(channel)
            .check(HealthCheckRequest {
                service: String::new(),
            })
            .await
            .map_err(status_error)?;
        anyhow::Ok(r.into_inner().status)
    })?;
    if status != tonic_health::pb::health_check_response::ServingStatus::Serving as i32 {
        bail!("{} is not serving (status {status})", args.addr);
    }
    crate::out!("{}: SERVING", args.addr);
    Ok(())
}
