"""Stage 3 (swept path): contact against the interpolated surface without a per-step refit.

Between reconstruction frames k and k+1 every vertex moves on a straight segment, so the
triangle at any blend factor lies inside the box of its six vertices at k and k+1. A
``wp.Bvh`` over these swept boxes is refit once per frame change; every step the contact
kernel finds the candidate faces with a box query and evaluates the interpolated triangles
itself (from frames k, k+1 and alpha): no per-step vertex copy or refit.

The closest-feature selection mirrors ``wp.mesh_query_point_sign_normal`` (angle-weighted
pseudo-normal over faces tied within epsilon), so the contacts equal the refit path's.
"""

import warp as wp

from .collide import contact_reach, make_contact
from .frames import blend_pair, frame_pair, store_frame_key
from .geometry import closest_point_on_triangle


#: the distance of a candidate that is not one (a sliver, a face beyond reach) [m]
NO_DIST = wp.constant(1.0e30)
#: no candidate pair yet / no distance yet: the pair passes' accumulators between steps
NO_PAIR = wp.constant(2147483647)


@wp.kernel
def detect_frame_change(
    # State in:
    sim_time_in: wp.array[wp.float64],
    # In:
    fps: wp.float64,
    num_frames: int,
    mode: int,
    # State out:
    frame_key_out: wp.array[wp.int32],
    frame_changed_out: wp.array[wp.int32],
):
    """frame_changed_out[0] = 1 when the frame pair (k, k+1) at sim_time_in differs from frame_key_out[0] (then updated)."""
    store_frame_key(sim_time_in[0], fps, num_frames, mode, frame_key_out, frame_changed_out)


@wp.kernel
def compute_swept_bounds(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    # State in:
    sim_time_in: wp.array[wp.float64],
    # In:
    fps: wp.float64,
    mode: int,
    # Out:
    lowers: wp.array[wp.vec3],
    uppers: wp.array[wp.vec3],
):
    """Box of each face over the interval between frames k and k+1 (both frames' vertices).

    frames (T, N) [m]; indices (3M,); lowers/uppers (M,) [m].
    """
    f = wp.tid()
    k0, k1, alpha = frame_pair(sim_time_in[0], fps, frames.shape[0], mode)
    i0 = indices[3 * f + 0]
    i1 = indices[3 * f + 1]
    i2 = indices[3 * f + 2]
    a0 = frames[k0, i0]
    b0 = frames[k0, i1]
    c0 = frames[k0, i2]
    a1 = frames[k1, i0]
    b1 = frames[k1, i1]
    c1 = frames[k1, i2]
    lo = wp.min(wp.min(wp.min(a0, b0), wp.min(c0, a1)), wp.min(b1, c1))
    hi = wp.max(wp.max(wp.max(a0, b0), wp.max(c0, a1)), wp.max(b1, c1))
    lowers[f] = lo
    uppers[f] = hi


@wp.func
def vertex_weight_angle(c: wp.vec3, a: wp.vec3, b: wp.vec3, e: wp.vec3, eps_sq: float) -> float:
    """Angle weight of face abc's pseudo-normal at closest point c (as wp.mesh_query_point_sign_normal)."""
    e0 = b - a
    e1 = e - a
    e2 = e - b
    ca = c - a
    cb = c - b
    ce = c - e
    if wp.length_sq(ca) < eps_sq:
        return wp.acos(wp.dot(wp.normalize(e0), wp.normalize(e1)))
    if wp.length_sq(cb) < eps_sq:
        return wp.acos(wp.dot(wp.normalize(e2), wp.normalize(-e0)))
    if wp.length_sq(ce) < eps_sq:
        return wp.acos(wp.dot(wp.normalize(-e1), wp.normalize(-e2)))
    e0n = wp.dot(e0, e0)
    e1n = wp.dot(e1, e1)
    e2n = wp.dot(e2, e2)
    e0c = wp.dot(e0, ca)
    e2c = wp.dot(e2, cb)
    e1c = wp.dot(e1, ca)
    if (
        wp.length_sq(ca) * e0n - e0c * e0c < eps_sq * e0n
        or wp.length_sq(cb) * e2n - e2c * e2c < eps_sq * e2n
        or wp.length_sq(ca) * e1n - e1c * e1c < eps_sq * e1n
    ):
        return 3.14159265359
    return 2.0 * 3.14159265359


