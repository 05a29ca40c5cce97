//! SAVER's minibatch step by hand on the host (the passes of `saver.epochs`, on the CPU,
//! for layouts without a categorical choice; docs/PERFORMANCE.md): agent, vector critic
//! and env critic forward and backward with gemm into plain buffers (algo/host_mlp.rs),
//! the PCPN's trunk by gemm around its fused blocks, and the env term, the saturation
//! wall and the critics' losses written out; the optimiser steps its host copy of the
//! weights. The step through candle (step.rs: the losses, autograd, `Optimizer::step`)
//! is its reference, which a test holds it to (epochs.rs).
//!
//! For the rows' outputs μ = bound·tanh(μ_raw), log σ = clamp(ℓ) (ℓ the variable), the
//! gradient at (μ, log σ) of each row is the PCPN term's dL/dx plus c times the env
//! term's, c = w·|g_v| / |g_r| (env_return.rs), and with log π = Σ_i −½z_i² − log σ_i −
//! ½ ln 2π, z = (a − μ)/σ, the env term's −mean ω·log π gives −ω/n·z/σ on μ and
//! −ω/n·(z² − 1) on log σ (ω = Â_r, or ρ·Â_r and 0 where the clip holds).

use super::env_return::EnvReturn;
use super::grad::TrunkScratch;
use super::step::Losses;
use super::{Saver, Start};
use crate::algo::host_mlp::{clamped_log_std, layer_grads, value, HostMlp, MlpScratch};
use crate::algo::{check_finite, gather_rows};
use crate::config::MU_RAW_LIMIT;
use crate::nets::Linear;
use crate::optim::{join_if, HostState};
use crate::rng::uniform01;
use crate::rollout::Batch;
use crate::Result;

/// One minibatch's rows on the host, row-major.
struct HostRows<'a> {
    n: usize,
    /// [n, o], raw.
    obs: &'a [f32],
    /// [n, d]: Δp targets, advantages and the vector critic's targets.
    target: &'a [f32],
    adv: &'a [f32],
    returns: &'a [f32],
    /// The env term's rows, when it learns from this batch.
    env: Option<HostEnvRows<'a>>,
    /// For the KL stop of `saver.target_kl`: the rows' actions [n, a] and their log μ(a|o)
    /// under the policy that acted.
    kl_check: Option<(&'a [f32], &'a [f32])>,
}

/// The env term's rows: the scalar critic's targets, the advantages Â_r, the actions
/// and, with the clip, log μ(a|o) of the policy that acted.
struct HostEnvRows<'a> {
    returns: &'a [f32],
    adv: &'a [f32],
    actions: &'a [f32],
    logp_b: Option<&'a [f32]>,
}

/// The buffers of the host step, kept across an update's minibatches.
#[derive(Default)]
pub(super) struct HostScratch {
    seen: Vec<f32>,
    x: Vec<f32>,
    xc: Vec<f32>,
    agent: MlpScratch,
    critic: MlpScratch,
    env_critic: MlpScratch,
    trunk: TrunkScratch,
    d_log_std: Vec<f32>,
}

/// The policy outputs of some rows: μ [n, M], tanh(μ_raw) where bounded, log σ and
/// the share of its gradient that passes the clamp ([L] each).
struct Outputs {
    mu: Vec<f32>,
    tanh: Vec<f32>,
    log_std: Vec<f32>,
    ls_pass: Vec<f32>,
}

/// Σ log N(a | μ, σ²) over a row's entries.
fn log_prob(mu: &[f32], log_std: &[f32], a: &[f32]) -> f32 {
    let half_log_2pi = 0.5 * (2.0 * std::f32::consts::PI).ln();
    mu.iter()
        .zip(log_std)
        .zip(a)
        .map(|((m, l), a)| {
            let z = (a - m) / l.exp();
            -0.5 * z * z - l - half_log_2pi
        })
        .sum()
}

impl Saver {
    /// Whether the passes of `saver.epochs` take the host step.
    pub(super) fn host_path(&self) -> bool {
        self.path == crate::algo::GradPath::Fast && self.layout.choices == 0 && self.dev.is_cpu()
    }

    /// A pool of two threads for an update's host steps where the PCPN's blocks run on
    /// two or more (`Algorithm::set_threads`); none (the same bits on one thread) where
    /// they run on one or the OS refuses threads.
    pub(super) fn step_pool(&self) -> Option<rayon::ThreadPool> {
        if crate::algo::threads_for(self.pcpn.threads()) < 2 {
            return None;
        }
        crate::optim::pool_of_two("SAVER's")
    }

