//! The numbers behind `saver diagnose pcpn` (diagnose.rs): an angle PCPN's quantiles
//! and input gradients by autograd, the env's true ones by Monte Carlo, and how well
//! they agree. See diagnose.rs for the definitions.

use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor, Var};
use rand::Rng;
use saver_core::embedding::{cosine_embedding, EMBED_DIM};
use saver_core::env::Angle;
use saver_core::nets::Pcpn;
use saver_core::rng::SaverRng;

/// One input of the PCPN: position, policy mean and standard deviation, each [d].
#[derive(Clone, Debug)]
pub struct Input {
    pub p: Vec<f32>,
    pub mu: Vec<f32>,
    pub sigma: Vec<f32>,
}

/// Jacobians at one input, indexed [m][j][i]: τ level, coordinate, action entry.
pub struct Jacobians {
    /// ∂Q_j(τ_m)/∂μ_i.
    pub mu: Vec<Vec<Vec<f32>>>,
    /// ∂Q_j(τ_m)/∂log σ_i.
    pub log_std: Vec<Vec<Vec<f32>>>,
    /// Q_j(τ_m), [m][j].
    pub q: Vec<Vec<f32>>,
}

/// The PCPN's quantiles and their input gradients at every τ of `taus` (autograd).
///
/// One row per (coordinate j, τ_m), all rows the same input x = [p, μ, log σ] with
/// every dimension's τ set to τ_m; the sum of Q_j over row (j, m) differentiates to
/// ∂Q_j(τ_m)/∂x in that row.
pub fn pcpn_jacobians(pcpn: &Pcpn, input: &Input, taus: &[f32]) -> Result<Jacobians> {
    let d = pcpn.dim();
    let m = taus.len();
    let rows = d * m;
    let dev = Device::Cpu;
    let mut x = Vec::with_capacity(rows * 3 * d);
    for _ in 0..rows {
        x.extend_from_slice(&input.p);
        x.extend_from_slice(&input.mu);
        x.extend(input.sigma.iter().map(|s| s.ln()));
    }
    // In the PCPN's own dtype (f64 in the test that differentiates it numerically).
    let dtype = pcpn.dtype();
    let x = Var::from_tensor(&Tensor::from_vec(x, (rows, 3 * d), &dev)?.to_dtype(dtype)?)?;
    // τ [d, rows, 1]: row (j, m) uses τ_m for every dimension.
    let row_taus: Vec<f32> = (0..rows).map(|r| taus[r % m]).collect();
    let all: Vec<f32> = (0..d).flat_map(|_| row_taus.iter().copied()).collect();
    let cos = Tensor::from_vec(
        cosine_embedding(&all, EMBED_DIM),
        (d, rows, 1, EMBED_DIM),
        &dev,
    )?
    .to_dtype(dtype)?;
    let q = pcpn.forward(x.as_tensor(), &cos)?; // [d, rows, 1]
                                                // Row r = j·m + mm belongs to coordinate j.
    let mask: Vec<f32> = (0..d)
        .flat_map(|j| (0..rows).map(move |r| f32::from(u8::from(r / m == j))))
        .collect();
    let mask = Tensor::from_vec(mask, (d, rows, 1), &dev)?.to_dtype(dtype)?;
    let grads = (&q * &mask)?.sum_all()?.backward()?;
    let g: Vec<f32> = grads
        .get(x.as_tensor())
        .context("no gradient reached the PCPN input")?
        .to_dtype(DType::F32)?
        .flatten_all()?
        .to_vec1()?;
    let qv: Vec<f32> = (q * mask)?
        .sum(0)?
        .to_dtype(DType::F32)?
        .flatten_all()?
        .to_vec1()?; // [rows]
    let width = 3 * d;
    let at = |j: usize, mm: usize| &g[(j * m + mm) * width..(j * m + mm + 1) * width];
    Ok(Jacobians {
        mu: (0..m)
            .map(|mm| (0..d).map(|j| at(j, mm)[d..2 * d].to_vec()).collect())
            .collect(),
        log_std: (0..m)
            .map(|mm| (0..d).map(|j| at(j, mm)[2 * d..].to_vec()).collect())
            .collect(),
        q: (0..m)
            .map(|mm| (0..d).map(|j| qv[j * m + mm]).collect())
            .collect(),
    })
}

