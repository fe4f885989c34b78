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

from .collide import contact_reach, contact_side, keeps_contact, make_contact
from .frames import blend_pair, frame_pair, store_frame_key
from .geometry import closest_point_on_triangle

# CUDA fast math (approximate division and square root), as kernels/batch.py and render.py: the
# latency-bound contact queries lose the IEEE sequences' registers and slow-path calls; results
# move by float rounding only (docs/physics.md, "Fast math").
wp.set_module_options({"fast_math": True})


#: the distance of a candidate that is not one (a sliver, a face beyond reach) [m]
NO_DIST = wp.constant(1.0e30)
#: no face at the minimum (the tiled search's block reduction over face indices)
NO_PAIR = wp.constant(2147483647)
#: no candidate in a sphere's key (the face-parallel search's per-sphere atomic minimum)
NO_KEY = wp.constant(wp.int64(9223372036854775807))
#: the face-parallel key: a candidate's distance in KEY_QUANTA steps of the sphere's reach, then
#: its face index in the low FACE_BITS bits (the minimum key: the least distance, then the
#: lowest face index; distances closer than reach / 2^30 count as equal)
KEY_QUANTA = wp.constant(wp.float64(1073741824.0))
FACE_BITS = wp.constant(wp.int64(4294967296))


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
def seed_closest(frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], k0: int, k1: int, alpha: float,
                 p: wp.vec3, reach: float, epsilon: float, seed_face: int):
    """The serial closest-feature search's start: nothing within ``reach``, or ``seed_face`` (a
    face near p, the sphere's closest of the previous sub-step; -1 none) evaluated at the
    current blend. A seed tightens the box prune from the first candidate on; the search still
    meets every face under the same rule, so any seed gives the same closest face (up to the
    order in which faces within epsilon of each other are met); an index out of range (a stale
    face of another surface) is no seed."""
    min_dist = reach
    min_face = int(-1)
    min_w = wp.vec3(0.0)
    acc_n = wp.vec3(0.0)
    if seed_face >= 0 and seed_face < indices.shape[0] / 3:
        a, b, g = interpolated_triangle(frames, indices, seed_face, k0, k1, alpha)
        dist, w, wn = face_candidate(p, a, b, g, epsilon)
        min_dist, min_face, min_w, acc_n = keep_closest(dist, seed_face, w, wn, epsilon, min_dist, min_face, min_w,
                                                        acc_n)
    return min_dist, min_face, min_w, acc_n


@wp.func
def closest_on_swept_bvh(
    bvh: wp.uint64, lowers: wp.array[wp.vec3], uppers: wp.array[wp.vec3], frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32], k0: int, k1: int, alpha: float, p: wp.vec3, reach: float, epsilon: float,
    seed_face: int,
):
    """Closest feature of the interpolated surface within ``reach`` of p (serial box query). A
    face whose swept box (``lowers``/``uppers``, which contain it at every blend of the pair) is
    farther than the closest feature so far + epsilon is skipped unevaluated: it could neither be
    closer nor tie, so the result is that of evaluating every candidate. ``seed_face`` is
    evaluated first (``seed_closest``; -1 none)."""
    ext = wp.vec3(reach + epsilon)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    f = int(0)
    min_dist, min_face, min_w, acc_n = seed_closest(frames, indices, k0, k1, alpha, p, reach, epsilon, seed_face)
    while wp.bvh_query_next(query, f):
        if f != seed_face and box_distance(p, lowers[f], uppers[f]) < min_dist + epsilon:
            a, b, e = interpolated_triangle(frames, indices, f, k0, k1, alpha)
            dist, w, wn = face_candidate(p, a, b, e, epsilon)
            min_dist, min_face, min_w, acc_n = keep_closest(dist, f, w, wn, epsilon, min_dist, min_face, min_w, acc_n)
    return min_dist, min_face, min_w, acc_n


