//! What SAVER's actor signal is made of (docs/ALGORITHM.md §7.1), and the target that
//! keeps it when one step's position change is mostly velocity.
//!
//! SAVER's loss ρ_τ(y − Q_j(x, τ))·Â_j moves μ through ∂Q/∂μ weighted by
//! `1{y < Q_j(x, τ)} − τ`: what matters is where the target y falls among the PCPN's
//! quantiles for the policy's (μ, σ), its rank u. With an exact PCPN and y the observed
//! Δp, u is the rank of the action noise ε = (a − μ)/σ along the action's effect, and
//! the update is a score-function step routed by the PCPN's slopes. When the PCPN is
//! off by more than the action moves p (an inertial env: Δp is mostly velocity), u is
//! the PCPN's error instead, and the update is noise.
//!
//! The predicted target (`saver.target = "predicted"`) replaces the observed Δp by the
//! PCPN's own prediction for the action taken: the median `Q_j([o, clip(a, −1, 1),
//! log σ], ½)` at the policy's own σ. Whatever error the PCPN makes about the state's
//! own drift (or about how its median moves with σ) appears in the target and in the
//! quantiles alike, so u is again the rank of the action's effect. It does not see
//! what the PCPN does not know (a wall that stops the motion): measured, it is an
//! option, not a default.
//!
//! Per coordinate j, on [`SIGNAL_ROWS`] rows of every [`SIGNAL_EVERY`]-th batch
//! (per_dim.csv):
//!
//! ```text
//! rank_corr_j = corr_b(u(Δp_bj), u(Δp̃_bj))      u(y) = mean_m 1{y < Q_j(x_b, τ_m)}, τ_m = (m + ½)/M
//! act_share_j = var_b(Δp̃_bj − Δp⁰_bj) / var_b(Δp_bj)          Δp̃ = Q_j([o, clip(a), log σ], ½)
//! err_ratio_j = mean_b (Δp_bj − Δp̃_bj)² / mean_b (Δp̃_bj − Δp⁰_bj)²   Δp⁰ = Q_j([o, μ, log σ], ½)
//! ```
//!
//! (act_share: the share of the batch's spread of Δp that the action noise causes, per
//! the PCPN; err_ratio: the PCPN's error on the step taken against the action's effect
//! on it, above 1 when the error swamps the signal), and per continuous action entry i
//! over the whole batch, the signal-to-noise ratio |mean_b g_bi| / (std_b g_bi / √B) of
//! SAVER's gradient on μ_i (`snr_saver_i`) and of A2C's score-function gradient
//! −(ε_bi/σ_i)·Σ_j Â_bj on the same batch (`snr_a2c_i`). Nothing here changes training.

use crate::algo::tau_tensors;
use crate::env::EnvLayout;
use crate::nets::Pcpn;
use crate::Result;
use candle_core::{DType, Device, Tensor};

/// Rows of a batch the rank statistics are computed on (evenly spaced).
pub const SIGNAL_ROWS: usize = 64;
/// Updates between two computations of the rank statistics (SAVER repeats the last
/// ones in between: a per_dim.csv row, the mean over 10 updates, holds one).
pub const SIGNAL_EVERY: u64 = 10;
/// Quantile levels of the rank u.
pub const SIGNAL_TAUS: usize = 8;

/// The PCPN's quantiles Q_j(x_b, τ) for every row of `x` [B, I] at each of `taus`,
/// on the host as [B, d, M].
pub fn pcpn_quantiles(pcpn: &Pcpn, x: &Tensor, taus: &[f32]) -> Result<Vec<f32>> {
    let (b, d, m) = (x.dim(0)?, pcpn.dim(), taus.len());
    let all: Vec<f32> = (0..d * b).flat_map(|_| taus.iter().copied()).collect();
    let (_, cos) = tau_tensors(&all, d, b, m, x.device())?;
    let q = pcpn.forward(&x.to_dtype(pcpn.dtype())?, &cos.to_dtype(pcpn.dtype())?)?; // [d, B, M]
    let q = q.permute((1, 0, 2))?.contiguous()?;
    Ok(q.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?)
}

