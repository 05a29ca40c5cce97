//! SAVER's env-return term (docs/ALGORITHM.md §7.2): where the rollouts carry the env's
//! own scalar reward r (Gymnasium's reward, control cost and all), a scalar critic
//! V_r(x) learns its discounted return and the agent also follows the policy gradient
//! of that return, beside the vector term that reaches it through the PCPN:
//!
//! L_r   = −c · mean_B Â_r · log π(a | o)        (agent, Â_r normalised over the batch)
//! L_V_r = λ_c · mean_B (V_r(x) − R_r / s)²       (the scalar critic only)
//!
//! c = w · |∂(L_a + L_mon)/∂(μ, log σ)| / |∂(−mean Â_r log π)/∂(μ, log σ)| on each
//! step's rows: w = `saver.env_reward` is the ratio of the env term's push on the
//! policy outputs to the PCPN's (the PCPN's is ~10⁴ times smaller than a plain policy
//! gradient's, so a fixed weight would hand the update to the env term).
//!
//! with R_r the n-step (or GAE(λ)) return of r / s, s the running root-mean-square of
//! the env's reward per step (so that the critic's targets are of order one whatever
//! the env's units). The term is skipped on a batch whose
//! env reward is the sum of its progress reward (it would count that signal twice) or
//! that carries none (the presets).

use super::grad::OutputLeaves;
use crate::algo::{gather_rows, lambda_targets, matrix};
use crate::config::RunConfig;
use crate::env::EnvLayout;
use crate::nets::{gaussian_log_prob, Critic, ParamSet};
use crate::returns::normalize_advantages;
use crate::rng::SaverRng;
use crate::rollout::Batch;
use crate::Result;
use candle_core::{Device, Tensor};
use std::cell::Cell;

/// The name of the running mean square of the env reward in a checkpoint.
const MEAN_SQUARE: &str = "env_critic.reward_mean_square";
/// Weight of a batch in the running mean square of the env reward.
const MEAN_SQUARE_RATE: f32 = 0.01;

/// The scalar critic and the state of the term.
pub(super) struct EnvReturn {
    /// V_r(o, μ, log σ) ∈ R, named `env_critic.*`.
    critic: Critic,
    /// w.
    weight: f64,
    /// ε of PPO's clip on the term (`saver.env_clip`; 0: none).
    clip: f64,
    /// The running mean square of the env reward per step (0 before the first batch;
    /// a cell so that a batch's targets are made where the update's other targets are).
    mean_square: Cell<f32>,
}

/// What one optimiser step of the term trains on, for some rows.
pub(super) struct EnvRows {
    /// [N, 1]: the scalar critic's targets R_r / s.
    pub returns: Tensor,
    /// [N]: the normalised advantages Â_r.
    pub adv: Tensor,
    /// [N, action_dim]: the actions taken.
    pub actions: Tensor,
    /// With `saver.env_clip` ε > 0: [N] log μ(a|o) of the policy that acted, and ε.
    pub clip: Option<(Vec<f32>, f64)>,
}

/// The term's policy gradient at the policy outputs of some rows.
pub(super) struct EnvGrads {
    /// The unit loss: −mean Â_r·log π, or PPO's clipped surrogate with `clip`.
    pub loss: f32,
    /// (dμ, d log σ) of that loss: the direction the term pushes.
    pub push: (Tensor, Tensor),
    /// (dμ, d log σ) of the plain −mean Â_r·log π (the push itself without a clip), whose
    /// norm sets the scale c, so that rows a clip has stopped do not make the others
    /// push harder.
    pub plain: (Tensor, Tensor),
}

/// A batch's targets and advantages of the term, on the host.
pub(super) struct EnvTargets {
    pub returns: Vec<f32>,
    pub advantages: Vec<f32>,
}

