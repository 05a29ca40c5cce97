//! Hand-computed transitions of each environment.

use super::*;
use crate::rng::rng_for;

fn close(a: &[f32], b: &[f32], tol: f32) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
}

#[test]
fn angle_pair_step_and_vector_reward() {
    // p = (0.5, −0.3); a = (0.5, 0): s = 0.05, φ = (0 + 1)·π/2 = π/2 →
    // Δ = (0.05·sin π/2, 0.05·cos π/2) = (0.05, ~2e-9); p' = (0.55, −0.3).
    // r = |p| − |p'| = (0.5 − 0.55, 0.3 − 0.3) = (−0.05, ~0).
    let mut env = Angle::new(2, 1000);
    env.set_position(&[0.5, -0.3]);
    let mut obs = [0.0; 2];
    let s = env.step(&[0.5, 0.0], &mut obs);
    assert!(close(&obs, &[0.55, -0.3], 1e-6), "{obs:?}");
    assert!(close(&s.state_delta, &[0.05, 0.0], 1e-6));
    assert!(close(&s.vector_reward, &[-0.05, 0.0], 1e-6));
    assert!(!s.done());
}

#[test]
fn angle_clips_actions_and_the_cube_boundary() {
    // a = (5, −3) acts as (1, −1): s = 0.1, φ = 0 → Δ = (0, 0.1).
    // From p = (0.2, 0.95): p' = (0.2, clip(1.05) = 1.0); Δp = (0, 0.05) after clipping;
    // r = (0, 0.95 − 1.0) = (0, −0.05).
    let mut env = Angle::new(2, 1000);
    env.set_position(&[0.2, 0.95]);
    let mut obs = [0.0; 2];
    let s = env.step(&[5.0, -3.0], &mut obs);
    assert!(close(&obs, &[0.2, 1.0], 1e-6), "{obs:?}");
    assert!(
        close(&s.state_delta, &[0.0, 0.05], 1e-6),
        "{:?}",
        s.state_delta
    );
    assert!(close(&s.vector_reward, &[0.0, -0.05], 1e-6));
    // Second pair of a d = 4 cube moves independently: a = (0, 0, −1, 1), φ = π:
    // Δ = (0, 0, −0.1·sin π, −0.1·cos π) = (0, 0, ~0, 0.1).
    let mut env = Angle::new(4, 1000);
    env.set_position(&[0.3, 0.3, 0.3, 0.3]);
    let mut obs = [0.0; 4];
    env.step(&[0.0, 0.0, -1.0, 1.0], &mut obs);
    assert!(close(&obs, &[0.3, 0.3, 0.3, 0.4], 1e-6), "{obs:?}");
}

#[test]
fn success_is_strict_linf_below_point_one() {
    // select, d = 2: p = (0.2, 0.05), step −1 on dim 0 → p' = (0.2 − 0.1, 0.05) and
    // 0.2f32 − 0.1f32 == 0.1f32 exactly, so max |p'| = 0.1 is NOT < 0.1: no success.
    let mut env = Select::new(2, 1000);
    env.set_position(&[0.2, 0.05]);
    let mut obs = [0.0; 2];
    let s = env.step(&[-1.0, 1.0, 0.0], &mut obs);
    assert_eq!(obs[0], 0.1);
    assert!(!s.success && !s.done());
    // One more small step (0.1·0.01 = 0.001) gets strictly inside: success, done.
    let s = env.step(&[-0.01, 1.0, 0.0], &mut obs);
    assert!(s.success && s.done() && !s.timeout);
}

#[test]
fn select_moves_only_the_chosen_dimension() {
    // d = 3, p = (0.5, −0.5, 0.2), step 0.5 → 0.05 on the argmax of the one-hot (dim 1):
    // p' = (0.5, −0.45, 0.2), r = (0, 0.5 − 0.45, 0) = (0, 0.05, 0).
    let mut env = Select::new(3, 1000);
    env.set_position(&[0.5, -0.5, 0.2]);
    let mut obs = [0.0; 3];
    let s = env.step(&[0.5, 0.0, 1.0, 0.0], &mut obs);
    assert!(close(&obs, &[0.5, -0.45, 0.2], 1e-6));
    assert!(close(&s.vector_reward, &[0.0, 0.05, 0.0], 1e-6));
    assert!(close(&s.state_delta, &[0.0, 0.05, 0.0], 1e-6));
}