@wp.func
def reduce_closest_over_block(min_dist: float, min_face: int, acc_n: wp.vec3, epsilon: float):
    """The tiled searches' block reduction (every thread of the block calls it with its own
    closest so far): (the block's minimum distance, the lowest face index at exactly that
    distance or NO_PAIR when no thread found a face, the sum of the tie-normal terms of the
    threads whose closest lies within ``epsilon`` of the minimum). The thread whose
    ``min_face`` equals the returned face holds that face's weights."""
    m = wp.tile_min(wp.tile(min_dist))[0]
    first = NO_PAIR
    if min_face >= 0 and min_dist == m:
        first = min_face
    face = wp.tile_min(wp.tile(first))[0]
    tie = wp.vec3(0.0)
    if min_face >= 0 and min_dist < m + epsilon:
        tie = acc_n
    n = wp.tile_sum(wp.tile(tie, preserve_type=True))[0]
    return m, face, n


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
        sign = float(1.0)
        if wp.dot(p - c, acc_n) < 0.0:
            sign = -1.0
        fn = wp.normalize(wp.cross(b - a, e - a))
        side = contact_side(p, c, fn, sign)
        n, depth = make_contact(p, r, c, side, fn)
        if keeps_contact(side, depth, r):
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
    seed: int,
    # Out:
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    """Contact of each sphere with the surface interpolated at sim_time_in (same outputs as
    ``collide_sphere_mesh``), one thread per sphere walking the swept-box BVH (CPU path).
    ``epsilon`` [m] is the tie distance for the pseudo-normal. ``seed`` 1: the sphere's previous
    contact face (``contact_face``, read before it is written) is evaluated first
    (``seed_closest``; ``choices.SEED_PREVIOUS_FACE``)."""
    s = wp.tid()
    p = sphere_pos_in[s]
    r = sphere_radius[s]
    reach = contact_reach(r, sphere_vel_in[s], extra_speed, dt, margin)
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    seed_face = int(-1)
    if seed != 0:
        seed_face = contact_face[s]
    min_dist, min_face, min_w, acc_n = closest_on_swept_bvh(bvh, lowers, uppers, frames, indices, k0, k1, alpha, p,
                                                            reach, epsilon, seed_face)
    write_swept_contact(s, p, r, reach, min_dist, min_face, min_w, acc_n, frames, indices, k0, k1, alpha, fps,
                        contact_face, contact_point, contact_normal, contact_depth, contact_velocity)


@wp.func
def face_key(dist: float, reach: float, f: int) -> wp.int64:
    """The face-parallel search's key of candidate face f at ``dist`` < ``reach`` [m]."""
    q = wp.int64(wp.float64(dist) / wp.float64(reach) * KEY_QUANTA)
    return q * FACE_BITS + wp.int64(f)


@wp.kernel
def find_closest_per_face(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    # State in:
    sim_time_in: wp.array[wp.float64],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
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
    best_key: wp.array[wp.int64],
):
    """The face-parallel search, first pass (launch (M,); for few spheres on large meshes): each
    face tests every sphere; where its swept box is within the sphere's reach (+ epsilon) the
    interpolated triangle is evaluated, and a candidate closer than the reach puts its
    ``face_key`` into the sphere's atomic minimum ``best_key`` (S,) (NO_KEY before the pass).
    No BVH: the work is one read of the faces' boxes, whatever the spheres' neighbourhood holds."""
    f = wp.tid()
    lo = lowers[f]
    hi = uppers[f]
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    have = int(0)
    a = wp.vec3(0.0)
    b = wp.vec3(0.0)
    e = wp.vec3(0.0)
    for s in range(sphere_pos_in.shape[0]):
        p = sphere_pos_in[s]
        reach = contact_reach(sphere_radius[s], sphere_vel_in[s], extra_speed, dt, margin)
        if box_distance(p, lo, hi) < reach + epsilon:
            if have == 0:
                a, b, e = interpolated_triangle(frames, indices, f, k0, k1, alpha)
                have = 1
            dist, w, wn = face_candidate(p, a, b, e, epsilon)
            if dist < reach:
                wp.atomic_min(best_key, s, face_key(dist, reach, f))


@wp.func
def sum_tie_normals(
    frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], vertex_face_offsets: wp.array[wp.int32],
    vertex_faces: wp.array[wp.int32], k0: int, k1: int, alpha: float, p: wp.vec3, reach: float, epsilon: float,
    key: wp.int64, lane: int, lanes: int,
):
    """The face-parallel searches' resolve for one sphere: the face of its ``key`` (NO_KEY:
    none), the closest point on it, and the angle-weighted normal terms of the faces around its
    three vertices within ``epsilon`` of the closest distance that fall to this lane (entries
    lane, lane + lanes, ... of the three vertices' lists; each face counted once)."""
    face = int(-1)
    dist = reach
    w = wp.vec3(0.0)
    tie = wp.vec3(0.0)
    if key != NO_KEY:
        face = int(key - (key / FACE_BITS) * FACE_BITS)
        a, b, e = interpolated_triangle(frames, indices, face, k0, k1, alpha)
        dist, w, wn = face_candidate(p, a, b, e, epsilon)
        v0 = indices[3 * face + 0]
        v1 = indices[3 * face + 1]
        v2 = indices[3 * face + 2]
        n0 = vertex_face_offsets[v0 + 1] - vertex_face_offsets[v0]
        n1 = vertex_face_offsets[v1 + 1] - vertex_face_offsets[v1]
        n2 = vertex_face_offsets[v2 + 1] - vertex_face_offsets[v2]
        j = lane
        while j < n0 + n1 + n2:
            i = int(0)  # entry j of vertex i's list
            g = int(0)
            if j < n0:
                g = vertex_faces[vertex_face_offsets[v0] + j]
            elif j < n0 + n1:
                i = 1
                g = vertex_faces[vertex_face_offsets[v1] + j - n0]
            else:
                i = 2
                g = vertex_faces[vertex_face_offsets[v2] + j - n0 - n1]
            seen = int(0)  # g also holds an earlier vertex of the face: counted in that vertex's list
            for c in range(3):
                u = indices[3 * g + c]
                if (i > 0 and u == v0) or (i > 1 and u == v1):
                    seen = 1
            if seen == 0:
                ga, gb, ge = interpolated_triangle(frames, indices, g, k0, k1, alpha)
                gd, gw, gn = face_candidate(p, ga, gb, ge, epsilon)
                if gd < dist + epsilon:
                    tie = tie + gn
            j += lanes
    return face, dist, w, tie


