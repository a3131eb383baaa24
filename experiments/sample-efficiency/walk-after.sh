#!/usr/bin/env bash
# After a run has trained to MAX_IT with a checkpoint every 25 iterations: its first walking
# checkpoint by the time-to-walk protocol (`rall eval tracking --episodes 128 --seed 777`;
# linear tracking >= 0.8, yaw tracking >= MIN_YAW, falls < 5%), scanning from FROM, and its
# MAX_IT checkpoint on 512 episodes (same seed). MIN_YAW is 0 unless set (straight walking,
# what configs/flat-paper.toml learns); FROM is 450 unless set (no run has walked before 600).
#   [MIN_YAW=0] [FROM=450] experiments/sample-efficiency/walk-after.sh RUN_DIR MAX_IT > RUN_DIR.walk
set -u
run=$1; max_it=$2
min_yaw=${MIN_YAW:-0}; from=${FROM:-450}
rall=${RALL:-./target/release/rall}
ck() { printf '%s/checkpoints/model_%06d.safetensors' "$run" "$1"; }
[ -e "$(ck "$max_it")" ] || { echo "$(ck "$max_it") missing: train to $max_it first"; exit 2; }
echo "iteration tracking yaw falls%"
for it in $(seq "$from" 25 "$max_it"); do
  out=$("$rall" eval tracking --checkpoint "$(ck "$it")" --episodes 128 --seed 777 --threads 1 2>&1)
  tr=$(echo "$out" | grep -i 'lin-vel tracking' | grep -oE '[01]\.[0-9]+' | head -1)
  yaw=$(echo "$out" | grep -i 'yaw-rate tracking' | grep -oE '[01]\.[0-9]+' | head -1)
  fall=$(echo "$out" | grep -i 'fall rate' | grep -oE '[0-9]+(\.[0-9]+)?' | head -1)
  echo "$it $tr $yaw $fall"
  if awk -v t="$tr" -v y="$yaw" -v m="$min_yaw" -v f="$fall" \
    'BEGIN {exit !(t >= 0.8 && y >= m && f < 5)}'; then
    echo "walks: $it"; break
  fi
done
"$rall" eval tracking --checkpoint "$(ck "$max_it")" --episodes 512 --seed 777 --threads 1 2>&1
