//! The fast path of SAVER's agent-side gradient. The PCPN is frozen, so only the
//! gradient of L_a + L_mon with respect to the PCPN's input x = [obs, μ, log σ] is
//! needed, never its weight gradients. Forward and backward are written out:
//!
//! forward   h = relu(x·W0 + b0), z = relu(h·W1 + b1), e_jbk = z_bj ⊙ cos(π·i·τ_jbk),
//!           u = relu(e·W2_j + b2_j), q = u·w3_j + b3_j                      (batched over j)
//! losses    dL/dq from the quantile loss and the K×K monotonic pairs, in plain Rust
//! backward  du = dq·w3ᵀ ⊙ 1[u>0], de = du·W2ᵀ, dz = Σ_k de ⊙ cos ⊙ 1[z>0],
//!           dh = dz·W1ᵀ ⊙ 1[h>0], dx = dh·W0ᵀ
//!
//! The agent then gets its gradient from the surrogate Σ μ·dμ + Σ log σ·d(log σ), so
//! candle's autograd handles the agent. `saver_actor_losses` is the reference that a
//! test holds this path to.

use super::kernels;
use crate::config::SaverConfig;
use crate::nets::Pcpn;
use crate::Result;
use candle_core::{Tensor, D};

/// The frozen PCPN with the transposed weights the backward pass needs.
pub struct PcpnGrad {
    /// The network.
    pcpn: Pcpn,
    /// W0ᵀ [256, I].
    w0t: Tensor,
    /// W1ᵀ [d·128, 256].
    w1t: Tensor,
    /// W2ᵀ [d, 64, 128].
    w2t: Tensor,
}

/// Losses and the input gradient of one batch.
pub struct InputGrad {
    /// L_a.
    pub actor_loss: f32,
    /// L_mon (weighted).
    pub mon_loss: f32,
    /// dL/dx [B, I].
    pub dx: Tensor,
}

impl PcpnGrad {
    /// Prepares a frozen PCPN (the transposes are made once).
    pub fn new(pcpn: Pcpn) -> Result<Self> {
        Ok(Self {
            w0t: pcpn.l0.w.t()?.contiguous()?,
            w1t: pcpn.l1.w.t()?.contiguous()?,
            w2t: pcpn.w2.transpose(1, 2)?.contiguous()?,
            pcpn,
        })
    }

    /// The frozen PCPN.
    pub fn pcpn(&self) -> &Pcpn {
        &self.pcpn
    }

    /// Losses and dL/dx for `x` [B, I] (no autograd), targets `state_delta` and
    /// advantages `advantage` ([B, d] row-major), quantiles `taus` [d, B, K] with their
    /// embedding `cos` [d, B, K, 128].
    pub fn input_grad(
        &self,
        x: &Tensor,
        state_delta: &[f32],
        advantage: &[f32],
        taus: &[f32],
        cos: &Tensor,
        cfg: &SaverConfig,
    ) -> Result<InputGrad> {
        let p = &self.pcpn;
        let (d, b, k, _) = cos.dims4()?;
        let x = x.detach();
        // Forward.
        let h = p.l0.forward(&x)?.relu()?; // [B, 256]
        let z = p.l1.forward(&h)?.relu()?; // [B, d·128]
        let e = kernels::embed(&z, cos)?; // [d, B·K, 128]
                                          // u [d, B·K, 64] and q [d·B·K].
        let (u, q) = kernels::head_forward(&e.matmul(&p.w2)?, &p.b2, &p.w3, &p.b3)?;
        // Losses and dL/dq.
        let (actor_loss, mon_loss, dq) = loss_grad(&q, state_delta, advantage, taus, d, b, k, cfg);
        // Backward to x.
        let du = kernels::head_backward(&dq, &u, &p.w3)?; // [d, B·K, 64]
        let de = du.matmul(&self.w2t)?; // [d, B·K, 128]
        let dz = kernels::k_sum(&de, cos)?; // [B, d·128]
        let dz = dz.mul(&z.gt(0.0)?.to_dtype(z.dtype())?)?;
        let dh = dz
            .matmul(&self.w1t)?
            .mul(&h.gt(0.0)?.to_dtype(h.dtype())?)?;
        let dx = dh.matmul(&self.w0t)?;
        Ok(InputGrad {
            actor_loss,
            mon_loss,
            dx,
        })
    }
}

