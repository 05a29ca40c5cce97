//! The fast path of SAVER's agent-side gradient. The PCPN is frozen, so only the
//! gradient of L_a + L_mon with respect to the PCPN's input x = [obs, μ, log σ] is
//! needed, never its weight gradients. Forward and backward are written out:
//!
//! forward   h = relu(x·W0 + b0), z = relu(h·W1 + b1)                     (candle, B rows)
//!           then per dimension j and τ: the fused blocks of `fused.rs`, which give
//!           the losses and dz = dL/dz without materialising anything B·K·d·128 large
//! backward  dh = (dz ⊙ 1[z>0])·W1ᵀ ⊙ 1[h>0], dx = dh·W0ᵀ                  (candle)
//!
//! The agent then gets its gradient from the surrogate Σ μ·dμ + Σ log σ·d(log σ), so
//! candle's autograd handles the agent. [`saver_actor_losses`], at the end of this
//! file, is the reference through candle autograd that a test holds this path to (and
//! the path on devices other than the CPU).

use crate::algo::dense::matmul;
use crate::algo::fused::{self, Heads};
use crate::algo::host_mlp::relu_back;
use crate::config::SaverConfig;
use crate::loss::{monotonic_penalty, quantile_loss};
use crate::nets::Pcpn;
use crate::Result;
use candle_core::{Tensor, Var, D};

/// Σ μ·g_μ + Σ log σ·g_log σ over the policy's outputs `mu` and `log_std` (in the
/// agent's graph): its gradient with respect to the agent's weights is that of any loss
/// whose gradient at the outputs is (`g_mu`, `g_ls`). Both gradient paths and the
/// env-return term reach the agent through it.
pub(super) fn surrogate(
    mu: &Tensor,
    log_std: &Tensor,
    g_mu: &Tensor,
    g_ls: &Tensor,
) -> Result<Tensor> {
    Ok(((mu * g_mu)?.sum_all()? + (log_std * g_ls)?.sum_all()?)?)
}

/// Detached copies of the policy's outputs μ and log σ as leaves: a loss computed on them
/// has its gradient there ([`OutputLeaves::grads`]), which [`surrogate`] carries into
/// the agent.
pub(super) struct OutputLeaves {
    pub(super) mu: Var,
    pub(super) log_std: Var,
}

impl OutputLeaves {
    /// Leaves holding the values of `mu` and `log_std`.
    pub(super) fn of(mu: &Tensor, log_std: &Tensor) -> Result<Self> {
        Ok(Self {
            mu: Var::from_tensor(&mu.detach())?,
            log_std: Var::from_tensor(&log_std.detach())?,
        })
    }

    /// The gradient of `loss` at the leaves, (dμ, d log σ); zeros where it does not reach.
    pub(super) fn grads(&self, loss: &Tensor) -> Result<(Tensor, Tensor)> {
        let g = loss.backward()?;
        let at = |v: &Var| -> Result<Tensor> {
            Ok(match g.get(v.as_tensor()) {
                Some(t) => t.clone(),
                None => v.as_tensor().zeros_like()?,
            })
        };
        Ok((at(&self.mu)?, at(&self.log_std)?))
    }
}

/// The frozen PCPN with what the hand-written pass needs: W0ᵀ, W1ᵀ and the heads as
/// plain arrays.
pub struct PcpnGrad {
    /// The network.
    pcpn: Pcpn,
    /// W0ᵀ [256, I].
    w0t: Tensor,
    /// W1ᵀ [d·128, 256].
    w1t: Tensor,
    /// The per-dimension heads, row-major on the host.
    heads: Heads,
    /// The trunk on the host, row-major: W0 [I, 256], b0, W1 [256, d·128], b1.
    trunk: [Vec<f32>; 4],
    /// Threads of the fused blocks (0: one per core).
    threads: usize,
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

/// A tensor's values on the host, row-major.
pub(crate) fn host(t: &Tensor) -> Result<Vec<f32>> {
    Ok(t.flatten_all()?.to_vec1()?)
}

impl Heads {
    /// The current values of a PCPN's heads (of its variables while it trains).
    pub(crate) fn of(pcpn: &Pcpn) -> Result<Self> {
        Ok(Self {
            w2: host(&pcpn.w2)?,
            b2: host(&pcpn.b2)?,
            w3: host(&pcpn.w3)?,
            b3: host(&pcpn.b3)?,
        })
    }
}

impl PcpnGrad {
    /// Prepares a frozen PCPN (the transposes and host copies are made once).
    pub fn new(pcpn: Pcpn) -> Result<Self> {
        Ok(Self {
            w0t: pcpn.l0.w.t()?.contiguous()?,
            w1t: pcpn.l1.w.t()?.contiguous()?,
            heads: Heads::of(&pcpn)?,
            trunk: [
                host(&pcpn.l0.w)?,
                host(&pcpn.l0.b)?,
                host(&pcpn.l1.w)?,
                host(&pcpn.l1.b)?,
            ],
            pcpn,
            threads: 0,
        })
    }

