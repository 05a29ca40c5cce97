//! saver-learner: the learner side of SAVER. A [`Hub`] is what actors talk to
//! (register, hand over rollouts, wait for weights); the [`trainer`] thread forms
//! batches, runs the algorithm's update off any async runtime and publishes each new
//! version as one shared buffer. The embedded run reaches the hub through
//! [`InProcessLink`]; the gRPC service ([`grpc`]) reaches the same hub over the network.
//! [`checkpoint`] saves the learner and resumes a run.

pub mod best;
pub mod checkpoint;
pub mod grpc;
mod hub;
mod inproc;
pub mod ledger;
pub mod metrics;
mod sinks;
pub mod size_limit;
pub mod tensorboard;
pub mod trainer;
pub mod waiting;
pub mod warn;

pub use checkpoint::{resume, ActorStates, Counters, RunState, CHECKPOINT_FILE};
pub use hub::{Hub, HubStats, DEFAULT_ROUND_TIMEOUT, MAX_ENVS, MAX_PENDING, REGISTRATION_LEASE};
pub use inproc::InProcessLink;
pub use metrics::{EpisodeWindow, MetricsRow};
pub use trainer::{spawn_trainer, TrainerHandle, TrainerOptions, TrainerOutcome};
