"""Our sphere world vs Newton on the same deforming mesh, side by side in one run.

    python bench/bench_newton.py --device cpu        # -> bench/results/newton_cpu.json
    python bench/bench_newton.py --device cuda:0     # -> bench/results/newton_cuda.json

Paper scene: ../shared/data/horse_gallop.npz (8431 vertices, 16843 faces, 24 fps; Sumner &
Popovic 2004) when present, else a built-in surface of the same size; 5 spheres (r = 0.05 m,
1 kg) dropped on it, dt = 1/240 s, one sub-step per step, frames advancing at 24 fps with
interpolation, and (as in bench_step.py) a ground plane at the lowest vertex, so spheres that
slide off the surface stay in the scene (``--no-ground`` drops it). Engines: our ``World``
(default collider) and ``NewtonWorld`` with each solver in ``--solvers`` (Newton spheres of
the same radius and mass). Also timed alone: the adapter's per-sub-step surface update
(vertices + refit + collision bounds), which every Newton step pays.
Setup, compile/module load and graph capture are reported apart from the timed loop (warm-up,
then the median of repeats). On CUDA each step is one CUDA graph in both engines.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, describe_device, load_paper_sequence, time_loop, write_json  # noqa: E402

RADIUS = 0.05
DT = 1.0 / 240.0


def sphere_start(seq, count=5, seed=0):
    from dynmesh_warp.config import SpawnConfig, spawn_positions

    return spawn_positions(SpawnConfig(count=count, radius=RADIUS, height=0.05, seed=seed, spread=0.6), seq.V[0])


def build_ours(seq, device, pos, ground):
    from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, World

    surf = SurfaceModel(seq, device, playback="loop", interpolate=True)
    model = Model(surf, SphereModel(np.full(len(pos), RADIUS, np.float32), 1.0, device),
                  PhysicsParams(dt=DT, auto_substeps=False, ground_height=ground))
    return World(model, State(model, pos))


def build_newton(seq, device, pos, solver, ground):
    import newton

    from dynmesh_warp.newton_adapter import NewtonWorld
    from dynmesh_warp.world import SurfaceModel

    b = newton.ModelBuilder()
    density = 1.0 / (4.0 / 3.0 * np.pi * RADIUS**3)  # 1 kg spheres
    cfg = newton.ModelBuilder.ShapeConfig(density=density, mu=0.5)
    for p in pos:
        body = b.add_body(xform=wp.transform(wp.vec3(*[float(x) for x in p]), wp.quat_identity()))
        b.add_shape_sphere(body, radius=RADIUS, cfg=cfg)
    if ground is not None:
        b.add_ground_plane(height=ground, cfg=newton.ModelBuilder.ShapeConfig(mu=0.5))
    surf = SurfaceModel(seq, device, playback="loop", interpolate=True)
    return NewtonWorld(surf, b, dt=DT, substeps=1, solver=solver)


def timed(build, device):
    """Build, then the first two steps apart: NewtonWorld runs step 1 eagerly (loading, on a cold
    cache compiling, its modules) and captures the graph in step 2; our World loads its modules
    and captures in step 1."""
    t0 = time.perf_counter()
    w = build()
    wp.synchronize_device(device)
    t1 = time.perf_counter()
    w.step()
    wp.synchronize_device(device)
    t2 = time.perf_counter()
    w.step()
    wp.synchronize_device(device)
    t3 = time.perf_counter()
    return w, {"setup_s": t1 - t0, "step1_s": t2 - t1, "step2_s": t3 - t2,
               "first_2_steps_s (compile+capture)": t3 - t1}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--solvers", default="xpbd,featherstone", help="Newton solvers, comma separated")
    ap.add_argument("--steps", type=int, default=None, help="timed steps per repeat (default: 240 CUDA, 60 CPU)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--settle", type=float, default=0.25, help="simulated seconds run before reporting heights")
    ap.add_argument("--no-ground", action="store_true", help="no ground plane (spheres may fall off)")
    ap.add_argument("--builtin", action="store_true", help="use the built-in surface even if the data exists")
    ap.add_argument("--verbose", action="store_true", help="print Warp's module load/compile lines")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    wp.config.quiet = not args.verbose
    wp.init()
    device = wp.get_device(args.device)
    steps = args.steps or (240 if device.is_cuda else 60)
    seq, shared = load_paper_sequence(prefer_shared=not args.builtin)
    pos = sphere_start(seq)
    ground = None if args.no_ground else float(seq.V[:, :, 2].min())
    res = {"machine": describe_device(device), "scene": {
        "surface": seq.name, "source": seq.source if shared else "builtin (shared data absent)",
        "vertices": seq.num_vertices, "faces": seq.num_faces, "frames": seq.num_frames, "fps": seq.fps,
        "spheres": len(pos), "radius_m": RADIUS, "dt_s": DT, "substeps": 1, "ground_z_m": ground}, "engines": {}}
    try:
        import newton

        res["machine"]["newton"] = newton.__version__
    except ImportError:
        newton = None

    runs = [("ours", lambda: build_ours(seq, device, pos, ground))]
    if newton is not None:
        runs += [(f"newton_{s}", (lambda s=s: build_newton(seq, device, pos, s, ground))) for s in args.solvers.split(",") if s]
    for name, build in runs:
        try:
            w, info = timed(build, device)
        except Exception as e:  # noqa: BLE001 (a solver unavailable on this device: record why)
            res["engines"][name] = {"error": f"{type(e).__name__}: {e}"}
            print(f"{name}: skipped ({e})")
            continue
        info.update(time_loop(w.step, device, steps, repeats=args.repeats, warmup=args.warmup))
        if name.startswith("newton"):
            a = w.adapter
            info["adapter_update"] = time_loop(a.update, device, steps, repeats=args.repeats, warmup=5)
        # run on and report where the spheres are (scene-frame z [m])
        n_settle = int(round(args.settle / DT))
        for _ in range(n_settle):
            w.step()
        wp.synchronize_device(device)
        p = w.sphere_positions() if name == "ours" else w.body_transforms()[:, :3]
        info["after_run"] = {"sim_time_s": w.time, "sphere_z": p[:, 2].tolist(),
                                "finite": bool(np.isfinite(p).all())}
        res["engines"][name] = info
        print(f"{name}: {info['us_per_step']:.1f} us/step ({info['steps_per_s']:.0f} steps/s), "
              f"first 2 steps (compile+capture) {info['first_2_steps_s (compile+capture)']:.2f} s")
    out = Path(args.out) if args.out else RESULTS / f"newton_{'cuda' if device.is_cuda else 'cpu'}.json"
    write_json(out, res)


if __name__ == "__main__":
    main()