    /// Runs the fused blocks on `n` threads (0: one per core, the default); the
    /// results are the same bits on any number.
    pub fn set_threads(&mut self, n: usize) {
        self.threads = n;
    }

    /// The threads of the fused blocks (0: one per core).
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// The same on `pcpn`'s weights (its thread count kept).
    pub fn refreshed(&self, pcpn: Pcpn) -> Result<Self> {
        let mut g = Self::new(pcpn)?;
        g.threads = self.threads;
        Ok(g)
    }

    /// The frozen PCPN.
    pub fn pcpn(&self) -> &Pcpn {
        &self.pcpn
    }

    /// Losses and dL/dx for `x` [B, I] (no autograd), targets `state_delta` and
    /// advantages `advantage` ([B, d] row-major), quantiles `taus` [d, B, K].
    pub fn input_grad(
        &self,
        x: &Tensor,
        state_delta: &[f32],
        advantage: &[f32],
        taus: &[f32],
        cfg: &SaverConfig,
    ) -> Result<InputGrad> {
        let p = &self.pcpn;
        let (b, d) = (x.dim(0)?, p.dim);
        let x = x.detach();
        let h = p.l0.forward(&x)?.relu()?; // [B, 256]
        let z = p.l1.forward(&h)?.relu()?; // [B, d·128]
        let zv = host(&z)?;
        let batch = fused::Inputs {
            z: &zv,
            state_delta,
            advantage,
            taus,
            tau_base: 0.0,
            b,
            k: taus.len() / (b * d),
            d,
        };
        let out = fused::run(&self.heads, &batch, cfg.into(), self.threads, false);
        let dz = Tensor::from_vec(out.dz, z.shape(), z.device())?;
        let dz = dz.mul(&z.gt(0.0)?.to_dtype(z.dtype())?)?;
        let dh = dz
            .matmul(&self.w1t)?
            .mul(&h.gt(0.0)?.to_dtype(h.dtype())?)?;
        let dx = dh.matmul(&self.w0t)?;
        Ok(InputGrad {
            actor_loss: out.actor_loss,
            mon_loss: out.mon_loss,
            dx,
        })
    }
}

/// The buffers of [`PcpnGrad::input_grad_host`], kept across an update's minibatches.
#[derive(Default)]
pub(super) struct TrunkScratch {
    h: Vec<f32>,
    z: Vec<f32>,
    dh: Vec<f32>,
    /// dL/dx [n, I] of the last call.
    pub(super) dx: Vec<f32>,
}

/// `y` [n, o] = x·W + b for `x` [n, i], ReLU after.
fn relu_layer(y: &mut Vec<f32>, x: &[f32], w: &[f32], b: &[f32], (n, i, o): (usize, usize, usize)) {
    y.resize(n * o, 0.0);
    matmul(y, x, w, (n, i, o), (false, false));
    for row in y.chunks_exact_mut(o) {
        for (v, bias) in row.iter_mut().zip(b) {
            *v = (*v + bias).max(0.0);
        }
    }
}

impl PcpnGrad {
    /// [`PcpnGrad::input_grad`] on host rows `x` [n, I] (row-major), the trunk's
    /// matmuls by gemm: (L_a, L_mon), with dL/dx in `s.dx`. With `pooled` the fused
    /// blocks are tasks of the rayon pool this runs in, else on the PCPN's threads.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn input_grad_host(
        &self,
        x: &[f32],
        n: usize,
        state_delta: &[f32],
        advantage: &[f32],
        taus: &[f32],
        cfg: &SaverConfig,
        s: &mut TrunkScratch,
        pooled: bool,
    ) -> (f32, f32) {
        let [w0, b0, w1, b1] = &self.trunk;
        let (i, hid, wide) = (x.len() / n.max(1), b0.len(), b1.len());
        relu_layer(&mut s.h, x, w0, b0, (n, i, hid));
        relu_layer(&mut s.z, &s.h, w1, b1, (n, hid, wide));
        let batch = fused::Inputs {
            z: &s.z,
            state_delta,
            advantage,
            taus,
            tau_base: 0.0,
            b: n,
            k: taus.len() / (n * self.pcpn.dim),
            d: self.pcpn.dim,
        };
        let mut out = match pooled {
            true => fused::run_in_pool(&self.heads, &batch, cfg.into(), false),
            false => fused::run(&self.heads, &batch, cfg.into(), self.threads, false),
        };
        relu_back(&mut out.dz, &s.z);
        s.dh.resize(n * hid, 0.0);
        matmul(&mut s.dh, &out.dz, w1, (n, wide, hid), (false, true));
        relu_back(&mut s.dh, &s.h);
        s.dx.resize(n * i, 0.0);
        matmul(&mut s.dx, &s.dh, w0, (n, hid, i), (false, true));
        (out.actor_loss, out.mon_loss)
    }
}

