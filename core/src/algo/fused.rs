//! The τ-dependent half of the frozen PCPN (docs/ALGORITHM.md §7), forward and input-gradient, fused per
//! block of transitions so that nothing of size B·K·d·128 is ever materialised.
//!
//! For one state dimension j and a block of `BLOCK` transitions (R = BLOCK·K rows):
//!
//! ```text
//! cos[r, i] = cos(π·i·τ_r)                  (Chebyshev, embedding.rs)
//! e[r, i]   = z[b(r), j·128 + i] · cos[r, i]
//! u         = relu(e·W2_j + b2_j)           (gemm, R×128×64)
//! q[r]      = u[r]·w3_j + b3_j (+ s·(2τ_r − 1): QRRL's base quantile function)
//! dq        = dL/dq (quantile loss and monotonic pairs, one transition's K rows at a time)
//! du        = dq ⊗ w3_j ⊙ 1[u > 0]
//! de        = du·W2_jᵀ                      (gemm, R×64×128)
//! dz[b, i]  = Σ_k de[b·K + k, i] · cos[b·K + k, i]
//! ```
//!
//! With weight gradients on (PCPN pretraining, where the heads are trained), a block
//! also gives its share of the head gradients before its buffers are overwritten:
//!
//! ```text
//! dw3_j = uᵀ·dq,  db3_j = Σ_r dq[r]         (u after its ReLU)
//! dW2_j = eᵀ·du,  db2_j = Σ_r du[r, ·]      (gemm, 128×R×64)
//! ```
//!
//! Every buffer of a block (about 0.5 MB at BLOCK = 8) stays in the core's L2 cache,
//! where the unfused path wrote and re-read ~28 MB per update at d = 4 (measured: 11 %
//! of the update in memset alone). Blocks are independent, so they are split across
//! threads in contiguous runs (an option of the SAVER update, [`threads_for`]); the loss sums are added in block order,
//! so the result does not depend on the thread count.

use super::dense::{dot, matmul};
use crate::config::SaverConfig;
use crate::embedding::{cosine_embedding_lanes, EMBED_DIM};
use crate::loss::{pair_penalty, quantile_rho};
use crate::nets::PCPN_HEAD_HIDDEN;

/// Threads for `threads` = 0: one per core.
///
/// On the 2-core reference machine the blocks run 1.3-1.6x faster on two threads (d = 4
/// to 16), while candle's small agent and critic matmuls are slower on two (`saver
/// bench`), so this is apart from candle's own thread count.
pub fn threads_for(threads: usize) -> usize {
    match threads {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => n,
    }
}

/// Transitions per block (R = 8·32 = 256 rows at K = 32).
const BLOCK: usize = 8;

/// The per-dimension heads of a frozen PCPN as plain row-major arrays.
pub struct Heads {
    /// [d, 128, 64].
    pub w2: Vec<f32>,
    /// [d, 64].
    pub b2: Vec<f32>,
    /// [d, 64].
    pub w3: Vec<f32>,
    /// [d].
    pub b3: Vec<f32>,
}

impl Heads {
    /// Zeros of the shapes of a PCPN's heads with `d` dimensions.
    fn zeros(d: usize) -> Self {
        let h = PCPN_HEAD_HIDDEN;
        Self {
            w2: vec![0.0; d * EMBED_DIM * h],
            b2: vec![0.0; d * h],
            w3: vec![0.0; d * h],
            b3: vec![0.0; d],
        }
    }
}

/// The loss the blocks compute: SAVER's (κ and λ_mon from its config), or the plain
/// quantile loss of PCPN pretraining (advantages of 1, no κ, λ_mon = 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Loss {
    /// Huber threshold of the quantile loss (`None`: plain ρ_τ).
    pub kappa: Option<f64>,
    /// Weight of the monotonic penalty (0: none).
    pub lambda_mon: f64,
}

impl From<&SaverConfig> for Loss {
    fn from(c: &SaverConfig) -> Self {
        Self {
            kappa: c.kappa,
            lambda_mon: c.lambda_mon,
        }
    }
}

impl Loss {
    /// Pretraining's loss: mean ρ_τ(Δp − q), nothing else.
    pub const PRETRAIN: Self = Self {
        kappa: None,
        lambda_mon: 0.0,
    };
}

