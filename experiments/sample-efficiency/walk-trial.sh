#!/usr/bin/env bash
# Sample-efficiency trial: trains CONFIG on one thread for at most MAX_IT iterations,
# saving every 25, and evaluates every checkpoint as it appears the way
# experiments/time-to-walk.sh does (`rall eval tracking --episodes 128 --seed 777`,
# walking = linear tracking >= 0.8 and falls < 5%). Stops training at the first
# checkpoint that walks. Iterations, not minutes, are compared: training is
# deterministic across thread counts, so a 1-thread run makes the iterations a
# 2-thread run would.
#   experiments/sample-efficiency/walk-trial.sh CONFIG RUN_DIR MAX_IT [extra rall train args...]
set -u
cfg=$1; run=$2; max_it=$3; shift 3
rall=./target/release/rall
[ -e "$run" ] && { echo "$run exists: pick a fresh run directory"; exit 2; }
"$rall" train --config "$cfg" --run-dir "$run" --save-interval 25 --threads 1 \
  --iterations "$max_it" "$@" >"$run.log" 2>&1 &
train=$!
printf '%-10s %-9s %-7s\n' iteration tracking falls%
next=25
while [ "$next" -le "$max_it" ]; do
  ck=$(printf '%s/checkpoints/model_%06d.safetensors' "$run" "$next")
  if [ ! -e "$ck" ]; then
    kill -0 "$train" 2>/dev/null || { echo "training ended before iteration $next"; exit 1; }
    sleep 5; continue
  fi
  sleep 1 # the checkpoint is renamed into place whole; give the log a moment
  out=$("$rall" eval tracking --checkpoint "$ck" --episodes 128 --seed 777 --threads 1 2>&1)
  tr=$(echo "$out" | grep -i 'lin-vel tracking' | grep -oE '[01]\.[0-9]+' | head -1)
  fall=$(echo "$out" | grep -i 'fall rate' | grep -oE '[0-9]+(\.[0-9]+)?' | head -1)
  printf '%-10s %-9s %-7s\n' "$next" "$tr" "$fall"
  if awk -v t="$tr" -v f="$fall" 'BEGIN {exit !(t >= 0.8 && f < 5)}'; then
    echo "walks: iteration $next ($ck)"
    kill -INT "$train" 2>/dev/null; wait "$train"
    exit 0
  fi
  next=$((next + 25))
done
wait "$train"
echo "did not walk by iteration $max_it"; exit 1
