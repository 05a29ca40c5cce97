//! Training a quantile network of the PCPN's architecture (docs/ALGORITHM.md §9, §14) on
//! the hand-written path: the loss Σ ρ_τ(y − Q(x, τ))·w / (B·K·d) (+ the monotonic
//! penalty) over targets y [B, d] with weights w [B, d], and the gradients of every
//! variable of the network.
//!
//! ```text
//! trunk  h = relu(x·W0 + b0), z = relu(h·W1 + b1)           (candle, B rows)
//! heads  the fused blocks of fused.rs over the B·K·d rows: losses, dz = dL/dz and
//!        the heads' weight gradients, never materialising anything B·K·d·128 large
//! trunk  gradients from the surrogate Σ z·dz (dz held constant)
//! ```
//!
//! PCPN pretraining is this with w = 1 and the plain loss (y = Δp, x = [o, μ, log σ]);
//! standalone QRRL is this with y = the action taken, x = o and w = its advantage.

use super::fused::{self, Heads, Loss};
use crate::nets::Pcpn;
use crate::{CoreError, Result};
use candle_core::backprop::GradStore;
use candle_core::Tensor;

/// The losses of one batch and the gradients of all of `net`'s variables (and of
/// whatever `extra`, a scalar loss added to the same backward pass, depends on).
pub struct NetGrads {
    /// Σ ρ·w / (B·K·d).
    pub quantile_loss: f32,
    /// The weighted monotonic penalty (0 when λ_mon = 0).
    pub mon_loss: f32,
    /// Gradients by variable.
    pub grads: GradStore,
}

/// See the module docs. `x` [B, I], `target` and `weight` [B, d] row-major, `taus`
/// [d, B, K], `tau_base` s of a base quantile function s·(2τ − 1) added to the outputs
/// (0: none); the blocks run on `threads` threads (0: one per core) with the same bits
/// on any number.
#[allow(clippy::too_many_arguments)]
pub fn quantile_net_grads(
    net: &Pcpn,
    x: &Tensor,
    target: &[f32],
    weight: &[f32],
    taus: &[f32],
    loss: Loss,
    tau_base: f32,
    threads: usize,
    extra: Option<&Tensor>,
) -> Result<NetGrads> {
    let (b, d) = (x.dim(0)?, net.dim());
    let dev = x.device();
    let h = net.l0.forward(x)?.relu()?; // [B, 256]
    let z = net.l1.forward(&h)?.relu()?; // [B, d·128]
    let zv: Vec<f32> = z.flatten_all()?.to_vec1()?;
    let inputs = fused::Inputs {
        z: &zv,
        state_delta: target,
        advantage: weight,
        taus,
        tau_base,
        b,
        k: taus.len() / (b * d).max(1),
        d,
    };
    let out = fused::run(&Heads::of(net)?, &inputs, loss, threads, true);
    let dz = Tensor::from_vec(out.dz, z.shape(), dev)?;
    let mut total = (z * dz)?.sum_all()?;
    if let Some(e) = extra {
        total = (total + e)?;
    }
    let mut grads = total.backward()?;
    let g = out
        .head_grads
        .ok_or_else(|| CoreError::Config("the fused blocks gave no head gradients".into()))?;
    for (var, values) in [
        (&net.w2, g.w2),
        (&net.b2, g.b2),
        (&net.w3, g.w3),
        (&net.b3, g.b3),
    ] {
        grads.insert(var, Tensor::from_vec(values, var.shape(), dev)?);
    }
    Ok(NetGrads {
        quantile_loss: out.actor_loss,
        mon_loss: out.mon_loss,
        grads,
    })
}
