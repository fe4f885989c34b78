"""Stage 3 (tree path, a probe for issue 14's largest row): a pointer-free BVH over the faces
refit every sub-step from the interpolated frames, and a nearest-first closest-feature query.

The faces are put in Morton order of their centroids once (host, :func:`build_implicit_tree`)
and cut into leaves of ``leaf_faces`` consecutive faces; the leaves are padded to a power of two
P and the tree is the complete binary tree over them in heap layout: node 1 is the root, node i
has children 2i and 2i + 1, leaf l is node P + l. Its topology never changes, so there are no
child pointers and no build per step: a refit is one pass over the faces for the leaf boxes
(:func:`compute_tree_leaf_bounds`, at the step's blend of frames k and k+1, so no vertex buffer
is written) and a few launches for the levels above (:func:`compute_tree_level_bounds`, each doing
several levels in registers).

The query (:func:`closest_on_tree`) walks it nearest child first with a small stack and skips a
node whose box is farther than the closest feature so far + epsilon, the same prune as the swept
collider's serial search (kernels/swept.py), so the result is that of evaluating every face
within reach (the rule of ``wp.mesh_query_point_sign_normal``, ties within epsilon included).
"""

import numpy as np
import warp as wp

from .swept import box_distance, face_candidate, interpolated_triangle, keep_closest

wp.set_module_options({"fast_math": True})

#: the query's stack [nodes]: the nearest-first walk pushes at most one node a level, so a tree
#: of depth < TREE_STACK - 1 (2^46 leaves) never fills it
TREE_STACK = 48
_stack_t = wp.types.vector(length=TREE_STACK, dtype=wp.int32)
#: an empty box (padding leaves): the union's identity, infinitely far from every point
EMPTY_LO = wp.constant(wp.vec3(1.0e30))
EMPTY_HI = wp.constant(wp.vec3(-1.0e30))


def morton_codes(points: np.ndarray) -> np.ndarray:
    """30-bit Morton codes of points (n, 3) in their bounding box (10 bits an axis)."""
    p = np.asarray(points, np.float64)
    q = ((p - p.min(0)) / max(float(np.ptp(p, axis=0).max()), 1e-30) * 1023).astype(np.uint64)

    def spread(x):
        x = (x | (x << np.uint64(16))) & np.uint64(0x030000FF)
        x = (x | (x << np.uint64(8))) & np.uint64(0x0300F00F)
        x = (x | (x << np.uint64(4))) & np.uint64(0x030C30C3)
        return (x | (x << np.uint64(2))) & np.uint64(0x09249249)

    return spread(q[:, 0]) | (spread(q[:, 1]) << np.uint64(1)) | (spread(q[:, 2]) << np.uint64(2))


