//! End-to-end tests: the `saver` binary as a user runs it, and whole training runs.

mod cli;
mod grpc;
mod learning;
mod processes;

use std::path::PathBuf;

/// A fresh, empty temporary folder for one test.
pub fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("saver-e2e-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}
