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

from dataclasses import dataclass

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


@dataclass
class ImplicitTree:
    """A tree built by :func:`build_implicit_tree`, on a device.

    tree_faces (P B,) and tree_indices (3 P B,): the host arrays; faces, indices: the same as
    wp.int32 arrays; depth D and num_leaves P = 2^D; node_lower / node_upper (2P,) wp.vec3 [m]:
    the node boxes :func:`refit_tree` writes (:func:`update_tree_slot`'s scratch)."""

    tree_faces: np.ndarray
    tree_indices: np.ndarray
    faces: wp.array
    indices: wp.array
    depth: int
    num_leaves: int
    node_lower: wp.array
    node_upper: wp.array


def allocate_implicit_tree(V: np.ndarray, F: np.ndarray, leaf_faces: int, device) -> ImplicitTree:
    """:func:`build_implicit_tree` of pose ``V`` [m] and faces ``F``, uploaded to ``device``, with
    zeroed node box arrays."""
    tree_faces, tree_indices, depth = build_implicit_tree(V, F, leaf_faces)
    P = 1 << depth
    return ImplicitTree(tree_faces, tree_indices, wp.array(tree_faces, dtype=wp.int32, device=device),
                        wp.array(tree_indices, dtype=wp.int32, device=device), depth, P,
                        wp.zeros(2 * P, dtype=wp.vec3, device=device), wp.zeros(2 * P, dtype=wp.vec3, device=device))


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


# --------------------------------------------------------------------------- interpolated boxes
# The boxes of one tree at two reconstruction frames bound the surface at every blend between
# them: a coordinate of a blended vertex, (1 - alpha) a_i + alpha b_i, is >= (1 - alpha) min a +
# alpha min b (and <= the same with max), so lerp(box_k, box_k+1, alpha) contains the node's
# faces at the blend. The boxes are computed once a frame (slot s holds one frame's, the two
# slots swap roles as frames advance) and the sub-steps in between do no tree upkeep at all.
# Layout for the query's loads: node n's boxes are one row of 4 vec4 [lo slot 0, hi slot 0,
# lo slot 1, hi slot 1] (w unused; 64 bytes, so a node's two children share one 128-byte line),
# and the faces' vertices are copied per frame in tree order (tree_triangles[slot * 3PB + 3 j + c]:
# vertex c of tree slot j), so a leaf's faces are contiguous.

_dstack_t = wp.types.vector(length=TREE_STACK, dtype=wp.float32)


@wp.func_native("""
#if defined(__CUDA_ARCH__)
const float4 f = __ldg(reinterpret_cast<const float4*>(a.data) + i);
return wp::vec4(f.x, f.y, f.z, f.w);
#else
return a.data[i];
#endif
""")
def load_vec4(a: wp.array[wp.vec4], i: int) -> wp.vec4:
    """a[i] through the read-only data path with one 16-byte load on CUDA (as Warp's own BVH
    loads its nodes); a plain load on the CPU."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
const float* f = reinterpret_cast<const float*>(a.data + i);
return wp::vec3(__ldg(f), __ldg(f + 1), __ldg(f + 2));
#else
return a.data[i];
#endif
""")
def load_vec3(a: wp.array[wp.vec3], i: int) -> wp.vec3:
    """a[i] through the read-only data path on CUDA; a plain load on the CPU."""
    ...


@wp.kernel
def pack_tree_bounds(
    # In:
    node_lower: wp.array[wp.vec3],
    node_upper: wp.array[wp.vec3],
    slot: int,
    # Out:
    node_boxes: wp.array[wp.vec4],
):
    """Write node n's box [m] (from :func:`refit_tree` at one frame) into frame slot ``slot``
    (0 or 1) of node_boxes (4 * 2P,: node n's row is entries 4n .. 4n + 3)."""
    n = wp.tid()
    lo = node_lower[n]
    hi = node_upper[n]
    node_boxes[4 * n + 2 * slot] = wp.vec4(lo[0], lo[1], lo[2], 0.0)
    node_boxes[4 * n + 2 * slot + 1] = wp.vec4(hi[0], hi[1], hi[2], 0.0)


@wp.kernel
def gather_tree_triangles(
    # Model:
    frames: wp.array2d[wp.vec3],
    tree_indices: wp.array[wp.int32],
    # In:
    frame: int,
    slot: int,
    # Out:
    tree_triangles: wp.array[wp.vec3],
):
    """tree_triangles[slot * 3PB + i] = frames[frame, tree_indices[i]] [m]: frame ``frame``'s
    face vertices in tree order (3 P B of them a slot)."""
    i = wp.tid()
    tree_triangles[slot * tree_indices.shape[0] + i] = frames[frame, tree_indices[i]]


