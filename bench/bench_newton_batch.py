"""The same batched task in Newton's own batching and in ours, side by side (issue 15).

The paper scene (horse_gallop, or the built-in stand-in without ../shared): E envs of 5
spheres (radius 0.05 m, spawned as the paper scene), dt 1/240, loop playback, ground plane.

- **Newton**: the scene's spheres built once and replicated into E Newton worlds
  (``build_newton_world(..., num_worlds=E)``: ``ModelBuilder.replicate``), the deforming surface
  a global mesh shape shared by every world (refit once per step), Newton's collision pipeline
  and solver (``--solver``, default xpbd); one CUDA graph per step on a GPU. Newton has one
  clock: every world sees the surface at the same time.
- **ours, one clock**: ``batch.BatchedWorld`` with every env at the same phase (the same work
  as Newton's).
- **ours, own clocks**: every env at its own random phase (what Newton cannot do with one mesh).

Timed after ``--warmup`` steps (the spheres have landed), steps/s and env-steps/s per E.

    python bench/bench_newton_batch.py --device cuda --envs 1,64,1024,4096
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

from bench_envs import random_phases  # noqa: E402
from common import RESULTS, describe_device, load_paper_sequence, time_loop, write_json  # noqa: E402


def main(argv=None):
    from dynmesh_warp import load_scene_config
    from dynmesh_warp.batch import BatchedWorld, BatchModel, BatchState
    from dynmesh_warp.config import SpawnConfig, spawn_positions
    from dynmesh_warp.newton_adapter import build_newton_world
    from dynmesh_warp.world import PhysicsParams, SurfaceModel

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--envs", default="1,16,64")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=240)
    ap.add_argument("--solver", default="xpbd")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    device = wp.get_device(a.device)
    seq, shared = load_paper_sequence()
    S, r = 5, 0.05
    pos = spawn_positions(SpawnConfig(count=S, radius=r, height=0.05, seed=0, spread=0.6), seq.V[0])
    ground = float(seq.V[:, :, 2].min())
    cfg = load_scene_config(data={
        "name": "newton_batch", "surface": {"source": "builtin:wave_bowl", "playback": "loop"},
        "spheres": [{"position": p.tolist(), "radius": r} for p in pos],
        "physics": {"dt": 1.0 / 240.0, "auto_substeps": False, "ground": ground},
        "newton": {"solver": a.solver}})
    res = {"machine": describe_device(device), "scene": {"sequence": seq.name, "shared_data": shared,
           "faces": int(seq.F.shape[0]), "spheres_per_env": S, "radius": r, "dt": 1 / 240, "solver": a.solver,
           "warmup_steps": a.warmup, "timed_steps": a.steps}, "rows": []}
    params = PhysicsParams(dt=1.0 / 240.0, auto_substeps=False, ground_height=ground)
    surf = SurfaceModel(seq, device, playback="loop")
    for E in [int(x) for x in a.envs.split(",")]:
        row = {"num_envs": E}
        t0 = time.perf_counter()
        nw = build_newton_world(cfg, device=device, sequence=seq, num_worlds=E)
        nw.step()
        nw.capture()
        wp.synchronize_device(device)
        row["newton_build_s"] = time.perf_counter() - t0
        t = time_loop(nw.step, device, a.steps, repeats=a.repeats, warmup=a.warmup)
        row["newton"] = {**t, "env_steps_per_s": t["steps_per_s"] * E, "cuda_graph": nw.graph_captured,
                         "bodies": int(nw.model.body_count)}
        del nw
        for name, times in (("ours_one_clock", np.zeros(E)),
                            ("ours_own_clocks", random_phases(seq, E))):
            bm = BatchModel(surf, E, np.full(S, r), 1.0, params)
            w = BatchedWorld(bm, BatchState(bm, pos, times=times))
            w.step()
            w.capture()
            t = time_loop(w.step, device, a.steps, repeats=a.repeats, warmup=a.warmup)
            row[name] = {**t, "env_steps_per_s": t["steps_per_s"] * E, "cuda_graph": w.graph_captured,
                         "in_contact_final": w.contact_count()}
            del w, bm
        row["ours_one_clock_over_newton"] = row["ours_one_clock"]["steps_per_s"] / row["newton"]["steps_per_s"]
        res["rows"].append(row)
        print(f"E={E:>6}: newton {row['newton']['steps_per_s']:>10,.0f} steps/s, ours (one clock) "
              f"{row['ours_one_clock']['steps_per_s']:>10,.0f}, ours (own clocks) {row['ours_own_clocks']['steps_per_s']:>10,.0f}"
              f" -> {row['ours_one_clock_over_newton']:.1f}x", flush=True)
    out = Path(a.out) if a.out else RESULTS / f"newton_batch_{'cuda' if device.is_cuda else 'cpu'}.json"
    write_json(out, res)


if __name__ == "__main__":
    main()
