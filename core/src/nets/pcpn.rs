//! The position change prediction network (PCPN): x = [obs, μ, log σ] → 256 → d·128,
//! split into d chunks; for dim j with its own τ_j: h_j = chunk_j ⊙ cos(π·i·τ_j),
//! i = 1..128 → 64 (ReLU) → 1, with separate weights per dim. Output: the τ_j-quantile
//! of the change of state-aligned coordinate j.
//!
//! The architecture is an implicit quantile network of any input and output width:
//! QRRL's policy (algo/qrrl.rs) is one over the observation, one output per action dim.

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
    /// Prefix of its tensor names (`pcpn`; `agent.q` for QRRL's policy).
    prefix: String,
}

/// Names of the tensors of a quantile network under its prefix (`pcpn` for the PCPN), in
/// the order of [`quantile_net_shapes`].
const NET_NAMES: [&str; 8] = [
    "l0.w", "l0.b", "l1.w", "l1.b", "head.w0", "head.b0", "head.w1", "head.b1",
];

/// Names and shapes of the tensors of a quantile network with `input` inputs and `dim`
/// outputs under `prefix`, in a fixed order. The PCPN is one (`pcpn`, [obs, μ, log σ]
/// in, d out); QRRL's policy is another (`agent.q`, obs in, one output per action dim).
pub fn quantile_net_shapes(prefix: &str, input: usize, dim: usize) -> Vec<(String, Vec<usize>)> {
    let shapes = [
        vec![input, PCPN_HIDDEN],
        vec![PCPN_HIDDEN],
        vec![PCPN_HIDDEN, dim * PCPN_CHUNK],
        vec![dim * PCPN_CHUNK],
        vec![dim, PCPN_CHUNK, PCPN_HEAD_HIDDEN],
        vec![dim, 1, PCPN_HEAD_HIDDEN],
        vec![dim, PCPN_HEAD_HIDDEN, 1],
        vec![dim, 1, 1],
    ];
    NET_NAMES
        .iter()
        .map(|n| format!("{prefix}.{n}"))
        .zip(shapes)
        .collect()
}

impl Pcpn {
    /// An untrained frozen PCPN of `layout` (Glorot weights from stream 3 of `seed`,
    /// as `dtype`): what timings and tests use where training does not matter.
    pub fn random_frozen(
        layout: &EnvLayout,
        seed: u64,
        dtype: candle_core::DType,
        dev: &Device,
    ) -> Result<Self> {
        let mut params = ParamSet::default();
        let p = Self::init(layout, &mut crate::rng::rng_for(seed, 3), dev, &mut params)?;
        let t = p.tensors()?;
        Self::frozen(layout, &|n| {
            t.iter()
                .find(|(k, _)| k == n)
                .and_then(|(_, x)| x.to_dtype(dtype).ok())
        })
    }

    /// A trainable PCPN with fresh Glorot weights; its variables go into `params`.
    pub fn init(
        layout: &EnvLayout,
        rng: &mut SaverRng,
        dev: &Device,
        params: &mut ParamSet,
    ) -> Result<Self> {
        let (i, d) = (layout.pcpn_input_dim(), layout.aligned_dim);
        Self::init_net("pcpn", i, d, rng, dev, params)
    }

    /// A trainable quantile network of this architecture under `prefix`, with `input`
    /// inputs and `dim` outputs (fresh Glorot weights, zero biases).
    pub fn init_net(
        prefix: &str,
        input: usize,
        dim: usize,
        rng: &mut SaverRng,
        dev: &Device,
        params: &mut ParamSet,
    ) -> Result<Self> {
        let mut t = Vec::new();
        for (name, shape) in quantile_net_shapes(prefix, input, dim) {
            let n: usize = shape.iter().product();
            let values = if name.ends_with(".b") || name.contains(".head.b") {
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
            t.push(params.var(&name, values, &shape, dev)?);
        }
        Self::from_ordered(t, dim, prefix)
    }

    /// A trainable copy of this network: its weights as new variables in `params` (the
    /// same names), for a learner that keeps fitting a pretrained PCPN.
    pub fn trainable(&self, params: &mut ParamSet) -> Result<Self> {
        let mut t = Vec::new();
        for (name, x) in self.tensors()? {
            let values = x
                .to_dtype(candle_core::DType::F32)?
                .flatten_all()?
                .to_vec1::<f32>()?;
            t.push(params.var(&name, values, x.dims(), x.device())?);
        }
        Self::from_ordered(t, self.dim, &self.prefix)
    }

    /// A frozen copy of the current weights (plain tensors: a later optimiser step on
    /// this network's variables does not change it).
    pub fn snapshot(&self) -> Result<Self> {
        let t = self.tensors()?.into_iter().map(|(_, x)| x).collect();
        Self::from_ordered(t, self.dim, &self.prefix)
    }

    /// A frozen PCPN from named tensors (checked against the layout's shapes).
    pub fn frozen(layout: &EnvLayout, get: &dyn Fn(&str) -> Option<Tensor>) -> Result<Self> {
        let (i, d) = (layout.pcpn_input_dim(), layout.aligned_dim);
        Self::frozen_net("pcpn", i, d, get)
    }

    /// A frozen quantile network under `prefix` from named tensors (shapes checked).
    pub fn frozen_net(
        prefix: &str,
        input: usize,
        dim: usize,
        get: &dyn Fn(&str) -> Option<Tensor>,
    ) -> Result<Self> {
        let mut t = Vec::new();
        for (name, shape) in quantile_net_shapes(prefix, input, dim) {
            let x = get(&name)
                .ok_or_else(|| CoreError::Checkpoint(format!("{prefix} lacks tensor {name}")))?;
            if x.dims() != shape.as_slice() {
                return Err(CoreError::Checkpoint(format!(
                    "tensor {name} has shape {:?}, this env needs {shape:?}",
                    x.dims()
                )));
            }
            t.push(x.detach());
        }
        Self::from_ordered(t, dim, prefix)
    }

    fn from_ordered(t: Vec<Tensor>, dim: usize, prefix: &str) -> Result<Self> {
        let mut it = t.into_iter();
        let mut next = || it.next().expect("quantile_net_shapes lists 8 tensors");
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
            prefix: prefix.to_string(),
        })
    }

    /// A snapshot of the weights as named tensors (copies, for saving and comparing).
    pub fn tensors(&self) -> Result<Vec<(String, Tensor)>> {
        let all = [
            &self.l0.w, &self.l0.b, &self.l1.w, &self.l1.b, &self.w2, &self.b2, &self.w3, &self.b3,
        ];
        NET_NAMES
            .iter()
            .zip(all)
            .map(|(n, t)| Ok((format!("{}.{n}", self.prefix), t.copy()?.detach())))
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
