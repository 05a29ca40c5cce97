//! PPO's minibatch step by hand on the host (the default on the CPU for layouts without
//! a categorical choice): the agent's and critic's MLPs forward and backward with gemm
//! into plain buffers, the clipped surrogate, value loss and entropy bonus written out.
//! candle's graph of the same step (`Ppo::reference_grads`, `GradPath::Reference`) runs
//! ~60 small tensor ops forward and as many backward a minibatch, each with its
//! allocation and element-wise pass; here the element-wise work is one loop per layer.
//! Its gradients equal the reference's to rounding (tested), ties of min/max/clamp split
//! as candle splits them.

use super::{Minibatch, Totals};
use crate::algo::check_finite;
use crate::algo::dense::matmul;
use crate::config::{HeadConfig, PpoConfig};
use crate::nets::Linear;
use crate::optim::HostState;
use crate::Result;
use candle_core::{Tensor, TensorId};

/// One MLP's layers on the host, borrowed from the optimiser's [`HostState`]: (weight
/// [in, out] row-major, bias [out], in, out).
struct HostMlp<'a> {
    layers: Vec<(&'a [f32], &'a [f32], usize, usize)>,
}

impl<'a> HostMlp<'a> {
    fn of(layers: &[&Linear], h: &'a HostState) -> Result<Self> {
        let mut out = Vec::with_capacity(layers.len());
        for l in layers {
            let (i, o) = l.w.dims2()?;
            out.push((value(h, &l.w)?, value(h, &l.b)?, i, o));
        }
        Ok(Self { layers: out })
    }

    /// Every layer's output for `x` [n, in]: ReLU on all but the last, which is linear.
    fn forward(&self, x: &[f32], n: usize) -> Vec<Vec<f32>> {
        let mut acts: Vec<Vec<f32>> = Vec::with_capacity(self.layers.len());
        for (k, (w, b, i, o)) in self.layers.iter().enumerate() {
            let input = if k == 0 { x } else { &acts[k - 1] };
            let mut y = vec![0.0f32; n * o];
            matmul(&mut y, input, w, (n, *i, *o), (false, false));
            let last = k + 1 == self.layers.len();
            for row in y.chunks_exact_mut(*o) {
                for (v, bias) in row.iter_mut().zip(b.iter()) {
                    *v += bias;
                    if !last && *v < 0.0 {
                        *v = 0.0;
                    }
                }
            }
            acts.push(y);
        }
        acts
    }

    /// Each layer's (dW, db) from the gradient `dy` of the last layer's output, given
    /// the input `x` and the activations `forward` returned.
    fn backward(
        &self,
        x: &[f32],
        acts: &[Vec<f32>],
        mut dy: Vec<f32>,
        n: usize,
    ) -> Vec<(Vec<f32>, Vec<f32>)> {
        let mut grads = Vec::with_capacity(self.layers.len());
        for k in (0..self.layers.len()).rev() {
            let (w, _, i, o) = &self.layers[k];
            let input = if k == 0 { x } else { &acts[k - 1] };
            let mut dw = vec![0.0f32; i * o];
            matmul(&mut dw, input, &dy, (*i, n, *o), (true, false));
            let mut db = vec![0.0f32; *o];
            for row in dy.chunks_exact(*o) {
                for (s, v) in db.iter_mut().zip(row) {
                    *s += v;
                }
            }
            grads.push((dw, db));
            if k > 0 {
                let mut dx = vec![0.0f32; n * i];
                matmul(&mut dx, &dy, w, (n, *o, *i), (false, true));
                // Through the ReLU that made the input: no gradient where it was cut
                // (a select, not a branch, so that the loop vectorises).
                for (g, a) in dx.iter_mut().zip(input) {
                    *g = if *a > 0.0 { *g } else { 0.0 };
                }
                dy = dx;
            }
        }
        grads.reverse();
        grads
    }
}

/// The optimiser's current value of the variable `var`.
fn value<'a>(h: &'a HostState, var: &Tensor) -> Result<&'a [f32]> {
    h.value(var)
        .ok_or_else(|| crate::CoreError::Data("PPO's optimiser does not train a layer".into()))
}

/// candle's gradient share of `x` in max(x, y) or min(x, y) when `x` is the one taken:
/// 1, ½ on a tie, 0 when the other one is taken.
fn share(taken: bool, tie: bool) -> f32 {
    if tie {
        0.5
    } else if taken {
        1.0
    } else {
        0.0
    }
}

