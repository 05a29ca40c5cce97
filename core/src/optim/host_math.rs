//! Host arithmetic the optimiser's CPU steps are made of: the subnormal flush, the
//! vectorised sum of squares every norm uses, a tensor's elements on the host, and an
//! optional `rayon::join`. Nothing here knows an optimiser.

use crate::Result;
use candle_core::Tensor;

/// `x`, or 0 where it is below f32's smallest normal (1.2e-38). A weight whose gradient
/// stays 0 (a ReLU unit that no row reaches) decays its slots geometrically into
/// subnormals, where each multiply or square root takes ~100 cycles instead of a few:
/// after 65 k steps of PPO on angle d = 2, 11 % of the Adam slots were subnormal and the
/// optimiser's step took 46 % of the run (perf). The flush cannot move a weight above
/// ~1e-25 in size: with |m| < 1.2e-38 and ε = 1e-8 Adam's step lr_t·m/(√v + ε) is below
/// 1e-33, under half an ulp of such a weight, and a subnormal v or ms is below the ulp of
/// the ε it is added to. The tensor path (off the CPU) keeps its subnormals.
#[inline(always)]
pub(crate) fn flush_subnormal(x: f32) -> f32 {
    if x.abs() < f32::MIN_POSITIVE {
        0.0
    } else {
        x
    }
}

/// Σ x² in f64: eight partial sums over the elements i ≡ 0..7 (mod 8) in order, then
/// added in order, so that the loop vectorises (it was 7 % of PPO's hand-written
/// update as one chain). Every norm on the CPU is summed this way, so the host and
/// tensor paths still clip alike to the bit.
pub(crate) fn sum_sq(x: &[f32]) -> f64 {
    let mut acc = [0.0f64; 8];
    let chunks = x.chunks_exact(8);
    let tail: f64 = chunks
        .remainder()
        .iter()
        .map(|&v| v as f64 * v as f64)
        .sum();
    for c in chunks {
        for l in 0..8 {
            acc[l] += c[l] as f64 * c[l] as f64;
        }
    }
    acc.iter().sum::<f64>() + tail
}

/// A tensor's elements on the host, row-major.
pub(crate) fn to_host(x: &Tensor) -> Result<Vec<f32>> {
    Ok(x.flatten_all()?.to_vec1::<f32>()?)
}

/// `(a(), b())`: side by side by `rayon::join` when `parallel` (on the pool whose
/// `install` runs the caller, else on rayon's global pool), else in turn on this thread.
pub(crate) fn join_if<RA: Send, RB: Send>(
    parallel: bool,
    a: impl FnOnce() -> RA + Send,
    b: impl FnOnce() -> RB + Send,
) -> (RA, RB) {
    if parallel {
        rayon::join(a, b)
    } else {
        (a(), b())
    }
}

/// A rayon pool of two threads for one update's hand-off steps (a third thread would
/// only wait: every hand-off is two-way); none, with a warning naming `whose` update,
/// when the OS refuses threads (the update then runs on one, the same bits).
pub(crate) fn pool_of_two(whose: &str) -> Option<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .map_err(|e| tracing::warn!("{whose} update runs on one thread: {e}"))
        .ok()
}
