"""Our Warp splatting renderer against gsplat (issue 16): same Gaussians, same cameras.

Random scenes (G Gaussians in a unit cube, random rotations and scales, SH degree 3) at 1080p,
and a batch of small cameras for RL observations. Reports our forward time and, when gsplat is
importable (the GPU machine; a reference only, not a dependency), gsplat's forward time and the
PSNR between the two images. Median of ``--repeats`` after warm-up, device synchronised.

    python bench/bench_render.py --device cuda --gaussians 100000 --out bench/results/render_cuda.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, describe_device, write_json  # noqa: E402


def scene(G: int, degree: int, seed: int = 0, scale: float = 1.0):
    """G random Gaussians in [-1, 1]^3, axis scales uniform in scale x [0.005, 0.03] [m]."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-1, 1, (G, 3)).astype(np.float32)
    q = rng.normal(size=(G, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)  # (w, x, y, z) as gsplat takes them
    scales = (scale * rng.uniform(0.005, 0.03, (G, 3))).astype(np.float32)
    w, x, y, z = q.T
    R = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                  np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                  np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
    covs = np.einsum("gij,gj,gkj->gik", R, scales**2, R).astype(np.float32)
    sh = (rng.normal(0, 0.3, (G, (degree + 1) ** 2, 3))).astype(np.float32)
    op = rng.uniform(0.3, 1.0, G).astype(np.float32)
    return means, q, scales, covs, sh, op


def horse_scene(device, degree: int):
    """Gaussians generated on horse_gallop's first frame (the shared data; None without it), with
    a random view-dependent SH part, and 4 orbit cameras at 960 x 540: the issue's "real splat
    scene bound to the horse"."""
    from common import load_paper_sequence

    from dynmesh_warp.gaussians import generate_gaussians
    from dynmesh_warp.render import orbit_cameras, rgb_to_sh

    seq, shared = load_paper_sequence()
    if not shared:
        return None
    g = generate_gaussians(seq.V[0], seq.F, count=50_000, seed=0, device=device)
    g.update(wp.array(seq.V[0], dtype=wp.vec3, device=device),
             wp.array(seq.F.reshape(-1), dtype=wp.int32, device=device))
    q_xyzw = g.state.rotations.numpy()
    q = np.concatenate([q_xyzw[:, 3:], q_xyzw[:, :3]], axis=1).astype(np.float32)  # gsplat: (w, x, y, z)
    rng = np.random.default_rng(1)
    sh = np.concatenate([rgb_to_sh(g.binding.rgb),
                         rng.normal(0, 0.1, (g.count, (degree + 1) ** 2 - 1, 3)).astype(np.float32)], axis=1)
    V = seq.V[0]
    centre, diag = 0.5 * (V.min(0) + V.max(0)), float(np.linalg.norm(V.max(0) - V.min(0)))
    cams = orbit_cameras(centre, 1.1 * diag, 4, 20.0, 960, 540)
    return (g.state.centers.numpy(), q, g.state.scales.numpy().astype(np.float32),
            g.state.covariances.numpy(), sh, g.binding.opacity.astype(np.float32), cams)


def timed(fn, device, repeats, warmup=3):
    for _ in range(warmup):
        fn()
    wp.synchronize_device(device)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def psnr(a, b):
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def main(argv=None):
    from dynmesh_warp.choices import Rasteriser, values
    from dynmesh_warp.render import Renderer, look_at, orbit_cameras

    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--degree", type=int, default=3)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--batch", type=int, default=1024, help="cameras of the RL-observation batch (128 x 128; 0: none)")
    ap.add_argument("--scale", type=float, default=1.0, help="factor on the random Gaussians' scales (a sparser scene)")
    ap.add_argument("--wide-keys", action="store_true", help="sort 64-bit keys even where compact 32-bit ones fit")
    ap.add_argument("--rasteriser", choices=values(Rasteriser), default=None,
                    help="the rasteriser (default: the device kind's, choices.DEFAULT_RASTERISER)")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--profile", action="store_true", help="also time each stage (synchronised after each)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.init()
    device = wp.get_device(a.device)
    means, q, scales, covs, sh, op = scene(a.gaussians, a.degree, scale=a.scale)
    cam = look_at([2.2, 1.6, 1.2], [0, 0, 0], width=a.width, height=a.height, fov_y_deg=50)
    r = Renderer(device, compact_keys=not a.wide_keys, rasteriser=a.rasteriser)
    dm = wp.array(means, dtype=wp.vec3, device=device)
    dc = wp.array(covs, dtype=wp.mat33, device=device)
    ds = wp.array(sh, dtype=float, device=device)
    do = wp.array(op, dtype=float, device=device)
    res = {"machine": describe_device(device), "gaussians": a.gaussians, "sh_degree": a.degree,
           "image": [a.width, a.height], "scale": a.scale,
           "sort_keys": "64-bit" if a.wide_keys else "compact 32-bit where they fit", "rasteriser": str(r.rasteriser)}
    out = {}
    t = timed(lambda: out.__setitem__("r", r.render(dm, dc, ds, do, [cam], background=(0, 0, 0))), device, a.repeats)
    ours = out["r"].rgb.numpy()[0]
    res["ours_ms"] = t * 1e3
    if a.profile:  # each launch / the sort timed with a device sync before and after
        import dynmesh_warp.render as R

        stages: dict = {}
        launch, tiled, sort, scan = R.wp.launch, R.wp.launch_tiled, R.wp.utils.radix_sort_pairs, R.wp.utils.array_scan

        def wrap(name, fn):
            def call(*args, **kw):
                wp.synchronize_device(device)
                t0 = time.perf_counter()
                out = fn(*args, **kw)
                wp.synchronize_device(device)
                key = getattr(args[0], "key", name) if name == "launch" else name
                stages[key] = stages.get(key, 0.0) + (time.perf_counter() - t0) * 1e3
                return out
            return call

        R.wp.launch, R.wp.launch_tiled, R.wp.utils.radix_sort_pairs, R.wp.utils.array_scan = (
            wrap("launch", launch), wrap("launch", tiled), wrap("radix_sort_pairs", sort), wrap("array_scan", scan))
        try:
            for _ in range(a.repeats):
                r.render(dm, dc, ds, do, [cam], background=(0, 0, 0))
        finally:
            R.wp.launch, R.wp.launch_tiled, R.wp.utils.radix_sort_pairs, R.wp.utils.array_scan = launch, tiled, sort, scan
        res["stages_ms"] = {k: v / a.repeats for k, v in stages.items()}
        res["keys"] = int(r.capacity)
        print("stages (ms):", {k: round(v, 3) for k, v in res["stages_ms"].items()}, flush=True)
    print(f"ours {a.width}x{a.height}, {a.gaussians} Gaussians: {t * 1e3:.2f} ms ({1 / t:,.0f} frames/s)", flush=True)
    if device.is_cuda:  # the same render replayed from a CUDA graph (fixed capacity): device time, no host launches
        n = r.capacity  # the exact render above sized the buffers: room for every entry
        r.render(dm, dc, ds, do, [cam], background=(0, 0, 0), capacity=n)  # allocate outside the capture
        with wp.ScopedCapture(device) as capture:
            r.render(dm, dc, ds, do, [cam], background=(0, 0, 0), capacity=n)
        tg = timed(lambda: wp.capture_launch(capture.graph), device, a.repeats)
        res["ours_graph_ms"] = tg * 1e3
        print(f"ours, replayed from a CUDA graph: {tg * 1e3:.2f} ms ({1 / tg:,.0f} frames/s)", flush=True)
    cams = orbit_cameras([0, 0, 0], 3.0, a.batch, width=128, height=128) if a.batch > 0 else []
    if cams:
        tb = timed(lambda: r.render(dm, dc, ds, do, cams, background=(0, 0, 0)), device, max(2, a.repeats // 3),
                   warmup=1)
        res["batch"] = {"cameras": a.batch, "size": [128, 128], "ours_ms": tb * 1e3}
        print(f"ours batch of {a.batch} cameras at 128x128: {tb * 1e3:.2f} ms", flush=True)
    horse = horse_scene(device, a.degree)  # Gaussians bound to the horse (frame 0), if the data is here
    try:
        import gsplat
        import torch
    except ImportError as e:
        res["gsplat"] = f"not available: {e}"
    else:
        dev = "cuda" if device.is_cuda else "cpu"
        T = lambda x: torch.as_tensor(x, device=dev)  # noqa: E731
        K = T(np.array([[[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]]], np.float32))
        V = np.eye(4, dtype=np.float32)
        V[:3, :3], V[:3, 3] = cam.R, cam.t
        args = dict(means=T(means), quats=T(q), scales=T(scales), opacities=T(op), colors=T(sh),
                    viewmats=T(V[None]), Ks=K, width=a.width, height=a.height, sh_degree=a.degree)
        g = {}

        def run_gsplat():
            g["img"] = gsplat.rasterization(**args)[0]

        tg = timed(lambda: (run_gsplat(), torch.cuda.synchronize() if dev == "cuda" else None), device, a.repeats)
        ref = g["img"][0].detach().cpu().numpy()
        res["gsplat"] = {"version": gsplat.__version__, "ms": tg * 1e3, "psnr_db": psnr(ours, ref),
                         "ours_over_gsplat": t / tg}
        print(f"gsplat {gsplat.__version__}: {tg * 1e3:.2f} ms; ours/gsplat {t / tg:.2f}; "
              f"PSNR {res['gsplat']['psnr_db']:.1f} dB", flush=True)
        if cams:
            Ks = T(np.stack([[[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]] for c in cams]).astype(np.float32))
            Vs = np.tile(np.eye(4, dtype=np.float32), (len(cams), 1, 1))
            for i, c in enumerate(cams):
                Vs[i, :3, :3], Vs[i, :3, 3] = c.R, c.t
            bargs = dict(args, viewmats=T(Vs), Ks=Ks, width=128, height=128)
            tgb = timed(lambda: (gsplat.rasterization(**bargs), torch.cuda.synchronize() if dev == "cuda" else None),
                        device, max(2, a.repeats // 3), warmup=1)
            res["batch"]["gsplat_ms"] = tgb * 1e3
            print(f"gsplat batch {tgb * 1e3:.2f} ms", flush=True)
        if horse is not None:  # the real splat scene: Gaussians bound to the horse, 4 orbit views
            hm, hq, hs, hc, hsh, hop, hcams = horse
            ours_h = r.render(hm, hc, hsh, hop, hcams, background=(0, 0, 0)).rgb.numpy().copy()
            Ks = T(np.stack([[[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]] for c in hcams]).astype(np.float32))
            Vs = np.tile(np.eye(4, dtype=np.float32), (len(hcams), 1, 1))
            for i, c in enumerate(hcams):
                Vs[i, :3, :3], Vs[i, :3, 3] = c.R, c.t
            ref = gsplat.rasterization(means=T(hm), quats=T(hq), scales=T(hs), opacities=T(hop), colors=T(hsh),
                                       viewmats=T(Vs), Ks=Ks, width=hcams[0].width, height=hcams[0].height,
                                       sh_degree=int(round(np.sqrt(hsh.shape[1]))) - 1)[0]
            ref = ref.detach().cpu().numpy()
            res["horse"] = {"gaussians": int(len(hm)), "views": len(hcams),
                            "psnr_db": [psnr(ours_h[i], ref[i]) for i in range(len(hcams))]}
            print(f"horse ({len(hm)} bound Gaussians, {len(hcams)} views): PSNR "
                  + ", ".join(f"{x:.1f}" for x in res["horse"]["psnr_db"]) + " dB", flush=True)
    write_json(Path(a.out) if a.out else RESULTS / f"render_{'cuda' if device.is_cuda else 'cpu'}.json", res)


if __name__ == "__main__":
    main()
