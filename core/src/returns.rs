//! n-step returns inside a rollout (GAE with λ = 1; docs/ALGORITHM.md §6), per component:
//! R_n = bootstrap, R_t = r_t + γ·(1 − done_t)·R_{t+1}, or, where the episode ended at
//! t by its step limit and the run bootstraps there, R_t = r_t + γ·V(o_final); and
//! GAE(λ) advantages for PPO, and V-trace targets for async off-policy correction.

/// Returns of `n_traj` trajectories of `n_steps` steps with `c` reward components.
///
/// Layouts, row-major: `rewards` [n_traj, n_steps, c], `dones` [n_traj, n_steps],
/// `bootstrap` [n_traj, c] (the value of the observation after the last step);
/// `ends` (if any) [n_traj, n_steps, c] holds the value after each step that ended an
/// episode: V of the final observation at a timeout the run bootstraps, 0 elsewhere;
/// without it every end is terminal. The result has the layout of `rewards`.
pub fn n_step_returns(
    rewards: &[f32],
    dones: &[bool],
    bootstrap: &[f32],
    ends: Option<&[f32]>,
    n_steps: usize,
    c: usize,
    gamma: f32,
) -> Vec<f32> {
    let n_traj = dones.len() / n_steps;
    debug_assert_eq!(rewards.len(), n_traj * n_steps * c);
    debug_assert_eq!(bootstrap.len(), n_traj * c);
    debug_assert!(ends.is_none_or(|v| v.len() == rewards.len()));
    let mut out = vec![0.0f32; rewards.len()];
    for e in 0..n_traj {
        let mut acc = bootstrap[e * c..(e + 1) * c].to_vec();
        for t in (0..n_steps).rev() {
            let row = (e * n_steps + t) * c;
            let done = dones[e * n_steps + t];
            for j in 0..c {
                let next = match (done, ends) {
                    (false, _) => acc[j],
                    (true, Some(v)) => v[row + j],
                    (true, None) => 0.0,
                };
                acc[j] = rewards[row + j] + gamma * next;
                out[row + j] = acc[j];
            }
        }
    }
    out
}

/// Generalised advantage estimates (GAE(λ), Schulman et al. 2016; docs/ALGORITHM.md
/// §15) of `n_traj` trajectories of `n_steps` steps with `c` reward components, each
/// component on its own:
///   δ_t = r_t + γ·V_next − V(o_t),   A_t = δ_t + γλ·(1 − done_t)·A_{t+1},   A_n = 0,
/// where V_next is V(o_{t+1}) inside an episode, the trajectory's `bootstrap` after its
/// last step, and at a step that ended an episode the value in `ends` (V of the final
/// observation at a bootstrapped timeout, 0 elsewhere; all 0 without `ends`).
/// `values` is V(o_t) with the layout of `rewards`; the other layouts are
/// [`n_step_returns`]'. With λ = 1, A_t + V(o_t) is [`n_step_returns`]' R_t.
#[allow(clippy::too_many_arguments)]
pub fn gae(
    rewards: &[f32],
    values: &[f32],
    dones: &[bool],
    bootstrap: &[f32],
    ends: Option<&[f32]>,
    n_steps: usize,
    c: usize,
    gamma: f32,
    lambda: f32,
) -> Vec<f32> {
    let n_traj = dones.len() / n_steps;
    debug_assert_eq!(rewards.len(), n_traj * n_steps * c);
    debug_assert_eq!(values.len(), rewards.len());
    debug_assert_eq!(bootstrap.len(), n_traj * c);
    debug_assert!(ends.is_none_or(|v| v.len() == rewards.len()));
    let mut out = vec![0.0f32; rewards.len()];
    for e in 0..n_traj {
        let mut acc = vec![0.0f32; c];
        for t in (0..n_steps).rev() {
            let row = (e * n_steps + t) * c;
            let done = dones[e * n_steps + t];
            for j in 0..c {
                let next = match (done, ends) {
                    (false, _) if t + 1 == n_steps => bootstrap[e * c + j],
                    (false, _) => values[row + c + j],
                    (true, Some(v)) => v[row + j],
                    (true, None) => 0.0,
                };
                let delta = rewards[row + j] + gamma * next - values[row + j];
                let carry = if done { 0.0 } else { gamma * lambda * acc[j] };
                acc[j] = delta + carry;
                out[row + j] = acc[j];
            }
        }
    }
    out
}

