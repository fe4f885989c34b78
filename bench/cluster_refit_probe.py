"""Probe for issue 14's last row (10^6 vertices x 10^5 spheres): the cost of a per-step path
without wp.Mesh — faces in Morton order of their frame-0 centroids, cut into clusters of K; per
step each cluster's box from the frames interpolated at the step's blend, a wp.Bvh over the
clusters refit, and a query of each sphere (a box query over the clusters, the cluster's K faces
evaluated, closest kept) — against the refit path's pieces on the same data (vertex blend,
wp.Mesh.refit, mesh_query_point). Each piece graph-replayed and timed alone; the query's
distances checked against wp.mesh_query_point's. A measurement, not a collider.

    python bench/cluster_refit_probe.py --device cuda --vertices 1000000 --spheres 100000
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_step import wave_grid  # noqa: E402
from common import RESULTS, describe_device, write_json  # noqa: E402

from dynmesh_warp.kernels.swept import box_distance, face_candidate, interpolated_triangle, keep_closest  # noqa: E402
from dynmesh_warp.kernels.tree import morton_codes  # noqa: E402

wp.set_module_options({"fast_math": True})


@wp.kernel
def compute_cluster_bounds(frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], cluster_size: int, k0: int,
                           k1: int, alpha: float, lowers: wp.array[wp.vec3], uppers: wp.array[wp.vec3]):
    """Box [m] of cluster c's faces (c * K ... c * K + K - 1 of the Morton-ordered indices) at the blend."""
    c = wp.tid()
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for j in range(cluster_size):
        a, b, e = interpolated_triangle(frames, indices, c * cluster_size + j, k0, k1, alpha)
        lo = wp.min(lo, wp.min(a, wp.min(b, e)))
        hi = wp.max(hi, wp.max(a, wp.max(b, e)))
    lowers[c] = lo
    uppers[c] = hi


@wp.kernel
def find_closest_over_clusters(frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], cluster_size: int,
                               bvh: wp.uint64, lowers: wp.array[wp.vec3], uppers: wp.array[wp.vec3], k0: int, k1: int,
                               alpha: float, points: wp.array[wp.vec3], reach: float, epsilon: float,
                               dist_out: wp.array[float]):
    """Closest distance [m] of each point to the blended surface within ``reach`` (else reach)."""
    s = wp.tid()
    p = points[s]
    ext = wp.vec3(reach + epsilon)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    c = int(0)
    min_dist = reach
    min_face = int(-1)
    min_w = wp.vec3(0.0)
    acc_n = wp.vec3(0.0)
    while wp.bvh_query_next(query, c):
        if box_distance(p, lowers[c], uppers[c]) < min_dist + epsilon:
            for j in range(cluster_size):
                f = c * cluster_size + j
                a, b, e = interpolated_triangle(frames, indices, f, k0, k1, alpha)
                d, w, wn = face_candidate(p, a, b, e, epsilon)
                min_dist, min_face, min_w, acc_n = keep_closest(d, f, w, wn, epsilon, min_dist, min_face, min_w, acc_n)
    dist_out[s] = min_dist


@wp.kernel
def blend_points(frames: wp.array2d[wp.vec3], k0: int, k1: int, alpha: float, points_out: wp.array[wp.vec3]):
    i = wp.tid()
    points_out[i] = wp.lerp(frames[k0, i], frames[k1, i], alpha)


