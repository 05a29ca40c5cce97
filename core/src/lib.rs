//! saver-core: the algorithm of docs/ALGORITHM.md with no networking in it.
//!
//! Environments with state aligned vector rewards, the agent / A2C head / PCPN /
//! vector critic networks, the quantile and monotonic losses, n-step returns, TF1
//! RMSProp, PCPN pretraining and the SAVER and A2C updates. The learner, the actors and
//! the pcpn-trainer are built from these pieces; none of them does loss maths itself.

pub mod acting;
pub mod algo;
pub mod checkpoint;
pub mod config;
pub mod embedding;
pub mod env;
pub mod error;
pub mod limits;
pub mod link;
pub mod loss;
pub mod nets;
pub mod optim;
pub mod pretrain;
pub mod returns;
pub mod rng;
pub mod rollout;
pub mod settings;
pub mod wire;

pub use error::{CoreError, Result};
pub use saver_proto::clip_text;

/// The device updates run on: the first CUDA GPU when built with the `cuda` feature and
/// one is present, else the CPU.
pub fn device() -> candle_core::Device {
    #[cfg(feature = "cuda")]
    if let Ok(d) = candle_core::Device::new_cuda(0) {
        return d;
    }
    candle_core::Device::Cpu
}
