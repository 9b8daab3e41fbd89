#!/bin/bash
# GPU call 3 of 2026-11-23 (H100): the 15-minute nerf-synthetic training on bunny_plastic, detached with setsid
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD/src
rm -rf runs/gpu; mkdir -p runs
setsid nohup bash -c 'python3 -m anisdf.cli train .data/bunny_plastic --out runs/gpu --preset nerf-synthetic --max-minutes 15 --no-progress > runs/gpu_train.log 2>&1; echo $? > runs/gpu_exit' < /dev/null > /dev/null 2>&1 &
T0=$(date +%s)
while [ $(( $(date +%s)-T0 )) -lt 560 ] && [ ! -f runs/gpu_exit ]; do
  sleep 60; echo "t=$(( $(date +%s)-T0 ))s $(tail -c 300 runs/gpu/log.jsonl 2>/dev/null | tail -1 | cut -c1-200)"
done
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv
tail -3 runs/gpu_train.log
