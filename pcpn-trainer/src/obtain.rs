//! "The PCPN for this run": an explicit file, the store's, or a fresh one pretrained
//! into the store, always with the settings asked for (never a cached PCPN of other
//! settings) and, when the run names one, the weights it names.

use crate::store::{load_pcpn, same_pretraining, PcpnInfo, PcpnStore, StoreError};
use crate::train::{pretrain_pcpn, PretrainProgress};
use saver_core::config::PretrainConfig;
use saver_core::env::EnvSpec;
use saver_core::nets::Pcpn;
use std::path::Path;

/// Where the PCPN came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Origin {
    /// The file the caller named.
    File,
    /// The store had it.
    Cached,
    /// Pretrained now and stored.
    Pretrained,
}

/// The PCPN of `spec`: from `explicit` if given (refused for another env spec; its
/// own pretraining settings are reported in the info), else the store's for `p`, else
/// pretrained per `p` into the store (`starting` is told first, with the file it will
/// write; `progress` after each batch). `pinned`: the weights sha256 it must have.
pub fn obtain_pcpn(
    spec: &EnvSpec,
    p: &PretrainConfig,
    store: &PcpnStore,
    explicit: Option<&Path>,
    pinned: Option<&str>,
    starting: &mut dyn FnMut(&Path),
    progress: &mut dyn FnMut(&PretrainProgress),
) -> Result<(Pcpn, PcpnInfo, Origin), StoreError> {
    let dev = saver_core::device();
    let (pcpn, info, origin) = if let Some(path) = explicit {
        let (pcpn, info) = load_pcpn(path, spec, &dev)?;
        (pcpn, info, Origin::File)
    } else if let Some((pcpn, info)) = store.find(spec, p, &dev)? {
        (pcpn, info, Origin::Cached)
    } else {
        starting(&store.path_for(spec, p));
        let report = pretrain_pcpn(spec, p, &dev, None, progress)?;
        let info = store.save(spec, p, &report.tensors, report.meta)?;
        (report.pcpn, info, Origin::Pretrained)
    };
    if origin != Origin::File {
        same_pretraining(&info, p)?;
    }
    if let Some(want) = pinned {
        if want != info.weights_sha256 {
            return Err(StoreError::Pinned {
                path: info.path.display().to_string(),
                actual: info.weights_sha256,
                wanted: want.to_string(),
            });
        }
    }
    Ok((pcpn, info, origin))
}