/// The predicted target Δp̃ [B, d]: the PCPN's median change for each row's action.
pub fn predicted_delta(
    pcpn: &Pcpn,
    layout: &EnvLayout,
    s: &SignalBatch,
    dev: &Device,
) -> Result<Vec<f32>> {
    let rows: Vec<usize> = (0..s.rows(layout)).collect();
    pcpn_quantiles(pcpn, &s.inputs(layout, &rows, true, dev)?, &[0.5])
}

/// The noise-rank target [B, d] (`saver.target = "noise"`): `Q_j(x_b, τ*_bj)`, the
/// PCPN's quantile at the rank the step's own action noise takes along coordinate j,
/// `τ*_bj = Φ(z_bj)` with `z_bj = Σ_i s_bji σ_i ε_bi / √(Σ_i s_bji² σ_i²)` ([`noise_ranks`]).
/// Under a PCPN whose quantiles rise with τ, the target's rank among them is τ*: the
/// rank of the noise, never the PCPN's error about the state's drift, and the update
/// is the score-function step the module docs describe, routed by the PCPN's slopes.
pub fn noise_rank_delta(
    pcpn: &Pcpn,
    layout: &EnvLayout,
    s: &SignalBatch,
    dev: &Device,
) -> Result<Vec<f32>> {
    let (b, d) = (s.rows(layout), layout.aligned_dim);
    let rows: Vec<usize> = (0..b).collect();
    let x = s.inputs(layout, &rows, false, dev)?;
    let ranks = noise_ranks(pcpn, layout, s, &x)?; // [B, d]
    let taus: Vec<f32> = (0..d * b).map(|i| ranks[(i % b) * d + i / b]).collect(); // [d, B]
    let (_, cos) = tau_tensors(&taus, d, b, 1, dev)?;
    let q = pcpn.forward(&x.to_dtype(pcpn.dtype())?, &cos.to_dtype(pcpn.dtype())?)?; // [d, B, 1]
    let q = q.squeeze(2)?.t()?.contiguous()?; // [B, d]
    Ok(q.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?)
}

/// Step of μ in the central differences of the PCPN's slope ∂Q_j/∂μ_i at τ = ½.
pub const SLOPE_STEP: f32 = 0.05;

/// τ*_bj [B, d] of [`noise_rank_delta`]: the action noise ε_bi = (a_bi − μ_bi)/σ_bi of
/// each continuous entry, projected on coordinate j's slopes s_bji = ∂Q_j(x_b, ½)/∂μ_i
/// (central differences of ±[`SLOPE_STEP`], 2·c forward passes at τ = ½) scaled by σ,
/// normalised to N(0, 1) and mapped through Φ, within [0.001, 0.999]. ½ where no entry
/// moves coordinate j. `x` holds the rows' PCPN inputs [o, μ, log σ].
pub fn noise_ranks(
    pcpn: &Pcpn,
    layout: &EnvLayout,
    s: &SignalBatch,
    x: &Tensor,
) -> Result<Vec<f32>> {
    let (b, d, c) = (s.rows(layout), layout.aligned_dim, layout.continuous);
    let (o, m, l) = (layout.obs_dim, layout.mu_dim(), layout.log_std_dim());
    let host: Vec<f32> = x.flatten_all()?.to_vec1()?;
    let width = o + m + l;
    let mut slope = vec![0.0f32; b * d * c]; // [B, d, c]
    for i in 0..c {
        let shifted = |by: f32| -> Result<Vec<f32>> {
            let mut v = host.clone();
            v.iter_mut()
                .skip(o + i)
                .step_by(width)
                .for_each(|mu| *mu += by);
            pcpn_quantiles(pcpn, &Tensor::from_vec(v, (b, width), x.device())?, &[0.5])
        };
        let (up, down) = (shifted(SLOPE_STEP)?, shifted(-SLOPE_STEP)?);
        for (k, (u, w)) in up.iter().zip(&down).enumerate() {
            slope[k * c + i] = (u - w) / (2.0 * SLOPE_STEP);
        }
    }
    let a = layout.action_dim();
    let mut ranks = vec![0.5f32; b * d];
    for r in 0..b {
        for j in 0..d {
            let (mut num, mut den) = (0.0f64, 0.0f64);
            for i in 0..c {
                let sigma = (s.log_std[r * l + i] as f64).exp();
                let eps = (s.actions[r * a + i] - s.mu[r * m + i]) as f64 / sigma;
                let w = slope[(r * d + j) * c + i] as f64 * sigma;
                num += w * eps;
                den += w * w;
            }
            if den > 0.0 {
                ranks[r * d + j] = normal_cdf(num / den.sqrt()).clamp(1e-3, 1.0 - 1e-3) as f32;
            }
        }
    }
    Ok(ranks)
}

