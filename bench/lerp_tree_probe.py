"""Probe for issue 14's last row (10^6 vertices x 10^5 spheres), after implicit_tree_probe.py:
the same pointer-free tree, but with **no per-step upkeep** — its boxes and triangles are
written once a reconstruction frame into one of two slots, and a sub-step's query bounds the
blended surface by the blend of the two frames' boxes (kernels/tree.py, "interpolated boxes") —
and with the query's loads laid out for the GPU (a node's box pair in one 64-byte row, a leaf's
triangles contiguous). Optionally seeded by each point's previous closest face (the walk starts
at the seed's leaf and climbs). Timed against the refit path's pieces on the same data (vertex
blend, wp.Mesh.refit, mesh_query_point); every query's distances checked against
mesh_query_point's. Also: register-capped copies of the query, and the same walk written as
plain CUDA C++ (func_native), over two frames and over one, to tell the algorithm's and the
data's cost from the code generation's. A measurement, not a collider.

    python bench/lerp_tree_probe.py --device cuda --vertices 1000000 --spheres 100000
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cluster_refit_probe import probe_arguments, probe_scene, timed  # noqa: E402
from common import RESULTS, write_json  # noqa: E402

from dynmesh_warp.kernels.tree import (allocate_implicit_tree, find_closest_on_lerp_tree,  # noqa: E402
                                       find_closest_on_tree, morton_codes, query_lerp_tree_point, refit_tree,
                                       update_tree_slot)


def _capped(regs: int):
    """find_closest_on_lerp_tree with a register cap per thread on CUDA (``__maxnreg__``)."""

    def find_closest_on_lerp_tree_capped(
        tree_faces: wp.array[wp.int32], node_boxes: wp.array[wp.vec4], tree_triangles: wp.array[wp.vec3],
        leaf_faces: int, num_leaves: int, num_slots: int, s0: int, s1: int, alpha: float, points: wp.array[wp.vec3],
        seed_slots: wp.array[wp.int32], seed_up: int, reach: float, epsilon: float, dist_out: wp.array[float],
        slot_out: wp.array[wp.int32], face_out: wp.array[wp.int32],
    ):
        query_lerp_tree_point(wp.tid(), tree_faces, node_boxes, tree_triangles, leaf_faces, num_leaves, num_slots, s0,
                              s1, alpha, points, seed_slots, seed_up, reach, epsilon, dist_out, slot_out, face_out)

    return wp.kernel(find_closest_on_lerp_tree_capped, name=f"find_closest_on_lerp_tree_capped_{regs}",
                     cuda_max_registers=regs)


CAPPED = {r: _capped(r) for r in (32, 48, 64, 96)}

# The same walk written as plain CUDA C++ (a C array stack, float4 read-only loads, squared
# distances, the unsigned closest point as wp.mesh_query_point_no_sign computes it): tells the
# cost of the algorithm and layout from the cost of how the Warp-Python walk is compiled.
_NATIVE_WALK = """
const float4* nb = reinterpret_cast<const float4*>(node_boxes.data);
const float* tv = reinterpret_cast<const float*>(tree_triangles.data);
const float a1 = alpha;
const float a0 = 1.0f - alpha;
const int S = 3 * num_leaves * leaf_faces;
int stack[48];
float sd[48];
int sp = 1;
stack[0] = 1;
sd[0] = 0.0f;
float best = reach * reach;
int best_slot = -1;
while (sp > 0) {
    --sp;
    const int node = stack[sp];
    if (sd[sp] >= best) continue;
    if (node >= num_leaves) {
        const int first = (node - num_leaves) * leaf_faces;
        for (int j = 0; j < leaf_faces; ++j) {
            const int slot = first + j;
            if (slot >= num_slots) break;
            wp::vec3 v[3];
            for (int c = 0; c < 3; ++c) {
                const float* q0 = tv + 3 * (s0 * S + 3 * slot + c);
                const float* q1 = tv + 3 * (s1 * S + 3 * slot + c);
#if defined(__CUDA_ARCH__)
                v[c] = wp::vec3(a0 * __ldg(q0) + a1 * __ldg(q1), a0 * __ldg(q0 + 1) + a1 * __ldg(q1 + 1),
                                a0 * __ldg(q0 + 2) + a1 * __ldg(q1 + 2));
#else
                v[c] = wp::vec3(a0 * q0[0] + a1 * q1[0], a0 * q0[1] + a1 * q1[1], a0 * q0[2] + a1 * q1[2]);
#endif
            }
            const wp::vec3 e0 = v[1] - v[0];
            const wp::vec3 e1 = v[2] - v[0];
            const wp::vec3 e2 = v[2] - v[1];
            if (wp::length(wp::cross(e0, e1)) / (wp::dot(e0, e0) + wp::dot(e1, e1) + wp::dot(e2, e2)) < 1.e-6f)
                continue;
            const wp::vec2 b = wp::closest_point_to_triangle(v[0], v[1], v[2], p);
            const wp::vec3 c = b[0] * v[0] + b[1] * v[1] + (1.0f - b[0] - b[1]) * v[2];
            const float d2 = wp::length_sq(c - p);
            if (d2 < best) {
                best = d2;
                best_slot = slot;
            }
        }
    } else {
        float d[2];
        for (int k = 0; k < 2; ++k) {
            const int row = 4 * (2 * node + k);
#if defined(__CUDA_ARCH__)
            const float4 l0 = __ldg(nb + row + 2 * s0), l1 = __ldg(nb + row + 2 * s1);
            const float4 h0 = __ldg(nb + row + 2 * s0 + 1), h1 = __ldg(nb + row + 2 * s1 + 1);
#else
            const float4 l0 = nb[row + 2 * s0], l1 = nb[row + 2 * s1];
            const float4 h0 = nb[row + 2 * s0 + 1], h1 = nb[row + 2 * s1 + 1];
#endif
            const float dx = wp::max(wp::max(a0 * l0.x + a1 * l1.x - p[0], p[0] - a0 * h0.x - a1 * h1.x), 0.0f);
            const float dy = wp::max(wp::max(a0 * l0.y + a1 * l1.y - p[1], p[1] - a0 * h0.y - a1 * h1.y), 0.0f);
            const float dz = wp::max(wp::max(a0 * l0.z + a1 * l1.z - p[2], p[2] - a0 * h0.z - a1 * h1.z), 0.0f);
            d[k] = dx * dx + dy * dy + dz * dz;
        }
        const int near = d[1] < d[0] ? 1 : 0;
        if (d[1 - near] < best && sp < 48) {
            stack[sp] = 2 * node + 1 - near;
            sd[sp] = d[1 - near];
            ++sp;
        }
        if (d[near] < best && sp < 48) {
            stack[sp] = 2 * node + near;
            sd[sp] = d[near];
            ++sp;
        }
    }
}
return wp::vec2(wp::sqrt(best), static_cast<float>(best_slot));
"""


@wp.func_native(_NATIVE_WALK)
def closest_on_lerp_tree_native(node_boxes: wp.array[wp.vec4], tree_triangles: wp.array[wp.vec3], leaf_faces: int,
                                num_leaves: int, num_slots: int, s0: int, s1: int, alpha: float, p: wp.vec3,
                                reach: float) -> wp.vec2:
    """(distance [m] within reach, tree slot as a float or -1) of the unsigned closest point."""
    ...


@wp.kernel
def find_closest_on_lerp_tree_native(
    node_boxes: wp.array[wp.vec4], tree_triangles: wp.array[wp.vec3], leaf_faces: int, num_leaves: int,
    num_slots: int, s0: int, s1: int, alpha: float, points: wp.array[wp.vec3], reach: float,
    dist_out: wp.array[float], slot_out: wp.array[wp.int32],
):
    s = wp.tid()
    r = closest_on_lerp_tree_native(node_boxes, tree_triangles, leaf_faces, num_leaves, num_slots, s0, s1, alpha,
                                    points[s], reach)
    dist_out[s] = r[0]
    slot_out[s] = int(r[1])


def main(argv=None):
    ap = probe_arguments()
    ap.add_argument("--leaf-faces", default="2,4,8")
    ap.add_argument("--seed-up", default="0,2")
    ap.add_argument("--step-alpha", type=float, default=0.1, help="blend advance a sub-step (24 fps, dt 1/240)")
    a = ap.parse_args(argv)
    wp.init()
    dev = wp.get_device(a.device)
    d = probe_scene(a.vertices, a.spheres, a.reach, a.reps, dev)
    V, F, frames, pts, points, d_ref, res = (d[k] for k in ("V", "F", "frames", "pts", "points", "d_ref", "res"))
    k0, k1, alpha = d["blend"]
    eps = 1e-6
    n = a.spheres
    order = np.argsort(morton_codes(pts), kind="stable")
    points_sorted = wp.array(pts[order], dtype=wp.vec3, device=dev)
    res["step_alpha"] = a.step_alpha
    for B in [int(x) for x in a.leaf_faces.split(",")]:
        tree = allocate_implicit_tree(V[0], F, B, dev)
        tree_faces, tree_indices, depth, P = tree.tree_faces, tree.tree_indices, tree.depth, tree.num_leaves
        tf, ti, lo, hi = tree.faces, tree.indices, tree.node_lower, tree.node_upper
        boxes = wp.zeros(8 * P, dtype=wp.vec4, device=dev)
        tris = wp.zeros(2 * len(tree_indices), dtype=wp.vec3, device=dev)
        dist = wp.zeros(n, dtype=float, device=dev)
        face = wp.zeros(n, dtype=wp.int32, device=dev)
        slot = wp.zeros(n, dtype=wp.int32, device=dev)
        # previous code's query (boxes refit at the blend, separate arrays, triangles through indices)
        t_old_refit = timed(lambda: refit_tree(frames, ti, tf, B, depth, k0, k1, alpha, lo, hi, 4), dev, a.reps)
        t_old = timed(lambda: wp.launch(find_closest_on_tree, n, inputs=[frames, ti, tf, lo, hi, B, P, k0, k1, alpha,
                                                                         points, a.reach, eps],
                                        outputs=[dist, face], device=dev), dev, a.reps)
        # once a frame: one slot's boxes and triangles
        t_slot = timed(lambda: update_tree_slot(frames, ti, tf, B, depth, k1, 1, lo, hi, boxes, tris), dev, a.reps)
        update_tree_slot(frames, ti, tf, B, depth, k0, 0, lo, hi, boxes, tris)
        no_seed = wp.full(n, -1, dtype=wp.int32, device=dev)

        def query(pts_arr, seeds, up, al=alpha):
            return lambda: wp.launch(find_closest_on_lerp_tree, n,
                                     inputs=[tf, boxes, tris, B, P, len(F), 0, 1, al, pts_arr, seeds, up, a.reach, eps],
                                     outputs=[dist, slot, face], device=dev)

        row = {"leaf_faces": B, "depth": depth, "previous_tree_refit_us": t_old_refit, "previous_tree_query_us": t_old,
               "slot_update_per_frame_us": t_slot,
               "tree_bytes": int(boxes.capacity + tris.capacity + tree_faces.nbytes + tree_indices.nbytes)}
        t = timed(query(points, no_seed, 0), dev, a.reps)
        row["query_unseeded_us"] = t
        row["query_unseeded_max_abs_diff_m"] = float(np.abs(dist.numpy() - d_ref).max())
        exact = wp.clone(slot)
        t = timed(query(points_sorted, no_seed, 0), dev, a.reps)
        row["query_unseeded_sorted_points_us"] = t
        # seeds: the closest slots of the previous sub-step (same points, blend one step earlier)
        query(points, no_seed, 0, alpha - a.step_alpha)()
        prev = wp.clone(slot)
        row["seed_changed_fraction"] = float(np.mean(prev.numpy() != exact.numpy()))
        for up in [int(x) for x in a.seed_up.split(",")]:
            for name, seeds in (("previous_step", prev), ("exact", exact)):
                t = timed(query(points, seeds, up), dev, a.reps)
                row[f"query_seeded_{name}_up{up}_us"] = t
                row[f"query_seeded_{name}_up{up}_max_abs_diff_m"] = float(np.abs(dist.numpy() - d_ref).max())
        t = timed(lambda: wp.launch(find_closest_on_lerp_tree_native, n,
                                    inputs=[boxes, tris, B, P, len(F), 0, 1, alpha, points, a.reach],
                                    outputs=[dist, slot], device=dev), dev, a.reps)
        row["query_native_cpp_unsigned_us"] = t
        row["query_native_cpp_unsigned_max_abs_diff_m"] = float(np.abs(dist.numpy() - d_ref).max())
        t = timed(lambda: wp.launch(find_closest_on_lerp_tree_native, n,
                                    inputs=[boxes, tris, B, P, len(F), 0, 1, alpha, points_sorted, a.reach],
                                    outputs=[dist, slot], device=dev), dev, a.reps)
        row["query_native_cpp_unsigned_sorted_points_us"] = t
        # one frame only (both slots the same: every load hits the same line twice), against
        # frame k0's surface: the cost of the walk without the second frame's bytes
        t = timed(lambda: wp.launch(find_closest_on_lerp_tree_native, n,
                                    inputs=[boxes, tris, B, P, len(F), 0, 0, 0.0, points, a.reach],
                                    outputs=[dist, slot], device=dev), dev, a.reps)
        row["query_native_cpp_unsigned_one_frame_us"] = t
        for r, kern in CAPPED.items():
            t = timed(lambda: wp.launch(kern, n, inputs=[tf, boxes, tris, B, P, len(F), 0, 1, alpha, points, no_seed, 0,
                                                        a.reach, eps], outputs=[dist, slot, face], device=dev),
                      dev, a.reps)
            row[f"query_unseeded_max_registers_{r}_us"] = t
            row[f"query_unseeded_max_registers_{r}_max_abs_diff_m"] = float(np.abs(dist.numpy() - d_ref).max())
        res["rows"].append(row)
        print(B, {k: (round(v, 2) if isinstance(v, float) and v > 1e-3 else v) for k, v in row.items()}, flush=True)
    write_json(Path(a.out) if a.out else RESULTS / f"lerp_tree_probe_{'cuda' if dev.is_cuda else 'cpu'}.json", res)


if __name__ == "__main__":
    main()
