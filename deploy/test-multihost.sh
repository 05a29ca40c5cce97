#!/usr/bin/env bash
# Actors on other machines, proven on this one: three network namespaces stand for
# three hosts. Host A runs the learner; hosts B and C run 8 actors each and reach A over
# their own veth link (10.77.1.0/24 and 10.77.2.0/24). The test checks that
#   1. training advances with all 16 actors registered;
#   2. with B's link cut, training goes on with C's 8 actors;
#   3. when the link returns, B's actors rejoin by themselves (same processes).
# Needs root (ip netns). Run by .ci/run; alone: deploy/test-multihost.sh [SAVER_BIN].
set -euo pipefail
cd "$(dirname "$0")/.."
bin=$(realpath "${1:-${SAVER_BIN:-target/release/saver}}")
[ -x "$bin" ] || { echo "error: no saver binary at $bin (cargo build --release)" >&2; exit 1; }
if [ "$(id -u)" != 0 ] || ! command -v ip >/dev/null; then
  echo "error: the multi-host test needs root and iproute2 (ip netns); not run" >&2
  exit 1
fi

p=sv$$                       # prefix of every name this test creates
tmp=$(mktemp -d)
token=multihost-$RANDOM$RANDOM
pids=()
cleanup() {
  status=$?
  for pid in "${pids[@]}"; do kill -9 "$pid" 2>/dev/null || true; done
  # Whatever still runs inside the hosts goes too, then the hosts.
  for h in a b c; do
    ip netns pids "${p}$h" 2>/dev/null | xargs -r kill -9 2>/dev/null || true
    ip netns del "${p}$h" 2>/dev/null || true
  done
  if [ "$status" != 0 ]; then
    echo "--- multi-host test FAILED; learner log tail:" >&2
    tail -n 30 "$tmp/learner.log" >&2 || true
    echo "--- one actor of B:" >&2
    tail -n 10 "$tmp/actor-b1.log" >&2 || true
  fi
  rm -rf "$tmp"
}
trap cleanup EXIT

echo "== hosts: ${p}a (learner), ${p}b and ${p}c (8 actors each)"
for h in a b c; do
  ip netns add "${p}$h"
  ip -n "${p}$h" link set lo up
done
# A <-> B and A <-> C, one veth pair each.
for h in b c; do
  n=$([ "$h" = b ] && echo 1 || echo 2)
  ip link add "${p}a$h" netns "${p}a" type veth peer name eth0 netns "${p}$h"
  ip -n "${p}a" addr add "10.77.$n.1/24" dev "${p}a$h"
  ip -n "${p}$h" addr add "10.77.$n.2/24" dev eth0
  ip -n "${p}a" link set "${p}a$h" up
  ip -n "${p}$h" link set eth0 up
done

in_a() { ip netns exec "${p}a" "$@"; }
status() { in_a "$bin" status --learner http://127.0.0.1:50051 --token "$token" 2>/dev/null; }
field() { status | awk -v k="$1" '$1 == k { print $2 }'; }
# wait_for SECONDS DESCRIPTION CONDITION...: polls until CONDITION holds.
wait_for() {
  local limit=$1 what=$2
  shift 2
  local end=$((SECONDS + limit))
  until "$@"; do
    if [ $SECONDS -ge $end ]; then
      echo "error: not within ${limit} s: $what (status: $(status | tr '\n' ' '))" >&2
      exit 1
    fi
    sleep 1
  done
}
actors_are() { [ "$(field actors)" = "$1" ]; }
version_at_least() { local v; v=$(field version); [ -n "$v" ] && [ "$v" -ge "$1" ]; }

# The "hosts" are network namespaces on one filesystem; real other machines would not
# see the learner's weights directory, so it is off: every version crosses the links.
ip netns exec "${p}a" "$bin" learner --listen 0.0.0.0:50051 --token "$token" --algo a2c --env angle --dim 4 \
  --steps 1000000000 --actors 16 --out "$tmp/run" --weights-dir none >"$tmp/learner.log" 2>&1 &
pids+=($!)
disown
for h in b c; do
  n=$([ "$h" = b ] && echo 1 || echo 2)
  for i in 1 2 3 4 5 6 7 8; do
    ip netns exec "${p}$h" "$bin" actor --learner "http://10.77.$n.1:50051" --token "$token" \
      --name "$h$i" >"$tmp/actor-$h$i.log" 2>&1 &
    pids+=($!)
    disown
  done
done

wait_for 120 "16 actors registered" actors_are 16
wait_for 120 "20 updates with 16 actors" version_at_least 20
echo "   16 actors on two hosts: version $(field version)"

echo "== cutting host B's link"
ip -n "${p}a" link set "${p}ab" down
t=$SECONDS
wait_for 60 "B's 8 actors dropped" actors_are 8
echo "   the learner dropped B's actors after $((SECONDS - t)) s"
v=$(field version)
wait_for 60 "training going on with C's actors" version_at_least $((v + 20))
echo "   B cut off: 8 actors, version $v -> $(field version)"

echo "== restoring host B's link"
ip -n "${p}a" link set "${p}ab" up
t=$SECONDS
wait_for 90 "B's actors back" actors_are 16
echo "   B's actors registered again after $((SECONDS - t)) s"
v=$(field version)
wait_for 60 "training with all 16 again" version_at_least $((v + 20))
for pid in "${pids[@]}"; do
  kill -0 "$pid" 2>/dev/null || { echo "error: process $pid died" >&2; exit 1; }
done
echo "   B rejoined: 16 actors (the same 16 processes), version $(field version)"
echo "== multi-host test passed"