/// V-trace (Espeholt et al. 2018, IMPALA; docs/ALGORITHM.md §16) of `n_traj` trajectories
/// acted by a behaviour policy μ, for a learner whose policy is π, each of the `c`
/// reward components on its own: `rho` and `cs` hold the clipped ratios
/// ρ_t = min(ρ̄, π/μ) and c_t = min(c̄, π/μ), one a step ([n_traj, n_steps]) or one a
/// step and component (the layout of `rewards`: per-coordinate V-trace). Returns the
/// critic targets v_t and the policy-gradient advantages ρ_t·(r_t + γ·v_next − V(o_t)),
/// each with the layout of `rewards`:
///   v_t − V(o_t) = ρ_t·δ_t + γ·c_t·(1 − done_t)·(v_(t+1) − V(o_(t+1))),
///   δ_t = r_t + γ·V_next − V(o_t),
/// where V_next and v_next are V(o_(t+1)) and v_(t+1) inside an episode, the trajectory's
/// `bootstrap` after its last step, and at a step that ended an episode the value in
/// `ends` (or 0), as in [`gae`]. With every ratio 1, v_t is [`n_step_returns`]' R_t and
/// the advantage R_t − V(o_t).
#[allow(clippy::too_many_arguments)]
pub fn vtrace(
    rewards: &[f32],
    values: &[f32],
    dones: &[bool],
    bootstrap: &[f32],
    ends: Option<&[f32]>,
    rho: &[f32],
    cs: &[f32],
    n_steps: usize,
    c: usize,
    gamma: f32,
) -> (Vec<f32>, Vec<f32>) {
    let n_traj = dones.len() / n_steps;
    debug_assert_eq!(rewards.len(), n_traj * n_steps * c);
    debug_assert_eq!(values.len(), rewards.len());
    // One ratio a step, or one a step and coordinate.
    let per_coordinate = rho.len() != dones.len();
    debug_assert!(rho.len() == dones.len() || rho.len() == rewards.len());
    debug_assert_eq!(cs.len(), rho.len());
    let mut targets = vec![0.0f32; rewards.len()];
    let mut advantages = vec![0.0f32; rewards.len()];
    for e in 0..n_traj {
        // v_(t+1) − V(o_(t+1)) of the step after the current one.
        let mut acc = vec![0.0f32; c];
        for t in (0..n_steps).rev() {
            let i = e * n_steps + t;
            let row = i * c;
            let done = dones[i];
            for j in 0..c {
                let (next_v, next_target) = match (done, ends) {
                    (false, _) if t + 1 == n_steps => (bootstrap[e * c + j], bootstrap[e * c + j]),
                    (false, _) => (values[row + c + j], targets[row + c + j]),
                    (true, Some(v)) => (v[row + j], v[row + j]),
                    (true, None) => (0.0, 0.0),
                };
                let r = if per_coordinate { row + j } else { i };
                let delta = rewards[row + j] + gamma * next_v - values[row + j];
                let carry = if done { 0.0 } else { gamma * cs[r] * acc[j] };
                acc[j] = rho[r] * delta + carry;
                targets[row + j] = values[row + j] + acc[j];
                advantages[row + j] =
                    rho[r] * (rewards[row + j] + gamma * next_target - values[row + j]);
            }
        }
    }
    (targets, advantages)
}

