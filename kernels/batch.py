"""Batched environments (issue 15): many worlds in one Model/State, each with its own clock.

Every env plays the same reconstruction, each at its own time, so no single vertex buffer or
BVH fits them all. Instead the swept BVH of every frame pair is built once at load
(``compute_pair_bounds``: the faces' boxes over frames k and k+1, cut into ``slices`` time
slices so a fast-moving face's box stays small; pair T-1 is the loop's wrap pair (T-1, 0)); a
sphere of env e picks the slot of e's frame pair and blend and evaluates the interpolated
triangles itself, exactly as the single-clock swept collider does. Nothing is refit per step or
per env.

Flat layout: env e owns spheres ``sphere_env == e`` (E * S spheres in all, env-major).
"""

import warp as wp

from .collide import contact_reach
from .frames import PLAYBACK_LOOP, blend_pair, wrap_frame
from .integrate import advance_and_store_sphere, pinch_memory
from .swept import (
    NO_PAIR,
    box_distance,
    face_candidate,
    interpolated_triangle,
    keep_closest,
    reduce_closest_over_block,
    seed_closest,
    write_swept_contact,
)

# CUDA fast math (approximate division and square root, denormals flushed): IEEE division and
# square root are instruction sequences with a slow-path call, which cost the latency-bound
# queries registers, stack and issue slots; the approximations are within 2 ulp, far below the
# float32 geometry's own rounding and the searches' tie tolerance. H100, landing window at
# 4,096 envs: 9,831-9,838 -> 11,159-11,184 batched steps/s (docs/envs.md).
wp.set_module_options({"fast_math": True})


#: a candidate budget no query reaches (``closest_on_pair_bvh`` walks every candidate)
NO_BUDGET = wp.constant(2147483647)


@wp.func
def pair_slot(k0: int, k1: int, alpha: float, num_frames: int, slices: int) -> int:
    """The BVH slot of the surface between frames k0 and k1 at blend ``alpha``: frame pair p =
    min(k0, k1) for neighbours, T-1 for the loop's wrap pair (T-1, 0), and for a held frame
    (k0 == k1, clamped at an end) the pair that contains it; then the time slice of that pair,
    of ``slices`` equal slices of the interval from the pair's first frame to its second (a
    pingpong pair played backwards counts alpha from the other end). Slot = p * slices + slice."""
    T = num_frames
    p = int(0)
    u = float(0.0)  # position in the pair, 0 at its first frame, 1 at its second
    if k0 == k1:
        p = wp.min(k0, wp.max(T - 2, 0))
        if k0 != p:
            u = 1.0
    else:
        lo = wp.min(k0, k1)
        hi = wp.max(k0, k1)
        if hi == lo + 1:
            p = lo
            u = alpha
            if k0 > k1:
                u = 1.0 - alpha
        else:
            p = T - 1
            u = alpha
            if k0 < k1:
                u = 1.0 - alpha
    sl = wp.min(int(u * float(slices)), slices - 1)
    return p * slices + wp.max(sl, 0)


@wp.func
def closest_on_pair_bvh(
    bvh: wp.uint64, lowers: wp.array2d[wp.vec3], uppers: wp.array2d[wp.vec3], slot: int,
    frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], k0: int, k1: int, alpha: float, p: wp.vec3,
    reach: float, epsilon: float, budget: int, seed_face: int,
):
    """Closest feature of the interpolated surface within ``reach`` of p over the candidates of
    slot's BVH, skipping a face whose box is farther than the closest feature so far
    (+ epsilon): the box contains the face at every blend of the slot, so a skipped face could
    neither be closer nor tie; the result is that of evaluating all. The walk stops at the
    first candidate over ``budget`` (the last value returned is then 1 and the rest incomplete).
    ``seed_face`` is evaluated first (``seed_closest``; -1 none)."""
    ext = wp.vec3(reach + epsilon)
    query = wp.bvh_query_aabb(bvh, p - ext, p + ext)
    f = int(0)
    c = int(0)
    over = int(0)
    min_dist, min_face, min_w, acc_n = seed_closest(frames, indices, k0, k1, alpha, p, reach, epsilon, seed_face)
    while wp.bvh_query_next(query, f):
        c += 1
        if c > budget:
            over = 1
            break
        if f != seed_face and box_distance(p, lowers[slot, f], uppers[slot, f]) < min_dist + epsilon:
            a, b, g = interpolated_triangle(frames, indices, f, k0, k1, alpha)
            dist, w, wn = face_candidate(p, a, b, g, epsilon)
            min_dist, min_face, min_w, acc_n = keep_closest(dist, f, w, wn, epsilon, min_dist, min_face, min_w, acc_n)
    return min_dist, min_face, min_w, acc_n, over


