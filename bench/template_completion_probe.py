"""Probe (issue 12): can a template completed from other frames give chicken_crossing back the
thin part's tip that its key frame lacks? (docs/evaluation.md, "Template completion, tried")

The default conversion runs first. Its per-frame uncovered input (input vertices farther than
max(2 %, 3 x median) of the diagonal from the output) picks the frames where the input shows
more than the output. Each such frame's input is mapped back into the key frame's pose by a
local rigid fit (Kabsch, on the 16 output vertices nearest each input vertex, between the output
at that frame and at the key frame: the conversion's own correspondence). The completed template
is the union of the signed distance fields of the template and of the mapped-back input within
5 % of the diagonal of its uncovered points, re-meshed by marching cubes; the conversion runs
again from it, at the same key frame. A control re-meshes the template alone at the same grid.

    python bench/template_completion_probe.py --sequence chicken_crossing --out bench/results/x.json

Needs ../shared/data and the evaluation cache (bench/conversion_eval.py makes it).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

sys.path.insert(0, str(Path(__file__).resolve().parent))
import conversion_eval as ce  # noqa: E402

from dynmesh_warp.convert import nearest_surface, to_fixed_topology  # noqa: E402
from dynmesh_warp.geometry import orient_outward  # noqa: E402
from dynmesh_warp.kernels.remesh import compute_signed_distances  # noqa: E402


def signed(V, F, pts, dev) -> np.ndarray:
    pw = wp.array(np.ascontiguousarray(V, np.float32), dtype=wp.vec3, device=dev)
    iw = wp.array(np.ascontiguousarray(F, np.int32).reshape(-1), dtype=wp.int32, device=dev)
    mesh = wp.Mesh(points=pw, indices=iw, support_winding_number=True)
    q = wp.array(pts.astype(np.float32), dtype=wp.vec3, device=dev)
    out = wp.empty(len(pts), dtype=float, device=dev)
    wp.launch(compute_signed_distances, dim=len(pts), inputs=[mesh.id, q, 1e6], outputs=[out], device=dev)
    return out.numpy().astype(np.float64)


def back_map(v, X, TV, k: int = 16) -> np.ndarray:
    """Input points ``v`` at a frame whose output is ``X``, carried to the key frame's output
    ``TV`` by the rigid fit of their k nearest output vertices (Kabsch per point)."""
    _, nn = cKDTree(X).query(v, k=k)
    P, Q = X[nn], TV[nn]
    pc, qc = P.mean(1), Q.mean(1)
    H = np.einsum("nki,nkj->nij", P - pc[:, None], Q - qc[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.sign(np.linalg.det(np.einsum("nij,njk->nik", U, Vt)))
    Vt[:, 2] *= D[:, None]
    R = np.einsum("nji,nkj->nik", Vt, U)
    return np.einsum("nij,nj->ni", R, v - pc) + qc


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="chicken_crossing")
    ap.add_argument("--error", type=float, default=0.01)
    ap.add_argument("--cell", type=float, default=0.8, help="grid cell / the template's median edge")
    ap.add_argument("--frames", type=int, nargs="+", default=[1, 4], help="how many worst frames to complete from")
    ap.add_argument("--cache", default=str(ce.ROOT / "out" / "cache"))
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    wp.config.quiet = True
    dev = wp.get_device("cpu")
    gt = ce.ground_truth(a.sequence, None)
    if gt is None:
        sys.exit(f"skip {a.sequence}: not found")
    var = ce.varying_input(gt, 96, a.error, dev, Path(a.cache))
    T = var.num_frames
    inp = [ce.frame_metrics(gt.V[t], gt.F, *var.frames[t], dev) for t in range(T)]
    cov_in = [c for _, c in inp]
    cd_in = float(np.mean([m["cd"] for m, _ in inp]))

    def score(fx, label, seconds, **extra):
        per = [ce.frame_metrics(gt.V[t], gt.F, fx.V[t], fx.F, dev, cov_in[t])[0] for t in range(T)]
        loss = [p["coverage_loss_max"] for p in per]
        row = {"run": label, "cd_increase_pct": 100 * (np.mean([p["cd"] for p in per]) / cd_in - 1),
               "coverage_lost_max_pct": 100 * max(loss), "worst_frame": int(np.argmax(loss)),
               "frames_lost_over_3pct": int(sum(x > 0.03 for x in loss)), "template_vertices": int(fx.V.shape[1]),
               "seconds": seconds, **extra}
        print(json.dumps(row), flush=True)
        return row

    t0 = time.perf_counter()
    fx = to_fixed_topology(var, device=dev)
    rows = [score(fx, "default", time.perf_counter() - t0)]
    K = fx.conversion.key_frame
    TV, TF = fx.V[K].astype(np.float64), fx.F
    diag = ce._diag(TV)
    cands = []
    for t in range(T):
        v = var.frames[t][0]
        d = nearest_surface((fx.V[t], fx.F), v, device=dev).dist / diag
        m = d > max(0.02, 3 * np.median(d))
        if m.any():
            cands.append((float(d.max()), t, m))
    cands.sort(key=lambda c: -c[0])
    h = float(np.median(np.linalg.norm(TV[TF[:, 0]] - TV[TF[:, 1]], axis=1))) * a.cell

    def remesh(pieces):
        allv = np.concatenate([TV] + [p[0] for p in pieces])
        lo, hi = allv.min(0) - 3 * h, allv.max(0) + 3 * h
        n = np.ceil((hi - lo) / h).astype(int) + 1
        G = np.stack(np.meshgrid(*[lo[i] + h * np.arange(n[i]) for i in range(3)], indexing="ij"), -1).reshape(-1, 3)
        s = signed(TV, TF, G, dev)
        for vb, f, ub in pieces:
            near = cKDTree(ub).query(G)[0] < 0.05 * diag
            s = np.where(near, np.minimum(s, signed(vb, f, G, dev)), s)
        mv, mf, _, _ = marching_cubes(s.reshape(n), 0.0, spacing=(h, h, h))
        mv = (mv + lo).astype(np.float32)
        return mv, orient_outward(mv, mf.astype(np.int32))

    runs = [("remeshed template (control)", [])]
    for k in a.frames:
        pieces = []
        for _, t, m in cands[:k]:
            vb = back_map(var.frames[t][0].astype(np.float64), fx.V[t].astype(np.float64), TV)
            pieces.append((vb, var.frames[t][1], vb[m]))
        runs.append((f"completed from the {k} worst frame(s)", pieces))
    for label, pieces in runs:
        mv, mf = remesh(pieces)
        t0 = time.perf_counter()
        fx2 = to_fixed_topology(var, device=dev, template=(mv, mf), key_frame=K)
        rows.append(score(fx2, label, time.perf_counter() - t0,
                          frames=[int(c[1]) for c in cands[:len(pieces)]]))
    out = {"sequence": a.sequence, "error": a.error, "key_frame": K, "cell_over_median_edge": a.cell,
           "machine": platform.node(), "processor": platform.processor() or platform.machine(), "device": "cpu",
           "input_cd": cd_in, "runs": rows}
    Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
