//! Per-dimension diagnostics of a vector-reward update (docs/ALGORITHM.md §7): how well
//! the critic knows each coordinate's return, how large and how informative each
//! coordinate's advantage is, and where the policy sits per action entry. Written to
//! the run's per_dim.csv; nothing here changes training.
//!
//! For coordinate j over the batch (R the n-step return, V the critic, r the one-step
//! vector reward, Â = R − V before any normalisation):
//!
//! ```text
//! critic_mse_j       = mean (V_j − R_j)²
//! return_var_j       = var R_j                (explained variance: 1 − mse/var)
//! adv_std_j          = std Â_j
//! adv_reward_corr_j  = corr(Â_j, r_j)         (how much Â_j reflects what the step did)
//! ```
//!
//! and for action entry i: `mu_sat_i` = share of |μ_i| ≥ 0.98·bound (1 when unbounded),
//! `log_std_i` = mean log σ_i.

/// Row-major [rows, cols] columns' means and (population) variances.
fn column_moments(x: &[f32], cols: usize) -> (Vec<f64>, Vec<f64>) {
    let rows = (x.len() / cols.max(1)).max(1);
    let mut mean = vec![0.0f64; cols];
    for row in x.chunks_exact(cols) {
        for (m, &v) in mean.iter_mut().zip(row) {
            *m += v as f64 / rows as f64;
        }
    }
    let mut var = vec![0.0f64; cols];
    for row in x.chunks_exact(cols) {
        for ((s, &v), m) in var.iter_mut().zip(row).zip(&mean) {
            *s += (v as f64 - m).powi(2) / rows as f64;
        }
    }
    (mean, var)
}

/// The statistics of the module docs. `returns`, `value`, `reward`: [B, d]; `mu`:
/// [B, M]; `log_std`: [B, L]; `mu_bound`: the tanh bound of μ, if any.
pub fn per_dim_stats(
    returns: &[f32],
    value: &[f32],
    reward: &[f32],
    mu: &[f32],
    log_std: &[f32],
    d: usize,
    mu_bound: Option<f64>,
) -> Vec<(&'static str, Vec<f32>)> {
    let b = returns.len() / d.max(1);
    let adv: Vec<f32> = returns.iter().zip(value).map(|(r, v)| r - v).collect();
    let sq: Vec<f32> = adv.iter().map(|a| a * a).collect();
    let (mse, _) = column_moments(&sq, d);
    let (_, return_var) = column_moments(returns, d);
    let (adv_mean, adv_var) = column_moments(&adv, d);
    let (reward_mean, reward_var) = column_moments(reward, d);
    let mut cov = vec![0.0f64; d];
    for (ar, rr) in adv.chunks_exact(d).zip(reward.chunks_exact(d)) {
        for j in 0..d {
            cov[j] += (ar[j] as f64 - adv_mean[j]) * (rr[j] as f64 - reward_mean[j]) / b as f64;
        }
    }
    let corr: Vec<f32> = (0..d)
        .map(|j| {
            let den = (adv_var[j] * reward_var[j]).sqrt();
            if den > 0.0 {
                (cov[j] / den) as f32
            } else {
                0.0
            }
        })
        .collect();
    let m = mu.len() / b.max(1);
    let edge = 0.98 * mu_bound.unwrap_or(1.0) as f32;
    let sat: Vec<f32> = mu
        .iter()
        .map(|v| f32::from(u8::from(v.abs() >= edge)))
        .collect();
    let (mu_sat, _) = column_moments(&sat, m);
    let (ls_mean, _) = column_moments(log_std, log_std.len() / b.max(1));
    let f = |v: Vec<f64>| v.into_iter().map(|x| x as f32).collect::<Vec<_>>();
    vec![
        ("critic_mse", f(mse)),
        ("return_var", f(return_var)),
        ("adv_std", f(adv_var.into_iter().map(f64::sqrt).collect())),
        ("adv_reward_corr", corr),
        ("mu_sat", f(mu_sat)),
        ("log_std", f(ls_mean)),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// B = 2, d = 2, by hand. R = [[1, 0], [3, 0]], V = [[0, 0], [0, 1]]:
    /// Â = [[1, 0], [3, −1]]; mse = ((1 + 9)/2, (0 + 1)/2) = (5, 0.5);
    /// var R = (1, 0); std Â = (1, 0.5); r = [[0, 1], [1, 1]]: corr(Â_0, r_0) = 1,
    /// r_1 constant so corr 0. μ = [[0.99], [0.5]] with bound 1: sat 0.5; log σ (−1, −2): −1.5.
    #[test]
    fn per_dim_stats_by_hand() {
        let s = per_dim_stats(
            &[1.0, 0.0, 3.0, 0.0],
            &[0.0, 0.0, 0.0, 1.0],
            &[0.0, 1.0, 1.0, 1.0],
            &[0.99, 0.5],
            &[-1.0, -2.0],
            2,
            Some(1.0),
        );
        let get = |n: &str| s.iter().find(|(k, _)| *k == n).unwrap().1.clone();
        assert_eq!(get("critic_mse"), vec![5.0, 0.5]);
        assert_eq!(get("return_var"), vec![1.0, 0.0]);
        assert_eq!(get("adv_std"), vec![1.0, 0.5]);
        let c = get("adv_reward_corr");
        assert!((c[0] - 1.0).abs() < 1e-6 && c[1] == 0.0, "{c:?}");
        assert_eq!(get("mu_sat"), vec![0.5]);
        assert_eq!(get("log_std"), vec![-1.5]);
    }
}