/// The angle env's true quantiles of Δp_j and their derivatives in μ and log σ of the
/// action pair of j (the other entries are exactly 0), from `eps` ([draws, d] standard
/// normal draws, shared by every perturbation) and central differences of step `h`.
pub fn true_jacobians(input: &Input, taus: &[f32], eps: &[f32], h: f32) -> Jacobians {
    let d = input.p.len();
    let m = taus.len();
    let mut out = Jacobians {
        mu: vec![vec![vec![0.0; d]; d]; m],
        log_std: vec![vec![vec![0.0; d]; d]; m],
        q: vec![vec![0.0; d]; m],
    };
    for k in (0..d).step_by(2) {
        // Quantiles of (Δp_k, Δp_k+1) for the pair's (μ, σ).
        let quantiles = |mu: [f32; 2], sigma: [f32; 2]| -> [Vec<f32>; 2] {
            let draws = eps.len() / d;
            let mut cols = [Vec::with_capacity(draws), Vec::with_capacity(draws)];
            for e in eps.chunks_exact(d) {
                let a = [mu[0] + sigma[0] * e[k], mu[1] + sigma[1] * e[k + 1]];
                let delta = Angle::delta(&a);
                for (c, col) in cols.iter_mut().enumerate() {
                    let p = input.p[k + c];
                    col.push((p + delta[c]).clamp(-1.0, 1.0) - p);
                }
            }
            cols.map(|mut col| {
                col.sort_by(f32::total_cmp);
                taus.iter().map(|&t| quantile(&col, t)).collect()
            })
        };
        let mu = [input.mu[k], input.mu[k + 1]];
        let sigma = [input.sigma[k], input.sigma[k + 1]];
        let base = quantiles(mu, sigma);
        for (c, col) in base.iter().enumerate() {
            for (q, &v) in out.q.iter_mut().zip(col) {
                q[k + c] = v;
            }
        }
        for i in 0..2 {
            let (mut up, mut down) = (mu, mu);
            up[i] += h;
            down[i] -= h;
            let (qu, qd) = (quantiles(up, sigma), quantiles(down, sigma));
            let (mut su, mut sd) = (sigma, sigma);
            su[i] *= h.exp();
            sd[i] *= (-h).exp();
            let (su, sd) = (quantiles(mu, su), quantiles(mu, sd));
            for c in 0..2 {
                for mm in 0..m {
                    out.mu[mm][k + c][k + i] = (qu[c][mm] - qd[c][mm]) / (2.0 * h);
                    out.log_std[mm][k + c][k + i] = (su[c][mm] - sd[c][mm]) / (2.0 * h);
                }
            }
        }
    }
    out
}

/// The τ-quantile of sorted values, interpolated linearly between order statistics.
fn quantile(sorted: &[f32], tau: f32) -> f32 {
    let pos = tau * (sorted.len() - 1) as f32;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(sorted.len() - 1);
    let w = pos - lo as f32;
    sorted[lo] * (1.0 - w) + sorted[hi] * w
}

/// Sums of squares and products over every (input, τ, coordinate, entry) of one
/// Jacobian kind.
#[derive(Clone, Copy, Debug, Default)]
pub struct Agreement {
    /// Σ J_pcpn·J_true over in-pair entries.
    dot: f64,
    /// Σ J_pcpn² over in-pair entries.
    pcpn_in: f64,
    /// Σ J_true² over in-pair entries.
    true_in: f64,
    /// Σ (J_pcpn − J_true)² over in-pair entries.
    err_in: f64,
    /// Σ J_pcpn² over cross-pair entries (where the truth is 0).
    cross: f64,
}