@wp.kernel
def compute_pair_bounds(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    slices: int,
    # Out:
    lowers: wp.array2d[wp.vec3],
    uppers: wp.array2d[wp.vec3],
):
    """Box of each face over every time slice of every frame pair: slot k * slices + j spans the
    surface from frame k to frame (k + 1) mod T over blend [j / slices, (j + 1) / slices]
    (linear motion: the box of the triangle at the slice's two ends contains it in between).

    frames (T, N) [m]; indices (3M,); lowers/uppers (T * slices, M) [m]. Launch (T * slices, M)."""
    slot, f = wp.tid()
    T = frames.shape[0]
    k = slot / slices
    j = slot - k * slices
    k1 = wrap_frame(k + 1, T, PLAYBACK_LOOP)  # the last pair is the wrap pair (T-1, 0)
    a0 = float(j) / float(slices)
    a1 = float(j + 1) / float(slices)
    lo = frames[k, indices[3 * f]]
    hi = lo
    for c in range(3):
        v0 = frames[k, indices[3 * f + c]]
        v1 = frames[k1, indices[3 * f + c]]
        a = v0 * (1.0 - a0) + v1 * a0
        b = v0 * (1.0 - a1) + v1 * a1
        lo = wp.min(lo, wp.min(a, b))
        hi = wp.max(hi, wp.max(a, b))
    lowers[slot, f] = lo
    uppers[slot, f] = hi


#: the serial search's register cap per thread on CUDA, for the same reason as
#: GRID_QUERY_MAX_REGISTERS (uncapped: 115 registers, 17 warps an SM).
SERIAL_QUERY_MAX_REGISTERS = 80


@wp.kernel(cuda_max_registers=SERIAL_QUERY_MAX_REGISTERS)
def collide_and_integrate_env_spheres(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    pair_bvh: wp.array[wp.uint64],
    pair_lowers: wp.array2d[wp.vec3],
    pair_uppers: wp.array2d[wp.vec3],
    sphere_radius: wp.array[float],
    inv_mass: wp.array[float],
    sphere_env: wp.array[wp.int32],
    gravity: wp.vec3,
    restitution: float,
    friction: float,
    rest_speed: float,
    ground: int,
    ground_height: float,
    fps: wp.float64,
    interpolate: int,
    inertia: float,
    slices: int,
    # State in:
    env_time_in: wp.array[wp.float64],
    env_rate_in: wp.array[float],
    env_playback_in: wp.array[wp.int32],
    # In:
    dt: float,
    extra_speed: float,
    margin: float,
    epsilon: float,
    seed: int,
    # State out:
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
    sphere_spin_out: wp.array[wp.vec3],
    # Out:
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
    contact_memory: wp.array[pinch_memory],
):
    """One sub-step of every sphere of every env: contact with the surface at its env's time
    (``env_time_in[e]`` [s], played at ``env_rate_in[e]`` x, playback code
    ``env_playback_in[e]``), then the continuous response of ``integrate_spheres``. The
    surface velocity at the contact is scaled by the env's rate. One thread per sphere;
    (E * S,) arrays; dt [s] is the sub-step. ``seed`` 1: the sphere's previous contact face
    (``contact_face``, read before it is written) is evaluated first (``seed_closest``)."""
    s = wp.tid()
    e = sphere_env[s]
    T = frames.shape[0]
    rate = env_rate_in[e]
    k0, k1, alpha = blend_pair(env_time_in[e], fps, T, env_playback_in[e], interpolate)
    p = sphere_pos_out[s]
    v = sphere_vel_out[s]
    r = sphere_radius[s]
    reach = contact_reach(r, v, extra_speed, dt, margin)
    slot = pair_slot(k0, k1, alpha, T, slices)
    seed_face = int(-1)
    if seed != 0:
        seed_face = contact_face[s]
    min_dist, min_face, min_w, acc_n, over = closest_on_pair_bvh(pair_bvh[slot], pair_lowers, pair_uppers, slot,
                                                                 frames, indices, k0, k1, alpha, p, reach, epsilon,
                                                                 NO_BUDGET, seed_face)
    write_swept_contact(s, p, r, reach, min_dist, min_face, min_w, acc_n, frames, indices, k0, k1, alpha,
                        fps * wp.float64(rate), contact_face, contact_point, contact_normal, contact_depth,
                        contact_velocity)
    advance_and_store_sphere(s, p, v, inv_mass[s], r, gravity, dt, restitution, friction, rest_speed, ground,
                             ground_height, inertia, contact_face, contact_normal, contact_depth, contact_velocity,
                             contact_memory, sphere_pos_out, sphere_vel_out, sphere_spin_out)


