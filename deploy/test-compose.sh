#!/usr/bin/env bash
# The compose stack, end to end: builds the image, brings up deploy/compose.yaml with
# 16 actors under a project name of its own, waits (bounded) until the learner reports
# at least 50 updates with 16 actors registered, fetches the weights from the host with
# `saver weights`, and takes everything down with its volumes, on failure too.
# Run by .ci/run; alone: deploy/test-compose.sh
set -euo pipefail
cd "$(dirname "$0")/.."

if ! docker info >/dev/null 2>&1; then
  echo "error: NO DOCKER DAEMON ANSWERS (docker info failed): the compose test cannot run" >&2
  exit 1
fi
if docker compose version >/dev/null 2>&1; then
  dc=(docker compose)
elif command -v docker-compose >/dev/null 2>&1; then
  dc=(docker-compose)
else
  echo "error: neither 'docker compose' nor 'docker-compose' is installed" >&2
  exit 1
fi

project=saver-test-$$
export SAVER_IMAGE=saver:test-$$
export SAVER_TOKEN=compose-test-$RANDOM$RANDOM
export SAVER_PORT=${SAVER_TEST_PORT:-$((40000 + $$ % 20000))}
export SAVER_METRICS_PORT=$((SAVER_PORT + 1)) SAVER_PCPN_METRICS_PORT=$((SAVER_PORT + 2))
export SAVER_BIND=127.0.0.1 SAVER_ACTORS=16 SAVER_ALGO=a2c SAVER_STEPS=100000000
compose() { "${dc[@]}" -p "$project" -f deploy/compose.yaml "$@"; }
bin=target/x86_64-unknown-linux-gnu/release/saver
tmp=$(mktemp -d)

cleanup() {
  status=$?
  if [ "$status" != 0 ]; then
    echo "--- compose test FAILED; the learner's log tail:" >&2
    compose logs --tail 30 learner >&2 || true
    compose ps >&2 || true
  fi
  compose down -v --remove-orphans --timeout 20 >/dev/null 2>&1 || true
  docker image rm "$SAVER_IMAGE" >/dev/null 2>&1 || true
  rm -rf "$tmp"
}
trap cleanup EXIT

deploy/build-image.sh "$SAVER_IMAGE"
echo "== docker compose up ($project, 16 actors, learner on 127.0.0.1:$SAVER_PORT)"
compose up -d
url=http://127.0.0.1:$SAVER_PORT
field() { "$bin" status --learner "$url" 2>/dev/null | awk -v k="$1" '$1 == k { print $2 }'; }
end=$((SECONDS + 300))
until v=$(field version) && a=$(field actors) && [ -n "$v" ] && [ "$v" -ge 50 ] && [ "$a" = 16 ]; do
  if [ $SECONDS -ge $end ]; then
    echo "error: no 50 updates with 16 actors within 300 s (version ${v:-?}, actors ${a:-?})" >&2
    exit 1
  fi
  sleep 2
done
echo "   learner at version $v with $a actors"
s0=$(field steps); t0=$(date +%s.%N); sleep 20; s1=$(field steps); t1=$(date +%s.%N)
echo "   $(awk -v a="$s0" -v b="$s1" -v x="$t0" -v y="$t1" 'BEGIN { printf "%.0f", (b - a) / (y - x) }') steps/s with 16 actors (compare deploy/test-swarm.sh's)"
n=$(compose logs actor 2>/dev/null | grep -c "reading weights from the learner's files" || true)
[ "$n" -ge 16 ] || { echo "error: $n of 16 actors read the shared weights volume" >&2; exit 1; }
echo "   $n actor registrations read the weights from the shared volume"
"$bin" weights --learner "$url" --out "$tmp/weights.safetensors"
[ -s "$tmp/weights.safetensors" ] || { echo "error: no weights written" >&2; exit 1; }
# Prometheus, as a scraper sees it from the host (bash's /dev/tcp: no curl needed).
scrape() {
  exec 3<>"/dev/tcp/127.0.0.1/$1"
  printf 'GET /metrics HTTP/1.1\r\nHost: saver\r\nAuthorization: Bearer %s\r\n\r\n' "$SAVER_TOKEN" >&3
  cat <&3
  exec 3<&-
}
streaming=$(scrape "$SAVER_METRICS_PORT" | awk '$1 == "saver_actors_streaming" { print $2 }')
[ "$streaming" = 16 ] || { echo "error: metrics say ${streaming:-no} actors streaming, not 16" >&2; exit 1; }
echo "   Prometheus metrics at 127.0.0.1:$SAVER_METRICS_PORT: 16 actors streaming"
echo "== compose test passed"
