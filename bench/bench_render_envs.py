"""Camera observations of batched envs (issue 16): ``render.render_envs`` time per call.

E envs on the paper scene's surface (horse_gallop, or the built-in wave bowl without
../shared), each at its own random phase, G Gaussians bound to the surface, one W x H camera
per env looking at the surface centre from its own side; time per ``render_envs`` call (the
per-env Gaussian evaluation, projection, sort and rasterisation; the host read of the key
count included), after a warm-up, median of repeats.

    python bench/bench_render_envs.py --device cuda --envs 64,1024 --gaussians 5000 --size 64
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from common import describe_device, load_paper_sequence, write_json  # noqa: E402

RESULTS = ROOT / "bench" / "results"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--envs", default="16,64")
    ap.add_argument("--gaussians", type=int, default=5000)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import warp as wp

    from dynmesh_warp.batch import BatchedWorld, BatchModel, BatchState
    from dynmesh_warp.gaussians import generate_gaussians
    from dynmesh_warp.render import Renderer, look_at, render_envs
    from dynmesh_warp.world import PhysicsParams, SurfaceModel

    wp.config.quiet = True
    device = wp.get_device(args.device)
    seq, shared = load_paper_sequence()
    V0 = seq.V[0]
    center = 0.5 * (V0.min(0) + V0.max(0))
    diag = float(np.linalg.norm(np.ptp(V0, axis=0)))
    g = generate_gaussians(V0, seq.F, count=args.gaussians, seed=0, device=device)
    rows = []
    for E in [int(x) for x in args.envs.split(",")]:
        rng = np.random.default_rng(0)
        bm = BatchModel(SurfaceModel(seq, device, playback="loop"), E, [0.05], 1.0, PhysicsParams())
        top = V0[:, 2].max() + 0.2 * diag
        pos = np.column_stack([np.full(E, center[0]), np.full(E, center[1]), np.full(E, top)]).reshape(E, 1, 3)
        bw = BatchedWorld(bm, BatchState(bm, pos, times=rng.uniform(0, seq.num_frames / seq.fps, E)))
        ang = rng.uniform(0, 2 * np.pi, E)
        cams = [look_at(center + diag * np.array([np.cos(a), np.sin(a), 0.5]), center, width=args.size,
                        height=args.size) for a in ang]
        r = Renderer(device)
        render_envs(bw, g, cams, renderer=r)
        wp.synchronize_device(device)
        ts = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            render_envs(bw, g, cams, renderer=r)
            wp.synchronize_device(device)
            ts.append(time.perf_counter() - t0)
        t = float(np.median(ts))
        rows.append({"envs": E, "gaussians": g.count, "width": args.size, "height": args.size, "s_per_call": t,
                     "images_per_s": E / t, "repeats": args.repeats})
        print(f"E={E:6d} G={g.count} {args.size}x{args.size}: {1e3 * t:8.2f} ms per call, {E / t:10.0f} images/s",
              flush=True)
    out = Path(args.out) if args.out else RESULTS / f"render_envs_{'cuda' if device.is_cuda else 'cpu'}.json"
    write_json(out, {"machine": describe_device(device), "scene": seq.name, "from_shared_data": shared, "rows": rows})


if __name__ == "__main__":
    main()
