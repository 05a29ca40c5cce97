//! SAVER over several passes of shuffled minibatches per batch (`saver.epochs`,
//! `saver.minibatch_size`; docs/ALGORITHM.md §7.1), as PPO reuses its batches: the
//! batch's critic targets, advantages and Δp targets are made once at its start, as in
//! the one-step update, then every minibatch is one optimiser step of the same three
//! losses on its rows, with the agent's and critic's outputs of that moment. The PCPN,
//! when it learns, takes its one step on the whole batch after the passes. With
//! `saver.target_kl` the passes stop early once a minibatch's policy has moved that far
//! from the one that acted (approximate KL), as PPO's early stop.

use super::{Losses, Saver, StepRows};
use crate::algo::{gather_rows, Algorithm, UpdateStats};
use crate::rollout::Batch;
use crate::Result;
use candle_core::Tensor;
use rand::seq::SliceRandom;

impl Saver {
    /// Several optimiser steps: a non-finite loss in a later one puts back the weights,
    /// optimiser slots, step count and streams of the update's start.
    pub(super) fn update_epochs(&mut self, batch: &Batch) -> Result<UpdateStats> {
        let before = self.save_state()?;
        let result = self.epochs(batch);
        if result.is_err() {
            self.restore_state(&|name| before.get(name), &before.numbers)?;
        }
        result
    }

    /// The update's body; on an error the caller puts the state back. The statistics
    /// are the batch's at its start, the losses the mean over the steps, and the
    /// signal's dL/dμ the first pass's (each row once).
    fn epochs(&mut self, batch: &Batch) -> Result<UpdateStats> {
        let (b, m) = (batch.len(), self.cfg.minibatches(batch.len()));
        let (o, d, mu_dim, a) = (
            self.layout.obs_dim,
            self.layout.aligned_dim,
            self.layout.mu_dim(),
            self.layout.action_dim(),
        );
        let s = self.start(batch)?;
        let tune = self.tune_grads(&s.fwd.x, batch)?;
        let mut dmu = Some(vec![0f32; b * mu_dim]);
        let mut losses = Vec::with_capacity(self.cfg.epochs * m);
        let mut order: Vec<usize> = (0..b).collect();
        let behaviour = self.behaviour(batch, &s)?;
        'passes: for epoch in 0..self.cfg.epochs {
            // One minibatch is the whole batch: its order changes nothing but the bits.
            if m > 1 {
                order.shuffle(&mut self.rng);
            }
            for j in 0..m {
                // Minibatch j holds steps [j·B/m, (j+1)·B/m) of the shuffled order.
                let idx = &order[j * b / m..(j + 1) * b / m];
                let rows = |data: &[f32], w: usize| gather_rows(data, idx, w);
                let n = idx.len();
                let fwd =
                    self.forward(Tensor::from_vec(rows(&batch.obs, o), (n, o), &self.dev)?)?;
                if let Some(logp_b) = behaviour.as_ref().filter(|_| self.cfg.target_kl > 0.0) {
                    let first = epoch == 0 && j == 0;
                    if !first
                        && self.approx_kl(&fwd, &rows(&batch.actions, a), &rows(logp_b, 1))?
                            > self.cfg.target_kl
                    {
                        if epoch == 0 {
                            dmu = None; // the signal's dL/dμ would miss rows
                        }
                        break 'passes;
                    }
                }
                let (target, adv) = (rows(&s.target, d), rows(&s.adv_host, d));
                let step_rows = StepRows {
                    fwd: &fwd,
                    returns: Tensor::from_vec(rows(&s.returns_host, d), (n, d), &self.dev)?,
                    target: &target,
                    adv: &adv,
                    env: self.env_rows(&s, batch, Some(idx), behaviour.as_deref())?,
                };
                let step = self.step_loss(&step_rows)?;
                let (l, step_dmu) = self.take_step(step)?;
                losses.push(l);
                if epoch == 0 {
                    match (&mut dmu, step_dmu) {
                        (Some(all), Some(part)) => {
                            for (&i, row) in idx.iter().zip(part.chunks_exact(mu_dim)) {
                                all[i * mu_dim..(i + 1) * mu_dim].copy_from_slice(row);
                            }
                        }
                        _ => dmu = None,
                    }
                }
            }
        }
        let tune_loss = self.apply_tune(tune)?;
        self.finish(batch, s, dmu, Losses::mean(&losses), tune_loss)
    }

    /// KL(behaviour ‖ current) over some steps, approximated as PPO's diagnostics do:
    /// mean((ρ − 1) − log ρ), ρ = π(a|o)/μ(a|o) of each step's action, with `fwd` the
    /// current policy's outputs for the steps, `actions` theirs and `logp_b` the
    /// behaviour's log μ(a|o) of each.
    fn approx_kl(&self, fwd: &super::Forward, actions: &[f32], logp_b: &[f32]) -> Result<f64> {
        let n = logp_b.len();
        let actions = Tensor::from_slice(actions, (n, self.layout.action_dim()), &self.dev)?;
        let logp = crate::nets::gaussian_log_prob(&self.layout, &fwd.mu, &fwd.log_std, &actions)?
            .to_vec1::<f32>()?;
        let sum: f64 = logp
            .iter()
            .zip(logp_b)
            .map(|(lp, lb)| {
                let log_ratio = (lp - lb) as f64;
                log_ratio.exp_m1() - log_ratio
            })
            .sum();
        Ok(sum / n as f64)
    }
}

