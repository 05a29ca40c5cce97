//! Standalone QRRL's behaviour policy (paper Section 3; docs/ALGORITHM.md §14): an
//! implicit quantile network over the observation, one output per action dim, of the
//! PCPN's architecture ([`super::Pcpn`] under the prefix `agent.q`). An actor draws
//! τ_j ~ U(0, 1) per action dim and acts a_j = Q_j(τ_j, o), so the action distribution
//! is whatever the network's quantile function makes it (multi-modal included); each
//! step records its τ. Acting runs in plain Rust over the published weights.

use super::{host_dense, PCPN_CHUNK, PCPN_HEAD_HIDDEN, PCPN_HIDDEN, UNBOUNDED_MU};
use crate::acting::PolicyWeights;
use crate::acting::{ActingPolicy, PolicyFamily};
use crate::embedding::cosine_embedding_into;
use crate::env::slack;
use crate::env::EnvLayout;
use crate::rng::SaverRng;
use crate::{CoreError, Result};
use rand::Rng;
use std::collections::BTreeMap;
use std::sync::Arc;

/// Prefix of the quantile policy's tensors.
pub const QUANTILE_PREFIX: &str = "agent.q";

/// The base quantile function s·(2τ − 1) added to the network's output (so the
/// untrained policy is U(−s, s)); 0 exactly when s = 0. The one definition, acting,
/// the autograd update ([`base_quantiles`]) and the fused update use.
pub fn base_quantile(spread: f32, tau: f32) -> f32 {
    if spread == 0.0 {
        0.0
    } else {
        spread * (2.0 * tau - 1.0)
    }
}

/// [`base_quantile`] of every τ of a tensor.
pub fn base_quantiles(tau: &candle_core::Tensor, spread: f64) -> Result<candle_core::Tensor> {
    Ok(((tau * 2.0)? - 1.0)?.affine(spread, 0.0)?)
}

/// The quantile-network family in one env layout (continuous actions only).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QuantileFamily {
    /// The env layout.
    pub layout: EnvLayout,
    /// s of the base quantile function s·(2τ − 1) added to the network's output.
    pub spread: f64,
}

impl QuantileFamily {
    /// The family in `layout`; refused for a layout with a categorical choice, which
    /// is not a quantile of anything.
    pub fn new(layout: EnvLayout, spread: f64) -> Result<Self> {
        crate::config::check_quantile_policy(layout, spread)?;
        Ok(Self { layout, spread })
    }
}

impl PolicyFamily for QuantileFamily {
    fn name(&self) -> &'static str {
        "quantile-mlp"
    }

    fn payload_width(&self) -> usize {
        self.layout.continuous
    }

    fn payload_layout(&self) -> String {
        format!(
            "tau[{}] (each action dim's quantile level: action[j] = Q_j(tau[j], obs))",
            self.layout.continuous
        )
    }

    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([("spread".into(), self.spread)])
    }

    fn check(&self, payload: &[f32], actions: &[f32], steps: usize) -> Result<()> {
        let c = self.layout.continuous;
        if let Some(i) = payload[..steps * c]
            .iter()
            .position(|t| !(0.0..=1.0).contains(t))
        {
            return Err(CoreError::Data(format!(
                "rollout tau[{i}] = {} is outside [0, 1]",
                payload[i]
            )));
        }
        let far = UNBOUNDED_MU + slack(UNBOUNDED_MU);
        if let Some(i) = actions[..steps * c].iter().position(|a| a.abs() > far) {
            return Err(CoreError::Data(format!(
                "rollout actions[{i}] = {} is outside +-{UNBOUNDED_MU}",
                actions[i]
            )));
        }
        Ok(())
    }

    fn acting(&self, weights: Arc<PolicyWeights>) -> Result<Box<dyn ActingPolicy>> {
        Ok(Box::new(QuantilePolicy::new(
            weights,
            self.layout,
            self.spread,
        )?))
    }

    fn layout(&self) -> EnvLayout {
        self.layout
    }

    fn architecture(&self) -> String {
        let (o, c) = (self.layout.obs_dim, self.layout.continuous);
        format!(
            "tau[j] ~ U(0, 1) for j < {c}; h = relu(obs[{o}] @ {p}.l0.w + {p}.l0.b) [{PCPN_HIDDEN}]; \
             z = relu(h @ {p}.l1.w + {p}.l1.b) [{c}x{PCPN_CHUNK}]; for each j: \
             e[i] = z[j*{PCPN_CHUNK} + i] * cos(pi * (i + 1) * tau[j]) for i < {PCPN_CHUNK}; \
             u = relu(e @ {p}.head.w0[j] + {p}.head.b0[j]) [{PCPN_HEAD_HIDDEN}]; \
             action[j] = u @ {p}.head.w1[j] + {p}.head.b1[j] + spread * (2 * tau[j] - 1) \
             (w stored [in, out]); the env clips actions to [-1, 1]; the most likely action uses tau = 0.5",
            p = QUANTILE_PREFIX
        )
    }
}