/// The networks a step trains, by reference, and the loss settings.
pub(super) struct Nets<'a> {
    /// The agent's trunk then its μ layer.
    pub agent: Vec<&'a Linear>,
    /// The agent's log σ variable.
    pub log_std: &'a Tensor,
    /// The critic's layers.
    pub critic: Vec<&'a Linear>,
    /// The agent's head bounds.
    pub head: HeadConfig,
    /// Clip, entropy and value-clip settings.
    pub cfg: &'a PpoConfig,
    /// The value loss's weight.
    pub value_coef: f64,
    /// The critic's outputs.
    pub c: usize,
}

/// One minibatch step's losses and the gradients of every variable of `nets`, into
/// `totals` (the stats) and the host gradients [`crate::optim::Optimizer::step_host`] takes, at the weights
/// of the optimiser's host state `h`. Every action entry is continuous (the caller takes the reference path for a layout with a choice). With
/// `parallel` the critic's forward and backward run on a second thread.
pub(super) fn step_grads(
    nets: &Nets,
    h: &HostState,
    mb: &Minibatch,
    parallel: bool,
    totals: &mut Totals,
) -> Result<Vec<(TensorId, Vec<f32>)>> {
    let agent = HostMlp::of(&nets.agent, h)?;
    let critic = HostMlp::of(&nets.critic, h)?;
    std::thread::scope(|scope| {
        // The critic's part on a second thread while this one does the agent's: the
        // two share no sums, so the bits are the same either way.
        let critic_job = parallel.then(|| scope.spawn(|| value_grads(&critic, mb, nets)));
        policy_and_grads(nets, &agent, &critic, critic_job, h, mb, totals)
    })
}

/// The agent's part of [`step_grads`], the critic's from `critic_job` (or computed
/// here), then the checks and every gradient.
fn policy_and_grads<'s>(
    nets: &Nets,
    agent: &HostMlp,
    critic: &HostMlp,
    critic_job: Option<std::thread::ScopedJoinHandle<'s, CriticGrads>>,
    h: &HostState,
    mb: &Minibatch,
    totals: &mut Totals,
) -> Result<Vec<(TensorId, Vec<f32>)>> {
    let (n, cfg) = (mb.n, nets.cfg);
    let na = agent.layers.last().map_or(0, |l| l.3);
    let raw_log_std = value(h, nets.log_std)?;
    // log σ = clamp(p, lo, hi); candle's clamp is max(p, lo) then min(·, hi).
    let (log_std, ls_pass): (Vec<f32>, Vec<f32>) = raw_log_std
        .iter()
        .map(|&p| match nets.head.log_std_bounds {
            Some((lo, hi)) => {
                let (lo, hi) = (lo as f32, hi as f32);
                let m = p.max(lo);
                let pass = share(p > lo, p == lo) * share(m < hi, m == hi);
                (m.min(hi), pass)
            }
            None => (p, 1.0),
        })
        .unzip();

    // The agent: μ_raw [n, na], μ = bound·tanh(μ_raw) or μ_raw.
    let a_acts = agent.forward(&mb.obs, n);
    let mu_raw = &a_acts[a_acts.len() - 1];
    let eps = cfg.clip as f32;
    let half_log_2pi = 0.5 * (2.0 * std::f32::consts::PI).ln();
    let inv_n = 1.0 / n as f32;
    let mut d_raw = vec![0.0f32; n * na];
    let mut d_log_std = vec![0.0f64; na];
    let (mut policy_loss, mut kl, mut outside) = (0.0f64, 0.0f64, 0usize);
    let mut zs = vec![0.0f32; na];
    // σ per entry, and a row's tanh(μ_raw) for its backward: each computed once.
    let sigma: Vec<f32> = log_std.iter().map(|l| l.exp()).collect();
    let mut tanh = vec![0.0f32; na];
    for b in 0..n {
        let raw = &mu_raw[b * na..(b + 1) * na];
        let act = &mb.actions[b * na..(b + 1) * na];
        let mut logp = 0.0f32;
        for i in 0..na {
            let mu = match nets.head.mu_bound {
                Some(bd) => {
                    tanh[i] = raw[i].tanh();
                    tanh[i] * bd as f32
                }
                None => raw[i],
            };
            zs[i] = (act[i] - mu) / sigma[i];
            logp += -0.5 * zs[i] * zs[i] - log_std[i] - half_log_2pi;
        }
        let log_ratio = logp - mb.old_logp[b];
        let r = log_ratio.exp();
        let adv = mb.advantage[b];
        let unclipped = r * adv;
        let rc = r.max(1.0 - eps).min(1.0 + eps);
        let clipped = rc * adv;
        policy_loss -= unclipped.min(clipped) as f64;
        kl += ((r - 1.0) - log_ratio) as f64;
        outside += ((r - 1.0).abs() > eps) as usize;
        // d(−mean min(rA, clip(r)A))/dr, ties split as candle's min and clamp split them.
        let tie = unclipped == clipped;
        let clip_pass = share(r > 1.0 - eps, r == 1.0 - eps)
            * share(r.max(1.0 - eps) < 1.0 + eps, r.max(1.0 - eps) == 1.0 + eps);
        let dmin_dr =
            adv * (share(unclipped < clipped, tie) + share(clipped < unclipped, tie) * clip_pass);
        let dlogp = -inv_n * dmin_dr * r;
        for i in 0..na {
            // ∂logp/∂μ = z/σ, ∂logp/∂log σ = z² − 1.
            let dmu = dlogp * zs[i] / sigma[i];
            d_raw[b * na + i] = match nets.head.mu_bound {
                Some(bd) => dmu * bd as f32 * (1.0 - tanh[i] * tanh[i]),
                None => dmu,
            };
            d_log_std[i] += (dlogp * (zs[i] * zs[i] - 1.0)) as f64;
        }
    }
    // The entropy bonus −β·mean_b Σ_i (log σ_i + ½ ln 2πe): −β on each log σ_i.
    let half_log_2pi_e = 0.5 * (1.0 + (2.0 * std::f64::consts::PI).ln());
    let entropy: f64 = log_std.iter().map(|&l| l as f64 + half_log_2pi_e).sum();
    let beta = cfg.entropy_coef;

    // The agent's backward before the critic's part is waited for: the larger share of
    // the overlap.
    let a_grads = agent.backward(&mb.obs, &a_acts, d_raw, n);
    let (c_grads, value_loss) = match critic_job {
        Some(job) => job
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
        None => value_grads(critic, mb, nets),
    };
    let policy_loss = policy_loss * inv_n as f64;
    let pl = check_finite("policy_loss", policy_loss as f32)?;
    let vl = check_finite("value_loss", value_loss as f32)?;
    check_finite(
        "loss",
        (policy_loss + nets.value_coef * value_loss - beta * entropy) as f32,
    )?;

    let mut grads = Vec::with_capacity(2 * (nets.agent.len() + nets.critic.len()) + 1);
    for (layers, g) in [(&nets.agent, a_grads), (&nets.critic, c_grads)] {
        for (l, (dw, db)) in layers.iter().zip(g) {
            grads.push((l.w.id(), dw));
            grads.push((l.b.id(), db));
        }
    }
    let d_ls: Vec<f32> = d_log_std
        .iter()
        .zip(&ls_pass)
        .map(|(&g, &p)| (g as f32 - beta as f32) * p)
        .collect();
    grads.push((nets.log_std.id(), d_ls));

    totals.policy_loss += pl as f64;
    totals.value_loss += vl as f64;
    totals.entropy += entropy;
    totals.approx_kl += kl / n as f64;
    totals.clip_fraction += outside as f64 / n as f64;
    Ok(grads)
}

