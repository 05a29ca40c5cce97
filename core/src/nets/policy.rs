//! The Gaussian MLP behaviour policy of A2C and SAVER (docs/ALGORITHM.md §3): its
//! forward pass for acting, in plain Rust over the published weights (no autograd, no
//! allocation per step): μ = MLP(obs), a = μ + σ·N(0, 1) for the continuous dims, the
//! choice ~ softmax(logits) as a one-hot; and its family: the payload it records per
//! step (μ then log σ) and the values the learner accepts.

use super::HeadConfig;
use crate::acting::PolicyWeights;
use crate::acting::{ActingPolicy, PolicyFamily};
use crate::config::{MAX_HIDDEN_LAYERS, PAPER_HIDDEN};
use crate::env::slack;
use crate::env::EnvLayout;
use crate::rng::{normal, SaverRng};
use crate::{CoreError, Result};
use rand::Rng;
use std::collections::BTreeMap;
use std::sync::Arc;

/// |μ| when the head leaves it unbounded (the paper's linear mean): far beyond any
/// mean a learning policy reaches (actions are clipped to [-1, 1]), far below what
/// overflows a squared error in f32.
pub const UNBOUNDED_MU: f32 = 1e6;
/// |log σ| when the head leaves it unbounded: σ from 2e-9 to 5e8.
pub const UNBOUNDED_LOG_STD: f32 = 20.0;
/// A sampled action lies within this many σ of its mean (a 16-σ draw has probability
/// below 1e-57).
pub const ACTION_SIGMAS: f32 = 16.0;

/// The Gaussian MLP family in one env layout with one head.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Gaussian {
    /// The env layout.
    pub layout: EnvLayout,
    /// The bounds of μ and log σ.
    pub head: HeadConfig,
}

impl Gaussian {
    /// The family [`PolicyFamily::params`] describes (inf for no bound).
    pub fn from_params(layout: EnvLayout, params: &BTreeMap<String, f64>) -> Result<Self> {
        let get = |k: &str| {
            params.get(k).copied().ok_or_else(|| {
                CoreError::Config(format!("gaussian-mlp policy: parameter {k} is missing"))
            })
        };
        let bounded = |v: f64| Some(v).filter(|v| v.is_finite());
        let mu_bound = bounded(get("mu_bound")?);
        let (lo, hi) = (get("log_std_min")?, get("log_std_max")?);
        let log_std_bounds = match (bounded(lo), bounded(hi)) {
            (None, None) => None,
            (Some(lo), Some(hi)) if lo < hi => Some((lo, hi)),
            _ => {
                return Err(CoreError::Config(format!(
                    "gaussian-mlp policy: log_std [{lo}, {hi}] is not an interval"
                )))
            }
        };
        if mu_bound.is_some_and(|b| b <= 0.0) {
            return Err(CoreError::Config(format!(
                "gaussian-mlp policy: mu_bound {mu_bound:?} must be > 0"
            )));
        }
        Ok(Self {
            layout,
            // The weights carry log σ itself; where it started is the learner's business.
            head: HeadConfig {
                mu_bound,
                log_std_bounds,
                ..HeadConfig::FAITHFUL
            },
        })
    }

    /// Largest |μ| (continuous means and choice logits).
    pub fn mu_abs(&self) -> f32 {
        self.head.mu_bound.map_or(UNBOUNDED_MU, |b| b as f32)
    }

    /// log σ range.
    pub fn log_std_range(&self) -> (f32, f32) {
        self.head
            .log_std_bounds
            .map_or((-UNBOUNDED_LOG_STD, UNBOUNDED_LOG_STD), |(lo, hi)| {
                (lo as f32, hi as f32)
            })
    }
}