#[test]
fn arm_kinematics_and_angle_wrap() {
    // θ = (0, 0): hand = (sin 0 + sin 0, cos 0 + cos 0) = (0, 2). a = (1, 0):
    // θ1 = 0.02π → hand = (2·sin 0.02π, 2·cos 0.02π) = (0.1255810, 1.9960535) (python math).
    let mut env = Arm::new(1000);
    env.set_state([0.0, 0.0], [0.0, 0.0]);
    let mut obs = [0.0; 6];
    let s = env.step(&[1.0, 0.0], &mut obs);
    assert!(
        close(&obs[4..], &[0.125_581_04, 1.996_053_5], 1e-5),
        "{obs:?}"
    );
    assert!(close(&obs[2..4], &[0.062_831_85, 0.0], 1e-6));
    // r = |h − g| − |h' − g| with g = 0: (0 − 0.1255810, 2 − 1.9960535).
    assert!(close(&s.vector_reward, &[-0.125_581_04, 0.003_946_5], 1e-5));
    // Wrap: θ1 = π − 0.01 + 0.02π = π + 0.0528319 → −π + 0.0528319 = −3.0887608.
    env.set_state([std::f32::consts::PI - 0.01, 0.0], [0.0, 0.0]);
    env.step(&[1.0, 0.0], &mut obs);
    assert!((obs[2] - -3.088_760_8).abs() < 1e-5, "{obs:?}");
    assert_eq!(wrap_angle(std::f32::consts::PI), -std::f32::consts::PI);
    // Success on the hand: θ = (π/2, −π/2) puts the hand at (1 + 0, 0 + 1) = (1, 1);
    // a zero action keeps it there, and a goal 0.05 away in each axis is reached.
    env.set_state(
        [std::f32::consts::FRAC_PI_2, -std::f32::consts::FRAC_PI_2],
        [0.95, 1.05],
    );
    let s = env.step(&[0.0, 0.0], &mut obs);
    assert!(s.success, "{obs:?}");
}

#[test]
fn timeout_at_the_step_limit_is_done() {
    // max_steps = 3, zero steps from a corner: steps 1 and 2 continue, step 3 times out.
    let mut env = Angle::new(2, 3);
    env.set_position(&[0.9, 0.9]);
    let mut obs = [0.0; 2];
    assert!(!env.step(&[0.0, 0.0], &mut obs).done());
    assert!(!env.step(&[0.0, 0.0], &mut obs).done());
    let s = env.step(&[0.0, 0.0], &mut obs);
    assert!(s.timeout && s.done() && !s.success);
}

#[test]
fn resets_draw_from_the_spec_ranges() {
    let mut rng = rng_for(7, 0);
    let mut env = EnvSpec::new(EnvKind::Arm, 2).unwrap().make(1000).unwrap();
    let mut obs = [0.0; 6];
    for _ in 0..200 {
        env.reset(&mut rng, &mut obs);
        assert!(obs[..2].iter().all(|g| (-1.0..1.0).contains(g)));
        assert!(obs[2..4]
            .iter()
            .all(|t| (-std::f32::consts::PI..std::f32::consts::PI).contains(t)));
        let h = hand([obs[2], obs[3]]);
        assert!(close(&obs[4..], &h, 1e-6));
    }
    assert!(EnvSpec::new(EnvKind::Angle, 3).is_err());
    assert!(EnvSpec::new(EnvKind::Arm, 4).is_err());
    assert_eq!(
        EnvSpec::new(EnvKind::Select, 5)
            .unwrap()
            .layout()
            .action_dim(),
        6
    );
}