@wp.func
def locate_sphere_query(
    s: int, lane: int, frames: wp.array2d[wp.vec3], sphere_radius: wp.array[float], sphere_env: wp.array[wp.int32],
    fps: wp.float64, interpolate: int, slices: int, env_time_in: wp.array[wp.float64],
    env_playback_in: wp.array[wp.int32], sphere_pos_in: wp.array[wp.vec3], sphere_vel_in: wp.array[wp.vec3],
    dt: float, extra_speed: float, margin: float, query_time: wp.array[wp.float64],
):
    """Where sphere s's contact query of the split searches looks: its env's frame pair and
    blend (k0, k1, alpha), its centre p [m], its one-step reach [m] and the pair BVH / grid slot.
    The thread of ``lane`` 0 copies the env's time [s] into s's record (``query_time``): the
    resolve stage reads the blend from there while it advances the clocks."""
    e = sphere_env[s]
    T = frames.shape[0]
    t = env_time_in[e]
    if lane == 0:
        query_time[s] = t
    k0, k1, alpha = blend_pair(t, fps, T, env_playback_in[e], interpolate)
    p = sphere_pos_in[s]
    reach = contact_reach(sphere_radius[s], sphere_vel_in[s], extra_speed, dt, margin)
    return k0, k1, alpha, p, reach, pair_slot(k0, k1, alpha, T, slices)


@wp.func
def write_block_query(
    s: int, lane: int, reach: float, min_dist: float, min_face: int, min_w: wp.vec3, acc_n: wp.vec3, epsilon: float,
    query_dist: wp.array[float], query_face: wp.array[wp.int32], query_w: wp.array[wp.vec3],
    query_n: wp.array[wp.vec3],
):
    """The block searches' end (every thread of the block calls it with its own closest so
    far): the block reduction (``reduce_closest_over_block``), then sphere s's record written by
    the thread holding the winning face (its weights), or the no-contact record by the first."""
    m, face, n = reduce_closest_over_block(min_dist, min_face, acc_n, epsilon)
    if face == NO_PAIR:
        if lane == 0:  # nothing within reach
            query_dist[s] = reach
            query_face[s] = -1
            query_w[s] = wp.vec3(0.0)
            query_n[s] = wp.vec3(0.0)
    elif min_face == face and min_dist == m:
        query_dist[s] = m
        query_face[s] = face
        query_w[s] = min_w
        query_n[s] = n


@wp.func
def find_closest_tiled(
    s: int, lane: int,
    frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], pair_bvh: wp.array[wp.uint64],
    pair_lowers: wp.array2d[wp.vec3], pair_uppers: wp.array2d[wp.vec3], sphere_radius: wp.array[float],
    sphere_env: wp.array[wp.int32], fps: wp.float64, interpolate: int, slices: int,
    env_time_in: wp.array[wp.float64], env_playback_in: wp.array[wp.int32], sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3], dt: float, extra_speed: float, margin: float, epsilon: float,
    query_dist: wp.array[float], query_face: wp.array[wp.int32], query_w: wp.array[wp.vec3],
    query_n: wp.array[wp.vec3],
    query_time: wp.array[wp.float64],
):
    """Sphere s's contact query by the calling thread block (``lane`` = the thread's index in
    it; every thread of the block calls this for the same s): as the single world's
    ``collide_sphere_swept_tiled`` the block walks the box query in s's env's pair BVH together
    (``wp.tile_bvh_query_aabb``), each thread evaluates the faces handed to it with the serial
    rule (box prune against its own closest so far), then the block's minimum distance, the
    lowest face index at it and the tie-normal sum of the threads within ``epsilon`` of it are
    written to s's record (face -1 when nothing is within reach)."""
    k0, k1, alpha, p, reach, slot = locate_sphere_query(s, lane, frames, sphere_radius, sphere_env, fps,
                                                        interpolate, slices, env_time_in, env_playback_in,
                                                        sphere_pos_in, sphere_vel_in, dt, extra_speed, margin,
                                                        query_time)
    ext = wp.vec3(reach + epsilon)
    min_dist = reach
    min_face = int(-1)
    min_w = wp.vec3(0.0)
    acc_n = wp.vec3(0.0)
    query = wp.tile_bvh_query_aabb(pair_bvh[slot], p - ext, p + ext)
    while wp.tile_query_valid(query):
        f = wp.untile(wp.tile_bvh_query_next(query))
        if f >= 0:
            if box_distance(p, pair_lowers[slot, f], pair_uppers[slot, f]) < min_dist + epsilon:
                a, b, g = interpolated_triangle(frames, indices, f, k0, k1, alpha)
                dist, w, wn = face_candidate(p, a, b, g, epsilon)
                min_dist, min_face, min_w, acc_n = keep_closest(dist, f, w, wn, epsilon, min_dist, min_face, min_w,
                                                                acc_n)
    write_block_query(s, lane, reach, min_dist, min_face, min_w, acc_n, epsilon, query_dist, query_face, query_w,
                      query_n)