impl PolicyFamily for Gaussian {
    fn name(&self) -> &'static str {
        "gaussian-mlp"
    }

    fn payload_width(&self) -> usize {
        self.layout.mu_dim() + self.layout.log_std_dim()
    }

    fn payload_layout(&self) -> String {
        format!(
            "mu[{}] (continuous means, then choice logits), log_std[{}]",
            self.layout.mu_dim(),
            self.layout.log_std_dim()
        )
    }

    fn params(&self) -> BTreeMap<String, f64> {
        let (lo, hi) = self
            .head
            .log_std_bounds
            .unwrap_or((f64::NEG_INFINITY, f64::INFINITY));
        BTreeMap::from([
            (
                "mu_bound".into(),
                self.head.mu_bound.unwrap_or(f64::INFINITY),
            ),
            ("log_std_min".into(), lo),
            ("log_std_max".into(), hi),
        ])
    }

    fn check(&self, payload: &[f32], actions: &[f32], steps: usize) -> Result<()> {
        let l = &self.layout;
        let (m, c, a_dim, w) = (
            l.mu_dim(),
            l.continuous,
            l.action_dim(),
            self.payload_width(),
        );
        let out = |name: &str, i: usize, v: f32, what: String| {
            Err(CoreError::Data(format!(
                "rollout {name}[{i}] = {v} is outside {what}"
            )))
        };
        let mu_abs = self.mu_abs();
        let (lo, hi) = self.log_std_range();
        for s in 0..steps {
            let (mu, log_std) = payload[s * w..(s + 1) * w].split_at(m);
            if let Some(j) = mu.iter().position(|v| v.abs() > mu_abs + slack(mu_abs)) {
                return out("mu", s * m + j, mu[j], format!("the head's +-{mu_abs}"));
            }
            if let Some(j) = log_std
                .iter()
                .position(|&v| v < lo - slack(lo) || v > hi + slack(hi))
            {
                return out(
                    "log_std",
                    s * c + j,
                    log_std[j],
                    format!("the head's [{lo}, {hi}]"),
                );
            }
            // Continuous actions within ACTION_SIGMAS σ of their mean; the choice a
            // one-hot.
            let a = &actions[s * a_dim..(s + 1) * a_dim];
            for j in 0..c {
                let sigma = log_std[j].exp();
                let far = ACTION_SIGMAS * sigma + slack(mu[j]);
                if (a[j] - mu[j]).abs() > far {
                    return out(
                        "actions",
                        s * a_dim + j,
                        a[j],
                        format!(
                            "{ACTION_SIGMAS} sigma of its mean {} (sigma {sigma})",
                            mu[j]
                        ),
                    );
                }
            }
            let choice = &a[c..];
            if !choice.is_empty()
                && (choice.iter().any(|&v| v != 0.0 && v != 1.0)
                    || choice.iter().filter(|&&v| v == 1.0).count() != 1)
            {
                return Err(CoreError::Data(format!(
                    "rollout actions of step {s}: the choice {choice:?} is not a one-hot"
                )));
            }
        }
        Ok(())
    }

    fn acting(&self, weights: Arc<PolicyWeights>) -> Result<Box<dyn ActingPolicy>> {
        Ok(Box::new(Policy::new(weights, self.layout, self.head)?))
    }

    fn layout(&self) -> EnvLayout {
        self.layout
    }

    fn architecture(&self) -> String {
        let l = &self.layout;
        format!(
            "h0 = obs[{o}], or clip((obs - agent.obs_mean) / agent.obs_std, -b, b) when the \
             weights hold both (an observation normaliser), b = agent.obs_clip per entry \
             where the weights hold it (inf: that entry is not clipped), else 10; h(i+1) = relu(h(i) @ agent.l(i).w + agent.l(i).b) for each stored \
             agent.l(i) in turn, i = 0 .. L-1 (w stored [in, out]; the run's hidden widths, \
             {t:?} by default); raw = h(L) @ agent.mu.w + agent.mu.b [{m}]; \
             mu = mu_bound * tanh(raw) if mu_bound is finite, else raw; \
             log_std = clamp(agent.log_std [{c}], log_std_min, log_std_max); \
             action[j] = mu[j] + exp(log_std[j]) * N(0, 1) for j < {c}; then, if {ch} > 0, \
             a one-hot of choice ~ softmax(mu[{c}..{m}]); the env clips actions to [-1, 1]",
            o = l.obs_dim,
            t = PAPER_HIDDEN,
            m = l.mu_dim(),
            c = l.continuous,
            ch = l.choices,
        )
    }
}