/// The quantile policy acting on one version of the weights.
pub struct QuantilePolicy {
    /// The weights (shared by every actor of the process).
    weights: Arc<PolicyWeights>,
    /// Indices of the 8 tensors, in [`super::pcpn::quantile_net_shapes`] order.
    idx: [usize; 8],
    /// The env layout.
    layout: EnvLayout,
    /// s of the base quantile function.
    spread: f32,
    /// Scratch: trunk activations, chunk products, head hidden, embedding, product.
    buf: [Vec<f32>; 5],
}

impl QuantilePolicy {
    /// Checks the weights against the layout and indexes them.
    pub fn new(weights: Arc<PolicyWeights>, layout: EnvLayout, spread: f64) -> Result<Self> {
        let shapes =
            super::pcpn::quantile_net_shapes(QUANTILE_PREFIX, layout.obs_dim, layout.continuous);
        let mut idx = [0usize; 8];
        for (slot, (name, shape)) in idx.iter_mut().zip(&shapes) {
            *slot = super::weight_index(&weights, name, shape)?;
        }
        Ok(Self {
            weights,
            idx,
            layout,
            spread: spread as f32,
            buf: Default::default(),
        })
    }

    fn data(&self, k: usize) -> &[f32] {
        &self.weights.tensors[self.idx[k]].data
    }

    /// Q_j(τ_j, obs) for every action dim j, into `action`.
    pub fn quantiles(&mut self, obs: &[f32], taus: &[f32], action: &mut Vec<f32>) {
        let c = self.layout.continuous;
        let [mut h, mut z, mut u, mut cos, mut prod] = std::mem::take(&mut self.buf);
        host_dense(obs, self.data(0), self.data(1), PCPN_HIDDEN, true, &mut h);
        host_dense(&h, self.data(2), self.data(3), c * PCPN_CHUNK, true, &mut z);
        cos.resize(PCPN_CHUNK, 0.0);
        action.clear();
        let (w2, b2, w3, b3) = (self.data(4), self.data(5), self.data(6), self.data(7));
        let (e, hh) = (PCPN_CHUNK, PCPN_HEAD_HIDDEN);
        for (j, &tau) in taus.iter().enumerate().take(c) {
            cosine_embedding_into(tau, &mut cos);
            prod.clear();
            prod.extend(z[j * e..(j + 1) * e].iter().zip(&cos).map(|(a, b)| a * b));
            host_dense(
                &prod,
                &w2[j * e * hh..(j + 1) * e * hh],
                &b2[j * hh..(j + 1) * hh],
                hh,
                true,
                &mut u,
            );
            let w = &w3[j * hh..(j + 1) * hh];
            let base = base_quantile(self.spread, tau);
            action.push(u.iter().zip(w).map(|(a, b)| a * b).sum::<f32>() + b3[j] + base);
        }
        self.buf = [h, z, u, cos, prod];
    }
}

impl ActingPolicy for QuantilePolicy {
    fn version(&self) -> u64 {
        self.weights.version
    }

    fn act(
        &mut self,
        obs: &[f32],
        rng: &mut SaverRng,
        action: &mut Vec<f32>,
        payload: &mut Vec<f32>,
    ) {
        payload.clear();
        payload.extend((0..self.layout.continuous).map(|_| rng.random::<f32>()));
        self.quantiles(obs, payload, action);
    }

    /// The median action (τ = 0.5 in every dim).
    fn act_deterministic(&mut self, obs: &[f32], action: &mut Vec<f32>) {
        let half = vec![0.5; self.layout.continuous];
        self.quantiles(obs, &half, action);
    }
}