/// What the blocks add up to.
pub struct Fused {
    /// L_a = Σ ρ_τ(δ)·Â / (B·K·d).
    pub actor_loss: f32,
    /// L_mon = λ·2K/(B·K·K·d) Σ Huber_1(relu(q_a − q_b)) over ascending pairs.
    pub mon_loss: f32,
    /// dL/dz [B, d·128] (before z's ReLU mask).
    pub dz: Vec<f32>,
    /// dL/d(heads), in the layout of [`Heads`], when asked for.
    pub head_grads: Option<Heads>,
}

/// The inputs that every block reads.
pub struct Inputs<'a> {
    /// z = relu(h·W1 + b1) [B, d·128].
    pub z: &'a [f32],
    /// Δp [B, d].
    pub state_delta: &'a [f32],
    /// Â [B, d].
    pub advantage: &'a [f32],
    /// τ [d, B, K].
    pub taus: &'a [f32],
    /// s of a fixed base quantile function s·(2τ − 1) added to every output (standalone
    /// QRRL's policy; 0 for the PCPN). Its gradient is zero: only q's value moves.
    pub tau_base: f32,
    /// B, K, d.
    pub b: usize,
    pub k: usize,
    pub d: usize,
}

/// What every block reads: the heads, the inputs, the loss constants and the two
/// normalisers 1/(B·K·d) (L_a) and λ·2K/(B·K·K·d) (L_mon).
struct Job<'a> {
    heads: &'a Heads,
    x: &'a Inputs<'a>,
    loss: Loss,
    qn: f64,
    mn: f64,
    weight_grads: bool,
}

/// One block's results: (Σ ρ·Â, Σ Huber, dz block [n, 128], its head gradients).
struct UnitOut {
    la: f64,
    lm: f64,
    dz: Vec<f32>,
    grads: Option<HeadGrad>,
}

/// One block's share of one dimension's head gradients.
struct HeadGrad {
    /// [128, 64].
    w2: Vec<f32>,
    /// [64].
    b2: Vec<f32>,
    /// [64].
    w3: Vec<f32>,
    b3: f32,
}

/// Scratch buffers of one block, reused across the blocks a worker runs.
#[derive(Default)]
struct Scratch {
    cos: Vec<f32>,
    e: Vec<f32>,
    u: Vec<f32>,
    q: Vec<f32>,
    dq: Vec<f32>,
    order: Vec<usize>,
}

/// Runs every (dimension, block) unit on `threads` threads (0: one per core); see the
/// module docs. With `weight_grads` the result also holds the heads' gradients (added
/// in block order, so they too do not depend on the thread count).
pub fn run(heads: &Heads, x: &Inputs, loss: Loss, threads: usize, weight_grads: bool) -> Fused {
    let (units, job) = plan(heads, x, loss, weight_grads);
    let threads = threads_for(threads).clamp(1, units.len().max(1));
    let run_of = |part: &[(usize, usize)]| {
        let mut s = Scratch::default();
        part.iter()
            .map(|&(j, b0)| unit(&job, j, b0, &mut s))
            .collect::<Vec<_>>()
    };
    let parts: Vec<UnitOut> = if threads == 1 {
        run_of(&units)
    } else {
        let per = units.len().div_ceil(threads);
        std::thread::scope(|scope| {
            let handles: Vec<_> = units
                .chunks(per)
                .map(|part| scope.spawn(move || run_of(part)))
                .collect();
            handles
                .into_iter()
                .flat_map(|h| h.join().expect("a PCPN block thread panicked"))
                .collect()
        })
    };
    reduce(&job, &units, parts)
}

/// [`run`] with every unit a task of the rayon pool this is called in, so that a
/// worker that finishes other work of the pool (`rayon::join`) takes blocks over: the
/// same bits (the units' results are added in block order).
pub fn run_in_pool(heads: &Heads, x: &Inputs, loss: Loss, weight_grads: bool) -> Fused {
    use rayon::prelude::*;
    let (units, job) = plan(heads, x, loss, weight_grads);
    let parts: Vec<UnitOut> = units
        .par_iter()
        .map_init(Scratch::default, |s, &(j, b0)| unit(&job, j, b0, s))
        .collect();
    reduce(&job, &units, parts)
}

