#!/bin/bash
# GPU call 1 of 2026-11-23 (H100): environment, compiled-kernel tests, encoding bench, step profile, cpu-quick bench
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD/src
nvidia-smi -L; nproc
python3 -c "import torch, triton; print('torch', torch.__version__, 'triton', triton.__version__, torch.cuda.get_device_name())"
T0=$(date +%s)
echo "== pytest fast kernels (compiled)"; timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_hash_encoding_fast.py 2>&1 | tail -15
echo "== t=$(( $(date +%s)-T0 ))s encoding bench"; timeout 90 python3 -m anisdf.benchmarks.encoding --device cuda --points 262144 2>&1 | tee $OUT/enc.txt
echo "== t=$(( $(date +%s)-T0 ))s profile nerf-synthetic"; timeout 120 python3 benchmarks/profile_step.py .data/bunny_plastic --preset nerf-synthetic --device cuda > $OUT/prof_ns.txt 2>&1; head -5 $OUT/prof_ns.txt; grep -A40 "kernel launches" $OUT/prof_ns.txt | head -40
echo "== t=$(( $(date +%s)-T0 ))s bench cpu-quick (time to psnr)"; timeout 200 python3 -m anisdf.cli bench --device cuda --json --data .data/bunny_plastic > $OUT/bench_cpuquick.json 2> $OUT/bench_cpuquick.err; tail -3 $OUT/bench_cpuquick.err; python3 -c "import json;d=json.load(open('$OUT/bench_cpuquick.json'));[print(k, d[k]) for k in ('encoding_fwd_bwd_speedup','train_step_speedup','train_samples_per_s','peak_memory_mb','time_to_psnr')]"
echo "== t=$(( $(date +%s)-T0 ))s done"