def update_tree_slot(frames, tree_indices, tree_faces, leaf_faces: int, depth: int, frame: int, slot: int,
                     node_lower, node_upper, node_boxes, tree_triangles, levels_per_launch: int = 4):
    """Once a reconstruction frame: frame ``frame``'s boxes and triangles into slot ``slot``
    (node_lower / node_upper are scratch (2P,) arrays)."""
    refit_tree(frames, tree_indices, tree_faces, leaf_faces, depth, frame, frame, 0.0, node_lower, node_upper,
               levels_per_launch)
    dev = node_boxes.device
    wp.launch(pack_tree_bounds, node_lower.shape[0], inputs=[node_lower, node_upper, slot], outputs=[node_boxes],
              device=dev)
    wp.launch(gather_tree_triangles, tree_indices.shape[0], inputs=[frames, tree_indices, frame, slot],
              outputs=[tree_triangles], device=dev)


@wp.func
def lerp_box_distance(node_boxes: wp.array[wp.vec4], n: int, s0: int, s1: int, alpha: float, p: wp.vec3):
    """Squared distance [m^2] from p to node n's interpolated box (slot s0 weighted 1 - alpha)."""
    lo = wp.lerp(load_vec4(node_boxes, 4 * n + 2 * s0), load_vec4(node_boxes, 4 * n + 2 * s1), alpha)
    hi = wp.lerp(load_vec4(node_boxes, 4 * n + 2 * s0 + 1), load_vec4(node_boxes, 4 * n + 2 * s1 + 1), alpha)
    dx = wp.max(wp.max(lo[0] - p[0], p[0] - hi[0]), 0.0)
    dy = wp.max(wp.max(lo[1] - p[1], p[1] - hi[1]), 0.0)
    dz = wp.max(wp.max(lo[2] - p[2], p[2] - hi[2]), 0.0)
    return dx * dx + dy * dy + dz * dz


@wp.func
def walk_lerp_tree(
    node_boxes: wp.array[wp.vec4], tree_triangles: wp.array[wp.vec3], leaf_faces: int, num_leaves: int,
    num_slots: int, s0: int, s1: int, alpha: float, p: wp.vec3, epsilon: float, start: int, d_start: float,
    min_dist: float, min_slot: int, min_w: wp.vec3, acc_n: wp.vec3,
):
    """The nearest-first walk of the subtree at node ``start`` (squared box distance d_start), folding its
    faces into the running closest feature (min_dist, min_slot: tree slot, weights, tie normal
    sum); a node farther than the closest so far + epsilon is skipped."""
    stack = _stack_t()
    dists = _dstack_t()
    stack[0] = start
    dists[0] = d_start
    sp = int(1)
    o0 = s0 * 3 * num_leaves * leaf_faces
    o1 = s1 * 3 * num_leaves * leaf_faces
    while sp > 0:
        sp -= 1
        node = stack[sp]
        bound = min_dist + epsilon
        if dists[sp] < bound * bound:
            if node >= num_leaves:
                first = (node - num_leaves) * leaf_faces
                for j in range(leaf_faces):
                    slot = first + j
                    if slot < num_slots:
                        a = wp.lerp(load_vec3(tree_triangles, o0 + 3 * slot), load_vec3(tree_triangles, o1 + 3 * slot),
                                    alpha)
                        b = wp.lerp(load_vec3(tree_triangles, o0 + 3 * slot + 1),
                                    load_vec3(tree_triangles, o1 + 3 * slot + 1), alpha)
                        e = wp.lerp(load_vec3(tree_triangles, o0 + 3 * slot + 2),
                                    load_vec3(tree_triangles, o1 + 3 * slot + 2), alpha)
                        dist, w, wn = face_candidate(p, a, b, e, epsilon)
                        min_dist, min_slot, min_w, acc_n = keep_closest(dist, slot, w, wn, epsilon, min_dist, min_slot,
                                                                        min_w, acc_n)
            else:
                c0 = 2 * node
                d0 = lerp_box_distance(node_boxes, c0, s0, s1, alpha, p)
                d1 = lerp_box_distance(node_boxes, c0 + 1, s0, s1, alpha, p)
                near = c0
                far = c0 + 1
                d_near = d0
                d_far = d1
                if d1 < d0:
                    near = c0 + 1
                    far = c0
                    d_near = d1
                    d_far = d0
                if d_far < bound * bound:  # the far child first: popped after the near one
                    stack[sp] = far
                    dists[sp] = d_far
                    sp += 1
                if d_near < bound * bound:
                    stack[sp] = near
                    dists[sp] = d_near
                    sp += 1
    return min_dist, min_slot, min_w, acc_n


