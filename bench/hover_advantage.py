#!/usr/bin/env python3
"""Where a trained point-mass policy fails, and how visible the way out is to the
learner at each discount γ (docs/ALGORITHM.md §7.1, issue 31).

1. Runs the policy deterministically from reset seeds 0..E-1 and keeps the final state
   of every episode that did not reach the goal (a "hover" state: prints its distance
   to the goal, speed and |μ|, and μ along a line of states at rest through it: where
   it crosses zero is where the deterministic policy stops).
2. At each such state, starts M rollouts of the stochastic policy after a first action
   of μ + σ·u and M after μ − σ·u, u the sign of (g − p) per coordinate (towards the
   goal / away from it), and computes each rollout's discounted return of the vector
   reward the learner trains on (the sum over coordinates of |p − g| − |p' − g|,
   ending at success) for every γ given, and of the distance cost −|p' − g| that
   `--reward distance` trains on instead.
3. Prints, per γ, the median over the hover states of the one-rollout advantage SNR
   (mean R(towards) − mean R(away)) / std(R): how much a single row's advantage says
   about the right direction, against the noise in it.

    python3 bench/hover_advantage.py RUN/policy.safetensors [--episodes 50] [--rollouts 128]
        [--gammas 0.99 0.95 0.9] [--horizon 150]
"""
import argparse

import numpy as np
from saver_actor.examples import PointMass
from saver_actor.policy import Policy

ap = argparse.ArgumentParser()
ap.add_argument("policy")
ap.add_argument("--episodes", type=int, default=50)
ap.add_argument("--rollouts", type=int, default=128)
ap.add_argument("--gammas", type=float, nargs="+", default=[0.99, 0.95, 0.9])
ap.add_argument("--horizon", type=int, default=150)
ap.add_argument("--seed", type=int, default=0)
opts = ap.parse_args()
net = Policy.load(opts.policy).net
env = PointMass()


def step(s, a):
    """PointMass.step on rows [N, 6]: the next states, the vector reward [N, 2], success."""
    p, v, g = s[:, 0:2], s[:, 2:4], s[:, 4:6]
    v = (1.0 - env.drag) * v + env.accel * 0.1 * np.clip(a, -1.0, 1.0)
    q = p + 0.1 * v
    wall = np.abs(q) > 1.0
    q = np.clip(q, -1.0, 1.0)
    v = np.where(wall, 0.0, v)
    r = np.abs(p - g) - np.abs(q - g)
    cost = -np.abs(q - g)
    return np.concatenate([q, v, g], axis=1), r, cost, np.max(np.abs(q - g), axis=1) < env.radius


hover = []
for ep in range(opts.episodes):
    o, _ = env.reset(seed=ep)
    for _ in range(env.max_steps):
        o, _, term, trunc, _ = env.step(net.deterministic(o[None].astype(np.float32))[0])
        if term or trunc:
            break
    if not term:
        mu = net.mean(o[None].astype(np.float32))[0]
        print(f"episode {ep}: ends {np.abs(o[0:2] - o[4:6]).round(3)} from the goal, speed "
              f"{np.abs(o[2:4]).max():.3f}, |mu| {np.abs(mu).max():.3f}")
        # The mean along the farther coordinate k at rest, p_k - g_k from -0.15 to 0.15:
        # where it crosses zero is where the deterministic policy stops.
        k = int(np.argmax(np.abs(o[0:2] - o[4:6])))
        line = np.repeat(o[None], 13, axis=0)
        line[:, 2:4] = 0.0
        line[:, k] = o[4 + k] + np.linspace(-0.15, 0.15, 13)
        print(f"  mu_{k} at rest, p_{k} - g_{k} = -0.15 .. 0.15: "
              + " ".join(f"{m:+.2f}" for m in net.mean(line.astype(np.float32))[:, k]))
        hover.append(o)
print(f"{len(hover)} of {opts.episodes} episodes end short of the goal; sigma = {net.sigma.round(3)}")
if not hover:
    raise SystemExit(0)

rng = np.random.default_rng(opts.seed)
m = opts.rollouts
forms = [(f, g) for f in ("progress", "distance") for g in opts.gammas]
snr = {k: [] for k in forms}
for s0 in hover:
    u = np.sign(s0[4:6] - s0[0:2])
    s = np.repeat(s0[None], 2 * m, axis=0)
    mu = net.mean(s0[None].astype(np.float32))[0]
    first = np.concatenate([np.repeat((mu + net.sigma * u)[None], m, 0), np.repeat((mu - net.sigma * u)[None], m, 0)])
    ret = {k: np.zeros(2 * m) for k in forms}
    alive = np.ones(2 * m, dtype=bool)
    for t in range(opts.horizon):
        a = first if t == 0 else net.mean(s.astype(np.float32)) + net.sigma * rng.standard_normal((2 * m, 2))
        s, r, cost, done = step(s, a)
        for f, g in forms:
            ret[f, g] += np.where(alive, g ** t * (r if f == "progress" else cost).sum(axis=1), 0.0)
        alive &= ~done
    for k in forms:
        towards, away = ret[k][:m], ret[k][m:]
        snr[k].append((towards.mean() - away.mean()) / max(ret[k].std(), 1e-12))
for f, g in forms:
    v = snr[f, g]
    print(f"{f} reward, gamma {g}: one-rollout advantage SNR of pushing towards the goal, median over "
          f"{len(hover)} hover states: {np.median(v):.3f} (quartiles {np.percentile(v, 25):.3f} / "
          f"{np.percentile(v, 75):.3f})")
