#!/usr/bin/env python3
"""Where a goal-reaching policy spends its return (issue 31): 50 deterministic episodes
(seeds 0-49, as bench/custom_env_results.py evaluates) of each policy, a SAVER/A2C/PPO
policy.safetensors or an SB3 model (.zip, bench/sb3_custom.py --save). The area under
the L1 distance curve sum_t sum_j |p_j - g_j| (the point mass's return, negated) split
by window of steps, and times the approach (first step within 3 radii
in every coordinate) apart from the settling (from there to success). Also the mean
|a| of the first 3 steps (how hard it opens) and the median speed on entering the box.
With --rest-curve, the mean action along one coordinate k at rest, x away from the goal
on k alone (100 goals in [-0.3, 0.3]^n, averaged over k; "at rest" is every observation
entry but p and g at 0, as the point masses have it): how hard the policy pushes at each
distance, and its gain near the goal.

    python3 bench/approach_profile.py --factory saver_actor.examples:pointmass3 \\
        RUN/policy.safetensors sb3-ppo-seed0.zip [...] [--max-steps 200] [--rest-curve]
"""
import argparse

import numpy as np
from saver_actor import factory_function

ap = argparse.ArgumentParser()
ap.add_argument("policies", nargs="+")
ap.add_argument("--factory", required=True)
ap.add_argument("--max-steps", type=int, default=200)
ap.add_argument("--episodes", type=int, default=50)
ap.add_argument("--rest-curve", action="store_true")
opts = ap.parse_args()
make_env, decl = factory_function(opts.factory)()
OFFSETS = np.array([-0.6, -0.4, -0.2, -0.1, -0.05, -0.02, 0.0, 0.02, 0.05, 0.1, 0.2, 0.4, 0.6])
WINDOWS = [(0, 5), (5, 10), (10, 20), (20, 40), (40, opts.max_steps)]


def load(path):
    """A predict(obs) -> action in [-1, 1] (the env's Box scaled by decl.env_actions), for one
    observation or a batch."""
    if path.endswith(".zip"):
        from stable_baselines3 import PPO

        model = PPO.load(path, device="cpu")
        return lambda o: np.clip(model.predict(o, deterministic=True)[0], -1.0, 1.0)
    from saver_actor.policy import Policy

    policy = Policy.load(path)
    return lambda o: policy.predict(o, deterministic=True)[0]


def profile(predict):
    env = make_env()
    radius = decl.success_radius
    area = np.zeros(len(WINDOWS))
    opening, approach, settle, entry_speed, steps, success = [], [], [], [], [], 0
    for ep in range(opts.episodes):
        o, _ = env.reset(seed=ep)
        near = None
        for t in range(opts.max_steps):
            a = predict(np.asarray(o, dtype=np.float32))
            if t < 3:
                opening.append(float(np.mean(np.abs(a))))
            prev = np.asarray(o)
            o, r, term, trunc, _ = env.step(decl.env_actions(np.asarray(a)[None], env.action_space)[0])
            dist = np.abs(np.asarray(o)[decl.aligned] - np.asarray(o)[decl.goal])
            area[[lo <= t < hi for lo, hi in WINDOWS]] += dist.sum()
            if near is None and np.max(dist) < 3 * radius:
                near = t + 1
            if term:
                success += 1
                settle.append(t + 1 - near)
                entry_speed.append(float(np.abs(np.asarray(o)[decl.aligned] - prev[decl.aligned]).max()))
            if term or trunc:
                break
        steps.append(t + 1)
        approach.append(near if near is not None else np.nan)
    n = opts.episodes

    def stat(xs, f):
        return f(xs) if xs else float("nan")

    cells = " ".join(f"[{lo},{hi}) {a / n:6.2f}" for (lo, hi), a in zip(WINDOWS, area))
    return (f"distance area {area.sum() / n:6.2f} = {cells} | success {success / n:.2f}, steps median "
            f"{np.median(steps):.0f}, approach {np.nanmedian(approach):.0f}, settle median "
            f"{stat(settle, np.median):.0f} (90th {stat(settle, lambda s: np.percentile(s, 90)):.0f}), "
            f"opening |a| {np.mean(opening):.2f}, entry step |dp| median {stat(entry_speed, np.median):.3f}")


def rest_curve(predict):
    """The mean action on coordinate k at rest, x = OFFSETS from the goal, over k."""
    p_at = np.arange(len(decl.obs_low))[decl.aligned]
    g_at = np.arange(len(decl.obs_low))[decl.goal]
    goals = np.random.default_rng(0).uniform(-0.3, 0.3, (100, len(p_at)))
    curve = []
    for x in OFFSETS:
        pushes = []
        for k in range(len(p_at)):
            s = np.zeros((len(goals), len(decl.obs_low)), dtype=np.float32)
            s[:, p_at], s[:, g_at] = goals, goals
            s[:, p_at[k]] += x
            pushes.append(np.mean(predict(s)[:, k]))
        curve.append(np.mean(pushes))
    return " ".join(f"{x:+.2f}:{a:+.2f}" for x, a in zip(OFFSETS, curve))


for path in opts.policies:
    predict = load(path)
    print(f"{path}: {profile(predict)}", flush=True)
    if opts.rest_curve:
        print(f"  at rest, offset:action {rest_curve(predict)}", flush=True)
