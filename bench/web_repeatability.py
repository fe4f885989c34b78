"""How much the web trigger's outcome on the starfish curling at twice the speed (the case of
``tests/test_segments.py::test_web_restarts_the_fit_on_fast_curling_arms``) moves from run to run
on a device: per run, with the web trigger off and on, the per-frame web and coverage and the
recovered frames.

    python bench/web_repeatability.py cuda:0 3 bench/results/web_repeatability_cuda_h200.json
    python bench/web_repeatability.py cuda:0 3 OUT.json '{"deterministic": true}'   # options as JSON
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np

from dynmesh_warp.convert import to_fixed_topology
from dynmesh_warp.remesh import remesh_sequence
from dynmesh_warp.scenes import starfish


def main(device: str, reps: int, out: str, options: dict) -> None:
    gt = starfish(frames=24, curl=1.6, resolution=64)
    var = remesh_sequence(gt, resolution=48, error=0.0, device=device)
    result = {"device": device, "options": options, "runs": []}
    for rep in range(reps):
        for web in (False, True):
            t0 = time.time()
            c = to_fixed_topology(var, device=device, restart_on_web=web, converge_iterations=0, **options).conversion
            run = {"rep": rep, "web_on": web, "web": [round(float(x), 4) for x in c.web],
                   "coverage": [round(float(x), 5) for x in c.coverage],
                   "recovered": [list(map(str, x)) for x in c.recovered_frames],
                   "unrecovered": list(map(int, c.unrecovered_frames)), "s": round(time.time() - t0, 1)}
            result["runs"].append(run)
            print(device, rep, "web trigger" if web else "coverage only", "max web", max(run["web"]),
                  "at frame", int(np.argmax(run["web"])), "recovered", len(run["recovered"]), flush=True)
    with open(out, "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    a = sys.argv[1:] + [None] * 3
    main(a[0], int(a[1] or 2), a[2] or "web_repeatability.json", json.loads(a[3]) if a[3] else {})
