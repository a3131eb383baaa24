#!/usr/bin/env bash
# The risk-signal pilot's training runs (results/risk-signal/README.md): RALL with each
# risk design, seeds 1 and 2, 1,500 terrain iterations, checkpoints every 50. Runs
# JOBS at a time (default 2) with one worker thread each; a run that already has a
# checkpoint resumes (exactly) instead of starting again, a finished run is skipped.
#   bash experiments/risk-signal.sh            # all six
#   JOBS=1 bash experiments/risk-signal.sh paper-s1 rare-s2
set -euo pipefail
cd "$(dirname "$0")/.."
RALL="${RALL:-target/release/rall}"
JOBS="${JOBS:-2}"
ITERATIONS=1500
declare -A CONFIG=([paper]=configs/rall.toml [dt-scaled]=configs/rall-dt-scaled.toml [rare]=configs/rall-rare.toml)
runs=("$@")
if [ ${#runs[@]} -eq 0 ]; then
  runs=(paper-s1 dt-scaled-s1 rare-s1 paper-s2 dt-scaled-s2 rare-s2)
fi
mkdir -p runs/risk-signal
one_run() {
  local run="$1" design="${1%-s*}" seed="${1##*-s}" dir="runs/risk-signal/$1"
  local config="${CONFIG[$design]:?unknown design $design (paper, dt-scaled, rare)}"
  if [ -f "$dir/latest.safetensors" ]; then
    "$RALL" train --resume "$dir" --iterations "$ITERATIONS" --threads 1
  else
    "$RALL" train --config "$config" --seed "$seed" --iterations "$ITERATIONS" \
      --run-dir "$dir" --threads 1
  fi >>"runs/risk-signal/$run.log" 2>&1
  echo "$run: exit $? ($(tail -n 2 "runs/risk-signal/$run.log" | head -n 1 | cut -c1-24))"
}
export -f one_run
export RALL ITERATIONS
for run in "${runs[@]}"; do
  echo "$run"
done | xargs -P "$JOBS" -I{} bash -c "$(declare -p CONFIG); one_run {}"