def build_implicit_tree(V: np.ndarray, F: np.ndarray, leaf_faces: int = 4):
    """The tree's static part from one pose ``V`` (N, 3) [m] of the faces ``F`` (M, 3).

    Returns (tree_faces, tree_indices, depth): tree_faces (P * leaf_faces,) int32, the original
    face index in tree order (-1: padding); tree_indices (3 * P * leaf_faces,) int32, the faces'
    vertex indices in the same order (padding repeats a real face, which leaves its leaf's box
    unchanged); depth D with P = 2^D leaves (node count 2P, node 0 unused).
    """
    F = np.asarray(F, np.int64).reshape(-1, 3)
    M = len(F)
    if M == 0:
        raise ValueError("build_implicit_tree: no faces")
    if leaf_faces < 1:
        raise ValueError(f"build_implicit_tree: leaf_faces must be >= 1, got {leaf_faces}")
    order = np.argsort(morton_codes(np.asarray(V, np.float64)[F].mean(1)), kind="stable")
    leaves = -(-M // leaf_faces)
    depth = max(int(np.ceil(np.log2(leaves))), 1)
    slots = (1 << depth) * leaf_faces
    tree_faces = np.full(slots, -1, np.int32)
    tree_faces[:M] = order
    tree_indices = np.empty((slots, 3), np.int32)
    tree_indices[:M] = F[order]
    tree_indices[M:] = F[order[-1]]
    return tree_faces, tree_indices.ravel(), depth


@wp.kernel
def compute_tree_leaf_bounds(
    # Model:
    frames: wp.array2d[wp.vec3],
    tree_indices: wp.array[wp.int32],
    tree_faces: wp.array[wp.int32],
    # In:
    leaf_faces: int,
    num_leaves: int,
    k0: int,
    k1: int,
    alpha: float,
    # Out:
    node_lower: wp.array[wp.vec3],
    node_upper: wp.array[wp.vec3],
):
    """Box [m] of leaf l (node num_leaves + l): its faces at the blend; empty for padding.

    frames (T, N) [m]; tree_indices (3 P B,); tree_faces (P B,); node_lower/upper (2P,) [m].
    """
    leaf = wp.tid()
    lo = EMPTY_LO
    hi = EMPTY_HI
    for j in range(leaf_faces):
        slot = leaf * leaf_faces + j
        if tree_faces[slot] >= 0:
            a, b, e = interpolated_triangle(frames, tree_indices, slot, k0, k1, alpha)
            lo = wp.min(lo, wp.min(a, wp.min(b, e)))
            hi = wp.max(hi, wp.max(a, wp.max(b, e)))
    node_lower[num_leaves + leaf] = lo
    node_upper[num_leaves + leaf] = hi


@wp.kernel
def compute_tree_level_bounds(
    # In:
    top_level: int,
    levels: int,
    # Out:
    node_lower: wp.array[wp.vec3],
    node_upper: wp.array[wp.vec3],
):
    """Boxes [m] of the ``levels`` levels from ``top_level + levels - 1`` up to ``top_level`` of
    the subtree of node 2^top_level + tid, from the level below them (one thread a subtree,
    level by level). In place: reads level ``top_level + levels`` of node_lower/node_upper and
    writes the levels above it."""
    t = wp.tid()
    root = (1 << top_level) + t
    for up in range(levels):
        j = levels - 1 - up  # relative depth of the level written now
        first = root << j
        for m in range(first, first + (1 << j)):
            node_lower[m] = wp.min(node_lower[2 * m], node_lower[2 * m + 1])
            node_upper[m] = wp.max(node_upper[2 * m], node_upper[2 * m + 1])


def refit_tree(frames, tree_indices, tree_faces, leaf_faces: int, depth: int, k0: int, k1: int, alpha: float,
               node_lower, node_upper, levels_per_launch: int = 4):
    """Refit every node box at the blend (k0, k1, alpha): the leaves, then the levels above in
    launches of ``levels_per_launch`` levels (1 + ceil(depth / levels_per_launch) launches)."""
    P = 1 << depth
    dev = node_lower.device
    wp.launch(compute_tree_leaf_bounds, P, inputs=[frames, tree_indices, tree_faces, leaf_faces, P, k0, k1, alpha],
              outputs=[node_lower, node_upper], device=dev)
    below = depth  # the deepest level already up to date
    while below > 0:
        n = min(levels_per_launch, below)
        top = below - n
        wp.launch(compute_tree_level_bounds, 1 << top, inputs=[top, n], outputs=[node_lower, node_upper], device=dev)
        below = top


@wp.func
def closest_on_tree(
    frames: wp.array2d[wp.vec3], tree_indices: wp.array[wp.int32], tree_faces: wp.array[wp.int32],
    node_lower: wp.array[wp.vec3], node_upper: wp.array[wp.vec3], leaf_faces: int, num_leaves: int,
    k0: int, k1: int, alpha: float, p: wp.vec3, reach: float, epsilon: float,
):
    """Closest feature of the blended surface within ``reach`` of p [m]: (distance, original
    face index or -1, its closest point's weights, the tie pseudo-normal sum), by a nearest-first
    walk of the tree (a node farther than the closest so far + epsilon is skipped)."""
    min_dist = reach
    min_face = int(-1)
    min_w = wp.vec3(0.0)
    acc_n = wp.vec3(0.0)
    stack = _stack_t()
    stack[0] = 1
    sp = int(1)
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if box_distance(p, node_lower[node], node_upper[node]) < min_dist + epsilon:
            if node >= num_leaves:
                leaf = node - num_leaves
                for j in range(leaf_faces):
                    slot = leaf * leaf_faces + j
                    f = tree_faces[slot]
                    if f >= 0:
                        a, b, e = interpolated_triangle(frames, tree_indices, slot, k0, k1, alpha)
                        dist, w, wn = face_candidate(p, a, b, e, epsilon)
                        min_dist, min_face, min_w, acc_n = keep_closest(dist, f, w, wn, epsilon, min_dist, min_face,
                                                                        min_w, acc_n)
            else:
                c0 = 2 * node
                d0 = box_distance(p, node_lower[c0], node_upper[c0])
                d1 = box_distance(p, node_lower[c0 + 1], node_upper[c0 + 1])
                near = c0
                far = c0 + 1
                d_far = d1
                if d1 < d0:
                    near = c0 + 1
                    far = c0
                    d_far = d0
                if d_far < min_dist + epsilon:  # the far child first: popped after the near one
                    stack[sp] = far
                    sp += 1
                stack[sp] = near
                sp += 1
    return min_dist, min_face, min_w, acc_n


@wp.kernel
def find_closest_on_tree(
    # Model:
    frames: wp.array2d[wp.vec3],
    tree_indices: wp.array[wp.int32],
    tree_faces: wp.array[wp.int32],
    # In:
    node_lower: wp.array[wp.vec3],
    node_upper: wp.array[wp.vec3],
    leaf_faces: int,
    num_leaves: int,
    k0: int,
    k1: int,
    alpha: float,
    points: wp.array[wp.vec3],
    reach: float,
    epsilon: float,
    # Out:
    dist_out: wp.array[float],
    face_out: wp.array[wp.int32],
):
    """Distance [m] of each point to the blended surface within ``reach`` (else reach) and the
    closest face (original index; -1 none)."""
    s = wp.tid()
    d, f, w, n = closest_on_tree(frames, tree_indices, tree_faces, node_lower, node_upper, leaf_faces, num_leaves,
                                 k0, k1, alpha, points[s], reach, epsilon)
    dist_out[s] = d
    face_out[s] = f