/// Normalises advantages over a batch (docs/ALGORITHM.md §6): `adv` is [B, d]
/// row-major; each dimension is centred on its batch mean and divided by
/// sqrt(var + 1e-8), with var the dimension's own batch variance or, with `joint`, the
/// mean of the d variances (one scale for every dimension, so a dimension whose
/// advantages are only noise stays small). Sums in f64.
pub fn normalize_advantages(adv: &mut [f32], d: usize, joint: bool) {
    let b = adv.len() / d.max(1);
    if b == 0 {
        return;
    }
    let mut mean = vec![0.0f64; d];
    for row in adv.chunks_exact(d) {
        for (m, &a) in mean.iter_mut().zip(row) {
            *m += a as f64;
        }
    }
    mean.iter_mut().for_each(|m| *m /= b as f64);
    let mut var = vec![0.0f64; d];
    for row in adv.chunks_exact(d) {
        for ((v, &a), m) in var.iter_mut().zip(row).zip(&mean) {
            *v += (a as f64 - m).powi(2);
        }
    }
    var.iter_mut().for_each(|v| *v /= b as f64);
    if joint {
        let all = var.iter().sum::<f64>() / d as f64;
        var.iter_mut().for_each(|v| *v = all);
    }
    for row in adv.chunks_exact_mut(d) {
        for j in 0..d {
            row[j] = ((row[j] as f64 - mean[j]) / (var[j] + 1e-8).sqrt()) as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn advantages_are_centred_and_scaled_per_dimension_or_jointly() {
        // B = 2, d = 2: rows (1, 10) and (3, 30). Means (2, 20); centred rows
        // (-1, -10), (1, 10); variances (1, 100).
        //   per dimension: (-1, -10)/(1, 10) = (-1, -1), and (1, 1);
        //   joint: var = (1 + 100)/2 = 50.5, sqrt = 7.106335 → (-0.140719, -1.407195).
        let mut a = [1.0f32, 10.0, 3.0, 30.0];
        normalize_advantages(&mut a, 2, false);
        let want = [-1.0f32, -1.0, 1.0, 1.0];
        assert!(
            a.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-6),
            "{a:?}"
        );
        let mut a = [1.0f32, 10.0, 3.0, 30.0];
        normalize_advantages(&mut a, 2, true);
        let want = [-0.140719f32, -1.407195, 0.140719, 1.407195];
        assert!(
            a.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-5),
            "{a:?}"
        );
        // A constant dimension becomes 0, not NaN (the 1e-8 under the root).
        let mut a = [5.0f32, 5.0, 5.0];
        normalize_advantages(&mut a, 1, false);
        assert_eq!(a, [0.0; 3]);
    }

    #[test]
    fn gae_by_hand_and_lambda_one_is_the_n_step_return() {
        // One trajectory, 3 steps, 2 components, γ = 0.5, λ = 0.5; the episode ends by
        // its step limit at step 1 (index 1) with the final observation valued (4, 8);
        // bootstrap (10, 20); V(o_t) = (1, 1), (2, 2), (3, 3); rewards as below.
        //   t = 2: δ = r2 + 0.5·bootstrap − V2 = (5 + 5 − 3, 6 + 10 − 3) = (7, 13); A2 = δ
        //   t = 1: done, next = V_final:  δ = (3 + 2 − 2, 4 + 4 − 2) = (3, 6); A1 = δ (no carry)
        //   t = 0: δ = r0 + 0.5·V1 − V0 = (1 + 1 − 1, 2 + 1 − 1) = (1, 2);
        //          A0 = δ + 0.25·A1 = (1.75, 3.5)
        let rewards = [1., 2., 3., 4., 5., 6.];
        let values = [1., 1., 2., 2., 3., 3.];
        let dones = [false, true, false];
        let ends = [0., 0., 4., 8., 0., 0.];
        let a = gae(
            &rewards,
            &values,
            &dones,
            &[10., 20.],
            Some(&ends),
            3,
            2,
            0.5,
            0.5,
        );
        assert_eq!(a, vec![1.75, 3.5, 3., 6., 7., 13.]);
        // λ = 1: A + V is the n-step return of the test below
        // (a_bootstrapped_timeout_adds_the_discounted_final_value): (3.5, 6), (5, 8), (10, 16).
        let a = gae(
            &rewards,
            &values,
            &dones,
            &[10., 20.],
            Some(&ends),
            3,
            2,
            0.5,
            1.0,
        );
        let r: Vec<f32> = a.iter().zip(values).map(|(a, v)| a + v).collect();
        let want = n_step_returns(&rewards, &dones, &[10., 20.], Some(&ends), 3, 2, 0.5);
        assert_eq!(r, want);
        assert_eq!(want, vec![3.5, 6., 5., 8., 10., 16.]);
        // Without ends every episode end is terminal: A1 = r1 − V1 = (1, 2).
        let a = gae(&rewards, &values, &dones, &[10., 20.], None, 3, 2, 0.5, 0.5);
        assert_eq!(&a[2..4], &[1., 2.]);
    }

    #[test]
    fn vtrace_by_hand_on_a_three_step_vector_rollout() {
        // One trajectory, 3 steps, 2 components, γ = 0.5, no episode end; bootstrap
        // (10, 20); V(o_t) = (1, 1), (2, 2), (3, 3); rewards (1, 2), (3, 4), (5, 6).
        // Ratios π/μ = 2, 0.5, 1.5 with ρ̄ = 1, c̄ = 1: ρ = c = (1, 0.5, 1).
        //   δ2 = r2 + 0.5·(10, 20) − 3 = (7, 13);          v2 − V2 = 1·δ2 = (7, 13)
        //   δ1 = r1 + 0.5·V2 − 2 = (2.5, 3.5);  v1 − V1 = 0.5·δ1 + 0.5·0.5·(7, 13)
        //                                            = (1.25 + 1.75, 1.75 + 3.25) = (3, 5)
        //   δ0 = r0 + 0.5·V1 − 1 = (1, 2);      v0 − V0 = 1·δ0 + 0.5·1·(3, 5) = (2.5, 4.5)
        //   v = (3.5, 5.5), (5, 7), (10, 16)
        //   advantages ρ_t·(r_t + γ·v_(t+1) − V_t):
        //     t = 0: 1·(1 + 2.5 − 1, 2 + 3.5 − 1) = (2.5, 4.5)
        //     t = 1: 0.5·(3 + 5 − 2, 4 + 8 − 2) = (3, 5)
        //     t = 2: 1·(5 + 5 − 3, 6 + 10 − 3) = (7, 13)
        let rewards = [1., 2., 3., 4., 5., 6.];
        let values = [1., 1., 2., 2., 3., 3.];
        let dones = [false; 3];
        // ρ̄ = c̄ = 1: the same clipped ratios for both.
        let clipped = |r: &[f32]| {
            vtrace(
                &rewards,
                &values,
                &dones,
                &[10., 20.],
                None,
                r,
                r,
                3,
                2,
                0.5,
            )
        };
        let (v, a) = clipped(&[1., 0.5, 1.]);
        assert_eq!(v, vec![3.5, 5.5, 5., 7., 10., 16.]);
        assert_eq!(a, vec![2.5, 4.5, 3., 5., 7., 13.]);
        // Per coordinate: component 0 keeps the ratios above, component 1 has π/μ = 1 at
        // every step, so it is the n-step return of component 1 alone:
        //   v2 − V2 = 13, v1 − V1 = 3.5 + 0.5·13 = 10, v0 − V0 = 2 + 0.5·10 = 7
        //   v = (·, 8), (·, 12), (·, 16); advantages r_t + γ·v_(t+1) − V_t = R_t − V_t:
        //   (7, 10, 13); component 0 as before.
        let (v, a) = clipped(&[1., 1., 0.5, 1., 1., 1.]);
        assert_eq!(v, vec![3.5, 8., 5., 12., 10., 16.]);
        assert_eq!(a, vec![2.5, 7., 3., 10., 7., 13.]);
        // Every ratio 1: the n-step returns and R − V, a timeout bootstrapped included.
        let ends = [0., 0., 4., 8., 0., 0.];
        let dones = [false, true, false];
        let ones = [1.0f32; 3];
        let (v, a) = vtrace(
            &rewards,
            &values,
            &dones,
            &[10., 20.],
            Some(&ends),
            &ones,
            &ones,
            3,
            2,
            0.5,
        );
        let r = n_step_returns(&rewards, &dones, &[10., 20.], Some(&ends), 3, 2, 0.5);
        assert_eq!(v, r);
        let adv: Vec<f32> = r.iter().zip(values).map(|(r, v)| r - v).collect();
        assert_eq!(a, adv);
    }

    #[test]
    fn vector_returns_with_done_and_bootstrap() {
        // One trajectory, 3 steps, 2 components, γ = 0.5, done after step 1 (index 0):
        //   rewards r0 = (1, 2), r1 = (3, 4), r2 = (5, 6); bootstrap V = (10, 20).
        //   R2 = r2 + 0.5·V       = (5 + 5, 6 + 10)          = (10, 16)
        //   R1 = r1 + 0.5·R2      = (3 + 5, 4 + 8)           = (8, 12)
        //   R0 = r0 + 0·R1 (done) = (1, 2)
        let r = n_step_returns(
            &[1., 2., 3., 4., 5., 6.],
            &[true, false, false],
            &[10., 20.],
            None,
            3,
            2,
            0.5,
        );
        assert_eq!(r, vec![1., 2., 8., 12., 10., 16.]);
    }

    #[test]
    fn done_on_last_step_ignores_bootstrap_and_trajectories_are_separate() {
        // Two trajectories of 2 steps, 1 component, γ = 0.99.
        //   traj 0: r = (1, 1), done at the end → R1 = 1, R0 = 1 + 0.99·1 = 1.99
        //   traj 1: r = (0, 2), bootstrap 3    → R1 = 2 + 0.99·3 = 4.97, R0 = 0.99·4.97 = 4.9203
        let r = n_step_returns(
            &[1., 1., 0., 2.],
            &[false, true, false, false],
            &[100., 3.],
            None,
            2,
            1,
            0.99,
        );
        let want = [1.99f32, 1.0, 4.9203, 4.97];
        for (g, w) in r.iter().zip(want) {
            assert!((g - w).abs() < 1e-5, "{r:?}");
        }
    }

    #[test]
    fn a_bootstrapped_timeout_adds_the_discounted_final_value() {
        // One trajectory, 3 steps, 2 components, γ = 0.5; the episode hits its step
        // limit at step 1 (index 1), final observation valued (4, 8); bootstrap (10, 20).
        //   R2 = r2 + 0.5·V        = (5 + 5, 6 + 10)     = (10, 16)
        //   R1 = r1 + 0.5·V_final  = (3 + 2, 4 + 4)      = (5, 8)    (not 0.5·R2)
        //   R0 = r0 + 0.5·R1       = (1 + 2.5, 2 + 4)    = (3.5, 6)
        // With every end terminal R1 = r1 = (3, 4) and R0 = (2.5, 4).
        let rewards = [1., 2., 3., 4., 5., 6.];
        let dones = [false, true, false];
        let ends = [0., 0., 4., 8., 0., 0.];
        let r = n_step_returns(&rewards, &dones, &[10., 20.], Some(&ends), 3, 2, 0.5);
        assert_eq!(r, vec![3.5, 6., 5., 8., 10., 16.]);
        let r = n_step_returns(&rewards, &dones, &[10., 20.], None, 3, 2, 0.5);
        assert_eq!(r, vec![2.5, 4., 3., 4., 10., 16.]);
    }
}
