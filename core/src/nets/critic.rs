//! The critics: SAVER's vector critic x = [obs, μ, log σ] → hidden → d (a value per
//! state-aligned dimension), and standalone QRRL's and PPO's obs → hidden → 1 (or d);
//! the hidden widths are the run's (256 → 128 → 64 by default).

use super::{mlp_forward, Linear, ParamSet};
use crate::env::EnvLayout;
use crate::rng::SaverRng;
use crate::Result;
use candle_core::{Device, Tensor};

/// The vector critic V(o, μ, log σ) ∈ R^d.
pub struct Critic {
    /// x → the hidden widths (ReLU) → d (linear).
    layers: Vec<Linear>,
    /// Trainable variables, named `critic.*`.
    params: ParamSet,
}

impl Critic {
    /// A freshly initialised SAVER critic with `hidden` widths.
    pub fn new(
        layout: &EnvLayout,
        hidden: &[usize],
        rng: &mut SaverRng,
        dev: &Device,
    ) -> Result<Self> {
        Self::with_sizes(
            layout.pcpn_input_dim(),
            layout.aligned_dim,
            hidden,
            rng,
            dev,
        )
    }

    /// A freshly initialised critic of `input` inputs, `hidden` widths and `outputs`
    /// values.
    pub fn with_sizes(
        input: usize,
        outputs: usize,
        hidden: &[usize],
        rng: &mut SaverRng,
        dev: &Device,
    ) -> Result<Self> {
        Self::named("critic", input, outputs, hidden, rng, dev)
    }

    /// [`Self::with_sizes`] with its variables named `<name>.*` (a second critic
    /// beside the first).
    pub fn named(
        name: &str,
        input: usize,
        outputs: usize,
        hidden: &[usize],
        rng: &mut SaverRng,
        dev: &Device,
    ) -> Result<Self> {
        let mut params = ParamSet::default();
        let mut layers = Vec::new();
        let mut fan_in = input;
        for (i, &h) in hidden.iter().enumerate() {
            layers.push(params.linear(&format!("{name}.l{i}"), fan_in, h, rng, dev)?);
            fan_in = h;
        }
        layers.push(params.linear(&format!("{name}.out"), fan_in, outputs, rng, dev)?);
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
