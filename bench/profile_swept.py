"""Per-kernel device time of the swept step, in the paper scene and on the scaling grids.

    python bench/profile_swept.py --device cuda:0 [--rows paper,1e5x5,...] [--out file.json]

Each row builds a swept world (each ``--searches``: tiled, serial, in turn), lets the
spheres settle for ``--settle`` steps (graph), then runs ``--steps`` eager steps under Warp's
activity timing (``wp.timing_begin``: CUDA events around every kernel, memset and copy) and
sums the device time per kernel over those steps. Eager launches carry more host overhead than
the graph, but the device time of each kernel is the same; the graph step's wall time is
reported beside it. Also: the spheres in contact and the faces in their one-step reach box
(what a search walks). Rows of earlier searches (pairs, nearest; dropped) are in
bench/results/profile_swept_cuda_*.json.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_step import make_world, wave_grid  # noqa: E402
from common import describe_device, load_paper_sequence, time_loop, write_json  # noqa: E402

ROWS = {"paper": None, "1e4x5": (10_000, 5), "1e5x5": (100_000, 5), "1e5x1000": (100_000, 1_000),
        "1e6x5": (1_000_000, 5), "1e6x1e5": (1_000_000, 100_000)}


def reach_info(w) -> dict:
    """Faces in each sphere's one-step reach box (what a search walks) and spheres in contact."""
    c = w.collider
    lo, hi = c.lowers.numpy(), c.uppers.numpy()
    p = w.state.sphere_pos.numpy()
    v = np.linalg.norm(w.state.sphere_vel.numpy(), axis=1)
    r = w.model.spheres.radius.numpy()
    reach = r + w.model.params.margin + (v + w.ctx.extra_speed) * w.ctx.sub_dt + c.epsilon
    contact = w.contacts.face.numpy() >= 0
    touching = np.flatnonzero(contact)[:64]  # the counts of at most 64 touching spheres
    counts = [int(np.all((lo <= p[s] + reach[s]) & (hi >= p[s] - reach[s]), axis=1).sum()) for s in touching]
    return {"in_contact": int(contact.sum()),
            "faces_in_reach_box_touching_median": float(np.median(counts)) if counts else 0.0,
            "faces_in_reach_box_touching_max": int(max(counts)) if counts else 0}


def profile_row(name, device, search, settle, steps, tile_threads=None):
    import dynmesh_warp.world as W

    W.SWEPT_TILE_THREADS = tile_threads or W.SWEPT_TILE_THREADS
    if ROWS[name] is None:
        seq, _ = load_paper_sequence()
        w = make_world(seq, device, "swept", swept_search=search)
    else:
        nv, ns = ROWS[name]
        n = int(round(np.sqrt(nv)))
        w = make_world(wave_grid(n), device, "swept", spheres=ns, radius=float(min(0.05, 0.5 / np.sqrt(ns))),
                       spread=0.9, swept_search=search)
    for _ in range(settle):
        w.step()
    graph = time_loop(w.step, device, steps, 3, warmup=3)
    info = reach_info(w)
    w.use_graph = False  # eager steps from here: each launch timed on its own
    w.step()
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    for _ in range(steps):
        w.step()
    res = wp.timing_end()
    per = defaultdict(lambda: [0.0, 0])
    for r in res:
        key = r.name.split("(")[0][:60]
        per[key][0] += r.elapsed * 1e3 / steps  # ms -> us per step
        per[key][1] += 1
    kernels = {k: {"us_per_step": v[0], "launches": v[1]} for k, v in sorted(per.items(), key=lambda kv: -kv[1][0])}
    total = sum(v[0] for v in per.values())
    return {"row": name, "search": search, "tile_threads": w.collider.tile_threads if search == "tiled" else None,
            "graph_us_per_step": graph["us_per_step"],
            "device_us_per_step_eager": total, "kernels": kernels, "state": info}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--rows", default="paper,1e5x5,1e6x5,1e5x1000,1e6x1e5")
    ap.add_argument("--searches", default="tiled,serial")
    ap.add_argument("--tile-threads", default=None, help="comma-separated block sizes of the tiled search")
    ap.add_argument("--settle", type=int, default=240)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    wp.config.quiet = True
    device = wp.get_device(args.device)
    out = []
    for name in args.rows.split(","):
        import dynmesh_warp.world as W

        default_threads = W.SWEPT_TILE_THREADS
        runs = [(s, None) for s in args.searches.split(",") if s != "tiled"]
        if "tiled" in args.searches.split(","):
            runs[:0] = [("tiled", int(t)) for t in (args.tile_threads or str(default_threads)).split(",")]
        for search, threads in runs:
            r = profile_row(name, device, search, args.settle, args.steps, threads or default_threads)
            out.append(r)
            search = search + (f"/{threads}" if threads else "")
            top = ", ".join(f"{k} {v['us_per_step']:.1f}" for k, v in list(r["kernels"].items())[:5])
            print(f"{name:<9} {search:<10} graph {r['graph_us_per_step']:8.1f} us/step, device "
                  f"{r['device_us_per_step_eager']:8.1f} us/step: {top}  {r['state']}", flush=True)
    result = {"machine": describe_device(device), "settle_steps": args.settle, "profiled_steps": args.steps,
              "rows": out}
    if args.out:
        write_json(Path(args.out), result)


if __name__ == "__main__":
    main()
