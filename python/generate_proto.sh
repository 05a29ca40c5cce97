#!/usr/bin/env bash
# Regenerates saver_actor/_proto from proto/saver.proto (needs grpcio-tools).
set -euo pipefail
cd "$(dirname "$0")"
out=saver_actor/_proto
python -m grpc_tools.protoc -I../proto --python_out="$out" --grpc_python_out="$out" saver.proto
# The stubs import the messages as a sibling module of the package.
sed -i 's/^import saver_pb2 as saver__pb2/from . import saver_pb2 as saver__pb2/' "$out/saver_pb2_grpc.py"
