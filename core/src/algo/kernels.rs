//! Two fused CPU loops of the PCPN's cosine step, where candle would materialise
//! broadcasts, transposes and a reduction over a middle axis:
//!
//! - `embed`:   e[j, b, k, :] = z[b, j·128 .. (j+1)·128] ⊙ cos[j, b, k, :]
//! - `k_sum`:   dz[b, j·128 + i] = Σ_k de[j, b, k, i] · cos[j, b, k, i]
//!
//! On other devices they fall back to the equivalent candle ops.

use crate::Result;
use candle_core::{Storage, Tensor};

/// Runs `f` on the row-major f32 data of two CPU tensors (made contiguous first);
/// `None` when they are not on the CPU.
fn with_two<R>(a: &Tensor, b: &Tensor, f: impl FnOnce(&[f32], &[f32]) -> R) -> Result<Option<R>> {
    if !a.device().is_cpu() || !b.device().is_cpu() {
        return Ok(None);
    }
    let (a, b) = (a.contiguous()?, b.contiguous()?);
    let (sa, la) = a.storage_and_layout();
    let (sb, lb) = b.storage_and_layout();
    match (&*sa, &*sb) {
        (Storage::Cpu(ca), Storage::Cpu(cb)) => {
            let xa = &ca.as_slice::<f32>()?[la.start_offset()..][..a.elem_count()];
            let xb = &cb.as_slice::<f32>()?[lb.start_offset()..][..b.elem_count()];
            Ok(Some(f(xa, xb)))
        }
        _ => Ok(None),
    }
}

/// e [d, B·K, w] from z [B, d·w] and cos [d, B, K, w].
pub fn embed(z: &Tensor, cos: &Tensor) -> Result<Tensor> {
    let (d, b, k, w) = cos.dims4()?;
    let out = with_two(z, cos, |z, c| {
        let mut e = vec![0.0f32; d * b * k * w];
        for j in 0..d {
            for bi in 0..b {
                let zrow = &z[bi * d * w + j * w..bi * d * w + (j + 1) * w];
                for kk in 0..k {
                    let off = ((j * b + bi) * k + kk) * w;
                    for ((o, &c), &zv) in e[off..off + w].iter_mut().zip(&c[off..off + w]).zip(zrow)
                    {
                        *o = c * zv;
                    }
                }
            }
        }
        e
    })?;
    match out {
        Some(e) => Ok(Tensor::from_vec(e, (d, b * k, w), z.device())?),
        None => {
            let zt = z.reshape((b, d, w))?.transpose(0, 1)?.unsqueeze(2)?;
            Ok(zt.broadcast_mul(cos)?.reshape((d, b * k, w))?)
        }
    }
}

/// dz [B, d·w] = Σ_k de ⊙ cos, from de [d, B·K, w] and cos [d, B, K, w].
pub fn k_sum(de: &Tensor, cos: &Tensor) -> Result<Tensor> {
    let (d, b, k, w) = cos.dims4()?;
    let out = with_two(de, cos, |g, c| {
        let mut dz = vec![0.0f32; b * d * w];
        for j in 0..d {
            for bi in 0..b {
                let acc = &mut dz[bi * d * w + j * w..bi * d * w + (j + 1) * w];
                for kk in 0..k {
                    let off = ((j * b + bi) * k + kk) * w;
                    for ((a, &gv), &cv) in
                        acc.iter_mut().zip(&g[off..off + w]).zip(&c[off..off + w])
                    {
                        *a += gv * cv;
                    }
                }
            }
        }
        dz
    })?;
    match out {
        Some(dz) => Ok(Tensor::from_vec(dz, (b, d * w), de.device())?),
        None => {
            let dzt = de.reshape((d, b, k, w))?.mul(cos)?.sum(2)?;
            Ok(dzt.transpose(0, 1)?.reshape((b, d * w))?)
        }
    }
}

/// The per-dimension head after its first matmul: from m = e·W2 [d, R, h] (no bias),
/// u = relu(m + b2) and q = u·w3 + b3, with b2 [d, 1, h], w3 [d, h, 1], b3 [d, 1, 1].
/// Returns u [d, R, h] and q [d·R].
pub fn head_forward(
    m: &Tensor,
    b2: &Tensor,
    w3: &Tensor,
    b3: &Tensor,
) -> Result<(Tensor, Vec<f32>)> {
    let (d, r, h) = m.dims3()?;
    let (b2v, w3v, b3v): (Vec<f32>, Vec<f32>, Vec<f32>) = (
        b2.flatten_all()?.to_vec1()?,
        w3.flatten_all()?.to_vec1()?,
        b3.flatten_all()?.to_vec1()?,
    );
    let out = with_two(m, m, |mv, _| {
        let mut u = vec![0.0f32; d * r * h];
        let mut q = vec![0.0f32; d * r];
        for j in 0..d {
            let (bias, w) = (&b2v[j * h..(j + 1) * h], &w3v[j * h..(j + 1) * h]);
            for row in 0..r {
                let off = (j * r + row) * h;
                let urow = &mut u[off..off + h];
                for ((o, &x), &bb) in urow.iter_mut().zip(&mv[off..off + h]).zip(bias) {
                    *o = (x + bb).max(0.0);
                }
                q[j * r + row] = dot(urow, w) + b3v[j];
            }
        }
        (u, q)
    })?;
    match out {
        Some((u, q)) => Ok((Tensor::from_vec(u, (d, r, h), m.device())?, q)),
        None => {
            let u = m.broadcast_add(b2)?.relu()?;
            let q = u.matmul(w3)?.broadcast_add(b3)?.flatten_all()?.to_vec1()?;
            Ok((u, q))
        }
    }
}

/// The head's backward to its hidden layer: du[j, r, c] = dq[j, r]·w3[j, c]·1[u > 0].
pub fn head_backward(dq: &[f32], u: &Tensor, w3: &Tensor) -> Result<Tensor> {
    let (d, r, h) = u.dims3()?;
    let w3v: Vec<f32> = w3.flatten_all()?.to_vec1()?;
    let out = with_two(u, u, |uv, _| {
        // Written in order with no zero fill first, the mask a multiply, so it vectorises.
        let mut du = Vec::with_capacity(d * r * h);
        for j in 0..d {
            let w = &w3v[j * h..(j + 1) * h];
            for row in 0..r {
                let g = dq[j * r + row];
                let off = (j * r + row) * h;
                du.extend(
                    uv[off..off + h]
                        .iter()
                        .zip(w)
                        .map(|(&a, &ww)| g * ww * f32::from(u8::from(a > 0.0))),
                );
            }
        }
        du
    })?;
    match out {
        Some(du) => Ok(Tensor::from_vec(du, (d, r, h), u.device())?),
        None => {
            let dq = Tensor::from_slice(dq, (d, r, 1), u.device())?;
            Ok(dq
                .matmul(&w3.transpose(1, 2)?)?
                .mul(&u.gt(0.0)?.to_dtype(u.dtype())?)?)
        }
    }
}

/// A dot product with eight independent partial sums, so that it vectorises.
fn dot(a: &[f32], b: &[f32]) -> f32 {
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