    /// The policy's outputs for rows whose agent output (μ_raw) is `raw` [n, M].
    fn outputs(&self, h: &HostState, raw: &[f32]) -> Result<Outputs> {
        let head = self.agent.head();
        let var = value(h, self.agent.log_std_var())?;
        let (log_std, ls_pass) = clamped_log_std(var, head.log_std_bounds);
        let (mu, tanh) = match head.mu_bound {
            Some(b) => {
                let t: Vec<f32> = raw.iter().map(|r| r.tanh()).collect();
                (t.iter().map(|t| t * b as f32).collect(), t)
            }
            None => (raw.to_vec(), Vec::new()),
        };
        Ok(Outputs {
            mu,
            tanh,
            log_std,
            ls_pass,
        })
    }

    /// The host step on the rows `idx` of `batch`, whose update started with `s`;
    /// `behaviour` is the batch's log μ(a|o) where the update has it, and `kl_stop` says
    /// whether this minibatch checks the KL stop.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn host_minibatch(
        &mut self,
        h: &mut HostState,
        scratch: &mut HostScratch,
        batch: &Batch,
        s: &Start,
        idx: &[usize],
        behaviour: Option<&[f32]>,
        kl_stop: bool,
        pooled: bool,
    ) -> Result<Option<(Losses, Vec<f32>)>> {
        let rows = |data: &[f32], w: usize| gather_rows(data, idx, w);
        let (o, d, a) = (
            self.layout.obs_dim,
            self.layout.aligned_dim,
            self.layout.action_dim(),
        );
        let (obs, target, adv) = (
            rows(&batch.obs, o),
            rows(&s.target, d),
            rows(&s.adv_host, d),
        );
        let (returns, actions) = (rows(&s.returns_host, d), rows(&batch.actions, a));
        let logp_b = behaviour.map(|l| rows(l, 1));
        let env_cols = match (&self.env, &s.env) {
            (Some(_), Some(t)) => Some((rows(&t.returns, 1), rows(&t.advantages, 1))),
            _ => None,
        };
        let clips = self.env.as_ref().is_some_and(|e| e.clips());
        let r = HostRows {
            n: idx.len(),
            obs: &obs,
            target: &target,
            adv: &adv,
            returns: &returns,
            env: env_cols.as_ref().map(|(ret, ad)| HostEnvRows {
                returns: ret,
                adv: ad,
                actions: &actions,
                logp_b: logp_b.as_deref().filter(|_| clips),
            }),
            kl_check: logp_b
                .as_deref()
                .filter(|_| kl_stop)
                .map(|l| (&actions[..], l)),
        };
        self.host_step(h, scratch, &r, pooled)
    }

    /// One minibatch step on the host state `h`: the step's losses with the gradient
    /// norm and the PCPN term's dL/dμ per row, or `None` where the KL stop holds (nothing
    /// changed). A non-finite loss or step is an error with `h` unusable (drop it).
    fn host_step(
        &mut self,
        h: &mut HostState,
        s: &mut HostScratch,
        r: &HostRows,
        pooled: bool,
    ) -> Result<Option<(Losses, Vec<f32>)>> {
        let (n, o, d, k) = (
            r.n,
            self.layout.obs_dim,
            self.layout.aligned_dim,
            self.cfg.quantiles,
        );
        let (m, l) = (self.layout.mu_dim(), self.layout.log_std_dim());
        let (i, lc) = (o + m + l, self.cfg.lambda_critic);
        // The observations as the agent and critics read them.
        s.seen.clear();
        s.seen.extend_from_slice(r.obs);
        if let Some(scale) = &self.obs_norm {
            let (mean, std, bound) = scale.mean_std();
            crate::nets::obs_norm::normalize(&mut s.seen, &mean, &std, bound.as_deref());
        }
        let agent_layers = self.agent.layers();
        let agent = HostMlp::of(&agent_layers, h)?;
        agent.forward(&s.seen, n, &mut s.agent);
        let raw = &s.agent.acts[s.agent.acts.len() - 1];
        let out = self.outputs(h, raw)?;
        if let Some((actions, logp_b)) = r.kl_check {
            let a = self.layout.action_dim();
            let kl: f64 = (0..n)
                .map(|b| {
                    let lp = log_prob(
                        &out.mu[b * m..(b + 1) * m],
                        &out.log_std,
                        &actions[b * a..b * a + m],
                    );
                    let log_ratio = (lp - logp_b[b]) as f64;
                    log_ratio.exp_m1() - log_ratio
                })
                .sum::<f64>()
                / n as f64;
            if kl > self.cfg.target_kl {
                return Ok(None);
            }
        }
        // The PCPN's input [o, μ, log σ] and the critics' [seen, μ, log σ].
        for (buf, obs) in [(&mut s.x, r.obs), (&mut s.xc, &s.seen[..])] {
            buf.clear();
            for b in 0..n {
                buf.extend_from_slice(&obs[b * o..(b + 1) * o]);
                buf.extend_from_slice(&out.mu[b * m..(b + 1) * m]);
                buf.extend_from_slice(&out.log_std);
            }
        }
        // The critics (λ_c·mean (V − R)², dV = 2λ_c/(n·c)·(V − R), forward and
        // backward) beside the PCPN term, whose blocks the second worker takes over
        // once the critics are done (τ drawn where the reference step draws them).
        let critic_layers: Vec<&Linear> = self.critic.layers().iter().collect();
        let env_layers: Vec<&Linear> = match &self.env {
            Some(e) => e.critic_layers(),
            None => Vec::new(),
        };
        let env = match (&self.env, &r.env) {
            (Some(term), Some(e)) => Some((term, e)),
            _ => None,
        };
        let env_returns = env.map(|(_, e)| e.returns);
        let taus = uniform01(&mut self.rng, d * n * k);
        let HostScratch {
            x,
            xc,
            critic: critic_s,
            env_critic: env_s,
            trunk,
            ..
        } = s;
        let (pcpn, cfg) = (&self.pcpn, &self.cfg);
        let (critics, (actor, mon)) = join_if(
            pooled,
            || -> Result<(f64, Option<f64>)> {
                let critic = HostMlp::of(&critic_layers, h)?;
                critic.forward(xc, n, critic_s);
                let loss = squared_error(critic_s, r.returns, lc);
                critic.backward(xc, n, critic_s);
                let env_loss = match env_returns {
                    Some(returns) => {
                        let net = HostMlp::of(&env_layers, h)?;
                        net.forward(xc, n, env_s);
                        let loss = squared_error(env_s, returns, lc);
                        net.backward(xc, n, env_s);
                        Some(loss)
                    }
                    None => None,
                };
                Ok((loss, env_loss))
            },
            || pcpn.input_grad_host(x, n, r.target, r.adv, &taus, cfg, trunk, pooled),
        );
        let (critic_loss, env_critic_loss) = critics?;
        let dx = &s.trunk.dx;
        let mut g_mu: Vec<f32> = (0..n)
            .flat_map(|b| dx[b * i + o..b * i + o + m].iter().copied())
            .collect();
        let dmu = g_mu.clone();
        let mut g_ls: Vec<f32> = (0..n)
            .flat_map(|b| dx[b * i + o + m..(b + 1) * i].iter().copied())
            .collect();
        // The env term.
        let (mut env_pg, mut env_scale) = (0.0, 0.0);
        let env_critic = match env_critic_loss {
            Some(l) => check_finite("env_critic_loss", l as f32)?,
            None => 0.0,
        };
        if let Some((term, e)) = env {
            let dims = (m, l, self.layout.action_dim());
            let (unit, c) = env_push(term, e, &out, dims, &mut g_mu, &mut g_ls);
            env_pg = check_finite("env_pg_loss", unit as f32)?;
            env_scale = check_finite("env_pg_scale", c)?;
        }
        let losses = Losses {
            actor: check_finite("actor_loss", actor)?,
            mon: check_finite("mon_loss", mon)?,
            critic: check_finite("critic_loss", critic_loss as f32)?,
            grad_norm: 0.0,
            env_pg,
            env_scale,
            env_critic,
        };
        // Into the agent: through the bound's tanh, plus the saturation wall's
        // w/n·2·relu(|raw| − limit)·sign(raw) on its entries.
        let bound = self.agent.head().mu_bound;
        let d_raw = &mut s.agent.dy;
        d_raw.clear();
        d_raw.extend(g_mu.iter().enumerate().map(|(e, &g)| match bound {
            Some(bd) => g * bd as f32 * (1.0 - out.tanh[e] * out.tanh[e]),
            None => g,
        }));
        let w = self.cfg.mu_raw_penalty;
        if w != 0.0 {
            let raw = &s.agent.acts[s.agent.acts.len() - 1];
            let entries = &self.cfg.mu_raw_penalty_entries;
            let scale = (2.0 * w / n as f64) as f32;
            for (e, (g, &x)) in d_raw.iter_mut().zip(raw).enumerate() {
                let over = (x.abs() - MU_RAW_LIMIT as f32).max(0.0);
                if over > 0.0 && (entries.is_empty() || entries.contains(&(e % m))) {
                    *g += scale * over * x.signum();
                }
            }
        }
        s.d_log_std.clear();
        s.d_log_std.extend((0..l).map(|j| {
            let sum: f64 = (0..n).map(|b| g_ls[b * l + j] as f64).sum();
            sum as f32 * out.ls_pass[j]
        }));
        agent.backward(&s.seen, n, &mut s.agent);
        let mut grads = Vec::with_capacity(2 * (agent_layers.len() + 2 * critic_layers.len()) + 1);
        layer_grads(&agent_layers, &s.agent.grads, &mut grads);
        grads.push((self.agent.log_std_var().id(), &s.d_log_std[..]));
        layer_grads(&critic_layers, &s.critic.grads, &mut grads);
        if env.is_some() {
            layer_grads(&env_layers, &s.env_critic.grads, &mut grads);
        }
        let grad_norm = self.opt.step_host(h, &grads)? as f32;
        Ok(Some((
            Losses {
                grad_norm,
                ..losses
            },
            dmu,
        )))
    }
}

