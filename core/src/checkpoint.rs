//! Checkpoint files: named f32 tensors plus string metadata in one safetensors file,
//! written atomically (temporary file in the same directory, fsync, rename).

use crate::{CoreError, Result};
use candle_core::{Device, Tensor};
use saver_proto::NamedTensor;
use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

/// A candle tensor as a named f32 tensor.
pub fn to_named(name: &str, t: &Tensor) -> Result<NamedTensor> {
    Ok(NamedTensor {
        name: name.to_string(),
        shape: t.dims().to_vec(),
        data: t
            .flatten_all()?
            .to_dtype(candle_core::DType::F32)?
            .to_vec1::<f32>()?,
    })
}

/// Many candle tensors as named f32 tensors.
pub fn to_named_all(tensors: &[(String, Tensor)]) -> Result<Vec<NamedTensor>> {
    tensors.iter().map(|(n, t)| to_named(n, t)).collect()
}

/// Named f32 tensors as a name → candle tensor map on `dev`.
pub fn to_candle(tensors: &[NamedTensor], dev: &Device) -> Result<HashMap<String, Tensor>> {
    let mut map = HashMap::new();
    for t in tensors {
        map.insert(
            t.name.clone(),
            Tensor::from_slice(&t.data, t.shape.as_slice(), dev)?,
        );
    }
    Ok(map)
}

/// Writes bytes to `path` atomically: a temporary file beside it, fsync, rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let io = |e: std::io::Error| CoreError::Checkpoint(format!("writing {}: {e}", path.display()));
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(io)?;
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("checkpoint");
    // Named after this process: [`remove_stale_temporaries`] knows a dead writer's.
    let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    let mut f = std::fs::File::create(&tmp).map_err(io)?;
    f.write_all(bytes).map_err(io)?;
    f.sync_all().map_err(io)?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(io)
}

/// Removes the temporaries [`write_atomic`] left in `dir` when its process was killed
/// mid-write (`.<name>.tmp-<pid>` of a pid that no longer runs here, or older than a
/// day); returns how many it removed. A live writer's temporary is kept, this
/// process's included (one left by an earlier process of the same pid, as in a
/// restarted container, is overwritten by the next write of that file).
pub fn remove_stale_temporaries(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let mut removed = 0;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = name
            .to_str()
            .filter(|n| n.starts_with('.'))
            .and_then(|n| n.rsplit_once(".tmp-"))
            .and_then(|(_, pid)| pid.parse::<u32>().ok())
        else {
            continue;
        };
        let old = entry
            .metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|age| age.as_secs() > 24 * 3600);
        let alive = Path::new(&format!("/proc/{pid}")).exists();
        if (old || !alive) && std::fs::remove_file(entry.path()).is_ok() {
            tracing::info!(
                "removed {}, left by a killed writer",
                entry.path().display()
            );
            removed += 1;
        }
    }
    removed
}

/// Saves tensors and metadata to `path` atomically; returns the file's sha256.
pub fn save(
    path: &Path,
    tensors: &[NamedTensor],
    meta: &HashMap<String, String>,
) -> Result<String> {
    let bytes = saver_proto::encode(tensors, meta)?;
    write_atomic(path, &bytes)?;
    Ok(saver_proto::sha256_hex(&bytes))
}

/// A loaded checkpoint.
pub struct Loaded {
    /// Tensors by name.
    pub tensors: Vec<NamedTensor>,
    /// The string metadata.
    pub meta: HashMap<String, String>,
    /// sha256 of the file's bytes.
    pub sha256: String,
}

/// Loads a checkpoint written by [`save`] (or any f32 safetensors file).
pub fn load(path: &Path) -> Result<Loaded> {
    let bytes = std::fs::read(path)
        .map_err(|e| CoreError::Checkpoint(format!("reading {}: {e}", path.display())))?;
    let (tensors, meta) = saver_proto::decode(&bytes)
        .map_err(|e| CoreError::Checkpoint(format!("{}: {e}", path.display())))?;
    Ok(Loaded {
        tensors,
        meta,
        sha256: saver_proto::sha256_hex(&bytes),
    })
}
