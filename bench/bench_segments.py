"""Benchmark: playing a piecewise-fixed surface (template segments) against the same input as
a truly varying one, with the rebuild collider per segment (the default) and per sub-step (the
baseline).

Input: the built-in torus closing into a ball (marching cubes per frame), converted by
``to_piecewise_fixed`` (what ``convert`` writes: here two templates, cut where the hole
closes). Rows: the segmented sequence with ``rebuild_every`` segment / step, and the raw varying
input with segment (a BVH per frame: each frame is its own segment) / step. Spheres dropped on
the surface; steps/s (median of repeats, synchronized), BVH builds per simulated second.

    python bench/bench_segments.py --device cpu        # -> bench/results/segments_cpu.json
    python bench/bench_segments.py --device cuda:0     # -> bench/results/segments_cuda.json
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

from common import RESULTS, describe_device, time_loop, write_json  # noqa: E402


def make_world(seq, device, spheres: int, every: str, radius: float = 0.03, seed: int = 0):
    from dynmesh_warp.config import SpawnConfig, spawn_positions
    from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, VaryingSurfaceModel, World

    surf = VaryingSurfaceModel(seq, device, playback="loop")
    V0 = seq.frames[0][0]
    pos = spawn_positions(SpawnConfig(count=spheres, radius=radius, height=0.05, seed=seed, spread=0.6), V0)
    model = Model(surf, SphereModel(np.full(spheres, radius, np.float32), 1.0, device),
                  PhysicsParams(dt=1.0 / 240.0, auto_substeps=False, ground_height=float(V0[:, 2].min()) - 0.2))
    return World(model, State(model, pos), collider="rebuild", rebuild_every=every)


def main(argv=None):
    import warp as wp

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default=None)
    p.add_argument("--frames", type=int, default=48)
    p.add_argument("--resolution", type=int, default=48, help="marching-cubes grid of the input")
    p.add_argument("--spheres", default="5,1000")
    p.add_argument("--steps", type=int, default=240, help="timed steps per repeat (240 = 1 s at 240 Hz)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(a.device)
    from dynmesh_warp.convert import to_piecewise_fixed
    from dynmesh_warp.scenes import torus_to_sphere

    raw = torus_to_sphere(frames=a.frames, resolution=a.resolution)
    t0 = time.perf_counter()
    seg = to_piecewise_fixed(raw, device=device)
    convert_s = time.perf_counter() - t0
    seqs = {"segmented": seg, "varying": raw}
    res = {"benchmark": "segments", **describe_device(device),
           "input": {"scene": "torus_to_sphere", "frames": a.frames, "resolution": a.resolution, "fps": raw.fps,
                     "segments": [list(map(int, x)) for x in seg.conversion.segments] if hasattr(seg, "conversion") else None,
                     "raw_segments": len(raw.segments()), "convert_s": convert_s},
           "rows": []}
    print(f"input: {a.frames} frames; converted into {len(seg.conversion.segments)} segment(s) in {convert_s:.1f} s; "
          f"the raw input has {len(raw.segments())} runs of equal faces")
    for n in [int(x) for x in a.spheres.split(",")]:
        for name, seq in seqs.items():
            for every in ("segment", "step"):
                w = make_world(seq, device, n, every)
                builds = []
                real = wp.Mesh

                def counting(*args, _real=real, **kw):
                    builds.append(1)
                    return _real(*args, **kw)

                t = time_loop(w.step, device, a.steps, a.repeats, warmup=10)
                wp.Mesh = counting  # BVH builds over one more simulated second
                try:
                    for _ in range(240):
                        w.step()
                finally:
                    wp.Mesh = real
                row = {"sequence": name, "rebuild_every": every, "spheres": n, **t, "bvh_builds_per_s": len(builds),
                       "finite": bool(np.isfinite(w.sphere_positions()).all())}
                res["rows"].append(row)
                print(f"{name:10s} rebuild_every {every:8s} {n:5d} spheres: {t['steps_per_s']:9.0f} steps/s, "
                      f"{len(builds)} BVH builds per simulated s", flush=True)
    out = Path(a.out) if a.out else RESULTS / f"segments_{device.alias.split(':')[0]}.json"
    write_json(out, res)


if __name__ == "__main__":
    main()
