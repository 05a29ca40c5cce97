//! End-to-end tests: the `saver` binary as a user runs it, and whole training runs.

mod abuse;
mod cli;
mod faults;
mod grpc;
mod hostile;
mod learning;
mod pretrain;
mod processes;
mod tls;

use std::path::PathBuf;
use std::process::{Command, Output};

/// Runs the `saver` binary with `args` to its end.
pub fn saver(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_saver"))
        .args(args)
        .output()
        .expect("the saver binary runs")
}

/// What a run of the binary printed: its stdout then its stderr.
pub fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// Runs the `saver` binary with `args`, which must succeed: what it printed.
pub fn saver_ok(args: &[&str]) -> String {
    let o = saver(args);
    let printed = text(&o);
    assert!(o.status.success(), "saver {args:?}: {printed}");
    printed
}

/// A fresh, empty temporary folder for one test.
pub fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("saver-e2e-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The one PCPN file of a store folder (its name hashes the env and the settings).
pub fn only_pcpn(store: &std::path::Path) -> PathBuf {
    let files: Vec<PathBuf> = std::fs::read_dir(store)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "safetensors"))
        .collect();
    assert_eq!(files.len(), 1, "{files:?}");
    files[0].clone()
}

/// Every tensor of `part` is in `whole` with the same shape and bit-identical values.
pub fn assert_tensors_in(part: &[saver_proto::NamedTensor], whole: &[saver_proto::NamedTensor]) {
    for p in part {
        let w = whole
            .iter()
            .find(|w| w.name == p.name)
            .unwrap_or_else(|| panic!("{} is missing", p.name));
        assert_eq!(w.shape, p.shape, "{}", p.name);
        assert!(
            w.data
                .iter()
                .zip(&p.data)
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "{} differs",
            p.name
        );
    }
}
