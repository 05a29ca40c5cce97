//! The dense kernels of the fused blocks (fused.rs), one thread each: a gemm call over
//! row-major slices in any operand layout, and a dot product that vectorises.

/// dst [m, n] = lhs [m, kk] · rhs [kk, n], all row-major, where `(lhs_t, rhs_t)` say
/// that an operand is given as its transpose (lhs as a row-major [kk, m], rhs as a
/// row-major [n, kk]). One thread (the blocks are the parallelism).
pub(crate) fn matmul(
    dst: &mut [f32],
    lhs: &[f32],
    rhs: &[f32],
    (m, kk, n): (usize, usize, usize),
    (lhs_t, rhs_t): (bool, bool),
) {
    assert!(dst.len() == m * n && lhs.len() == m * kk && rhs.len() == kk * n);
    // (column stride, row stride) of each operand as an [rows, cols] matrix.
    let (lhs_cs, lhs_rs) = if lhs_t { (m, 1) } else { (1, kk) };
    let (rhs_cs, rhs_rs) = if rhs_t { (kk, 1) } else { (1, n) };
    // SAFETY: the three slices hold exactly the elements the strides address (asserted
    // above), dst does not alias the inputs (&mut), and with read_dst = false gemm only
    // writes dst: dst = 0·dst + 1·lhs·rhs.
    unsafe {
        gemm::gemm(
            m,
            n,
            kk,
            dst.as_mut_ptr(),
            1,
            n as isize,
            false,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            0.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// A dot product with eight independent partial sums, so that it vectorises.
#[inline(always)]
pub(crate) fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for l in 0..8 {
            acc[l] += x[l] * y[l];
        }
    }
    acc.iter().sum::<f32>() + tail
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matmul_matches_by_hand_in_every_layout() {
        // [1 2 3; 4 5 6] · [1 0; 0 1; 1 1] = [4 5; 10 11] (by hand).
        let lhs = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        let rhs = [1.0, 0.0, 0.0, 1.0, 1.0, 1.0];
        let mut dst = [f32::NAN; 4]; // never read: read_dst = false
        matmul(&mut dst, &lhs, &rhs, (2, 3, 2), (false, false));
        assert_eq!(dst, [4.0, 5.0, 10.0, 11.0]);
        // The same rhs given as its transpose [2, 3] = [1 0 1; 0 1 1].
        let rhs_t = [1.0, 0.0, 1.0, 0.0, 1.0, 1.0];
        let mut dst = [f32::NAN; 4];
        matmul(&mut dst, &lhs, &rhs_t, (2, 3, 2), (false, true));
        assert_eq!(dst, [4.0, 5.0, 10.0, 11.0]);
        // The same lhs given as its transpose [3, 2] = [1 4; 2 5; 3 6].
        let lhs_t = [1.0, 4.0, 2.0, 5.0, 3.0, 6.0];
        let mut dst = [f32::NAN; 4];
        matmul(&mut dst, &lhs_t, &rhs, (2, 3, 2), (true, false));
        assert_eq!(dst, [4.0, 5.0, 10.0, 11.0]);
    }
}