/// The hidden widths of the agent in `weights`: the output width of each stored
/// `agent.l{i}.w` for i = 0, 1, ... (their shapes are checked by the caller).
fn hidden_widths(weights: &PolicyWeights) -> Result<Vec<usize>> {
    let mut widths = Vec::new();
    for i in 0..=MAX_HIDDEN_LAYERS {
        let name = format!("agent.l{i}.w");
        let Some(t) = weights.tensors.iter().find(|t| t.name == name) else {
            break;
        };
        if i == MAX_HIDDEN_LAYERS {
            return Err(CoreError::Checkpoint(format!(
                "weights have more than {MAX_HIDDEN_LAYERS} hidden layers ({name})"
            )));
        }
        match t.shape[..] {
            [_, w] => widths.push(w),
            _ => {
                return Err(CoreError::Checkpoint(format!(
                    "weights {name} have shape {:?}, not [in, out]",
                    t.shape
                )))
            }
        }
    }
    if widths.is_empty() {
        return Err(CoreError::Checkpoint("weights lack agent.l0.w".into()));
    }
    Ok(widths)
}

/// Index of one dense layer's weight and bias in the shared weights.
#[derive(Clone, Copy)]
struct Layer {
    w: usize,
    b: usize,
    fan_in: usize,
    fan_out: usize,
}

/// The Gaussian MLP acting policy: borrows one shared version of the weights.
pub struct Policy {
    /// The weights (shared by every actor of the process).
    weights: Arc<PolicyWeights>,
    /// Trunk layers then the μ head.
    layers: Vec<Layer>,
    /// Index of `agent.log_std`.
    log_std: usize,
    /// Where the observation normaliser's mean, std and bounds are, when the weights
    /// carry one (obs_norm.rs).
    obs_norm: Option<super::obs_norm::ObsNormAt>,
    /// The env layout.
    layout: EnvLayout,
    /// Output bounds, as in training.
    head: HeadConfig,
    /// Scratch activations.
    buf: [Vec<f32>; 2],
}

impl Policy {
    /// Checks the weights against the layout and indexes them. The hidden widths are
    /// the weights' own (`agent.l0.w`, `agent.l1.w`, ... as stored, 1 to
    /// [`MAX_HIDDEN_LAYERS`] of them), so an actor follows whatever `hidden` the
    /// learner's run has.
    pub fn new(weights: Arc<PolicyWeights>, layout: EnvLayout, head: HeadConfig) -> Result<Self> {
        let find = |name: &str, shape: &[usize]| super::weight_index(&weights, name, shape);
        let hidden = hidden_widths(&weights)?;
        let mut layers = Vec::new();
        let mut fan_in = layout.obs_dim;
        let heads = hidden
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
        let obs_norm = super::obs_norm::find_in(&weights, layout.obs_dim)?;
        Ok(Self {
            weights,
            layers,
            log_std,
            obs_norm,
            layout,
            head,
            buf: [Vec::new(), Vec::new()],
        })
    }

    /// μ for one observation, written into `mu`.
    pub fn mean(&mut self, obs: &[f32], mu: &mut Vec<f32>) {
        let [a, b] = &mut self.buf;
        a.clear();
        a.extend_from_slice(obs);
        if let Some(at) = self.obs_norm {
            let t = &self.weights.tensors;
            let bound = at.bound.map(|b| t[b].data.as_slice());
            super::obs_norm::normalize(a, &t[at.mean].data, &t[at.std].data, bound);
        }
        let last = self.layers.len() - 1;
        for (li, l) in self.layers.iter().enumerate() {
            let (w, bias) = (
                &self.weights.tensors[l.w].data,
                &self.weights.tensors[l.b].data,
            );
            let n = l.fan_in.min(a.len());
            super::host_dense(&a[..n], w, bias, l.fan_out, li < last, b);
            std::mem::swap(a, b);
        }
        mu.clear();
        mu.extend(a.iter().map(|&m| self.head.mu(m)));
    }