#[cfg(test)]
mod tests {
    use crate::algo::tests::{random_batch, random_pcpn};
    use crate::algo::{Algorithm, Saver};
    use crate::config::Algo;
    use crate::env::{EnvKind, EnvSpec};
    use candle_core::{DType, Device, Tensor};

    fn weights(s: &Saver) -> Vec<(String, Vec<f32>)> {
        let state = s.save_state().unwrap();
        let flat = |x: Tensor| x.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        state
            .tensors
            .into_iter()
            .map(|(n, x)| (n, flat(x)))
            .collect()
    }

    /// SAVER on angle d = 2 with `epochs` passes of `minibatch_size`-step minibatches.
    fn saver(epochs: usize, minibatch_size: usize, lr: f64) -> (Saver, crate::rollout::Batch) {
        let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
        let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
        (config.saver.epochs, config.saver.minibatch_size, config.lr) =
            (epochs, minibatch_size, lr);
        let pcpn = random_pcpn(&spec.layout(), DType::F32);
        let batch = random_batch(&spec.layout(), 4, 6, 9, 1.0, vec![false; 24]);
        (Saver::new(&config, pcpn, &Device::Cpu).unwrap(), batch)
    }

    /// One pass over one whole-batch minibatch through the epochs code is the paper's
    /// one-step update: the same weights after it, to float rounding (the minibatch
    /// forward runs over the B steps alone, the one-step one over B + bootstrap rows).
    #[test]
    fn one_whole_batch_pass_is_the_one_step_update() {
        let (mut one, batch) = saver(1, 0, 1e-3);
        let (mut via_epochs, _) = saver(1, 0, 1e-3);
        let a = one.update(&batch).unwrap();
        let b = via_epochs.update_epochs(&batch).unwrap();
        assert_eq!(
            (one.optimizer_steps(), via_epochs.optimizer_steps()),
            (1, 1)
        );
        for ((name, x), (_, y)) in weights(&one).iter().zip(weights(&via_epochs)) {
            let worst = x
                .iter()
                .zip(&y)
                .map(|(p, q)| (p - q).abs())
                .fold(0f32, f32::max);
            assert!(worst <= 1e-6, "{name}: differs by {worst:e}");
        }
        let get =
            |s: &crate::algo::UpdateStats, k: &str| s.values.iter().find(|v| v.0 == k).unwrap().1;
        for k in ["actor_loss", "critic_loss", "grad_norm"] {
            let (x, y) = (get(&a, k), get(&b, k));
            assert!((x - y).abs() <= 1e-5 * x.abs().max(1e-6), "{k}: {x} vs {y}");
        }
    }

    /// E passes of ⌈B / m⌉ minibatches take E·⌈B / m⌉ optimiser steps: 24 steps in
    /// minibatches of 5 are 5 of them (of 4 or 5 steps), 3 passes 15 steps.
    #[test]
    fn every_minibatch_of_every_pass_is_one_optimiser_step() {
        let (mut s, batch) = saver(3, 5, 1e-3);
        let before = weights(&s);
        s.update(&batch).unwrap();
        assert_eq!(s.optimizer_steps(), 15);
        s.update(&batch).unwrap();
        assert_eq!(s.optimizer_steps(), 30);
        assert_ne!(before, weights(&s));
    }

    /// The KL stop: the behaviour policy of the batch (μ = 0.1, its own σ) is far from
    /// the fresh agent's, so a threshold of 1e-9 stops the passes before the second
    /// minibatch (one optimiser step of 15), while one no minibatch reaches (1e30) takes
    /// all 15 and the same weights, bit for bit, as no stop: the check draws nothing.
    #[test]
    fn the_kl_stop_ends_the_passes_and_costs_nothing_when_never_reached() {
        let stopped = |kl: f64| {
            let (mut s, batch) = saver(3, 5, 1e-3);
            s.cfg.target_kl = kl;
            s.update(&batch).unwrap();
            (s.optimizer_steps(), weights(&s))
        };
        assert_eq!(stopped(1e-9).0, 1);
        let (steps, free) = stopped(1e30);
        assert_eq!(steps, 15);
        let (_, off) = stopped(0.0);
        assert_eq!(free, off);
    }

    /// At a learning rate of 1e30 the first minibatch's step blows the weights up and
    /// a later minibatch's loss is not finite: the update fails and puts back the
    /// weights and optimiser of its start, bit for bit.
    #[test]
    fn a_non_finite_later_minibatch_puts_back_the_update_start() {
        let (mut s, batch) = saver(2, 6, 1e30);
        let before = weights(&s);
        let err = s.update(&batch).unwrap_err().to_string();
        assert!(err.contains("finite"), "{err}");
        assert_eq!(s.optimizer_steps(), 0);
        for ((name, x), (_, y)) in before.iter().zip(weights(&s)) {
            let same = x.iter().zip(&y).all(|(p, q)| p.to_bits() == q.to_bits());
            assert!(same, "{name} was not put back");
        }
    }
}
