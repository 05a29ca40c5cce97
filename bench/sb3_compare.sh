#!/usr/bin/env bash
# Side by side on this machine, in one run: Stable-Baselines3 A2C (CPU torch) on a
# Python transcription of the angle env (bench/sb3_a2c_angle.py) against our
# `saver train --algo a2c` and `--algo saver`, the same number of env steps each, the
# paper's settings (16 envs x 8 steps, 256-128-64, RMSProp, lr 3e-4). Prints env
# steps/s of each and the ratios (goals: our A2C >= 5x SB3, our SAVER >= 1x SB3).
#
#   bench/sb3_compare.sh [STEPS] [DIM]        (defaults: 200000, 4)
#
# SB3 goes into its own virtual environment (target/sb3-venv; PyPI's torch wheel pulls
# the CUDA libraries, ~5 GB, though only the CPU is used). SAVER uses the committed
# PCPN in results/pcpn (pretraining is not timed).
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${1:-200000}
dim=${2:-4}
venv=${SB3_VENV:-target/sb3-venv}
if ! "$venv/bin/python" -c "import stable_baselines3" 2>/dev/null; then
  echo "== installing stable-baselines3 into $venv (minutes; ~5 GB)"
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet --disable-pip-version-check "stable-baselines3==2.9.2"
fi
bin=${SAVER_BIN:-target/release/saver}
[ -x "$bin" ] || cargo build --release
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# "… N steps, U updates in T s of training (X steps/s)…" -> X
rate() { sed -n 's/.* in \([0-9.]*\) s of training (\([0-9]*\) steps\/s).*/\2/p' | head -1; }
len() { sed -n 's/.*mean episode length (last 100): \([0-9.]*\).*/\1/p' | head -1; }

echo "== SB3 A2C, angle d=$dim, $steps steps"
read -r _ _ _ sb3 sb3_len threads < <("$venv/bin/python" bench/sb3_a2c_angle.py --steps "$steps" --dim "$dim")
echo "== saver train --algo a2c"
out=$("$bin" train --algo a2c --dim "$dim" --steps "$steps" --out "$tmp/a2c" 2>/dev/null)
a2c=$(rate <<<"$out"); a2c_len=$(len <<<"$out")
echo "== saver train --algo saver"
out=$("$bin" train --algo saver --dim "$dim" --steps "$steps" --pcpn-dir results/pcpn --out "$tmp/saver" 2>/dev/null)
sv=$(rate <<<"$out"); sv_len=$(len <<<"$out")

printf '\n%-34s %12s %10s %18s\n' "angle d=$dim, $steps steps" "steps/s" "vs SB3" "mean len (last 100)"
printf '%-34s %12.0f %10s %18s\n' "SB3 A2C (torch, $threads)" "$sb3" "1.00" "$sb3_len"
printf '%-34s %12.0f %9.2fx %18s\n' "saver A2C" "$a2c" "$(echo "$a2c / $sb3" | bc -l)" "$a2c_len"
printf '%-34s %12.0f %9.2fx %18s\n' "saver SAVER (default)" "$sv" "$(echo "$sv / $sb3" | bc -l)" "$sv_len"
echo "goals: A2C >= 5x SB3, SAVER >= 1x SB3"
