#!/bin/bash
# The whole GPU check in one device call of about 8 minutes, sized for a 15-minute lease (machine start included):
#   1. the tests that exercise CUDA: kernels, the two `needs CUDA` tests, closed-form normals, compiled vs eager;
#   2. what train.compile fuses on CUDA, and ms/step of the nerf-synthetic step eager and compiled (profile_step);
#   3. up to 3 minutes of the real nerf-synthetic schedule with the faster of the two (as long as the call's 10
#      minutes allow), and the projected time of all 20k steps (project.py; a 15-minute run does not fit the lease).
# First, on the development machine: `bash benchmarks/gpu/prepare.sh`; then run this with carry [".whl", ".data"].
# Outputs land in $OUT (at most 8 files come back).
# Dry run of the script's logic on a CPU: `DEV=cpu WARMUP=2 STEPS=2 SLICE_MINUTES=0.5 bash benchmarks/gpu/check.sh`.
source "$(dirname "$0")/common.sh"
DEV=${DEV:-cuda} WARMUP=${WARMUP:-40} STEPS=${STEPS:-60}
nvidia-smi -L; python3 -c "import torch, triton; print('torch', torch.__version__, 'triton', triton.__version__)"
stamp "tests on CUDA"
timeout 180 python3 -m pytest -rs -p no:cacheprovider tests/test_hash_encoding_fast.py tests/test_data_rays.py \
  tests/test_model_components.py "tests/test_training.py::test_compiled_heads_give_the_eager_gradients[cuda]" \
  > "$OUT/pytest_cuda.txt" 2>&1; tail -6 "$OUT/pytest_cuda.txt"
stamp "what train.compile fuses"; timeout 60 python3 benchmarks/compiled_kernel_count.py --device "$DEV" 2>&1 | tail -4
best=eager; best_ms=1e9
for v in eager compiled; do
  stamp "profile nerf-synthetic, $v"
  timeout 100 python3 benchmarks/profile_step.py "$DATA" --device "$DEV" --warmup "$WARMUP" --steps "$STEPS" --profile 3 \
    train.compile=$([ $v = compiled ] && echo true || echo false) > "$OUT/profile_$v.txt" 2>&1
  grep -E "ms/step|kernel launches|WARNING|Error" "$OUT/profile_$v.txt" | head -4
  ms=$(grep -oE "[0-9.]+ ms/step" "$OUT/profile_$v.txt" | cut -d' ' -f1)
  [ -n "$ms" ] && python3 -c "import sys; sys.exit(not $ms < $best_ms)" && best=$v && best_ms=$ms
done
left=$(( 570 - $(date +%s) + T0 ))  # seconds to the call's end, less a margin for the copies and the projection
: "${SLICE_MINUTES:=$(python3 -c "print(round(min(3.0, max(0.5, ($left - 45) / 60)), 1))")}"
stamp "$SLICE_MINUTES minutes of the nerf-synthetic schedule, $best ($best_ms ms/step in the profile)"
rm -rf runs/slice
timeout $(( left > 60 ? left - 5 : 55 )) python3 -m anisdf train "$DATA" --out runs/slice --preset nerf-synthetic --device "$DEV" \
  --max-minutes "$SLICE_MINUTES" --no-progress train.compile=$([ $best = compiled ] && echo true || echo false) \
  > "$OUT/slice_train.txt" 2>&1; tail -3 "$OUT/slice_train.txt"
cp runs/slice/log.jsonl "$OUT/slice_log.jsonl" 2>/dev/null
python3 benchmarks/gpu/project.py runs/slice/log.jsonl
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv
stamp done
