"""How many faces each sphere's swept query must walk on the scaling grids (issue 14).

The swept collider's former gathered-candidate paths (the 256-entry lists, then the pool of
pairs; both dropped after measuring, docs/benchmarks.md) gathered, at each frame change, the
faces whose swept box (a face's box over the frame interval) lies in the ball a sphere can reach
during that interval: R = r + margin + 1.25 (|v| T + g T^2 / 2), T = 1 / fps. This counts
them with the same rule (a BVH query per sphere, ``count_ball_faces`` below), on the wave
grids of ``bench_step.py --scaling`` after 30 steps (spheres falling onto the sheet), the
candidates per sphere and the share of spheres that would overflow 256. Counts are the same
on every device (they are geometry); run on the CPU.

    python bench/swept_candidates.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_step import make_world, wave_grid  # noqa: E402
from common import RESULTS, describe_device, write_json  # noqa: E402


#: the per-sphere list length of the first gathered path
SWEPT_MAX_CANDIDATES = 256


@wp.kernel
def count_ball_faces(radius: wp.array[float], pos: wp.array[wp.vec3], vel: wp.array[wp.vec3], bvh: wp.uint64,
                     horizon: float, gravity: float, margin: float, count: wp.array[wp.int32]):
    """Faces whose swept box meets the box of the ball a sphere reaches in ``horizon`` seconds."""
    s = wp.tid()
    T = horizon
    R = radius[s] + margin + 1.25 * (wp.length(vel[s]) * T + 0.5 * gravity * T * T)
    query = wp.bvh_query_aabb(bvh, pos[s] - wp.vec3(R), pos[s] + wp.vec3(R))
    f = int(0)
    n = int(0)
    while wp.bvh_query_next(query, f):
        n += 1
    count[s] = n


def main():
    wp.config.quiet = True
    rows = []
    for nv in (1024, 10000, 99856, 1000000):
        n = int(round(np.sqrt(nv)))
        seq = wave_grid(n)
        for ns in (5, 1000):
            radius = float(min(0.05, 0.5 / np.sqrt(ns)))  # as bench_step's scaling rows
            w = make_world(seq, "cpu", "swept", spheres=ns, radius=radius, spread=0.9)
            for _ in range(30):
                w.step()
            col, m = w.collider, w.model
            cnt = wp.zeros(ns, dtype=wp.int32, device="cpu")
            g = float(np.linalg.norm(m.params.gravity))
            step_reach = m.params.margin + 2.0 * g * w.ctx.sub_dt ** 2 + col.epsilon
            wp.launch(count_ball_faces, ns, inputs=[m.spheres.radius, w.state.sphere_pos, w.state.sphere_vel,
                                                    col.bvh.id, 1.0 / m.surface.fps, g, step_reach],
                      outputs=[cnt], device="cpu")
            c = cnt.numpy()
            edge = float(w.model.surface.average_edge_length.mean())
            row = {"vertices": n * n, "faces": int(seq.F.shape[0]), "spheres": ns, "radius": radius,
                   "mean_edge": edge, "candidates_median": float(np.median(c)), "candidates_max": int(c.max()),
                   "candidates_mean_nonzero": float(c[c > 0].mean()) if (c > 0).any() else 0.0,
                   "spheres_with_candidates": float((c > 0).mean()),
                   "overflow_share_at_cap": float((c > SWEPT_MAX_CANDIDATES).mean()), "cap": SWEPT_MAX_CANDIDATES}
            rows.append(row)
            print(f"N={n * n:>8} S={ns:>5}: candidates per sphere median {row['candidates_median']:.0f}, "
                  f"mean of those with any {row['candidates_mean_nonzero']:.0f}, max {row['candidates_max']}; "
                  f"over the cap of {SWEPT_MAX_CANDIDATES}: {100 * row['overflow_share_at_cap']:.0f} % of spheres",
                  flush=True)
    write_json(RESULTS / "swept_candidates_cpu.json", {"machine": describe_device("cpu"), "rows": rows})


if __name__ == "__main__":
    main()
