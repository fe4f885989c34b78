"""Probe for issue 14's last row (10^6 vertices x 10^5 spheres), after cluster_refit_probe.py: the
pointer-free tree of kernels/tree.py — faces in Morton order, leaves of B faces, the complete
binary tree over them refit every step from the frames at the step's blend (no vertex buffer),
a nearest-first query — against the refit path's pieces on the same data (vertex blend,
wp.Mesh.refit, mesh_query_point). Each piece graph-replayed and timed alone; the query's
distances checked against wp.mesh_query_point's. A measurement, not a collider yet.

    python bench/implicit_tree_probe.py --device cuda --vertices 1000000 --spheres 100000
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cluster_refit_probe import find_closest_on_mesh, probe_arguments, probe_scene, timed  # noqa: E402
from common import RESULTS, write_json  # noqa: E402

from dynmesh_warp.kernels.tree import allocate_implicit_tree, find_closest_on_tree, morton_codes, refit_tree  # noqa: E402


def main(argv=None):
    ap = probe_arguments()
    ap.add_argument("--leaf-faces", default="2,4,8")
    ap.add_argument("--levels", default="3,4,6", help="tree levels refit per launch")
    a = ap.parse_args(argv)
    wp.init()
    dev = wp.get_device(a.device)
    d = probe_scene(a.vertices, a.spheres, a.reach, a.reps, dev)
    V, F, frames, pts, points, mesh, d_ref, res = (d[k] for k in ("V", "F", "frames", "pts", "points", "mesh", "d_ref",
                                                                   "res"))
    k0, k1, alpha = d["blend"]
    t_q = res["refit_path_us"]["mesh_query_point"]
    eps = 1e-6
    # the same query with the points in Morton order (thread t takes the t-th point along the curve)
    order = np.argsort(morton_codes(pts), kind="stable")
    points_sorted = wp.array(pts[order], dtype=wp.vec3, device=dev)
    ref_sorted = wp.zeros(a.spheres, dtype=float, device=dev)
    t_qs = timed(lambda: wp.launch(find_closest_on_mesh, a.spheres, inputs=[mesh.id, points_sorted, a.reach],
                                   outputs=[ref_sorted], device=dev), dev, a.reps)
    res["refit_path_us"]["mesh_query_point_morton_sorted_points"] = t_qs
    res["sorted_vs_unsorted_max_abs_diff_m"] = float(np.abs(ref_sorted.numpy() - d_ref[order]).max())
    print(f"mesh_query_point, points in Morton order: {t_qs:.1f} us (unsorted {t_q:.1f})", flush=True)
    for B in [int(x) for x in a.leaf_faces.split(",")]:
        tree = allocate_implicit_tree(V[0], F, B, dev)
        tree_faces, tree_indices, depth, P = tree.tree_faces, tree.tree_indices, tree.depth, tree.num_leaves
        tf, ti, lo, hi = tree.faces, tree.indices, tree.node_lower, tree.node_upper
        dist = wp.zeros(a.spheres, dtype=float, device=dev)
        face = wp.zeros(a.spheres, dtype=wp.int32, device=dev)
        for L in [int(x) for x in a.levels.split(",")]:
            t_r = timed(lambda: refit_tree(frames, ti, tf, B, depth, k0, k1, alpha, lo, hi, L), dev, a.reps)
            t_c = timed(lambda: wp.launch(find_closest_on_tree, a.spheres,
                                          inputs=[frames, ti, tf, lo, hi, B, P, k0, k1, alpha, points, a.reach, eps],
                                          outputs=[dist, face], device=dev), dev, a.reps)
            err = float(np.abs(dist.numpy() - d_ref).max())
            t_cs = timed(lambda: wp.launch(find_closest_on_tree, a.spheres,
                                           inputs=[frames, ti, tf, lo, hi, B, P, k0, k1, alpha, points_sorted, a.reach,
                                                   eps], outputs=[dist, face], device=dev), dev, a.reps)
            row = {"query_morton_sorted_points_us": t_cs,
                   "leaf_faces": B, "depth": depth, "levels_per_launch": L, "tree_refit_us": t_r, "query_us": t_c,
                   "sum_us": t_r + t_c, "max_abs_diff_vs_mesh_query_m": err,
                   "tree_bytes": int(2 * P * 24 + tree_faces.nbytes + tree_indices.nbytes)}
            res["rows"].append(row)
            print(f"B={B} depth {depth} levels/launch {L}: refit {t_r:.1f} + query {t_c:.1f} = {t_r + t_c:.1f} us "
                  f"(max |d - mesh| {err:.2e} m); query on sorted points {t_cs:.1f} us", flush=True)
    write_json(Path(a.out) if a.out else RESULTS / f"implicit_tree_probe_{'cuda' if dev.is_cuda else 'cpu'}.json", res)


if __name__ == "__main__":
    main()
