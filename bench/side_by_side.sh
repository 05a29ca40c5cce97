#!/bin/bash
# The side-by-side of issue 55 on Reacher-v5 (or FACTORY's env), one run of each per seed at equal env
# steps, every one evaluated the same way (50 deterministic episodes, success and the
# env's own return; saver_actor.evaluate.scored_episodes), with curves:
#   saver      SAVER at its custom-env default
#   ppo-tuned  our PPO at RL Zoo's tuned Reacher settings (VecNormalize's obs and
#              reward normalisation, n_steps 512 x 8 envs, batch 32, 5 epochs, γ 0.9,
#              λ 1, lr 1.04e-4, clip 0.3, vf 0.95, grad norm 0.9, 64-64) on the env's reward,
#              its episodes going on past success as the peers' do
#   a2c        our A2C at its custom-env default
#   sb3-ppo    Stable-Baselines3 PPO at the same RL Zoo settings (bench/sb3_tuned.py)
#   sb3-sac    Stable-Baselines3 SAC at its defaults
# then the table and the figure (bench/env_return_table.py).
#
#   bench/side_by_side.sh OUT STEPS SEED...      e.g. bench/side_by_side.sh R 1000000 0 1 2 3 4
# SAVER_PY: a Python with saver_actor, gymnasium[mujoco] and matplotlib (default python3);
# SB3_PY: one with stable-baselines3, rl_zoo3 and saver_actor (unset: no SB3 rows);
# FACTORY, MAX_STEPS: another env of saver_actor's kind and its episode length
# (default saver_actor.examples:reacher, 50; the point mass: saver_actor.examples:pointmass, 200);
# ONLY: a space-separated subset of the rows above. Each row's JSON lines go to
# OUT/<row>.jsonl (appended), its run folders under OUT/<row>/.
# BUDGETS: env-step budgets (e.g. "20000 30000 50000") at which each of our rows also runs
# whole runs of its own (SAVER's rate decays over the run, so a run of N steps is not step
# N of a longer one) into OUT/<row>-budgets.jsonl, and the SB3 PPO rows once more with the
# rate falling to 0 over each budget (sb3-ppo-lr-decay.jsonl); then bench/budget_table.py
# over every file (a run's end is its budget; SB3's constant-rate evaluations are budgets too).
set -euo pipefail
out=$1; steps=$2; shift 2; seeds=("$@")
[ ${#seeds[@]} -gt 0 ] || { echo "usage: $0 OUT STEPS SEED..." >&2; exit 2; }
here=$(cd "$(dirname "$0")" && pwd); root=$(dirname "$here")
saver=${SAVER_BIN:-$root/target/release/saver}
py=${SAVER_PY:-python3}
only=${ONLY:-saver ppo-tuned a2c sb3-ppo sb3-sac}
factory=${FACTORY:-saver_actor.examples:reacher}
max_steps=${MAX_STEPS:-50}
curve=$(( steps / 10 ))
mkdir -p "$out"
export MUJOCO_GL=${MUJOCO_GL:-egl}
ppo_tuned="ppo --rollout 512 --ppo-minibatch-size 32 --ppo-epochs 5 --gamma 0.9 --lr 1.04e-4 \
--entropy-coef 7.5e-8 --ppo-clip 0.3 --gae-lambda 1.0 --grad-clip 0.9 --value-coef 0.95 \
--ppo-obs-norm true --ppo-reward-norm true --ppo-env-reward true --hidden 64 --hidden 64 \
--continue-past-success true"
budgets=${BUDGETS:-}
ours() { # row, algo and flags
  local row=$1 algo=$2
  echo "== $row: $steps steps, seeds ${seeds[*]} -> $out/$row.jsonl"
  "$py" "$here/custom_env_results.py" "$saver" --factory "$factory" --max-steps "$max_steps" \
    --steps "$steps" --seeds "${seeds[@]}" --algos "$algo" --curve-every "$curve" --out "$out/$row" \
    | grep '^{' >> "$out/$row.jsonl"
  for n in $budgets; do
    echo "== $row: a budget of $n steps, seeds ${seeds[*]} -> $out/$row-budgets.jsonl"
    "$py" "$here/custom_env_results.py" "$saver" --factory "$factory" --max-steps "$max_steps" \
      --steps "$n" --seeds "${seeds[@]}" --algos "$algo" --out "$out/$row" --tag="-budget$n" \
      | grep '^{' >> "$out/$row-budgets.jsonl"
  done
}
peer() { # row, sb3_tuned.py algorithm
  local row=$1 algo=$2
  if [ -z "${SB3_PY:-}" ]; then echo "== $row: skipped (set SB3_PY to a Python with stable-baselines3)"; return; fi
  for seed in "${seeds[@]}"; do
    echo "== $row seed $seed: $steps steps -> $out/$row.jsonl"
    "$SB3_PY" "$here/sb3_tuned.py" "$algo" --steps "$steps" --seed "$seed" --eval-every "$curve" \
      --factory "$factory" --max-steps "$max_steps" >> "$out/$row.jsonl"
    if [ "$algo" = ppo-zoo ]; then
      for n in $budgets; do
        echo "== $row seed $seed: a budget of $n steps, the rate decaying -> $out/$row-lr-decay.jsonl"
        "$SB3_PY" "$here/sb3_tuned.py" "$algo" --lr-decay --steps "$n" --seed "$seed" --eval-every 1000000000 \
          --factory "$factory" --max-steps "$max_steps" >> "$out/$row-lr-decay.jsonl"
      done
    fi
  done
}
for row in $only; do
  case $row in
    saver) ours saver saver ;;
    ppo-tuned) ours ppo-tuned "$ppo_tuned" ;;
    a2c) ours a2c a2c ;;
    sb3-ppo) peer sb3-ppo ppo-zoo ;;
    sb3-sac) peer sb3-sac sac ;;
    *) echo "unknown row $row" >&2; exit 2 ;;
  esac
done
shopt -s nullglob
curves=()
for f in "$out"/*.jsonl; do
  case $f in *-budgets.jsonl|*-lr-decay.jsonl) ;; *) curves+=("$f") ;; esac
done
rm -f "$out/curves.png"
"$py" "$here/env_return_table.py" "${curves[@]}" --png "$out/curves.png"  # says why where no figure
[ -z "$budgets" ] || "$py" "$here/budget_table.py" "$out"/*.jsonl
figure=""; [ ! -f "$out/curves.png" ] || figure="; figure: $out/curves.png"
echo "tables above$figure; runs: $out/"