@wp.func
def closest_on_lerp_tree(
    node_boxes: wp.array[wp.vec4], tree_triangles: wp.array[wp.vec3], leaf_faces: int, num_leaves: int,
    num_slots: int, s0: int, s1: int, alpha: float, p: wp.vec3, reach: float, epsilon: float, seed_slot: int,
    seed_up: int,
):
    """Closest feature of the blended surface within ``reach`` of p [m] over the interpolated
    boxes: (distance, tree slot or -1, weights, tie normal sum). With a seed (a tree slot near p,
    e.g. the previous sub-step's closest; -1 none) the walk starts in the subtree ``seed_up``
    levels above the seed's leaf and then visits the siblings on the way to the root, so every
    face is still met under the same prune: any seed gives the same closest feature (up to the
    order of faces within epsilon of each other)."""
    min_dist = reach
    min_slot = int(-1)
    min_w = wp.vec3(0.0)
    acc_n = wp.vec3(0.0)
    if seed_slot >= 0 and seed_slot < num_slots:
        node = (num_leaves + seed_slot // leaf_faces) >> seed_up
        if node < 1:
            node = 1
        min_dist, min_slot, min_w, acc_n = walk_lerp_tree(
            node_boxes, tree_triangles, leaf_faces, num_leaves, num_slots, s0, s1, alpha, p, epsilon, node,
            lerp_box_distance(node_boxes, node, s0, s1, alpha, p), min_dist, min_slot, min_w, acc_n)
        while node > 1:
            sib = node ^ 1
            d = lerp_box_distance(node_boxes, sib, s0, s1, alpha, p)
            if d < (min_dist + epsilon) * (min_dist + epsilon):
                min_dist, min_slot, min_w, acc_n = walk_lerp_tree(
                    node_boxes, tree_triangles, leaf_faces, num_leaves, num_slots, s0, s1, alpha, p, epsilon, sib, d,
                    min_dist, min_slot, min_w, acc_n)
            node = node >> 1
    else:
        min_dist, min_slot, min_w, acc_n = walk_lerp_tree(
            node_boxes, tree_triangles, leaf_faces, num_leaves, num_slots, s0, s1, alpha, p, epsilon, 1,
            lerp_box_distance(node_boxes, 1, s0, s1, alpha, p), min_dist, min_slot, min_w, acc_n)
    return min_dist, min_slot, min_w, acc_n


@wp.func
def query_lerp_tree_point(
    s: int, tree_faces: wp.array[wp.int32], node_boxes: wp.array[wp.vec4], tree_triangles: wp.array[wp.vec3],
    leaf_faces: int, num_leaves: int, num_slots: int, s0: int, s1: int, alpha: float, points: wp.array[wp.vec3],
    seed_slots: wp.array[wp.int32], seed_up: int, reach: float, epsilon: float, dist_out: wp.array[float],
    slot_out: wp.array[wp.int32], face_out: wp.array[wp.int32],
):
    """Point s's query of :func:`find_closest_on_lerp_tree` (its body, shared with the probe's
    register-capped copies)."""
    d, slot, w, n = closest_on_lerp_tree(node_boxes, tree_triangles, leaf_faces, num_leaves, num_slots, s0, s1, alpha,
                                         points[s], reach, epsilon, seed_slots[s], seed_up)
    dist_out[s] = d
    slot_out[s] = slot
    f = int(-1)
    if slot >= 0:
        f = tree_faces[slot]
    face_out[s] = f


@wp.kernel
def find_closest_on_lerp_tree(
    # Model:
    tree_faces: wp.array[wp.int32],
    # In:
    node_boxes: wp.array[wp.vec4],
    tree_triangles: wp.array[wp.vec3],
    leaf_faces: int,
    num_leaves: int,
    num_slots: int,
    s0: int,
    s1: int,
    alpha: float,
    points: wp.array[wp.vec3],
    seed_slots: wp.array[wp.int32],
    seed_up: int,
    reach: float,
    epsilon: float,
    # Out:
    dist_out: wp.array[float],
    slot_out: wp.array[wp.int32],
    face_out: wp.array[wp.int32],
):
    """Distance [m] of each point to the surface blended between the frames in slots s0 and s1
    (within ``reach``, else reach), its tree slot (a seed for the next query; -1 none) and its
    original face index (-1 none). seed_slots (n,): each point's seed (-1 none)."""
    query_lerp_tree_point(wp.tid(), tree_faces, node_boxes, tree_triangles, leaf_faces, num_leaves, num_slots, s0, s1,
                          alpha, points, seed_slots, seed_up, reach, epsilon, dist_out, slot_out, face_out)
