#!/usr/bin/env bash
# The risk-signal pilot's training runs (results/risk-signal/README.md): RALL with each
# risk design, seeds 1 and 2, 1,500 terrain iterations, checkpoints every 50. Runs
# JOBS at a time (default 2) with one worker thread each; a run that already has a
# checkpoint resumes (exactly) instead of starting again, a finished run is skipped.
# A finished run ships without its resume state (only its checkpoints 1100-1500).
#   bash experiments/risk-signal.sh            # all six
#   JOBS=1 bash experiments/risk-signal.sh paper-s1 rare-s2
#   bash experiments/risk-signal.sh --ship     # each run's state (and its checkpoints 1100-1500,
#                                              # actor-only) to policies/risk-signal
# A run missing from runs/risk-signal starts from its copy in policies/risk-signal.
set -euo pipefail
cd "$(dirname "$0")/.."
RALL="${RALL:-target/release/rall}"
JOBS="${JOBS:-2}"
ITERATIONS=1500
declare -A CONFIG=([paper]=configs/rall-paper-weights.toml [dt-scaled]=configs/rall.toml [rare]=configs/rall-rare.toml)
SHIPPED=policies/risk-signal
if [ "${1:-}" = "--ship" ]; then
  for dir in runs/risk-signal/*/; do
    run="$(basename "$dir")"
    [ -f "$dir/latest.safetensors" ] || continue
    mkdir -p "$SHIPPED/$run"
    for f in latest.safetensors config.toml metrics.csv; do
      cp "$dir/$f" "$SHIPPED/$run/$f.tmp" && mv "$SHIPPED/$run/$f.tmp" "$SHIPPED/$run/$f"
    done
    # a finished run needs no resume state: its checkpoints below are what is judged
    if [ -f "$dir/checkpoints/model_$(printf '%06d' "$ITERATIONS").safetensors" ]; then
      rm -f "$SHIPPED/$run/latest.safetensors"
    fi
    # the five checkpoints the pilot judges a run on, actor-only (evaluation needs no more)
    for it in 1100 1200 1300 1400 1500; do
      ckpt="$(printf '%s/checkpoints/model_%06d.safetensors' "$dir" "$it")"
      copy="$SHIPPED/$run/checkpoints/$(basename "$ckpt")"
      if [ -f "$ckpt" ] && [ ! -f "$copy" ]; then
        mkdir -p "$SHIPPED/$run/checkpoints"
        "$RALL" checkpoint actor-only --checkpoint "$ckpt" --out "$copy" >/dev/null
      fi
    done
    echo "shipped $run ($(tail -n 1 "$dir/metrics.csv" | cut -d, -f1) iterations) to $SHIPPED/$run"
  done
  exit 0
fi
runs=("$@")
if [ ${#runs[@]} -eq 0 ]; then
  runs=(paper-s1 dt-scaled-s1 rare-s1 paper-s2 dt-scaled-s2 rare-s2)
fi
mkdir -p runs/risk-signal
one_run() {
  local run="$1" design="${1%-s*}" seed="${1##*-s}" dir="runs/risk-signal/$1"
  local config="${CONFIG[$design]:?unknown design $design (paper, dt-scaled, rare)}"
  local last; last="checkpoints/model_$(printf '%06d' "$ITERATIONS").safetensors"
  if [ -f "$dir/$last" ] || [ -f "$SHIPPED/$run/$last" ]; then
    echo "$run: finished ($ITERATIONS iterations), skipped"
    return 0
  fi
  if [ ! -f "$dir/latest.safetensors" ] && [ -f "$SHIPPED/$run/latest.safetensors" ]; then
    mkdir -p "$dir" && cp "$SHIPPED/$run/"{latest.safetensors,config.toml,metrics.csv} "$dir/"
  fi
  if [ -f "$dir/latest.safetensors" ]; then
    "$RALL" train --resume "$dir" --iterations "$ITERATIONS" --threads 1
  else
    "$RALL" train --config "$config" --seed "$seed" --iterations "$ITERATIONS" \
      --run-dir "$dir" --threads 1
  fi >>"runs/risk-signal/$run.log" 2>&1
  echo "$run: exit $? ($(tail -n 2 "runs/risk-signal/$run.log" | head -n 1 | cut -c1-24))"
}
export -f one_run
export RALL ITERATIONS SHIPPED
for run in "${runs[@]}"; do
  echo "$run"
done | xargs -P "$JOBS" -I{} bash -c "$(declare -p CONFIG); one_run {}"
