//! Optimisers, written out so their semantics are exact and checkpointable.
//!
//! RMSProp with TensorFlow-1 semantics (the paper's): ms initialised to 1.0,
//! `ms ← ms + (g² − ms)·(1 − ρ)`, `θ ← θ − lr·g/√(ms + ε)`, ρ = 0.9, ε = 1e-10, no momentum.
//! Adam with TensorFlow-1 semantics: `lr_t = lr·√(1 − β2^t)/(1 − β1^t)`,
//! `θ ← θ − lr_t·m/(√v + ε̂)`.

mod host;
mod host_math;

use crate::{CoreError, Result};
use candle_core::{backprop::GradStore, Tensor, Var};
pub use host::HostState;
use host_math::to_host;
pub(crate) use host_math::{join_if, pool_of_two};
use serde::{Deserialize, Serialize};

/// Which optimiser, with its constants.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum OptimizerConfig {
    /// TF1 RMSProp (the paper's).
    Rmsprop {
        /// Decay ρ of the mean square.
        decay: f64,
        /// ε inside the square root.
        eps: f64,
        /// Initial value of the mean square slots (TF1: 1.0).
        init: f64,
    },
    /// TF1 Adam.
    Adam {
        /// β1.
        beta1: f64,
        /// β2.
        beta2: f64,
        /// ε̂.
        eps: f64,
    },
}

impl OptimizerConfig {
    /// TF1 RMSProp defaults (docs/ALGORITHM.md §10).
    pub const RMSPROP_TF1: Self = Self::Rmsprop {
        decay: 0.9,
        eps: 1e-10,
        init: 1.0,
    };
    /// TF1 Adam defaults.
    pub const ADAM_TF1: Self = Self::Adam {
        beta1: 0.9,
        beta2: 0.999,
        eps: 1e-8,
    };

    /// Checks the constants.
    pub fn validate(&self) -> Result<()> {
        let ok = match *self {
            Self::Rmsprop { decay, eps, init } => {
                (0.0..1.0).contains(&decay) && eps > 0.0 && init >= 0.0
            }
            Self::Adam { beta1, beta2, eps } => {
                (0.0..1.0).contains(&beta1) && (0.0..1.0).contains(&beta2) && eps > 0.0
            }
        };
        if ok {
            Ok(())
        } else {
            Err(CoreError::Config(format!(
                "optimizer: constants out of range in {self:?}"
            )))
        }
    }
}

/// An optimiser over a named set of variables, with named slots for checkpoints.
pub struct Optimizer {
    /// The variables it trains, in a fixed order.
    vars: Vec<(String, Var)>,
    /// First slot per variable: ms (RMSProp) or m (Adam).
    slot1: Vec<Tensor>,
    /// Second slot per variable: v (Adam); empty for RMSProp.
    slot2: Vec<Tensor>,
    /// Constants.
    config: OptimizerConfig,
    /// Learning rate.
    lr: f64,
    /// Steps taken (Adam's bias correction; also checkpointed).
    t: u64,
    /// Global gradient-norm clip, if any.
    clip: Option<f64>,
    /// Decay the learning rate linearly to zero over this many steps, if set.
    decay_over: Option<u64>,
    /// Step on the host in one pass per variable (every variable on the CPU) instead of
    /// a dozen tensor ops; the same f32 arithmetic, so the same bits, but for slots
    /// flushed below f32's smallest normal ([`host_math::flush_subnormal`]).
    host: bool,
}

impl Optimizer {
    /// A fresh optimiser; slots start at their initial values.
    pub fn new(vars: Vec<(String, Var)>, config: OptimizerConfig, lr: f64) -> Result<Self> {
        Self::with_clip(vars, config, lr, None)
    }

