#!/usr/bin/env python3
"""Where a Reacher-v5 policy's return goes (results/README.md, issue 31): runs it
deterministically from reset seeds 0..E-1, each episode until the fingertip is within
the success radius in both coordinates (as the evaluation of bench/custom_env_results.py
counts it) or 50 steps, and splits the mean return into the env's control cost
(-sum a^2) and distance cost (-|fingertip - target|), for the successful and the failed
episodes; then, over all 50 steps of every episode, the mean sum a^2, L-inf distance
and joint speed every 5 steps (how hard the policy pushes, and when).

    python3 bench/reacher_return.py RUN/policy.safetensors [--episodes 50] [--radius 0.02]
"""
import argparse

import numpy as np
from saver_actor.examples import reacher
from saver_actor.policy import Policy

ap = argparse.ArgumentParser()
ap.add_argument("policy")
ap.add_argument("--episodes", type=int, default=50)
ap.add_argument("--radius", type=float, default=0.02)
opts = ap.parse_args()
net = Policy.load(opts.policy).net
make_env, _ = reacher(success_radius=opts.radius)
env = make_env()
rows, prof = [], np.zeros((50, 3))
for ep in range(opts.episodes):
    o, _ = env.reset(seed=ep)
    ctrl = dist = 0.0
    reached = None
    for t in range(50):
        a = np.clip(net.deterministic(np.asarray(o, np.float32)[None])[0], -1.0, 1.0)
        o, _, _, _, info = env.step(a)
        if reached is None:
            ctrl -= float(info["reward_ctrl"])
            dist -= float(info["reward_dist"])
        d = float(np.abs(o[8:10]).max())
        prof[t] += [np.square(a).sum(), d, np.abs(o[6:8]).sum()]
        if reached is None and d < opts.radius:
            reached = t + 1
    rows.append((reached or 50, ctrl, dist, reached is not None))
r = np.array(rows, dtype=float)
ok = r[:, 3] > 0


def part(m):
    return f"control {-r[m, 1].mean():.2f}, distance {-r[m, 2].mean():.2f}" if m.any() else "none"


print(f"success {ok.mean():.2f}, steps to success (median) {np.median(r[ok, 0]) if ok.any() else float('nan'):.0f}, "
      f"return {-(r[:, 1] + r[:, 2]).mean():.2f} = control {-r[:, 1].mean():.2f} + distance {-r[:, 2].mean():.2f}")
print(f"  successful episodes: {part(ok)}; failed ({(~ok).sum()}): {part(~ok)}")
p = prof / opts.episodes
print("  step          " + " ".join(f"{t:5d}" for t in range(0, 50, 5)))
print("  sum a^2       " + " ".join(f"{p[t, 0]:5.2f}" for t in range(0, 50, 5)))
print("  max |p - g|   " + " ".join(f"{p[t, 1]:5.3f}" for t in range(0, 50, 5)))
print("  |joint speed| " + " ".join(f"{p[t, 2]:5.2f}" for t in range(0, 50, 5)))
