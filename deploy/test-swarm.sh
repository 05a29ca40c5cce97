#!/usr/bin/env bash
# The swarm stack (deploy/stack.yaml) under the engine, end to end: a single-node swarm
# (made here and left at the end, unless this machine was in one already), the image
# built from the static binary, the token as a swarm secret; then 16 actor replicas
# training A2C, and under the engine: actor tasks killed (the engine replaces them),
# the actor service scaled 16 -> 4 -> 24 while training, the learner task killed
# (the engine restarts it; it resumes from its checkpoint volume, the actors come back
# on their own), a rolling update of the actors. Every phase is bounded and says what
# it measured; the stack, its secret, volumes and image go at the end, on failure too.
# Run by .ci/run; alone: deploy/test-swarm.sh
set -euo pipefail
cd "$(dirname "$0")/.."

if ! docker info >/dev/null 2>&1; then
  echo "error: NO DOCKER DAEMON ANSWERS (docker info failed): the swarm test cannot run" >&2
  exit 1
fi

stack=savertest$$
export SAVER_IMAGE=saver:swarm-$$
export SAVER_TOKEN_SECRET=${stack}_token
export SAVER_PORT=${SAVER_TEST_PORT:-$((40000 + $$ % 20000))}
export SAVER_ACTORS=16 SAVER_ALGO=a2c SAVER_STEPS=100000000 SAVER_CHECKPOINT_EVERY=20
bin=target/x86_64-unknown-linux-gnu/release/saver
url=http://127.0.0.1:$SAVER_PORT
tmp=$(mktemp -d)
token=swarm-test-$RANDOM$RANDOM
made_swarm=0

cleanup() {
  status=$?
  if [ "$status" != 0 ]; then
    echo "--- swarm test FAILED; the services and the learner's log tail:" >&2
    docker stack services "$stack" >&2 || true
    docker service logs --tail 40 "${stack}_learner" >&2 || true
  fi
  docker stack rm "$stack" >/dev/null 2>&1 || true
  # The tasks' containers go first; then their volumes and the secret can.
  for _ in $(seq 60); do
    [ -z "$(docker ps -aq --filter "label=com.docker.stack.namespace=$stack")" ] && break
    sleep 1
  done
  docker volume rm "${stack}_run" "${stack}_pcpn" "${stack}_weights" >/dev/null 2>&1 || true
  docker secret rm "$SAVER_TOKEN_SECRET" >/dev/null 2>&1 || true
  docker image rm "$SAVER_IMAGE" >/dev/null 2>&1 || true
  if [ "$made_swarm" = 1 ]; then
    docker swarm leave --force >/dev/null 2>&1 || true
  fi
  rm -rf "$tmp"
}
trap cleanup EXIT

deploy/build-image.sh "$SAVER_IMAGE"
if [ "$(docker info --format '{{.Swarm.LocalNodeState}}')" != active ]; then
  echo "== docker swarm init (a single-node swarm, left at the end)"
  docker swarm init --advertise-addr 127.0.0.1 >/dev/null
  made_swarm=1
fi
printf '%s\n' "$token" | docker secret create "$SAVER_TOKEN_SECRET" - >/dev/null
echo "== docker stack deploy $stack (16 actor replicas, learner published on $SAVER_PORT)"
docker stack deploy -c deploy/stack.yaml --resolve-image never "$stack" >/dev/null

status_field() {
  "$bin" status --learner "$url" --token "$token" 2>/dev/null | awk -v k="$1" '$1 == k { print $2 }'
}
# Waits (at most $1 s) until the learner reports `actors` = $2 and a version above $3;
# prints the seconds it took.
wait_for() {
  local limit=$1 want=$2 above=$3 start=$SECONDS v a
  until v=$(status_field version) && a=$(status_field actors) && [ -n "$v" ] && [ "$v" -gt "$above" ] \
      && [ "$a" = "$want" ]; do
    if [ $((SECONDS - start)) -ge "$limit" ]; then
      echo "error: not $want actors past version $above within $limit s (version ${v:-?}, actors ${a:-?})" >&2
      exit 1
    fi
    sleep 1
  done
  echo $((SECONDS - start))
}
# Steps per second over $1 s.
rate() {
  local s0 s1 t0 t1
  s0=$(status_field steps); t0=$(date +%s.%N)
  sleep "$1"
  s1=$(status_field steps); t1=$(date +%s.%N)
  awk -v a="$s0" -v b="$s1" -v x="$t0" -v y="$t1" 'BEGIN { printf "%.0f", (b - a) / (y - x) }'
}
task_containers() {
  docker ps -q --filter "label=com.docker.swarm.service.name=${stack}_$1"
}

