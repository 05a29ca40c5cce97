//! The same-host shortcut for weights: every published version also lands as a
//! safetensors file in a directory (by default in /dev/shm, i.e. memory), so that actor
//! processes on the learner's machine read one file per version instead of each
//! receiving its bytes over a socket. The gRPC stream then carries only the file's name.
//!
//! Readers find out whether they share the directory by reading its `id` file, which
//! holds a random string the learner also sends at registration. Files are written
//! under a temporary name and renamed, so a reader never sees a partial file; the
//! newest [`KEEP`] versions stay, older ones are removed, and everything the learner
//! wrote is removed when it stops.

use crate::sha256_hex;
use std::collections::VecDeque;
use std::io;
use std::path::{Path, PathBuf};

/// Versions kept on disk: a reader more than this many versions behind falls back to
/// GetWeights.
pub const KEEP: usize = 8;

/// Default directories are /dev/shm/saver-weights-<process id>.
const DEFAULT_PREFIX: &str = "saver-weights-";

/// Name of the file that identifies a weights directory.
pub const ID_FILE: &str = "id";

/// A weights directory this learner owns.
#[derive(Debug)]
pub struct WeightsDir {
    /// What to remove at the end.
    remover: Remover,
    /// Version files written, oldest first.
    files: VecDeque<PathBuf>,
}

/// Removes what a learner wrote into its weights directory: the version files, their
/// temporary files and the `id` (if still its own), and the directory if it made it.
#[derive(Clone, Debug)]
pub struct Remover {
    /// The directory.
    path: PathBuf,
    /// The random identity written to `id`.
    id: String,
    /// Whether the learner created the directory.
    created: bool,
}

impl Remover {
    /// Removes it all; what is already gone is skipped.
    pub fn remove(&self) {
        if !shares(&self.path, &self.id) {
            return; // another learner took the directory over
        }
        if let Ok(entries) = std::fs::read_dir(&self.path) {
            for e in entries.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                let ours = is_version_file(&name)
                    || name == "id.tmp"
                    || name
                        .strip_suffix(".tmp")
                        .is_some_and(|n| is_version_file(&format!("{n}.safetensors")));
                if ours {
                    let _ = std::fs::remove_file(e.path());
                }
            }
        }
        let _ = std::fs::remove_file(self.path.join(ID_FILE));
        if self.created {
            let _ = std::fs::remove_dir(&self.path);
        }
    }
}

impl WeightsDir {
    /// Creates (if needed) `path` and writes a fresh identity into it.
    pub fn create(path: &Path) -> io::Result<Self> {
        let created = !path.exists();
        std::fs::create_dir_all(path)?;
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or_default();
        let id =
            sha256_hex(format!("{}:{nanos}:{}", std::process::id(), path.display()).as_bytes())
                [..32]
                .to_string();
        write_atomically(&path.join(ID_FILE), id.as_bytes())?;
        Ok(Self {
            remover: Remover {
                path: path.to_path_buf(),
                id,
                created,
            },
            files: VecDeque::new(),
        })
    }

    /// A directory in /dev/shm named after this process, where /dev/shm exists. Also
    /// removes such directories left by learners that are no longer running (killed
    /// before they could clean up).
    pub fn default_path() -> Option<PathBuf> {
        let shm = Path::new("/dev/shm");
        if !shm.is_dir() {
            return None;
        }
        for e in std::fs::read_dir(shm).into_iter().flatten().flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let pid = name
                .strip_prefix(DEFAULT_PREFIX)
                .and_then(|p| p.parse::<u32>().ok());
            if let Some(pid) = pid {
                if !Path::new(&format!("/proc/{pid}")).exists() {
                    let _ = std::fs::remove_dir_all(e.path());
                }
            }
        }
        Some(shm.join(format!("{DEFAULT_PREFIX}{}", std::process::id())))
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.remover.path
    }

    /// The identity readers check.
    pub fn id(&self) -> &str {
        &self.remover.id
    }

    /// What removes this directory's files at the end, for an owner that may outlive
    /// the writer or must not wait for it (the writer's drop does the same).
    pub fn remover(&self) -> Remover {
        self.remover.clone()
    }

    /// Writes version `version`'s safetensors bytes; returns the file's name. Removes
    /// the oldest file beyond [`KEEP`].
    pub fn write(&mut self, version: u64, bytes: &[u8]) -> io::Result<String> {
        let name = file_name(version);
        let path = self.remover.path.join(&name);
        write_atomically(&path, bytes)?;
        self.files.push_back(path);
        while self.files.len() > KEEP {
            if let Some(old) = self.files.pop_front() {
                let _ = std::fs::remove_file(old);
            }
        }
        Ok(name)
    }
}

impl Drop for WeightsDir {
    fn drop(&mut self) {
        self.remover.remove();
    }
}

/// The file name of a version.
pub fn file_name(version: u64) -> String {
    format!("v{version}.safetensors")
}

/// Whether `name` is a version file name as the learner writes it (a reader must not
/// follow anything else the network hands it, such as `../x`).
pub fn is_version_file(name: &str) -> bool {
    name.strip_prefix('v')
        .and_then(|s| s.strip_suffix(".safetensors"))
        .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
}

/// Whether `dir` holds the identity `id`: the reader shares the learner's directory.
pub fn shares(dir: &Path, id: &str) -> bool {
    !id.is_empty()
        && std::fs::read_to_string(dir.join(ID_FILE)).is_ok_and(|found| found.trim() == id)
}

fn write_atomically(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_the_newest_versions_and_cleans_up() {
        let root = std::env::temp_dir().join(format!("saver-wdir-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let mut dir = WeightsDir::create(&root).unwrap();
        assert!(shares(&root, dir.id()));
        assert!(!shares(&root, "someone-else"));
        for v in 1..=(KEEP as u64 + 3) {
            let name = dir.write(v, &v.to_le_bytes()).unwrap();
            assert!(is_version_file(&name), "{name}");
        }
        // Versions 1..=3 are gone, 4..=11 readable with their bytes.
        assert!(!root.join(file_name(3)).exists());
        for v in 4..=(KEEP as u64 + 3) {
            assert_eq!(
                std::fs::read(root.join(file_name(v))).unwrap(),
                v.to_le_bytes()
            );
        }
        let remover = dir.remover();
        drop(dir);
        assert!(
            !root.exists(),
            "the learner's directory is removed at the end"
        );
        remover.remove(); // twice is harmless

        // In a directory of the user's, only the learner's own files go.
        std::fs::create_dir_all(&root).unwrap();
        std::fs::write(root.join("notes.txt"), "mine").unwrap();
        let mut dir = WeightsDir::create(&root).unwrap();
        dir.write(1, b"w").unwrap();
        std::fs::write(root.join("v2.tmp"), "half").unwrap();
        dir.remover().remove();
        let left: Vec<_> = std::fs::read_dir(&root)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert_eq!(left, vec!["notes.txt".to_string()]);
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn only_plain_version_names_are_files() {
        for bad in [
            "../v1.safetensors",
            "v.safetensors",
            "v1.safetensors/x",
            "id",
            "v1x.safetensors",
            "/etc/passwd",
        ] {
            assert!(!is_version_file(bad), "{bad}");
        }
        assert!(is_version_file("v0.safetensors"));
    }
}
