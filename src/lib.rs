//! The `saver` command-line tool as a library: each module is one subcommand, so the
//! end-to-end tests can drive a run in-process as well as through the binary.

pub mod bench;
pub mod config;
pub mod plot;
pub mod pretrain;
pub mod progress;
pub mod train;

/// Process-wide set-up, before any thread exists: pins candle's CPU thread count.
///
/// candle reads RAYON_NUM_THREADS at every matmul and, when it is unset, parses
/// /proc/cpuinfo each time (~15 file reads per update, measured with strace). The
/// default is 1 thread: on the 2-core reference machine the A2C angle-d2 run does
/// 47k steps/s with 1 thread against 38k with 2 (actors need the other core).
pub fn init_process(threads: Option<usize>) {
    let n = threads.or_else(|| {
        std::env::var("RAYON_NUM_THREADS")
            .ok()
            .and_then(|s| s.parse().ok())
            .filter(|&n: &usize| n > 0)
    });
    std::env::set_var("RAYON_NUM_THREADS", n.unwrap_or(1).to_string());
}
