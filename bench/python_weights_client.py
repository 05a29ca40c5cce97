#!/usr/bin/env python3
"""Fetch a SAVER learner's weights from Python with grpcio, decode them with the
safetensors package and act with them in numpy, using only what the weights file says
about itself (its metadata): no SAVER code. The check that the wire format is open.

    python3 -m venv .venv && .venv/bin/pip install grpcio grpcio-tools safetensors numpy
    .venv/bin/python bench/python_weights_client.py 127.0.0.1:50051 [--token-file FILE]

A learner started with a token wants it on every call as the gRPC metadata
`authorization: Bearer <token>`.
"""
import argparse
import json
import os
import sys
import tempfile

from grpc_tools import protoc
import grpc
import numpy as np

root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "proto")
out = tempfile.mkdtemp(prefix="saver-pb-")
if protoc.main(["protoc", f"-I{root}", f"--python_out={out}", f"--grpc_python_out={out}", "saver.proto"]) != 0:
    sys.exit("protoc failed on proto/saver.proto")
sys.path.insert(0, out)
import saver_pb2  # noqa: E402
import saver_pb2_grpc  # noqa: E402
from safetensors import safe_open  # noqa: E402
from safetensors.numpy import load  # noqa: E402


def act(w, meta, obs, rng):
    """One action of the gaussian-mlp policy, as its metadata's `architecture` says
    (a bound of null in `policy_params` is no bound)."""
    layout = json.loads(meta["layout"])
    params = json.loads(meta["policy_params"])
    bound = params["mu_bound"]
    lo = -np.inf if params["log_std_min"] is None else params["log_std_min"]
    hi = np.inf if params["log_std_max"] is None else params["log_std_max"]
    h = obs
    if "agent.obs_mean" in w:
        # The observation normaliser: each entry's clip, or 10 (inf: not clipped).
        b = w.get("agent.obs_clip", np.full(layout["obs_dim"], 10.0, dtype=np.float32))
        h = np.clip((h - w["agent.obs_mean"]) / w["agent.obs_std"], -b, b)
    i = 0
    while f"agent.l{i}.w" in w:
        h = np.maximum(h @ w[f"agent.l{i}.w"] + w[f"agent.l{i}.b"], 0.0)
        i += 1
    raw = h @ w["agent.mu.w"] + w["agent.mu.b"]
    mu = bound * np.tanh(raw) if bound is not None else raw
    log_std = np.clip(w["agent.log_std"], lo, hi)
    c, ch = layout["continuous"], layout["choices"]
    action = mu[:c] + np.exp(log_std) * rng.standard_normal(c)
    if ch > 0:
        logits = mu[c:c + ch]
        p = np.exp(logits - logits.max())
        onehot = np.zeros(ch)
        onehot[rng.choice(ch, p=p / p.sum())] = 1.0
        action = np.concatenate([action, onehot])
    return action


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("addr", nargs="?", default="127.0.0.1:50051")
    ap.add_argument("--token-file", help="the learner's token (as for `saver --token-file`)")
    args = ap.parse_args()
    metadata = []
    if args.token_file:
        token = open(args.token_file).read().strip()
        metadata.append(("authorization", f"Bearer {token}"))
    options = [("grpc.max_receive_message_length", 64 << 20)]
    with grpc.insecure_channel(args.addr, options=options) as channel:
        stub = saver_pb2_grpc.LearnerStub(channel)
        reply = stub.GetWeights(saver_pb2.WeightsRequest(min_version=0), timeout=30, metadata=metadata)
    tensors = load(reply.safetensors)
    path = os.path.join(out, "weights.safetensors")
    with open(path, "wb") as f:
        f.write(reply.safetensors)
    with safe_open(path, framework="numpy") as f:
        meta = f.metadata()
    print(f"version {reply.version}: {meta['algo']} on {meta['env']}, policy {meta['policy_family']}")
    for name in sorted(tensors):
        t = tensors[name]
        print(f"{name:<16} {list(t.shape)} {t.dtype} mean {float(t.mean()):+.5f}")
    layout = json.loads(meta["layout"])
    rng = np.random.default_rng(0)
    obs = rng.uniform(-1, 1, layout["obs_dim"]).astype(np.float32)
    a = act(tensors, meta, obs, rng)
    print(f"obs {np.round(obs, 3)} -> action {np.round(a, 3)}")


if __name__ == "__main__":
    main()