    /// An optimiser that first scales the gradients so their global norm is at most `clip`.
    pub fn with_clip(
        vars: Vec<(String, Var)>,
        config: OptimizerConfig,
        lr: f64,
        clip: Option<f64>,
    ) -> Result<Self> {
        let mut slot1 = Vec::with_capacity(vars.len());
        let mut slot2 = Vec::new();
        for (_, v) in &vars {
            match config {
                OptimizerConfig::Rmsprop { init, .. } => {
                    slot1.push((v.as_tensor().ones_like()? * init)?)
                }
                OptimizerConfig::Adam { .. } => {
                    slot1.push(v.as_tensor().zeros_like()?);
                    slot2.push(v.as_tensor().zeros_like()?);
                }
            }
        }
        Ok(Self {
            host: vars.iter().all(|(_, v)| v.device().is_cpu()),
            vars,
            slot1,
            slot2,
            config,
            lr,
            t: 0,
            clip,
            decay_over: None,
        })
    }

    /// Makes the learning rate fall linearly from its initial value to zero over
    /// `steps` steps (A3C's schedule): step t (from 1) uses lr·(1 − (t − 1)/steps),
    /// and every step after the last uses 0.
    pub fn decaying_over(mut self, steps: u64) -> Self {
        self.decay_over = Some(steps.max(1));
        self
    }