/// Φ(z), the standard normal CDF, as ½·erfc(−z/√2) with Abramowitz & Stegun's 7.1.26
/// for erf (absolute error below 1.5e-7).
pub fn normal_cdf(z: f64) -> f64 {
    let x = z.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let erf = 1.0 - poly * (-x * x).exp();
    if z >= 0.0 {
        0.5 * (1.0 + erf)
    } else {
        0.5 * (1.0 - erf)
    }
}

/// Population mean and variance.
fn moments(v: &[f64]) -> (f64, f64) {
    let n = v.len().max(1) as f64;
    let mean = v.iter().sum::<f64>() / n;
    (mean, v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n)
}

/// Pearson correlation (0 where either side does not vary).
fn correlation(x: &[f64], y: &[f64]) -> f64 {
    let ((mx, vx), (my, vy)) = (moments(x), moments(y));
    let n = x.len().max(1) as f64;
    let cov = x
        .iter()
        .zip(y)
        .map(|(a, b)| (a - mx) * (b - my))
        .sum::<f64>()
        / n;
    if vx > 0.0 && vy > 0.0 {
        cov / (vx * vy).sqrt()
    } else {
        0.0
    }
}

/// |mean| / (std / √n) of `v` (0 where it does not vary).
fn snr(v: &[f64]) -> f64 {
    let (mean, var) = moments(v);
    if var > 0.0 {
        mean.abs() / (var / v.len() as f64).sqrt()
    } else {
        0.0
    }
}

/// One batch on the host, row-major: the policy's inputs and what happened.
pub struct SignalBatch<'a> {
    /// Observations [B, O], policy means [B, M] and log σ [B, L] (the actions' policy).
    pub obs: &'a [f32],
    pub mu: &'a [f32],
    pub log_std: &'a [f32],
    /// Actions taken [B, A], observed Δp [B, d], advantages as trained on [B, d].
    pub actions: &'a [f32],
    pub state_delta: &'a [f32],
    pub advantage: &'a [f32],
    /// SAVER's per-row gradient on μ [B, M], where the update computed it per row.
    pub dmu: Option<&'a [f32]>,
}

impl<'a> SignalBatch<'a> {
    /// A batch's rows with the policy's μ and log σ, the advantages as trained on and
    /// (where the update computed it) dL/dμ.
    pub fn of(
        batch: &'a crate::rollout::Batch,
        mu: &'a [f32],
        log_std: &'a [f32],
        advantage: &'a [f32],
        dmu: Option<&'a [f32]>,
    ) -> Self {
        Self {
            obs: &batch.obs,
            mu,
            log_std,
            actions: &batch.actions,
            state_delta: &batch.state_delta,
            advantage,
            dmu,
        }
    }

    /// Rows B.
    fn rows(&self, layout: &EnvLayout) -> usize {
        self.obs.len() / layout.obs_dim.max(1)
    }