impl Agreement {
    /// Adds one input's Jacobians.
    pub fn add(&mut self, pcpn: &[Vec<Vec<f32>>], truth: &[Vec<Vec<f32>>]) {
        for (pm, tm) in pcpn.iter().zip(truth) {
            for (j, (prow, trow)) in pm.iter().zip(tm).enumerate() {
                for (i, (&a, &b)) in prow.iter().zip(trow).enumerate() {
                    let (a, b) = (a as f64, b as f64);
                    if i / 2 == j / 2 {
                        self.dot += a * b;
                        self.pcpn_in += a * a;
                        self.true_in += b * b;
                        self.err_in += (a - b) * (a - b);
                    } else {
                        self.cross += a * a;
                    }
                }
            }
        }
    }

    /// Cosine of the in-pair entries, PCPN against truth.
    pub fn cosine(&self) -> f64 {
        self.dot / (self.pcpn_in * self.true_in).sqrt()
    }

    /// ‖J_in,pcpn − J_in,true‖ / ‖J_in,true‖.
    pub fn relative_error(&self) -> f64 {
        (self.err_in / self.true_in).sqrt()
    }

    /// ‖J_cross,pcpn‖ / ‖J_in,true‖.
    pub fn cross_ratio(&self) -> f64 {
        (self.cross / self.true_in).sqrt()
    }
}

