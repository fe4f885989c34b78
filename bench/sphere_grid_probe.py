"""Issue 14: the swept collider's ``sphere_grid`` search (face-parallel over a hashed grid of the
spheres rebuilt every step) against the refit collider on bench_step's scaling scenes.

For each (vertices, spheres) row: the scene of ``bench_step.scaling`` (a wave sheet, spheres
dropped in one layer), run ``--settle`` steps so the spheres land and bounce, then, from the
same state, the whole step's steps/s of each collider in ``--compare`` and of ``sphere_grid``
(graph-replayed on CUDA), the sphere_grid stages alone (binning: count + scan + scatter; the
face pass; the face pass + resolve), and what the grid held (entries, levels, spheres in
contact, the contacts equal to refit's at that state).

    python bench/sphere_grid_probe.py --device cuda:0 --verts 1000000 --spheres 100000
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_step import graph_or_eager, make_world, wave_grid  # noqa: E402
from common import RESULTS, checked_output, describe_device, time_loop, write_json  # noqa: E402


def _contacts(w):
    w.update_surface()
    w.collider.update(w.model, w.state, w.ctx)
    w.collider.collide(w.model, w.state, w.contacts, w.ctx)
    return w.contacts.numpy()


def row(nv: int, ns: int, device, compare: list, steps: int, repeats: int, settle: int, variants: list,
        profile: int = 0) -> dict:
    import warp as wp

    import dynmesh_warp.world as world_mod
    from dynmesh_warp.world import State, World

    n = int(round(np.sqrt(nv)))
    seq = wave_grid(n)
    radius = float(min(0.05, 0.5 / np.sqrt(ns)))
    t0 = time.perf_counter()
    base = make_world(seq, device, "swept", spheres=ns, radius=radius, spread=0.9, swept_search="sphere_grid")
    build_s = time.perf_counter() - t0
    for _ in range(settle):
        base.step()
    wp.synchronize_device(device)
    pos, vel = base.sphere_positions(), base.state.sphere_vel.numpy()
    t = float(base.state.sim_time.numpy()[0])
    out = {"vertices": n * n, "faces": 2 * (n - 1) ** 2, "spheres": ns, "radius": radius, "settle_steps": settle,
           "build_s": build_s, "variants": []}

    def world(col):
        b, _, search = col.partition("/")
        return World(base.model, State(base.model, pos, vel, t0=t), collider=b, swept_search=search or None)

    ref = world("refit")
    c_ref = _contacts(ref)
    m = c_ref["face"] >= 0
    out["in_contact"] = int(m.sum())
    defaults = {k: getattr(world_mod, k) for k in ("SPHERE_GRID_CELL_SCALE", "SPHERE_GRID_LEVEL_SCALE",
                                                   "SPHERE_GRID_BUCKETS_PER_SPHERE")}
    for cell_scale, level_scale, buckets in variants:
        for k, v in zip(defaults, (cell_scale, level_scale, buckets)):
            setattr(world_mod, k, v)
        try:
            g = world("swept/sphere_grid")
        finally:
            for k, v in defaults.items():
                setattr(world_mod, k, v)
        c = _contacts(g)
        v = {"cell_scale": cell_scale, "level_scale": level_scale, "buckets_per_sphere": buckets,
             "same_contacts": bool(np.array_equal(c["face"] >= 0, m)),
             "max_point_diff_m": float(np.abs(c["point"][m] - c_ref["point"][m]).max()) if m.any() else 0.0}
        col = g.collider
        grid = col.grid
        lv = grid.sphere_level.numpy()
        v["levels"] = {str(k): int((lv == k).sum()) for k in (-1, 0, 1, 2)}
        v["entries"] = int(grid.bucket_start.numpy()[-1])
        v["buckets"] = grid.num_buckets
        v["cell_size_m"] = [float(grid.cell_size[0]), float(grid.cell_size[1])]
        mm, st, cc, ctx = g.model, g.state, g.contacts, g.ctx
        face = cc.face.numpy().copy()
        binning = graph_or_eager(lambda: grid.bin_spheres(mm, st, cc, ctx, col.epsilon), device)
        stages = {"binning": time_loop(binning, device, steps, repeats)["us_per_step"],
                  "collide": time_loop(graph_or_eager(lambda: col.collide(mm, st, cc, ctx), device), device, steps,
                                       repeats)["us_per_step"]}
        if profile and wp.get_device(device).is_cuda:  # each kernel's and memset's device time, eager
            col.collide(mm, st, cc, ctx)
            wp.timing_begin(cuda_filter=wp.TIMING_ALL)
            for _ in range(profile):
                col.collide(mm, st, cc, ctx)
            prof = {}
            for r in wp.timing_end():
                prof[r.name] = prof.get(r.name, 0.0) + 1e3 * r.elapsed / profile
            v["profile_us"] = prof
            print("   profile (us): " + ", ".join(f"{k.split(' ')[-1]} {t:.1f}" for k, t in prof.items()), flush=True)
        cc.face.assign(face)
        v["stages_us"] = stages
        v["steps_per_s"] = time_loop(g.step, device, steps, repeats, warmup=5)["steps_per_s"]
        out["variants"].append(v)
        print(f"N={n * n:>8} S={ns:>6} cell {cell_scale} level {level_scale} buckets {buckets}: "
              f"{v['steps_per_s']:,.0f} steps/s | binning {stages['binning']:.1f}, collide {stages['collide']:.1f} us "
              f"| levels {v['levels']} entries {v['entries']} same {v['same_contacts']}", flush=True)
        del g
    rates = {}
    for name in compare:
        w = world(name)
        rates[name] = time_loop(w.step, device, steps, repeats, warmup=5)["steps_per_s"]
        del w
    out["steps_per_s"] = rates
    print(f"N={n * n:>8} S={ns:>6} " + "  ".join(f"{k} {v:,.0f}" for k, v in rates.items()), flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--verts", default="100000,1000000")
    ap.add_argument("--spheres", default="5,1000,100000")
    ap.add_argument("--compare", default="refit", help="comma-separated colliders timed from the same state")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--settle", type=int, default=120, help="steps run before the state is copied")
    ap.add_argument("--variants", default="4/4/8",
                    help="comma-separated CELL/LEVEL/BUCKETS: choices.SPHERE_GRID_CELL_SCALE, _LEVEL_SCALE and "
                         "_BUCKETS_PER_SPHERE of each sphere_grid variant timed")
    ap.add_argument("--profile", type=int, default=0, help="on CUDA: time each kernel of this many eager collides")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    device = wp.get_device(args.device)
    out = checked_output(args.out or RESULTS / f"sphere_grid_probe_{'cuda' if device.is_cuda else 'cpu'}.json", "file",
                         "--out")
    res = {**describe_device(device), "args": vars(args), "rows": []}
    for nv in [int(float(v)) for v in args.verts.split(",")]:
        for ns in [int(float(v)) for v in args.spheres.split(",")]:
            variants = [tuple(float(x) for x in v.split("/")) for v in args.variants.split(",")]
            res["rows"].append(row(nv, ns, device, [c for c in args.compare.split(",") if c], args.steps, args.repeats,
                                   args.settle, variants, args.profile))
            write_json(out, res)


if __name__ == "__main__":
    main()
