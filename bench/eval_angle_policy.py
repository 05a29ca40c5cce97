#!/usr/bin/env python3
"""Where does a trained angle policy get stuck? Reads a run's checkpoint.safetensors
with numpy alone (the format is 8 bytes of header length, a JSON header, raw data),
runs the agent on the angle env (SPEC.md: step s = 0.1*a[k], angle (a[k+1]+1)*pi/2)
from uniform starts, and prints per coordinate: the mean |p| after 200 steps, the share
of episodes within the 0.1 goal, and how often mu sits within 0.02 of the tanh bound.

    bench/eval_angle_policy.py results/runs/default-d16-seed2 [--episodes 256] [--mu-only]
"""
import argparse
import json
import struct

import numpy as np


def load(path):
    with open(path, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        header = json.loads(f.read(n))
        data = f.read()
    out = {}
    for name, meta in header.items():
        if name == "__metadata__":
            continue
        a, b = meta["data_offsets"]
        assert meta["dtype"] == "F32", (name, meta["dtype"])
        out[name] = np.frombuffer(data[a:b], dtype=np.float32).reshape(meta["shape"])
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--episodes", type=int, default=256)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--mu-only", action="store_true", help="act with mu (no noise)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    w = load(f"{args.run}/checkpoint.safetensors")
    cfg = open(f"{args.run}/config.toml").read()
    bound = 1.0 if "mu_bound = 1" in cfg else None
    layers = sorted(k[:-2] for k in w if k.startswith("agent.l") and k.endswith(".w"))

    def policy(p):
        h = p
        for l in layers:
            h = np.maximum(h @ w[l + ".w"] + w[l + ".b"], 0.0)
        mu = h @ w["agent.mu.w"] + w["agent.mu.b"]
        return np.tanh(mu) * bound if bound else mu

    log_std = np.clip(w["agent.log_std"], -4.6, 0.0) if bound else w["agent.log_std"]
    rng = np.random.default_rng(args.seed)
    d = w["agent.mu.w"].shape[1]
    p = rng.uniform(-1, 1, (args.episodes, d)).astype(np.float32)
    done_at = np.full(args.episodes, -1)
    sat = np.zeros(d)
    for t in range(args.steps):
        mu = policy(p)
        sat += (np.abs(mu) > 0.98).mean(0)
        a = mu if args.mu_only else mu + np.exp(log_std) * rng.standard_normal(mu.shape)
        a = np.clip(a, -1, 1)
        s, phi = 0.1 * a[:, 0::2], (a[:, 1::2] + 1) * np.pi / 2
        delta = np.empty_like(p)
        delta[:, 0::2], delta[:, 1::2] = s * np.sin(phi), s * np.cos(phi)
        p = np.clip(p + delta, -1, 1)
        hit = (np.abs(p).max(1) < 0.1) & (done_at < 0)
        done_at[hit] = t + 1
    print(f"{args.run}: d={d}, log_std={np.round(log_std, 2)}")
    print(f"episodes within the goal by step {args.steps}: {(done_at > 0).mean():.2f}; "
          f"over all coordinates: mean |p| {np.abs(p).mean():.3f}, "
          f"within 0.1 {(np.abs(p) < 0.1).mean():.2f} (uniform start: 0.500, 0.10)")
    print("coord  mean|p|  within0.1  mu-at-bound")
    for i in range(d):
        print(f"{i:5d}  {np.abs(p[:, i]).mean():7.3f}  {(np.abs(p[:, i]) < 0.1).mean():9.2f}"
              f"  {sat[i] / args.steps:11.2f}")


if __name__ == "__main__":
    main()
