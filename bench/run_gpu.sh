#!/usr/bin/env bash
# GPU benchmarks and the GPU test pass, for the GPU machine (see ../shared/gpu/README.md).
# Usage: bash bench/run_gpu.sh PHASE OUTDIR   (Warp and the wheels already installed in /root/site)
#   PHASE: step (tests, swept profile, step benchmark) | other (gaussians, metrics, convert,
#          newton) | probe (graph conversion, 200 frames, the issue-12 10 s target) | eval (full
#          evaluation table) | table (conversion table) | soak (10^6 steps, paper scene) |
#          envs (batched envs: tests, the serial / tiled / hybrid searches in the landing window and after it)
set -u
phase=${1:-step}
out=${2:-bench/results}
mkdir -p "$out"
export PYTHONPATH=${PYTHONPATH:-/root/site}
case "$phase" in
step)
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv > "$out/gpu.txt" 2>&1
  DYNMESH_TEST_DEVICES=cuda:0 python3 -m pytest -q -p no:cacheprovider tests/test_kernels.py tests/test_world.py \
      tests/test_swept.py tests/test_render.py tests/test_gaussians.py tests/test_metrics.py tests/test_shared_data.py \
      > "$out/gpu_tests.log" 2>&1
  tail -5 "$out/gpu_tests.log"
  python3 bench/profile_swept.py --device cuda:0 --out "$out/profile_swept_cuda.json" 2>&1 | grep -v "^Module" | tail -14
  python3 bench/bench_step.py --device cuda:0 --out "$out/step_cuda.json" 2>&1 | grep -v "^Module" | tail -50 ;;
other)
  python3 bench/bench_gaussians.py --device cuda:0 --out "$out/gaussians_cuda.json" 2>&1 | grep -v "^Module" | tail -4
  python3 bench/bench_metrics.py --device cuda:0 --out "$out/metrics_cuda.json" 2>&1 | grep -v "^Module" | tail -6
  python3 bench/bench_convert.py --device cuda:0 --out "$out/convert_cuda.json" 2>&1 | grep -v "^Module" | tail -8
  python3 bench/bench_newton.py --device cuda:0 --out "$out/newton_cuda.json" 2>&1 | grep -v "^Module" | tail -8 ;;
probe)
  python3 bench/gpu_probe.py --device cuda:0 --frames 200 --out "$out/graph_probe_cuda_200.json" 2>&1 | grep -v "^Module" | tail -3 ;;
eval)
  timeout 540 python3 -m dynmesh_warp.evaluate ../shared/data/horse_gallop.npz ../shared/data/horse_collapse.npz \
      ../shared/data/pcow.npz --num-frames 200 --frame-order auto --device cuda:0 --no-progress \
      --out "$out/eval" 2>&1 | grep -v "^Module" | tail -40
  tar czf "$out/eval.tgz" -C "$out" eval && rm -rf "$out/eval" ;;
soak)
  # ~9 min at the measured 1,860 steps/s: stopped by the time limit, it writes a checkpoint;
  # run the phase again to continue (--resume) until 10^6 steps are done
  resume=""; [ -f "$out/soak_ck.npz" ] && resume="--resume $out/soak_ck.npz"
  timeout -s TERM 540 python3 bench/soak.py --device cuda:0 --steps 1000000 --scenes paper --check-every 1000 \
      --recycle oldest --checkpoint "$out/soak_ck.npz" $resume --out "$out/soak_cuda.json" 2>&1 | grep -v "^Module" | tail -8 ;;
envs)
  DYNMESH_TEST_DEVICES=cuda:0 python3 -m pytest -q -p no:cacheprovider tests/test_batch.py > "$out/gpu_tests_batch.log" 2>&1
  tail -3 "$out/gpu_tests_batch.log"
  E=1,64,1024,4096,16384,65536
  for search in serial tiled hybrid; do
    python3 bench/bench_envs.py --device cuda:0 --envs $E --warmup 40 --steps 80 --search $search \
        --out "$out/envs_cuda_landing_$search.json" 2>&1 | grep -v "^Module" | tail -7
  done
  for search in serial tiled hybrid; do
    python3 bench/bench_envs.py --device cuda:0 --envs $E --steps 300 --search $search \
        --out "$out/envs_cuda_$search.json" 2>&1 | grep -v "^Module" | tail -7
  done ;;
table)
  python3 bench/conversion_table.py --device cuda:0 --out "$out/conversion_table_cuda.json" 2>&1 | grep -v "^Module" | tail -30 ;;
esac
