"""Step benchmark: the fixed-topology step vs the rebuild baseline, per-stage breakdown,
launch floor, and scaling over vertex and sphere counts.

    python bench/bench_step.py --device cpu            # -> bench/results/step_cpu.json
    python bench/bench_step.py --device cuda:0         # -> bench/results/step_cuda.json

Paper scene: ../shared/data/horse_gallop.npz (8431 vertices, 16843 faces, 24 fps; Sumner &
Popovic 2004) when present, else a built-in surface of the same size; 5 spheres dropped on it,
dt = 1/240 s, frames advancing at 24 fps with interpolation, one sub-step per step
(auto_substeps off so every collider does the same work), and a ground plane at the lowest
surface point so spheres that roll off the horse come to rest instead of falling forever. Colliders, in the same run:
swept (the default with interpolation), refit (BVH refit every step), rebuild every step,
rebuild on frame change. Compile/module-load time and graph capture are reported apart from
the timed loop (warm-up, then the median of repeats). On CUDA the fixed step is one graph.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, describe_device, load_paper_sequence, time_loop, write_json  # noqa: E402


#: number the spawned spheres along a Morton curve of their positions (--spatial-order: what a
#: user who orders their bodies spatially gets; the default keeps the spawn's random order)
SPATIAL_ORDER = False


def make_world(seq, device, collider, spheres=5, radius=0.05, rebuild_every="step", seed=0, spread=0.6,
               interpolate=True, swept_search=None):
    from dynmesh_warp.config import SpawnConfig, spawn_positions
    from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, World

    surf = SurfaceModel(seq, device, playback="loop", interpolate=interpolate)
    pos = spawn_positions(SpawnConfig(count=spheres, radius=radius, height=0.05, seed=seed, spread=spread), seq.V[0])
    if spheres > 50:  # many spheres: a single layer just above the surface, not a tall column
        pos[:, 2] = seq.V[0][:, 2].max() + radius * (1.0 + np.random.default_rng(seed).random(spheres))
    if SPATIAL_ORDER:  # the same spheres numbered along a Morton curve (--spatial-order)
        from dynmesh_warp.kernels.tree import morton_codes

        pos = pos[np.argsort(morton_codes(pos), kind="stable")]
    model = Model(surf, SphereModel(np.full(spheres, radius, np.float32), 1.0, device),
                  PhysicsParams(dt=1.0 / 240.0, auto_substeps=False, ground_height=float(seq.V[:, :, 2].min()),
                                swept_search=swept_search))
    return World(model, State(model, pos), collider=collider, rebuild_every=rebuild_every)


def timed_build(seq, device, collider, **kw):
    import warp as wp

    t0 = time.perf_counter()
    w = make_world(seq, device, collider, **kw)
    t1 = time.perf_counter()
    w.step()  # compiles/loads the step's modules (an eager step)
    w.capture()  # the CUDA graph (nothing on the CPU)
    wp.synchronize_device(device)
    t2 = time.perf_counter()
    return w, {"build_s": t1 - t0, "first_step_s (compile+capture)": t2 - t1}


def graph_or_eager(fn, device):
    """A callable replaying fn: captured as a CUDA graph on CUDA, eager on the CPU."""
    import warp as wp

    d = wp.get_device(device)
    if not d.is_cuda:
        return fn
    fn()
    with wp.ScopedCapture(device=d) as cap:
        fn()
    g = cap.graph
    return lambda: wp.capture_launch(g)


def stage_breakdown(seq, device, steps, repeats):
    """Each stage alone, replayed like the step (graph on CUDA)."""
    import warp as wp

    out = {}
    w, _ = timed_build(seq, device, "refit")
    st = {
        "frame_copy_interp": w.update_surface,
        "normals": w.compute_normals,
        "refit": lambda: w.collider.mesh.refit(),
        "contact": lambda: w.collider.collide(w.model, w.state, w.contacts, w.ctx),
        "integrate_and_advance_time": w.integrate,
    }
    out["refit_step"] = {k: time_loop(graph_or_eager(f, device), device, steps, repeats)["us_per_step"]
                         for k, f in st.items()}
    ws, _ = timed_build(seq, device, "swept")
    c = ws.collider
    st = {
        "conditional_refit_node (not taken)": lambda: c.update(ws.model, ws.state, ws.ctx),
        "contact_interpolated": lambda: c.collide(ws.model, ws.state, ws.contacts, ws.ctx),
        "integrate_advance_time_frame_test": ws.integrate,
        "swept_bounds_and_bvh_refit (once per frame)": lambda: c.refit_frame(ws.model, ws.state, ws.ctx),
    }
    out["swept_step"] = {k: time_loop(graph_or_eager(f, device), device, steps, repeats)["us_per_step"]
                         for k, f in st.items()}
    s = w.state
    idx = w.model.surface.indices
    out["rebuild"] = {"bvh_build (wp.Mesh)": time_loop(lambda: wp.Mesh(points=s.points, indices=idx), device,
                                                       max(5, steps // 50), repeats)["us_per_step"]}
    return out


@wp.kernel
def do_nothing(x: wp.array(dtype=float)):
    pass


def launch_floor(seq, device, steps, repeats, launch_counts):
    """The floor under a step: graphs of K empty kernels (with and without an empty conditional
    node, as the swept step has); a D2D copy of the vertex buffer."""
    d = wp.get_device(device)
    x = wp.zeros(1, dtype=float, device=d)
    flag = wp.zeros(1, dtype=wp.int32, device=d)
    src = wp.array(seq.V[0], dtype=wp.vec3, device=d)
    dst = wp.zeros_like(src)
    res = {}

    def empty(k):
        for _ in range(k):
            wp.launch(do_nothing, 1, inputs=[x], device=d)

    for k in sorted(set(launch_counts)):
        res[f"empty_launches_{k}"] = time_loop(graph_or_eager(lambda k=k: empty(k), d), d, steps, repeats)["us_per_step"]
        res[f"empty_launches_{k}_plus_conditional"] = time_loop(graph_or_eager(
            lambda k=k: (wp.capture_if(flag, on_true=lambda: empty(1)), empty(k)), d), d, steps, repeats)["us_per_step"]
    res["d2d_copy_vertex_buffer"] = time_loop(graph_or_eager(lambda: wp.copy(dst, src), d), d, steps,
                                              repeats)["us_per_step"]
    return res


def wave_grid(n: int, frames: int = 4, fps: float = 24.0):
    from dynmesh_warp.scenes import grid_sheet
    from dynmesh_warp.sequence import FixedTopologySequence

    V0, F = grid_sheet(n, 2.0)
    V = np.repeat(V0[None], frames, 0)
    for t in range(frames):
        V[t, :, 2] = 0.05 * np.sin(3 * V0[:, 0] + 2 * np.pi * t / frames) * np.cos(2 * V0[:, 1])
    return FixedTopologySequence(V, F, fps, f"grid{n}")


def mem_used(device):
    import warp as wp

    d = wp.get_device(device)
    if d.is_cuda and wp.is_mempool_enabled(d):
        return int(wp.get_mempool_used_mem_current(d))
    return None


def scaling(device, verts, spheres, colliders, steps, repeats):
    import warp as wp

    rows = []
    for nv in verts:
        n = int(round(np.sqrt(nv)))
        seq = wave_grid(n)
        for ns in spheres:
            radius = float(min(0.05, 0.5 / np.sqrt(ns)))
            for col in colliders:
                if col.startswith("rebuild") and wp.get_device(device).is_cpu and nv > 2e5:
                    continue
                # free the previous row's world first: it was still alive during the next build
                # and its release between m0 and m1 made the H100 figures negative in some rows
                w = None
                gc.collect()
                wp.synchronize_device(device)
                m0 = mem_used(device)
                # "swept/serial": the swept collider with that search (physics.swept_search)
                base, _, search = col.partition("/")
                w, comp = timed_build(seq, device, base, spheres=ns, radius=radius, spread=0.9,
                                      rebuild_every="step", swept_search=search or None)
                m1 = mem_used(device)
                nsteps = steps if not col.startswith("rebuild") else max(3, steps // 20)
                if wp.get_device(device).is_cpu:
                    # keep >= 2 frame intervals (10 steps each) in the timed loop, so the per-frame
                    # work of the swept collider is always included
                    floor = 3 if col.startswith("rebuild") else 20
                    nsteps = max(floor, int(nsteps * min(1.0, 2e4 / nv)))
                t = time_loop(w.step, device, nsteps, repeats, warmup=3)
                rows.append({"vertices": n * n, "faces": 2 * (n - 1) ** 2, "spheres": ns, "collider": col,
                             "steps_per_s": t["steps_per_s"], "us_per_step": t["us_per_step"],
                             "device_mem_bytes": None if m0 is None else m1 - m0, **comp})
                if w.collider.name == "swept":
                    rows[-1]["swept_search"] = str(w.collider.search)
                if col == "fixed":  # the automatic choice: what it measured and kept
                    rows[-1]["chosen"] = w.collider.name
                    rows[-1]["measured_steps_per_s"] = {k: 1.0 / v for k, v in (w.collider_costs or {}).items()}
                print(f"  N={n*n:>8} S={ns:>6} {col:<8} {t['steps_per_s']:>10.0f} steps/s"
                      + (f" (chose {w.collider.name})" if col == "fixed" else ""), flush=True)
                del w
    return rows


def fixed_vs_best(rows) -> list:
    """Per (vertices, spheres): the automatic choice's time per step over the best collider's
    (issue 14: never more than 1.2)."""
    out = []
    for key in sorted({(r["vertices"], r["spheres"]) for r in rows}):
        grp = {r["collider"]: r for r in rows if (r["vertices"], r["spheres"]) == key}
        if "fixed" not in grp:
            continue
        # the colliders a scene can name (the swept searches beside them are reported, not compared)
        best = max((r for c, r in grp.items() if c != "fixed" and "/" not in c), key=lambda r: r["steps_per_s"])
        # and against every timed column, a swept search named in physics.swept_search included
        best_any = max((r for c, r in grp.items() if c != "fixed"), key=lambda r: r["steps_per_s"])
        out.append({"vertices": key[0], "spheres": key[1], "chosen": grp["fixed"].get("chosen"),
                    "chosen_search": grp["fixed"].get("swept_search"),
                    "best": best["collider"], "fixed_steps_per_s": grp["fixed"]["steps_per_s"],
                    "best_steps_per_s": best["steps_per_s"],
                    "slowdown_vs_best": best["steps_per_s"] / grp["fixed"]["steps_per_s"],
                    "best_column": best_any["collider"],
                    "slowdown_vs_best_column": best_any["steps_per_s"] / grp["fixed"]["steps_per_s"]})
        print(f"  N={key[0]:>8} S={key[1]:>6} fixed chose {out[-1]['chosen']}, best {best['collider']}: "
              f"{out[-1]['slowdown_vs_best']:.2f}x the best's time", flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--no-scaling", action="store_true")
    ap.add_argument("--out", default=None)
    ap.add_argument("--scaling-only", action="store_true", help="skip the paper scene and the stage breakdown")
    ap.add_argument("--verts", default=None, help="comma-separated vertex counts of the scaling table")
    ap.add_argument("--spheres", default=None, help="comma-separated sphere counts of the scaling table")
    ap.add_argument("--colliders", default=None, help="comma-separated colliders of the scaling table "
                    "(fixed, swept, swept/serial, swept/tiled, refit, rebuild)")
    ap.add_argument("--refit-bvh", default=None, metavar="CTOR:LEAF",
                    help="the refit collider's BVH for this run, e.g. sah:8 (default: choices.REFIT_BVH)")
    ap.add_argument("--refit-seed", choices=("on", "off"), default=None,
                    help="the refit collider's seeded query for this run (default: choices.SEED_REFIT_QUERY)")
    ap.add_argument("--spatial-order", action="store_true",
                    help="number the spheres along a Morton curve of their spawn positions (default: random order)")
    args = ap.parse_args(argv)
    global SPATIAL_ORDER
    SPATIAL_ORDER = bool(args.spatial_order)
    if args.refit_bvh:  # an A/B of the refit path's tree: set for this process only
        from dynmesh_warp import choices

        ctor, _, leaf = args.refit_bvh.partition(":")
        for kind in choices.REFIT_BVH:
            choices.REFIT_BVH[kind] = (ctor, int(leaf or 4))
    if args.refit_seed:  # an A/B of the refit path's seeded query: set for this process only
        from dynmesh_warp import choices

        for kind in choices.SEED_REFIT_QUERY:
            choices.SEED_REFIT_QUERY[kind] = args.refit_seed == "on"
    import warp as wp

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    dev_key = "cuda" if device.is_cuda else "cpu"
    out = Path(args.out) if args.out else RESULTS / f"step_{dev_key}.json"
    seq, shared = load_paper_sequence()
    from dynmesh_warp.choices import REFIT_BVH

    from dynmesh_warp.choices import SEED_REFIT_QUERY

    result = {"machine": describe_device(device), "refit_bvh": list(REFIT_BVH["cuda" if device.is_cuda else "cpu"]),
              "refit_seed": bool(SEED_REFIT_QUERY["cuda" if device.is_cuda else "cpu"]),
              "paper_scene": {
        "sequence": seq.name, "from_shared_data": shared, "vertices": seq.num_vertices, "faces": seq.num_faces,
        "frames": seq.num_frames, "fps": seq.fps, "spheres": 5, "radius": 0.05, "dt": 1 / 240, "substeps": 1,
        "interpolate": True}}
    print(f"device {device} ({result['machine']['device_name']}), paper scene {seq.name}", flush=True)
    paper = {}
    variants = [("swept/serial", None)] if device.is_cuda else []
    for col, every in ([] if args.scaling_only else
                       [("fixed", None), ("swept", None), *variants, ("refit", None), ("rebuild", "step"),
                        ("rebuild", "frame")]):
        name = col if every is None else f"rebuild_every_{every}"
        base, _, search = col.partition("/")
        # rebuilding only on frame change is valid when the surface changes only per frame:
        # that variant runs with interpolation off (frames held), as a varying-topology method would
        w, comp = timed_build(seq, device, base, rebuild_every=every or "step", interpolate=every != "frame",
                              swept_search=search or None)
        n = args.steps if col != "rebuild" else max(20, args.steps // (20 if every == "step" else 4))
        t = time_loop(w.step, device, n, args.repeats)
        paper[name] = {**t, **comp, "cuda_graph": bool(w.use_graph), "interpolate": bool(w.model.surface.interpolate)}
        pos = w.sphere_positions()
        paper[name]["final_finite"] = bool(np.isfinite(pos).all())
        if col == "fixed":
            paper[name]["chosen"] = w.collider.name
            paper[name]["measured_steps_per_s"] = {k: 1.0 / v for k, v in (w.collider_costs or {}).items()}
        if w.collider.name == "swept":
            paper[name]["swept_search"] = str(w.collider.search)
        print(f"  {name:<22} {t['steps_per_s']:>10.0f} steps/s  ({t['us_per_step']:.1f} us)", flush=True)
        del w
    for k in ("swept", "refit") if paper else ():
        paper[f"speedup_{k}_vs_rebuild_every_step"] = paper[k]["steps_per_s"] / paper["rebuild_every_step"]["steps_per_s"]
        paper[f"speedup_{k}_vs_rebuild_every_frame"] = paper[k]["steps_per_s"] / paper["rebuild_every_frame"]["steps_per_s"]
    result["paper"] = paper
    if args.scaling_only:
        stages = {}
    else:
        stages = stage_breakdown(seq, device, max(200, args.steps // 4), args.repeats)
        result["stages_us"] = stages
        result["floor_us"] = launch_floor(seq, device, max(200, args.steps // 2), args.repeats, [3, 4, 10])
    result.setdefault("floor_us", {})["note"] = (
        "empty_launches_K: a graph (CUDA) or eager loop (CPU) of K empty kernels; _plus_conditional adds an "
        "empty conditional node. The swept step (parallel path) is 3 launches + 1 conditional node (evaluate, "
        "resolve, integrate); the refit step is 4 launches (interpolate, normals, contact, integrate) plus "
        "wp.Mesh.refit's 6 (edge lengths, scan, average, bounds, memset, bottom-up refit)")
    print("  stages:", {k: {a: round(b, 2) for a, b in v.items()} for k, v in stages.items()}, flush=True)
    print("  floor:", result["floor_us"], flush=True)
    if not args.no_scaling:
        if device.is_cuda:
            verts, sph = [1_000, 10_000, 100_000, 1_000_000], [5, 1_000, 100_000]
            st = 300
        else:
            verts, sph = [1_000, 10_000, 100_000, 1_000_000], [5, 1_000, 10_000]
            st = 200
        verts = [int(float(v)) for v in args.verts.split(",")] if args.verts else verts
        sph = [int(float(v)) for v in args.spheres.split(",")] if args.spheres else sph
        cols = ["fixed", "swept", "refit", "rebuild"]
        if device.is_cuda:  # the swept collider's other search (the default is tiled on CUDA)
            cols[2:2] = ["swept/serial"]
        cols = args.colliders.split(",") if args.colliders else cols
        result["scaling"] = scaling(device, verts, sph, cols, st, 3)
        result["fixed_vs_best"] = fixed_vs_best(result["scaling"])
    write_json(out, result)


if __name__ == "__main__":
    main()