@wp.kernel
def resolve_closest_per_sphere(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    vertex_face_offsets: wp.array[wp.int32],
    vertex_faces: wp.array[wp.int32],
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
    # Out (read, then reset to NO_KEY for the next step's pass):
    best_key_in_out: wp.array[wp.int64],
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    """The face-parallel search, second pass (``wp.launch_tiled``, dim (S,), a block of threads
    per sphere): each sphere's contact from its key's face (the closest point recomputed), as
    ``collide_sphere_swept``. The pseudo-normal's ties are looked for among the faces around the
    winning face's three vertices (CSR ``vertex_face_offsets`` (N+1,) / ``vertex_faces`` (3M,)),
    the block's threads taking the entries of the three lists in parallel (``sum_tie_normals``):
    each such face within ``epsilon`` of the closest distance adds its angle-weighted normal
    term (summed over the block), as the serial rule's ties do (a tie shares the closest vertex
    or edge; a face elsewhere that happens to lie within epsilon is not looked for). Thread 0
    writes the contact and resets the key for the next step."""
    s, lane = wp.tid()
    p = sphere_pos_in[s]
    r = sphere_radius[s]
    reach = contact_reach(r, sphere_vel_in[s], extra_speed, dt, margin)
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    face, dist, w, tie = sum_tie_normals(frames, indices, vertex_face_offsets, vertex_faces, k0, k1, alpha, p, reach,
                                         epsilon, best_key_in_out[s], lane, wp.block_dim())
    acc_n = wp.tile_sum(wp.tile(tie, preserve_type=True))[0]
    if lane == 0:
        write_swept_contact(s, p, r, reach, dist, face, w, acc_n, frames, indices, k0, k1, alpha, fps,
                            contact_face, contact_point, contact_normal, contact_depth, contact_velocity)
        best_key_in_out[s] = NO_KEY


@wp.kernel
def resolve_closest_per_sphere_serial(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    vertex_face_offsets: wp.array[wp.int32],
    vertex_faces: wp.array[wp.int32],
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
    # Out (read, then reset to NO_KEY for the next step's pass):
    best_key_in_out: wp.array[wp.int64],
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    """``resolve_closest_per_sphere`` with one thread per sphere walking the tie candidates in
    turn (launch (S,)): for many spheres, where a block per sphere would mostly idle (most
    spheres have no key) and the spheres themselves fill the device."""
    s = wp.tid()
    p = sphere_pos_in[s]
    r = sphere_radius[s]
    reach = contact_reach(r, sphere_vel_in[s], extra_speed, dt, margin)
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    face, dist, w, tie = sum_tie_normals(frames, indices, vertex_face_offsets, vertex_faces, k0, k1, alpha, p, reach,
                                         epsilon, best_key_in_out[s], 0, 1)
    write_swept_contact(s, p, r, reach, dist, face, w, tie, frames, indices, k0, k1, alpha, fps,
                        contact_face, contact_point, contact_normal, contact_depth, contact_velocity)
    best_key_in_out[s] = NO_KEY


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
    m, face, n = reduce_closest_over_block(min_dist, min_face, acc_n, epsilon)
    if face == NO_PAIR:
        if lane == 0:  # nothing within reach: the no-contact record
            write_swept_contact(s, p, r, reach, reach, -1, min_w, n, frames, indices, k0, k1, alpha, fps,
                                contact_face, contact_point, contact_normal, contact_depth, contact_velocity)
    elif min_face == face and min_dist == m:
        write_swept_contact(s, p, r, reach, m, face, min_w, n, frames, indices, k0, k1, alpha, fps,
                            contact_face, contact_point, contact_normal, contact_depth, contact_velocity)