/// The (dimension, first transition) units of a run and what every unit reads.
fn plan<'a>(
    heads: &'a Heads,
    x: &'a Inputs<'a>,
    loss: Loss,
    weight_grads: bool,
) -> (Vec<(usize, usize)>, Job<'a>) {
    let units: Vec<(usize, usize)> = (0..x.d)
        .flat_map(|j| (0..x.b).step_by(BLOCK).map(move |b0| (j, b0)))
        .collect();
    let (b, k, d) = (x.b as f64, x.k as f64, x.d as f64);
    let job = Job {
        heads,
        x,
        loss,
        qn: 1.0 / (b * k * d),
        mn: loss.lambda_mon * 2.0 * k / (b * k * k * d),
        weight_grads,
    };
    (units, job)
}

/// The units' results `parts` (in the order of `units`) added up in block order.
fn reduce(job: &Job, units: &[(usize, usize)], parts: Vec<UnitOut>) -> Fused {
    let x = job.x;
    let weight_grads = job.weight_grads;
    let (w, dw) = (EMBED_DIM, x.d * EMBED_DIM);
    let mut dz = vec![0.0f32; x.b * dw];
    let (mut actor_sum, mut mon_sum) = (0.0, 0.0);
    let mut head_grads = weight_grads.then(|| Heads::zeros(x.d));
    for (&(j, b0), out) in units.iter().zip(parts) {
        actor_sum += out.la;
        mon_sum += out.lm;
        for (r, row) in out.dz.chunks_exact(w).enumerate() {
            let at = (b0 + r) * dw + j * w;
            dz[at..at + w].copy_from_slice(row);
        }
        if let (Some(all), Some(g)) = (head_grads.as_mut(), out.grads) {
            let h = PCPN_HEAD_HIDDEN;
            add_into(&mut all.w2[j * w * h..(j + 1) * w * h], &g.w2);
            add_into(&mut all.b2[j * h..(j + 1) * h], &g.b2);
            add_into(&mut all.w3[j * h..(j + 1) * h], &g.w3);
            all.b3[j] += g.b3;
        }
    }
    Fused {
        actor_loss: (actor_sum * job.qn) as f32,
        mon_loss: (mon_sum * job.mn) as f32,
        dz,
        head_grads,
    }
}

fn add_into(acc: &mut [f32], x: &[f32]) {
    for (a, &v) in acc.iter_mut().zip(x) {
        *a += v;
    }
}