impl EnvReturn {
    /// The term of `config`, or none with `saver.env_reward` 0. Its critic draws its
    /// initial weights from `rng` after the agent's and the vector critic's.
    pub(super) fn of(
        config: &RunConfig,
        layout: &EnvLayout,
        rng: &mut SaverRng,
        dev: &Device,
    ) -> Result<Option<Self>> {
        if config.saver.env_reward == 0.0 {
            return Ok(None);
        }
        let critic = Critic::named(
            "env_critic",
            layout.pcpn_input_dim(),
            1,
            &config.hidden,
            rng,
            dev,
        )?;
        Ok(Some(Self {
            critic,
            weight: config.saver.env_reward,
            clip: config.saver.env_clip,
            mean_square: Cell::new(0.0),
        }))
    }

    /// The critic's trainable variables.
    pub(super) fn params(&self) -> &ParamSet {
        self.critic.params()
    }

    /// Whether the term learns from `batch`: it carries the env's reward, and that
    /// reward is not the sum of the progress reward.
    pub(super) fn applies(batch: &Batch) -> bool {
        if batch.env_reward.is_empty() {
            return false;
        }
        let progress = batch.scalar_reward();
        batch
            .env_reward
            .iter()
            .zip(&progress)
            .any(|(r, p)| (r - p).abs() > 1e-5 * (1.0 + p.abs()))
    }

    /// The scalar critic's targets and the normalised advantages of `batch`, from its
    /// values `v_all` [B + T, 1] at the rows of [`crate::algo::update_rows`] (`n_ends`
    /// timeouts); updates the running mean square of the reward first.
    pub(super) fn targets(
        &self,
        batch: &Batch,
        v_all: &Tensor,
        n_ends: usize,
        gamma: f32,
        lambda: f32,
    ) -> Result<EnvTargets> {
        let b = batch.len();
        let ms = batch.env_reward.iter().map(|r| (r * r) as f64).sum::<f64>() / b.max(1) as f64;
        let before = self.mean_square.get();
        let mean_square = if before == 0.0 {
            ms as f32
        } else {
            (1.0 - MEAN_SQUARE_RATE) * before + MEAN_SQUARE_RATE * ms as f32
        };
        self.mean_square.set(mean_square);
        let scale = mean_square.sqrt().max(1e-6);
        let rewards: Vec<f32> = batch.env_reward.iter().map(|r| r / scale).collect();
        let v_all = v_all.detach();
        let values: Vec<f32> = v_all.narrow(0, 0, b)?.flatten_all()?.to_vec1()?;
        let (mut advantages, returns) =
            lambda_targets(batch, &rewards, &values, &v_all, n_ends, gamma, lambda)?;
        normalize_advantages(&mut advantages, 1, false);
        Ok(EnvTargets {
            returns,
            advantages,
        })
    }

    /// V_r at the inputs `x` [N, pcpn_input_dim] → [N, 1].
    pub(super) fn value(&self, x: &Tensor) -> Result<Tensor> {
        Ok(self.critic.forward(x)?)
    }

    /// The scalar critic's loss `λ_c · mean (V_r(x) − R_r / s)²` on some rows whose
    /// critic inputs are `x`.
    pub(super) fn critic_loss(
        &self,
        x: &Tensor,
        rows: &EnvRows,
        lambda_critic: f64,
    ) -> Result<Tensor> {
        Ok(((self.critic.forward(x)? - &rows.returns)?
            .sqr()?
            .mean_all()?
            * lambda_critic)?)
    }