    /// Samples an action for `obs` into `action`, with the μ and log σ it came from
    /// into `payload` (μ then log σ).
    pub fn sample(
        &mut self,
        obs: &[f32],
        rng: &mut SaverRng,
        action: &mut Vec<f32>,
        payload: &mut Vec<f32>,
    ) {
        self.mean(obs, payload);
        let (m, c) = (self.layout.mu_dim(), self.layout.continuous);
        let head = self.head;
        payload.extend(
            self.weights.tensors[self.log_std]
                .data
                .iter()
                .map(|&l| head.log_std(l)),
        );
        let (mu, log_std) = payload.split_at(m);
        action.clear();
        for j in 0..c {
            action.push(mu[j] + log_std[j].exp() * normal(rng));
        }
        if self.layout.choices > 0 {
            let choice = sample_softmax(&mu[c..], rng);
            action.extend((0..self.layout.choices).map(|i| if i == choice { 1.0 } else { 0.0 }));
        }
    }
}

impl ActingPolicy for Policy {
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
        self.sample(obs, rng, action, payload);
    }

    /// μ for the continuous dims and a one-hot of the largest logit.
    fn act_deterministic(&mut self, obs: &[f32], action: &mut Vec<f32>) {
        self.mean(obs, action);
        let c = self.layout.continuous;
        if self.layout.choices > 0 {
            let best = (c..action.len())
                .max_by(|&a, &b| action[a].total_cmp(&action[b]))
                .unwrap_or(c);
            for (i, a) in action.iter_mut().enumerate().skip(c) {
                *a = if i == best { 1.0 } else { 0.0 };
            }
        }
    }
}

/// log π(a) of the Gaussian MLP policy, differentiable (A2C's policy gradient):
/// Σ_j −(a_j − μ_j)²/(2σ_j²) − log σ_j − ½·log 2π over the continuous dims, plus
/// log softmax(logits)·one-hot of the choice. `mu` [B, mu_dim], `log_std` [B, c],
/// `actions` [B, action_dim]; returns [B].
pub fn gaussian_log_prob(
    layout: &EnvLayout,
    mu: &candle_core::Tensor,
    log_std: &candle_core::Tensor,
    actions: &candle_core::Tensor,
) -> Result<candle_core::Tensor> {
    let c = layout.continuous;
    let half_log_2pi = 0.5 * (2.0 * std::f64::consts::PI).ln();
    let mu_c = mu.narrow(1, 0, c)?;
    let a_c = actions.narrow(1, 0, c)?;
    let z = ((a_c - mu_c)? / log_std.exp()?)?;
    let gauss = ((z.sqr()? * -0.5)? - log_std)?;
    let mut logp = (gauss - half_log_2pi)?.sum(1)?;
    if layout.choices > 0 {
        let logits = mu.narrow(1, c, layout.choices)?;
        let onehot = actions.narrow(1, c, layout.choices)?;
        let log_soft = candle_nn::ops::log_softmax(&logits, candle_core::D::Minus1)?;
        logp = (logp + (log_soft * onehot)?.sum(1)?)?;
    }
    Ok(logp)
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

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Tensor};

    /// One continuous dim and a choice of 2: μ = 0, log σ = 0, a = 1 gives
    /// −½ − ½·log 2π = −1.4189385; logits (0, ln 3) with the second chosen add
    /// log(3/4) = −0.2876821: −1.7066206.
    #[test]
    fn log_prob_by_hand() {
        let layout = EnvLayout {
            obs_dim: 1,
            continuous: 1,
            choices: 2,
            aligned_start: 0,
            aligned_dim: 1,
        };
        let dev = Device::Cpu;
        let mu = Tensor::new(&[[0.0f32, 0.0, 3.0f32.ln()]], &dev).unwrap();
        let log_std = Tensor::new(&[[0.0f32]], &dev).unwrap();
        let actions = Tensor::new(&[[1.0f32, 0.0, 1.0]], &dev).unwrap();
        let lp = gaussian_log_prob(&layout, &mu, &log_std, &actions)
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!((lp[0] - -1.7066206).abs() < 1e-6, "{lp:?}");
    }
}
