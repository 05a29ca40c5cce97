#!/usr/bin/env python3
"""SAVER and A2C on a custom env through Python actors (results/README.md, issue 31):
for each algorithm and seed, a `saver learner`, two `saver-actor act` processes (4 envs
each) and, for SAVER, a `saver pcpn-trainer` that pretrains the PCPN from the actors'
streamed walks (one PCPN for every seed of a batch of runs); then 50 deterministic
episodes (seeds 0-49) of the untrained and the trained policy: mean return (the env's
own reward), success rate and mean final L1 distance |p - g|. One JSON line per run;
each run's learner folder (metrics.csv, per_dim.csv) stays under --out.

    python3 bench/custom_env_results.py target/release/saver --factory saver_actor.examples:pointmass \\
        --steps 300000 --seeds 0 1 2 [--algos "a2c,saver,saver --saver-target predicted"] [--extra "FLAGS"]
        [--max-steps 200] [--out DIR] [--curve-every STEPS] [--tag=-30k]

--algos: comma-separated algorithms, each optionally followed by flags of its own (all
SAVER variants of one invocation share one PCPN).
"""
import argparse
import hashlib
import json
import os
import shutil
import sys

here = os.path.dirname(os.path.abspath(__file__))
ap = argparse.ArgumentParser()
ap.add_argument("saver")
ap.add_argument("--factory", required=True)
ap.add_argument("--steps", type=int, required=True)
ap.add_argument("--seeds", type=int, nargs="+", required=True)
ap.add_argument("--algos", default="a2c,saver")
ap.add_argument("--extra", default="", help="flags for every learner")
ap.add_argument("--max-steps", type=int, default=200, help="the learner's max_episode_steps")
ap.add_argument("--out", default=None, help="folder for the learners' run folders (default: a temp folder)")
ap.add_argument("--tag", default="", help="appended to every run folder's name (e.g. --tag=-30k: runs of another "
                "length beside these in one --out, sharing its PCPN)")
ap.add_argument("--curve-every", type=int, default=0,
                help="also evaluate the weights every so many steps while the run trains (\"curve\" in the JSON)")
opts = ap.parse_args()
sys.argv = ["custom_env_results", opts.saver]
sys.path.insert(0, os.path.join(here, "..", "tests", "python"))
import test_saver_actor as t  # noqa: E402

_, decl = t.custom_env(opts.factory)
out = opts.out or t.TMP
os.makedirs(out, exist_ok=True)


def rounded(r):
    return {"return": round(r["return"], 3), "success": r["success"], "distance": round(r["distance"], 4),
            "env_return": round(r["env_return"], 3)}


store = None
try:  # the store goes with the script, whatever ends it
    for variant in opts.algos.split(","):
        saver = variant.split()[0] == "saver"
        for seed in opts.seeds:
            if saver and store is None:
                store = t.Server("pcpn-trainer", ["pcpn-trainer", "--store", os.path.join(out, "store")]).wait_ready()
            algo, *flags = variant.split()
            flags += opts.extra.split()
            name = f"{decl.name}-{algo}-seed{seed}" + "".join(flags).replace("-", "_")
            if len(name) > 120:  # a file name's limit is 255 bytes: a long flag list by its hash
                name = f"{decl.name}-{algo}-seed{seed}-" + hashlib.sha1(" ".join(flags).encode()).hexdigest()[:12]
            name += opts.tag
            shutil.rmtree(os.path.join(out, name), ignore_errors=True)  # a fresh run, not a resumed one
            before, after, _, wall = t.custom_run(opts.factory, algo, opts.steps, ["--seed", str(seed), *flags],
                                                  store if saver else None, name, opts.max_steps, out, 100 * seed,
                                                  opts.curve_every)
            print(json.dumps({"env": decl.name, "algo": variant, "extra": opts.extra, "seed": seed, "steps": opts.steps,
                              "wall_s": round(wall, 1), "pcpn_wait_s": round(t.LAST_RUN["pcpn_wait_s"], 1),
                              "untrained": rounded(before), "trained": rounded(after),
                              **({"curve": [{"steps": c["steps"], **rounded(c)} for c in t.LAST_RUN["curve"]]}
                                 if opts.curve_every else {})}), flush=True)
finally:
    if store is not None:
        store.stop()

