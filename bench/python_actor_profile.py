#!/usr/bin/env python3
"""Where a Python actor's time goes: one saver_actor.Actor of E Reacher-v5 envs against
a real `saver learner` (A2C, sync), its stepping thread under cProfile, and the
process's CPU time against its wall time (the gRPC threads' share).

    python3 bench/python_actor_profile.py target/release/saver [--envs 16] [--steps 100000] [--top 25]
        [--env-processes N]

Prints the functions with the most own time on the stepping thread, then the share
of the actor's non-waiting time spent in each stage of a rollout: env.step, the
policy's forward pass, the step bookkeeping (outcome, checks), the rest (the loop,
the message packing). cProfile adds a cost to every Python call, so the shares of
the Python-heavy stages are overstated; the rates are bench/python_actor_speed.py's.
"""
import argparse
import cProfile
import pstats
import time

import reacher_learner  # bench/, beside this script
from saver_actor import Actor, Connection
from saver_actor.examples import reacher

ap = argparse.ArgumentParser()
ap.add_argument("saver", nargs="?", default="target/release/saver")
ap.add_argument("--envs", type=int, default=16)
ap.add_argument("--steps", type=int, default=100_000)
ap.add_argument("--top", type=int, default=25)
ap.add_argument("--env-processes", type=int, default=0, help="the actor's env worker processes (0: none)")
args = ap.parse_args()
make_env, decl = reacher()

learner, url = reacher_learner.start(args.saver, decl, 1, args.steps, "saver-profile-")
actor = Actor(make_env, decl, Connection(url), n_envs=args.envs, give_up=30,
              log=lambda m: None, env_processes=args.env_processes)
prof = cProfile.Profile()
cpu0, wall0 = time.process_time(), time.perf_counter()
try:
    prof.enable()
    summary = actor.run()
    prof.disable()
finally:
    actor.close()
    learner.wait(60)
cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
busy = summary.seconds - summary.wait_seconds
print(f"Reacher-v5, {args.envs} envs, {summary.steps} steps: {wall:.1f} s wall, {summary.wait_seconds:.1f} s "
      f"waiting for weights, {cpu:.1f} s CPU of the actor process (all its threads; under cProfile)")
stats = pstats.Stats(prof)
stats.sort_stats("tottime").print_stats(args.top)


def cum(name, file=""):
    """Cumulative seconds of the functions called `name` (in a file whose name ends
    with `file`) on the stepping thread."""
    return sum(v[3] for k, v in stats.stats.items()  # type: ignore[attr-defined]
               if k[2] == name and k[0].endswith(file))


stages = [("env.step (the env set's step)", cum("step", "envset.py")),
          ("episode resets (the env set's reset)", cum("reset", "envset.py")),
          ("policy forward (act)", cum("act", "policy.py")),
          ("actions to the env's (ActionMap)", cum("__call__", "env.py")),
          ("outcome (rewards, success)", cum("outcome", "env.py")),
          ("rollout checks (check_obs, check_steps)", cum("check_obs", "env.py") + cum("check_steps", "env.py")),
          ("the rollout queue (_Rollouts.send)", cum("send", "actor.py"))]
collect = cum("_collect", "actor.py")
print(f"the stepping thread's busy time: {busy:.1f} s; inside Actor._collect {collect:.1f} s")
for what, s in stages:
    print(f"  {what:42s} {s:7.2f} s  {s / busy:6.1%}")
rest = collect - sum(s for _, s in stages)  # (the checks of reset observations are counted twice)
print(f"  {'the rest of _collect (loop, packing)':42s} {rest:7.2f} s  {rest / busy:6.1%}")