/// One dimension j and the transitions b0..b0+BLOCK.
///
/// Compiled twice: for the baseline x86-64 target and with AVX2 (8 f32 lanes instead
/// of 4), picked at run time. No `mul_add` is written and no float reduction is
/// reordered, so both give the same bits.
fn unit(job: &Job, j: usize, b0: usize, s: &mut Scratch) -> UnitOut {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just now).
        return unsafe { unit_avx2(job, j, b0, s) };
    }
    unit_body(job, j, b0, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn unit_avx2(job: &Job, j: usize, b0: usize, s: &mut Scratch) -> UnitOut {
    unit_body(job, j, b0, s)
}

#[inline(always)]
fn unit_body(job: &Job, j: usize, b0: usize, s: &mut Scratch) -> UnitOut {
    let (heads, x) = (job.heads, job.x);
    let (w, h, k) = (EMBED_DIM, PCPN_HEAD_HIDDEN, x.k);
    let n = BLOCK.min(x.b - b0);
    let rows = n * k;
    let w2 = &heads.w2[j * w * h..(j + 1) * w * h];
    let (b2, w3, b3) = (
        &heads.b2[j * h..(j + 1) * h],
        &heads.w3[j * h..(j + 1) * h],
        heads.b3[j],
    );
    let taus = &x.taus[(j * x.b + b0) * k..(j * x.b + b0 + n) * k];

    s.cos.resize(rows * w, 0.0);
    // The inlined recurrence, so that it is compiled with this unit's features.
    cosine_embedding_lanes(taus, w, &mut s.cos);
    s.e.clear();
    for (r, c) in s.cos.chunks_exact(w).enumerate() {
        let zb = b0 + r / k;
        let zrow = &x.z[zb * x.d * w + j * w..][..w];
        s.e.extend(c.iter().zip(zrow).map(|(&c, &z)| c * z));
    }
    s.u.resize(rows * h, 0.0);
    matmul(&mut s.u, &s.e, w2, (rows, w, h), (false, false));
    s.q.clear();
    for (urow, &tau) in s.u.chunks_exact_mut(h).zip(taus) {
        for (v, &bias) in urow.iter_mut().zip(b2) {
            *v = (*v + bias).max(0.0);
        }
        let base = crate::nets::base_quantile(x.tau_base, tau);
        s.q.push(dot(urow, w3) + b3 + base);
    }

    s.dq.clear();
    s.dq.resize(rows, 0.0);
    let (mut la, mut lm) = (0.0f64, 0.0f64);
    for t in 0..n {
        let b = b0 + t;
        let rg = t * k..(t + 1) * k;
        let (a, m) = transition_grad(
            &s.q[rg.clone()],
            &taus[rg.clone()],
            x.state_delta[b * x.d + j],
            x.advantage[b * x.d + j],
            &mut s.dq[rg],
            job.loss,
            (job.qn, job.mn as f32),
            &mut s.order,
        );
        la += a;
        lm += m;
    }

    // dw3 = uᵀ·dq and db3 = Σ dq while u still holds the activations.
    let mut grads = job.weight_grads.then(|| {
        let mut dw3 = vec![0.0f32; h];
        for (urow, &g) in s.u.chunks_exact(h).zip(&s.dq) {
            for (a, &v) in dw3.iter_mut().zip(urow) {
                *a += g * v;
            }
        }
        HeadGrad {
            w2: vec![0.0; w * h],
            b2: vec![0.0; h],
            w3: dw3,
            b3: s.dq.iter().sum(),
        }
    });
    // du (in u's buffer), then de (in e's buffer).
    for (urow, &g) in s.u.chunks_exact_mut(h).zip(&s.dq) {
        for (v, &ww) in urow.iter_mut().zip(w3) {
            *v = g * ww * f32::from(u8::from(*v > 0.0));
        }
    }
    if let Some(g) = grads.as_mut() {
        // dW2 = eᵀ·du [128, 64], db2 = Σ_r du[r, ·], before e is overwritten.
        matmul(&mut g.w2, &s.e, &s.u, (w, rows, h), (true, false));
        for urow in s.u.chunks_exact(h) {
            add_into(&mut g.b2, urow);
        }
    }
    matmul(&mut s.e, &s.u, w2, (rows, h, w), (false, true));
    let mut dz = vec![0.0f32; n * w];
    for (t, acc) in dz.chunks_exact_mut(w).enumerate() {
        let off = t * k * w;
        for (g, c) in s.e[off..off + k * w]
            .chunks_exact(w)
            .zip(s.cos[off..off + k * w].chunks_exact(w))
        {
            for ((a, &gv), &cv) in acc.iter_mut().zip(g).zip(c) {
                *a += gv * cv;
            }
        }
    }
    UnitOut { la, lm, dz, grads }
}

/// One transition's K rows for one dimension: adds dL/dq into `gs` and returns the
/// unnormalised (Σ ρ_τ(δ)·Â, Σ Huber_1(relu(q_a − q_b))).
///
/// dL_a/dq = −ρ'_τ(δ)·Â·qn; a pair v = q_a − q_b > 0 with τ_a < τ_b adds ±min(v, 1)·mn.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn transition_grad(
    qs: &[f32],
    ts: &[f32],
    target: f32,
    adv: f32,
    gs: &mut [f32],
    loss: Loss,
    (qn, mn): (f64, f32),
    order: &mut Vec<usize>,
) -> (f64, f64) {
    let k = qs.len();
    let kappa = loss.kappa.map(|k| k as f32);
    let mut la = 0.0f64;
    for i in 0..k {
        let (rho, drho) = quantile_rho(target - qs[i], ts[i], kappa);
        la += (rho * adv) as f64;
        gs[i] += (-(drho * adv) as f64 * qn) as f32;
    }
    if loss.lambda_mon == 0.0 {
        return (la, 0.0);
    }
    // Pairs in ascending τ, each once, without branches: `pair_penalty` of
    // v = q_a − q_b, times 0 when the τ are equal (the strict < excludes them).
    order.clear();
    order.extend(0..k);
    order.sort_unstable_by(|&x, &y| ts[x].total_cmp(&ts[y]));
    let mut row_loss = 0.0f32;
    for a in 0..k {
        let ia = order[a];
        let (qa, ta) = (qs[ia], ts[ia]);
        let mut ga = 0.0f32;
        for &ib in &order[a + 1..] {
            let ordered = f32::from(u8::from(ta < ts[ib]));
            let (l, c) = pair_penalty(qa - qs[ib]);
            row_loss += l * ordered;
            let g = c * ordered * mn;
            ga += g;
            gs[ib] -= g;
        }
        gs[ia] += ga;
    }
    (la, row_loss as f64)
}
