#!/bin/bash
# The maze curators' steady training speed at their defaults, as a user runs them: DR (plr.py --replay-prob 0),
# Robust PLR (plr.py) and ACCEL (accel.py), each for a fixed wall time, printing its own progress line every
# 5 updates (steps/s over those 5). Validation, checkpoints and level images are pushed past the run. Robust
# PLR and ACCEL only score new levels until their buffer is half full (update 63), then replay (and edit):
# run them past update 70 to see both phases. Each device flag runs all three; one log per flag in OUT_DIR.
#   bash benchmarks/maze_steady.sh OUT_DIR DR_SECONDS CURATOR_SECONDS --cuda --no-cuda
# On an H200 with 16 cores, 30 and 50 s gave about 60 and 270 updates on the GPU.
set -u
out=$1; dr=$2; curators=$3; shift 3
mkdir -p "$out"
export PYTHONUNBUFFERED=1  # (timeout's signal would lose a buffered log)
for device in "$@"; do
  log="$out/steady_${device#--}.log"
  for spec in "dr:$dr:plr.py --replay-prob 0" "robust_plr:$curators:plr.py" "accel:$curators:accel.py"; do
    IFS=: read -r tag seconds command <<< "$spec"
    echo "=== $tag $device: $command, $seconds s" >> "$log"
    timeout "$seconds" python3 $command --env maze $device --log-interval 5 --eval-interval 1000000 \
      --checkpoint-interval 1000000 --levels-interval 1000000 --total-timesteps 1000000000 >> "$log" 2>&1
  done
done
