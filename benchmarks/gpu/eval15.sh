#!/bin/bash
# Device call 2 of 2: wait for train15.sh's run to end, then evaluate it on every test view and the mesh.
source "$(dirname "$0")/common.sh"
while [ ! -f runs/gpu15_exit ] && [ $(( $(date +%s) - T0 )) -lt 420 ]; do sleep 10; done
stamp "training exit $(cat runs/gpu15_exit 2>/dev/null)"; tail -5 runs/gpu15_train.log
cp runs/gpu15_train.log runs/gpu15/log.jsonl runs/gpu15/config.yaml "$OUT/" 2>/dev/null
timeout 170 python3 -m anisdf.cli eval runs/gpu15 --gt-mesh "$DATA/gt_mesh.ply" 2>&1 | grep -v "it/s" | tail -20
cp runs/gpu15/eval.json "$OUT/" 2>/dev/null
stamp done