@wp.func
def interpolated_triangle(
    frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], f: int, k0: int, k1: int, alpha: float
):
    """Vertices of face f blended between frames k0 and k1."""
    i0 = indices[3 * f + 0]
    i1 = indices[3 * f + 1]
    i2 = indices[3 * f + 2]
    a = wp.lerp(frames[k0, i0], frames[k1, i0], alpha)
    b = wp.lerp(frames[k0, i1], frames[k1, i1], alpha)
    e = wp.lerp(frames[k0, i2], frames[k1, i2], alpha)
    return a, b, e


@wp.func
def face_candidate(p: wp.vec3, a: wp.vec3, b: wp.vec3, e: wp.vec3, epsilon: float):
    """Distance from p to triangle abc, the closest point's weights, and the face's
    angle-weighted normal contribution; distance is +inf for slivers (skipped as by wp.Mesh)."""
    e0 = b - a
    e1 = e - a
    e2 = e - b
    nrm = wp.cross(e0, e1)
    if wp.length(nrm) / (wp.dot(e0, e0) + wp.dot(e1, e1) + wp.dot(e2, e2)) < 1.0e-6:
        return float(NO_DIST), wp.vec3(0.0), wp.vec3(0.0)
    w = closest_point_on_triangle(p, a, b, e)
    c = w[0] * a + w[1] * b + w[2] * e
    weight = vertex_weight_angle(c, a, b, e, epsilon * epsilon)
    return wp.length(c - p), w, weight * wp.normalize(nrm)


@wp.func
def keep_closest(
    dist: float, f: int, w: wp.vec3, wn: wp.vec3, epsilon: float,
    min_dist: float, min_face: int, min_w: wp.vec3, acc_n: wp.vec3,
):
    """Sequential closest-feature update with pseudo-normal accumulation over ties (the rule of
    wp.mesh_query_point_sign_normal)."""
    if dist < min_dist + epsilon:
        if dist > min_dist - epsilon:
            acc_n = acc_n + wn
            if dist < min_dist:
                min_dist = dist
                min_face = f
                min_w = w
        else:
            min_dist = dist
            min_face = f
            min_w = w
            acc_n = wn
    return min_dist, min_face, min_w, acc_n


@wp.func
def box_distance(p: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> float:
    """Distance from p to the box [lo, hi] (0 inside)."""
    return wp.length(wp.max(wp.max(lo - p, p - hi), wp.vec3(0.0)))


@wp.func
def closest_on_swept_bvh(
    bvh: wp.uint64, lowers: wp.array[wp.vec3], uppers: wp.array[wp.vec3], frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32], k0: int, k1: int, alpha: float, p: wp.vec3, reach: float, epsilon: float,
):
    """Closest feature of the interpolated surface within ``reach`` of p (serial box query). A
    face whose swept box (``lowers``/``uppers``, which contain it at every blend of the pair) is
    farther than the closest feature so far + epsilon is skipped unevaluated: it could neither be
    closer nor tie, so the result is that of evaluating every candidate."""
    ext = wp.vec3(reach + epsilon)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    f = int(0)
    min_dist = reach
    min_face = int(-1)
    min_w = wp.vec3(0.0)
    acc_n = wp.vec3(0.0)
    while wp.bvh_query_next(query, f):
        if box_distance(p, lowers[f], uppers[f]) < min_dist + epsilon:
            a, b, e = interpolated_triangle(frames, indices, f, k0, k1, alpha)
            dist, w, wn = face_candidate(p, a, b, e, epsilon)
            min_dist, min_face, min_w, acc_n = keep_closest(dist, f, w, wn, epsilon, min_dist, min_face, min_w, acc_n)
    return min_dist, min_face, min_w, acc_n