@wp.kernel
def find_closest_on_mesh(mesh: wp.uint64, points: wp.array[wp.vec3], reach: float, dist_out: wp.array[float]):
    s = wp.tid()
    q = wp.mesh_query_point_no_sign(mesh, points[s], reach)
    d = reach
    if q.result:
        d = wp.length(points[s] - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
    dist_out[s] = d


def timed(fn, device, reps: int) -> float:
    """Median µs of one graph replay of fn (eager first: load)."""
    fn()
    wp.synchronize_device(device)
    if device.is_cuda:
        with wp.ScopedCapture(device=device) as cap:
            fn()
        run = lambda: wp.capture_launch(cap.graph)  # noqa: E731
    else:
        run = fn
    out = []
    for _ in range(5):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        for _ in range(reps):
            run()
        wp.synchronize_device(device)
        out.append((time.perf_counter() - t0) / reps * 1e6)
    return float(np.median(out))


def probe_arguments() -> argparse.ArgumentParser:
    """The probes' common options: device, vertices, spheres (query points), reach, reps, out."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--vertices", type=int, default=10_000)
    ap.add_argument("--spheres", type=int, default=1_000)
    ap.add_argument("--reach", type=float, default=0.0106, help="query reach [m]: r 1.6 mm + margin 1 mm + 8 mm of motion")
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--out", default=None)
    return ap


def probe_scene(vertices: int, spheres: int, reach: float, reps: int, dev) -> dict:
    """The probes' data and the refit path's pieces timed on it: the wave grid of ``vertices``
    (frames V, faces F), ``spheres`` points within 4 mm above its surface at the blend (1, 2,
    0.37), and blend + ``wp.Mesh.refit`` + ``mesh_query_point`` (SAH, 4 a leaf) graph-replayed.
    Returns V, F, frames, pts (host), points, blend, mesh, d_ref (the query's distances [m]) and
    res (the JSON's head, with ``refit_path_us``)."""
    n = int(round(np.sqrt(vertices)))
    seq = wave_grid(n)
    V, F = seq.V.astype(np.float32), seq.F.astype(np.int32)
    k0, k1, alpha = 1, 2, 0.37
    Vt = (1 - alpha) * V[k0] + alpha * V[k1]
    rng = np.random.default_rng(0)
    fi = rng.integers(0, len(F), spheres)
    bc = rng.dirichlet([1, 1, 1], spheres)
    tri = Vt[F[fi]]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pts = (np.einsum("sk,skd->sd", bc, tri) + nrm * rng.uniform(0.0, 0.004, (spheres, 1))).astype(np.float32)
    frames = wp.array(V, dtype=wp.vec3, device=dev)
    points = wp.array(pts, dtype=wp.vec3, device=dev)
    res = {"machine": describe_device(dev), "vertices": n * n, "faces": len(F), "spheres": spheres,
           "reach_m": reach, "rows": []}
    P = wp.zeros(n * n, dtype=wp.vec3, device=dev)
    wp.launch(blend_points, n * n, inputs=[frames, k0, k1, alpha], outputs=[P], device=dev)
    mesh = wp.Mesh(points=P, indices=wp.array(F.ravel(), dtype=wp.int32, device=dev), bvh_constructor="sah",
                   bvh_leaf_size=4)
    ref = wp.zeros(spheres, dtype=float, device=dev)
    t_blend = timed(lambda: wp.launch(blend_points, n * n, inputs=[frames, k0, k1, alpha], outputs=[P], device=dev),
                    dev, reps)
    t_refit = timed(mesh.refit, dev, reps)
    t_q = timed(lambda: wp.launch(find_closest_on_mesh, spheres, inputs=[mesh.id, points, reach], outputs=[ref],
                                  device=dev), dev, reps)
    res["refit_path_us"] = {"blend_vertices": t_blend, "mesh_refit": t_refit, "mesh_query_point": t_q,
                            "sum": t_blend + t_refit + t_q}
    print(f"refit path: blend {t_blend:.1f} + refit {t_refit:.1f} + query {t_q:.1f} = {t_blend + t_refit + t_q:.1f} us",
          flush=True)
    return {"V": V, "F": F, "frames": frames, "pts": pts, "points": points, "blend": (k0, k1, alpha), "mesh": mesh,
            "d_ref": ref.numpy(), "res": res}


def main(argv=None):
    ap = probe_arguments()
    ap.add_argument("--clusters", default="8,16,32")
    a = ap.parse_args(argv)
    wp.init()
    dev = wp.get_device(a.device)
    d = probe_scene(a.vertices, a.spheres, a.reach, a.reps, dev)
    V, F, frames, points, (k0, k1, alpha), d_ref, res = (d[k] for k in ("V", "F", "frames", "points", "blend",
                                                                         "d_ref", "res"))
    eps = 1e-6
    order = np.argsort(morton_codes(V[0][F].mean(1)), kind="stable")
    for K in [int(x) for x in a.clusters.split(",")]:
        C = (len(F) + K - 1) // K
        Fo = F[order]
        Fo = np.concatenate([Fo, np.repeat(Fo[-1:], C * K - len(Fo), 0)])  # pad with a repeated face
        idx = wp.array(Fo.ravel(), dtype=wp.int32, device=dev)
        lo = wp.zeros(C, dtype=wp.vec3, device=dev)
        hi = wp.zeros(C, dtype=wp.vec3, device=dev)
        wp.launch(compute_cluster_bounds, C, inputs=[frames, idx, K, k0, k1, alpha], outputs=[lo, hi], device=dev)
        bvh = wp.Bvh(lo, hi, constructor="sah", leaf_size=1)
        dist = wp.zeros(a.spheres, dtype=float, device=dev)
        t_b = timed(lambda: wp.launch(compute_cluster_bounds, C, inputs=[frames, idx, K, k0, k1, alpha],
                                      outputs=[lo, hi], device=dev), dev, a.reps)
        t_r = timed(bvh.refit, dev, a.reps)
        t_c = timed(lambda: wp.launch(find_closest_over_clusters, a.spheres,
                                      inputs=[frames, idx, K, bvh.id, lo, hi, k0, k1, alpha, points, a.reach, eps],
                                      outputs=[dist], device=dev), dev, a.reps)
        err = float(np.abs(dist.numpy() - d_ref).max())
        row = {"cluster_faces": K, "clusters": C, "cluster_bounds_us": t_b, "bvh_refit_us": t_r, "query_us": t_c,
               "sum_us": t_b + t_r + t_c, "max_abs_diff_vs_mesh_query_m": err}
        res["rows"].append(row)
        print(f"K={K:>3}: bounds {t_b:.1f} + refit {t_r:.1f} + query {t_c:.1f} = {t_b + t_r + t_c:.1f} us "
              f"(max |d - mesh| {err:.2e} m)", flush=True)
    write_json(Path(a.out) if a.out else RESULTS / f"cluster_refit_probe_{'cuda' if dev.is_cuda else 'cpu'}.json", res)


if __name__ == "__main__":
    main()
