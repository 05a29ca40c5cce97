//! SAVER over several passes of shuffled minibatches per batch (`saver.epochs`,
//! `saver.minibatch_size`; docs/ALGORITHM.md §7.1), as PPO reuses its batches: the
//! batch's critic targets, advantages and Δp targets are made once at its start, as in
//! the one-step update, then every minibatch is one optimiser step of the same three
//! losses on its rows, with the agent's and critic's outputs of that moment. The PCPN,
//! when it learns, takes its one step on the whole batch after the passes. With
//! `saver.target_kl` the passes stop early once a minibatch's policy has moved that far
//! from the one that acted (approximate KL), as PPO's early stop.
//! On the CPU, for layouts without a choice, every minibatch step is the host step
//! (host_step.rs); elsewhere the step through candle (step.rs).

use super::host_step::HostScratch;
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
        let mu_dim = self.layout.mu_dim();
        let s = self.start(batch)?;
        let tune = self.tune_grads(&s.fwd.x, batch)?;
        let mut dmu = Some(vec![0f32; b * mu_dim]);
        let mut losses = Vec::with_capacity(self.cfg.epochs * m);
        let mut order: Vec<usize> = (0..b).collect();
        let behaviour = self.behaviour(batch, &s)?;
        // The host step reads and writes the optimiser's host copy of the weights,
        // written back after the passes (host_step.rs).
        let mut host = match self.host_path() {
            true => Some((self.opt.host_state()?, HostScratch::default())),
            false => None,
        };
        // With two threads or more the host steps run on a pool of two made for this
        // update: the critics on one worker, the PCPN's blocks shared by both.
        let pool = host.as_ref().and_then(|_| self.step_pool());
        let pooled = pool.is_some();
        let mut passes = || -> Result<()> {
            'passes: for epoch in 0..self.cfg.epochs {
                // One minibatch is the whole batch: its order changes nothing but the bits.
                if m > 1 {
                    order.shuffle(&mut self.rng);
                }
                for j in 0..m {
                    // Minibatch j holds steps [j·B/m, (j+1)·B/m) of the shuffled order.
                    let idx = &order[j * b / m..(j + 1) * b / m];
                    let kl_stop = self.cfg.target_kl > 0.0 && !(epoch == 0 && j == 0);
                    let behaviour = behaviour.as_deref();
                    let step = match host.as_mut() {
                        Some((h, scratch)) => self
                            .host_minibatch(h, scratch, batch, &s, idx, behaviour, kl_stop, pooled)?
                            .map(|(l, part)| (l, Some(part))),
                        None => self.candle_minibatch(batch, &s, idx, behaviour, kl_stop)?,
                    };
                    let Some((l, part)) = step else {
                        if epoch == 0 {
                            dmu = None; // the signal's dL/dμ would miss rows
                        }
                        break 'passes;
                    };
                    losses.push(l);
                    if epoch == 0 {
                        match (&mut dmu, part) {
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
            Ok(())
        };
        match &pool {
            Some(pool) => pool.install(passes)?,
            None => passes()?,
        }
        if let Some((h, _)) = host {
            self.opt.commit_host(h)?;
        }
        let tune_loss = self.apply_tune(tune)?;
        self.finish(batch, s, dmu, Losses::mean(&losses), tune_loss)
    }

    /// One minibatch step through candle (step.rs) on the rows `idx` of `batch`, whose
    /// update started with `s`: its losses and (fast path) the PCPN term's dL/dμ, or
    /// `None` where `kl_stop` asks for the KL check and it holds (nothing changed).
    fn candle_minibatch(
        &mut self,
        batch: &Batch,
        s: &super::Start,
        idx: &[usize],
        behaviour: Option<&[f32]>,
        kl_stop: bool,
    ) -> Result<Option<(Losses, Option<Vec<f32>>)>> {
        let rows = |data: &[f32], w: usize| gather_rows(data, idx, w);
        let (n, o, d, a) = (
            idx.len(),
            self.layout.obs_dim,
            self.layout.aligned_dim,
            self.layout.action_dim(),
        );
        let fwd = self.forward(Tensor::from_vec(rows(&batch.obs, o), (n, o), &self.dev)?)?;
        if let Some(logp_b) = behaviour.filter(|_| kl_stop) {
            if self.approx_kl(&fwd, &rows(&batch.actions, a), &rows(logp_b, 1))?
                > self.cfg.target_kl
            {
                return Ok(None);
            }
        }
        let (target, adv) = (rows(&s.target, d), rows(&s.adv_host, d));
        let step_rows = StepRows {
            fwd: &fwd,
            returns: Tensor::from_vec(rows(&s.returns_host, d), (n, d), &self.dev)?,
            target: &target,
            adv: &adv,
            env: self.env_rows(s, batch, Some(idx), behaviour)?,
        };
        let step = self.step_loss(&step_rows)?;
        Ok(Some(self.take_step(step)?))
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

    /// A custom env's defaults on the plane (minibatches of 5, the PCPN's step on a
    /// draw of 7 rows) and a batch with the env's reward, some rows' raw means beyond
    /// the wall's ±2 (a large first-layer input).
    fn custom_case() -> (crate::config::RunConfig, crate::rollout::Batch) {
        let spec = crate::algo::tests::plane_spec(1.0, None);
        let l = spec.layout();
        let mut config = crate::algo::recommended(&spec, Algo::Saver, 1);
        (config.saver.minibatch_size, config.saver.pcpn_tune_rows) = (5, 7);
        let mut batch = random_batch(&l, 4, 6, 9, 1.0, vec![false; 24]);
        for (i, o) in batch.obs.iter_mut().enumerate() {
            *o *= if i % 6 == 2 { 40.0 } else { 1.0 };
        }
        batch.env_reward = (0..24).map(|i| -0.05 * (i % 5) as f32).collect();
        (config, batch)
    }

    /// Three updates of SAVER at `config` on `batch` from the same start on `threads`:
    /// every saved tensor (as f64), the statistics and the optimiser steps.
    #[allow(clippy::type_complexity)]
    fn three_updates(
        config: &crate::config::RunConfig,
        batch: &crate::rollout::Batch,
        path: crate::algo::GradPath,
        threads: usize,
    ) -> (Vec<(String, Vec<f64>)>, Vec<Vec<(&'static str, f32)>>, u64) {
        let l = config.env.layout();
        let mut s = Saver::new(config, random_pcpn(&l, DType::F32), &Device::Cpu).unwrap();
        s.set_grad_path(path);
        s.set_threads(threads);
        assert_eq!(s.host_path(), path == crate::algo::GradPath::Fast);
        let stats: Vec<_> = (0..3).map(|_| s.update(batch).unwrap().values).collect();
        let as_f64 = |x: &Tensor| {
            let x = x.to_dtype(DType::F64).unwrap();
            x.flatten_all().unwrap().to_vec1::<f64>().unwrap()
        };
        let state = s.save_state().unwrap().tensors;
        let saved = state.iter().map(|(n, x)| (n.clone(), as_f64(x))).collect();
        (saved, stats, s.optimizer_steps())
    }

    /// The host step's critics beside its PCPN blocks on a pool of two threads give
    /// the bits of one thread (they share no sum; the blocks add up in block order).
    #[test]
    fn the_host_step_gives_one_threads_bits_on_two() {
        let (config, batch) = custom_case();
        let path = crate::algo::GradPath::Fast;
        let one = three_updates(&config, &batch, path, 1);
        let two = three_updates(&config, &batch, path, 2);
        assert_eq!(one, two);
    }

    /// The host step (host_step.rs) against the step through candle's autograd (the
    /// PCPN's gradient by autograd too) at a custom env's defaults: observations read
    /// through `auto`'s scale, the env term clipped at 0.2, the saturation wall, the
    /// PCPN's own step on a draw of rows, two passes of minibatches of 5 steps, and the
    /// KL stop on and off. Over three updates every saved tensor (agent, both critics,
    /// the optimiser's slots, the tuned PCPN) and every statistic agree to float
    /// rounding; the wall and the clip act (μ_raw beyond ±2, rows past the clip).
    #[test]
    fn the_host_step_takes_the_reference_step() {
        use crate::algo::GradPath;
        let (mut config, batch) = custom_case();
        for target_kl in [0.0, 0.02] {
            config.saver.target_kl = target_kl;
            let run = |path| three_updates(&config, &batch, path, 0);
            let (host, host_stats, host_steps) = run(GradPath::Fast);
            let (reference, ref_stats, ref_steps) = run(GradPath::Reference);
            assert_eq!(host_steps, ref_steps);
            for ((name, x), (_, y)) in host.iter().zip(&reference) {
                let scale = y.iter().fold(1e-3f64, |m, v| m.max(v.abs()));
                let worst = x
                    .iter()
                    .zip(y)
                    .map(|(p, q)| (p - q).abs())
                    .fold(0f64, f64::max);
                assert!(
                    worst <= 2e-4 * scale,
                    "{name}: differs by {worst:e} (scale {scale})"
                );
            }
            for (a, b) in host_stats.iter().flatten().zip(ref_stats.iter().flatten()) {
                assert_eq!(a.0, b.0);
                let tol = 1e-3 * a.1.abs().max(b.1.abs()).max(1e-4);
                assert!((a.1 - b.1).abs() <= tol, "{}: {} vs {}", a.0, a.1, b.1);
            }
            // The env term pushed, and μ passed tanh(2) = 0.964 (the wall's ±2 on μ_raw).
            let most = |k: &str| {
                let v = host_stats.iter().flatten().filter(|v| v.0 == k);
                v.fold(0f32, |m, v| m.max(v.1))
            };
            assert!(most("env_pg_scale") > 0.0, "{host_stats:?}");
            assert!(most("mu_abs_max") > 0.964, "{host_stats:?}");
            eprintln!("target_kl {target_kl}: {host_steps} optimiser steps");
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
