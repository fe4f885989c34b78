"""Gaussian splat update benchmark: per-frame update of 100k mesh-bound Gaussians vs the physics step.

Scene: ../shared/data/horse_gallop.npz (Sumner & Popovic 2004; 8431 vertices, 16843 faces) when
present, else a built-in surface of similar size; 5 spheres, dt = 1/240 s, default collider.
100k Gaussians are generated (seeded, area-weighted) on frame 0. Timed, each the median of
repeats after a warm-up (module compile/load timed separately, first):

- update_kernel: ``update_gaussians`` alone (centres, rotations, scales, covariances);
- physics_step: ``world.step()`` without Gaussians; step_with_gaussians: with the update as a
  post-step hook (on CUDA both are one captured graph);
- viewer_pack: what the viewer does per frame on top: float16 clamped covariances
  (``pack_splat_covariances``) + device->host copy of centres and covariances + buffer packing.

    python bench/bench_gaussians.py --device cpu    # -> bench/results/gaussians_cpu.json
    python bench/bench_gaussians.py --device cuda   # -> bench/results/gaussians_cuda.json
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


def make_world(seq, device):
    from dynmesh_warp.config import SpawnConfig, spawn_positions
    from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, World

    surf = SurfaceModel(seq, device)
    r = 0.02 * float(np.linalg.norm(seq.V[0].max(0) - seq.V[0].min(0)))
    pos = spawn_positions(SpawnConfig(count=5, radius=r, height=2 * r, seed=0), seq.V[0])
    model = Model(surf, SphereModel(np.full(5, r, np.float32), 1.0, device),
                  PhysicsParams(dt=1 / 240, auto_substeps=False))
    return World(model, State(model, pos))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default=None)
    ap.add_argument("--count", type=int, default=100_000)
    ap.add_argument("--steps", type=int, default=None, help="calls per repeat (default: 200 CUDA, 20 CPU)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(a.device)
    steps = a.steps or (200 if device.is_cuda else 20)
    from dynmesh_warp.gaussians import generate_gaussians
    from dynmesh_warp.viewer import MIN_RATIO, MIN_SCALE_REL

    seq, real = load_paper_sequence()
    res = {"benchmark": "gaussians", "machine": describe_device(device),
           "scene": {"name": seq.name, "source": seq.source if real else "builtin (shared data absent)",
                     "vertices": seq.num_vertices, "faces": seq.num_faces},
           "gaussians": a.count, "steps_per_repeat": steps, "repeats": a.repeats}

    g = generate_gaussians(seq.V[0], seq.F, count=a.count, seed=0, device=device)
    pts = wp.array(seq.V[1], dtype=wp.vec3, device=device)
    idx = wp.array(seq.F.reshape(-1), dtype=wp.int32, device=device)
    t0 = time.perf_counter()
    g.update(pts, idx)  # first launch: compile or load the kernel module
    wp.synchronize_device(device)
    res["compile_or_load_s"] = time.perf_counter() - t0
    # the update as it runs inside the step: replayed from a CUDA graph (eager on the CPU)
    upd = lambda: g.update(pts, idx)  # noqa: E731
    if device.is_cuda:
        with wp.ScopedCapture(device=device) as cap:
            upd()
        graph = cap.graph
        res["update_kernel"] = time_loop(lambda: wp.capture_launch(graph), device, steps, a.repeats, warmup=5)
        res["update_kernel"]["cuda_graph"] = True
    else:
        res["update_kernel"] = time_loop(upd, device, steps, a.repeats, warmup=5)
    res["update_eager_launch"] = time_loop(upd, device, steps, a.repeats, warmup=5)  # incl. Python launch cost

    scale = float(np.linalg.norm(seq.V[0].max(0) - seq.V[0].min(0)))
    centers16 = np.empty((a.count, 8), np.uint32)

    def viewer_pack():
        cov = g.splat_covariances_f16(MIN_SCALE_REL * scale, MIN_RATIO)
        c = g.state.centers.numpy()
        centers16[:, 0:3] = np.ascontiguousarray(c, np.float32).view(np.uint32)
        centers16[:, 4:7] = cov.view(np.uint32)

    res["viewer_pack"] = time_loop(viewer_pack, device, max(5, steps // 10), a.repeats, warmup=2)

    world = make_world(seq, device)
    t0 = time.perf_counter()
    world.step()
    wp.synchronize_device(device)
    res["physics_compile_or_load_s"] = time.perf_counter() - t0
    res["physics_step"] = time_loop(world.step, device, steps, a.repeats, warmup=10)
    res["collider"] = world.collider.name
    res["cuda_graph"] = bool(world.use_graph)
    g.attach(world)
    world.step()
    wp.synchronize_device(device)
    res["step_with_gaussians"] = time_loop(world.step, device, steps, a.repeats, warmup=10)
    u = res["update_kernel"]["us_per_step"]
    p = res["physics_step"]["us_per_step"]
    res["update_over_step"] = u / p
    res["hook_overhead_us"] = res["step_with_gaussians"]["us_per_step"] - p
    out = Path(a.out) if a.out else RESULTS / f"gaussians_{str(device).split(':')[0]}.json"
    write_json(out, res)
    print(f"{a.count} Gaussians on {device}: update {u:.0f} us, physics step {p:.0f} us "
          f"(ratio {u / p:.2f}); step+gaussians {res['step_with_gaussians']['us_per_step']:.0f} us; "
          f"viewer pack {res['viewer_pack']['us_per_step']:.0f} us")


if __name__ == "__main__":
    main()
