//! The networks (docs/ALGORITHM.md §3): ReLU MLPs with Glorot-uniform weights and zero
//! biases drawn from our seeded RNG. Weights are stored [in, out] so a layer is x·W + b.

mod agent;
mod critic;
pub mod obs_norm;
mod pcpn;
mod policy;
mod quantile_policy;

pub use crate::config::HeadConfig;
pub use agent::{Agent, AgentOut};
pub use critic::Critic;
pub use pcpn::{quantile_net_shapes, Pcpn, PCPN_CHUNK, PCPN_HEAD_HIDDEN, PCPN_HIDDEN};
pub use policy::{
    gaussian_log_prob, sample_softmax as sample_softmax_pub, Gaussian, Policy, ACTION_SIGMAS,
    UNBOUNDED_LOG_STD, UNBOUNDED_MU,
};
pub use quantile_policy::{
    base_quantile, base_quantiles, QuantileFamily, QuantilePolicy, QUANTILE_PREFIX,
};

use crate::rng::{glorot_uniform, SaverRng};
use crate::{CoreError, Result};
use candle_core::{Device, Tensor, Var};

/// A dense layer y = x·W + b over plain tensors (frozen) or variables (trainable).
#[derive(Clone, Debug)]
pub struct Linear {
    /// [in, out].
    pub w: Tensor,
    /// [out].
    pub b: Tensor,
}

impl Linear {
    /// x [N, in] → [N, out].
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        x.matmul(&self.w)?.broadcast_add(&self.b)
    }
}

/// Named trainable variables, in creation order: what the optimiser trains and what a
/// checkpoint stores.
#[derive(Clone, Default)]
pub struct ParamSet {
    /// (name, variable).
    pub vars: Vec<(String, Var)>,
}

impl ParamSet {
    /// A Glorot-uniform [fan_in, fan_out] weight and a zero bias named `{name}.w`, `{name}.b`.
    pub fn linear(
        &mut self,
        name: &str,
        fan_in: usize,
        fan_out: usize,
        rng: &mut SaverRng,
        dev: &Device,
    ) -> Result<Linear> {
        let w = self.var(
            &format!("{name}.w"),
            glorot_uniform(rng, fan_in, fan_out),
            &[fan_in, fan_out],
            dev,
        )?;
        let b = self.var(&format!("{name}.b"), vec![0.0; fan_out], &[fan_out], dev)?;
        Ok(Linear { w, b })
    }

    /// Adds a variable with the given values; returns its tensor (same storage).
    pub fn var(
        &mut self,
        name: &str,
        values: Vec<f32>,
        shape: &[usize],
        dev: &Device,
    ) -> Result<Tensor> {
        let v = Var::from_vec(values, shape, dev)?;
        let t = v.as_tensor().clone();
        self.vars.push((name.to_string(), v));
        Ok(t)
    }

    /// A snapshot of the variables' current values as plain named tensors (copies: a
    /// later optimiser step, which writes the variables in place, does not change them).
    pub fn tensors(&self) -> Result<Vec<(String, Tensor)>> {
        self.vars
            .iter()
            .map(|(n, v)| Ok((n.clone(), v.as_tensor().copy()?.detach())))
            .collect()
    }

    /// Overwrites every variable from `get` (shapes must match).
    pub fn load(&self, get: &dyn Fn(&str) -> Option<Tensor>) -> Result<()> {
        for (name, var) in &self.vars {
            let t =
                get(name).ok_or_else(|| CoreError::Checkpoint(format!("missing tensor {name}")))?;
            if t.dims() != var.dims() {
                return Err(CoreError::Checkpoint(format!(
                    "tensor {name} has shape {:?}, expected {:?}",
                    t.dims(),
                    var.dims()
                )));
            }
            var.set(&t.to_device(var.device())?)?;
        }
        Ok(())
    }
}

/// The index of tensor `name` in published `weights`, checked to have `shape` (actors
/// index their policy's tensors once per version).
pub(crate) fn weight_index(
    weights: &crate::acting::PolicyWeights,
    name: &str,
    shape: &[usize],
) -> Result<usize> {
    let i = weights
        .tensors
        .iter()
        .position(|t| t.name == name)
        .ok_or_else(|| CoreError::Checkpoint(format!("weights lack {name}")))?;
    let t = &weights.tensors[i];
    if t.shape != shape || t.data.len() != t.numel() {
        return Err(CoreError::Checkpoint(format!(
            "weights {name} have shape {:?}, expected {shape:?}",
            t.shape
        )));
    }
    Ok(i)
}

/// An actor's dense layer on the host: out = x·W + b (W stored [in, out]; zero inputs,
/// common after a ReLU, are skipped), then ReLU when `relu`.
pub(crate) fn host_dense(
    x: &[f32],
    w: &[f32],
    b: &[f32],
    fan_out: usize,
    relu: bool,
    out: &mut Vec<f32>,
) {
    out.clear();
    out.extend_from_slice(b);
    for (i, &xi) in x.iter().enumerate() {
        if xi != 0.0 {
            for (o, &wij) in out.iter_mut().zip(&w[i * fan_out..(i + 1) * fan_out]) {
                *o += xi * wij;
            }
        }
    }
    if relu {
        for o in out.iter_mut() {
            *o = o.max(0.0);
        }
    }
}

/// A ReLU MLP: every layer but the last is followed by ReLU.
pub(crate) fn mlp_forward(
    layers: &[Linear],
    x: &Tensor,
    relu_last: bool,
) -> candle_core::Result<Tensor> {
    let mut h = x.clone();
    for (i, l) in layers.iter().enumerate() {
        h = l.forward(&h)?;
        if relu_last || i + 1 < layers.len() {
            h = h.relu()?;
        }
    }
    Ok(h)
}

/// The family a peer names on the wire, in `layout`, with its `params`.
pub fn family_from_wire(
    name: &str,
    layout: crate::env::EnvLayout,
    params: &std::collections::BTreeMap<String, f64>,
) -> crate::Result<std::sync::Arc<dyn crate::acting::PolicyFamily>> {
    match name {
        "gaussian-mlp" => Ok(std::sync::Arc::new(Gaussian::from_params(layout, params)?)),
        "quantile-mlp" => {
            let spread = params.get("spread").copied().ok_or_else(|| {
                crate::CoreError::Config("quantile-mlp policy: parameter spread is missing".into())
            })?;
            Ok(std::sync::Arc::new(QuantileFamily::new(layout, spread)?))
        }
        other => Err(crate::CoreError::Config(format!(
            "policy family {:?} is not one this build knows (gaussian-mlp, quantile-mlp)",
            crate::clip_text(other)
        ))),
    }
}
