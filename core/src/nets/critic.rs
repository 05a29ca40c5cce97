//! The QRRL vector critic: x = [obs, μ, log σ] → 256 → 128 → 64 → d (a value per
//! state-aligned dimension).

use super::{mlp_forward, Linear, ParamSet, TRUNK};
use crate::env::EnvLayout;
use crate::rng::SaverRng;
use crate::Result;
use candle_core::{Device, Tensor};

/// The vector critic V(o, μ, log σ) ∈ R^d.
pub struct Critic {
    /// x → 256 → 128 → 64 (ReLU) → d (linear).
    layers: Vec<Linear>,
    /// Trainable variables, named `critic.*`.
    params: ParamSet,
}

impl Critic {
    /// A freshly initialised critic.
    pub fn new(layout: &EnvLayout, rng: &mut SaverRng, dev: &Device) -> Result<Self> {
        let mut params = ParamSet::default();
        let mut layers = Vec::new();
        let mut fan_in = layout.pcpn_input_dim();
        for (i, &h) in TRUNK.iter().enumerate() {
            layers.push(params.linear(&format!("critic.l{i}"), fan_in, h, rng, dev)?);
            fan_in = h;
        }
        layers.push(params.linear("critic.out", fan_in, layout.aligned_dim, rng, dev)?);
        Ok(Self { layers, params })
    }

    /// x [N, pcpn_input_dim] → V [N, d].
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        mlp_forward(&self.layers, x, false)
    }

    /// The trainable variables.
    pub fn params(&self) -> &ParamSet {
        &self.params
    }
}
