//! The PCPN store: `pcpn-<env>-d<dim>-<key>.safetensors` files, one per env spec and
//! pretraining settings (`key` hashes both), whose metadata name the spec, the
//! settings, the architecture, the held-out loss and a content hash. Loading verifies
//! the spec, the settings and the hash.

use crate::train::PRETRAIN_META;
use candle_core::Device;
use saver_core::checkpoint;
use saver_core::config::PretrainConfig;
use saver_core::env::EnvSpec;
use saver_core::nets::Pcpn;
use saver_proto::NamedTensor;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Metadata format tag.
pub const FORMAT: &str = "saver-pcpn/1";

/// Why a stored PCPN cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The file is for other dynamics.
    #[error("{path}: this PCPN was pretrained for {found}, but the run needs {wanted}; pretrain one with `saver pretrain --env {} --dim {}` or point --pcpn at the right file", wanted.name(), wanted.dim())]
    SpecMismatch {
        /// File.
        path: String,
        /// Spec in the file.
        found: String,
        /// Spec the caller needs.
        wanted: Box<EnvSpec>,
    },
    /// The file was pretrained with other settings.
    #[error("{path}: this PCPN was pretrained with {found}, but the run asks for {wanted}; a PCPN of other settings is never used in their place")]
    SettingsMismatch {
        /// File.
        path: String,
        /// Settings in the file.
        found: String,
        /// Settings the caller asked for.
        wanted: String,
    },
    /// The run names other weights than the PCPN found.
    #[error("{path}: its weights sha256 is {actual}, but the run uses the PCPN {wanted} (pcpn_sha256 of its config); pass that PCPN with --pcpn FILE, or drop pcpn_sha256 to use this one")]
    Pinned {
        /// File.
        path: String,
        /// Its weights hash.
        actual: String,
        /// The hash the run names.
        wanted: String,
    },
    /// The tensors do not hash to the recorded sha256.
    #[error("{path}: weights sha256 is {actual}, metadata says {recorded}: the file is corrupt")]
    HashMismatch {
        /// File.
        path: String,
        /// Recorded.
        recorded: String,
        /// Computed.
        actual: String,
    },
    /// Unreadable or malformed.
    #[error(transparent)]
    Core(#[from] saver_core::CoreError),
    /// Metadata missing or unparsable.
    #[error("{path}: {why}")]
    Meta {
        /// File.
        path: String,
        /// What is wrong.
        why: String,
    },
}

/// What a stored PCPN says about itself.
#[derive(Clone, Debug)]
pub struct PcpnInfo {
    /// The env spec it models.
    pub spec: EnvSpec,
    /// How it was pretrained.
    pub pretrain: PretrainConfig,
    /// All metadata entries.
    pub meta: HashMap<String, String>,
    /// sha256 of the tensor contents (names, shapes, values).
    pub weights_sha256: String,
    /// The file.
    pub path: PathBuf,
}

