//! The optimiser's arithmetic on the host: one pass per variable over plain `f32`
//! buffers in a [`HostState`]. [`Optimizer::step`] takes its CPU steps through one (copy,
//! step, commit); PPO's hand-written minibatch steps keep one for a whole update, so no
//! tensor is read or written between them until [`Optimizer::commit_host`].

use super::host_math::{flush_subnormal, join_if, sum_sq, to_host};
use super::{Optimizer, OptimizerConfig};
use crate::{CoreError, Result};
use candle_core::{Tensor, TensorId};

/// The constants of one optimiser step: rate `lr` on step `t` (from 1) and the clip
/// factor `scale` every gradient is multiplied by (1 when unclipped).
#[derive(Clone, Copy)]
struct StepAt {
    config: OptimizerConfig,
    lr: f64,
    t: u64,
    scale: f32,
}

/// One variable's step in place: `value` and its slots `s1` (ms or m) and `s2` (v; empty
/// for RMSProp) from the gradient `g`, with the constants `at`. The arithmetic of the tensor path with each
/// constant rounded to f32 as candle's affine rounds it, so both give the same bits, but
/// that a new slot value below f32's smallest normal is stored as 0 ([`flush_subnormal`]).
/// True when any new value or slot is non-finite.
///
/// Compiled twice, for the baseline x86-64 target and with AVX2 (eight f32 lanes instead
/// of four), picked at run time; no `mul_add` is written, so both give the same bits.
/// This pass was a fifth of PPO's hand-written update (perf, angle d = 2).
fn apply(at: StepAt, value: &mut [f32], s1: &mut [f32], s2: &mut [f32], g: &[f32]) -> bool {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just now).
        return unsafe { apply_avx2(at, value, s1, s2, g) };
    }
    apply_lanes(at, value, s1, s2, g)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn apply_avx2(
    at: StepAt,
    value: &mut [f32],
    s1: &mut [f32],
    s2: &mut [f32],
    g: &[f32],
) -> bool {
    apply_lanes(at, value, s1, s2, g)
}

#[inline(always)]
fn apply_lanes(at: StepAt, value: &mut [f32], s1: &mut [f32], s2: &mut [f32], g: &[f32]) -> bool {
    // Any non-finite value or slot sets a bit; a bitwise or (no early exit) lets the
    // loops vectorise, sqrt and division included (the same IEEE results per lane).
    // x·1 is x, so an unclipped step multiplies by 1 and keeps its bits.
    let StepAt {
        config,
        lr,
        t,
        scale,
    } = at;
    let mut bad = false;
    match config {
        OptimizerConfig::Rmsprop { decay, eps, .. } => {
            let one_minus = 1.0f32 - decay as f32;
            let (lr, eps) = (lr as f32, eps as f32);
            for ((w, ms), &g) in value.iter_mut().zip(s1.iter_mut()).zip(g) {
                let g = g * scale;
                *ms = flush_subnormal(*ms + (g * g - *ms) * one_minus);
                *w -= (g * lr) / (*ms + eps).sqrt();
                bad |= !w.is_finite() | !ms.is_finite();
            }
        }
        OptimizerConfig::Adam { beta1, beta2, eps } => {
            let ti = t as i32;
            let lr_t = (lr * (1.0 - beta2.powi(ti)).sqrt() / (1.0 - beta1.powi(ti))) as f32;
            let (b1, b2) = (beta1 as f32, beta2 as f32);
            let (c1, c2, eps) = ((1.0 - beta1) as f32, (1.0 - beta2) as f32, eps as f32);
            for (((w, m), v), &g) in value.iter_mut().zip(s1).zip(s2).zip(g) {
                let g = g * scale;
                *m = flush_subnormal(*m * b1 + g * c1);
                *v = flush_subnormal(*v * b2 + g * g * c2);
                *w -= (*m * lr_t) / (v.sqrt() + eps);
                bad |= !w.is_finite() | !m.is_finite() | !v.is_finite();
            }
        }
    }
    bad
}