t=$(wait_for 300 16 50 0)
steady=$(rate 20)
echo "   16 replicas registered and 50 updates in $t s; $steady steps/s"
n=$(docker service logs "${stack}_actor" 2>&1 | grep -c "reading weights from the learner's files" || true)
[ "$n" -ge 16 ] || { echo "error: $n of 16 replicas read the shared weights volume" >&2; exit 1; }

echo "== killing 4 actor tasks (the engine replaces them)"
v=$(status_field version)
task_containers actor | head -4 | xargs docker kill >/dev/null
t=$(wait_for 60 16 "$((v + 10))" 0)
echo "   16 actors again and 10 more updates $t s after the kill; $(rate 10) steps/s"

echo "== docker service scale actor 16 -> 4 -> 24 while training"
docker service scale --detach "${stack}_actor=4" >/dev/null
v=$(status_field version)
t=$(wait_for 90 4 "$v" 0)
echo "   4 actors training $t s after scaling down; $(rate 10) steps/s"
docker service scale --detach "${stack}_actor=24" >/dev/null
v=$(status_field version)
t=$(wait_for 90 24 "$v" 0)
echo "   24 actors training $t s after scaling up; $(rate 10) steps/s"

echo "== killing the learner task (the engine restarts it; it resumes from its checkpoint)"
old=$(task_containers learner)
before=$(status_field version)
docker kill "$old" >/dev/null
start=$SECONDS
# A new learner container (the engine's restart), then its first answer.
until new=$(task_containers learner) && [ -n "$new" ] && [ "$new" != "$old" ] \
    && r=$(status_field version) && [ -n "$r" ]; do
  [ $((SECONDS - start)) -ge 120 ] && { echo "error: no new learner answers 120 s after the kill" >&2; exit 1; }
  sleep 0.5
done
up=$((SECONDS - start))
resumed=$(docker logs "$new" 2>&1 | grep -m1 "from its checkpoint" || true)
[ -n "$resumed" ] || { echo "error: the restarted learner did not resume from its checkpoint" >&2; exit 1; }
# Versions go on from the last one published (metrics.csv), never back: none issued
# twice. The same number again only when the kill came right after a checkpoint of it
# (nothing dropped: the same weights).
if [ "$r" -lt "$before" ] || { [ "$r" = "$before" ] && [[ "$resumed" == *dropped* ]]; }; then
  echo "error: version $before before the kill, $r after ($resumed): versions reissued" >&2
  exit 1
fi
t=$(wait_for 120 24 "$r" 0)
echo "   a new container answered $up s after the kill: ${resumed#*resuming }"
echo "   version $before before the kill, $r at its first answer (none reissued); 24 actors training $t s later"

echo "== rolling update of the actor service (4 at a time, start-first)"
v=$(status_field version)
docker service update --detach --force "${stack}_actor" >/dev/null
start=$SECONDS
until [ "$(docker service inspect --format '{{if .UpdateStatus}}{{.UpdateStatus.State}}{{end}}' "${stack}_actor")" = completed ]; do
  [ $((SECONDS - start)) -ge 180 ] && { echo "error: the rolling update did not complete in 180 s" >&2; exit 1; }
  sleep 2
done
t=$(wait_for 60 24 "$v" 0)
echo "   updated in $((SECONDS - start)) s; 24 actors training; $(rate 10) steps/s"
"$bin" weights --learner "$url" --token "$token" --out "$tmp/weights.safetensors"
[ -s "$tmp/weights.safetensors" ] || { echo "error: no weights written" >&2; exit 1; }
echo "== swarm test passed"
