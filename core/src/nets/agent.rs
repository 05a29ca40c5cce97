//! The agent: obs → hidden layers (256 → 128 → 64 by default) → linear μ, a
//! state-independent trainable log σ (initialised to `head.log_std_init`, −1 unless
//! set), and for A2C a value head → 1 on the shared trunk.

use super::{mlp_forward, Linear, ParamSet};
use crate::config::HeadConfig;
use crate::env::EnvLayout;
use crate::rng::SaverRng;
use crate::Result;
use candle_core::{Device, Tensor};

/// The agent network (and, for A2C, its value head).
pub struct Agent {
    /// obs → the hidden widths, ReLU after each.
    trunk: Vec<Linear>,
    /// Last hidden layer → μ (continuous means, then choice logits).
    mu: Linear,
    /// [continuous]: log σ, shared by all states.
    log_std: Tensor,
    /// Last hidden layer → 1, A2C only.
    value: Option<Linear>,
    /// Output bounds.
    head: HeadConfig,
    /// Trainable variables, named `agent.*`.
    params: ParamSet,
}

/// The agent's outputs for a batch of observations.
pub struct AgentOut {
    /// [N, mu_dim].
    pub mu: Tensor,
    /// [N, mu_dim]: the mean head's output before the bound (equal to `mu` unbounded).
    pub mu_raw: Tensor,
    /// [N, log_std_dim] (the same row repeated).
    pub log_std: Tensor,
    /// [N] value estimates (A2C only).
    pub value: Option<Tensor>,
}

impl Agent {
    /// A freshly initialised agent with `hidden` widths (the config's `hidden`);
    /// `with_value` adds the A2C value head.
    pub fn new(
        layout: &EnvLayout,
        head: HeadConfig,
        hidden: &[usize],
        with_value: bool,
        rng: &mut SaverRng,
        dev: &Device,
    ) -> Result<Self> {
        let mut params = ParamSet::default();
        let mut trunk = Vec::new();
        let mut fan_in = layout.obs_dim;
        for (i, &h) in hidden.iter().enumerate() {
            trunk.push(params.linear(&format!("agent.l{i}"), fan_in, h, rng, dev)?);
            fan_in = h;
        }
        let mu = params.linear("agent.mu", fan_in, layout.mu_dim(), rng, dev)?;
        let n = layout.log_std_dim();
        let log_std = params.var(
            "agent.log_std",
            vec![head.log_std_init as f32; n],
            &[n],
            dev,
        )?;
        let value = if with_value {
            Some(params.linear("agent.value", fan_in, 1, rng, dev)?)
        } else {
            None
        };
        Ok(Self {
            trunk,
            mu,
            log_std,
            value,
            head,
            params,
        })
    }

    /// obs [N, obs_dim] → μ, log σ and (A2C) V.
    pub fn forward(&self, obs: &Tensor) -> candle_core::Result<AgentOut> {
        let n = obs.dim(0)?;
        let h = mlp_forward(&self.trunk, obs, true)?;
        let mu_raw = self.mu.forward(&h)?;
        let mu = match self.head.mu_bound {
            Some(b) => (mu_raw.tanh()? * b)?,
            None => mu_raw.clone(),
        };
        let mut log_std = self.log_std.clone();
        if let Some((lo, hi)) = self.head.log_std_bounds {
            log_std = log_std.clamp(lo as f32, hi as f32)?;
        }
        let log_std = log_std.unsqueeze(0)?.broadcast_as((n, log_std.dim(0)?))?;
        let value = match &self.value {
            Some(v) => Some(v.forward(&h)?.squeeze(1)?),
            None => None,
        };
        Ok(AgentOut {
            mu,
            mu_raw,
            log_std,
            value,
        })
    }

    /// The trainable variables.
    pub fn params(&self) -> &ParamSet {
        &self.params
    }

    /// The trunk's layers then the μ layer (not the value head), input to output.
    pub fn layers(&self) -> Vec<&Linear> {
        self.trunk.iter().chain([&self.mu]).collect()
    }

    /// The log σ variable, before the head's clamp.
    pub fn log_std_var(&self) -> &Tensor {
        &self.log_std
    }

    /// The head's bounds.
    pub fn head(&self) -> HeadConfig {
        self.head
    }
}
