#!/usr/bin/env python3
"""A run folder's TensorBoard event file, read back with the `tensorboard` package:
every scalar of metrics.csv is there, one value per update, equal to the CSV's.

    python3 tests/python/test_tensorboard.py target/release/saver
"""
import csv
import glob
import math
import os
import subprocess
import sys
import tempfile

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams import plugin_data_pb2

saver = sys.argv[1] if len(sys.argv) > 1 else "target/release/saver"
with tempfile.TemporaryDirectory() as tmp:
    run = os.path.join(tmp, "run")
    subprocess.run([saver, "train", "--steps", "20480", "--out", run], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    files = glob.glob(os.path.join(run, "events.out.tfevents.*"))
    assert len(files) == 1, files
    acc = EventAccumulator(run, size_guidance={"scalars": 0})
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    rows = list(csv.DictReader(open(os.path.join(run, "metrics.csv"))))
    assert len(rows) == 160, len(rows)  # 20,480 steps at 128 per update
    for tag in ["steps_per_s", "mean_ep_len_100", "policy_loss", "value_loss", "grad_norm",
                "episode/return_mean", "episode/success_rate"]:
        assert tag in tags, (tag, sorted(tags))
    for tag in ["policy_loss", "value_loss", "grad_norm"]:
        events = acc.Scalars(tag)
        assert len(events) == len(rows), (tag, len(events))
        for e, r in zip(events, rows):
            assert e.step == int(r["steps"]), (tag, e.step, r["steps"])
            want = float(r[tag])
            assert math.isclose(e.value, want, rel_tol=1e-6, abs_tol=1e-12), (tag, e.value, want)
    # The run's settings as the hparams plugin's session start, read with its own proto.
    content = acc.PluginTagToContent("hparams")["_hparams_/session_start_info"]
    hp = plugin_data_pb2.HParamsPluginData.FromString(content).session_start_info.hparams
    assert hp["algo"].string_value == "a2c" and hp["env.kind"].string_value == "angle", dict(hp)
    assert hp["env.dim"].number_value == 4 and hp["steps"].number_value == 20480, dict(hp)
    assert hp["seed"].number_value == 0 and "lr" in hp, dict(hp)
    rate = [e.value for e in acc.Scalars("episode/success_rate")]
    assert all(0.0 <= v <= 1.0 for v in rate), rate
    print(f"tensorboard reads {len(tags)} scalars x {len(rows)} updates and {len(hp)} hparams from "
          f"{os.path.basename(files[0])}")
