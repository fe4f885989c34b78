"""Graph conversion option sweep on the issue-12 protocol (docs/conversion.md): one sequence,
one key frame ("auto" or an index), ``key_candidates`` 0 (one run each), CD (DG-Mesh
convention: vertices, squared) of every third frame against the ground truth, against the
varying input's. Used to choose the fine stage's defaults (iterations, smoothing).

    python bench/fine_stage_sweep.py chicken_crossing 102 '[{}, {"iterations": 6, "smooth_iterations": 1}]' \
        --out bench/results/fine_stage_sweep_chicken_cpu.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import describe_device, write_json  # noqa: E402
from conversion_eval import ground_truth, varying_input  # noqa: E402


def main(argv=None):
    from dynmesh_warp.convert import to_fixed_topology
    from dynmesh_warp.metrics import chamfer_distance

    ap = argparse.ArgumentParser()
    ap.add_argument("sequence")
    ap.add_argument("key", help='"auto" or a frame index')
    ap.add_argument("variants", help="JSON list of graph option dicts")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cache", default=str(Path(__file__).resolve().parents[1] / "out" / "cache"))
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    gt = ground_truth(a.sequence, None)
    if gt is None:
        raise SystemExit(f"{a.sequence}: not found")
    var = varying_input(gt, 96, 0.01, a.device, Path(a.cache))

    def cd(A, B):
        return chamfer_distance(A, B, squared=True, device=a.device).value

    ts = range(0, gt.num_frames, 3)
    cin = float(np.mean([cd(var.frames[t][0], gt.V[t]) for t in ts]))
    res = {"machine": describe_device(wp.get_device(a.device)), "sequence": a.sequence, "key": a.key,
           "protocol": "issue 12: remesh resolution 96, 1 % smooth error; CD on every third frame",
           "input_cd": cin, "runs": []}
    for v in json.loads(a.variants):
        opts = dict(key_candidates=0, **v)
        if a.key != "auto":
            opts["key_frame"] = int(a.key)
        t0 = time.perf_counter()
        fx = to_fixed_topology(var, strategy="graph", device=a.device, **opts)
        s = time.perf_counter() - t0
        co = float(np.mean([cd(fx.V[t], gt.V[t]) for t in ts]))
        row = {"options": v, "cd": co, "cd_increase_pct": 100 * (co / cin - 1),
               "coverage_mean": float(np.mean(fx.conversion.coverage)), "seconds": s}
        res["runs"].append(row)
        print(f"{a.sequence} key {a.key} {json.dumps(v):60s} CD {co * 1e3:.4f} vs in {cin * 1e3:.4f}: "
              f"{row['cd_increase_pct']:+.1f}%  cov {row['coverage_mean']:.4f} {s:.0f}s", flush=True)
    if a.out:
        write_json(Path(a.out), res)


if __name__ == "__main__":
    main()
