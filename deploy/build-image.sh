#!/usr/bin/env bash
# Builds the statically linked `saver` binary and the `saver` Docker image from it.
# No base image is pulled: the image is FROM scratch and holds only the binary and an
# empty, writable /data.
#
#   deploy/build-image.sh [TAG]        (default tag: saver:latest)
#
# The binary lands in target/x86_64-unknown-linux-gnu/release/saver; it runs on any
# x86_64 Linux machine as it is (no glibc needed), which is how actors go to machines
# that have no Docker.
set -euo pipefail
cd "$(dirname "$0")/.."
tag=${1:-saver:latest}
target=x86_64-unknown-linux-gnu

echo "== building the static saver binary (target $target)"
# --target keeps RUSTFLAGS away from build scripts and proc-macros.
RUSTFLAGS="-C target-feature=+crt-static" cargo build --release --locked \
  --target "$target" -p saver --bin saver
bin=target/$target/release/saver
if ldd "$bin" 2>&1 | grep -q "=>"; then
  echo "error: $bin links shared libraries; a FROM scratch image cannot run it" >&2
  exit 1
fi

if ! docker info >/dev/null 2>&1; then
  echo "error: no Docker daemon answers (docker info failed); the binary is at $bin" >&2
  exit 1
fi

echo "== building the image $tag"
ctx=$(mktemp -d)
trap 'rm -rf "$ctx"' EXIT
# The image gets the binary without its debug info (~95 MB -> ~20 MB).
strip -o "$ctx/saver" "$bin" 2>/dev/null || cp "$bin" "$ctx/saver"
cp deploy/Dockerfile "$ctx/Dockerfile"
mkdir -p "$ctx/data"
docker build --quiet -t "$tag" "$ctx" >/dev/null
echo "image $tag built from $bin ($(du -h "$ctx/saver" | cut -f1) stripped)"
