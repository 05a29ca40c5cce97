//! What SAVER's update learns from (docs/ALGORITHM.md §6): the vector critic's targets
//! and the per-coordinate advantages of a batch, by the rollout's n-step returns (the
//! paper), GAE(λ) per coordinate (`saver.gae_lambda` < 1) or V-trace (`--vtrace`, its
//! traces decayed by the same λ).

use super::{Forward, Saver};
use crate::algo::vtrace::{coordinate_log_ratios, shared_log_ratios};
use crate::algo::{lambda_targets, matrix};
use crate::env::Routing;
use crate::nets::gaussian_log_prob;
use crate::rollout::Batch;
use crate::Result;
use candle_core::Tensor;

/// A batch's critic targets and advantages, [B, d] each.
pub(super) struct Targets {
    pub returns: Vec<f32>,
    pub advantages: Vec<f32>,
    /// V-trace's statistics, when it runs.
    pub vtrace_stats: Vec<(&'static str, f32)>,
}

impl Saver {
    /// The targets of `batch`, whose B steps' forward is `fwd` (their μ and log σ on the
    /// host in `policy_host`, their V(x) in `value_host`), with `v_all` V at every row of
    /// [`crate::algo::update_rows`] (`n_ends` timeouts).
    pub(super) fn targets(
        &self,
        batch: &Batch,
        fwd: &Forward,
        policy_host: (&[f32], &[f32]),
        v_all: &Tensor,
        value_host: &[f32],
        n_ends: usize,
    ) -> Result<Targets> {
        let (b, d) = (batch.len(), self.layout.aligned_dim);
        if let Some(vt) = self.vtrace {
            // Each coordinate weighs its step by the part of the action that moves it,
            // where the env says which part that is (§16); else one ratio a step.
            let log_ratio = if self.routing == Routing::Shared {
                let actions = matrix(&batch.actions, b, self.layout.action_dim(), &self.dev)?;
                let log_pi = gaussian_log_prob(&self.layout, &fwd.mu, &fwd.log_std, &actions)?
                    .detach()
                    .to_vec1::<f32>()?;
                shared_log_ratios(&self.layout, batch, &log_pi, &self.dev)?
            } else {
                let (mu, log_std) = policy_host;
                coordinate_log_ratios(self.routing, &self.layout, batch, mu, log_std)?
            };
            let corrected = vt.targets(
                batch,
                &batch.vector_reward,
                &v_all.detach(),
                n_ends,
                d,
                self.gamma,
                &log_ratio,
            )?;
            return Ok(Targets {
                returns: corrected.targets,
                advantages: corrected.advantages,
                vtrace_stats: corrected.stats,
            });
        }
        let (advantages, returns) = lambda_targets(
            batch,
            &batch.vector_reward,
            value_host,
            v_all,
            n_ends,
            self.gamma,
            self.cfg.gae_lambda as f32,
        )?;
        Ok(Targets {
            returns,
            advantages,
            vtrace_stats: Vec::new(),
        })
    }
}

#[cfg(test)]
mod tests {
    use crate::algo::tests::{random_batch, random_pcpn};
    use crate::algo::{matrix, Saver};
    use crate::config::Algo;
    use crate::env::{EnvKind, EnvSpec};
    use candle_core::{DType, Device};

    /// SAVER's critic targets on angle d = 2, 2 trajectories of 3 steps, the first
    /// ending at its second step, against the recursion written out here:
    /// δ_t = r_t + γ·V_next − V(x_t) (V_next = 0 after the end, V(x_3) of the last
    /// observation after the last step), A_t = δ_t + γλ·(1 − done_t)·A_(t+1), target
    /// A_t + V(x_t), per coordinate. λ = 1 is the paper's n-step return, λ = 0 the
    /// one-step r_t + γ·V_next; γ = 0.9.
    #[test]
    fn targets_are_td_lambda_per_coordinate() {
        let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
        let l = spec.layout();
        let (t, n, d) = (2, 3, l.aligned_dim);
        let done = vec![false, true, false, false, false, false];
        let batch = random_batch(&l, t, n, 5, 1.0, done.clone());
        let mut seen = Vec::new();
        for lambda in [1.0f32, 0.5, 0.0] {
            let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
            (config.gamma, config.saver.gae_lambda) = (0.9, lambda as f64);
            let s = Saver::new(&config, random_pcpn(&l, DType::F32), &Device::Cpu).unwrap();
            let start = s.start(&batch).unwrap();
            let last = matrix(&batch.last_obs, t, l.obs_dim, &Device::Cpu).unwrap();
            let boot: Vec<f32> = s
                .forward(last)
                .unwrap()
                .value
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let v = &start.value_host;
            let mut want = vec![0f32; t * n * d];
            for e in 0..t {
                for j in 0..d {
                    let (mut next_v, mut next_a) = (boot[e * d + j], 0f32);
                    for k in (0..n).rev() {
                        let i = (e * n + k) * d + j;
                        if done[e * n + k] {
                            (next_v, next_a) = (0.0, 0.0);
                        }
                        let a =
                            batch.vector_reward[i] + 0.9 * next_v - v[i] + 0.9 * lambda * next_a;
                        want[i] = a + v[i];
                        (next_v, next_a) = (v[i], a);
                    }
                }
            }
            for (i, (got, want)) in start.returns_host.iter().zip(&want).enumerate() {
                assert!(
                    (got - want).abs() < 1e-6,
                    "λ = {lambda}, entry {i}: {got} against {want}"
                );
            }
            seen.push(start.returns_host.clone());
        }
        // The three λ give three different targets (the recursion is not degenerate).
        assert!(seen[0] != seen[1] && seen[1] != seen[2]);
    }

    /// On-policy every ratio π/μ is 1, so V-trace's traces are c_t = λ and its critic
    /// targets are GAE(λ)'s: v_t − V(x_t) = δ_t + γλ·(v_(t+1) − V(x_(t+1))). Angle d = 2,
    /// 4 trajectories of 5 steps, λ = 0.5; the payload is the learner's own (μ, log σ).
    #[test]
    fn vtrace_on_policy_decays_its_traces_by_lambda() {
        let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
        let l = spec.layout();
        let done = (0..20).map(|i| i == 7).collect();
        let mut batch = random_batch(&l, 4, 5, 3, 0.8, done);
        let mut targets = Vec::new();
        for vtrace in [false, true] {
            let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
            (config.vtrace, config.saver.gae_lambda) = (vtrace, 0.5);
            let s = Saver::new(&config, random_pcpn(&l, DType::F32), &Device::Cpu).unwrap();
            let obs = matrix(&batch.obs, 20, l.obs_dim, &Device::Cpu).unwrap();
            let f = s.forward(obs).unwrap();
            let (mu, ls): (Vec<Vec<f32>>, Vec<Vec<f32>>) =
                (f.mu.to_vec2().unwrap(), f.log_std.to_vec2().unwrap());
            batch.payload = mu
                .iter()
                .zip(&ls)
                .flat_map(|(m, s)| m.iter().chain(s))
                .copied()
                .collect();
            targets.push(s.start(&batch).unwrap().returns_host);
        }
        for (i, (plain, vt)) in targets[0].iter().zip(&targets[1]).enumerate() {
            assert!(
                (plain - vt).abs() < 1e-5,
                "entry {i}: GAE {plain} against V-trace {vt}"
            );
        }
    }
}
