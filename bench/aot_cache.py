"""Fill a Warp kernel cache with CUDA binaries on a machine without a GPU, to carry to the GPU
machine (whose device time is scarce; Newton's mesh-contact kernel alone takes ~55 s in NVRTC).

    python bench/aot_cache.py --cache /tmp/wcache        # then on the GPU: WARP_CACHE_PATH=/tmp/wcache

Runs bench_newton.py briefly on the CPU, so every module the benchmark loads is registered (with
its generic overloads), then compiles each loaded module for ``--arch`` as CUBIN and as PTX
(Warp picks one by driver) into the cache. Modules whose hash differs on the GPU (CUDA-only
overloads) still compile there. Needs no GPU: Warp's NVRTC runs on the host.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import warp as wp


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", required=True, help="kernel cache directory to fill")
    ap.add_argument("--arch", type=int, default=90, help="SM architecture for the CUBINs (90: H100/H200)")
    ap.add_argument("--ptx-arch", type=int, default=75, help="PTX target (Warp's default)")
    a = ap.parse_args(argv)
    wp.config.kernel_cache_dir = a.cache
    wp.config.quiet = True
    wp.init()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_newton

    bench_newton.main(["--device", "cpu", "--steps", "2", "--repeats", "1", "--warmup", "1",
                       "--settle", "0.01", "--out", str(Path(a.cache) / "bench_newton_cpu.json")])
    from warp._src.context import user_modules

    t0 = time.perf_counter()
    for name, module in list(user_modules.items()):
        if not module.execs:  # not loaded by the run above
            continue
        for use_ptx, arch in ((False, a.arch), (True, a.ptx_arch)):
            wp.compile_aot_module(module, arch=arch, use_ptx=use_ptx)
        print(f"{name}: done at {time.perf_counter() - t0:.1f} s", flush=True)


if __name__ == "__main__":
    main()