@wp.kernel
def collide_env_sphere_tiled(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    pair_bvh: wp.array[wp.uint64],
    pair_lowers: wp.array2d[wp.vec3],
    pair_uppers: wp.array2d[wp.vec3],
    sphere_radius: wp.array[float],
    sphere_env: wp.array[wp.int32],
    fps: wp.float64,
    interpolate: int,
    slices: int,
    # State in:
    env_time_in: wp.array[wp.float64],
    env_playback_in: wp.array[wp.int32],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    dt: float,
    extra_speed: float,
    margin: float,
    epsilon: float,
    # Out:
    query_dist: wp.array[float],
    query_face: wp.array[wp.int32],
    query_w: wp.array[wp.vec3],
    query_n: wp.array[wp.vec3],
    query_time: wp.array[wp.float64],
):
    """The contact query of every sphere by one thread block each (``wp.launch_tiled``, dim
    (E * S,)): ``find_closest_tiled``; the records are resolved by
    ``resolve_and_integrate_env_spheres``."""
    s, lane = wp.tid()
    find_closest_tiled(s, lane, frames, indices, pair_bvh, pair_lowers, pair_uppers, sphere_radius, sphere_env, fps,
                       interpolate, slices, env_time_in, env_playback_in, sphere_pos_in, sphere_vel_in, dt,
                       extra_speed, margin, epsilon, query_dist, query_face, query_w, query_n, query_time)


@wp.kernel
def collide_env_spheres_bounded(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    pair_bvh: wp.array[wp.uint64],
    pair_lowers: wp.array2d[wp.vec3],
    pair_uppers: wp.array2d[wp.vec3],
    sphere_radius: wp.array[float],
    sphere_env: wp.array[wp.int32],
    fps: wp.float64,
    interpolate: int,
    slices: int,
    # State in:
    env_time_in: wp.array[wp.float64],
    env_playback_in: wp.array[wp.int32],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    budget: int,
    dt: float,
    extra_speed: float,
    margin: float,
    epsilon: float,
    # Out:
    query_dist: wp.array[float],
    query_face: wp.array[wp.int32],
    query_w: wp.array[wp.vec3],
    query_n: wp.array[wp.vec3],
    query_time: wp.array[wp.float64],
    heavy_count: wp.array[wp.int32],
    heavy: wp.array[wp.int32],
):
    """The contact query of each sphere by one thread (serial), for the spheres whose box query
    holds at most ``budget`` candidate faces; a sphere with more stops at the first one over
    and is appended to ``heavy`` (count in ``heavy_count[0]``, zeroed before the launch) for
    ``collide_env_heavy_spheres_tiled``. (E * S,) records as ``collide_env_sphere_tiled``."""
    s = wp.tid()
    k0, k1, alpha, p, reach, slot = locate_sphere_query(s, 0, frames, sphere_radius, sphere_env, fps,
                                                        interpolate, slices, env_time_in, env_playback_in,
                                                        sphere_pos_in, sphere_vel_in, dt, extra_speed, margin,
                                                        query_time)
    min_dist, min_face, min_w, acc_n, over = closest_on_pair_bvh(pair_bvh[slot], pair_lowers, pair_uppers, slot,
                                                                 frames, indices, k0, k1, alpha, p, reach, epsilon,
                                                                 budget, -1)
    if over != 0:
        heavy[wp.atomic_add(heavy_count, 0, 1)] = s
    else:
        query_dist[s] = min_dist
        query_face[s] = min_face
        query_w[s] = min_w
        query_n[s] = acc_n


