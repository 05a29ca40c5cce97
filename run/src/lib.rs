//! saver-run: what the `saver` binary's commands do, as a library above the learner,
//! actor and pcpn-trainer crates: the embedded run (`train`), the service roles
//! (`services`), the clients, the benchmarks and the plots. The binary only parses
//! flags and calls one function here; the end-to-end tests call the same functions.

pub mod access;
pub mod act;
pub mod bench;
mod bench_custom;
pub mod bench_services;
pub mod clients;
pub mod config;
pub mod diagnose;
pub mod eval;
pub mod figures;
pub mod histogram;
pub mod labels;
pub mod output;
pub mod pcpn_gradients;
pub mod plot;
pub mod pretrain;
pub mod progress;
pub mod prometheus;
pub mod repro;
pub mod services;
pub mod train;

/// The threads of SAVER's fused PCPN blocks for this process's learners: one per core
/// (0) unless SAVER_PCPN_THREADS says otherwise; handed to each algorithm
/// ([`saver_core::algo::Algorithm::set_threads`]). Read once.
pub fn pcpn_threads() -> usize {
    static N: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *N.get_or_init(|| match std::env::var("SAVER_PCPN_THREADS") {
        Err(_) => 0,
        Ok(v) => v.parse().unwrap_or_else(|_| {
            eprintln!(
                "warning: SAVER_PCPN_THREADS={v:?} is not a thread count; using one per core"
            );
            0
        }),
    })
}

/// Process-wide set-up, before any thread exists.
///
/// - glibc malloc keeps freed memory: candle allocates a fresh buffer for every tensor
///   op, and buffers above glibc's mmap threshold were mapped, faulted in and unmapped
///   each time. Measured on `saver pretrain --env angle --dim 2 --batches 100`: 6.85 s
///   wall, 3.3 s of it in the kernel and 1.29 M page faults, against 3.22 s, 0.04 s and
///   15 k with these settings.
/// - candle reads RAYON_NUM_THREADS at every matmul and, when it is unset, parses
///   /proc/cpuinfo each time (~15 file reads per update, seen with strace), so it is
///   pinned here. The default is 1 thread: on the 2-core reference machine the A2C
///   angle-d2 run does 47k steps/s with 1 thread against 38k with 2 (the actors need
///   the other core).
/// - SAVER's fused PCPN blocks have their own thread count ([`pcpn_threads`]).
pub fn init_process(threads: Option<usize>) {
    let _ = pcpn_threads();
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; it is called before other threads.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 256 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 512 << 20);
    }
    let n = threads.or_else(|| {
        std::env::var("RAYON_NUM_THREADS")
            .ok()
            .and_then(|s| s.parse().ok())
            .filter(|&n: &usize| n > 0)
    });
    std::env::set_var("RAYON_NUM_THREADS", n.unwrap_or(1).to_string());
}