@wp.func
def write_swept_contact(
    s: int, p: wp.vec3, r: float, reach: float, min_dist: float, min_face: int, min_w: wp.vec3, acc_n: wp.vec3,
    frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], k0: int, k1: int, alpha: float,
    fps: wp.float64,
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    face = int(-1)
    c = wp.vec3(0.0)
    n = wp.vec3(0.0)
    depth = float(0.0)
    vs = wp.vec3(0.0)
    if min_face >= 0 and min_dist < reach:
        a, b, e = interpolated_triangle(frames, indices, min_face, k0, k1, alpha)
        c = min_w[0] * a + min_w[1] * b + min_w[2] * e
        side = float(1.0)
        if wp.dot(p - c, acc_n) < 0.0:
            side = -1.0
        fn = wp.normalize(wp.cross(b - a, e - a))
        n, depth = make_contact(p, r, c, side, fn)
        if depth > 0.0 or side > 0.0:
            face = min_face
            if k0 != k1:
                i0 = indices[3 * min_face + 0]
                i1 = indices[3 * min_face + 1]
                i2 = indices[3 * min_face + 2]
                vs = float(fps) * (
                    min_w[0] * (frames[k1, i0] - frames[k0, i0])
                    + min_w[1] * (frames[k1, i1] - frames[k0, i1])
                    + min_w[2] * (frames[k1, i2] - frames[k0, i2])
                )
    contact_face[s] = face
    contact_point[s] = c
    contact_normal[s] = n
    contact_depth[s] = depth
    contact_velocity[s] = vs