    /// The unit-weight policy-gradient loss `−mean Â_r · log π(a | o)` at the policy
    /// outputs `mu`, `log_std` (their values only) and its gradient with respect to
    /// them; with `rows.clip` (log μ(a|o), ε) the push is PPO's clipped surrogate
    /// `−mean min(ρ·Â_r, clip(ρ, 1 − ε, 1 + ε)·Â_r)`, ρ = π(a|o)/μ(a|o), whose gradient is
    /// that of `−mean ω·log π` with the detached weights ω = ρ·Â_r, 0 on the rows where
    /// the clip holds (ρ > 1 + ε with Â_r > 0, ρ < 1 − ε with Â_r < 0).
    pub(super) fn policy_grads(
        layout: &EnvLayout,
        mu: &Tensor,
        log_std: &Tensor,
        rows: &EnvRows,
    ) -> Result<EnvGrads> {
        let at = OutputLeaves::of(mu, log_std)?;
        let log_pi = gaussian_log_prob(
            layout,
            at.mu.as_tensor(),
            at.log_std.as_tensor(),
            &rows.actions,
        )?;
        let loss = ((&rows.adv * &log_pi)?.mean_all()? * -1.0)?;
        let plain = at.grads(&loss)?;
        let Some((logp_b, eps)) = &rows.clip else {
            return Ok(EnvGrads {
                loss: loss.to_scalar::<f32>()?,
                push: plain.clone(),
                plain,
            });
        };
        let (logp, adv) = (log_pi.to_vec1::<f32>()?, rows.adv.to_vec1::<f32>()?);
        let (mut weights, mut surrogate) = (Vec::with_capacity(adv.len()), 0f64);
        for ((lp, lb), a) in logp.iter().zip(logp_b).zip(&adv) {
            let (rho, a) = (((lp - lb) as f64).exp(), *a as f64);
            let clipped = rho.clamp(1.0 - eps, 1.0 + eps);
            surrogate += (rho * a).min(clipped * a);
            let held = (a > 0.0 && rho > 1.0 + eps) || (a < 0.0 && rho < 1.0 - eps);
            weights.push(if held { 0.0 } else { (rho * a) as f32 });
        }
        let n = adv.len().max(1);
        let weights = Tensor::from_vec(weights, adv.len(), log_pi.device())?;
        let push = at.grads(&((weights * &log_pi)?.mean_all()? * -1.0)?)?;
        Ok(EnvGrads {
            loss: (-surrogate / n as f64) as f32,
            push,
            plain,
        })
    }

    /// The scale c of the unit policy gradient (g_r) beside the vector term's (g_v),
    /// both over μ and log σ of the same rows: c = w · |g_v| / |g_r|, so that w is the
    /// ratio of the two pushes whatever the env's units (0 where g_r is 0).
    pub(super) fn scale(&self, vector: [&Tensor; 2], env: [&Tensor; 2]) -> Result<f32> {
        let norm = |ts: [&Tensor; 2]| -> Result<f64> {
            let mut sq = 0.0;
            for t in ts {
                sq += t.sqr()?.sum_all()?.to_scalar::<f32>()? as f64;
            }
            Ok(sq.sqrt())
        };
        Ok(self.scale_of(norm(vector)?, norm(env)?))
    }

    /// [`Self::scale`] from the two norms |g_v| and |g_r| (the host step's).
    pub(super) fn scale_of(&self, vector: f64, env: f64) -> f32 {
        if env > 0.0 {
            (self.weight * vector / env) as f32
        } else {
            0.0
        }
    }

    /// ε of the clip (0: none).
    pub(super) fn clip_eps(&self) -> f64 {
        self.clip
    }

    /// The scalar critic's layers, input to output.
    pub(super) fn critic_layers(&self) -> Vec<&crate::nets::Linear> {
        self.critic.layers().iter().collect()
    }

    /// Whether the term clips, and so needs the log μ(a|o) of the policy that acted.
    pub(super) fn clips(&self) -> bool {
        self.clip > 0.0
    }

    /// The rows `idx` (all with `None`) of a batch's targets as one step's [`EnvRows`];
    /// where the term clips, with theirs of `behaviour` (the batch's log μ(a|o) per step).
    pub(super) fn rows(
        &self,
        t: &EnvTargets,
        batch: &Batch,
        idx: Option<&[usize]>,
        behaviour: Option<&[f32]>,
        action_dim: usize,
        dev: &Device,
    ) -> Result<EnvRows> {
        let pick = |data: &[f32], w: usize| -> Vec<f32> {
            idx.map_or_else(|| data.to_vec(), |idx| gather_rows(data, idx, w))
        };
        let n = idx.map_or(batch.len(), <[usize]>::len);
        Ok(EnvRows {
            returns: matrix(&pick(&t.returns, 1), n, 1, dev)?,
            adv: Tensor::from_vec(pick(&t.advantages, 1), n, dev)?,
            actions: matrix(&pick(&batch.actions, action_dim), n, action_dim, dev)?,
            clip: behaviour
                .filter(|_| self.clips())
                .map(|logp_b| (pick(logp_b, 1), self.clip)),
        })
    }

