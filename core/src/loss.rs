//! The losses (docs/ALGORITHM.md §4, §5), as candle tensor functions (element-wise, no
//! reduction) and as scalar functions with their derivatives (what the fused SAVER
//! path calls per quantile):
//!
//! - quantile loss ρ_τ(δ) = (τ − 1{δ<0})·δ; Huber variant |τ − 1{δ<0}|·L_κ(δ)/κ;
//! - monotonic penalty Huber_{κ=1}(relu(Q(τ_i) − Q(τ_k))) on pairs with τ_i < τ_k.

use candle_core::{Tensor, D};

/// Standard Huber with κ: 0.5·x² for |x| ≤ κ, κ·(|x| − κ/2) beyond.
pub fn huber(x: &Tensor, kappa: f64) -> candle_core::Result<Tensor> {
    let abs = x.abs()?;
    let small = abs.le(kappa)?;
    let quad = (x.sqr()? * 0.5)?;
    let lin = ((abs - kappa / 2.0)? * kappa)?;
    small.where_cond(&quad, &lin)
}

/// Element-wise quantile loss of errors `delta` at quantiles `tau` (same shape or
/// broadcastable). `kappa = None`: plain ρ_τ; `Some(κ)`: the Huber quantile loss
/// |τ − 1{δ<0}|·L_κ(δ)/κ, which tends to ρ_τ as κ → 0.
pub fn quantile_loss(
    delta: &Tensor,
    tau: &Tensor,
    kappa: Option<f64>,
) -> candle_core::Result<Tensor> {
    // The indicator is piecewise constant: no gradient flows through it.
    let below = delta.lt(0.0)?.to_dtype(delta.dtype())?.detach();
    let weight = tau.broadcast_sub(&below)?;
    match kappa {
        None => weight.broadcast_mul(delta),
        Some(k) => weight.abs()?.broadcast_mul(&(huber(delta, k)? / k)?),
    }
}

/// Monotonic penalty of quantile estimates `q` with their quantiles `tau`, both of
/// shape [.., K]: returns [.., K, K] with entry (i, k) = Huber_1(relu(q_i − q_k)) where
/// τ_i < τ_k and 0 elsewhere. docs/ALGORITHM.md §5 reduces it as λ·2K·mean.
pub fn monotonic_penalty(q: &Tensor, tau: &Tensor) -> candle_core::Result<Tensor> {
    let k = q.dim(D::Minus1)?;
    let mut shape = q.dims().to_vec();
    shape.push(k);
    let qi = q.unsqueeze(D::Minus1)?.broadcast_as(shape.as_slice())?;
    let qk = q.unsqueeze(D::Minus2)?.broadcast_as(shape.as_slice())?;
    let ti = tau.unsqueeze(D::Minus1)?.broadcast_as(shape.as_slice())?;
    let tk = tau.unsqueeze(D::Minus2)?.broadcast_as(shape.as_slice())?;
    let ordered = ti.lt(&tk)?.to_dtype(q.dtype())?.detach();
    let violation = (qi - qk)?.relu()?;
    huber(&violation, 1.0)? * ordered
}

/// The quantile loss of one residual δ at τ (`kappa`: the Huber variant) and its
/// derivative in δ: (ρ, dρ/dδ). The scalar form of [`quantile_loss`].
#[inline(always)]
pub fn quantile_rho(delta: f32, tau: f32, kappa: Option<f32>) -> (f32, f32) {
    let w = tau - if delta < 0.0 { 1.0 } else { 0.0 };
    match kappa {
        None => (w * delta, w),
        Some(kappa) => {
            let (l, dl) = if delta.abs() <= kappa {
                (0.5 * delta * delta, delta)
            } else {
                (kappa * (delta.abs() - 0.5 * kappa), kappa * delta.signum())
            };
            (w.abs() * l / kappa, w.abs() * dl / kappa)
        }
    }
}

