#!/usr/bin/env bash
# Sample-efficiency trial: trains CONFIG on one thread for at most MAX_IT iterations,
# saving every 25, and evaluates every checkpoint as it appears the way
# experiments/time-to-walk.sh does (`rall eval tracking --episodes 128 --seed 777`).
# Walking = linear tracking >= 0.8, yaw tracking >= MIN_YAW and falls < 5%; MIN_YAW is
# 0.7 (a robot that turns when told to) unless set, and MIN_YAW=0 is the straight-walking
# rule of the trials before yaw was required. Stops training at the first checkpoint that
# walks. Iterations, not minutes, are compared, so trials can run beside other jobs. Training
# is exact for a given thread count only: a 2-thread run of the same seed sums the update's
# gradients in another order and follows another trajectory, so judge a variant on seeds.
#   [MIN_YAW=0.7] experiments/sample-efficiency/walk-trial.sh CONFIG RUN_DIR MAX_IT [extra rall train args...]
set -u
cfg=$1; run=$2; max_it=$3; shift 3
min_yaw=${MIN_YAW:-0.7}
rall=${RALL:-./target/release/rall}
[ -e "$run" ] && { echo "$run exists: pick a fresh run directory"; exit 2; }
"$rall" train --config "$cfg" --run-dir "$run" --save-interval 25 --threads 1 \
  --iterations "$max_it" "$@" >"$run.log" 2>&1 &
train=$!
printf '%-10s %-9s %-9s %-7s\n' iteration tracking yaw falls%
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
  yaw=$(echo "$out" | grep -i 'yaw-rate tracking' | grep -oE '[01]\.[0-9]+' | head -1)
  fall=$(echo "$out" | grep -i 'fall rate' | grep -oE '[0-9]+(\.[0-9]+)?' | head -1)
  printf '%-10s %-9s %-9s %-7s\n' "$next" "$tr" "$yaw" "$fall"
  if awk -v t="$tr" -v y="$yaw" -v m="$min_yaw" -v f="$fall" \
    'BEGIN {exit !(t >= 0.8 && y >= m && f < 5)}'; then
    echo "walks: iteration $next ($ck)"
    kill -INT "$train" 2>/dev/null; wait "$train"
    exit 0
  fi
  next=$((next + 25))
done
wait "$train"
echo "did not walk by iteration $max_it"; exit 1
