#!/bin/bash
# Device call 1 of 2: the nerf-synthetic preset for 15 minutes in its own process session (a call lasts at most
# 10 minutes; the training outlives it). Follow with eval15.sh in the very next call. Config overrides chosen from
# check.sh's numbers go in EXTRA, e.g. `EXTRA=train.compile=true bash benchmarks/gpu/train15.sh`.
source "$(dirname "$0")/common.sh"
rm -rf runs/gpu15 runs/gpu15_exit; mkdir -p runs
setsid nohup bash -c "python3 -m anisdf.cli train $DATA --out runs/gpu15 --preset nerf-synthetic --max-minutes 15 \
  --no-progress ${EXTRA:-} > runs/gpu15_train.log 2>&1; echo \$? > runs/gpu15_exit" < /dev/null > /dev/null 2>&1 &
while [ $(( $(date +%s) - T0 )) -lt 540 ] && [ ! -f runs/gpu15_exit ]; do
  sleep 60; stamp "$(tail -1 runs/gpu15/log.jsonl 2>/dev/null | cut -c1-160)"
done
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv
