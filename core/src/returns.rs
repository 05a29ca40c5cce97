//! n-step returns inside a rollout (GAE with λ = 1), per component:
//! R_n = bootstrap, R_t = r_t + γ·(1 − done_t)·R_{t+1}, or, where the episode ended at
//! t by its step limit and the run bootstraps there, R_t = r_t + γ·V(o_final).

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

#[cfg(test)]
mod tests {
    use super::*;

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
