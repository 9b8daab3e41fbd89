# Sourced by the scripts here. The device machine has torch+CUDA+Triton but not trimesh and PyMCubes: carry
# `.whl` (their wheels) and `.data/` (the dataset), both made by prepare.sh and git-ignored.
export PYTHONUNBUFFERED=1
DATA=${DATA:-.data/bunny_plastic}
[ -f "$DATA/transforms_train.json" ] || { echo "no dataset at $DATA: run benchmarks/gpu/prepare.sh on the development machine and carry .data and .whl"; exit 1; }
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
fi
export PYTHONPATH=/tmp/site:$PWD/src
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
T0=$(date +%s)
stamp() { echo "== t=$(( $(date +%s) - T0 ))s $*"; }
