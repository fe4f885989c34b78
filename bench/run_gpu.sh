#!/usr/bin/env bash
# All GPU benchmarks and the GPU test pass, for the GPU machine (see ../shared/gpu/README.md).
# Usage: bash bench/run_gpu.sh OUTDIR     (Warp and the wheels in .gpu/ already installed)
set -u
out=${1:-bench/results}
mkdir -p "$out"
export PYTHONPATH=${PYTHONPATH:-/root/site}
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv > "$out/gpu.txt" 2>&1
{
  echo "== GPU test pass (DYNMESH_TEST_DEVICE=cuda:0)"
  DYNMESH_TEST_DEVICE=cuda:0 python3 -m pytest -q -p no:cacheprovider tests/test_kernels.py tests/test_world.py \
      tests/test_swept.py tests/test_gaussians.py tests/test_metrics.py tests/test_shared_data.py 2>&1 | tail -15
} > "$out/gpu_tests.log" 2>&1
python3 bench/bench_step.py --device cuda:0 --out "$out/step_cuda.json" 2>&1 | grep -v "^Module" | tail -60
python3 bench/bench_gaussians.py --device cuda:0 --out "$out/gaussians_cuda.json" 2>&1 | grep -v "^Module" | tail -8
python3 bench/bench_metrics.py --device cuda:0 --out "$out/metrics_cuda.json" 2>&1 | grep -v "^Module" | tail -8
python3 bench/bench_convert.py --device cuda:0 --out "$out/convert_cuda.json" 2>&1 | grep -v "^Module" | tail -8
python3 bench/bench_newton.py --device cuda:0 --out "$out/newton_cuda.json" 2>&1 | grep -v "^Module" | tail -8
cat "$out/gpu_tests.log"
