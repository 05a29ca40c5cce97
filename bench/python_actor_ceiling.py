#!/usr/bin/env python3
"""How close one Python actor process can come to the bare env's step rate: the
actor's work added one layer at a time, in one run, with no learner and no gRPC.

    python3 bench/python_actor_ceiling.py [--envs 16] [--steps 100000]

1. bare: E Reacher-v5 envs stepped in a loop (reacher_learner.bare_rate, as
   bench/python_actor_speed.py measures it);
2. + env set: the same through the actor's LocalEnvs (actions mapped to the env's,
   outcomes written into arrays);
3. + policy.act: and the policy's forward pass and draw for every step (the default 256-128-64
   Gaussian, random weights, one BLAS thread as the actor runs it);
4. the actor's whole step loop (Actor._collect: sampling, outcome, vector rewards,
   bookkeeping, checks, the rollout message), 8 steps a rollout as the learner asks.

Each row is against the bare rate. What the actor does beyond (weights, gRPC, the
sync round) is bench/python_actor_speed.py's gap between its own time and row 4.
"""
import argparse
import time
from types import SimpleNamespace

import numpy as np
import reacher_learner  # bench/, beside this script
from saver_actor import Actor, Connection
from saver_actor.envset import LocalEnvs
from saver_actor.examples import reacher
from saver_actor.policy import policy_for
from threadpoolctl import threadpool_limits

ap = argparse.ArgumentParser()
ap.add_argument("--envs", type=int, default=16)
ap.add_argument("--steps", type=int, default=100_000)
args = ap.parse_args()
make_env, decl = reacher()
E = args.envs
rounds = args.steps // (8 * E)
rng = np.random.default_rng(0)


def random_policy():
    widths = [decl.obs_dim, 256, 128, 64]
    t = {}
    for i in range(3):
        t[f"agent.l{i}.w"] = (rng.standard_normal((widths[i], widths[i + 1])) * 0.05).astype(np.float32)
        t[f"agent.l{i}.b"] = np.zeros(widths[i + 1], np.float32)
    t["agent.mu.w"] = (rng.standard_normal((64, decl.continuous)) * 0.05).astype(np.float32)
    t["agent.mu.b"] = np.zeros(decl.continuous, np.float32)
    t["agent.log_std"] = np.zeros(decl.continuous, np.float32)
    layout = SimpleNamespace(obs_dim=decl.obs_dim, continuous=decl.continuous, choices=0)
    return policy_for("gaussian-mlp", t, layout, {"mu_bound": 1.0})


def env_set(policy):
    envs = LocalEnvs(make_env, E, decl.obs_dim, decl.continuous, decl.action_dim)
    obs = np.stack(envs.reset(range(E), list(range(E))))
    t0 = time.perf_counter()
    for _ in range(8 * rounds):
        if policy is None:
            acts = reacher_learner.policy_actions(rng, (E, 2)).astype(np.float32)
        else:
            acts, _ = policy.act(obs, rng)
        o, _, term, trunc, _ = envs.step(acts)
        obs[:] = o
        done = np.flatnonzero(term | trunc)
        if len(done):
            obs[done] = envs.reset(done, [None] * len(done))
    rate = 8 * rounds * E / (time.perf_counter() - t0)
    envs.close()
    return rate


def collect(policy):
    actor = Actor(make_env, decl, Connection(), n_envs=E)
    obs = np.stack(actor._reset(range(E), 0, 0))
    running, returns = np.zeros(E, np.int64), np.zeros(E, np.float32)
    t0 = time.perf_counter()
    for _ in range(rounds):
        msg, obs = actor._collect(policy, rng, obs, running, returns, 8, 50, False)
        msg.SerializeToString()
    wall = time.perf_counter() - t0
    actor.close()
    return 8 * rounds * E / wall, actor.summary.env_seconds, wall


with threadpool_limits(limits=1, user_api="blas"):
    policy = random_policy()
    # The bare rate first and last (the mean is the reference): the first loop of a
    # process runs a few % slower than the later ones, and the host drifts.
    b0 = reacher_learner.bare_rate(make_env, E, 8 * rounds * E, reacher_learner.policy_actions)
    rows = [("+ env set", env_set(None)), ("+ policy.act (forward, draw)", env_set(policy))]
    c, env_s, wall = collect(policy)
    b1 = reacher_learner.bare_rate(make_env, E, 8 * rounds * E, reacher_learner.policy_actions)
b = (b0 + b1) / 2
print(f"Reacher-v5, {E} envs, {8 * rounds * E} steps, one process, no learner")
print(f"  bare env                       {b:8.0f} steps/s (first {b0:.0f}, last {b1:.0f})")
for name, r in rows:
    print(f"  {name:30s} {r:8.0f} steps/s ({r / b:.0%} of bare)")
print(f"  the actor's step loop          {c:8.0f} steps/s ({c / b:.0%} of bare; "
      f"env.step {env_s:.1f} s of {wall:.1f} s)")
