#!/usr/bin/env python3
"""How fast a Python actor steps its envs, against the bare env, in one run.

    python3 bench/python_actor_speed.py target/release/saver [--envs 8] [--steps 100000]

1. bare: the actor's E Reacher-v5 envs stepped with uniform random actions (reset at
   the end of each episode), nothing else;
2. actor: the same E envs in a saver_actor.Actor with the policy, the bookkeeping and
   the rollout stream, against a real `saver learner` (A2C, sync: while the learner
   updates, the actor waits and does not compete for the cores). Reported per second
   of the actor's time not spent waiting for weights (its own cost), and per wall
   second.
"""
import argparse
import os
import socket
import subprocess
import tempfile
import time

import numpy as np

from saver_actor import Actor, Connection
from saver_actor.examples import reacher

ap = argparse.ArgumentParser()
ap.add_argument("saver", nargs="?", default="target/release/saver")
ap.add_argument("--envs", type=int, default=8)
ap.add_argument("--steps", type=int, default=100_000)
args = ap.parse_args()
make_env, decl = reacher()

envs = [make_env() for _ in range(args.envs)]
for i, e in enumerate(envs):
    e.reset(seed=i)
rng = np.random.default_rng(0)
n = args.steps // args.envs
t = time.perf_counter()
for _ in range(n):
    acts = rng.uniform(-1, 1, (args.envs, 2)).astype(np.float32)
    for e, a in zip(envs, acts):
        _, _, term, trunc, _ = e.step(a)
        if term or trunc:
            e.reset()
bare = n * args.envs / (time.perf_counter() - t)

tmp = tempfile.mkdtemp(prefix="saver-speed-")
cfg = os.path.join(tmp, "reacher.toml")
open(cfg, "w").write("max_episode_steps = 50\n" + decl.toml())
with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
learner = subprocess.Popen([args.saver, "learner", "--config", cfg, "--actors", "1",
                            "--steps", str(args.steps), "--out", os.path.join(tmp, "run"), "--exit-when-done",
                            "--listen", f"127.0.0.1:{port}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
try:
    actor = Actor(make_env, decl, Connection(f"http://127.0.0.1:{port}"), n_envs=args.envs, give_up=30,
                  log=lambda m: None)
    s = actor.run()
finally:
    learner.wait(60)
active = s.steps / (s.seconds - s.wait_seconds)
wall = s.steps / s.seconds
print(f"Reacher-v5, {args.envs} envs, {s.steps} steps")
print(f"  bare env:   {bare:8.0f} steps/s")
print(f"  actor:      {active:8.0f} steps/s of its own time ({active / bare:.0%} of bare); "
      f"{wall:.0f} per wall second ({wall / bare:.0%}; {s.wait_seconds:.1f} s of {s.seconds:.1f} waiting for weights)")
print(f"  inside env.step: {s.env_seconds:.1f} s of the actor's {s.seconds - s.wait_seconds:.1f} s")
