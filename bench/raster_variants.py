"""Rasteriser variants timed on the same sorted splats (issue 16: the default density's
rasteriser is 0.81 ms of a 1.21 ms render on an H100).

Renders bench_render's random scene once (exact, 1080p) to fill the renderer's sorted-splat
buffers, then times each candidate rasterise kernel alone, replayed from a CUDA graph of
``--launches`` launches, and compares its images with the per-pixel kernel's (max |diff|):
``current`` (the per-pixel kernel, the CPU's), ``two_pixels`` (two pixels per thread, rejected)
and ``product_shared`` (the shared-memory kernel, CUDA's default). The session's other probes
(a spheres-only shared-batch kernel, the shared kernel with and without the loop over a block's
pixels) were removed once chosen; their figures are in ``raster_variants_cuda*.json`` and
docs/rendering.md, their code in the history.

    python bench/raster_variants.py --device cuda --scale 1 --out bench/results/raster_variants_cuda.json
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

from kernels.render import (  # noqa: E402
    NO_HIT,
    TILE,
    occluder_at_pixel,
    rasterize_gaussians,
    RASTERIZE_SHARED,
)

wp.set_module_options({"fast_math": True})  # as kernels/render.py

@wp.kernel
def rasterize_pairs(
    sorted_xy_opacity_depth: wp.array[wp.vec4],
    sorted_conic: wp.array[wp.vec3],
    sorted_color: wp.array[wp.vec3],
    tile_start: wp.array[wp.int32],
    tile_end: wp.array[wp.int32],
    view_rotation: wp.array[wp.mat33],
    view_translation: wp.array[wp.vec3],
    intrinsics: wp.array[wp.vec4],
    sphere_centers: wp.array[wp.vec3],
    sphere_radii: wp.array[float],
    spheres_per_camera: int,
    sphere_color: wp.vec3,
    solid: wp.array3d[wp.vec4],
    has_solid: int,
    background: wp.vec3,
    width: int,
    height: int,
    rgb: wp.array3d[wp.vec3],
    alpha: wp.array3d[float],
    expected_depth: wp.array3d[float],
):
    """Two pixels per thread, rows y and y + TILE / 2 of a tile (launch (C, tiles * TILE * TILE / 2)):
    each splat's loads serve two pixels. No sphere shading (a timing variant: measured slower,
    0.95 vs 0.75 ms, raster_variants_cuda*.json)."""
    c, k = wp.tid()
    half = TILE * TILE / 2
    tiles_x = (width + TILE - 1) / TILE
    tiles_y = (height + TILE - 1) / TILE
    t = k / half
    local = k - t * half
    ty = t / tiles_x
    px = (t - ty * tiles_x) * TILE + local % TILE
    py0 = ty * TILE + local / TILE
    py1 = py0 + TILE / 2
    tile = c * tiles_x * tiles_y + t
    if px >= width or py0 >= height:
        return
    in1 = py1 < height
    z0, sk0, sh0, o0, d0, t0 = occluder_at_pixel(c, px, py0, view_rotation, view_translation, intrinsics,
                                                 sphere_centers, sphere_radii, spheres_per_camera, solid, has_solid)
    z1 = float(NO_HIT)
    s1 = int(1)
    if in1:
        z1, sk1, sh1, o1, d1, t1 = occluder_at_pixel(c, px, py1, view_rotation, view_translation, intrinsics,
                                                     sphere_centers, sphere_radii, spheres_per_camera, solid, has_solid)
        s1 = 0
    s0 = int(0)
    x = float(px) + 0.5
    y0 = float(py0) + 0.5
    y1 = float(py1) + 0.5
    T0 = float(1.0)
    T1 = float(1.0)
    acc0 = wp.vec3(0.0)
    acc1 = wp.vec3(0.0)
    az0 = float(0.0)
    az1 = float(0.0)
    for i in range(tile_start[tile], tile_end[tile]):
        if s0 != 0 and s1 != 0:
            break
        mo = sorted_xy_opacity_depth[i]
        zg = mo[3]
        q = sorted_conic[i]
        dx = mo[0] - x
        if s0 == 0:
            if zg > z0:
                s0 = 1
            else:
                dy = mo[1] - y0
                sigma = 0.5 * (q[0] * dx * dx + q[2] * dy * dy) + q[1] * dx * dy
                a = wp.min(0.999, mo[2] * wp.exp(-sigma))
                if sigma >= 0.0 and a >= 1.0 / 255.0:
                    nt = T0 * (1.0 - a)
                    if nt <= 1.0e-4:
                        s0 = 2
                    else:
                        w = a * T0
                        acc0 = acc0 + sorted_color[i] * w
                        az0 = az0 + zg * w
                        T0 = nt
        if s1 == 0:
            if zg > z1:
                s1 = 1
            else:
                dy = mo[1] - y1
                sigma = 0.5 * (q[0] * dx * dx + q[2] * dy * dy) + q[1] * dx * dy
                a = wp.min(0.999, mo[2] * wp.exp(-sigma))
                if sigma >= 0.0 and a >= 1.0 / 255.0:
                    nt = T1 * (1.0 - a)
                    if nt <= 1.0e-4:
                        s1 = 2
                    else:
                        w = a * T1
                        acc1 = acc1 + sorted_color[i] * w
                        az1 = az1 + zg * w
                        T1 = nt
    rgb[c, py0, px] = acc0 + background * T0
    alpha[c, py0, px] = 1.0 - T0
    e0 = float(0.0)
    if T0 < 1.0:
        e0 = az0 / (1.0 - T0)
    expected_depth[c, py0, px] = e0
    if in1:
        rgb[c, py1, px] = acc1 + background * T1
        alpha[c, py1, px] = 1.0 - T1
        e1 = float(0.0)
        if T1 < 1.0:
            e1 = az1 / (1.0 - T1)
        expected_depth[c, py1, px] = e1


def main(argv=None):
    from dynmesh_warp.render import Renderer, look_at

    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--scale", type=float, nargs="+", default=[1.0, 0.25])
    ap.add_argument("--launches", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.init()
    device = wp.get_device(a.device)
    rows = []
    for scale in a.scale:
        means, q, scales, covs, sh, op = scene(a.gaussians, 3, scale=scale)
        cam = look_at([2.2, 1.6, 1.2], [0, 0, 0], width=1920, height=1080, fov_y_deg=50)
        r = Renderer(device)
        dm, dc = wp.array(means, dtype=wp.vec3, device=device), wp.array(covs, dtype=wp.mat33, device=device)
        ds, do = wp.array(sh, dtype=float, device=device), wp.array(op, dtype=float, device=device)
        res0 = r.render(dm, dc, ds, do, [cam], background=(0, 0, 0))
        ref = [res0.rgb.numpy().copy(), res0.alpha.numpy().copy(), res0.depth.numpy().copy()]
        b = r._b
        Rs, ts, ks = r._camera_arrays([cam])
        C, H, W = 1, 1080, 1920
        tiles = b["start"].shape[0]
        sc, sr = r._no_spheres
        rgb = wp.zeros((C, H, W), dtype=wp.vec3, device=device)
        alpha = wp.zeros((C, H, W), dtype=float, device=device)
        zbuf = wp.zeros((C, H, W), dtype=float, device=device)
        common = [r._s_xyod, r._s_conic, r._s_color, b["start"], b["end"], Rs, ts, ks, sc, sr, 0]

        def run_current():
            wp.launch(rasterize_gaussians, (C, (tiles // C) * TILE * TILE),
                      inputs=[*common, wp.vec3(1.0), r._no_solid, 0, wp.vec3(0.0), W, H],
                      outputs=[rgb, alpha, zbuf], device=device)

        def run_pairs():
            wp.launch(rasterize_pairs, (C, (tiles // C) * TILE * TILE // 2), inputs=full,
                      outputs=[rgb, alpha, zbuf], device=device)

        full = [*common, wp.vec3(1.0), r._no_solid, 0, wp.vec3(0.0), W, H]

        def run_product_shared():
            wp.launch_tiled(RASTERIZE_SHARED["cuda" if device.is_cuda else "cpu"], dim=(tiles,), inputs=full,
                            outputs=[rgb, alpha, zbuf], block_dim=TILE * TILE, device=device)

        row = {"scale": scale, "entries": int(r.capacity), "variants": {}}
        variants = [("current", run_current), ("two_pixels", run_pairs), ("product_shared", run_product_shared)]
        for name, fn in variants:
            for arr in (rgb, alpha, zbuf):
                arr.zero_()
            fn()
            got = [rgb.numpy(), alpha.numpy(), zbuf.numpy()]
            diff = [float(np.abs(g - f).max()) for g, f in zip(got, ref)]
            ts_ = []
            if device.is_cuda:
                with wp.ScopedCapture(device) as cap:
                    for _ in range(a.launches):
                        fn()
                wp.capture_launch(cap.graph)
                for _ in range(a.repeats):
                    wp.synchronize_device(device)
                    t0 = time.perf_counter()
                    wp.capture_launch(cap.graph)
                    wp.synchronize_device(device)
                    ts_.append((time.perf_counter() - t0) / a.launches)
            else:
                for _ in range(a.repeats):
                    t0 = time.perf_counter()
                    fn()
                    wp.synchronize_device(device)
                    ts_.append(time.perf_counter() - t0)
            ms = float(np.median(ts_)) * 1e3
            row["variants"][name] = {"ms": ms, "max_abs_diff_rgb_alpha_depth": diff}
            print(f"scale {scale} {name}: {ms:.3f} ms, max |diff| rgb/alpha/depth {diff}", flush=True)
        rows.append(row)
    res = {"machine": describe_device(device), "image": [1920, 1080], "gaussians": a.gaussians, "rows": rows}
    if a.out:
        write_json(a.out, res)


if __name__ == "__main__":
    main()
