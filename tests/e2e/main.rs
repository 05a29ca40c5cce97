//! End-to-end tests: the `saver` binary as a user runs it, and whole training runs.

mod cli;
mod faults;
mod grpc;
mod hostile;
mod learning;
mod processes;
mod tls;

use std::path::PathBuf;

/// A fresh, empty temporary folder for one test.
pub fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("saver-e2e-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
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

/// Serves the Learner service over `hub` (with `access`) on 127.0.0.1:0 on `rt`, for as
/// long as the runtime lives; returns its URL.
pub fn serve_learner(
    rt: &tokio::runtime::Runtime,
    hub: std::sync::Arc<saver_learner::Hub>,
    access: saver_proto::Access,
) -> String {
    let (service, _status) = saver_learner::grpc::LearnerService::new(hub);
    let listener = rt
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    rt.spawn(saver_learner::grpc::serve(
        service.with_access(access),
        listener,
        std::future::pending(),
    ));
    url
}