/// An optimiser's variables, slots and step count copied to the host
/// ([`Optimizer::host_state`]): [`Optimizer::step_host`] takes steps on it from host
/// gradients with the optimiser's arithmetic, rate schedule and clip, and
/// [`Optimizer::commit_host`] writes the result back. Nothing reaches the optimiser or its variables before the
/// commit, so dropping the state instead leaves them as they were.
pub struct HostState {
    /// The variables' tensor ids, in the optimiser's order.
    ids: Vec<TensorId>,
    values: Vec<Vec<f32>>,
    s1: Vec<Vec<f32>>,
    /// Empty for RMSProp.
    s2: Vec<Vec<f32>>,
    /// Steps taken, as [`Optimizer::steps`].
    t: u64,
}

impl HostState {
    /// The current value of the variable whose tensor is `var`, if the optimiser trains it.
    pub fn value(&self, var: &Tensor) -> Option<&[f32]> {
        let i = self.index(var.id())?;
        Some(&self.values[i])
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u64 {
        self.t
    }

    fn index(&self, id: TensorId) -> Option<usize> {
        self.ids.iter().position(|&i| i == id)
    }
}

/// One variable's part of a host step: its index, value, slots and gradient.
struct VarStep<'a> {
    i: usize,
    value: &'a mut [f32],
    s1: &'a mut [f32],
    s2: &'a mut [f32],
    g: &'a [f32],
}

/// Each variable's Σ g², in order.
fn squares(vars: &[VarStep]) -> Vec<f64> {
    vars.iter().map(|v| sum_sq(v.g)).collect()
}

/// √ of the sums added in order from 0.
fn norm_of(squares: &[f64]) -> f64 {
    squares.iter().fold(0.0f64, |acc, &s| acc + s).sqrt()
}

/// Every variable's step; the index of the first whose new value or slot is not finite.
fn apply_all(at: StepAt, vars: &mut [VarStep]) -> Option<usize> {
    for v in vars {
        if apply(at, v.value, v.s1, v.s2, v.g) {
            return Some(v.i);
        }
    }
    None
}

/// Where to split `vars` into two runs of about equal elements: after the first
/// variable that takes the running count to half or more.
fn half_way(vars: &[VarStep]) -> usize {
    let total: usize = vars.iter().map(|v| v.g.len()).sum();
    let mut seen = 0;
    for (k, v) in vars.iter().enumerate() {
        seen += v.g.len();
        if 2 * seen >= total {
            return k + 1;
        }
    }
    vars.len()
}

impl Optimizer {
    /// The variables, slots and step count on the host, for a run of [`Optimizer::step_host`]s
    /// (every variable on the CPU); [`Optimizer::commit_host`] writes them back.
    pub fn host_state(&self) -> Result<HostState> {
        let all = |ts: &[Tensor]| ts.iter().map(to_host).collect::<Result<Vec<_>>>();
        let vars: Vec<Tensor> = self
            .vars
            .iter()
            .map(|(_, v)| v.as_tensor().clone())
            .collect();
        Ok(HostState {
            ids: vars.iter().map(|v| v.id()).collect(),
            values: all(&vars)?,
            s1: all(&self.slot1)?,
            s2: all(&self.slot2)?,
            t: self.t,
        })
    }

    /// Whether `h` holds this optimiser's variables.
    fn made(&self, h: &HostState) -> Result<()> {
        let same = h.ids.len() == self.vars.len()
            && h.ids
                .iter()
                .zip(&self.vars)
                .all(|(&id, (_, v))| id == v.as_tensor().id());
        if same {
            Ok(())
        } else {
            Err(CoreError::Data(
                "a host state used with an optimiser that did not make it".into(),
            ))
        }
    }

    /// One step on the host state `h` with `grads` (variable tensor id, gradient in the
    /// variable's row-major order), with this optimiser's constants, rate schedule and
    /// clip; variables without a gradient are left alone. Returns the gradients' global
    /// norm before clipping (squares summed in f64 per variable, in the optimiser's
    /// order). A gradient of the wrong size, for a variable the optimiser does not train
    /// or for one already given is [`CoreError::Data`]; a non-finite norm, or a step
    /// that would make a value or slot non-finite, is [`CoreError::NonFinite`] and
    /// leaves `h` unusable: drop it (nothing has been written back).
    pub fn step_host<G: AsRef<[f32]> + Sync>(
        &self,
        h: &mut HostState,
        grads: &[(TensorId, G)],
    ) -> Result<f64> {
        self.step_host_on(h, grads, 1)
    }

