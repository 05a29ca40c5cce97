#!/usr/bin/env python3
"""A markdown table from the JSON lines of bench/custom_env_results.py and
bench/sb3_custom.py: per algorithm (and its flags), the trained policy's success rate,
return and final distance per seed (the seeds named where they are not 0, 1, ...), and their
means.

    python3 bench/custom_env_table.py results/inertial/pointmass-300k.jsonl [...]
"""
import json
import sys

runs = {}
for path in sys.argv[1:]:
    for line in open(path):
        if line.startswith("{"):
            r = json.loads(line)
            runs.setdefault((r["env"], r["steps"], r["algo"]), []).append(r)
print("| env, steps | algo | success per seed | mean | return per seed | mean | final distance, mean |")
print("|---|---|---|---|---|---|---|")
for (env, steps, algo), rs in runs.items():
    rs.sort(key=lambda r: r["seed"])
    t = [r["trained"] for r in rs]
    success = " / ".join(f"{x['success']:.2f}" for x in t)
    ret = " / ".join(f"{x['return']:.1f}" for x in t)
    mean = {k: sum(x[k] for x in t) / len(t) for k in ("success", "return", "distance")}
    seeds = [r["seed"] for r in rs]
    if seeds != list(range(len(seeds))):
        algo += " (seeds " + ", ".join(map(str, seeds)) + ")"
    print(f"| {env}, {steps // 1000} k | {algo} | {success} | {mean['success']:.2f} | {ret} | {mean['return']:.1f} "
          f"| {mean['distance']:.3f} |")