/// Each critic layer's (dW, db) and the value loss over a minibatch: c_v·mean (V − R)²,
/// or the larger of it and the clipped one's.
type CriticGrads = (Vec<(Vec<f32>, Vec<f32>)>, f64);

/// The critic's part of [`step_grads`]: V [n, c], its loss and its gradients.
fn value_grads(critic: &HostMlp, mb: &Minibatch, nets: &Nets) -> CriticGrads {
    let (n, c, cfg) = (mb.n, nets.c, nets.cfg);
    let c_acts = critic.forward(&mb.obs, n);
    let v = &c_acts[c_acts.len() - 1];
    let scale = (2.0 * nets.value_coef / (n * c) as f64) as f32;
    let mut dv = vec![0.0f32; n * c];
    let mut value_loss = 0.0f64;
    for e in 0..n * c {
        let diff = v[e] - mb.returns[e];
        let err = diff * diff;
        match cfg.value_clip {
            Some(vc) => {
                let vc = vc as f32;
                let moved = v[e] - mb.old_value[e];
                let mc = moved.max(-vc).min(vc);
                let pass = share(moved > -vc, moved == -vc)
                    * share(moved.max(-vc) < vc, moved.max(-vc) == vc);
                let cdiff = (mb.old_value[e] + mc) - mb.returns[e];
                let cerr = cdiff * cdiff;
                let tie = err == cerr;
                value_loss += err.max(cerr) as f64;
                dv[e] =
                    scale * (diff * share(err > cerr, tie) + cdiff * pass * share(cerr > err, tie));
            }
            None => {
                value_loss += err as f64;
                dv[e] = scale * diff;
            }
        }
    }
    let value_loss = value_loss / (n * c) as f64;
    let grads = critic.backward(&mb.obs, &c_acts, dv, n);
    (grads, value_loss)
}