/// Random inputs of the diagnosis.
pub fn random_input(d: usize, sigma: (f32, f32), rng: &mut SaverRng) -> Input {
    Input {
        p: (0..d).map(|_| rng.random_range(-1.0f32..1.0)).collect(),
        mu: (0..d).map(|_| rng.random_range(-1.0f32..1.0)).collect(),
        sigma: (0..d).map(|_| rng.random_range(sigma.0..sigma.1)).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use saver_core::env::{EnvKind, EnvSpec};
    use saver_core::nets::ParamSet;
    use saver_core::rng::{normal, rng_for};

    /// Nearly deterministic actions (σ = 0.001) at p = 0, μ = (0.5, 0): φ = π/2, so
    /// Δ0 = 0.1·a0·sin φ and Δ1 = 0.1·a0·cos φ give (by hand)
    /// Q0 = 0.05, ∂Q0/∂μ0 = 0.1, ∂Q0/∂μ1 = 0.1·0.5·cos(π/2)·π/2 = 0,
    /// Q1 = 0,    ∂Q1/∂μ0 = 0.1·cos(π/2) = 0, ∂Q1/∂μ1 = −0.1·0.5·sin(π/2)·π/2 = −0.07854;
    /// the second pair sits at p = 0.99 with a full step along +x: Δ2 = clip(0.99 +
    /// 0.1) − 0.99 = 0.01 whatever small change of μ2, so ∂Q2/∂μ2 = 0 (the wall).
    #[test]
    fn true_jacobians_by_hand() {
        let input = Input {
            p: vec![0.0, 0.0, 0.99, 0.0],
            mu: vec![0.5, 0.0, 1.0, 0.0],
            sigma: vec![0.001; 4],
        };
        let mut rng = rng_for(0, 0);
        let eps: Vec<f32> = (0..2000 * 4).map(|_| normal(&mut rng)).collect();
        let t = true_jacobians(&input, &[0.5], &eps, 0.01);
        let close = |a: f32, b: f32| (a - b).abs() < 2e-3;
        assert!(close(t.q[0][0], 0.05) && close(t.q[0][1], 0.0), "{:?}", t.q);
        assert!(close(t.mu[0][0][0], 0.1), "{:?}", t.mu[0][0]);
        assert!(close(t.mu[0][0][1], 0.0), "{:?}", t.mu[0][0]);
        assert!(close(t.mu[0][1][0], 0.0), "{:?}", t.mu[0][1]);
        assert!(close(t.mu[0][1][1], -0.078_54), "{:?}", t.mu[0][1]);
        assert!(
            close(t.q[0][2], 0.01) && close(t.mu[0][2][2], 0.0),
            "{:?}",
            t.mu[0][2]
        );
        // Entries across pairs are exactly zero.
        assert!(t.mu[0][0][2..].iter().all(|&v| v == 0.0));
        assert!(t.log_std[0][3][..2].iter().all(|&v| v == 0.0));
    }

    /// The autograd Jacobian of a (random) PCPN equals central differences of its own
    /// forward pass (in f64), entry by entry, at several τ.
    #[test]
    fn pcpn_jacobians_equal_finite_differences_of_the_network() {
        let spec = EnvSpec::new(EnvKind::Angle, 4).unwrap();
        let mut params = ParamSet::default();
        let p32 = Pcpn::init(
            &spec.layout(),
            &mut rng_for(3, 0),
            &Device::Cpu,
            &mut params,
        )
        .unwrap();
        let t = p32.tensors().unwrap();
        let pcpn = Pcpn::frozen(&spec.layout(), &|n| {
            t.iter()
                .find(|(k, _)| k == n)
                .map(|(_, x)| x.to_dtype(DType::F64).unwrap())
        })
        .unwrap();
        let input = random_input(4, (0.1, 0.9), &mut rng_for(1, 0));
        let taus = [0.2f32, 0.7];
        let j = pcpn_jacobians(&pcpn, &input, &taus).unwrap();
        // Q_c(τ) at x = [p, μ, log σ] in f64 throughout: the net has ReLU kinks at the
        // 1e-3 scale (one entry: differences 0.00252 at h = 1e-3, 0.0038343 at 1e-5 and
        // 1e-7, autograd 0.0038343), so h must be small and f64.
        let mut x: Vec<f64> = input.p.iter().chain(&input.mu).map(|&v| v as f64).collect();
        x.extend(input.sigma.iter().map(|s| s.ln() as f64));
        let q = |x: &[f64], tau: f32, c: usize| -> f64 {
            let cos = cosine_embedding(&[tau; 4], EMBED_DIM);
            let cos = Tensor::from_vec(cos, (4, 1, 1, EMBED_DIM), &Device::Cpu)
                .unwrap()
                .to_dtype(DType::F64)
                .unwrap();
            let x = Tensor::from_slice(x, (1, 12), &Device::Cpu).unwrap();
            pcpn.forward(&x, &cos)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f64>()
                .unwrap()[c]
        };
        let h = 1e-6;
        for (m, &tau) in taus.iter().enumerate() {
            for c in 0..4 {
                for i in 0..8 {
                    let (mut up, mut down) = (x.clone(), x.clone());
                    up[4 + i] += h;
                    down[4 + i] -= h;
                    let fd = (q(&up, tau, c) - q(&down, tau, c)) / (2.0 * h);
                    let g = if i < 4 {
                        j.mu[m][c][i]
                    } else {
                        j.log_std[m][c][i - 4]
                    } as f64;
                    assert!(
                        (fd - g).abs() <= 1e-5 * g.abs().max(1e-3),
                        "τ {tau} Q{c}/x{}: autograd {g}, differences {fd}",
                        4 + i
                    );
                }
            }
        }
    }

    /// The summary numbers by hand: PCPN (1, 0.5 | cross 0.3) against truth (1, 1 | 0):
    /// cos = 1.5/√(1.25·2) = 0.94868, relerr = √(0.25/2) = 0.35355, cross = √(0.09/2)
    /// = 0.21213.
    #[test]
    fn agreement_by_hand() {
        let mut a = Agreement::default();
        // d = 4, one τ: coordinate 0's row has in-pair entries 0, 1 and cross 2, 3.
        let row = |v: [f32; 4]| vec![v.to_vec(), vec![0.0; 4], vec![0.0; 4], vec![0.0; 4]];
        a.add(&[row([1.0, 0.5, 0.3, 0.0])], &[row([1.0, 1.0, 0.0, 0.0])]);
        assert!((a.cosine() - 0.948_68).abs() < 1e-5);
        assert!((a.relative_error() - 0.353_55).abs() < 1e-5);
        assert!((a.cross_ratio() - 0.212_13).abs() < 1e-5);
    }
}