@wp.kernel
def collide_env_heavy_spheres_tiled(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    pair_bvh: wp.array[wp.uint64],
    pair_lowers: wp.array2d[wp.vec3],
    pair_uppers: wp.array2d[wp.vec3],
    sphere_radius: wp.array[float],
    sphere_env: wp.array[wp.int32],
    fps: wp.float64,
    interpolate: int,
    slices: int,
    # State in:
    env_time_in: wp.array[wp.float64],
    env_playback_in: wp.array[wp.int32],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    heavy_count: wp.array[wp.int32],
    heavy: wp.array[wp.int32],
    num_blocks: int,
    dt: float,
    extra_speed: float,
    margin: float,
    epsilon: float,
    # Out:
    query_dist: wp.array[float],
    query_face: wp.array[wp.int32],
    query_w: wp.array[wp.vec3],
    query_n: wp.array[wp.vec3],
    query_time: wp.array[wp.float64],
):
    """The contact query of the spheres ``collide_env_spheres_bounded`` left (``heavy``), by
    ``num_blocks`` thread blocks (``wp.launch_tiled``, dim (num_blocks,)) each taking every
    num_blocks-th of them: ``find_closest_tiled``. A fixed launch whatever the count (capturable)."""
    b, lane = wp.tid()
    count = heavy_count[0]
    i = b
    while i < count:
        find_closest_tiled(heavy[i], lane, frames, indices, pair_bvh, pair_lowers, pair_uppers, sphere_radius,
                           sphere_env, fps, interpolate, slices, env_time_in, env_playback_in, sphere_pos_in,
                           sphere_vel_in, dt, extra_speed, margin, epsilon, query_dist, query_face, query_w, query_n,
                           query_time)
        i += num_blocks


@wp.func
def grid_cell(x: wp.vec3, origin: wp.vec3, inv_cell: float, dims: wp.vec3i) -> wp.vec3i:
    """The cell (clamped to the grid) holding point x [m] of a grid from ``origin`` [m] with
    cells of 1 / ``inv_cell`` [m] and ``dims`` cells a side. The grid's builder and its queries
    call this one function, so a face is found in every cell a query computes for it."""
    c = wp.vec3i(0, 0, 0)
    for a in range(3):
        c[a] = wp.clamp(int(wp.floor((x[a] - origin[a]) * inv_cell)), 0, dims[a] - 1)
    return c


@wp.func
def grid_key(slot: int, cells_per_slot: int, dims: wp.vec3i, x: int, y: int, z: int) -> int:
    """The cell lists' key of cell (x, y, z) of a slot's grid of ``dims`` cells."""
    return slot * cells_per_slot + (z * dims[1] + y) * dims[0] + x


@wp.kernel
def count_face_cells(
    # Model:
    pair_lowers: wp.array2d[wp.vec3],
    pair_uppers: wp.array2d[wp.vec3],
    grid_origin: wp.array[wp.vec3],
    grid_dims: wp.array[wp.vec3i],
    inv_cell: float,
    # Out:
    counts: wp.array2d[wp.int32],
):
    """How many grid cells each face's pair box overlaps in each slot (launch (slots, M))."""
    slot, f = wp.tid()
    a = grid_cell(pair_lowers[slot, f], grid_origin[slot], inv_cell, grid_dims[slot])
    b = grid_cell(pair_uppers[slot, f], grid_origin[slot], inv_cell, grid_dims[slot])
    counts[slot, f] = (b[0] - a[0] + 1) * (b[1] - a[1] + 1) * (b[2] - a[2] + 1)


@wp.kernel
def emit_face_cells(
    # Model:
    pair_lowers: wp.array2d[wp.vec3],
    pair_uppers: wp.array2d[wp.vec3],
    grid_origin: wp.array[wp.vec3],
    grid_dims: wp.array[wp.vec3i],
    inv_cell: float,
    cells_per_slot: int,
    # In:
    offsets: wp.array[wp.int32],
    # Out:
    keys: wp.array[wp.int32],
    values: wp.array[wp.int32],
):
    """One (slot * cells_per_slot + cell, face) pair per cell a face's pair box overlaps, at the
    face's offset (launch (slots, M)); sorted by key they are the grid's cell lists."""
    slot, f = wp.tid()
    d = grid_dims[slot]
    a = grid_cell(pair_lowers[slot, f], grid_origin[slot], inv_cell, d)
    b = grid_cell(pair_uppers[slot, f], grid_origin[slot], inv_cell, d)
    i = offsets[slot * pair_lowers.shape[1] + f]
    for z in range(a[2], b[2] + 1):
        for y in range(a[1], b[1] + 1):
            for x in range(a[0], b[0] + 1):
                keys[i] = grid_key(slot, cells_per_slot, d, x, y, z)
                values[i] = f
                i += 1


