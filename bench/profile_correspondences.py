"""Where the graph conversion's correspondence time goes (issue 12 speed): the closest-point
queries of ``find_correspondences`` (template -> frame and frame -> template) for one frame
pair of the torus_to_sphere benchmark input (~10k vertices), by BVH constructor and query
radius. Median of repeated synchronised launches. Writes a JSON naming machine and device.

    python bench/profile_correspondences.py --device cuda:0 --out bench/results/profile_correspondences_cuda.json
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import describe_device, write_json  # noqa: E402

from dynmesh_warp.kernels import register as kr  # noqa: E402
from dynmesh_warp.remesh import vertex_normals  # noqa: E402
from dynmesh_warp.scenes import torus_to_sphere  # noqa: E402


def _time(fn, reps: int) -> float:
    fn()
    wp.synchronize()
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        wp.synchronize()
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--frame", type=int, default=40)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    wp.config.quiet = True
    wp.init()
    d = wp.get_device(a.device)
    seq = torus_to_sphere(frames=200, resolution=76)
    (V0, F0), (V1, F1) = seq.frames[a.frame], seq.frames[a.frame + 1]
    diag = float(np.linalg.norm(np.ptp(V0, axis=0)))
    # the template at frame k, moved halfway to frame k+1's bounding box (a typical prediction error)
    T = (V0 + 0.5 * (V1.mean(axis=0) - V0.mean(axis=0))).astype(np.float32)
    arr = lambda x, dt: wp.array(x, dtype=dt, device=d)  # noqa: E731
    tp, ti = arr(T, wp.vec3), arr(F0.reshape(-1).astype(np.int32), wp.int32)
    tn = arr(vertex_normals(T, F0).astype(np.float32), wp.vec3)
    fp, fi = arr(V1.astype(np.float32), wp.vec3), arr(F1.reshape(-1).astype(np.int32), wp.int32)
    fn = arr(vertex_normals(V1, F1).astype(np.float32), wp.vec3)
    outs = lambda n: [wp.empty(n, dtype=wp.vec3, device=d), wp.empty(n, dtype=wp.int32, device=d),  # noqa: E731
                      wp.empty(n, dtype=wp.vec3, device=d), wp.empty(n, dtype=float, device=d),
                      wp.empty(n, dtype=float, device=d)]
    fo, bo = outs(len(T)), outs(len(V1))
    rows = []
    for ctor in ("lbvh", "sah", "median"):
        try:
            t0 = time.perf_counter()
            fmesh = wp.Mesh(points=fp, indices=fi, bvh_constructor=ctor)
            tmesh = wp.Mesh(points=tp, indices=ti, bvh_constructor=ctor)
            wp.synchronize()
            build_ms = 1e3 * (time.perf_counter() - t0) / 2
        except Exception as e:  # noqa: BLE001
            rows.append({"constructor": ctor, "error": str(e)})
            continue
        for rad in (10.0, 1.0, 0.1, 0.03):
            md = rad * diag

            def fwd():
                wp.launch(kr.find_correspondences, dim=len(T), inputs=[fmesh.id, fp, fi, tp, tn, md, 0.5],
                          outputs=fo, device=d)

            def bwd():
                wp.launch(kr.find_correspondences, dim=len(V1), inputs=[tmesh.id, tp, ti, fp, fn, md, 0.5],
                          outputs=bo, device=d)

            r = {"constructor": ctor, "build_ms": build_ms, "max_dist_diag": rad,
                 "forward_ms": _time(fwd, a.reps), "backward_ms": _time(bwd, a.reps),
                 "forward_found": int((fo[1].numpy() >= 0).sum()), "backward_found": int((bo[1].numpy() >= 0).sum())}
            refit = lambda: tmesh.refit()  # noqa: E731
            r["template_refit_ms"] = _time(refit, a.reps)
            rows.append(r)
            print(r, flush=True)
    res = {"benchmark": "profile_correspondences", **describe_device(a.device),
           "input": f"torus_to_sphere(frames=200, resolution=76), frames {a.frame}, {a.frame + 1}",
           "template_vertices": len(T), "frame_vertices": len(V1), "rows": rows}
    if a.out:
        write_json(a.out, res)


if __name__ == "__main__":
    main()