    /// [`Optimizer::step_host`] with the variables split into two runs of about equal
    /// size when `threads` > 1, the two run side by side by `rayon::join` (on the pool
    /// whose `install` calls this, else on rayon's global pool): the same bits (every
    /// element's arithmetic is its own, and the squares of each variable are summed as
    /// before and added in the optimiser's order).
    pub fn step_host_on<G: AsRef<[f32]> + Sync>(
        &self,
        h: &mut HostState,
        grads: &[(TensorId, G)],
        threads: usize,
    ) -> Result<f64> {
        self.made(h)?;
        let at = self.trained(h, grads)?;
        let lr = super::lr_at(self.lr, self.decay_over, h.t);
        let t = h.t + 1;
        let step_for = |norm: f64| StepAt {
            config: self.config,
            lr,
            t,
            scale: self
                .clip
                .filter(|&c| norm > c)
                .map_or(1.0, |c| (c / norm) as f32),
        };
        // Each trained variable's buffers, in the optimiser's order.
        let mut s2s = h.s2.iter_mut();
        let mut vars = Vec::with_capacity(at.len());
        for (i, (value, s1)) in h.values.iter_mut().zip(h.s1.iter_mut()).enumerate() {
            let s2 = s2s.next().map_or(&mut [][..], |s| &mut s[..]);
            if let Some(k) = at.iter().position(|&j| j == i) {
                let g = grads[k].1.as_ref();
                vars.push(VarStep {
                    i,
                    value,
                    s1,
                    s2,
                    g,
                });
            }
        }
        let split = if threads > 1 {
            half_way(&vars)
        } else {
            vars.len()
        };
        let (first, later) = vars.split_at_mut(split);
        let two = !later.is_empty();
        let (mut sq, sq_later) = join_if(two, || squares(first), || squares(later));
        sq.extend(sq_later);
        let norm = norm_of(&sq);
        let bad = norm.is_finite().then(|| {
            let step = step_for(norm);
            let (a, b) = join_if(two, || apply_all(step, first), || apply_all(step, later));
            a.or(b)
        });
        let bad = bad.flatten();
        if !norm.is_finite() {
            return Err(CoreError::NonFinite(format!("the gradient norm is {norm}")));
        }
        if let Some(i) = bad {
            return Err(CoreError::NonFinite(format!(
                "the step would make the value or a slot of {} non-finite",
                self.vars[i].0
            )));
        }
        h.t = t;
        Ok(norm)
    }

    /// The index of each gradient's variable in `h`; a gradient of the wrong size, for a
    /// variable not trained here or for one already given is [`CoreError::Data`].
    fn trained<G: AsRef<[f32]>>(
        &self,
        h: &HostState,
        grads: &[(TensorId, G)],
    ) -> Result<Vec<usize>> {
        let mut at = Vec::with_capacity(grads.len());
        for (id, g) in grads {
            let g = g.as_ref();
            let i = h.index(*id).ok_or_else(|| {
                CoreError::Data("a host gradient for a variable not trained here".into())
            })?;
            if at.contains(&i) {
                return Err(CoreError::Data(
                    "two host gradients for one variable in one step".into(),
                ));
            }
            if g.len() != h.values[i].len() {
                return Err(CoreError::Data(format!(
                    "a host gradient of {} elements for {} of {}",
                    g.len(),
                    self.vars[i].0,
                    h.values[i].len()
                )));
            }
            at.push(i);
        }
        Ok(at)
    }

    /// Writes a [`HostState`] made by this optimiser back: the variables' values, the
    /// slots and the step count.
    pub fn commit_host(&mut self, h: HostState) -> Result<()> {
        self.made(&h)?;
        let mut s2 = h.s2.into_iter();
        for (i, (value, s1)) in h.values.into_iter().zip(h.s1).enumerate() {
            let var = &self.vars[i].1;
            let (shape, dev) = (var.shape().clone(), var.device().clone());
            var.set(&Tensor::from_vec(value, shape.clone(), &dev)?)?;
            self.slot1[i] = Tensor::from_vec(s1, shape.clone(), &dev)?;
            if let Some(s) = s2.next() {
                self.slot2[i] = Tensor::from_vec(s, shape, &dev)?;
            }
        }
        self.t = h.t;
        Ok(())
    }
}