    /// The running mean square as a checkpoint tensor.
    pub(super) fn state(&self, dev: &Device) -> Result<(String, Tensor)> {
        Ok((
            MEAN_SQUARE.into(),
            Tensor::new(&[self.mean_square.get()], dev)?,
        ))
    }

    /// Takes the running mean square back from a checkpoint (0 when it has none).
    pub(super) fn restore(&self, get: &dyn Fn(&str) -> Option<Tensor>) -> Result<()> {
        let saved = match get(MEAN_SQUARE) {
            Some(t) => t
                .flatten_all()?
                .to_vec1::<f32>()?
                .first()
                .copied()
                .unwrap_or(0.0),
            None => 0.0,
        };
        self.mean_square.set(saved);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::algo::tests::{plane_spec, random_batch, random_pcpn};
    use crate::algo::{Algorithm, GradPath, Saver};
    use crate::config::Algo;
    use crate::env::EnvLayout;
    use crate::rollout::Batch;
    use candle_core::{DType, Device, Tensor};

    /// SAVER's config on a custom env of d = 2 (the point mass's layout: 6 entries, 2
    /// actions), with the env-return term at weight `w` and γ = 0.9, λ = 1.
    fn config(w: f64) -> crate::config::RunConfig {
        let spec = plane_spec(1.0, None);
        let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
        (config.saver.env_reward, config.gamma) = (w, 0.9);
        (config.saver.pcpn_tune_lr, config.saver.minibatch_size) = (0.0, 0);
        config
    }

    fn saver(w: f64) -> (Saver, EnvLayout) {
        let config = config(w);
        let l = config.env.layout();
        (
            Saver::new(&config, random_pcpn(&l, DType::F32), &Device::Cpu).unwrap(),
            l,
        )
    }

    fn batch(l: &EnvLayout, env_reward: impl Fn(&Batch, usize) -> f32) -> Batch {
        let done = (0..12).map(|i| i == 4).collect();
        let mut b = random_batch(l, 2, 6, 7, 1.0, done);
        b.env_reward = (0..b.len()).map(|i| env_reward(&b, i)).collect();
        b
    }

    /// The saved tensors named `prefix…`, bit for bit (f32 and the f64 statistics of
    /// `saver.obs_norm`, both exact in f64).
    fn weights(s: &Saver, prefix: &str) -> Vec<(String, Vec<u64>)> {
        let bits = |x: &Tensor| {
            let x = x.to_dtype(DType::F64).unwrap();
            x.flatten_all().unwrap().to_vec1::<f64>().unwrap()
        };
        s.save_state()
            .unwrap()
            .tensors
            .iter()
            .filter(|(n, _)| n.starts_with(prefix))
            .map(|(n, x)| (n.clone(), bits(x).iter().map(|v| v.to_bits()).collect()))
            .collect()
    }

    /// Without the env's reward (a preset's rollouts), or with one that is only the
    /// sum of the progress reward, the term changes nothing: the agent and the vector
    /// critic take the same step, bit for bit, as a run without the term.
    #[test]
    fn no_env_reward_or_the_progress_reward_leaves_the_paper_update() {
        let (mut off, l) = saver(0.0);
        let plain = batch(&l, |_, _| 0.0);
        let mut none = plain.clone();
        none.env_reward.clear();
        let progress = batch(&l, |b, i| {
            b.vector_reward[2 * i] + b.vector_reward[2 * i + 1]
        });
        off.update(&none).unwrap();
        for b in [&none, &progress] {
            let (mut on, _) = saver(0.5);
            let stats = on.update(b).unwrap();
            for net in ["agent", "critic."] {
                assert_eq!(weights(&on, net), weights(&off, net), "{net}");
            }
            let pg = stats.values.iter().find(|v| v.0 == "env_pg_loss").unwrap();
            assert_eq!(pg.1, 0.0);
        }
        // A real env reward moves the agent elsewhere.
        let (mut on, _) = saver(0.5);
        on.update(&plain).unwrap_or_else(|e| panic!("{e}"));
        let (mut cost, _) = saver(0.5);
        let actions = plain.actions.clone();
        cost.update(&batch(&l, |_, i| {
            -(actions[2 * i].powi(2) + actions[2 * i + 1].powi(2))
        }))
        .unwrap();
        assert_ne!(weights(&cost, "agent"), weights(&off, "agent"));
    }

    /// The scalar critic's targets are the n-step returns of r / s, s the root mean
    /// square of the batch's rewards (the first batch sets it), by the recursion
    /// written out here: R_t = r_t / s + γ·R_(t+1), 0 after an episode's end, V of the
    /// trajectory's last observation after its last step; γ = 0.9. The advantages
    /// R − V are normalised to mean 0 and variance 1.
    #[test]
    fn targets_are_the_scaled_n_step_returns() {
        let (s, l) = saver(0.5);
        let b = batch(&l, |_, i| -0.5 + 0.1 * i as f32);
        let start = s.start(&b).unwrap();
        let t = start.env.expect("the term runs");
        let env = s.env.as_ref().unwrap();
        let scale = (b.env_reward.iter().map(|r| r * r).sum::<f32>() / 12.0).sqrt();
        let last = crate::algo::matrix(&b.last_obs, 2, l.obs_dim, &Device::Cpu).unwrap();
        let fwd = s.forward(last).unwrap();
        let boot: Vec<f32> = env
            .value(&fwd.xc)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let mut want = vec![0f32; 12];
        for (e, &b0) in boot.iter().enumerate() {
            let mut next = b0;
            for k in (0..6).rev() {
                let i = e * 6 + k;
                if b.done[i] {
                    next = 0.0;
                }
                want[i] = b.env_reward[i] / scale + 0.9 * next;
                next = want[i];
            }
        }
        for (i, (got, want)) in t.returns.iter().zip(&want).enumerate() {
            assert!((got - want).abs() < 1e-5, "row {i}: {got} against {want}");
        }
        let mean = t.advantages.iter().sum::<f32>() / 12.0;
        let var = t.advantages.iter().map(|a| (a - mean).powi(2)).sum::<f32>() / 12.0;
        assert!(
            mean.abs() < 1e-5 && (var - 1.0).abs() < 1e-3,
            "{mean} {var}"
        );
    }

    /// The env term's λ is `saver.env_gae_lambda`, not the vector term's
    /// `saver.gae_lambda`: with the vector λ at 0.5 the env term's targets are those of
    /// λ = 1 to the bit while the vector advantages move, and its own λ at 0.5 moves
    /// its returns.
    #[test]
    fn the_env_term_has_a_lambda_of_its_own() {
        let b = batch(&saver(0.5).1, |_, i| -0.5 + 0.1 * i as f32);
        let start = |vector: f64, env: f64| {
            let mut config = config(0.5);
            (config.saver.gae_lambda, config.saver.env_gae_lambda) = (vector, env);
            let l = config.env.layout();
            let s = Saver::new(&config, random_pcpn(&l, DType::F32), &Device::Cpu).unwrap();
            let st = s.start(&b).unwrap();
            let t = st.env.expect("the term runs");
            (t.returns, t.advantages, st.adv_host)
        };
        let (plain, vector_only, env_only) = (start(1.0, 1.0), start(0.5, 1.0), start(1.0, 0.5));
        assert_eq!((&plain.0, &plain.1), (&vector_only.0, &vector_only.1));
        assert_ne!(plain.2, vector_only.2);
        assert_ne!(plain.0, env_only.0);
        assert_eq!(plain.2, env_only.2);
    }

    /// The unit L_r = −mean_B Â·log π(a|o), log π of the diagonal Gaussian written out:
    /// Σ_i −(a_i − μ_i)² / (2σ_i²) − log σ_i − ½ log 2π, on 3 rows of 2 actions, with
    /// its gradient; and the scale c = w·|g_v|/|g_r| (|(3, 4)| = 5, |(0, 10)| = 10).
    #[test]
    fn the_policy_gradient_loss_is_the_weighted_log_likelihood() {
        let (s, l) = saver(0.5);
        let env = s.env.as_ref().unwrap();
        let dev = Device::Cpu;
        let mu = [0.1f32, -0.2, 0.3, 0.0, -0.5, 0.4];
        let log_std = [-1.0f32, -0.5, 0.0, -0.2, -0.8, -1.2];
        let actions = [0.3f32, -0.1, 0.0, 0.5, -0.2, 0.9];
        let adv = [1.0f32, -0.5, 0.25];
        let rows = super::EnvRows {
            returns: Tensor::zeros((3, 1), DType::F32, &dev).unwrap(),
            adv: Tensor::new(&adv, &dev).unwrap(),
            actions: Tensor::from_slice(&actions, (3, 2), &dev).unwrap(),
            clip: None,
        };
        let t = |v: &[f32]| Tensor::from_slice(v, (3, 2), &dev).unwrap();
        let e = super::EnvReturn::policy_grads(&l, &t(&mu), &t(&log_std), &rows).unwrap();
        let (pg, (dmu, dls)) = (e.loss, e.push);
        let want = -(0..3)
            .map(|r| adv[r] as f64 * row_log_prob(&mu, &log_std, &actions, r))
            .sum::<f64>()
            / 3.0;
        assert!((pg as f64 - want).abs() < 1e-5, "{pg} against {want}");
        // Its gradient: dL/dμ = −Â (a − μ) / (3σ²), dL/dlog σ = −Â ((a − μ)²/σ² − 1) / 3.
        let (dmu, dls) = (dmu.to_vec2::<f32>().unwrap(), dls.to_vec2::<f32>().unwrap());
        for r in 0..3 {
            for j in 0..2 {
                let (m, ls, a) = (
                    mu[2 * r + j] as f64,
                    log_std[2 * r + j] as f64,
                    actions[2 * r + j] as f64,
                );
                let var = (2.0 * ls).exp();
                let gm = -(adv[r] as f64) * (a - m) / var / 3.0;
                let gs = -(adv[r] as f64) * ((a - m).powi(2) / var - 1.0) / 3.0;
                assert!((dmu[r][j] as f64 - gm).abs() < 1e-5, "dμ {r} {j}");
                assert!((dls[r][j] as f64 - gs).abs() < 1e-5, "dlog σ {r} {j}");
            }
        }
        // The scale: w = 0.5 times the ratio of the norms.
        let v = Tensor::new(&[[3.0f32, 4.0]], &dev).unwrap();
        let z = Tensor::zeros((1, 2), DType::F32, &dev).unwrap();
        let r = Tensor::new(&[[0.0f32, 10.0]], &dev).unwrap();
        assert_eq!(env.scale([&v, &z], [&r, &z]).unwrap(), 0.25);
        assert_eq!(env.scale([&v, &z], [&z, &z]).unwrap(), 0.0);
    }

    /// log π(a|o) of row r of 2-action rows: Σ_i −(a_i − μ_i)² / (2σ_i²) − log σ_i − ½ log 2π.
    fn row_log_prob(mu: &[f32], log_std: &[f32], actions: &[f32], r: usize) -> f64 {
        (2 * r..2 * r + 2)
            .map(|i| {
                let (m, ls, a) = (mu[i] as f64, log_std[i] as f64, actions[i] as f64);
                -(a - m).powi(2) / (2.0 * (2.0 * ls).exp())
                    - ls
                    - 0.5 * (2.0 * std::f64::consts::PI).ln()
            })
            .sum()
    }

    /// PPO's clip on the term (`saver.env_clip` ε = 0.2), the behaviour's log μ(a|o) set
    /// so that ρ = 1.5, 0.5, 1.1 on rows with Â = 1, −0.5, 0.25: rows 0 and 1 have moved
    /// past 1 ± ε the way their advantage wants, so they push nothing; row 2 pushes
    /// ρ·Â = 0.275 times its log-likelihood's gradient. The surrogate is
    /// −(min(1.5, 1.2)·1 + min(−0.25, −0.4) + 0.275) / 3 = −(1.2 − 0.4 + 0.275) / 3, and the
    /// plain gradient (for the scale) is the unclipped one's.
    #[test]
    fn the_clipped_term_stops_the_rows_that_moved_past_the_clip() {
        let (_, l) = saver(0.5);
        let dev = Device::Cpu;
        let mu = [0.1f32, -0.2, 0.3, 0.0, -0.5, 0.4];
        let log_std = [-1.0f32, -0.5, 0.0, -0.2, -0.8, -1.2];
        let actions = [0.3f32, -0.1, 0.0, 0.5, -0.2, 0.9];
        let adv = [1.0f32, -0.5, 0.25];
        let rho = [1.5f64, 0.5, 1.1];
        let logp_b = (0..3)
            .map(|r| (row_log_prob(&mu, &log_std, &actions, r) - rho[r].ln()) as f32)
            .collect();
        let rows = |clip| super::EnvRows {
            returns: Tensor::zeros((3, 1), DType::F32, &dev).unwrap(),
            adv: Tensor::new(&adv, &dev).unwrap(),
            actions: Tensor::from_slice(&actions, (3, 2), &dev).unwrap(),
            clip,
        };
        let t = |v: &[f32]| Tensor::from_slice(v, (3, 2), &dev).unwrap();
        let grads =
            |rows| super::EnvReturn::policy_grads(&l, &t(&mu), &t(&log_std), &rows).unwrap();
        let (plain, clipped) = (grads(rows(None)), grads(rows(Some((logp_b, 0.2)))));
        let want = -(1.2 - 0.4 + 0.275) / 3.0;
        assert!(
            (clipped.loss as f64 - want).abs() < 1e-5,
            "{} against {want}",
            clipped.loss
        );
        let v = |x: &Tensor| x.to_vec2::<f32>().unwrap();
        for (p, c) in [
            (&plain.push.0, &clipped.push.0),
            (&plain.push.1, &clipped.push.1),
        ] {
            let (p, c) = (v(p), v(c));
            for j in 0..2 {
                assert_eq!((c[0][j], c[1][j]), (0.0, 0.0), "held rows push");
                // Plain row 2 is −0.25·∇log π / 3; clipped −0.275·∇log π / 3.
                assert!(
                    (c[2][j] - 1.1 * p[2][j]).abs() < 1e-6,
                    "row 2: {} vs {}",
                    c[2][j],
                    p[2][j]
                );
            }
        }
        assert_eq!(v(&clipped.plain.0), v(&plain.push.0));
        assert_eq!(v(&clipped.plain.1), v(&plain.push.1));
    }

    /// The clip reaches the one-step update too (a lagged batch's behaviour is not the
    /// current policy): on a batch whose payload policy is far from the fresh agent's,
    /// ε = 0.05 moves the agent elsewhere than no clip, the vector critic not at all.
    #[test]
    fn the_one_step_update_clips_to_the_policy_that_acted() {
        let b = batch(&saver(0.5).1, |_, i| -0.1 * i as f32);
        let run = |eps: f64| {
            let mut config = config(0.5);
            // One optimiser step per batch (the custom-env default makes two passes).
            (config.saver.env_clip, config.saver.epochs) = (eps, 1);
            config.saver.minibatch_size = 0;
            let l = config.env.layout();
            let mut s = Saver::new(&config, random_pcpn(&l, DType::F32), &Device::Cpu).unwrap();
            s.update(&b).unwrap();
            (weights(&s, "agent"), weights(&s, "critic."))
        };
        let (plain, clipped) = (run(0.0), run(0.05));
        assert_ne!(plain.0, clipped.0);
        assert_eq!(plain.1, clipped.1);
    }

    /// Past success (`continue_past_success`) a step that starts inside the success box
    /// (radius 0.3 around the origin; the rows' p are uniform in [-1, 1]²) has no
    /// vector advantage, and every other row keeps the advantage it has without the
    /// flag, bit for bit. Without the env term (w = 0) nothing is masked.
    #[test]
    fn past_success_the_steps_at_the_goal_have_no_vector_advantage() {
        let (_, l) = saver(0.5);
        let b = batch(&l, |_, i| -0.1 * i as f32);
        let advantages = |past: bool, w: f64| {
            let rule = crate::env::SuccessRule {
                radius: 0.3,
                goal_start: None,
            };
            let mut config = config(w);
            config.env = config.env.clone().with_success(Some(rule)).unwrap();
            config.continue_past_success = past;
            let s = Saver::new(&config, random_pcpn(&l, DType::F32), &Device::Cpu).unwrap();
            s.start(&b).unwrap().adv_host
        };
        let (free, past) = (advantages(false, 0.5), advantages(true, 0.5));
        assert_eq!(advantages(true, 0.0), advantages(false, 0.0));
        let mut inside = 0;
        for (k, row) in b.obs.chunks_exact(6).enumerate() {
            let at_goal = row[0].abs() < 0.3 && row[1].abs() < 0.3;
            inside += at_goal as usize;
            let want: &[f32] = if at_goal {
                &[0.0, 0.0]
            } else {
                &free[2 * k..2 * k + 2]
            };
            assert_eq!(&past[2 * k..2 * k + 2], want, "row {k}");
        }
        assert!(inside > 0 && inside < 12, "{inside} of 12 rows inside");
    }

    /// With the term on, the reference path (candle autograd through the PCPN) takes
    /// the fast path's step: the same weights after an update to float rounding, and a
    /// scale c above 0.
    #[test]
    fn both_gradient_paths_take_the_same_step_with_the_term() {
        let (_, l) = saver(0.5);
        let actions = random_batch(&l, 2, 6, 7, 1.0, vec![false; 12]).actions;
        let b = batch(&l, |_, i| {
            -(actions[2 * i].powi(2) + actions[2 * i + 1].powi(2))
        });
        let mut out = Vec::new();
        for path in [GradPath::Fast, GradPath::Reference] {
            let (mut s, _) = saver(0.5);
            s.set_grad_path(path);
            let stats = s.update(&b).unwrap();
            assert!(stats.get("env_pg_scale").unwrap() > 0.0);
            let state = s.save_state().unwrap();
            out.push(
                state
                    .tensors
                    .iter()
                    .filter(|(n, _)| n.starts_with("agent"))
                    .map(|(_, t)| t.flatten_all().unwrap().to_vec1::<f32>().unwrap())
                    .collect::<Vec<_>>(),
            );
        }
        for (x, y) in out[0].iter().zip(&out[1]) {
            let worst = x
                .iter()
                .zip(y)
                .map(|(p, q)| (p - q).abs())
                .fold(0f32, f32::max);
            assert!(worst < 1e-5, "differs by {worst:e}");
        }
    }

    /// The scalar critic and the reward's running mean square survive a checkpoint:
    /// a restored learner takes the same next step, bit for bit.
    #[test]
    fn the_term_survives_a_checkpoint() {
        let (mut a, l) = saver(0.5);
        let b = batch(&l, |_, i| -0.1 * (i % 3) as f32);
        a.update(&b).unwrap();
        let state = a.save_state().unwrap();
        assert!(state.get("env_critic.reward_mean_square").is_some());
        let (mut resumed, _) = saver(0.5);
        resumed
            .restore_state(&|n| state.get(n), &state.numbers)
            .unwrap();
        a.update(&b).unwrap();
        resumed.update(&b).unwrap();
        assert_eq!(weights(&a, ""), weights(&resumed, ""));
    }
}
