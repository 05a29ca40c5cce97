//! A multilayer perceptron's forward and backward on the host with gemm into plain
//! buffers (PPO's and SAVER's hand-written minibatch steps, ppo/fast.rs and
//! saver/host_step.rs), its weights read from the optimiser's [`HostState`].

use crate::algo::dense::matmul;
use crate::nets::Linear;
use crate::optim::HostState;
use crate::Result;

/// One MLP's layers on the host, borrowed from the optimiser's [`HostState`]: (weight
/// [in, out] row-major, bias [out], in, out).
pub(crate) struct HostMlp<'a> {
    pub(crate) layers: Vec<(&'a [f32], &'a [f32], usize, usize)>,
}

impl<'a> HostMlp<'a> {
    pub(crate) fn of(layers: &[&Linear], h: &'a HostState) -> Result<Self> {
        let mut out = Vec::with_capacity(layers.len());
        for l in layers {
            let (i, o) = l.w.dims2()?;
            out.push((value(h, &l.w)?, value(h, &l.b)?, i, o));
        }
        Ok(Self { layers: out })
    }

    /// Every layer's output for `x` [n, in] into `s.acts`: ReLU on all but the last,
    /// which is linear.
    pub(crate) fn forward(&self, x: &[f32], n: usize, s: &mut MlpScratch) {
        s.acts.resize_with(self.layers.len(), Vec::new);
        for (k, (w, b, i, o)) in self.layers.iter().enumerate() {
            let (done, rest) = s.acts.split_at_mut(k);
            let input = if k == 0 { x } else { &done[k - 1] };
            let y = &mut rest[0];
            // gemm writes every element (it never reads dst), so no zeroing.
            y.resize(n * o, 0.0);
            matmul(y, input, w, (n, *i, *o), (false, false));
            let last = k + 1 == self.layers.len();
            for row in y.chunks_exact_mut(*o) {
                for (v, bias) in row.iter_mut().zip(b.iter()) {
                    *v += bias;
                    if !last && *v < 0.0 {
                        *v = 0.0;
                    }
                }
            }
        }
    }

    /// Each layer's (dW, db) into `s.grads` from the gradient of the last layer's
    /// output in `s.dy` [n, out], given the input `x` and the activations of
    /// [`HostMlp::forward`] in `s.acts`. Leaves `s.dy` and `s.dx` as scratch.
    pub(crate) fn backward(&self, x: &[f32], n: usize, s: &mut MlpScratch) {
        s.grads.resize_with(self.layers.len(), Default::default);
        for k in (0..self.layers.len()).rev() {
            let (w, _, i, o) = &self.layers[k];
            let input = if k == 0 { x } else { &s.acts[k - 1] };
            let (dw, db) = &mut s.grads[k];
            dw.resize(i * o, 0.0);
            matmul(dw, input, &s.dy, (*i, n, *o), (true, false));
            db.clear();
            db.resize(*o, 0.0);
            for row in s.dy.chunks_exact(*o) {
                for (sum, v) in db.iter_mut().zip(row) {
                    *sum += v;
                }
            }
            if k > 0 {
                s.dx.resize(n * i, 0.0);
                matmul(&mut s.dx, &s.dy, w, (n, *o, *i), (false, true));
                // Through the ReLU that made the input: no gradient where it was cut
                // (a select, not a branch, so that the loop vectorises).
                relu_back(&mut s.dx, input);
                std::mem::swap(&mut s.dy, &mut s.dx);
            }
        }
    }
}

/// One MLP's buffers for [`HostMlp::forward`] and [`HostMlp::backward`], kept across
/// the minibatches of an update: each step writes the same memory (no allocation, no
/// zeroing, and addresses that stay in cache beside the optimiser's state).
#[derive(Default)]
pub(crate) struct MlpScratch {
    /// Each layer's output [n, out].
    pub(crate) acts: Vec<Vec<f32>>,
    /// Each layer's (dW [in, out], db [out]).
    pub(crate) grads: Vec<(Vec<f32>, Vec<f32>)>,
    /// The gradient of the layer output being propagated back, and of its input.
    pub(crate) dy: Vec<f32>,
    pub(crate) dx: Vec<f32>,
}

/// The optimiser's current value of the variable `var`.
pub(crate) fn value<'a>(h: &'a HostState, var: &candle_core::Tensor) -> Result<&'a [f32]> {
    h.value(var).ok_or_else(|| {
        crate::CoreError::Data("the optimiser does not train a layer of this step".into())
    })
}

/// candle's gradient share of `x` in max(x, y) or min(x, y) when `x` is the one taken:
/// 1, ½ on a tie, 0 when the other one is taken.
pub(crate) fn share(taken: bool, tie: bool) -> f32 {
    if tie {
        0.5
    } else if taken {
        1.0
    } else {
        0.0
    }
}

/// `g` ← g ⊙ 1[a > 0]: a gradient through the ReLU whose output was `a` (a select, not a
/// branch, so that the loop vectorises).
pub(crate) fn relu_back(g: &mut [f32], a: &[f32]) {
    for (g, a) in g.iter_mut().zip(a) {
        *g = if *a > 0.0 { *g } else { 0.0 };
    }
}

/// log σ = clamp(ℓ, lo, hi) of each entry of the variable ℓ (`raw`), candle's clamp being
/// max(ℓ, lo) then min(·, hi), with the share of a gradient at log σ that reaches ℓ
/// (ties split as candle splits them); unbounded: ℓ itself and 1.
pub(crate) fn clamped_log_std(raw: &[f32], bounds: Option<(f64, f64)>) -> (Vec<f32>, Vec<f32>) {
    raw.iter()
        .map(|&p| match bounds {
            Some((lo, hi)) => {
                let (lo, hi) = (lo as f32, hi as f32);
                let m = p.max(lo);
                (m.min(hi), share(p > lo, p == lo) * share(m < hi, m == hi))
            }
            None => (p, 1.0),
        })
        .unzip()
}

/// Each layer's (weight, bias) gradient of `grads` (as [`HostMlp::backward`] leaves
/// them) with its variable's id, appended to `out` (what `Optimizer::step_host` takes).
pub(crate) fn layer_grads<'s>(
    layers: &[&Linear],
    grads: &'s [(Vec<f32>, Vec<f32>)],
    out: &mut Vec<(candle_core::TensorId, &'s [f32])>,
) {
    for (l, (dw, db)) in layers.iter().zip(grads) {
        out.push((l.w.id(), &dw[..]));
        out.push((l.b.id(), &db[..]));
    }
}
