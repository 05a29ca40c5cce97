//! saver-pcpn-trainer: pretrains PCPNs and keeps them in a store on disk, one
//! safetensors file per env spec, with metadata that says what it is and how good.

pub mod service;
pub mod store;
mod train;

pub use store::{load_pcpn, load_pcpn_bytes, weights_sha256, PcpnInfo, PcpnStore, StoreError};
pub use train::{pretrain_pcpn, PretrainProgress, PretrainReport};
