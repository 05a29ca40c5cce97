#!/usr/bin/env python3
"""How many streamed walk transitions (and batches) a custom env's PCPN needs:
pretrains it (batches of 128, K 32, RMSProp 1e-3: the custom-env default settings)
from N distinct transitions in B batches for each N:B of --grid (N 0: a fresh
transition for every batch row, B x 128, as before pretrain.walk_samples existed) and
reports the held-out loss (16 batches of 128 held out from the same walks), the time
the samples took to arrive and the whole time.

One `saver pcpn-trainer` per env, one `saver-actor samples --envs 16` provider per
pretraining (the samples of every env of an actor, as `saver-actor act
--pcpn-samples` streams them). Writes results/pcpn-samples/pcpn_samples.csv.

    python3 bench/pcpn_samples.py target/release/saver \\
        [--factories saver_actor.examples:reacher,saver_actor.examples:pointmass] \\
        [--grid 8192:5000,...] [--seeds 0]
"""
import argparse
import csv
import os
import subprocess
import sys
import tempfile
import threading
import time

import grpc
from safetensors import safe_open
from saver_actor._proto import saver_pb2 as pb
from saver_actor._proto import saver_pb2_grpc as pb_grpc

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests", "python"))


def pretrain(t, factory, count, batches, seed, store_dir):
    """One pretraining of `factory`'s PCPN from `count` walk transitions in `batches`
    batches (`t`: tests/python/test_saver_actor, for its Server): returns a row."""
    _, decl = t.custom_env(factory)
    store = t.Server(f"store-{decl.name}-{count}-{batches}-{seed}", ["pcpn-trainer", "--store", store_dir])
    url = f"127.0.0.1:{store.port}"
    provider = None
    try:
        store.wait_ready()
        provider = subprocess.Popen([sys.executable, "-m", "saver_actor", "samples", "--factory", factory, "--pcpn",
                                     store.url, "--envs", "16", "--seed", str(seed)],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        settings = pb.PretrainSettings(optimizer="rmsprop", lr=0.001, batches=batches, batch_size=128, quantiles=32,
                                       seed=seed, samples="walk", walk_samples=count)
        samples_done = [None]
        start = time.time()
        finished = threading.Event()

        def watch():
            with grpc.insecure_channel(url) as ch:
                stub = pb_grpc.PcpnStoreStub(ch)
                while not finished.wait(0.5):
                    try:
                        p = stub.Progress(pb.ProgressRequest(), timeout=5).pretraining
                    except grpc.RpcError:
                        continue
                    # The samples are all in when the batches begin (walk_samples > 0; with
                    # 0 they arrive as the batches need them).
                    if p and samples_done[0] is None and p[0].phase == "batches":
                        samples_done[0] = time.time() - start

        threading.Thread(target=watch, daemon=True).start()
        with grpc.insecure_channel(url) as ch:
            reply = pb_grpc.PcpnStoreStub(ch).Pretrain(pb.PretrainRequest(env=decl.spec(), settings=settings),
                                                       timeout=7200)
        wall = time.time() - start
        finished.set()
        files = [f for f in os.listdir(store_dir) if f.startswith(f"pcpn-{decl.name}-") and
                 f.endswith(".safetensors")]
        path = max((os.path.join(store_dir, f) for f in files), key=os.path.getmtime)
        with safe_open(path, framework="numpy") as f:
            meta = f.metadata()
        streamed = int(meta["samples"].split()[0])
        return {"env": decl.name, "walk_samples": count, "batches": batches, "seed": seed, "streamed": streamed,
                "initial_held_out_loss": float(meta["initial_held_out_loss"]),
                "held_out_loss": float(meta["held_out_loss"]),
                "samples_s": round(samples_done[0] or wall, 1), "wall_s": round(wall, 1),
                "sha": reply.info.weights_sha256[:12]}
    finally:
        if provider is not None and provider.poll() is None:
            provider.terminate()
            provider.wait(60)
        store.stop()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("saver")
    ap.add_argument("--factories", default="saver_actor.examples:reacher,saver_actor.examples:pointmass")
    ap.add_argument("--grid", default="8192:5000,16384:5000,32768:5000,65536:5000,131072:5000,0:5000,"
                                      "65536:1000,65536:2000", help="walk_samples:batches, ...")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--out", default=os.path.join(ROOT, "results", "pcpn-samples", "pcpn_samples.csv"))
    args = ap.parse_args()
    sys.argv = ["pcpn_samples", args.saver]
    import test_saver_actor as t  # its SAVER is argv[1]

    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    rows = []
    for factory in args.factories.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            for cell in args.grid.split(","):
                count, batches = (int(x) for x in cell.split(":"))
                with tempfile.TemporaryDirectory(prefix="pcpn-samples-") as store_dir:
                    row = pretrain(t, factory, count, batches, seed, store_dir)
                rows.append(row)
                print(", ".join(f"{k} {v}" for k, v in row.items()), flush=True)
                with open(args.out, "w", newline="") as f:
                    w = csv.DictWriter(f, fieldnames=list(rows[0]))
                    w.writeheader()
                    w.writerows(rows)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