/// The env term at the policy outputs `out` of `e`'s rows: its push on (μ, log σ),
/// scaled to c = w·|g_v| / |g_r| against the PCPN term's gradient (`g_mu`, `g_ls`, to
/// which it is added); returns the unit loss and c. `dims` = (M, L, action_dim).
fn env_push(
    term: &EnvReturn,
    e: &HostEnvRows,
    out: &Outputs,
    (m, l, a): (usize, usize, usize),
    g_mu: &mut [f32],
    g_ls: &mut [f32],
) -> (f64, f32) {
    let n = e.adv.len();
    let inv_n = 1.0 / n as f32;
    // Per row: its log π's gradient at (μ, log σ) scaled by the plain weight −Â_r/n
    // and by the push's −ω/n.
    let (mut plain_sq, mut surrogate, mut plain_loss) = (0.0f64, 0.0f64, 0.0f64);
    let mut push_mu = vec![0.0f32; n * m];
    let mut push_ls = vec![0.0f32; n * l];
    for b in 0..n {
        let mu = &out.mu[b * m..(b + 1) * m];
        let act = &e.actions[b * a..b * a + m];
        let lp = log_prob(mu, &out.log_std, act);
        let adv = e.adv[b];
        plain_loss -= (adv * lp) as f64;
        let omega = match e.logp_b {
            Some(logp_b) => {
                let eps = term.clip_eps();
                let (rho, a64) = (((lp - logp_b[b]) as f64).exp(), adv as f64);
                surrogate += (rho * a64).min(rho.clamp(1.0 - eps, 1.0 + eps) * a64);
                let held = (a64 > 0.0 && rho > 1.0 + eps) || (a64 < 0.0 && rho < 1.0 - eps);
                if held {
                    0.0
                } else {
                    (rho * a64) as f32
                }
            }
            None => adv,
        };
        for j in 0..m {
            let sigma = out.log_std[j].exp();
            let z = (act[j] - mu[j]) / sigma;
            let (dlp_mu, dlp_ls) = (z / sigma, z * z - 1.0);
            let (pm, pl) = (-adv * inv_n * dlp_mu, -adv * inv_n * dlp_ls);
            plain_sq += (pm * pm + pl * pl) as f64;
            push_mu[b * m + j] = -omega * inv_n * dlp_mu;
            push_ls[b * l + j] = -omega * inv_n * dlp_ls;
        }
    }
    let sq = |v: &[f32]| v.iter().map(|x| (x * x) as f64).sum::<f64>();
    let c = term.scale_of((sq(g_mu) + sq(g_ls)).sqrt(), plain_sq.sqrt());
    for (g, p) in g_mu.iter_mut().zip(&push_mu) {
        *g += c * p;
    }
    for (g, p) in g_ls.iter_mut().zip(&push_ls) {
        *g += c * p;
    }
    let unit = match e.logp_b {
        Some(_) => -surrogate / n as f64,
        None => plain_loss / n as f64,
    };
    (unit, c)
}

/// `λ·mean (V − R)²` over an MLP's last output V [n, c] in `s` against `returns`, with its
/// gradient 2λ/(n·c)·(V − R) into `s.dy`.
fn squared_error(s: &mut MlpScratch, returns: &[f32], lambda: f64) -> f64 {
    let v = &s.acts[s.acts.len() - 1];
    let scale = (2.0 * lambda / v.len() as f64) as f32;
    s.dy.clear();
    let mut sum = 0.0f64;
    for (v, r) in v.iter().zip(returns) {
        let diff = v - r;
        sum += (diff * diff) as f64;
        s.dy.push(scale * diff);
    }
    lambda * sum / v.len() as f64
}
