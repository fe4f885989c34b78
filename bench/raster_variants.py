"""The rasterisers of ``choices.Rasteriser`` on the same scene (issue 16: the default density's
per-pixel rasteriser was 0.81 ms of a 1.21 ms render on an H100).

Renders bench_render's random scene (1080p) with one renderer per rasteriser and compares their
images with the per-pixel one's (max |diff|: the shared-memory kernel is meant to be bit-equal).
On CUDA each rasteriser kernel's device time comes from ``wp.timing_begin`` (CUDA events around
each launch, over ``--repeats`` renders); on the CPU the whole render is timed. The session's
probes before the product kernel (two pixels per thread, a spheres-only shared-batch kernel, the
shared kernel with a loop over a block's pixels) were removed once the choice was made; their
figures are in ``raster_variants_cuda*.json`` and docs/rendering.md, their code in the history.

    python bench/raster_variants.py --device cuda --scale 1 0.25 --out bench/results/raster_variants_cuda.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_render import scene  # noqa: E402
from common import describe_device, write_json  # noqa: E402


def main(argv=None):
    from dynmesh_warp.choices import Rasteriser, values
    from dynmesh_warp.render import Renderer, look_at

    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--scale", type=float, nargs="+", default=[1.0, 0.25])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.init()
    device = wp.get_device(a.device)
    rows = []
    for scale in a.scale:
        means, q, scales, covs, sh, op = scene(a.gaussians, 3, scale=scale)
        cam = look_at([2.2, 1.6, 1.2], [0, 0, 0], width=1920, height=1080, fov_y_deg=50)
        args = (wp.array(means, dtype=wp.vec3, device=device), wp.array(covs, dtype=wp.mat33, device=device),
                wp.array(sh, dtype=float, device=device), wp.array(op, dtype=float, device=device), [cam])
        row = {"scale": scale, "variants": {}}
        ref = None
        for name in values(Rasteriser):
            r = Renderer(device, rasteriser=name)
            out = r.render(*args, background=(0, 0, 0))  # warm-up: modules loaded, buffers sized
            got = [out.rgb.numpy().copy(), out.alpha.numpy().copy(), out.depth.numpy().copy()]
            ref = ref if ref is not None else got
            diff = [float(np.abs(g - f).max()) for g, f in zip(got, ref)]
            if device.is_cuda:  # the rasteriser kernel's device time, nothing else
                wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
                for _ in range(a.repeats):
                    r.render(*args, background=(0, 0, 0))
                times = [t.elapsed for t in wp.timing_end() if "raster" in t.name]
                ms = float(np.median(times))
                what = "rasterise kernel, device time"
            else:
                ts = []
                for _ in range(a.repeats):
                    t0 = time.perf_counter()
                    r.render(*args, background=(0, 0, 0))
                    wp.synchronize_device(device)
                    ts.append(time.perf_counter() - t0)
                ms = float(np.median(ts)) * 1e3
                what = "whole render"
            row["variants"][name] = {"ms": ms, "timed": what, "max_abs_diff_rgb_alpha_depth_vs_first": diff}
            print(f"scale {scale} {name}: {ms:.3f} ms ({what}), max |diff| rgb/alpha/depth {diff}", flush=True)
        rows.append(row)
    res = {"machine": describe_device(device), "image": [1920, 1080], "gaussians": a.gaussians, "rows": rows}
    if a.out:
        write_json(a.out, res)


if __name__ == "__main__":
    main()
