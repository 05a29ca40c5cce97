//! The critics: SAVER's vector critic x = [obs, μ, log σ] → 256 → 128 → 64 → d (a value
//! per state-aligned dimension), and standalone QRRL's obs → 256 → 128 → 64 → 1.

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
    /// A freshly initialised SAVER critic.
    pub fn new(layout: &EnvLayout, rng: &mut SaverRng, dev: &Device) -> Result<Self> {
        Self::with_sizes(layout.pcpn_input_dim(), layout.aligned_dim, rng, dev)
    }

    /// A freshly initialised critic of `input` inputs and `outputs` values.
    pub fn with_sizes(
        input: usize,
        outputs: usize,
        rng: &mut SaverRng,
        dev: &Device,
    ) -> Result<Self> {
        let mut params = ParamSet::default();
        let mut layers = Vec::new();
        let mut fan_in = input;
        for (i, &h) in TRUNK.iter().enumerate() {
            layers.push(params.linear(&format!("critic.l{i}"), fan_in, h, rng, dev)?);
            fan_in = h;
        }
        layers.push(params.linear("critic.out", fan_in, outputs, rng, dev)?);
        Ok(Self { layers, params })
    }

    /// x [N, pcpn_input_dim] → V [N, d].
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        mlp_forward(&self.layers, x, false)
    }

    /// The layers, input to output (ReLU on all but the last).
    pub fn layers(&self) -> &[Linear] {
        &self.layers
    }

    /// The trainable variables.
    pub fn params(&self) -> &ParamSet {
        &self.params
    }
}
