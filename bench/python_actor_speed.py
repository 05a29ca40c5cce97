#!/usr/bin/env python3
"""How fast Python actors step their envs, against the bare env, in one run.

    python3 bench/python_actor_speed.py target/release/saver [--envs 16] [--steps 100000]
        [--env-processes N] [--actors P]

1. bare: E Reacher-v5 envs stepped in one process, nothing else, reset at the end of
   each episode, with the actions of the untrained policy (N(0, 1) clipped to [-1, 1]:
   the actors' Gaussian at mu ~ 0, log sigma 0), and with uniform random actions for
   reference (MuJoCo's step costs less at smaller torques: ~15 % more steps/s here);
2. actor: P saver_actor.Actor processes of E/P envs each (their envs stepped in this
   process, or in N worker processes each with --env-processes), with the policy, the
   bookkeeping and the rollout stream, against a real `saver learner` (A2C, sync:
   while the learner updates, the actors wait for its weights and do not compete for
   the cores). Reported per second of the actors' time not spent waiting for weights
   (their own cost), and per wall second, both against the bare rate.
"""
import argparse
import multiprocessing as mp

import reacher_learner  # bench/, beside this script
from saver_actor import Actor, Connection
from saver_actor.examples import reacher

ap = argparse.ArgumentParser()
ap.add_argument("saver", nargs="?", default="target/release/saver")
ap.add_argument("--envs", type=int, default=16, help="envs in all (split over --actors)")
ap.add_argument("--steps", type=int, default=100_000)
ap.add_argument("--env-processes", type=int, default=0, help="each actor's env worker processes (0: none)")
ap.add_argument("--actors", type=int, default=1, help="actor processes")
args = ap.parse_args()
make_env, decl = reacher()


def act(url, n_envs, out):
    actor = Actor(make_env, decl, Connection(url), n_envs=n_envs, give_up=30, log=lambda m: None,
                  env_processes=args.env_processes)
    try:
        s = actor.run()
    finally:
        actor.close()
    out.put((s.steps, s.seconds, s.wait_seconds, s.env_seconds))


bare = reacher_learner.bare_rate(make_env, args.envs, args.steps, reacher_learner.policy_actions)
uniform = reacher_learner.bare_rate(make_env, args.envs, args.steps, lambda rng, shape: rng.uniform(-1, 1, shape))
learner, url = reacher_learner.start(args.saver, decl, args.actors, args.steps, "saver-speed-")
try:
    ctx = mp.get_context("fork")
    out = ctx.Queue()
    procs = [ctx.Process(target=act, args=(url, args.envs // args.actors, out))
             for _ in range(args.actors)]
    for p in procs:
        p.start()
    results = [out.get(timeout=3600) for _ in procs]
    for p in procs:
        p.join()
finally:
    learner.wait(60)
steps = sum(r[0] for r in results)
wall = steps / max(r[1] for r in results)
own = steps / max(r[1] - r[2] for r in results)
waiting = max(r[2] for r in results)
print(f"Reacher-v5, {args.envs} envs in {args.actors} actor process(es), env processes per actor "
      f"{args.env_processes}, {steps} steps")
print(f"  bare env:   {bare:8.0f} steps/s (one process; the untrained policy's actions; uniform random actions: "
      f"{uniform:.0f})")
print(f"  actors:     {own:8.0f} steps/s of their own time ({own / bare:.0%} of bare); {wall:.0f} per wall second "
      f"({wall / bare:.0%}; up to {waiting:.1f} s waiting for weights)")
print(f"  inside env.step: {max(r[3] for r in results):.1f} s of the actors' "
      f"{max(r[1] - r[2] for r in results):.1f} s")
