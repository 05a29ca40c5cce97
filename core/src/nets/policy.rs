//! The agent's forward pass for acting, in plain Rust over the published weights
//! (no autograd, no allocation per step): μ = MLP(obs), a = μ + σ·N(0, 1) for the
//! continuous dims, the choice ~ softmax(logits) as a one-hot.

use super::{HeadConfig, TRUNK};
use crate::env::EnvLayout;
use crate::link::PolicyWeights;
use crate::rng::{normal, SaverRng};
use crate::{CoreError, Result};
use rand::Rng;
use std::sync::Arc;

/// A sampled action with the distribution it came from.
#[derive(Clone, Debug, Default)]
pub struct Action {
    /// [mu_dim].
    pub mu: Vec<f32>,
    /// [log_std_dim].
    pub log_std: Vec<f32>,
    /// [action_dim]: continuous samples, then a one-hot of the choice.
    pub action: Vec<f32>,
}

/// Index of one dense layer's weight and bias in the shared weights.
#[derive(Clone, Copy)]
struct Layer {
    w: usize,
    b: usize,
    fan_in: usize,
    fan_out: usize,
}

/// The acting policy: borrows one shared version of the weights.
pub struct Policy {
    /// The weights (shared by every actor of the process).
    weights: Arc<PolicyWeights>,
    /// Trunk layers then the μ head.
    layers: Vec<Layer>,
    /// Index of `agent.log_std`.
    log_std: usize,
    /// The env layout.
    layout: EnvLayout,
    /// Output bounds, as in training.
    head: HeadConfig,
    /// Scratch activations.
    buf: [Vec<f32>; 2],
}

impl Policy {
    /// Checks the weights against the layout and indexes them.
    pub fn new(weights: Arc<PolicyWeights>, layout: EnvLayout, head: HeadConfig) -> Result<Self> {
        let find = |name: &str, shape: &[usize]| -> Result<usize> {
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
        };
        let mut layers = Vec::new();
        let mut fan_in = layout.obs_dim;
        let heads = TRUNK
            .iter()
            .enumerate()
            .map(|(i, &h)| (format!("agent.l{i}"), h));
        for (name, fan_out) in heads.chain([("agent.mu".to_string(), layout.mu_dim())]) {
            layers.push(Layer {
                w: find(&format!("{name}.w"), &[fan_in, fan_out])?,
                b: find(&format!("{name}.b"), &[fan_out])?,
                fan_in,
                fan_out,
            });
            fan_in = fan_out;
        }
        let log_std = find("agent.log_std", &[layout.log_std_dim()])?;
        Ok(Self {
            weights,
            layers,
            log_std,
            layout,
            head,
            buf: [Vec::new(), Vec::new()],
        })
    }

    /// The version of the weights in use.
    pub fn version(&self) -> u64 {
        self.weights.version
    }

    /// μ for one observation, written into `mu`.
    pub fn mean(&mut self, obs: &[f32], mu: &mut Vec<f32>) {
        let [a, b] = &mut self.buf;
        a.clear();
        a.extend_from_slice(obs);
        let last = self.layers.len() - 1;
        for (li, l) in self.layers.iter().enumerate() {
            let w = &self.weights.tensors[l.w].data;
            b.clear();
            b.extend_from_slice(&self.weights.tensors[l.b].data);
            for (i, &x) in a.iter().enumerate().take(l.fan_in) {
                if x != 0.0 {
                    let row = &w[i * l.fan_out..(i + 1) * l.fan_out];
                    for (o, &wij) in b.iter_mut().zip(row) {
                        *o += x * wij;
                    }
                }
            }
            if li < last {
                for o in b.iter_mut() {
                    *o = o.max(0.0);
                }
            }
            std::mem::swap(a, b);
        }
        mu.clear();
        mu.extend(a.iter().map(|&m| self.head.mu(m)));
    }

    /// Samples an action for `obs` into `out`.
    pub fn act(&mut self, obs: &[f32], rng: &mut SaverRng, out: &mut Action) {
        let mut mu = std::mem::take(&mut out.mu);
        self.mean(obs, &mut mu);
        out.mu = mu;
        let c = self.layout.continuous;
        out.log_std.clear();
        let head = self.head;
        out.log_std.extend(
            self.weights.tensors[self.log_std]
                .data
                .iter()
                .map(|&l| head.log_std(l)),
        );
        out.action.clear();
        for j in 0..c {
            out.action
                .push(out.mu[j] + out.log_std[j].exp() * normal(rng));
        }
        if self.layout.choices > 0 {
            let choice = sample_softmax(&out.mu[c..], rng);
            out.action
                .extend((0..self.layout.choices).map(|i| if i == choice { 1.0 } else { 0.0 }));
        }
    }
}

/// Draws an index from softmax(logits).
pub fn sample_softmax(logits: &[f32], rng: &mut SaverRng) -> usize {
    let max = logits.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
    let weights: Vec<f32> = logits.iter().map(|l| (l - max).exp()).collect();
    let total: f32 = weights.iter().sum();
    let mut u = rng.random::<f32>() * total;
    for (i, w) in weights.iter().enumerate() {
        if u < *w {
            return i;
        }
        u -= w;
    }
    logits.len() - 1
}
