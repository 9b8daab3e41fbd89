#!/bin/bash
# One device call (~8 min): the test suite on CUDA (with the tests that need it), then the step's ms and profile
# for the default, train.compile=true and train.amp=true (launch counts for the eager ones: the counter cannot see
# inside compiled graphs), and `anisdf bench --device cuda`. Outputs land in $OUT.
source "$(dirname "$0")/common.sh"
nvidia-smi -L; python3 -c "import torch, triton; print('torch', torch.__version__, 'triton', triton.__version__)"
stamp "tests on CUDA"; timeout 240 python3 -m pytest -q -rs -p no:cacheprovider tests > "$OUT/pytest_cuda.txt" 2>&1; tail -8 "$OUT/pytest_cuda.txt"
stamp "what train.compile fuses"; timeout 60 python3 benchmarks/count_compiled_heads.py --device cuda 2>&1 | tail -4
for v in train.amp=false train.compile=true train.amp=true; do
  stamp "profile nerf-synthetic $v"
  [ "$v" = train.compile=true ] || timeout 60 python3 benchmarks/profile_step.py "$DATA" --device cuda --count --warmup 40 --rows 0 $v
  timeout 110 python3 benchmarks/profile_step.py "$DATA" --device cuda --warmup 40 --steps 60 $v > "$OUT/profile_$v.txt" 2>&1
  head -3 "$OUT/profile_$v.txt" | tail -2; grep "kernel launches" "$OUT/profile_$v.txt"
done
stamp "bench"; timeout 120 python3 -m anisdf.cli bench --device cuda --quick --json --data "$DATA" > "$OUT/bench_quick.json" 2> "$OUT/bench_quick.err"; tail -2 "$OUT/bench_quick.err"
stamp done
