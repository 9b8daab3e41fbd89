#!/bin/bash
# Run on the development machine before the device call: the GPU image lacks trimesh and PyMCubes, and the call
# carries only the repository. Puts their cp312 wheels in .whl/ and a copy of bunny_plastic in .data/ (both
# git-ignored, ~8 MB together); then call the device with carry [".whl", ".data"] and `bash benchmarks/gpu/check.sh`.
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
src=${1:-../shared/data/bunny_plastic}
[ -f "$src/transforms_train.json" ] || { echo "no NeRF-synthetic dataset at $src"; exit 1; }
rm -rf .data/bunny_plastic .whl; mkdir -p .data .whl
cp -r "$src" .data/bunny_plastic
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .whl trimesh==5.2.0 PyMCubes==0.1.6
ls .whl; du -sh .data .whl
