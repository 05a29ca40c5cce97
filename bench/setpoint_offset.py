#!/usr/bin/env python3
"""Where a trained point-mass policy's mean action would hold the mass at rest, against
the goal (docs/ALGORITHM.md §7.1, issue 31): for G goals g ~ U(-0.8, 0.8)^2 and each
coordinate k, the states at rest (v = 0) with p = g but for p_k = g_k + x, x in
[-0.3, 0.3]; the set point of coordinate k is the x nearest 0 where mu_k changes sign
(mu_k pushes towards +x below it, towards -x above it). A set point outside the success
box (|x| > radius) is where the deterministic policy can stop short of the goal: the
misses of issue 31. Prints, per policy: the median and 90th percentile of |x|, the share
of set points outside the box, and the median |mu_k| at the goal itself.

    python3 bench/setpoint_offset.py RUN/policy.safetensors [RUN2/policy.safetensors ...]
        [--goals 200] [--radius 0.05]
"""
import argparse

import numpy as np
from saver_actor.policy import Policy

ap = argparse.ArgumentParser()
ap.add_argument("policies", nargs="+")
ap.add_argument("--goals", type=int, default=200)
ap.add_argument("--radius", type=float, default=0.05)
opts = ap.parse_args()
xs = np.linspace(-0.3, 0.3, 241)
goals = np.random.default_rng(0).uniform(-0.8, 0.8, (opts.goals, 2))
for path in opts.policies:
    net = Policy.load(path).net
    offsets, at_goal = [], []
    for g in goals:
        for k in range(2):
            s = np.zeros((len(xs), 6), dtype=np.float32)
            s[:, 0:2] = g
            s[:, k] += xs
            s[:, 4:6] = g
            mu = net.mean(s)[:, k]
            at_goal.append(abs(mu[len(xs) // 2]))
            # Sign changes from + to - (a stable rest point); the one nearest x = 0.
            idx = np.nonzero((mu[:-1] > 0) & (mu[1:] <= 0))[0]
            if len(idx) == 0:
                offsets.append(np.inf)
                continue
            cross = xs[idx] + (xs[idx + 1] - xs[idx]) * mu[idx] / (mu[idx] - mu[idx + 1])
            offsets.append(cross[np.argmin(np.abs(cross))])
    o = np.abs(np.array(offsets))
    print(f"{path}: |set point - goal| median {np.median(o):.4f}, 90th percentile {np.percentile(o, 90):.4f}, "
          f"outside the box {np.mean(o > opts.radius):.3f}; |mu| at the goal median {np.median(at_goal):.3f}")
