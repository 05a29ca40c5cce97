#!/usr/bin/env python3
"""Sample efficiency as a budget (issue 55): for each variant and each env-step budget N,
the success and env return of the policy a run of N steps ends with, over its seeds, and
the smallest budget at which every seed (and the seeds' mean) reaches 0.9 success, first
and for good (every larger budget too).

Why budgets: SAVER's rate on a custom env falls linearly to zero over the run
(`lr_decay`), so a run of N steps is not the first N steps of a longer run, and a long
run's curve says little about what a short one reaches. Runs whose schedule does not
depend on their length (SB3 PPO at RL Zoo's constant rate, SB3 SAC) give every budget
from one run: each evaluation of the curve counts as the final policy of a run that
long. SAVER's rows also count the env steps its PCPN was pretrained on (the walks: the
pool, `--pretrain-walk-samples`, 65,536 by default, and 2,048 held out), which one PCPN
spends once for every seed and goal of an env.

Input: the JSON lines of bench/custom_env_results.py (one per run, "trained" the final
policy) and bench/sb3_tuned.py (one per evaluation, "final": true at the end; a name
ending in "-lr-decay" is a decaying rate, whose curve is not a budget).

    python3 bench/budget_table.py FILE.jsonl... [--target 0.9]
"""
import argparse
import collections
import json
import re
import statistics

ap = argparse.ArgumentParser()
ap.add_argument("files", nargs="+")
ap.add_argument("--target", type=float, default=0.9, help="the success level a budget must reach")
opts = ap.parse_args()

HELD_OUT = 16 * 128  # the pretraining's held-out batches, streamed from the same walks
DEFAULT_WALKS = 65_536


def pretraining_steps(variant):
    """The env steps a SAVER variant's PCPN was pretrained on; 0 for the others."""
    if not variant.startswith("saver"):
        return 0
    m = re.search(r"--pretrain-walk-samples[ =](\d+)", variant)
    return (int(m.group(1)) if m else DEFAULT_WALKS) + HELD_OUT


def budget(n, pre):
    """A budget as the table's summary line writes it, with the pretraining added where any."""
    return f"{n:,}" + (f" ({n + pre:,} with pretraining)" if pre else "")


def first(ok):
    """The smallest budget that reached the target."""
    return next((n for n, good in ok if good), None)


def held(ok):
    """The smallest budget from which every larger one reached the target too (None where
    the largest did not)."""
    n = None
    for b, good in reversed(ok):
        if not good:
            break
        n = b
    return n


# "env: variant" -> budget -> {seed: (success, env_return)}
table = collections.defaultdict(lambda: collections.defaultdict(dict))
for path in opts.files:
    with open(path) as f:
        for line in f:
            if not line.startswith("{"):
                continue
            r = json.loads(line)
            env = r.get("env", "reacher").split(":")[-1]
            if "trained" in r:  # custom_env_results.py: the run's final policy
                t = r["trained"]
                table[f"{env}: {r['algo']}"][r["steps"]][r["seed"]] = (t["success"], t["env_return"])
            elif r.get("final") or not r["algo"].endswith("-lr-decay"):
                table[f"{env}: sb3 {r['algo']}"][r["steps"]][r["seed"]] = (r["success"], r["env_return"])

for variant in sorted(table):
    budgets = table[variant]
    pre = pretraining_steps(variant.split(": ", 1)[1])
    print(f"\n### {variant}" + (f" (+ {pre:,} pretraining steps)" if pre else ""))
    print("| budget (env steps) | seeds | success per seed | mean success | mean env return |")
    print("|---|---|---|---|---|")
    ok_every, ok_mean = [], []
    for n in sorted(budgets):
        seeds = budgets[n]
        succ = [seeds[s][0] for s in sorted(seeds)]
        ret = statistics.mean(seeds[s][1] for s in seeds)
        print(f"| {n:,} | {len(succ)} | {' / '.join(f'{x:.2f}' for x in succ)} | {statistics.mean(succ):.2f}"
              f" | {ret:.1f} |")
        ok_every.append((n, min(succ) >= opts.target))
        ok_mean.append((n, statistics.mean(succ) >= opts.target))
    for what, ok in (("every seed", ok_every), ("the seeds' mean", ok_mean)):
        at, kept = first(ok), held(ok)
        if at is None:
            print(f"{what} >= {opts.target}: at no budget up to {max(budgets):,}")
        else:
            since = f"at every larger budget from {budget(kept, pre)}" if kept else "not at the largest budget"
            print(f"{what} >= {opts.target}: first at {budget(at, pre)}, {since}")