    /// The PCPN inputs [o, mean, log σ] of `rows`, with the policy's mean or, with
    /// `taken`, the action taken clipped to [−1, 1] (as the envs clip it) in its place.
    pub(crate) fn inputs(
        &self,
        layout: &EnvLayout,
        rows: &[usize],
        taken: bool,
        dev: &Device,
    ) -> Result<Tensor> {
        let (o, m, l) = (layout.obs_dim, layout.mu_dim(), layout.log_std_dim());
        let mut x = Vec::with_capacity(rows.len() * (o + m + l));
        for &r in rows {
            x.extend_from_slice(&self.obs[r * o..(r + 1) * o]);
            if taken {
                x.extend(
                    self.actions[r * m..(r + 1) * m]
                        .iter()
                        .map(|v| v.clamp(-1.0, 1.0)),
                );
            } else {
                x.extend_from_slice(&self.mu[r * m..(r + 1) * m]);
            }
            x.extend_from_slice(&self.log_std[r * l..(r + 1) * l]);
        }
        Ok(Tensor::from_vec(x, (rows.len(), o + m + l), dev)?)
    }
}

/// rank_corr, act_share and err_ratio (module docs), on [`SIGNAL_ROWS`] rows; empty for
/// layouts with a choice. Two PCPN forward passes of a few rows.
pub fn rank_stats(
    pcpn: &Pcpn,
    layout: &EnvLayout,
    s: &SignalBatch,
    dev: &Device,
) -> Result<Vec<(&'static str, Vec<f32>)>> {
    if layout.choices > 0 {
        return Ok(Vec::new());
    }
    let (b, d) = (s.rows(layout), layout.aligned_dim);
    let rows: Vec<usize> = (0..b).step_by(b.div_ceil(SIGNAL_ROWS).max(1)).collect();
    // The M levels of the rank, then ½ for Δp⁰: [S, d, M + 1].
    let taus: Vec<f32> = (0..SIGNAL_TAUS)
        .map(|m| (m as f32 + 0.5) / SIGNAL_TAUS as f32)
        .chain([0.5])
        .collect();
    let q = pcpn_quantiles(pcpn, &s.inputs(layout, &rows, false, dev)?, &taus)?;
    let tilde = pcpn_quantiles(pcpn, &s.inputs(layout, &rows, true, dev)?, &[0.5])?; // Δp̃ [S, d]
    let per = SIGNAL_TAUS + 1;
    let rank = |row: usize, j: usize, y: f32| -> f64 {
        let qs = &q[(row * d + j) * per..(row * d + j) * per + SIGNAL_TAUS];
        qs.iter().filter(|&&qm| y < qm).count() as f64 / SIGNAL_TAUS as f64
    };
    let (mut rank_corr, mut act_share, mut err_ratio) = (vec![], vec![], vec![]);
    for j in 0..d {
        let (mut u_obs, mut u_pred, mut dp, mut act, mut err) =
            (vec![], vec![], vec![], vec![], vec![]);
        for (i, &r) in rows.iter().enumerate() {
            let (y, yt, y0) = (
                s.state_delta[r * d + j],
                tilde[i * d + j],
                q[(i * d + j) * per + SIGNAL_TAUS],
            );
            u_obs.push(rank(i, j, y));
            u_pred.push(rank(i, j, yt));
            dp.push(y as f64);
            act.push((yt - y0) as f64);
            err.push((y - yt) as f64);
        }
        let act_sq = act.iter().map(|v| v * v).sum::<f64>();
        rank_corr.push(correlation(&u_obs, &u_pred) as f32);
        let var_dp = moments(&dp).1;
        act_share.push(if var_dp > 0.0 {
            (moments(&act).1 / var_dp) as f32
        } else {
            0.0
        });
        let err_sq = err.iter().map(|v| v * v).sum::<f64>();
        err_ratio.push((err_sq / act_sq.max(1e-30)) as f32);
    }
    Ok(vec![
        ("rank_corr", rank_corr),
        ("act_share", act_share),
        ("err_ratio", err_ratio),
    ])
}

