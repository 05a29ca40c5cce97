#!/usr/bin/env python3
"""SAVER's and A2C's Reacher-v5 results (results/README.md): for each algorithm and
seed, a learner, two Python actor processes (4 envs each) and, for SAVER, a
pcpn-trainer pretraining the PCPN from the actors' streamed walks (its default 5,000
batches; one PCPN for every seed, as the paper intends); then the mean final
|fingertip - target| of 50 deterministic episodes, untrained and trained. One JSON
line per run. SB3's numbers on the same env and reward: bench/sb3_reacher.py.

    python3 bench/reacher_results.py target/release/saver STEPS SEED... [--algos a2c,saver] [--extra "FLAGS"]
"""
import json
import os
import sys
import time

here = os.path.dirname(os.path.abspath(__file__))
args = sys.argv[1:]
algos = ["a2c", "saver"]
if "--algos" in args:
    i = args.index("--algos")
    algos = args[i + 1].split(",")
    del args[i:i + 2]
extra = []
if "--extra" in args:
    i = args.index("--extra")
    extra = args[i + 1].split()
    del args[i:i + 2]
saver, steps, seeds = args[0], int(args[1]), [int(s) for s in args[2:]]
sys.argv = ["reacher_results", saver]
sys.path.insert(0, os.path.join(here, "..", "tests", "python"))
import test_saver_actor as t  # noqa: E402

store = None
for algo in algos:
    for seed in seeds:
        if algo == "saver" and store is None:
            store = t.Server("pcpn-trainer", ["pcpn-trainer", "--store", os.path.join(t.TMP, "store")]).wait_ready()
        start = time.time()
        before, after = t.reacher_run(algo, steps, ["--seed", str(seed), *extra], pcpn=store if algo == "saver" else None,
                                       name=f"reacher-{algo}-seed{seed}" + "".join(extra).replace("-", "_"))
        print(json.dumps({"algo": algo, "extra": " ".join(extra), "seed": seed, "steps": steps, "wall_s": round(time.time() - start, 1),
                          "untrained": round(before, 4), "trained": round(after, 4)}), flush=True)
if store is not None:
    store.stop()