/// SAVER's agent-side losses and their gradient with respect to q [d, B, K].
///
/// L_a = Σ ρ_τ(Δp − q)·Â / (B·K·d), so dL_a/dq = −ρ'_τ(δ)·Â / (B·K·d);
/// L_mon = λ·2K/(B·K·K·d) Σ_{τ_i<τ_k} Huber_1(relu(q_i − q_k)), whose pair gradient is
/// ±min(v, 1) for v = q_i − q_k > 0.
#[allow(clippy::too_many_arguments)]
fn loss_grad(
    q: &[f32],
    state_delta: &[f32],
    advantage: &[f32],
    taus: &[f32],
    d: usize,
    b: usize,
    k: usize,
    cfg: &SaverConfig,
) -> (f32, f32, Vec<f32>) {
    let mut dq = vec![0.0f32; q.len()];
    let qn = 1.0 / (b * k * d) as f64;
    let mn = cfg.lambda_mon * 2.0 * k as f64 / (b * k * k * d) as f64;
    let (mut la, mut lm) = (0.0f64, 0.0f64);
    let mnf = mn as f32;
    let mut order: Vec<usize> = Vec::with_capacity(k);
    for j in 0..d {
        for bi in 0..b {
            let row = (j * b + bi) * k;
            let target = state_delta[bi * d + j];
            let adv = advantage[bi * d + j];
            let (qs, ts, gs) = (&q[row..row + k], &taus[row..row + k], &mut dq[row..row + k]);
            for i in 0..k {
                let delta = target - qs[i];
                let w = ts[i] - if delta < 0.0 { 1.0 } else { 0.0 };
                let (rho, drho) = match cfg.kappa {
                    None => (w * delta, w),
                    Some(kappa) => {
                        let kappa = kappa as f32;
                        let (l, dl) = if delta.abs() <= kappa {
                            (0.5 * delta * delta, delta)
                        } else {
                            (kappa * (delta.abs() - 0.5 * kappa), kappa * delta.signum())
                        };
                        (w.abs() * l / kappa, w.abs() * dl / kappa)
                    }
                };
                la += (rho * adv) as f64;
                gs[i] += (-(drho * adv) as f64 * qn) as f32;
            }
            if cfg.lambda_mon != 0.0 {
                // Pairs in ascending τ, each once, without branches: with c = clamp(v, 0,
                // 1) for v = q_a − q_b, Huber_1(relu(v)) = c·(v − c/2) and its slope is c
                // (c = 0 also when the τ are equal, which the strict < excludes).
                order.clear();
                order.extend(0..k);
                order.sort_unstable_by(|&x, &y| ts[x].total_cmp(&ts[y]));
                let mut row_loss = 0.0f32;
                for a in 0..k {
                    let ia = order[a];
                    let (qa, ta) = (qs[ia], ts[ia]);
                    let mut ga = 0.0f32;
                    for &ib in &order[a + 1..] {
                        let v = qa - qs[ib];
                        let c = v.clamp(0.0, 1.0) * f32::from(u8::from(ta < ts[ib]));
                        row_loss += c * (v - 0.5 * c);
                        let g = c * mnf;
                        ga += g;
                        gs[ib] -= g;
                    }
                    gs[ia] += ga;
                }
                lm += row_loss as f64;
            }
        }
    }
    ((la * qn) as f32, (lm * mn) as f32, dq)
}

/// Splits dL/dx [B, I] into the parts for μ [B, M] and log σ [B, L].
pub fn policy_grads(dx: &Tensor, obs_dim: usize, mu_dim: usize) -> Result<(Tensor, Tensor)> {
    let i = dx.dim(D::Minus1)?;
    Ok((
        dx.narrow(1, obs_dim, mu_dim)?,
        dx.narrow(1, obs_dim + mu_dim, i - obs_dim - mu_dim)?,
    ))
}