@wp.kernel
def find_cell_ranges(
    # In:
    keys: wp.array[wp.int32],
    count: int,
    # Out:
    cell_start: wp.array[wp.int32],
    cell_end: wp.array[wp.int32],
):
    """[cell_start, cell_end) of each (slot, cell) key in the sorted keys (launch (count,);
    empty cells keep 0, 0)."""
    i = wp.tid()
    key = keys[i]
    if i == 0:
        cell_start[key] = 0
    elif keys[i - 1] != key:
        cell_start[key] = i
        cell_end[keys[i - 1]] = i
    if i == count - 1:
        cell_end[key] = count


@wp.kernel
def gather_cell_boxes(
    # Model:
    pair_lowers: wp.array2d[wp.vec3],
    pair_uppers: wp.array2d[wp.vec3],
    cells_per_slot: int,
    # In:
    keys: wp.array[wp.int32],
    cell_faces: wp.array[wp.int32],
    # Out:
    cell_lowers: wp.array[wp.vec3],
    cell_uppers: wp.array[wp.vec3],
):
    """Each cell-list entry's face box [m] next to it (launch (refs,)): a query reads an entry's
    box in the same contiguous run as its face index instead of through it."""
    i = wp.tid()
    slot = keys[i] / cells_per_slot
    f = cell_faces[i]
    cell_lowers[i] = pair_lowers[slot, f]
    cell_uppers[i] = pair_uppers[slot, f]


@wp.func
def find_closest_grid(
    s: int, lane: int,
    frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], grid_origin: wp.array[wp.vec3],
    grid_dims: wp.array[wp.vec3i],
    inv_cell: float, cells_per_slot: int, cell_start: wp.array[wp.int32], cell_end: wp.array[wp.int32],
    cell_faces: wp.array[wp.int32], cell_lowers: wp.array[wp.vec3], cell_uppers: wp.array[wp.vec3],
    sphere_radius: wp.array[float], sphere_env: wp.array[wp.int32],
    fps: wp.float64, interpolate: int, slices: int, env_time_in: wp.array[wp.float64],
    env_playback_in: wp.array[wp.int32], sphere_pos_in: wp.array[wp.vec3], sphere_vel_in: wp.array[wp.vec3],
    dt: float, extra_speed: float, margin: float, epsilon: float, query_dist: wp.array[float],
    query_face: wp.array[wp.int32], query_w: wp.array[wp.vec3], query_n: wp.array[wp.vec3],
    query_time: wp.array[wp.float64],
):
    """Sphere s's contact query by the calling thread block over a uniform grid of its slot's
    face boxes (no tree walk: a cell's faces are one contiguous list): for each cell of the
    query box the block's threads split its list and apply the serial rule (box prune against
    the thread's closest so far); a face listed in several cells is evaluated only in the cell
    holding the low corner of its box's overlap with the query box, so each candidate is met
    once; a query box outside the slot's grid reads no cell. Then the block reduction and s's
    record, as ``find_closest_tiled``."""
    k0, k1, alpha, p, reach, slot = locate_sphere_query(s, lane, frames, sphere_radius, sphere_env, fps,
                                                        interpolate, slices, env_time_in, env_playback_in,
                                                        sphere_pos_in, sphere_vel_in, dt, extra_speed, margin,
                                                        query_time)
    ext = wp.vec3(reach + epsilon)
    qlo = p - ext
    qhi = p + ext
    o = grid_origin[slot]
    d = grid_dims[slot]
    a = grid_cell(qlo, o, inv_cell, d)
    b = grid_cell(qhi, o, inv_cell, d)
    nx = b[0] - a[0] + 1
    ny = b[1] - a[1] + 1
    ncell = nx * ny * (b[2] - a[2] + 1)
    top = o + wp.vec3(float(d[0]), float(d[1]), float(d[2])) / inv_cell
    if qhi[0] < o[0] or qhi[1] < o[1] or qhi[2] < o[2] or qlo[0] > top[0] or qlo[1] > top[1] or qlo[2] > top[2]:
        ncell = 0  # the query box misses the slot's faces altogether
    min_dist = reach
    min_face = int(-1)
    min_w = wp.vec3(0.0)
    acc_n = wp.vec3(0.0)
    for c in range(ncell):  # every thread meets every cell; the threads split its list
        cx = a[0] + c % nx
        cy = a[1] + (c / nx) % ny
        cz = a[2] + c / (nx * ny)
        cell = grid_key(slot, cells_per_slot, d, cx, cy, cz)
        for j in range(cell_start[cell] + lane, cell_end[cell], wp.block_dim()):
            flo = cell_lowers[j]
            fhi = cell_uppers[j]
            lo = wp.max(flo, qlo)
            hi = wp.min(fhi, qhi)
            if lo[0] <= hi[0] and lo[1] <= hi[1] and lo[2] <= hi[2]:
                owner = grid_cell(lo, o, inv_cell, d)
                if owner[0] == cx and owner[1] == cy and owner[2] == cz:
                    if box_distance(p, flo, fhi) < min_dist + epsilon:
                        f = cell_faces[j]
                        ta, tb, tg = interpolated_triangle(frames, indices, f, k0, k1, alpha)
                        dist, w, wn = face_candidate(p, ta, tb, tg, epsilon)
                        min_dist, min_face, min_w, acc_n = keep_closest(dist, f, w, wn, epsilon, min_dist, min_face,
                                                                        min_w, acc_n)
    write_block_query(s, lane, reach, min_dist, min_face, min_w, acc_n, epsilon, query_dist, query_face, query_w,
                      query_n)


