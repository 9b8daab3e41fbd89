#!/bin/bash
# GPU call 2 of 2026-11-23 (H100): compiled-kernel tests (relaxed GPU tolerance), step profile, cpu-quick bench, short full-preset train + eval
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD/src
T0=$(date +%s)
echo "== pytest"; timeout 100 python3 -m pytest -q -p no:cacheprovider tests/test_hash_encoding_fast.py -k "values_and_gradients or eikonal or table_gradient" 2>&1 | tail -6
echo "== t=$(( $(date +%s)-T0 ))s profile nerf-synthetic"; timeout 100 python3 benchmarks/profile_step.py .data/bunny_plastic --preset nerf-synthetic --device cuda > $OUT/prof_ns.txt 2>&1; head -3 $OUT/prof_ns.txt; grep -A32 "kernel launches" $OUT/prof_ns.txt | cut -c1-60,100-200 | head -32
echo "== t=$(( $(date +%s)-T0 ))s short train"; timeout 100 python3 -m anisdf.cli train .data/bunny_plastic --out runs/short --preset nerf-synthetic --max-minutes 1 --no-progress 2>&1 | tail -4
echo "== t=$(( $(date +%s)-T0 ))s eval"; timeout 80 python3 -m anisdf.cli eval runs/short --gt-mesh .data/bunny_plastic/gt_mesh.ply --max-views 10 2>&1 | tail -12
echo "== t=$(( $(date +%s)-T0 ))s bench cpu-quick"; timeout 170 python3 -m anisdf.cli bench --device cuda --json --data .data/bunny_plastic > $OUT/bench_cpuquick.json 2> $OUT/bench_cpuquick.err; tail -3 $OUT/bench_cpuquick.err; python3 -c "import json;d=json.load(open('$OUT/bench_cpuquick.json'));[print(k, d[k]) for k in ('encoding_fwd_bwd_speedup','train_step_speedup','train_samples_per_s','peak_memory_mb','time_to_psnr')];print(d['train_step'])"
echo "== t=$(( $(date +%s)-T0 ))s done"
