#!/usr/bin/env python3
"""The side-by-side table and curves of issue 55 from the JSON lines of
bench/custom_env_results.py (with --curve-every) and bench/sb3_tuned.py: per variant,
success and env return (the env's own return over the whole episode) per seed at the
end, and the steps at which each seed's deterministic evaluation first reached 0.9
success and an env return of -6 (">N": never within the run; "-": no curve), and the step
from which every later evaluation, the final one included, stayed at 0.9 success or
more ("held"; a first crossing can be a lucky evaluation). With --png, the mean and
standard deviation over seeds of success and env return against steps (matplotlib).

    python3 bench/env_return_table.py results/env-return/*.jsonl [--png results/env-return/curves.png]
"""
import argparse
import collections
import json
import sys

import numpy as np

ap = argparse.ArgumentParser()
ap.add_argument("files", nargs="+")
ap.add_argument("--png")
opts = ap.parse_args()


def env_of(r):
    """The env's short name: custom_env_results.py writes it, sb3_tuned.py its factory
    (module:function; lines written before it did are Reacher-v5's)."""
    return r.get("env", "reacher").split(":")[-1]


runs = collections.defaultdict(list)  # "env: variant" -> [(seed, final, curve, steps)]
for path in opts.files:
    sb3 = collections.defaultdict(list)
    with open(path) as f:
        for line in f:
            if not line.startswith("{"):
                continue
            r = json.loads(line)
            if "trained" in r:  # custom_env_results.py: one line per run, its curve inside
                runs[f"{env_of(r)}: {r['algo']}"].append((r["seed"], r["trained"], r.get("curve", []), r["steps"]))
            elif r.get("final"):
                key = (env_of(r), r["algo"], r["seed"])
                runs[f"{env_of(r)}: sb3 {r['algo']}"].append((r["seed"], r, sb3[key], r["steps"]))
            else:
                sb3[(env_of(r), r["algo"], r["seed"])].append(r)


def first(curve, ok, steps):
    if not curve:
        return "-"
    hit = [c["steps"] for c in curve if ok(c)]
    return f"{hit[0] // 1000} k" if hit else f">{steps // 1000} k"


def held(curve, final, steps):
    """The step of the first evaluation from which every later one, and the final one, has
    success >= 0.9."""
    if not curve:
        return "-"
    if final["success"] < 0.9:
        return f">{steps // 1000} k"
    i = len(curve)
    while i > 0 and curve[i - 1]["success"] >= 0.9:
        i -= 1
    return f"{curve[i]['steps'] // 1000} k" if i < len(curve) else f"{steps // 1000} k"


print("| variant | seeds | success per seed | env return per seed | mean | steps to 0.9 success | 0.9 success held from"
      " | steps to env return -6 |")
print("|---|---|---|---|---|---|---|---|")
for variant, rs in runs.items():
    rs.sort(key=lambda r: r[0])
    succ = " / ".join(f"{r[1]['success']:.2f}" for r in rs)
    ret = " / ".join(f"{r[1]['env_return']:.1f}" for r in rs)
    mean = np.mean([r[1]["env_return"] for r in rs])
    to_s = " / ".join(first(r[2], lambda c: c["success"] >= 0.9, r[3]) for r in rs)
    kept = " / ".join(held(r[2], r[1], r[3]) for r in rs)
    to_r = " / ".join(first(r[2], lambda c: c["env_return"] >= -6.0, r[3]) for r in rs)
    print(f"| {variant} | {len(rs)} | {succ} | {ret} | {mean:.2f} | {to_s} | {kept} | {to_r} |")

if opts.png:
    try:
        import matplotlib
    except ImportError:  # the table above is the product and the figure the last step: no failure
        print(f"env_return_table: no figure {opts.png}: this Python has no matplotlib (pip install matplotlib)",
              file=sys.stderr)
        sys.exit(0)
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for variant, rs in runs.items():
        curves = [r[2] for r in rs if r[2]]
        if not curves:
            continue
        n = min(len(c) for c in curves)
        steps = np.mean([[c[i]["steps"] for i in range(n)] for c in curves], axis=0)
        for ax, key in zip(axes, ("success", "env_return")):
            v = np.array([[c[i][key] for i in range(n)] for c in curves])
            m, s = v.mean(axis=0), v.std(axis=0)
            ax.plot(steps, m, label=f"{variant} ({len(curves)} seeds)")
            ax.fill_between(steps, m - s, m + s, alpha=0.2)
    for ax, title in zip(axes, ("success (50 deterministic episodes)", "env return over the whole episode")):
        ax.set_xlabel("env steps")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(opts.png, dpi=110)
    print(f"curves: {opts.png}")