/// Splits dL/dx [B, I] into the parts for μ [B, M] and log σ [B, L].
pub fn policy_grads(dx: &Tensor, obs_dim: usize, mu_dim: usize) -> Result<(Tensor, Tensor)> {
    let i = dx.dim(D::Minus1)?;
    Ok((
        dx.narrow(1, obs_dim, mu_dim)?,
        dx.narrow(1, obs_dim + mu_dim, i - obs_dim - mu_dim)?,
    ))
}

// ---- The reference: the same losses through candle autograd.

/// The two agent-side loss terms of one batch (scalars).
pub struct SaverLosses {
    /// L_a.
    pub actor: Tensor,
    /// L_mon (weighted).
    pub mon: Tensor,
}

/// SAVER's agent-side losses for given policy outputs.
///
/// `obs` [B, O], `mu` [B, M], `log_std` [B, L] (gradients flow from here), `state_delta`
/// and `advantage` [B, d] (constants), `tau` [d, B, K] with its embedding `cos`.
#[allow(clippy::too_many_arguments)]
pub fn saver_actor_losses(
    pcpn: &Pcpn,
    obs: &Tensor,
    mu: &Tensor,
    log_std: &Tensor,
    state_delta: &Tensor,
    advantage: &Tensor,
    tau: &Tensor,
    cos: &Tensor,
    cfg: &SaverConfig,
) -> Result<SaverLosses> {
    let x = Tensor::cat(&[obs, mu, log_std], 1)?; // [B, I]
    let q = pcpn.forward(&x, cos)?; // [d, B, K]
    weighted_quantile_losses(&q, state_delta, advantage, tau, cfg)
}

/// The loss both quantile algorithms share, through autograd: quantiles `q` [d, B, K]
/// at `tau`, targets [B, d], weights [B, d] or [B, 1] (one per step):
/// `mean ρ_τ(y − q)·w` and `λ_mon·2K·mean` of the monotonic penalty. The reference of
/// the fused blocks (SAVER: y = Δp, w = Â_j; QRRL: y = the action, w = Â).
pub fn weighted_quantile_losses(
    q: &Tensor,
    target: &Tensor,
    weight: &Tensor,
    tau: &Tensor,
    cfg: &SaverConfig,
) -> Result<SaverLosses> {
    let k = tau.dim(2)?;
    let target = target.t()?.unsqueeze(2)?; // [d, B, 1]
    let w = weight.t()?.unsqueeze(2)?; // [d or 1, B, 1]
    let rho = quantile_loss(&target.broadcast_sub(q)?, tau, cfg.kappa)?;
    let actor = rho.broadcast_mul(&w)?.mean_all()?;
    let mon = (monotonic_penalty(q, tau)?.mean_all()? * (cfg.lambda_mon * 2.0 * k as f64))?;
    Ok(SaverLosses { actor, mon })
}
