"""The cells collider (issue 14; dynmesh_warp/face_cells.py, measured and not kept) on the scaling
table's wave grids: its pieces timed apart, the whole step against the refit (and swept)
collider in the same run, and its contacts against the refit reference's on the same state.

    python bench/cells_probe.py --device cuda:0 --verts 1000000 --spheres 100000 --clusters 32/4,16/4 \
        --compare refit --out bench/results/cells_probe_cuda.json

Per (vertices, spheres, cluster faces K / sub-box faces B, cell edge in cluster edges E): after
30 steps of the cells world, CUDA graphs of (a) the per-step upkeep (vertices, boxes, counting
sort) alone and each of its three pieces, (b) the contact query alone, (c) the full step; then
the refit reference's contacts at the same state (the same set of spheres in contact, the
largest point and depth differences).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, describe_device, time_loop, write_json  # noqa: E402
from bench_step import make_world, wave_grid  # noqa: E402


def graph_time(fn, device, steps: int, repeats: int) -> float:
    """µs per call of ``fn`` replayed from a CUDA graph (eager on the CPU), median of repeats."""
    import warp as wp

    fn()
    if wp.get_device(device).is_cuda:
        with wp.ScopedCapture(device=device) as cap:
            fn()
        g = cap.graph
        t = time_loop(lambda: wp.capture_launch(g), device, steps, repeats, warmup=5)
    else:
        t = time_loop(fn, device, steps, repeats, warmup=2)
    return t["us_per_step"]


def compare_with_refit(w, seq, device, radius) -> dict:
    """The refit reference's contacts on the cells world's current state."""
    from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, World

    pos, vel = w.state.sphere_pos.numpy(), w.state.sphere_vel.numpy()
    t0 = float(w.state.sim_time.numpy()[0])
    model = Model(SurfaceModel(seq, device, playback="loop", interpolate=True),
                  SphereModel(np.full(len(pos), radius, np.float32), 1.0, device),
                  PhysicsParams(dt=1.0 / 240.0, auto_substeps=False, ground_height=w.model.params.ground_height))
    ref = World(model, State(model, pos, vel, t0=t0), collider="refit")
    out = []
    for x in (ref, w):
        x.update_surface()
        x.collider.update(x.model, x.state, x.ctx)
        x.collider.collide(x.model, x.state, x.contacts, x.ctx)
        out.append(x.contacts.numpy())
    a, b = out
    m = a["face"] >= 0
    same = bool(np.array_equal(m, b["face"] >= 0))
    return {"contacts_ref": int(m.sum()), "contacts_cells": int((b["face"] >= 0).sum()), "same_contact_set": same,
            "max_point_diff_m": float(np.abs(a["point"][m] - b["point"][m]).max()) if m.any() and same else None,
            "max_depth_diff_m": float(np.abs(a["depth"][m] - b["depth"][m]).max()) if m.any() and same else None}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--verts", default="100000,1000000")
    ap.add_argument("--spheres", default="5,1000,100000")
    ap.add_argument("--clusters", default="32/4", help="comma-separated faces a cluster / a sub-box (K/B)")
    ap.add_argument("--extents", default="1.0", help="comma-separated cell edges in median cluster edges (E)")
    ap.add_argument("--nearest", default="1", help="comma-separated query orders: 1 nearest-first sub-boxes, 0 walk order")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--compare", default="refit,swept", help="whole-step colliders timed alongside")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import warp as wp

    import dynmesh_warp.face_cells as cells_mod

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    out = Path(args.out) if args.out else RESULTS / f"cells_probe_{'cuda' if device.is_cuda else 'cpu'}.json"
    rows = []
    for nv in (int(float(v)) for v in args.verts.split(",")):
        seq = wave_grid(int(round(np.sqrt(nv))))
        for ns in (int(float(v)) for v in args.spheres.split(",")):
            radius = float(min(0.05, 0.5 / np.sqrt(ns)))
            for col in [c for c in args.compare.split(",") if c]:
                w = make_world(seq, device, col, spheres=ns, radius=radius, spread=0.9)
                t = time_loop(w.step, device, args.steps, args.repeats, warmup=3)
                rows.append({"vertices": seq.num_vertices, "spheres": ns, "collider": col,
                             "step_us": t["us_per_step"], "steps_per_s": t["steps_per_s"]})
                print(rows[-1], flush=True)
                del w
            for KB in args.clusters.split(","):
                K, _, B = KB.partition("/")
                K, B = int(K), int(B or 4)
                for E, NF in ((float(e), int(o)) for e in args.extents.split(",") for o in args.nearest.split(",")):
                    cells_mod.CELLS_CLUSTER_FACES, cells_mod.CELLS_SUB_FACES, cells_mod.CELLS_CELL_EXTENTS = K, B, E
                    cells_mod.CELLS_NEAREST_FIRST = NF
                    w = make_world(seq, device, "refit", spheres=ns, radius=radius, spread=0.9)
                    t0 = time.perf_counter()  # the cells collider's own build, not the refit world's around it
                    w = cells_mod.use_cells_collider(w)
                    collider_build_s = time.perf_counter() - t0
                    for _ in range(30):
                        w.step()
                    m, s, c, ctx = w.model, w.state, w.contacts, w.ctx
                    cc = w.collider
                    row = {"vertices": seq.num_vertices, "spheres": ns, "collider": "cells", "cluster_faces": K, "sub_faces": B,
                           "cell_extents": E, "nearest_first": NF, "clusters": cc.cells.num_clusters,
                           "grid_dims": cc.cells.grid_dims.tolist(), "cell_m": cc.cells.cell,
                           "capacity": cc.cells.capacity, "collider_build_s": collider_build_s,
                           "upkeep_us": graph_time(lambda: cc.update(m, s, ctx), device, args.steps, args.repeats),
                           **{f"{k}_us": graph_time(lambda k=k: getattr(cc, k)(m, s, ctx), device, args.steps,
                                                    args.repeats) for k in ("blend", "bound", "sort")},
                           "query_us": graph_time(lambda: cc.collide(m, s, c, ctx), device, args.steps, args.repeats)}
                    t = time_loop(w.step, device, args.steps, args.repeats, warmup=3)
                    row.update(step_us=t["us_per_step"], steps_per_s=t["steps_per_s"])
                    counts = cc.cell_count.numpy()
                    row["entries"] = int(counts.sum())
                    row["entries_per_busy_cell"] = float(counts[counts > 0].mean())
                    row.update(compare_with_refit(w, seq, device, radius))
                    rows.append(row)
                    print(row, flush=True)
                    del w
    write_json(out, {"machine": describe_device(device), "rows": rows,
                     "note": "wave grids of bench_step.py's scaling table (2 m sheet, 4 frames at 24 fps, dt 1/240, "
                             "one sub-step); upkeep/query: the collider's update/collide alone replayed from a CUDA "
                             "graph; step: World.step (one graph)"})


if __name__ == "__main__":
    main()
