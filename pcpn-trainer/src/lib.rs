//! saver-pcpn-trainer: pretrains PCPNs and keeps them in a store on disk, one
//! safetensors file per env spec and pretraining settings, with metadata that says
//! what it is, how it was made and how good it is; hands the right one to a run.

mod obtain;
pub mod progress;
pub mod samples;
pub mod service;
pub mod store;
mod train;

pub use obtain::{obtain_pcpn, Origin};
pub use store::{load_pcpn, load_pcpn_bytes, weights_sha256, PcpnInfo, PcpnStore, StoreError};
pub use train::{pretrain_from, pretrain_pcpn, PretrainProgress, PretrainReport, PRETRAIN_META};
