#!/bin/bash
# GPU call 4 of 2026-11-23 (H100): wait for the training of call 3, then evaluate it
export PYTHONUNBUFFERED=1
export PYTHONPATH=/tmp/site:$PWD/src
T0=$(date +%s)
while [ ! -f runs/gpu_exit ] && [ $(( $(date +%s)-T0 )) -lt 420 ]; do sleep 10; done
echo "training exit $(cat runs/gpu_exit 2>/dev/null) after waiting $(( $(date +%s)-T0 ))s"; tail -12 runs/gpu_train.log
cp runs/gpu_train.log runs/gpu/log.jsonl runs/gpu/config.yaml $OUT/ 2>/dev/null
timeout 170 python3 -m anisdf.cli eval runs/gpu --gt-mesh .data/bunny_plastic/gt_mesh.ply 2>&1 | grep -v "it/s\|view/s\|chunk/s" | tail -25
cp runs/gpu/eval.json $OUT/ 2>/dev/null; cp runs/gpu/eval/000.png $OUT/eval_000.png 2>/dev/null; ls runs/gpu
echo "t=$(( $(date +%s)-T0 ))s done"
