#!/usr/bin/env python3
"""Summarises a SAVER run's per_dim.csv (written by the learner, see
core/src/algo/per_dim.rs) over windows of steps: per coordinate j the critic's
explained variance 1 - mse/var(R), the raw advantage's std and its correlation with
the step's own reward; per action entry the share of mu at the tanh bound and the mean
log sigma. Where the run has them (SAVER on continuous actions,
core/src/algo/saver/signal.rs): per coordinate the rank correlation of the observed
and the predicted target, the share of the position change the action causes and the
PCPN's error against the action's effect; per action entry the signal-to-noise ratio
of SAVER's and of A2C's gradient on the same batches. Next to it, the run's mean
episode length from metrics.csv. Several runs (seeds) pool their rows per window: each
line is then the mean over every run's batches in it.

    bench/per_dim_summary.py RUN_DIR... [--every 100000]
"""
import argparse
import csv
import os
import sys


def rows(path):
    if not os.path.isfile(path):
        sys.exit(f"per_dim_summary: {path} not found (each RUN_DIR is a SAVER learner's run folder)")
    with open(path) as f:
        return list(csv.DictReader(f))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--every", type=int, default=100_000)
    args = ap.parse_args()
    per_dim = [r for run in args.runs for r in rows(os.path.join(run, "per_dim.csv"))]
    d = sum(1 for k in per_dim[0] if k.startswith("critic_mse_"))
    m = sum(1 for k in per_dim[0] if k.startswith("mu_sat_"))
    windows = {}
    for r in per_dim:
        windows.setdefault((int(r["steps"]) - 1) // args.every, []).append(r)
    lengths = {}  # the last mean length of each run in each window
    for run in args.runs:
        last = {}
        for r in rows(os.path.join(run, "metrics.csv")):
            if r["mean_ep_len_100"]:
                last[(int(r["steps"]) - 1) // args.every] = float(r["mean_ep_len_100"])
        for w, x in last.items():
            lengths.setdefault(w, []).append(x)
    length = {w: sum(xs) / len(xs) for w, xs in lengths.items()}

    def mean(rs, key):
        return sum(float(r[key]) for r in rs) / len(rs)

    def fmt(xs, f):
        return " ".join(f.format(x) for x in xs)

    print(f"{' '.join(args.runs)}: d = {d}, {m} mean entries; per window of {args.every} steps")
    for w in sorted(windows):
        rs = windows[w]
        ev = [1 - mean(rs, f"critic_mse_{j}") / max(mean(rs, f"return_var_{j}"), 1e-12) for j in range(d)]
        print(f"\nsteps <= {(w + 1) * args.every}: mean length {length.get(w, float('nan')):.1f}")
        print("  critic explained var  " + fmt(ev, "{:6.2f}"))
        print("  advantage std         " + fmt([mean(rs, f"adv_std_{j}") for j in range(d)], "{:6.4f}"))
        print("  corr(adv, own reward) " + fmt([mean(rs, f"adv_reward_corr_{j}") for j in range(d)], "{:6.2f}"))
        print("  mu at the bound       " + fmt([mean(rs, f"mu_sat_{i}") for i in range(m)], "{:6.2f}"))
        print("  log sigma             " + fmt([mean(rs, f"log_std_{i}") for i in range(m)], "{:6.2f}"))
        if "rank_corr_0" in rs[0]:
            print("  rank corr obs/pred    " + fmt([mean(rs, f"rank_corr_{j}") for j in range(d)], "{:6.2f}"))
            print("  action share of dp    " + fmt([mean(rs, f"act_share_{j}") for j in range(d)], "{:6.3f}"))
            print("  PCPN error / action   " + fmt([mean(rs, f"err_ratio_{j}") for j in range(d)], "{:6.2f}"))
        if "snr_saver_0" in rs[0]:
            c = sum(1 for k in rs[0] if k.startswith("snr_saver_"))
            print("  SNR SAVER grad        " + fmt([mean(rs, f"snr_saver_{i}") for i in range(c)], "{:6.2f}"))
            print("  SNR A2C grad          " + fmt([mean(rs, f"snr_a2c_{i}") for i in range(c)], "{:6.2f}"))


if __name__ == "__main__":
    main()
