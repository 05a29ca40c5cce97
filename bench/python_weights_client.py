#!/usr/bin/env python3
"""Fetch a SAVER learner's weights from Python with grpcio and decode them with the
safetensors package alone (no SAVER code): the check that the wire format is open.

    python3 -m venv .venv && .venv/bin/pip install grpcio grpcio-tools safetensors numpy
    .venv/bin/python bench/python_weights_client.py 127.0.0.1:50051
"""
import os
import sys
import tempfile

from grpc_tools import protoc
import grpc

root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "proto")
out = tempfile.mkdtemp(prefix="saver-pb-")
if protoc.main(["protoc", f"-I{root}", f"--python_out={out}", f"--grpc_python_out={out}", "saver.proto"]) != 0:
    sys.exit("protoc failed on proto/saver.proto")
sys.path.insert(0, out)
import saver_pb2  # noqa: E402
import saver_pb2_grpc  # noqa: E402
from safetensors.numpy import load  # noqa: E402

addr = sys.argv[1] if len(sys.argv) > 1 else "127.0.0.1:50051"
options = [("grpc.max_receive_message_length", 64 << 20)]
with grpc.insecure_channel(addr, options=options) as channel:
    stub = saver_pb2_grpc.LearnerStub(channel)
    reply = stub.GetWeights(saver_pb2.WeightsRequest(min_version=0), timeout=30)
    tensors = load(reply.safetensors)
    print(f"version {reply.version}")
    for name in sorted(tensors):
        t = tensors[name]
        print(f"{name:<16} {list(t.shape)} {t.dtype} mean {float(t.mean()):+.5f}")
