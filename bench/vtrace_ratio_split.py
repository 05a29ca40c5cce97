#!/usr/bin/env python3
"""Where V-trace's ratios come from on `select` (issue 32): the steps of an older
policy (the behaviour, `OLD`) judged by a newer one (`NEW`, e.g. 8 updates later, the
lag of the async grid), numpy only.

On select the action is a step a_0 ~ N(mu_0, sigma) and a choice k ~ softmax(logits);
the step moves coordinate k alone. The learner's ratio pi/mu multiplies both factors,
and every coordinate's V-trace uses it. This splits it:

- `step`: N(a_0; mu'_0, sigma') / N(a_0; mu_0, sigma), the Gaussian factor;
- `choice`: p'_k / p_k;
- `shared`: their product, what `--vtrace` uses for every coordinate today;
- `per-coordinate`: for coordinate j, the ratio of what coordinate j sees of the
  action, p'_j N'/(p_j N) where j was chosen and (1 - p'_j) / (1 - p_j) where not.

For each: the mean ratio, the share above rho_bar = 1, the mean of min(1, r) (the
scale V-trace gives the advantage) and the mean product of min(1, r) over 8
consecutive steps (what is left of a trace across an 8-step rollout, c_bar = 1).

    python bench/vtrace_ratio_split.py OLD.safetensors NEW.safetensors [--steps 4096] [--seed 0]
"""
import argparse
import math

import numpy as np
from saver_actor import Policy

ap = argparse.ArgumentParser()
ap.add_argument("old")
ap.add_argument("new")
ap.add_argument("--steps", type=int, default=4096)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--max-episode-steps", type=int, default=1000)
a = ap.parse_args()

old, new = Policy.load(a.old).net, Policy.load(a.new).net
if old.c != 1 or old.ch == 0:
    raise SystemExit("select's layout (one step and a choice) is what this splits")
d = old.ch
rng = np.random.default_rng(a.seed)


def parts(net, obs):
    mu = net.mean(obs)
    logits = mu[:, 1:].astype(np.float64)
    p = np.exp(logits - logits.max(axis=1, keepdims=True))
    return mu[:, 0].astype(np.float64), float(net.sigma[0]), p / p.sum(axis=1, keepdims=True)


# The behaviour's steps, one env at a time as the actor steps it (goal at the origin,
# the episode ends within 0.1 of it in every coordinate or at the step limit).
obs_rows, step_rows, pick_rows = [], [], []
pos, t = rng.uniform(-1, 1, d), 0
while len(obs_rows) < a.steps:
    action, _ = old.act(pos[None].astype(np.float32), rng)
    k = int(np.argmax(action[0, 1:]))
    obs_rows.append(pos.copy())
    step_rows.append(float(action[0, 0]))
    pick_rows.append(k)
    pos[k] = np.clip(pos[k] + 0.1 * np.clip(action[0, 0], -1, 1), -1, 1)
    t += 1
    if np.max(np.abs(pos)) < 0.1 or t >= a.max_episode_steps:
        pos, t = rng.uniform(-1, 1, d), 0
obs = np.array(obs_rows, dtype=np.float32)
step, pick = np.array(step_rows), np.array(pick_rows)
rows = np.arange(len(pick))
mu0, s0, p0 = parts(old, obs)
mu1, s1, p1 = parts(new, obs)


def log_normal(x, m, s):
    return -0.5 * ((x - m) / s) ** 2 - math.log(s)


log_step = log_normal(step, mu1, s1) - log_normal(step, mu0, s0)
log_choice = np.log(p1[rows, pick]) - np.log(p0[rows, pick])
chosen = pick[:, None] == np.arange(d)[None]
log_coord = np.where(chosen, (log_step + log_choice)[:, None], np.log1p(-p1) - np.log1p(-p0))


def summary(name, log_r):
    r = np.exp(log_r)
    clipped = np.minimum(r, 1.0)
    n8 = (len(r) // 8) * 8
    trace = np.prod(clipped[:n8].reshape(-1, 8, *r.shape[1:]), axis=1)
    print(f"| {name} | {r.mean():.3f} | {np.mean(r > 1.0001):.1%} | {clipped.mean():.3f} | {trace.mean():.3f} | "
          f"{np.std(log_r):.3f} |")


print(f"{len(pick)} steps of {a.old}, judged by {a.new}; sigma {s0:.3f} -> {s1:.3f}; "
      f"mean p(chosen) {p0[rows, pick].mean():.3f}")
print("| ratio | mean | above 1 | mean min(1, r) | 8-step trace | std log r |")
print("|---|---|---|---|---|---|")
summary("step (Gaussian)", log_step)
summary("choice", log_choice)
summary("shared (today)", log_step + log_choice)
summary("per-coordinate, chosen j", log_coord[chosen])
summary("per-coordinate, other j", log_coord[~chosen])
summary("per-coordinate, all", log_coord)