#: the grid query's register cap per thread on CUDA (``__maxnreg__``): uncapped the compiler
#: gives it 96, which holds an SM to 21 of its 64 warps; this latency-bound walk runs faster with
#: more warps in flight despite a few spills (docs/envs.md, H100).
GRID_QUERY_MAX_REGISTERS = 72


@wp.kernel(cuda_max_registers=GRID_QUERY_MAX_REGISTERS)
def collide_env_sphere_grid(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    grid_origin: wp.array[wp.vec3],
    grid_dims: wp.array[wp.vec3i],
    inv_cell: float,
    cells_per_slot: int,
    cell_start: wp.array[wp.int32],
    cell_end: wp.array[wp.int32],
    cell_faces: wp.array[wp.int32],
    cell_lowers: wp.array[wp.vec3],
    cell_uppers: wp.array[wp.vec3],
    sphere_radius: wp.array[float],
    sphere_env: wp.array[wp.int32],
    fps: wp.float64,
    interpolate: int,
    slices: int,
    # State in:
    env_time_in: wp.array[wp.float64],
    env_playback_in: wp.array[wp.int32],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    dt: float,
    extra_speed: float,
    margin: float,
    epsilon: float,
    # Out:
    query_dist: wp.array[float],
    query_face: wp.array[wp.int32],
    query_w: wp.array[wp.vec3],
    query_n: wp.array[wp.vec3],
    query_time: wp.array[wp.float64],
):
    """The contact query of every sphere by one thread block each over its slot's face grid
    (``wp.launch_tiled``, dim (E * S,)): ``find_closest_grid``; the records are resolved by
    ``resolve_and_integrate_env_spheres``."""
    s, lane = wp.tid()
    find_closest_grid(s, lane, frames, indices, grid_origin, grid_dims, inv_cell,
                      cells_per_slot, cell_start, cell_end, cell_faces, cell_lowers, cell_uppers, sphere_radius,
                      sphere_env, fps, interpolate,
                      slices, env_time_in, env_playback_in, sphere_pos_in, sphere_vel_in, dt, extra_speed, margin,
                      epsilon, query_dist, query_face, query_w, query_n, query_time)


@wp.func
def advance_env_clock(e: int, env_rate_in: wp.array[float], dt: wp.float64, env_time_out: wp.array[wp.float64]):
    """env_time_out[e] += env_rate_in[e] * dt [s] (float64, as the single world's clock): the
    one clock rule of ``advance_env_clocks`` and ``resolve_and_integrate_env_spheres``."""
    env_time_out[e] = env_time_out[e] + wp.float64(env_rate_in[e]) * dt


