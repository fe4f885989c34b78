"""Where a batched step's time goes (issue 15): each kernel's device time (``wp.timing_begin``,
CUDA events) and each launch timed alone from the host (synchronised before and after), in the
landing window of bench_envs (horse_gallop, 5
spheres per env, random phases, ``--warmup`` steps after the drop), per contact search; and, for
the hybrid, how many spheres its threads hand over to the blocks per sub-step.

    python bench/profile_envs.py --device cuda --envs 4096 --out bench/results/profile_envs_cuda.json
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

from bench_envs import RADIUS, SPHERES_PER_ENV, paper_envs_scene, random_phases  # noqa: E402
from common import describe_device, write_json  # noqa: E402


def main(argv=None):
    import dynmesh_warp.batch as B

    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--envs", type=int, default=4096)
    ap.add_argument("--warmup", type=int, default=40)
    ap.add_argument("--steps", type=int, default=80)
    ap.add_argument("--searches", default="grid,hybrid,tiled,serial")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.init()
    device = wp.get_device(a.device)
    seq, shared, pos, params, surf = paper_envs_scene(device)
    S, r = SPHERES_PER_ENV, RADIUS
    res = {"machine": describe_device(device), "sequence": seq.name, "shared_data": shared, "envs": a.envs,
           "warmup": a.warmup, "steps": a.steps, "searches": {}}
    for search in a.searches.split(","):
        bm = B.BatchModel(surf, a.envs, np.full(S, r), 1.0, params)
        times = random_phases(seq, a.envs)
        w = B.BatchedWorld(bm, B.BatchState(bm, pos, times=times), search=search, use_graph=False)
        for _ in range(a.warmup):
            w.step()
        wp.synchronize_device(device)
        stages: dict = {}
        launch, tiled = B.wp.launch, B.wp.launch_tiled

        def wrap(fn):
            def call(kernel, *args, **kw):
                wp.synchronize_device(device)
                t0 = time.perf_counter()
                out = fn(kernel, *args, **kw)
                wp.synchronize_device(device)
                stages[kernel.key] = stages.get(kernel.key, 0.0) + (time.perf_counter() - t0) * 1e6
                return out
            return call

        handed = []
        device_us: dict = {}
        if device.is_cuda:  # device time per kernel (CUDA events around each launch), no host in it
            wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_KERNEL_BUILTIN)
            for _ in range(a.steps):
                w.step()
            for t in wp.timing_end():
                device_us[t.name] = device_us.get(t.name, 0.0) + t.elapsed * 1e3 / a.steps
        B.wp.launch, B.wp.launch_tiled = wrap(launch), wrap(tiled)
        try:
            for _ in range(a.steps):
                w.step()
                if w.query is not None and search == "hybrid":
                    handed.append(int(w.query.heavy_count.numpy()[0]))
        finally:
            B.wp.launch, B.wp.launch_tiled = launch, tiled
        row = {"us_per_step": {k: v / a.steps for k, v in stages.items()}, "device_us_per_step": device_us,
               "in_contact": w.contact_count(), "spheres": a.envs * S}
        if handed:
            row["handed_to_blocks_mean"] = float(np.mean(handed))
        res["searches"][search] = row
        print(search, {k: round(v, 1) for k, v in row["us_per_step"].items()}, "in contact", row["in_contact"],
              "handed", row.get("handed_to_blocks_mean"), flush=True)
        print("  device us/step:", {k: round(v, 1) for k, v in device_us.items()}, flush=True)
        del w, bm
    if a.out:
        write_json(a.out, res)


if __name__ == "__main__":
    main()