/// sha256 over every tensor's name, shape and little-endian values, in name order: a
/// hash of the weights that does not depend on metadata.
pub fn weights_sha256(tensors: &[NamedTensor]) -> String {
    let mut sorted: Vec<&NamedTensor> = tensors.iter().collect();
    sorted.sort_by(|a, b| a.name.cmp(&b.name));
    let mut bytes = Vec::new();
    for t in sorted {
        bytes.extend_from_slice(t.name.as_bytes());
        for d in &t.shape {
            bytes.extend_from_slice(&(*d as u64).to_le_bytes());
        }
        for v in &t.data {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    saver_proto::sha256_hex(&bytes)
}

/// A folder of PCPN files.
#[derive(Clone, Debug)]
pub struct PcpnStore {
    /// The folder.
    dir: PathBuf,
}

impl PcpnStore {
    /// A store in `dir` (created on first save); temporary files that a killed
    /// writer left there are removed ([`checkpoint::remove_stale_temporaries`]).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        let dir = dir.into();
        checkpoint::remove_stale_temporaries(&dir);
        Self { dir }
    }

    /// The store's folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Where the PCPN of `spec` pretrained with `p` lives.
    pub fn path_for(&self, spec: &EnvSpec, p: &PretrainConfig) -> PathBuf {
        self.dir
            .join(format!("pcpn-{spec}-{}.safetensors", p.key(spec)))
    }

    /// Saves tensors with metadata (spec, settings and hash are added here).
    pub fn save(
        &self,
        spec: &EnvSpec,
        p: &PretrainConfig,
        tensors: &[NamedTensor],
        mut meta: HashMap<String, String>,
    ) -> Result<PcpnInfo, StoreError> {
        let path = self.path_for(spec, p);
        let hash = weights_sha256(tensors);
        meta.insert("format".into(), FORMAT.into());
        meta.insert(
            "env_spec".into(),
            serde_json::to_string(&spec.dynamics()).unwrap_or_default(),
        );
        meta.insert("env".into(), spec.to_string());
        meta.insert(
            PRETRAIN_META.into(),
            serde_json::to_string(p).unwrap_or_default(),
        );
        meta.insert("weights_sha256".into(), hash.clone());
        checkpoint::save(&path, tensors, &meta)?;
        Ok(PcpnInfo {
            spec: spec.clone(),
            pretrain: *p,
            meta,
            weights_sha256: hash,
            path,
        })
    }

    /// The PCPN of `spec` pretrained with `p`, if the store has it (a file of the
    /// right name but other settings inside is refused).
    pub fn find(
        &self,
        spec: &EnvSpec,
        p: &PretrainConfig,
        dev: &Device,
    ) -> Result<Option<(Pcpn, PcpnInfo)>, StoreError> {
        let path = self.path_for(spec, p);
        if !path.exists() {
            return Ok(None);
        }
        let found = load_pcpn(&path, spec, dev)?;
        same_pretraining(&found.1, p)?;
        Ok(Some(found))
    }
}

/// Refuses a PCPN pretrained with settings other than `p`.
pub fn same_pretraining(info: &PcpnInfo, p: &PretrainConfig) -> Result<(), StoreError> {
    if info.pretrain == *p {
        return Ok(());
    }
    Err(StoreError::SettingsMismatch {
        path: info.path.display().to_string(),
        found: format!("{:?}", info.pretrain),
        wanted: format!("{p:?}"),
    })
}

/// Loads a PCPN file, refusing one for another env spec or with a wrong hash.
pub fn load_pcpn(
    path: &Path,
    wanted: &EnvSpec,
    dev: &Device,
) -> Result<(Pcpn, PcpnInfo), StoreError> {
    let bytes = std::fs::read(path).map_err(|e| {
        saver_core::CoreError::Checkpoint(format!("reading {}: {e}", path.display()))
    })?;
    load_pcpn_bytes(&bytes, path, wanted, dev)
}

/// Reads the env spec a PCPN file says it models (no other checks).
pub fn spec_of(bytes: &[u8]) -> Option<EnvSpec> {
    let (_, meta) = saver_proto::decode(bytes).ok()?;
    serde_json::from_str(meta.get("env_spec")?).ok()
}

/// Loads the bytes of a PCPN file (`path` names it in errors and in the info), refusing
/// one for another env spec or with a wrong hash.
pub fn load_pcpn_bytes(
    bytes: &[u8],
    path: &Path,
    wanted: &EnvSpec,
    dev: &Device,
) -> Result<(Pcpn, PcpnInfo), StoreError> {
    let (tensors, info) = check_pcpn_bytes(bytes, path, wanted)?;
    let map = checkpoint::to_candle(&tensors, dev)?;
    let pcpn = Pcpn::frozen(&info.spec.layout(), &|n| map.get(n).cloned())?;
    Ok((pcpn, info))
}

/// What the bytes of a PCPN file are, every check of [`load_pcpn_bytes`] made (spec,
/// settings, hash) but no network built: the tensors and the info.
pub fn check_pcpn_bytes(
    bytes: &[u8],
    path: &Path,
    wanted: &EnvSpec,
) -> Result<(Vec<NamedTensor>, PcpnInfo), StoreError> {
    let shown = path.display().to_string();
    let (tensors, meta) = saver_proto::decode(bytes)
        .map_err(|e| saver_core::CoreError::Checkpoint(format!("{shown}: {e}")))?;
    let loaded = checkpoint::Loaded {
        tensors,
        meta,
        sha256: saver_proto::sha256_hex(bytes),
    };
    let meta_err = |why: &str| StoreError::Meta {
        path: shown.clone(),
        why: why.to_string(),
    };
    let spec_json = loaded
        .meta
        .get("env_spec")
        .ok_or_else(|| meta_err("no env_spec in metadata: not a SAVER PCPN file"))?;
    let spec: EnvSpec = serde_json::from_str(spec_json)
        .map_err(|e| meta_err(&format!("env_spec {spec_json:?} is unreadable: {e}")))?;
    if spec.dynamics() != wanted.dynamics() {
        return Err(StoreError::SpecMismatch {
            path: shown,
            found: spec.to_string(),
            wanted: Box::new(wanted.clone()),
        });
    }
    let pretrain_json = loaded.meta.get(PRETRAIN_META).ok_or_else(|| {
        meta_err(
            "no pretraining settings in metadata (a file of an older SAVER): pretrain it again",
        )
    })?;
    let pretrain: PretrainConfig = serde_json::from_str(pretrain_json).map_err(|e| {
        meta_err(&format!(
            "pretraining settings {pretrain_json:?} are unreadable: {e}"
        ))
    })?;
    let recorded = loaded
        .meta
        .get("weights_sha256")
        .ok_or_else(|| meta_err("no weights_sha256 in metadata"))?
        .clone();
    let actual = weights_sha256(&loaded.tensors);
    if recorded != actual {
        return Err(StoreError::HashMismatch {
            path: shown,
            recorded,
            actual,
        });
    }
    Ok((
        loaded.tensors,
        PcpnInfo {
            spec,
            pretrain,
            meta: loaded.meta,
            weights_sha256: actual,
            path: path.to_path_buf(),
        },
    ))
}