@wp.kernel
def collide_sphere_swept(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    # State in:
    sim_time_in: wp.array[wp.float64],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    bvh: wp.uint64,
    lowers: wp.array[wp.vec3],
    uppers: wp.array[wp.vec3],
    fps: wp.float64,
    mode: int,
    interpolate: int,
    epsilon: float,
    dt: float,
    extra_speed: float,
    margin: float,
    # Out:
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    """Contact of each sphere with the surface interpolated at sim_time_in (same outputs as
    ``collide_sphere_mesh``), one thread per sphere walking the swept-box BVH (CPU path).
    ``epsilon`` [m] is the tie distance for the pseudo-normal."""
    s = wp.tid()
    p = sphere_pos_in[s]
    r = sphere_radius[s]
    reach = contact_reach(r, sphere_vel_in[s], extra_speed, dt, margin)
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    min_dist, min_face, min_w, acc_n = closest_on_swept_bvh(bvh, lowers, uppers, frames, indices, k0, k1, alpha, p,
                                                            reach, epsilon)
    write_swept_contact(s, p, r, reach, min_dist, min_face, min_w, acc_n, frames, indices, k0, k1, alpha, fps,
                        contact_face, contact_point, contact_normal, contact_depth, contact_velocity)


@wp.kernel
def collide_sphere_swept_tiled(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    # State in:
    sim_time_in: wp.array[wp.float64],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    bvh: wp.uint64,
    lowers: wp.array[wp.vec3],
    uppers: wp.array[wp.vec3],
    fps: wp.float64,
    mode: int,
    interpolate: int,
    epsilon: float,
    dt: float,
    extra_speed: float,
    margin: float,
    # Out:
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    """``collide_sphere_swept`` with one thread block per sphere (``wp.launch_tiled``, dim (S,)):
    the block walks the sphere's box query together (``wp.tile_bvh_query_aabb``), each thread
    evaluating the faces handed to it with the serial rule (``keep_closest``, box prune against
    its own closest so far); then the block's minimum distance, the lowest face index at it
    (deterministic whatever the hand-out order) and the pseudo-normal terms of the threads whose
    own closest lies within ``epsilon`` of that minimum. A sphere with thousands of faces in
    reach is no longer one thread's serial loop (issue 14)."""
    s, lane = wp.tid()
    p = sphere_pos_in[s]
    r = sphere_radius[s]
    reach = contact_reach(r, sphere_vel_in[s], extra_speed, dt, margin)
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    ext = wp.vec3(reach + epsilon)
    min_dist = reach
    min_face = int(-1)
    min_w = wp.vec3(0.0)
    acc_n = wp.vec3(0.0)
    query = wp.tile_bvh_query_aabb(bvh, p - ext, p + ext)
    while wp.tile_query_valid(query):
        f = wp.untile(wp.tile_bvh_query_next(query))
        if f >= 0:
            if box_distance(p, lowers[f], uppers[f]) < min_dist + epsilon:
                a, b, e = interpolated_triangle(frames, indices, f, k0, k1, alpha)
                dist, w, wn = face_candidate(p, a, b, e, epsilon)
                min_dist, min_face, min_w, acc_n = keep_closest(dist, f, w, wn, epsilon, min_dist, min_face, min_w,
                                                                acc_n)
    m = wp.tile_min(wp.tile(min_dist))[0]
    first = NO_PAIR
    if min_face >= 0 and min_dist == m:
        first = min_face
    face = wp.tile_min(wp.tile(first))[0]
    tie = wp.vec3(0.0)
    if min_face >= 0 and min_dist < m + epsilon:
        tie = acc_n
    n = wp.tile_sum(wp.tile(tie, preserve_type=True))[0]
    if face == NO_PAIR:
        if lane == 0:  # nothing within reach: the no-contact record
            write_swept_contact(s, p, r, reach, reach, -1, min_w, n, frames, indices, k0, k1, alpha, fps,
                                contact_face, contact_point, contact_normal, contact_depth, contact_velocity)
    elif min_face == face and min_dist == m:
        write_swept_contact(s, p, r, reach, m, face, min_w, n, frames, indices, k0, k1, alpha, fps,
                            contact_face, contact_point, contact_normal, contact_depth, contact_velocity)


# --- nearest-first search: our own tree over the swept boxes ---------------------------------
# An implicit, balanced binary tree (heap layout: node n has children 2n+1 and 2n+2) over the
# faces sorted by the Morton code of their swept boxes at build, TREE_LEAF_SIZE faces per leaf,
# the leaves padded to a power of two (face -1, empty box). Refit bottom-up one level per launch
# when the frame pair changes; each sphere walks it nearest child first and prunes every node
# whose box is farther than the closest feature so far (+ epsilon), as wp.mesh_query_point does
# for a triangle mesh: a sphere resting on a fine mesh evaluates the few faces under it, not
# every face in its reach box.

TREE_LEAF_SIZE = wp.constant(4)
#: the walk's stack: the tree is balanced, so its depth is log2(leaves) <= 31 and the stack holds
#: at most depth + 1 entries
TREE_STACK = 64
tree_stack_t = wp.types.vector(length=TREE_STACK, dtype=wp.int32)


@wp.kernel
def refit_tree_leaves(
    # In:
    face_order: wp.array[wp.int32],
    lowers: wp.array[wp.vec3],
    uppers: wp.array[wp.vec3],
    first_leaf: int,
    # Out:
    node_lower: wp.array[wp.vec3],
    node_upper: wp.array[wp.vec3],
):
    """Box of each leaf (launch (leaves,)): the union of its faces' swept boxes [m]; an empty
    (padding) leaf gets an inverted box, farther than anything."""
    j = wp.tid()
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for k in range(TREE_LEAF_SIZE):
        f = face_order[j * TREE_LEAF_SIZE + k]
        if f >= 0:
            lo = wp.min(lo, lowers[f])
            hi = wp.max(hi, uppers[f])
    node_lower[first_leaf + j] = lo
    node_upper[first_leaf + j] = hi


@wp.kernel
def refit_tree_level(
    # In:
    level_start: int,
    # Out:
    node_lower: wp.array[wp.vec3],
    node_upper: wp.array[wp.vec3],
):
    """Boxes of one level of inner nodes (launch (2^level,)) from their children's."""
    n = level_start + wp.tid()
    node_lower[n] = wp.min(node_lower[2 * n + 1], node_lower[2 * n + 2])
    node_upper[n] = wp.max(node_upper[2 * n + 1], node_upper[2 * n + 2])


@wp.func
def closest_on_swept_tree(
    node_lower: wp.array[wp.vec3], node_upper: wp.array[wp.vec3], face_order: wp.array[wp.int32], first_leaf: int,
    lowers: wp.array[wp.vec3], uppers: wp.array[wp.vec3], frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32], k0: int, k1: int, alpha: float, p: wp.vec3, reach: float, epsilon: float,
):
    """``closest_on_swept_bvh``'s answer by a nearest-first walk of the tree: a node (or face)
    whose box is farther than the closest feature so far + epsilon holds nothing closer and no
    tie, so it is skipped; children are visited nearest first so the bound tightens early."""
    min_dist = reach
    min_face = int(-1)
    min_w = wp.vec3(0.0)
    acc_n = wp.vec3(0.0)
    stack = tree_stack_t()
    stack[0] = 0
    top = int(1)
    while top > 0:
        top -= 1
        n = stack[top]
        if box_distance(p, node_lower[n], node_upper[n]) < min_dist + epsilon:
            if n >= first_leaf:
                base = (n - first_leaf) * TREE_LEAF_SIZE
                for k in range(TREE_LEAF_SIZE):
                    f = face_order[base + k]
                    if f >= 0:
                        if box_distance(p, lowers[f], uppers[f]) < min_dist + epsilon:
                            a, b, e = interpolated_triangle(frames, indices, f, k0, k1, alpha)
                            dist, w, wn = face_candidate(p, a, b, e, epsilon)
                            min_dist, min_face, min_w, acc_n = keep_closest(dist, f, w, wn, epsilon, min_dist,
                                                                            min_face, min_w, acc_n)
            else:
                c0 = 2 * n + 1
                c1 = 2 * n + 2
                d0 = box_distance(p, node_lower[c0], node_upper[c0])
                d1 = box_distance(p, node_lower[c1], node_upper[c1])
                near = c0
                far = c1
                dn = d0
                df = d1
                if d1 < d0:
                    near = c1
                    far = c0
                    dn = d1
                    df = d0
                if df < min_dist + epsilon:  # farther child below, popped after the nearer one
                    stack[top] = far
                    top += 1
                if dn < min_dist + epsilon:
                    stack[top] = near
                    top += 1
    return min_dist, min_face, min_w, acc_n


@wp.kernel
def collide_sphere_swept_nearest(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    # State in:
    sim_time_in: wp.array[wp.float64],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    node_lower: wp.array[wp.vec3],
    node_upper: wp.array[wp.vec3],
    face_order: wp.array[wp.int32],
    first_leaf: int,
    lowers: wp.array[wp.vec3],
    uppers: wp.array[wp.vec3],
    fps: wp.float64,
    mode: int,
    interpolate: int,
    epsilon: float,
    dt: float,
    extra_speed: float,
    margin: float,
    # Out:
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    """``collide_sphere_swept`` with the nearest-first walk of the swept-box tree
    (``closest_on_swept_tree``), one thread per sphere."""
    s = wp.tid()
    p = sphere_pos_in[s]
    r = sphere_radius[s]
    reach = contact_reach(r, sphere_vel_in[s], extra_speed, dt, margin)
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    min_dist, min_face, min_w, acc_n = closest_on_swept_tree(node_lower, node_upper, face_order, first_leaf, lowers,
                                                             uppers, frames, indices, k0, k1, alpha, p, reach,
                                                             epsilon)
    write_swept_contact(s, p, r, reach, min_dist, min_face, min_w, acc_n, frames, indices, k0, k1, alpha, fps,
                        contact_face, contact_point, contact_normal, contact_depth, contact_velocity)


# --- parallel path (GPU): candidates gathered once per frame into one pool, evaluated and
# reduced over (sphere, candidate) pairs, so a sphere with thousands of candidates does not walk
# them in one thread (issue 14) ---------------------------------------------------------------



@wp.kernel
def gather_sphere_candidates(
    # Model:
    sphere_radius: wp.array[float],
    # State in:
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    bvh: wp.uint64,
    horizon: float,
    gravity: float,
    margin: float,
    # Out:
    cand_face: wp.array[wp.int32],
    cand_sphere: wp.array[wp.int32],
    cand_start: wp.array[wp.int32],
    cand_count: wp.array[wp.int32],
    cand_center: wp.array[wp.vec3],
    cand_radius: wp.array[float],
    pool_used: wp.array[wp.int32],
):
    """Faces whose swept box lies within the sphere's reach over the next ``horizon`` seconds
    (one frame interval): R = radius + margin + 1.25 (|v| T + g T^2 / 2) + (one step's reach,
    folded into margin by the caller). Each sphere counts its faces, reserves that many entries
    of the pool (cand_face, cand_sphere (P,); ``pool_used`` (1,) zeroed before: the entries asked
    for, which may exceed P; only the first P are used) and writes them
    in BVH order: cand_start (S,) its first entry, -1 if the pool was full (then the sphere takes
    the serial path); cand_count (S,) the faces found. A sphere that travels farther than this
    ball allows during the interval also takes the serial path (checked every step)."""
    s = wp.tid()
    p = sphere_pos_in[s]
    T = horizon
    R = sphere_radius[s] + margin + 1.25 * (wp.length(sphere_vel_in[s]) * T + 0.5 * gravity * T * T)
    lo = p - wp.vec3(R)
    hi = p + wp.vec3(R)
    query = wp.bvh_query_aabb(bvh, lo, hi)
    f = int(0)
    n = int(0)
    while wp.bvh_query_next(query, f):
        n += 1
    cand_count[s] = n
    cand_center[s] = p
    cand_radius[s] = R
    base = wp.atomic_add(pool_used, 0, n)
    if base + n > cand_face.shape[0]:
        cand_start[s] = -1
        for k in range(base, cand_face.shape[0]):  # the part of its range inside the pool: unused
            cand_sphere[k] = -1
        return
    cand_start[s] = base
    query = wp.bvh_query_aabb(bvh, lo, hi)
    j = int(0)
    while wp.bvh_query_next(query, f):
        cand_face[base + j] = f
        cand_sphere[base + j] = s
        j += 1


@wp.kernel
def evaluate_sphere_candidates(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    # State in:
    sim_time_in: wp.array[wp.float64],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    fps: wp.float64,
    mode: int,
    interpolate: int,
    epsilon: float,
    dt: float,
    extra_speed: float,
    margin: float,
    cand_face: wp.array[wp.int32],
    cand_sphere: wp.array[wp.int32],
    cand_start: wp.array[wp.int32],
    pool_used: wp.array[wp.int32],
    lowers: wp.array[wp.vec3],
    uppers: wp.array[wp.vec3],
    threads: int,
    # Out:
    cand_dist: wp.array[float],
    cand_w: wp.array[wp.vec3],
    cand_wn: wp.array[wp.vec3],
    min_dist: wp.array[float],
):
    """Distance, closest-point weights and pseudo-normal term of every pooled (sphere, face)
    pair (launch (threads,), each thread striding over the pool's used entries), and each
    sphere's minimum distance below its reach (atomic; ``min_dist`` holds NO_DIST between steps).
    A face whose swept box lies beyond the reach is skipped (distance NO_DIST)."""
    t = wp.tid()
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    for i in range(t, wp.min(pool_used[0], cand_sphere.shape[0]), threads):
        cand_dist[i] = NO_DIST
        s = cand_sphere[i]
        if s >= 0 and cand_start[s] >= 0:
            f = cand_face[i]
            p = sphere_pos_in[s]
            reach = contact_reach(sphere_radius[s], sphere_vel_in[s], extra_speed, dt, margin)
            if box_distance(p, lowers[f], uppers[f]) < reach + epsilon:
                a, b, e = interpolated_triangle(frames, indices, f, k0, k1, alpha)
                dist, w, wn = face_candidate(p, a, b, e, epsilon)
                cand_dist[i] = dist
                cand_w[i] = w
                cand_wn[i] = wn
                if dist < reach:
                    wp.atomic_min(min_dist, s, dist)


@wp.kernel
def find_closest_candidates(
    # In:
    epsilon: float,
    cand_sphere: wp.array[wp.int32],
    cand_dist: wp.array[float],
    cand_wn: wp.array[wp.vec3],
    pool_used: wp.array[wp.int32],
    min_dist: wp.array[float],
    threads: int,
    # Out:
    min_pair: wp.array[wp.int32],
    acc_normal: wp.array[wp.vec3],
):
    """Per pooled pair (launch (threads,), striding): the first pair in gather order at its
    sphere's minimum distance is the closest feature (the serial rule keeps the first of equal
    distances; ``min_pair`` holds NO_PAIR between steps), and every pair within ``epsilon`` of
    the minimum adds its pseudo-normal term (the tie rule of wp.mesh_query_point_sign_normal,
    taken against the final minimum)."""
    t = wp.tid()
    for i in range(t, wp.min(pool_used[0], cand_sphere.shape[0]), threads):
        d = cand_dist[i]
        if d < NO_DIST:
            s = cand_sphere[i]
            m = min_dist[s]
            if m < NO_DIST:
                if d < m + epsilon:
                    wp.atomic_add(acc_normal, s, cand_wn[i])
                if d == m:
                    wp.atomic_min(min_pair, s, i)


@wp.kernel
def resolve_sphere_candidates(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    # State in:
    sim_time_in: wp.array[wp.float64],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    bvh: wp.uint64,
    lowers: wp.array[wp.vec3],
    uppers: wp.array[wp.vec3],
    fps: wp.float64,
    mode: int,
    interpolate: int,
    epsilon: float,
    cand_face: wp.array[wp.int32],
    cand_start: wp.array[wp.int32],
    cand_center: wp.array[wp.vec3],
    cand_radius: wp.array[float],
    cand_w: wp.array[wp.vec3],
    dt: float,
    extra_speed: float,
    margin: float,
    # Out:
    min_dist: wp.array[float],
    min_pair: wp.array[wp.int32],
    acc_normal: wp.array[wp.vec3],
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    """Closest feature per sphere from the pair passes; a sphere whose reach left its gathered
    ball, or that found the pool full, walks the BVH serially. Same outputs as
    ``collide_sphere_mesh``. Resets the sphere's pair-pass accumulators for the next step."""
    s = wp.tid()
    p = sphere_pos_in[s]
    r = sphere_radius[s]
    reach = contact_reach(r, sphere_vel_in[s], extra_speed, dt, margin)
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    md = reach
    mf = int(-1)
    mw = wp.vec3(0.0)
    an = wp.vec3(0.0)
    if cand_start[s] < 0 or wp.length(p - cand_center[s]) + reach + epsilon > cand_radius[s]:
        md, mf, mw, an = closest_on_swept_bvh(bvh, lowers, uppers, frames, indices, k0, k1, alpha, p, reach, epsilon)
    else:
        i = min_pair[s]
        if i != NO_PAIR:
            md = min_dist[s]
            mf = cand_face[i]
            mw = cand_w[i]
            an = acc_normal[s]
    min_dist[s] = NO_DIST
    min_pair[s] = NO_PAIR
    acc_normal[s] = wp.vec3(0.0)
    write_swept_contact(s, p, r, reach, md, mf, mw, an, frames, indices, k0, k1, alpha, fps,
                        contact_face, contact_point, contact_normal, contact_depth, contact_velocity)
