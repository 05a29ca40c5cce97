#!/usr/bin/env python3
"""Where a Reacher-v5 policy's return goes (issue 55): over the 50 deterministic
evaluation episodes (env seeds 0-49, 50 steps, never ended at success), the mean
distance cost Σ|fingertip − target| and control cost Σa² per episode (Reacher-v5's
reward is minus their sum), the first step at which the fingertip is inside the 0.02
box, and both costs after that step.

    python3 bench/reacher_cost_split.py RUN/policy.safetensors [...]
"""
import os
import sys

import numpy as np
from saver_actor import Policy
from saver_actor.examples import reacher

make_env, decl = reacher()
for path in sys.argv[1:]:
    policy = Policy.load(path)
    env = make_env()
    rows = []
    for seed in range(50):
        o, _ = env.reset(seed=seed)
        dist = ctrl = late_dist = late_ctrl = 0.0
        entered = None
        for t in range(50):
            a, _ = policy.predict(o)
            o, _, term, trunc, info = env.step(policy.env_action(a, env.action_space))
            d, c = -info["reward_dist"], -info["reward_ctrl"]
            dist, ctrl = dist + d, ctrl + c
            tip = env.unwrapped.get_body_com("fingertip")[:2] - env.unwrapped.get_body_com("target")[:2]
            if entered is None and np.all(np.abs(tip) < 0.02):
                entered = t
            if entered is not None:
                late_dist, late_ctrl = late_dist + d, late_ctrl + c
            if term or trunc:
                break
        rows.append((dist, ctrl, 50 if entered is None else entered, late_dist, late_ctrl))
    m = np.mean(rows, axis=0)
    run = os.path.basename(os.path.dirname(os.path.abspath(path)))
    print(f"{run}: distance {m[0]:.2f}, control {m[1]:.2f}, return {-(m[0] + m[1]):.2f}; first step in the box "
          f"{m[2]:.1f}; after it distance {m[3]:.2f}, control {m[4]:.2f}")
    env.close()
