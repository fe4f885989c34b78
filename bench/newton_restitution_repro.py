"""Is XPBD with restitution reproducible from run to run? The same Newton scene (wave_bowl, a box
and two spheres, XPBD) stepped twice per setting, one world and four replicated worlds, with
restitution 0 and 0.3; reports the largest body-pose difference between the two runs and between
the replicated worlds and the one-world run (docs/newton.md).

    python bench/newton_restitution_repro.py --device cuda:0 --out bench/results/newton_restitution_repro_cuda_h100.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import describe_device, write_json  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, default=120)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.newton_adapter import build_newton_world

    out = {"machine": describe_device(a.device), "steps": a.steps, "rows": []}
    for rest in (0.0, 0.3):
        data = {"device": a.device, "surface": {"source": "builtin:wave_bowl", "params": {"n": 10, "frames": 6}},
                "spheres": {"count": 2, "radius": 0.06, "seed": 3},
                "physics": {"ground": "auto", "restitution": rest},
                "newton": {"solver": "xpbd", "bodies": [{"type": "box", "position": [0.1, 0.0, 1.0],
                                                          "half_extents": [0.08, 0.08, 0.05]}]}}
        runs = {}
        for name, n in (("one_a", 1), ("one_b", 1), ("four", 4)):
            w = build_newton_world(load_scene_config(data=data), num_worlds=n)
            for _ in range(a.steps):
                w.step()
            runs[name] = w.body_transforms().reshape(n, 3, -1)
        row = {"restitution": rest,
               "one_world_run_to_run_max_diff": float(np.abs(runs["one_a"] - runs["one_b"]).max()),
               "replicated_vs_one_world_max_diff": float(np.abs(runs["four"] - runs["one_a"][0]).max())}
        print(row, flush=True)
        out["rows"].append(row)
    if a.out:
        write_json(Path(a.out), out)
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
