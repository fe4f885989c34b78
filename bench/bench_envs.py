"""Batched environments (issue 15): env-steps/s vs num_envs on the paper scene.

horse_gallop (or the built-in stand-in), 5 spheres per env (radius 0.05 m, spawned over the
surface as bench_step's paper scene), dt 1/240, every env at its own random phase of the
gallop; loop playback. Timed after ``--warmup`` steps (2 s simulated: the spheres have landed
and ride the horse; timing them in the air would measure empty BVH queries). Per num_envs:
batched steps/s, env-steps/s (= steps/s x envs), spheres in contact at the end, memory (pair
BVHs once, per env). CUDA graph on a GPU.

    python bench/bench_envs.py --device cuda --envs 1,64,1024,4096,16384,65536
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import RESULTS, describe_device, load_paper_sequence, time_loop, write_json  # noqa: E402

#: spheres per env and their radius [m] of the batched paper scene
SPHERES_PER_ENV, RADIUS = 5, 0.05


def paper_envs_scene(device):
    """The batched benchmarks' scene (this file, profile_envs.py): (sequence, whether it is the
    shared data, the spawn positions of one env's spheres (S, 3) [m], physics, surface model)."""
    from dynmesh_warp.config import SpawnConfig, spawn_positions
    from dynmesh_warp.world import PhysicsParams, SurfaceModel

    seq, shared = load_paper_sequence()
    pos = spawn_positions(SpawnConfig(count=SPHERES_PER_ENV, radius=RADIUS, height=0.05, seed=0, spread=0.6),
                          seq.V[0])
    params = PhysicsParams(dt=1.0 / 240.0, auto_substeps=False, ground_height=float(seq.V[:, :, 2].min()))
    return seq, shared, pos, params, SurfaceModel(seq, device, playback="loop")


def random_phases(seq, num_envs: int) -> np.ndarray:
    """Each env's start time [s]: uniform over one playback of ``seq`` (seeded, the same every run)."""
    return np.random.default_rng(1).uniform(0.0, seq.num_frames / seq.fps, num_envs)


def main(argv=None):
    from dynmesh_warp.batch import BatchedWorld, BatchModel, BatchState

    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--envs", default="1,16,64,256,1024")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=480,
                    help="steps before timing (2 s: the spheres have landed and ride the surface)")
    ap.add_argument("--time-slices", type=int, default=None, help="slices per frame pair (default: batch.TIME_SLICES)")
    ap.add_argument("--search", default=None, help="the contact search: serial, tiled, hybrid, grid (default: the batch's)")
    ap.add_argument("--tile-threads", type=int, default=None, help="threads per block of the tiled/hybrid search")
    ap.add_argument("--budget", type=int, default=None, help="the hybrid's candidate budget per thread")
    ap.add_argument("--blocks", type=int, default=None, help="the hybrid's thread blocks")
    ap.add_argument("--grid-cell-radii", type=float, default=None,
                    help="the grid search's cell edge in sphere radii (default: batch.GRID_CELL_RADII)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.init()
    device = wp.get_device(a.device)
    seq, shared, pos, params, surf = paper_envs_scene(device)
    S, r = SPHERES_PER_ENV, RADIUS
    res = {"machine": describe_device(device), "scene": {"sequence": seq.name, "shared_data": shared,
           "frames": seq.num_frames, "faces": int(seq.F.shape[0]), "spheres_per_env": S, "radius": r,
           "dt": 1 / 240, "substeps": 1, "phase": "uniform random over one gallop", "warmup_steps": a.warmup,
           "timed_steps": a.steps}, "rows": []}
    for E in [int(x) for x in a.envs.split(",")]:
        t0 = time.perf_counter()
        bm = BatchModel(surf, E, np.full(S, r), 1.0, params,
                        **({"time_slices": a.time_slices} if a.time_slices else {}),
                        **({"grid_cell_radii": a.grid_cell_radii} if a.grid_cell_radii else {}))
        times = random_phases(seq, E)
        w = BatchedWorld(bm, BatchState(bm, pos, times=times), search=a.search,
                         tile_threads=a.tile_threads, budget=a.budget, blocks=a.blocks)
        w.step()
        w.capture()
        wp.synchronize_device(device)
        build_s = time.perf_counter() - t0
        t = time_loop(w.step, device, a.steps, repeats=a.repeats, warmup=a.warmup)
        P = w.sphere_positions()
        row = {"num_envs": E, **t, "env_steps_per_s": t["steps_per_s"] * E, "build_s": build_s,
               "cuda_graph": w.graph_captured, "final_finite": bool(np.isfinite(P).all()),
               "in_contact_final": w.contact_count(), "time_slices": bm.time_slices,
               "swept_search": str(w.search), "tile_threads": w.tile_threads if w.query is not None else None,
               "hybrid_budget": w.budget if str(w.search) == "hybrid" else None,
               "hybrid_blocks": w.blocks if str(w.search) == "hybrid" else None, "grid_cell_m": bm.grid_cell,
               "memory_bytes": w.memory_bytes}
        res["rows"].append(row)
        print(f"E={E:>6}: {t['steps_per_s']:>10,.0f} steps/s  {row['env_steps_per_s']:>14,.0f} env-steps/s  "
              f"mem/env {w.memory_bytes['per_env']} B", flush=True)
        del w, bm
    out = Path(a.out) if a.out else RESULTS / f"envs_{'cuda' if device.is_cuda else 'cpu'}.json"
    write_json(out, res)


if __name__ == "__main__":
    main()
