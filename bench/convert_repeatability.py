"""Repeatability of the default conversion: the same input converted several times in one process.

On the CPU every run gives the same bytes. On a GPU the fit's sums are float atomics, whose
order varies, so runs can differ in the last bits and, through the drift trigger of the key
trials, in the decision to try other key frames (docs/conversion.md, "Speed with larger
templates"). Records per run: key frame, number of key trials, seconds, the template's vertex
count, and, when the templates match, the largest vertex difference to run 0 and the largest
distance between the two runs' surfaces (each run's vertices to the other's surface, both ways).

    python bench/convert_repeatability.py --device cuda:0 --out bench/results/convert_repeatability_cuda.json
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dynmesh_warp.convert import nearest_surface, to_fixed_topology  # noqa: E402
from dynmesh_warp.outputs import atomic_write_json  # noqa: E402
from dynmesh_warp.scenes import torus_to_sphere  # noqa: E402
from dynmesh_warp.sequence import VaryingTopologySequence  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default=None)
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--resolution", type=int, default=76)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--deterministic", action="store_true", help="the conversion option deterministic=True")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(a.device)
    seq = torus_to_sphere(frames=a.frames, resolution=a.resolution)
    opts = {"deterministic": True} if a.deterministic else {}
    to_fixed_topology(VaryingTopologySequence(seq.frames[:2]), device=device, **opts)  # compile
    runs, first = [], None
    for _ in range(a.runs):
        t0 = time.perf_counter()
        out = to_fixed_topology(seq, device=device, **opts)
        wp.synchronize_device(device)
        row = {"seconds": time.perf_counter() - t0, "key_frame": out.conversion.key_frame,
               "key_trials": len(out.conversion.key_trials), "template_vertices": int(out.num_vertices),
               "coverage_max": float(np.max(out.conversion.coverage))}
        if first is None:
            first = out
        elif out.V.shape == first.V.shape:
            d = np.abs(out.V.astype(np.float64) - first.V)
            diag = float(np.linalg.norm(np.ptp(first.V[0], axis=0)))
            row["max_vertex_difference_to_run0"] = float(d.max())
            row["max_vertex_difference_to_run0_over_diag"] = float(d.max()) / diag
            row["identical_to_run0"] = bool(np.array_equal(out.V, first.V))
            # the surfaces, not the vertices: each run's vertices to the other's surface, worst frame
            surf = [max(float(nearest_surface((first.V[t], first.F), out.V[t], device=device).dist.max()),
                        float(nearest_surface((out.V[t], out.F), first.V[t], device=device).dist.max()))
                    for t in range(len(out.V))]
            row["max_surface_distance_to_run0_over_diag"] = max(surf) / diag
            row["mean_surface_distance_to_run0_over_diag"] = float(np.mean(surf)) / diag
        runs.append(row)
        print(row, flush=True)
    atomic_write_json(Path(a.out), {"benchmark": "convert_repeatability", "device": device.alias,
                                    "device_name": device.name, "machine": platform.node(),
                                    "warp": wp.__version__, "input": {"scene": "torus_to_sphere", "frames": a.frames,
                                                                      "resolution": a.resolution},
                                    "options": opts,
                                    "runs": runs})


if __name__ == "__main__":
    main()
