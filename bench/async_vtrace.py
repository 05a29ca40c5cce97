#!/usr/bin/env python3
"""Async mode with slow actors, with and without V-trace, against sync (issue 32):
a `saver learner` and 16 `saver actor` processes over gRPC on loopback, the first
--slow of them (one by default) slowed by --delay-us a step; per run, one JSON line: wall seconds, env steps/s, mean and
largest policy lag, stale rollouts dropped, the steps at which the mean episode length
of the last 100 episodes first fell below --threshold, and the final mean length.
Standard library only.

    python3 bench/async_vtrace.py target/release/saver --algo a2c --env angle --dim 4 \\
        --steps 1000000 --seeds 0 --delay-us 400 [--slow 1] [--modes sync,async,vtrace] [--out DIR]
"""
import argparse
import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

ap = argparse.ArgumentParser()
ap.add_argument("saver")
ap.add_argument("--algo", default="a2c")
ap.add_argument("--env", default="angle")
ap.add_argument("--dim", type=int, default=4)
ap.add_argument("--steps", type=int, default=1_000_000)
ap.add_argument("--seeds", type=int, nargs="+", default=[0])
ap.add_argument("--actors", type=int, default=16)
ap.add_argument("--delay-us", type=int, default=400, help="step delay of each slow actor")
ap.add_argument("--slow", type=int, default=1, help="how many of the actors are slowed")
ap.add_argument("--max-lag", type=int, default=8)
ap.add_argument("--threshold", type=float, default=100.0)
ap.add_argument("--modes", default="sync,async,vtrace")
ap.add_argument("--extra", default="", help="flags for every learner")
ap.add_argument("--out", default=None)
opts = ap.parse_args()
out = opts.out or tempfile.mkdtemp(prefix="saver-async-")
os.makedirs(out, exist_ok=True)


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(mode, seed):
    port = free_port()
    name = f"{opts.env}{opts.dim}-{opts.algo}-{mode}-seed{seed}"
    folder = os.path.join(out, name)
    shutil.rmtree(folder, ignore_errors=True)  # a fresh run, not a resumed one
    flags = ["--algo", opts.algo, "--env", opts.env, "--dim", str(opts.dim), "--steps", str(opts.steps),
             "--seed", str(seed), "--actors", str(opts.actors), *opts.extra.split()]
    if mode != "sync":
        flags += ["--mode", "async", "--max-lag", str(opts.max_lag)]
    if mode == "vtrace":
        flags += ["--vtrace", "true"]
    log = open(folder + ".log", "w")
    learner = subprocess.Popen([opts.saver, "learner", "--out", folder, "--listen", f"127.0.0.1:{port}", *flags],
                               stdout=log, stderr=subprocess.STDOUT)
    start = time.time()
    actors = []
    for i in range(opts.actors):
        delay = opts.delay_us if i < opts.slow else 0
        actors.append(subprocess.Popen([opts.saver, "actor", "--learner", f"http://127.0.0.1:{port}",
                                        "--name", f"a{i}", "--step-delay-us", str(delay)],
                                       stdout=log, stderr=subprocess.STDOUT))
    for a in actors:
        a.wait(timeout=7200)
    wall = time.time() - start
    # The learner serves its final weights until told to stop.
    learner.send_signal(signal.SIGINT)
    learner.wait(timeout=60)
    rows = list(csv.DictReader(open(os.path.join(folder, "metrics.csv"))))
    reached = next((int(r["steps"]) for r in rows
                    if r["mean_ep_len_100"] and float(r["mean_ep_len_100"]) < opts.threshold
                    and int(r["episodes"]) >= 100), None)
    last = rows[-1]
    return {"algo": opts.algo, "env": f"{opts.env}-d{opts.dim}", "mode": mode, "seed": seed,
            "steps": int(last["steps"]),
            "delay_us": opts.delay_us, "slow": opts.slow, "wall_s": round(wall, 1),
            "steps_per_s": round(int(last["steps"]) / wall),
            "lag_mean": round(sum(float(r["lag_mean"]) for r in rows) / len(rows), 2),
            "lag_max": max(int(r["lag_max"]) for r in rows), "stale_dropped": int(last["stale_dropped"]),
            f"steps_to_{opts.threshold:g}": reached, "final_mean_len": float(last["mean_ep_len_100"])}


print(f"runs in {out}", file=sys.stderr)
for seed in opts.seeds:
    for mode in opts.modes.split(","):
        print(json.dumps(run(mode, seed)), flush=True)