    /// The learning rate the next step will use.
    pub fn current_lr(&self) -> f64 {
        lr_at(self.lr, self.decay_over, self.t)
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u64 {
        self.t
    }

    /// The global L2 norm of the gradients of this optimiser's variables. A gradient on
    /// the CPU has its squares summed in f64 as [`Optimizer::step_host`]
    /// sums them, so both clip alike to the bit.
    pub fn grad_norm(&self, grads: &GradStore) -> Result<f64> {
        let mut sq = 0.0f64;
        for (_, v) in &self.vars {
            if let Some(g) = grads.get(v.as_tensor()) {
                if g.device().is_cpu() {
                    sq += host_math::sum_sq(&to_host(g)?);
                    continue;
                }
                sq += g
                    .sqr()?
                    .sum_all()?
                    .to_dtype(candle_core::DType::F64)?
                    .to_scalar::<f64>()?;
            }
        }
        Ok(sq.sqrt())
    }

    /// Applies one step with the gradients in `grads`; variables without a gradient
    /// are left alone (their slots too). Returns the gradients' global norm (before
    /// clipping). A non-finite gradient norm, or a step that would make any variable
    /// or slot non-finite, changes nothing (not even the step count) and is
    /// [`CoreError::NonFinite`]: one bad batch never poisons the weights.
    pub fn step(&mut self, grads: &GradStore) -> Result<f64> {
        if self.host {
            // One pass per variable on the host: copy, step, commit (nothing is written
            // back when the step fails).
            let mut host_grads = Vec::with_capacity(self.vars.len());
            for (_, v) in &self.vars {
                if let Some(g) = grads.get(v.as_tensor()) {
                    host_grads.push((v.as_tensor().id(), to_host(g)?));
                }
            }
            let mut h = self.host_state()?;
            let norm = self.step_host(&mut h, &host_grads)?;
            self.commit_host(h)?;
            return Ok(norm);
        }
        let lr = self.current_lr();
        let norm = self.grad_norm(grads)?;
        if !norm.is_finite() {
            return Err(CoreError::NonFinite(format!("the gradient norm is {norm}")));
        }
        let t = self.t + 1;
        let scale = match self.clip {
            Some(c) if norm > c => c / norm,
            _ => 1.0,
        };
        // (index, new value, new slot 1, new slot 2): computed in full, committed only
        // when every value is finite.
        let mut next = Vec::with_capacity(self.vars.len());
        for i in 0..self.vars.len() {
            let var = &self.vars[i].1;
            let Some(g) = grads.get(var.as_tensor()) else {
                continue;
            };
            // Gradients can carry the op graph that produced them; the slots must not
            // keep it (and the previous slots) alive from step to step.
            let g = &if scale < 1.0 {
                (g * scale)?.detach()
            } else {
                g.detach()
            };
            match self.config {
                OptimizerConfig::Rmsprop { decay, eps, .. } => {
                    // TF1 ApplyRMSProp: ms += (g² − ms)·(1 − ρ); var −= lr·g/√(ms + ε).
                    let one_minus = 1.0f32 - decay as f32;
                    let ms = &self.slot1[i];
                    let ms = (ms + ((g.sqr()? - ms)? * one_minus as f64)?)?;
                    let step = ((g * lr)? / (&ms + eps)?.sqrt()?)?;
                    next.push((i, (var.as_tensor() - step)?, ms.detach(), None));
                }
                OptimizerConfig::Adam { beta1, beta2, eps } => {
                    let t = t as i32;
                    let lr_t = lr * (1.0 - beta2.powi(t)).sqrt() / (1.0 - beta1.powi(t));
                    let m = ((&self.slot1[i] * beta1)? + (g * (1.0 - beta1))?)?;
                    let v = ((&self.slot2[i] * beta2)? + (g.sqr()? * (1.0 - beta2))?)?;
                    let step = ((&m * lr_t)? / (v.sqrt()? + eps)?)?;
                    next.push((i, (var.as_tensor() - step)?, m.detach(), Some(v.detach())));
                }
            }
        }
        for (i, value, s1, s2) in &next {
            for (what, x) in [
                ("value", Some(value)),
                ("slot", Some(s1)),
                ("slot", s2.as_ref()),
            ] {
                let Some(x) = x else { continue };
                // A sum of finite values of this size is finite; inf or NaN anywhere
                // makes it non-finite.
                let sum = x
                    .sum_all()?
                    .to_dtype(candle_core::DType::F64)?
                    .to_scalar::<f64>()?;
                if !sum.is_finite() {
                    return Err(CoreError::NonFinite(format!(
                        "the step would make the {what} of {} non-finite",
                        self.vars[*i].0
                    )));
                }
            }
        }
        for (i, value, s1, s2) in next {
            self.vars[i].1.set(&value)?;
            self.slot1[i] = s1;
            if let Some(s2) = s2 {
                self.slot2[i] = s2;
            }
        }
        self.t = t;
        Ok(norm)
    }

    /// The slots as named tensors (`opt.<slot>.<var>`), for checkpoints.
    pub fn slots(&self) -> Vec<(String, Tensor)> {
        let (n1, n2) = self.slot_names();
        let mut out = Vec::new();
        for (i, (name, _)) in self.vars.iter().enumerate() {
            out.push((format!("opt.{n1}.{name}"), self.slot1[i].clone()));
            if let Some(s) = self.slot2.get(i) {
                out.push((format!("opt.{n2}.{name}"), s.clone()));
            }
        }
        out
    }

    /// Restores slots and the step count saved by [`Optimizer::slots`].
    pub fn restore(&mut self, get: &dyn Fn(&str) -> Option<Tensor>, t: u64) -> Result<()> {
        let (n1, n2) = self.slot_names();
        for (i, (name, var)) in self.vars.iter().enumerate() {
            let load = |slot: &str| -> Result<Tensor> {
                let key = format!("opt.{slot}.{name}");
                let s = get(&key)
                    .ok_or_else(|| CoreError::Checkpoint(format!("missing tensor {key}")))?;
                if s.dims() != var.dims() {
                    return Err(CoreError::Checkpoint(format!(
                        "{key} has shape {:?}, expected {:?}",
                        s.dims(),
                        var.dims()
                    )));
                }
                Ok(s)
            };
            self.slot1[i] = load(n1)?;
            if i < self.slot2.len() {
                self.slot2[i] = load(n2)?;
            }
        }
        self.t = t;
        Ok(())
    }

    fn slot_names(&self) -> (&'static str, &'static str) {
        match self.config {
            OptimizerConfig::Rmsprop { .. } => ("ms", ""),
            OptimizerConfig::Adam { .. } => ("m", "v"),
        }
    }
}

/// The rate of the step after `t` steps: `lr`, or with `decay_over` = n falling linearly
/// to zero, `lr·(1 − min(t, n)/n)`.
fn lr_at(lr: f64, decay_over: Option<u64>, t: u64) -> f64 {
    match decay_over {
        Some(n) => lr * (1.0 - t.min(n) as f64 / n as f64),
        None => lr,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// One weight θ0 and an optimiser over it.
    fn one_weight(theta0: f32, config: OptimizerConfig, lr: f64) -> (Var, Optimizer) {
        let v = Var::from_slice(&[theta0], 1, &Device::Cpu).unwrap();
        let opt = Optimizer::new(vec![("w".into(), v.clone())], config, lr).unwrap();
        (v, opt)
    }

    #[test]
    fn rmsprop_two_tf1_steps_by_hand() {
        // θ0 = 1, lr = 0.01, ρ = 0.9, ε = 1e-10, ms0 = 1, loss = 3·θ so g = 3 at every step:
        //   step 1: ms1 = 1 + (9 − 1)·0.1 = 1.8;   θ1 = 1 − 0.01·3/√1.8 = 0.977639320
        //   step 2: ms2 = 1.8 + (9 − 1.8)·0.1 = 2.52; θ2 = θ1 − 0.03/√2.52 = 0.958740717
        // (python: 1 - 0.03/1.8**0.5 - 0.03/2.52**0.5)
        let (v, mut opt) = one_weight(1f32, OptimizerConfig::RMSPROP_TF1, 0.01);
        let mut seen = vec![];
        for _ in 0..2 {
            let loss = (v.as_tensor() * 3.0).unwrap().sum_all().unwrap();
            opt.step(&loss.backward().unwrap()).unwrap();
            seen.push(v.as_tensor().to_vec1::<f32>().unwrap()[0]);
        }
        assert!((seen[0] - 0.977_639_3).abs() < 1e-6, "{seen:?}");
        assert!((seen[1] - 0.958_740_7).abs() < 1e-6, "{seen:?}");
        let ms = opt.slots()[0].1.to_vec1::<f32>().unwrap()[0];
        assert!((ms - 2.52).abs() < 1e-5);
        // The slots hold values, not the graph of the step that made them: a slot that
        // tracked its op would keep every earlier step alive (a leak of ~2 MB/update).
        assert!(opt.slots().iter().all(|(_, t)| !t.track_op()));
    }

    #[test]
    fn rmsprop_turns_tiny_gradients_into_sign_like_steps_once_ms_decays() {
        // The SPEC's observation: with ms → g² (after many steps on g = 1e-4) the step is
        // lr·g/√(g²+ε) ≈ lr. After 200 steps ms = 1·0.9^200 + g²·(1 − 0.9^200) ≈ 1e-8,
        // so step 201 moves θ by 0.01·1e-4/√(7.06e-10 + 1e-8 + 1e-10) ≈ 9.63e-3.
        let (v, mut opt) = one_weight(0f32, OptimizerConfig::RMSPROP_TF1, 0.01);
        let mut before = 0.0;
        for _ in 0..201 {
            before = v.as_tensor().to_vec1::<f32>().unwrap()[0];
            let loss = (v.as_tensor() * 1e-4).unwrap().sum_all().unwrap();
            opt.step(&loss.backward().unwrap()).unwrap();
        }
        let moved = before - v.as_tensor().to_vec1::<f32>().unwrap()[0];
        assert!((moved - 9.63e-3).abs() < 2e-4, "moved {moved}");
    }

    #[test]
    fn adam_first_step_is_lr_sized() {
        // TF1 Adam, t = 1: m = 0.1·g, v = 0.001·g², lr_t = lr·√0.001/0.1;
        // step = lr_t·m/(√v + ε) = lr·g/(|g| + ε/√0.001) ≈ lr for g = 3: 0.001·3/(3+3.16e-7).
        let (v, mut opt) = one_weight(1f32, OptimizerConfig::ADAM_TF1, 0.001);
        let loss = (v.as_tensor() * 3.0).unwrap().sum_all().unwrap();
        opt.step(&loss.backward().unwrap()).unwrap();
        let theta = v.as_tensor().to_vec1::<f32>().unwrap()[0];
        assert!((theta - 0.999).abs() < 1e-6, "{theta}");
    }

    #[test]
    fn linear_decay_scales_each_step_and_reaches_zero() {
        // Adam with a constant gradient takes steps of ≈ lr (bias-corrected m/√v = 1,
        // see above). Over 4 steps the rates are 0.01·(1, 0.75, 0.5, 0.25), then 0:
        // θ = 1 − 0.01·(1 + 0.75 + 0.5 + 0.25) = 0.975 after 4 steps and after 6.
        let (v, opt) = one_weight(1f32, OptimizerConfig::ADAM_TF1, 0.01);
        let mut opt = opt.decaying_over(4);
        let mut seen = Vec::new();
        for _ in 0..6 {
            seen.push(opt.current_lr());
            let loss = (v.as_tensor() * 3.0).unwrap().sum_all().unwrap();
            opt.step(&loss.backward().unwrap()).unwrap();
            if opt.steps() == 4 {
                let theta = v.as_tensor().to_vec1::<f32>().unwrap()[0];
                assert!((theta - 0.975).abs() < 1e-5, "{theta}");
            }
        }
        for (got, want) in seen.iter().zip([0.01, 0.0075, 0.005, 0.0025, 0.0, 0.0]) {
            assert!((got - want).abs() < 1e-12, "{seen:?}");
        }
        let theta = v.as_tensor().to_vec1::<f32>().unwrap()[0];
        assert!((theta - 0.975).abs() < 1e-5, "{theta}");
    }

    /// The lane-wise sum of squares covers every element, the tail after the last full
    /// eight included: Σ (i/2)² for i = 0..19 is ¼·Σ i² = ¼·(19·20·39/6) = ¼·2470 = 617.5,
    /// exact in f64 at every partial sum (all multiples of ¼ below 2¹⁰).
    #[test]
    fn the_sum_of_squares_takes_every_element() {
        let x: Vec<f32> = (0..20).map(|i| i as f32 * 0.5).collect();
        assert_eq!(host_math::sum_sq(&x), 617.5);
        assert_eq!(host_math::sum_sq(&x[..7]), 0.25 * 91.0); // Σ i² for i < 7 = 91: tail only
        assert_eq!(host_math::sum_sq(&[]), 0.0);
    }

    /// The one-pass host step and the tensor ops give the same bits: a 3x5 weight and
    /// a bias through 6 steps of a loss with varied gradients, clipped on some steps,
    /// for both optimisers (no slot gets near a subnormal in 6 steps).
    #[test]
    fn the_host_step_equals_the_tensor_step_to_the_bit() {
        // 0: tensor ops, 1: the host step, 2: a HostState's steps, committed at the end,
        // 3: the same on two threads of a pool (w and b side by side).
        for config in [OptimizerConfig::RMSPROP_TF1, OptimizerConfig::ADAM_TF1] {
            let run = |mode: usize| -> Vec<Vec<f32>> {
                let w = Var::from_slice(
                    &(0..15).map(|i| (i as f32 * 0.37).sin()).collect::<Vec<_>>(),
                    (3, 5),
                    &Device::Cpu,
                )
                .unwrap();
                let b = Var::from_slice(&[0.1f32, -0.2, 0.3], 3, &Device::Cpu).unwrap();
                let vars = vec![("w".into(), w.clone()), ("b".into(), b.clone())];
                let mut opt = Optimizer::with_clip(vars, config, 0.01, Some(2.0)).unwrap();
                assert!(opt.host);
                opt.host = mode > 0;
                let mut state = (mode >= 2).then(|| opt.host_state().unwrap());
                let mut clipped = 0;
                let x = Tensor::from_slice(&[0.5f32, -1.5, 2.0, 0.25, -0.75], (5, 1), &Device::Cpu)
                    .unwrap();
                for k in 0..6 {
                    // loss = Σ (W·x + b)³ · (k + 1): gradients change with W and k (the
                    // host state's W and b are its own until the commit).
                    let (wk, bk) = match &state {
                        Some(h) => (
                            Var::from_slice(h.value(w.as_tensor()).unwrap(), (3, 5), &Device::Cpu)
                                .unwrap(),
                            Var::from_slice(h.value(b.as_tensor()).unwrap(), 3, &Device::Cpu)
                                .unwrap(),
                        ),
                        None => (w.clone(), b.clone()),
                    };
                    let y = (wk.as_tensor().matmul(&x).unwrap().squeeze(1).unwrap()
                        + bk.as_tensor())
                    .unwrap();
                    let loss = (y.powf(3.0).unwrap().sum_all().unwrap() * (k + 1) as f64).unwrap();
                    let grads = loss.backward().unwrap();
                    match &mut state {
                        Some(h) => {
                            let g = |v: &Var, of: &Var| {
                                let g = grads.get(of.as_tensor()).unwrap();
                                (v.as_tensor().id(), to_host(g).unwrap())
                            };
                            let grads = vec![g(&w, &wk), g(&b, &bk)];
                            let threads = if mode == 3 { 2 } else { 1 };
                            let n = opt.step_host_on(h, &grads, threads).unwrap();
                            clipped += (n > 2.0) as usize;
                        }
                        None => {
                            opt.step(&grads).unwrap();
                        }
                    }
                }
                if let Some(h) = state {
                    assert_eq!(h.steps(), 6);
                    assert!(clipped > 0, "the clip is taken on some step");
                    opt.commit_host(h).unwrap();
                }
                assert_eq!(opt.steps(), 6);
                let mut out: Vec<Vec<f32>> = [w.as_tensor(), b.as_tensor()]
                    .iter()
                    .map(|t| t.flatten_all().unwrap().to_vec1().unwrap())
                    .collect();
                out.extend(
                    opt.slots()
                        .iter()
                        .map(|(_, t)| t.flatten_all().unwrap().to_vec1().unwrap()),
                );
                out
            };
            let host = run(1);
            assert_eq!(run(0), host, "{config:?}");
            assert_eq!(run(2), host, "{config:?}");
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(2)
                .build()
                .unwrap();
            assert_eq!(pool.install(|| run(3)), host, "{config:?}");
        }
    }

    /// A host state's step that would make a weight non-finite is refused, and a state
    /// dropped instead of committed leaves the optimiser and its variables untouched;
    /// a gradient of the wrong size is refused.
    #[test]
    fn a_host_state_refuses_bad_steps_and_changes_nothing_until_committed() {
        let (v, opt) = one_weight(1.0, OptimizerConfig::ADAM_TF1, 0.1);
        let id = v.as_tensor().id();
        let mut h = opt.host_state().unwrap();
        opt.step_host(&mut h, &[(id, vec![0.5])]).unwrap();
        assert!(h.value(v.as_tensor()).unwrap()[0] < 1.0);
        assert!(matches!(
            opt.step_host(&mut h, &[(id, vec![f32::INFINITY])]),
            Err(CoreError::NonFinite(_))
        ));
        assert!(matches!(
            opt.step_host(&mut h, &[(id, vec![0.5, 0.5])]),
            Err(CoreError::Data(_))
        ));
        assert!(matches!(
            opt.step_host(&mut h, &[(id, vec![0.5]), (id, vec![0.5])]),
            Err(CoreError::Data(_))
        ));
        drop(h);
        assert_eq!(v.as_tensor().to_vec1::<f32>().unwrap(), vec![1.0]);
        assert_eq!(opt.steps(), 0);

        // On two threads (a and b side by side): a gradient whose square
        // overflows f32 in b's slot (f32::MAX² ≈ 1.2e77 is finite in the f64 norm) is
        // refused and named; a NaN gradient on either thread makes the norm NaN.
        let (a, b) = (
            Var::from_slice(&[1.0f32], 1, &Device::Cpu).unwrap(),
            Var::from_slice(&[2.0f32], 1, &Device::Cpu).unwrap(),
        );
        let vars = vec![("a".into(), a.clone()), ("b".into(), b.clone())];
        let opt = Optimizer::new(vars, OptimizerConfig::ADAM_TF1, 0.1).unwrap();
        let (ia, ib) = (a.as_tensor().id(), b.as_tensor().id());
        let mut h = opt.host_state().unwrap();
        let err = opt
            .step_host_on(&mut h, &[(ia, vec![0.5]), (ib, vec![f32::MAX])], 2)
            .unwrap_err();
        assert!(
            matches!(&err, CoreError::NonFinite(m) if m.contains(" b ")),
            "{err}"
        );
        for grads in [
            vec![(ia, vec![f32::NAN]), (ib, vec![0.5])],
            vec![(ia, vec![0.5]), (ib, vec![f32::NAN])],
        ] {
            let mut h = opt.host_state().unwrap();
            let err = opt.step_host_on(&mut h, &grads, 2).unwrap_err();
            assert!(
                matches!(&err, CoreError::NonFinite(m) if m.contains("norm")),
                "{err}"
            );
            assert_eq!(h.steps(), 0);
        }
    }

    /// A weight whose gradient falls to 0 (a ReLU unit no row reaches any more): after
    /// 1,000 steps its slots would be subnormal (Adam's m decays by 0.9 a step: 1e-3 ·
    /// 0.9^999 ≈ 3e-49, ms by 0.9 likewise), and the host step holds them at 0 instead,
    /// while the weights stay the tensor path's (which keeps the subnormals) to the bit.
    #[test]
    fn slots_that_decay_below_the_smallest_normal_are_flushed_without_moving_a_weight() {
        for config in [OptimizerConfig::RMSPROP_TF1, OptimizerConfig::ADAM_TF1] {
            let run = |host: bool| -> (Vec<f32>, Vec<f32>) {
                let w = Var::from_slice(&[0.3f32, -0.7], 2, &Device::Cpu).unwrap();
                let mut opt = Optimizer::new(vec![("w".into(), w.clone())], config, 0.01).unwrap();
                opt.host = host;
                for k in 0..1000 {
                    // A gradient of 1e-3 on the first 10 steps, then none.
                    let g = if k < 10 { 1e-3f32 } else { 0.0 };
                    let g = Tensor::from_slice(&[g, g], 2, &Device::Cpu).unwrap();
                    let loss = (w.as_tensor() * g).unwrap().sum_all().unwrap();
                    opt.step(&loss.backward().unwrap()).unwrap();
                }
                let slots: Vec<f32> = opt
                    .slots()
                    .iter()
                    .flat_map(|(_, t)| t.flatten_all().unwrap().to_vec1::<f32>().unwrap())
                    .collect();
                (w.as_tensor().to_vec1().unwrap(), slots)
            };
            let ((w_host, s_host), (w_tensor, s_tensor)) = (run(true), run(false));
            assert_eq!(w_host, w_tensor, "{config:?}");
            assert!(
                s_tensor.iter().any(|x| x.is_subnormal()),
                "{config:?}: {s_tensor:?}"
            );
            assert!(
                s_host.iter().all(|x| *x == 0.0 || x.is_normal()),
                "{config:?}: {s_host:?}"
            );
        }
    }
}
