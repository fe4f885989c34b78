"""How far the issue-12 protocol's reconstruction error alone puts the ground truth from the
input: the smooth error field of ``remesh.reconstruction_error`` (RMS ``--error`` x the bbox
diagonal, along the normals) applied to each ground-truth frame itself (no remeshing), and the
distance of every GT vertex to that displaced surface, as a fraction of the diagonal. Its worst
vertex per frame is the floor any conversion that follows its input meets on the "no GT vertex
farther than 3 % of the diagonal" criterion (docs/conversion.md).

    python bench/error_peak.py --out bench/results/error_peak_cpu.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import write_json  # noqa: E402
from conversion_eval import SHARED, ground_truth  # noqa: E402


def main(argv=None):
    from dynmesh_warp.convert import nearest_surface
    from dynmesh_warp.remesh import reconstruction_error

    ap = argparse.ArgumentParser()
    ap.add_argument("--error", type=float, default=0.01)
    ap.add_argument("--stride", type=int, default=5, help="every n-th frame")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    res = {"error_rms": a.error, "what": "distance of each GT vertex to the GT frame displaced by the protocol's "
           "error field (no remeshing), / bbox diagonal", "sequences": {}}
    for name in list(SHARED) + ["articulated_figure"]:
        gt = ground_truth(name, None)
        if gt is None:
            continue
        frames = [(v, gt.F) for v in gt.V]
        v0 = np.asarray(gt.V[0], np.float64)
        diag = float(np.linalg.norm(v0.max(axis=0) - v0.min(axis=0)))
        noisy = reconstruction_error(frames, a.error, seed=0, diag=diag)  # the same field as remesh_sequence's
        worst, disp = [], []
        for t in range(0, gt.num_frames, a.stride):
            d = nearest_surface((noisy[t][0], gt.F), gt.V[t], device="cpu").dist
            worst.append(float(d.max()) / diag)
            disp.append(float(np.linalg.norm(noisy[t][0] - gt.V[t], axis=1).max()) / diag)
        res["sequences"][name] = {"frames_measured": len(worst), "worst_vertex_max": max(worst),
                                  "worst_vertex_mean": float(np.mean(worst)), "displacement_max": max(disp)}
        print(f"{name:18s} GT vertex farthest from the error-displaced GT: max {100 * max(worst):.2f} % "
              f"(mean over frames {100 * np.mean(worst):.2f} %), largest displacement {100 * max(disp):.2f} %",
              flush=True)
    if a.out:
        write_json(Path(a.out), res)


if __name__ == "__main__":
    main()
