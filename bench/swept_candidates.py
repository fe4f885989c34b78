"""How many faces each sphere's swept query must walk on the scaling grids (issue 14).

The swept collider's parallel path gathers, at each frame change, the faces whose swept box
(a face's box over the frame interval) lies in the ball a sphere can reach during that
interval; before this round at most ``SWEPT_MAX_CANDIDATES`` (256) per sphere, a sphere with
more walking the BVH serially (now one pool, reduced over pairs). This counts, on the wave
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


def main():
    from dynmesh_warp.world import SWEPT_MAX_CANDIDATES

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
            col = w.collider
            col.parallel = True
            col.resize(w.model, w.state, w.ctx)  # the gather counts every face, whatever the pool holds
            c = col.cand_count.numpy()
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
