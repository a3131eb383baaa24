#!/usr/bin/env bash
# Time-to-walk: train a config from scratch for at most MINUTES of wall clock (checkpoints
# every 25 iterations), then evaluate every checkpoint in order with
# `rall eval tracking --episodes 128 --seed 777` and print the first that walks: linear
# tracking >= 0.8 and falls < 5%, with its wall time from metrics.csv. The first checkpoint
# that also turns (yaw tracking >= 0.7) is printed too when there is one. Run it from the
# repository root after `cargo build --release`, on a machine with nothing else running
# (the minutes depend on it; the iterations do not: training is deterministic).
#   experiments/time-to-walk.sh [CONFIG] [MINUTES] [RUN_DIR] [extra rall train args...]
#   e.g. experiments/time-to-walk.sh configs/flat.toml 10 runs/ttw
set -u
cfg=${1:-configs/flat.toml}; minutes=${2:-10}; run=${3:-runs/time-to-walk}
shift $(( $# < 3 ? $# : 3 ))
rall=${RALL:-./target/release/rall}
[ -x "$rall" ] || { echo "build first: cargo build --release"; exit 2; }
[ -e "$run" ] && { echo "$run exists: pick a fresh run directory"; exit 2; }
mkdir -p "$(dirname "$run")"
echo "training $cfg for at most $minutes min into $run"
timeout -s INT $((minutes * 60)) "$rall" train --config "$cfg" --run-dir "$run" \
  --save-interval 25 "$@" >"$run.log" 2>&1
echo "training stopped ($(tail -1 "$run.log" | cut -c1-100))"
printf '%-10s %-9s %-9s %-9s %-7s\n' iteration minutes tracking yaw falls%
walks=
for ck in $(ls "$run"/checkpoints/model_*.safetensors | sort); do
  it=$((10#$(basename "$ck" .safetensors | sed 's/model_//')))
  wall=$(awk -F, -v it="$it" 'NR > 1 && $1 == it {print $2}' "$run/metrics.csv")
  out=$("$rall" eval tracking --checkpoint "$ck" --episodes 128 --seed 777 2>&1)
  tr=$(echo "$out" | grep -i 'lin-vel tracking' | grep -oE '[01]\.[0-9]+' | head -1)
  yaw=$(echo "$out" | grep -i 'yaw-rate tracking' | grep -oE '[01]\.[0-9]+' | head -1)
  fall=$(echo "$out" | grep -i 'fall rate' | grep -oE '[0-9]+(\.[0-9]+)?' | head -1)
  min=$(awk -v w="$wall" 'BEGIN {printf "%.1f", w / 60}')
  printf '%-10s %-9s %-9s %-9s %-7s\n' "$it" "$min" "$tr" "$yaw" "$fall"
  if [ -z "$walks" ] && awk -v t="$tr" -v f="$fall" 'BEGIN {exit !(t >= 0.8 && f < 5)}'; then
    walks="iteration $it at $min min ($ck)"
    echo "time-to-walk: $walks"
  fi
  if awk -v t="$tr" -v y="$yaw" -v f="$fall" 'BEGIN {exit !(t >= 0.8 && y >= 0.7 && f < 5)}'; then
    echo "walks and turns: iteration $it at $min min ($ck)"
    exit 0
  fi
done
[ -n "$walks" ] && { echo "no checkpoint turns as well within $minutes min (yaw < 0.7)"; exit 0; }
echo "did not walk within $minutes min"; exit 1