/// snr_saver and snr_a2c per continuous action entry (module docs), over the whole
/// batch, where the update gave its per-row gradient; host arithmetic only.
pub fn snr_stats(layout: &EnvLayout, s: &SignalBatch) -> Vec<(&'static str, Vec<f32>)> {
    let Some(dmu) = s.dmu else {
        return Vec::new();
    };
    let (b, d, c) = (s.rows(layout), layout.aligned_dim, layout.continuous);
    let (m, l) = (layout.mu_dim(), layout.log_std_dim());
    let (mut snr_saver, mut snr_a2c) = (vec![], vec![]);
    for i in 0..c {
        let g: Vec<f64> = (0..b).map(|r| dmu[r * m + i] as f64).collect();
        let a2c: Vec<f64> = (0..b)
            .map(|r| {
                let sigma = (s.log_std[r * l + i] as f64).exp();
                let eps = (s.actions[r * layout.action_dim() + i] - s.mu[r * m + i]) as f64 / sigma;
                let adv: f64 = s.advantage[r * d..(r + 1) * d]
                    .iter()
                    .map(|&v| v as f64)
                    .sum();
                -eps / sigma * adv
            })
            .collect();
        snr_saver.push(snr(&g) as f32);
        snr_a2c.push(snr(&a2c) as f32);
    }
    vec![("snr_saver", snr_saver), ("snr_a2c", snr_a2c)]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// By hand: x = (1, 2, 3), y = (2, 4, 7): means 2 and 13/3, cov = (−1·−7/3 + 0 +
    /// 1·8/3)/3 = 5/3, var x = 2/3, var y = (49/9 + 1/9 + 64/9)/3 = 38/9, so
    /// corr = (5/3)/√(2/3 · 38/9) = 0.99339927. snr(1, 2, 3) = 2/√((2/3)/3) = 4.2426407.
    #[test]
    fn correlation_and_snr_by_hand() {
        assert!((correlation(&[1.0, 2.0, 3.0], &[2.0, 4.0, 7.0]) - 0.993_399_27).abs() < 1e-7);
        assert_eq!(correlation(&[1.0, 1.0], &[2.0, 3.0]), 0.0);
        assert!((snr(&[1.0, 2.0, 3.0]) - 4.242_640_7).abs() < 1e-6);
        assert_eq!(snr(&[5.0, 5.0]), 0.0);
    }

    /// Three rows, one action entry, one coordinate: SAVER's per-row gradients 1, 2, 3
    /// give 4.2426 (above); A2C's −(ε/σ)·Â with μ = 0, σ = 1, a = (1, −2, 3), Â = (1,
    /// 1, −1) is (−1, 2, 3): mean 4/3, population variance (49 + 4 + 25)/27 = 78/27, so
    /// snr = (4/3)/√(78/81) = 1.3587324.
    #[test]
    fn snr_stats_by_hand() {
        let layout = EnvLayout {
            obs_dim: 1,
            continuous: 1,
            choices: 0,
            aligned_start: 0,
            aligned_dim: 1,
        };
        let zeros = [0.0f32; 3];
        let s = SignalBatch {
            obs: &zeros,
            mu: &zeros,
            log_std: &zeros,
            actions: &[1.0, -2.0, 3.0],
            state_delta: &[0.0; 3],
            advantage: &[1.0, 1.0, -1.0],
            dmu: Some(&[1.0, 2.0, 3.0]),
        };
        let out = snr_stats(&layout, &s);
        assert_eq!(out[0].0, "snr_saver");
        assert!((out[0].1[0] - 4.242_640_7).abs() < 1e-5, "{out:?}");
        assert_eq!(out[1].0, "snr_a2c");
        assert!((out[1].1[0] - 1.358_732_4).abs() < 1e-5, "{out:?}");
    }
}