/// Huber_1(relu(v)) of one ordered pair's violation v = q_a − q_b and its slope in v:
/// with c = clamp(v, 0, 1), (c·(v − c/2), c). The scalar form of one entry of
/// [`monotonic_penalty`].
#[inline(always)]
pub fn pair_penalty(v: f32) -> (f32, f32) {
    let c = v.clamp(0.0, 1.0);
    (c * (v - 0.5 * c), c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scalar_losses_by_hand_and_equal_to_the_tensor_forms() {
        // ρ: δ = 0.5, τ = 0.25: w = 0.25, ρ = 0.125, ρ' = 0.25;
        //    δ = -0.5, τ = 0.25: w = -0.75, ρ = 0.375, ρ' = -0.75.
        assert_eq!(quantile_rho(0.5, 0.25, None), (0.125, 0.25));
        assert_eq!(quantile_rho(-0.5, 0.25, None), (0.375, -0.75));
        // Huber, κ = 1: δ = 0.5, τ = 0.25: |w| = 0.25, L = 0.125, L' = 0.5 →
        // (0.03125, 0.125); δ = -2: |w| = 0.75, L = 1·(2 − 0.5) = 1.5, L' = -1 →
        // (1.125, -0.75).
        assert_eq!(quantile_rho(0.5, 0.25, Some(1.0)), (0.03125, 0.125));
        assert_eq!(quantile_rho(-2.0, 0.25, Some(1.0)), (1.125, -0.75));
        // Pairs: v = 0.5 → c = 0.5: 0.5·(0.5 − 0.25) = 0.125; v = 3 → c = 1:
        // 3 − 0.5 = 2.5; v = -1: nothing.
        assert_eq!(pair_penalty(0.5), (0.125, 0.5));
        assert_eq!(pair_penalty(3.0), (2.5, 1.0));
        assert_eq!(pair_penalty(-1.0).0, 0.0);
        // The tensor forms give the same values.
        let (d, tau) = ([0.5f32, -0.5, -2.0, 0.03], [0.25f32, 0.25, 0.25, 0.9]);
        for kappa in [None, Some(1.0), Some(0.01)] {
            let t = quantile_loss(&t(&d), &t(&tau), kappa)
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            for i in 0..4 {
                let (rho, _) = quantile_rho(d[i], tau[i], kappa.map(|k| k as f32));
                assert!(
                    (rho - t[i]).abs() <= 1e-6 * t[i].abs().max(1.0),
                    "{kappa:?} {i}"
                );
            }
        }
        let v = [0.5f32, 3.0, -1.0];
        let h = huber(&t(&v).relu().unwrap(), 1.0)
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        for i in 0..3 {
            assert_eq!(pair_penalty(v[i]).0.max(0.0), h[i]);
        }
    }
    use candle_core::Device;

    fn t(v: &[f32]) -> Tensor {
        Tensor::from_slice(v, v.len(), &Device::Cpu).unwrap()
    }

    #[test]
    fn quantile_loss_by_hand() {
        // ρ_τ(δ) = (τ − 1{δ<0})·δ:
        //   τ = 0.3, δ =  2   → 0.3·2           = 0.6
        //   τ = 0.3, δ = −2   → (0.3 − 1)·(−2)  = 1.4
        //   τ = 0.9, δ = −0.5 → (−0.1)·(−0.5)   = 0.05
        //   τ = 0.9, δ =  0   → 0
        let l = quantile_loss(&t(&[2., -2., -0.5, 0.]), &t(&[0.3, 0.3, 0.9, 0.9]), None)
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let want = [0.6f32, 1.4, 0.05, 0.0];
        for (g, w) in l.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{l:?}");
        }
    }

    #[test]
    fn huber_quantile_loss_by_hand() {
        // κ = 0.01: |τ − 1{δ<0}|·L_κ(δ)/κ.
        //   δ = 0.005 (inside):  L = 0.5·0.005² = 1.25e-5, /κ = 1.25e-3, ·τ(0.3) = 3.75e-4
        //   δ = −2 (outside):    L = 0.01·(2 − 0.005) = 0.01995, /κ = 1.995, ·0.7 = 1.3965
        let l = quantile_loss(&t(&[0.005, -2.]), &t(&[0.3, 0.3]), Some(0.01))
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!((l[0] - 3.75e-4).abs() < 1e-8, "{l:?}");
        assert!((l[1] - 1.3965).abs() < 1e-5, "{l:?}");
    }

    #[test]
    fn quantile_loss_gradient_is_tau_minus_indicator() {
        // dρ/dδ = τ − 1{δ<0}: at δ = (1, −1), τ = 0.25 → (0.25, −0.75).
        let d = candle_core::Var::from_slice(&[1f32, -1.], 2, &Device::Cpu).unwrap();
        let l = quantile_loss(d.as_tensor(), &t(&[0.25, 0.25]), None)
            .unwrap()
            .sum_all()
            .unwrap();
        let g = l.backward().unwrap();
        let g = g.get(d.as_tensor()).unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(g, vec![0.25, -0.75]);
    }

    #[test]
    fn monotonic_penalty_k3_by_hand() {
        // K = 3, τ = (0.2, 0.7, 0.5), q = (1.0, 0.4, 2.5).
        // Ordered pairs (i, k) with τ_i < τ_k: (0,1), (0,2), (2,1).
        //   (0,1): relu(1.0 − 0.4) = 0.6 → Huber_1 = 0.5·0.36 = 0.18
        //   (0,2): relu(1.0 − 2.5) = 0   → 0
        //   (2,1): relu(2.5 − 0.4) = 2.1 → Huber_1 = 2.1 − 0.5 = 1.6
        // Every other entry is 0; the sum is 1.78 and SPEC's λ·2K·mean over K·K = 9
        // entries is 1·6·1.78/9 = 1.186666…
        let p = monotonic_penalty(&t(&[1.0, 0.4, 2.5]), &t(&[0.2, 0.7, 0.5])).unwrap();
        assert_eq!(p.dims(), &[3, 3]);
        let m = p.to_vec2::<f32>().unwrap();
        let want = [[0.0, 0.18, 0.0], [0.0, 0.0, 0.0], [0.0, 1.6, 0.0]];
        for (gr, wr) in m.iter().zip(want) {
            for (g, w) in gr.iter().zip(wr) {
                assert!((g - w).abs() < 1e-6, "{m:?}");
            }
        }
        let reduced = (p.mean_all().unwrap() * 6.0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!((reduced - 1.186_666_7).abs() < 1e-5);
    }
}
