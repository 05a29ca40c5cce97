#!/usr/bin/env bash
# Our PPO against Stable-Baselines3's on a custom env, side by side in one run, at equal
# env steps (issue 32): ours as a user runs it (a `saver learner --algo ppo`, two
# `saver-actor act` processes of 4 envs each: bench/custom_env_results.py), SB3's PPO with
# its defaults on 8 envs in one process (bench/sb3_custom.py, torch on one thread). Both
# are evaluated the same way (50 deterministic episodes). Prints each one's training
# wall seconds, return and success, and the wall-clock ratio.
#
#   bench/ppo_vs_sb3.sh [STEPS] [SEED] [FACTORY] [MAX_STEPS] [FLAGS]
#       (defaults: 1000000, 0, saver_actor.examples:reacher, 50, none)
#
# FLAGS go to our learner, e.g. "--hidden 64,64" for SB3's network size.
#
# Needs the CI venv (.ci/venv: gymnasium[mujoco], stable-baselines3, ./python) and
# target/release/saver. Run it on an idle machine: the ratio is of wall clocks.
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${1:-1000000}
seed=${2:-0}
factory=${3:-saver_actor.examples:reacher}
max_steps=${4:-50}
flags=${5:-}
py=${PYTHON:-.ci/venv/bin/python}
bin=${SAVER_BIN:-target/release/saver}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

echo "== ours: saver learner --algo ppo $flags, $steps steps, seed $seed ($factory)" >&2
ours=$("$py" bench/custom_env_results.py "$bin" --factory "$factory" --steps "$steps" --seeds "$seed" \
  --algos ppo --extra "$flags" --max-steps "$max_steps" --out "$tmp" 2>/dev/null | grep '^{')
echo "== SB3 PPO, $steps steps, seed $seed" >&2
sb3=$("$py" bench/sb3_custom.py ppo --factory "$factory" --steps "$steps" --seed "$seed" --max-steps "$max_steps")
"$py" - "$ours" "$sb3" <<'EOF'
import json, sys
ours, sb3 = (json.loads(a) for a in sys.argv[1:3])
print(f"\n{ours['env']}, {ours['steps']} steps, seed {ours['seed']}, our flags: {ours['extra'] or 'none'}")
print(f"{'':<10} {'wall s':>8} {'return':>9} {'success':>8}")
for name, r in (("ours", ours), ("SB3", sb3)):
    t = r["trained"]
    print(f"{name:<10} {r['wall_s']:>8.1f} {t['return']:>9.2f} {t['success']:>8.2f}")
print(f"ours is {sb3['wall_s'] / ours['wall_s']:.2f}x faster in wall clock (issue 32's target: 5x)")
EOF
