"""Issue 12: does the GT-free coverage rank conversion runs from different key frames like their
true error? (The evidence behind ``key_candidates``; docs/conversion.md.)

For one sequence of the issue-12 protocol (docs/evaluation.md; the cached remeshed input of
``bench/conversion_eval.py``), run the graph conversion from each given key frame and report the
CD increase over the input (needs the ground truth), the mean coverage (99.5th percentile of the
input -> converted distance / diagonal: needs no ground truth), the mean edge strain against the
key frame and the time. ``key_candidates`` is off in these runs (one run per key).

    python bench/key_candidates_probe.py pcow auto,0,25,40,76,100,127,178,203 --out bench/results/key_candidates_probe_cpu.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

import conversion_eval as ce  # noqa: E402
from common import describe_device, write_json  # noqa: E402

from dynmesh_warp.convert import to_fixed_topology  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence")
    ap.add_argument("keys", help="comma-separated key frames ('auto' or indices)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cache", default=str(ROOT / "out" / "cache"))
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    gt = ce.ground_truth(a.sequence, None)
    if gt is None:
        raise SystemExit(f"{a.sequence}: no ground truth found")
    var = ce.varying_input(gt, 96, 0.01, a.device, Path(a.cache))
    T = gt.num_frames
    inp = np.mean([ce.frame_metrics(gt.V[t], gt.F, *var.frames[t], a.device)["cd"] for t in range(T)])
    runs = {}
    for k in a.keys.split(","):
        t0 = time.perf_counter()
        fx = to_fixed_topology(var, strategy="graph", device=a.device, key_candidates=0,
                               key_frame="auto" if k == "auto" else int(k))
        sec = time.perf_counter() - t0
        cd = np.mean([ce.frame_metrics(gt.V[t], gt.F, fx.V[t], fx.F, a.device)["cd"] for t in range(T)])
        F, key = fx.F, fx.conversion.key_frame
        E = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
        L0 = np.linalg.norm(fx.V[key][E[:, 0]] - fx.V[key][E[:, 1]], axis=1) + 1e-12
        strain = [float(np.mean(np.abs(np.log((np.linalg.norm(fx.V[t][E[:, 0]] - fx.V[t][E[:, 1]], axis=1)
                                               + 1e-12) / L0)))) for t in range(T)]
        cov = np.asarray(fx.conversion.coverage)
        # GT-free two-sided scores: the output's Chamfer distance to the input frames (DG-Mesh
        # convention) and the 99.5th percentile of output vertex -> input surface / diagonal
        cd_input = np.mean([ce.chamfer_distance(fx.V[t], var.frames[t][0], squared=True, device=a.device).value
                            for t in range(T)])
        off = np.mean([np.percentile(ce.nearest_surface(var.frames[t], fx.V[t], device=a.device).dist, 99.5)
                       for t in range(T)]) / ce._diag(gt.V[0])
        runs[k] = {"key": key, "cd_inc": float(100 * (cd / inp - 1)), "cov_mean": float(cov.mean()),
                   "cd_to_input": float(cd_input), "off_input_p995_mean": float(off),
                   "cov_p90": float(np.percentile(cov, 90)), "strain_mean": float(np.mean(strain)), "s": sec,
                   "recovered": len(fx.conversion.recovered_frames)}
        print(k, runs[k], flush=True)
    res = {"machine": describe_device(a.device), "sequence": a.sequence, "runs": runs}
    if a.out:
        write_json(a.out, res)


if __name__ == "__main__":
    main()
