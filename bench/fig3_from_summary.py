#!/usr/bin/env python3
"""Fig. 3's table (angle d = 4, 8, 16, 2.56 M steps) from the rows of
results/summary.csv that bench/saver_runs.sh made: per series and dimension, the mean
+/- std over seeds (population std, as `saver plot`) of the mean episode length at
0.5 M, 1 M and 2.56 M steps, and the steps until it first fell below 50 (seeds that
never did are counted apart). Python's standard library only.

    bench/fig3_from_summary.py [results/summary.csv]
"""
import csv
import statistics
import sys

# (series, dimension) -> the summary.csv name of the runs (2.56 M steps each).
ROWS = [
    ("SAVER default (3,000-batch PCPN at d = 8, 16)", 4, "joint-lr1e3-d4"),
    ("SAVER default (3,000-batch PCPN at d = 8, 16)", 8, "joint-lr1e3-d8"),
    ("SAVER default (3,000-batch PCPN at d = 8, 16)", 16, "joint-lr1e3-d16"),
    ("SAVER --faithful (5,000 / 3,000-batch PCPN)", 4, "faithful-d4-long"),
    ("SAVER --faithful (5,000 / 3,000-batch PCPN)", 16, "faithful-d16"),
    ("A2C (paper settings)", 4, "a2c-d4-long"),
    ("A2C (paper settings)", 8, "a2c-d8"),
    ("A2C (paper settings)", 16, "a2c-d16"),
]


def fmt(values, digits=1):
    if not values:
        return "-"
    m = statistics.fmean(values)
    s = statistics.pstdev(values) if len(values) > 1 else 0.0
    return f"{m:.{digits}f} +/- {s:.{digits}f}"


def main():
    path = sys.argv[1] if len(sys.argv) > 1 else "results/summary.csv"
    with open(path) as f:
        rows = [r for r in csv.DictReader(f) if r["steps"] == "2560000"]
    print("| series | d | seeds | at 0.5 M | at 1 M | at 2.56 M | steps to < 50 |")
    print("|---|---|---|---|---|---|---|")
    for series, d, name in ROWS:
        runs = sorted((r for r in rows if r["name"] == name), key=lambda r: int(r["seed"]))
        seeds = ", ".join(r["seed"] for r in runs)
        cols = [fmt([float(r[k]) for r in runs]) for k in ("len_0.5M", "len_1M", "len_2.56M")]
        reached = [float(r["steps_to_50"]) / 1000 for r in runs if r["steps_to_50"] != "never"]
        never = len(runs) - len(reached)
        to50 = (fmt(reached, 0) + " k" if reached else "") + (f" ({never} never)" if never else "")
        print(f"| {series} | {d} | {seeds} | {' | '.join(cols)} | {to50.strip()} |")


if __name__ == "__main__":
    main()
