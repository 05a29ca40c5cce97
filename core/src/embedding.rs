//! Cosine embedding of a quantile target: e_i(τ) = cos(π·i·τ), i = 1..=n (n = 128).
//!
//! Computed with the Chebyshev recurrence cos(i·x) = 2·cos(x)·cos((i-1)·x) − cos((i-2)·x)
//! in f64 (one `cos` per τ instead of n), then rounded to f32.

/// Embedding width of the PCPN (docs/ALGORITHM.md §3: 128).
pub const EMBED_DIM: usize = 128;

/// Writes cos(π·i·τ) for i = 1..=out.len() into `out`.
pub fn cosine_embedding_into(tau: f32, out: &mut [f32]) {
    let c1 = (std::f64::consts::PI * tau as f64).cos();
    let (mut prev, mut cur) = (1.0f64, c1); // cos(0·x), cos(1·x)
    for o in out.iter_mut() {
        *o = cur as f32;
        let next = 2.0 * c1 * cur - prev;
        prev = cur;
        cur = next;
    }
}

/// The embedding of every τ: [taus.len(), width], row-major.
pub fn cosine_embedding(taus: &[f32], width: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; taus.len() * width];
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just now).
        unsafe { embedding_avx2(taus, width, &mut out) };
        return out;
    }
    cosine_embedding_lanes(taus, width, &mut out);
    out
}

/// [`cosine_embedding_lanes`] compiled with AVX2 (four f64 lanes per instruction
/// instead of two); no `mul_add` is written, so the bits are the same.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn embedding_avx2(taus: &[f32], width: usize, out: &mut [f32]) {
    cosine_embedding_lanes(taus, width, out)
}

/// [`cosine_embedding`] into `out` ([taus.len(), width]): the same recurrence as
/// [`cosine_embedding_into`], run for `LANES` values of τ side by side. One τ's
/// recurrence is a chain of dependent multiply-adds, so eight independent chains keep
/// the FPU busy and vectorise, with bit-identical results (it was 16 % of a SAVER
/// update at d = 4 in a perf profile as a single chain). Always inlined, so a caller
/// compiled with other target features (the fused PCPN blocks) gets it compiled with
/// them.
#[inline(always)]
pub(crate) fn cosine_embedding_lanes(taus: &[f32], width: usize, out: &mut [f32]) {
    const LANES: usize = 8;
    assert_eq!(out.len(), taus.len() * width, "embedding buffer size");
    let mut rows = out.chunks_exact_mut(width * LANES);
    let mut groups = taus.chunks_exact(LANES);
    for (block, group) in (&mut rows).zip(&mut groups) {
        let mut c1 = [0.0f64; LANES];
        for (c, &tau) in c1.iter_mut().zip(group) {
            *c = (std::f64::consts::PI * tau as f64).cos();
        }
        let (mut prev, mut cur) = ([1.0f64; LANES], c1);
        for i in 0..width {
            for l in 0..LANES {
                block[l * width + i] = cur[l] as f32;
                let next = 2.0 * c1[l] * cur[l] - prev[l];
                prev[l] = cur[l];
                cur[l] = next;
            }
        }
    }
    for (row, &tau) in rows
        .into_remainder()
        .chunks_exact_mut(width)
        .zip(groups.remainder())
    {
        cosine_embedding_into(tau, row);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_direct_cosines() {
        // τ = 0.25: cos(π/4) = 0.70710678, cos(π/2) = 0, cos(3π/4) = −0.70710678,
        // cos(π) = −1, cos(5π/4) = −0.70710678 (by hand from the unit circle).
        let e = cosine_embedding(&[0.25], 5);
        let want = [0.707_106_77, 0.0, -0.707_106_77, -1.0, -0.707_106_77];
        for (g, w) in e.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{e:?}");
        }
        // τ = 0 gives all ones; τ = 1 alternates −1, +1 (cos(iπ) = (−1)^i).
        assert!(cosine_embedding(&[0.0], 4).iter().all(|&x| x == 1.0));
        assert_eq!(cosine_embedding(&[1.0], 4), vec![-1.0, 1.0, -1.0, 1.0]);
        // The eight-lane path equals the one-τ recurrence bit for bit (19 τ: two
        // blocks of eight and a remainder of three).
        let taus: Vec<f32> = (0..19).map(|i| i as f32 / 19.0).collect();
        let mut one = vec![0.0f32; 19 * 128];
        for (row, &t) in one.chunks_exact_mut(128).zip(&taus) {
            cosine_embedding_into(t, row);
        }
        assert_eq!(cosine_embedding(&taus, 128), one);
    }

    #[test]
    fn recurrence_stays_accurate_to_128() {
        // Against f64 `cos` for every i up to 128 at awkward τ values.
        for &tau in &[0.013f32, 0.37, 0.5, 0.918, 0.999] {
            let e = cosine_embedding(&[tau], EMBED_DIM);
            for (i, &g) in e.iter().enumerate() {
                let w = (std::f64::consts::PI * (i + 1) as f64 * tau as f64).cos();
                assert!((g as f64 - w).abs() < 1e-6, "tau {tau} i {}", i + 1);
            }
        }
    }
}