@wp.kernel
def resolve_and_integrate_env_spheres(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    inv_mass: wp.array[float],
    sphere_env: wp.array[wp.int32],
    gravity: wp.vec3,
    restitution: float,
    friction: float,
    rest_speed: float,
    ground: int,
    ground_height: float,
    fps: wp.float64,
    interpolate: int,
    inertia: float,
    # State in:
    env_rate_in: wp.array[float],
    env_playback_in: wp.array[wp.int32],
    # In:
    query_dist: wp.array[float],
    query_face: wp.array[wp.int32],
    query_w: wp.array[wp.vec3],
    query_n: wp.array[wp.vec3],
    query_time: wp.array[wp.float64],
    dt: float,
    extra_speed: float,
    margin: float,
    epsilon: float,
    clock_dt: wp.float64,
    # State out:
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
    sphere_spin_out: wp.array[wp.vec3],
    env_time_out: wp.array[wp.float64],
    # Out:
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
    contact_memory: wp.array[pinch_memory],
):
    """The contact of each sphere from its query record (``collide_env_sphere_tiled``,
    ``collide_env_sphere_grid`` or the hybrid pair ``collide_env_spheres_bounded`` /
    ``collide_env_heavy_spheres_tiled``) at the env time the query read (``query_time``), then
    the continuous response, as ``collide_and_integrate_env_spheres``; and each env's clock
    advanced by its first sphere's thread (``env_time_out[e] += env_rate_in[e] * clock_dt`` [s],
    float64, as ``advance_env_clocks``: no thread of this launch reads a clock). One thread per
    sphere; (E * S,) arrays sorted by env, every env with at least one sphere."""
    s = wp.tid()
    e = sphere_env[s]
    if s == 0 or sphere_env[s - 1] != e:
        advance_env_clock(e, env_rate_in, clock_dt, env_time_out)
    k0, k1, alpha = blend_pair(query_time[s], fps, frames.shape[0], env_playback_in[e], interpolate)
    p = sphere_pos_out[s]
    v = sphere_vel_out[s]
    r = sphere_radius[s]
    reach = contact_reach(r, v, extra_speed, dt, margin)
    write_swept_contact(s, p, r, reach, query_dist[s], query_face[s], query_w[s], query_n[s], frames, indices, k0, k1,
                        alpha, fps * wp.float64(env_rate_in[e]), contact_face, contact_point, contact_normal,
                        contact_depth, contact_velocity)
    advance_and_store_sphere(s, p, v, inv_mass[s], r, gravity, dt, restitution, friction, rest_speed, ground,
                             ground_height, inertia, contact_face, contact_normal, contact_depth, contact_velocity,
                             contact_memory, sphere_pos_out, sphere_vel_out, sphere_spin_out)


@wp.kernel
def advance_env_clocks(
    # State in:
    env_rate_in: wp.array[float],
    # In:
    dt: wp.float64,
    # State out:
    env_time_out: wp.array[wp.float64],
):
    """Every env's clock advanced one sub-step (``advance_env_clock``); one thread per env."""
    advance_env_clock(wp.tid(), env_rate_in, dt, env_time_out)


@wp.kernel
def reset_env_spheres(
    # Model:
    sphere_env: wp.array[wp.int32],
    # In:
    env_mask: wp.array[wp.int32],
    new_pos: wp.array[wp.vec3],
    new_vel: wp.array[wp.vec3],
    new_spin: wp.array[wp.vec3],
    # State out:
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
    sphere_spin_out: wp.array[wp.vec3],
    # Out:
    contact_memory: wp.array[pinch_memory],
):
    """Spheres of the envs with env_mask[e] != 0 from new_pos / new_vel / new_spin ((E * S,) [m],
    [m/s], [rad/s]), their pinch memory cleared (``kernels.integrate.pinch_memory``: a pinch before the reset
    would squeeze the first sub-step after it); the other envs' spheres are left untouched. One
    thread per sphere."""
    s = wp.tid()
    if env_mask[sphere_env[s]] == 0:
        return
    sphere_pos_out[s] = new_pos[s]
    sphere_vel_out[s] = new_vel[s]
    sphere_spin_out[s] = new_spin[s]
    contact_memory[s] = pinch_memory()


@wp.kernel
def reset_env_clocks(
    # In:
    env_mask: wp.array[wp.int32],
    new_time: wp.array[wp.float64],
    new_rate: wp.array[float],
    new_playback: wp.array[wp.int32],
    # State out:
    env_time_out: wp.array[wp.float64],
    env_rate_out: wp.array[float],
    env_playback_out: wp.array[wp.int32],
):
    """Clocks of the envs with env_mask[e] != 0 (time [s], rate, playback code); (E,) arrays."""
    e = wp.tid()
    if env_mask[e] == 0:
        return
    env_time_out[e] = new_time[e]
    env_rate_out[e] = new_rate[e]
    env_playback_out[e] = new_playback[e]
