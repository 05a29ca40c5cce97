#!/usr/bin/env bash
# Runs one SAVER/A2C variant for several seeds and prints the mean episode length at
# chosen step counts, plus the steps needed to reach a mean length of 50.
#
#   bench/saver_runs.sh NAME STEPS "SEEDS" -- saver train flags...
#   bench/saver_runs.sh adam-d4 1000000 "0 1 2" -- --algo saver --dim 4 --optimizer adam --lr 3e-4
#
# Runs land in results/runs/NAME-seed<S>; a summary line per seed is appended to
# results/summary.csv (name, seed, steps, len@0.5M, len@1M, len@2.56M, steps_to_50, final).
set -euo pipefail
cd "$(dirname "$0")/.."
name=$1 steps=$2 seeds=$3
shift 3
[ "${1:-}" = "--" ] && shift
bin=${SAVER_BIN:-target/release/saver}
[ -x "$bin" ] || cargo build --release
mkdir -p results/runs
[ -f results/summary.csv ] || echo "name,seed,steps,len_0.5M,len_1M,len_2.56M,steps_to_50,final_len,wall_s" > results/summary.csv
for seed in $seeds; do
  out=results/runs/$name-seed$seed
  rm -rf "$out"
  "$bin" train --steps "$steps" --seed "$seed" --out "$out" "$@" > "$out.log" 2>&1 || echo "run $name seed $seed failed: see $out.log"
  [ -f "$out/metrics.csv" ] || continue
  awk -F, -v name="$name" -v seed="$seed" -v steps="$steps" '
    NR == 1 { next }
    { s = $1; m = $5; w = $3 }
    m != "" && s <= 500000 { a = m }
    m != "" && s <= 1000000 { b = m }
    m != "" && s <= 2560000 { c = m }
    m != "" && m < 50 && t == "" && $7 >= 100 { t = s }
    END { printf "%s,%s,%s,%s,%s,%s,%s,%s,%.0f\n", name, seed, steps,
          (steps >= 500000 ? a : ""), (steps >= 1000000 ? b : ""), (steps >= 2560000 ? c : ""),
          (t == "" ? "never" : t), m, w }' "$out/metrics.csv" | tee -a results/summary.csv
done
