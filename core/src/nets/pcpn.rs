//! The position change prediction network (PCPN): x = [obs, μ, log σ] → 256 → d·128,
//! split into d chunks; for dim j with its own τ_j: h_j = chunk_j ⊙ cos(π·i·τ_j),
//! i = 1..128 → 64 (ReLU) → 1, with separate weights per dim. Output: the τ_j-quantile
//! of the change of state-aligned coordinate j.

use super::{Linear, ParamSet};
use crate::env::EnvLayout;
use crate::rng::{glorot_uniform, SaverRng};
use crate::{CoreError, Result};
use candle_core::{Device, Tensor};

/// Width of the shared first layer.
pub const PCPN_HIDDEN: usize = 256;
/// Width of each per-dimension chunk (and of the cosine embedding).
pub const PCPN_CHUNK: usize = crate::embedding::EMBED_DIM;
/// Width of each per-dimension head's hidden layer.
pub const PCPN_HEAD_HIDDEN: usize = 64;

/// The PCPN. Built from variables for pretraining, from plain tensors when frozen:
/// gradients then reach its inputs but never its weights.
#[derive(Clone)]
pub struct Pcpn {
    /// x → 256.
    pub(crate) l0: Linear,
    /// 256 → d·128.
    pub(crate) l1: Linear,
    /// [d, 128, 64]: per-dim first head layer.
    pub(crate) w2: Tensor,
    /// [d, 1, 64].
    pub(crate) b2: Tensor,
    /// [d, 64, 1]: per-dim output layer.
    pub(crate) w3: Tensor,
    /// [d, 1, 1].
    pub(crate) b3: Tensor,
    /// d.
    pub(crate) dim: usize,
}

/// Names of the PCPN tensors, in the order of [`pcpn_shapes`].
const PCPN_NAMES: [&str; 8] = [
    "pcpn.l0.w",
    "pcpn.l0.b",
    "pcpn.l1.w",
    "pcpn.l1.b",
    "pcpn.head.w0",
    "pcpn.head.b0",
    "pcpn.head.w1",
    "pcpn.head.b1",
];

/// Names and shapes of the PCPN tensors for a layout, in a fixed order.
pub fn pcpn_shapes(layout: &EnvLayout) -> Vec<(&'static str, Vec<usize>)> {
    let (i, d) = (layout.pcpn_input_dim(), layout.aligned_dim);
    let shapes = [
        vec![i, PCPN_HIDDEN],
        vec![PCPN_HIDDEN],
        vec![PCPN_HIDDEN, d * PCPN_CHUNK],
        vec![d * PCPN_CHUNK],
        vec![d, PCPN_CHUNK, PCPN_HEAD_HIDDEN],
        vec![d, 1, PCPN_HEAD_HIDDEN],
        vec![d, PCPN_HEAD_HIDDEN, 1],
        vec![d, 1, 1],
    ];
    PCPN_NAMES.into_iter().zip(shapes).collect()
}

impl Pcpn {
    /// A trainable PCPN with fresh Glorot weights; its variables go into `params`.
    pub fn init(
        layout: &EnvLayout,
        rng: &mut SaverRng,
        dev: &Device,
        params: &mut ParamSet,
    ) -> Result<Self> {
        let mut t = Vec::new();
        for (name, shape) in pcpn_shapes(layout) {
            let n: usize = shape.iter().product();
            let is_bias = name.ends_with(".b") || name.starts_with("pcpn.head.b");
            let values = if is_bias {
                vec![0.0; n]
            } else if shape.len() == 3 {
                // One Glorot draw per dim with the head layer's own fans.
                let mut v = Vec::with_capacity(n);
                for _ in 0..shape[0] {
                    v.extend(glorot_uniform(rng, shape[1], shape[2]));
                }
                v
            } else {
                glorot_uniform(rng, shape[0], shape[1])
            };
            t.push(params.var(name, values, &shape, dev)?);
        }
        Self::from_ordered(t, layout.aligned_dim)
    }

    /// A frozen PCPN from named tensors (checked against the layout's shapes).
    pub fn frozen(layout: &EnvLayout, get: &dyn Fn(&str) -> Option<Tensor>) -> Result<Self> {
        let mut t = Vec::new();
        for (name, shape) in pcpn_shapes(layout) {
            let x = get(name)
                .ok_or_else(|| CoreError::Checkpoint(format!("PCPN lacks tensor {name}")))?;
            if x.dims() != shape.as_slice() {
                return Err(CoreError::Checkpoint(format!(
                    "PCPN tensor {name} has shape {:?}, this env needs {shape:?}",
                    x.dims()
                )));
            }
            t.push(x.detach());
        }
        Self::from_ordered(t, layout.aligned_dim)
    }

    fn from_ordered(t: Vec<Tensor>, dim: usize) -> Result<Self> {
        let mut it = t.into_iter();
        let mut next = || it.next().expect("pcpn_shapes lists 8 tensors");
        Ok(Self {
            l0: Linear {
                w: next(),
                b: next(),
            },
            l1: Linear {
                w: next(),
                b: next(),
            },
            w2: next(),
            b2: next(),
            w3: next(),
            b3: next(),
            dim,
        })
    }

    /// A snapshot of the weights as named tensors (copies, for saving and comparing).
    pub fn tensors(&self) -> Result<Vec<(String, Tensor)>> {
        let all = [
            &self.l0.w, &self.l0.b, &self.l1.w, &self.l1.b, &self.w2, &self.b2, &self.w3, &self.b3,
        ];
        PCPN_NAMES
            .iter()
            .zip(all)
            .map(|(n, t)| Ok((n.to_string(), t.copy()?.detach())))
            .collect()
    }

    /// The dtype of its weights.
    pub fn dtype(&self) -> candle_core::DType {
        self.l0.w.dtype()
    }

    /// Number of state-aligned dims d.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The shared part: x [B, I] → chunks [d, B, 1, 128] (ReLU after both layers).
    pub fn chunks(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let b = x.dim(0)?;
        let h = self.l0.forward(x)?.relu()?;
        let z = self.l1.forward(&h)?.relu()?; // [B, d·128]
        z.reshape((b, self.dim, PCPN_CHUNK))?
            .transpose(0, 1)?
            .unsqueeze(2) // [d, B, 1, 128]
    }

    /// Quantile estimates: x [B, I], cosine embedding `cos` [d, B, K, 128] of τ [d, B, K]
    /// → Q [d, B, K].
    pub fn forward(&self, x: &Tensor, cos: &Tensor) -> candle_core::Result<Tensor> {
        let (d, b, k, e) = cos.dims4()?;
        let h = self.chunks(x)?.broadcast_mul(cos)?; // [d, B, K, 128]
        let h = h.reshape((d, b * k, e))?;
        let h = h.matmul(&self.w2)?.broadcast_add(&self.b2)?.relu()?; // [d, B·K, 64]
        let q = h.matmul(&self.w3)?.broadcast_add(&self.b3)?; // [d, B·K, 1]
        q.reshape((d, b, k))
    }
}
