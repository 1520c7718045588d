#!/usr/bin/env bash
# On a CUDA machine without network (the lent device): build gsplat 1.5.3 from the sdist in .whl/splats/,
# install the wheels that image lacks (pydantic and its deps), run the GPU tests and the GPU benchmark on a
# scene prepared beforehand with `python -m benchmarks.gpu_step --prepare .gpu/scene.npz`.
set -uo pipefail
REPO=$(pwd)
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} CUDA_HOME=/usr/local/cuda
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
(cd /tmp && tar xzf "$REPO/.whl/splats/gsplat-1.5.3.tar.gz" && cd gsplat-1.5.3 &&
  python3 -m pip install -q --no-build-isolation --no-deps --no-index --target /tmp/site . > "$OUT/build.log" 2>&1)
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site "$REPO"/.whl/splats/wheels/*.whl
export PYTHONPATH=/tmp/site:$REPO
python3 -m pytest -q --noconftest -p no:cacheprovider tests/test_splats_gpu.py 2>&1 | tail -4
python3 -m benchmarks.gpu_step --data .gpu/scene.npz --variants "${@:-rgb+depth+normal}" 2>&1 | tee "$OUT/gpu_step.log" | tail -4
