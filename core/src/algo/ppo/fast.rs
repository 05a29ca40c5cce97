//! PPO's minibatch step by hand on the host (the default on the CPU for layouts without
//! a categorical choice): the agent's and critic's MLPs forward and backward with gemm
//! into plain buffers, the clipped surrogate, value loss and entropy bonus written out.
//! candle's graph of the same step (`Ppo::reference_grads`, `GradPath::Reference`) runs
//! ~60 small tensor ops forward and as many backward a minibatch, each with its
//! allocation and element-wise pass; here the element-wise work is one loop per layer.
//! Its gradients equal the reference's to rounding (tested), ties of min/max/clamp split
//! as candle splits them.

use super::minibatch::{Minibatch, Totals};
use crate::algo::check_finite;
use crate::algo::host_mlp::{clamped_log_std, layer_grads, share, value, HostMlp, MlpScratch};
use crate::config::{HeadConfig, PpoConfig};
use crate::nets::Linear;
use crate::optim::{join_if, HostState};
use crate::Result;
use candle_core::{Tensor, TensorId};

/// The agent's buffers: its MLP's and the log σ gradient.
#[derive(Default)]
struct AgentScratch {
    mlp: MlpScratch,
    d_log_std: Vec<f32>,
}

/// The agent's and critic's buffers of [`step_grads`], made once per update.
#[derive(Default)]
pub(super) struct Scratch {
    agent: AgentScratch,
    critic: MlpScratch,
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
/// `totals` (the stats) and the host gradients [`crate::optim::Optimizer::step_host`]
/// takes, at the weights of the optimiser's host state `h`; the gradients live in
/// `scratch` until its next step. Every action entry is continuous (the caller takes the
/// reference path for a layout with a choice). With `parallel` the critic's forward and
/// backward run beside the agent's by `rayon::join` (on the pool whose `install` calls
/// this).
pub(super) fn step_grads<'s>(
    nets: &Nets,
    h: &HostState,
    mb: &Minibatch,
    parallel: bool,
    totals: &mut Totals,
    scratch: &'s mut Scratch,
) -> Result<Vec<(TensorId, &'s [f32])>> {
    let agent = HostMlp::of(&nets.agent, h)?;
    let critic = HostMlp::of(&nets.critic, h)?;
    let (agent_buffers, critic_buffers) = (&mut scratch.agent, &mut scratch.critic);
    // The two share no sums, so the bits are the same either way.
    let (policy, value_loss) = join_if(
        parallel,
        || policy_grads(nets, &agent, h, mb, agent_buffers),
        || value_grads(&critic, mb, nets, critic_buffers),
    );
    let policy = policy?;
    let beta = nets.cfg.entropy_coef;
    let n = mb.n as f64;
    let policy_loss = policy.loss * (1.0 / mb.n as f32) as f64;
    let pl = check_finite("policy_loss", policy_loss as f32)?;
    let vl = check_finite("value_loss", value_loss as f32)?;
    check_finite(
        "loss",
        (policy_loss + nets.value_coef * value_loss - beta * policy.entropy) as f32,
    )?;
    totals.policy_loss += pl as f64;
    totals.value_loss += vl as f64;
    totals.entropy += policy.entropy;
    totals.approx_kl += policy.kl / n;
    totals.clip_fraction += policy.outside as f64 / n;

    let scratch: &'s Scratch = scratch;
    let mut grads = Vec::with_capacity(2 * (nets.agent.len() + nets.critic.len()) + 1);
    for (layers, g) in [
        (&nets.agent, &scratch.agent.mlp.grads),
        (&nets.critic, &scratch.critic.grads),
    ] {
        layer_grads(layers, g, &mut grads);
    }
    grads.push((nets.log_std.id(), &scratch.agent.d_log_std[..]));
    Ok(grads)
}

/// The agent's sums over a minibatch: the clipped surrogate (summed, not yet averaged),
/// Σ_b KL estimate, the steps whose ratio left [1 − ε, 1 + ε], and the entropy.
struct PolicyPart {
    loss: f64,
    kl: f64,
    outside: usize,
    entropy: f64,
}

/// The agent's part of [`step_grads`]: its forward, the surrogate and entropy bonus,
/// and its backward into `s` (the log σ gradient into `s.d_log_std`).
fn policy_grads(
    nets: &Nets,
    agent: &HostMlp,
    h: &HostState,
    mb: &Minibatch,
    s: &mut AgentScratch,
) -> Result<PolicyPart> {
    let (n, cfg) = (mb.n, nets.cfg);
    let na = agent.layers.last().map_or(0, |l| l.3);
    let raw_log_std = value(h, nets.log_std)?;
    // log σ = clamp(p, lo, hi); candle's clamp is max(p, lo) then min(·, hi).
    let (log_std, ls_pass) = clamped_log_std(raw_log_std, nets.head.log_std_bounds);

    // The agent: μ_raw [n, na], μ = bound·tanh(μ_raw) or μ_raw.
    agent.forward(&mb.obs, n, &mut s.mlp);
    let mu_raw = &s.mlp.acts[s.mlp.acts.len() - 1];
    let eps = cfg.clip as f32;
    let half_log_2pi = 0.5 * (2.0 * std::f32::consts::PI).ln();
    let inv_n = 1.0 / n as f32;
    let d_raw = &mut s.mlp.dy;
    d_raw.resize(n * na, 0.0); // every element is written below
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
    let beta = cfg.entropy_coef as f32;
    s.d_log_std.clear();
    s.d_log_std.extend(
        d_log_std
            .iter()
            .zip(&ls_pass)
            .map(|(&g, &p)| (g as f32 - beta) * p),
    );
    agent.backward(&mb.obs, n, &mut s.mlp);
    Ok(PolicyPart {
        loss: policy_loss,
        kl,
        outside,
        entropy,
    })
}

/// The critic's part of [`step_grads`]: V [n, c], its loss c_v·mean (V − R)² (or the
/// larger of it and the clipped one's), returned, and its gradients into `s`.
fn value_grads(critic: &HostMlp, mb: &Minibatch, nets: &Nets, s: &mut MlpScratch) -> f64 {
    let (n, c, cfg) = (mb.n, nets.c, nets.cfg);
    critic.forward(&mb.obs, n, s);
    let v = &s.acts[s.acts.len() - 1];
    let scale = (2.0 * nets.value_coef / (n * c) as f64) as f32;
    let dv = &mut s.dy;
    dv.resize(n * c, 0.0); // every element is written below
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
    critic.backward(&mb.obs, n, s);
    value_loss / (n * c) as f64
}
