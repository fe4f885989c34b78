"""Stage 3 (swept path, ``sphere_grid`` search): the contacts found face-parallel over a grid of
the spheres rebuilt every step, for many spheres on large meshes (issue 14).

Each step:

1. ``compute_sphere_bounds`` (one thread per sphere): the sphere's search radius, ``bound``
   [m], is its reach (r + margin + motion, ``contact_reach``) or, when less, the distance to
   its previous contact face evaluated at the step's time (the closest face is no farther). A
   sphere whose ball of radius bound + epsilon misses the box of every frame of the surface has
   no contact and is left out. The others get a level: 0 (cells of ``cell_size[0]``) where the
   ball's box spans at most CELL_RANGE cells an axis, else 1 (the coarser ``cell_size[1]``)
   where it does there, else 2: a list every face tests. ``count_sphere_cells`` (one thread
   per (sphere, cell)) counts each level-0/1 sphere in every cell its ball's box overlaps.
   Cells are hashed into ``num_buckets`` buckets (a collision only adds candidates that are
   then skipped).
2. An exclusive scan of the buckets' counts (``wp.utils.array_scan``).
3. ``scatter_sphere_cells`` (one thread per (sphere, cell)): each sphere written into its cells'
   bucket ranges; the counts are counted back down to zero, ready for the next step.
4. ``find_closest_in_sphere_cells`` (one thread per face): the triangle at the step's time, its
   box, the cells the box overlaps at each level; each sphere listed there is tested once (in
   the first cell its range and the face's share), and where the box lies within the sphere's
   bound + epsilon the triangle is evaluated and a candidate closer than the reach goes into the
   sphere's atomic minimum of ``face_key`` (as the ``faces`` search).
5. ``resolve_closest_per_sphere_serial`` (kernels/swept.py): the contact from each sphere's key,
   one thread a sphere.

Exact: every face within a sphere's bound is tested (its box overlaps the sphere's ball, so
they share a cell), and the closest face lies within the bound. No BVH, no refit; the work
follows the faces and the (sphere, cell) entries near them, not a walk a sphere.
"""

import warp as wp

from .collide import contact_reach
from .frames import blend_pair
from .swept import box_distance, face_candidate, face_key, interpolated_triangle, seed_closest

wp.set_module_options({"fast_math": True})

#: cells an axis a sphere's ball may span at a level before it moves to the next (coarser) one
CELL_RANGE = wp.constant(3)
#: sphere_level of a sphere whose ball misses the surface's box (no entries, no contact)
LEVEL_NONE = wp.constant(-1)
#: sphere_level of a sphere too wide for both levels: every face tests it
LEVEL_EVERY_FACE = wp.constant(2)


@wp.func
def level_cell_size(cell_size: wp.vec2, level: int) -> float:
    """``cell_size``: the cell edge of level 0 and of level 1 [m]."""
    return cell_size[level]


@wp.func
def cell_of(x: wp.vec3, inv_h: float) -> wp.vec3i:
    return wp.vec3i(int(wp.floor(x[0] * inv_h)), int(wp.floor(x[1] * inv_h)), int(wp.floor(x[2] * inv_h)))


@wp.func
def bucket_of(c: wp.vec3i, level: int, num_buckets: int) -> int:
    """The hash bucket of cell c of a level (Teschner et al. 2003's primes)."""
    h = (wp.uint32(c[0]) * wp.uint32(73856093)) ^ (wp.uint32(c[1]) * wp.uint32(19349663)) ^ (
        wp.uint32(c[2]) * wp.uint32(83492791)) ^ (wp.uint32(level) * wp.uint32(1640531527))
    return int(h % wp.uint32(num_buckets))


@wp.func
def sphere_cells(p: wp.vec3, bound: float, epsilon: float, cell_size: wp.vec2, level: int):
    """The first and last cell (at ``level``) of the box of the ball (p, bound + epsilon)."""
    inv_h = 1.0 / level_cell_size(cell_size, level)
    q = wp.vec3(bound + epsilon)
    return cell_of(p - q, inv_h), cell_of(p + q, inv_h)


@wp.func
def fits_level(lo: wp.vec3i, hi: wp.vec3i) -> bool:
    return hi[0] - lo[0] < CELL_RANGE and hi[1] - lo[1] < CELL_RANGE and hi[2] - lo[2] < CELL_RANGE


@wp.kernel
def compute_sphere_bounds(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    # State in:
    sim_time_in: wp.array[wp.float64],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    contact_face: wp.array[wp.int32],
    surface_lower: wp.vec3,
    surface_upper: wp.vec3,
    fps: wp.float64,
    mode: int,
    interpolate: int,
    epsilon: float,
    dt: float,
    extra_speed: float,
    margin: float,
    cell_size: wp.vec2,
    # Out:
    sphere_reach: wp.array[float],
    sphere_bound: wp.array[float],
    sphere_level: wp.array[wp.int32],
    level_count: wp.array[wp.int32],
    every_face_spheres: wp.array[wp.int32],
):
    """Each sphere's reach [m], search radius ``sphere_bound`` [m] (the reach, or the distance
    to its previous contact face ``contact_face`` at the step's time when less) and grid level
    (LEVEL_NONE where the ball misses ``surface_lower``/``upper``, the box of every frame of the
    surface [m]); ``level_count`` (3,): [0] and [1] set to 1 where a sphere has level 0 / 1, [2]
    the count of the spheres too wide for both levels, appended to ``every_face_spheres`` (all
    zero before). ``cell_size``: the cell edge of levels 0 and 1 [m]."""
    s = wp.tid()
    p = sphere_pos_in[s]
    reach = contact_reach(sphere_radius[s], sphere_vel_in[s], extra_speed, dt, margin)
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    # the reach, or the seed face's distance when less (an index out of range is no seed)
    bound, seed_face, seed_w, seed_n = seed_closest(frames, indices, k0, k1, alpha, p, reach, epsilon, contact_face[s])
    sphere_reach[s] = reach
    sphere_bound[s] = bound
    level = int(LEVEL_NONE)
    if box_distance(p, surface_lower, surface_upper) <= bound + epsilon:
        level = int(LEVEL_EVERY_FACE)
        for trial in range(2):
            # (a ball over 1.5 cells wide cannot fit: not even its cells are computed, so a huge
            # bound never overflows a cell index)
            if level == LEVEL_EVERY_FACE and bound + epsilon < 1.5 * level_cell_size(cell_size, trial):
                lo, hi = sphere_cells(p, bound, epsilon, cell_size, trial)
                if fits_level(lo, hi):
                    level = trial
        if level == LEVEL_EVERY_FACE:
            every_face_spheres[wp.atomic_add(level_count, level, 1)] = s
        elif level_count[level] == 0:
            # levels 0 and 1 are flags (a count would be an atomic on one address from every sphere)
            level_count[level] = 1
    sphere_level[s] = level


@wp.func
def sphere_cell(p: wp.vec3, bound: float, level: int, epsilon: float, cell_size: wp.vec2, c: int):
    """Cell c (0..26, x-major) of the sphere's range at its level, and whether the range has it."""
    lo, hi = sphere_cells(p, bound, epsilon, cell_size, level)
    x = lo[0] + c / 9
    y = lo[1] + (c / 3) % 3
    z = lo[2] + c % 3
    return wp.vec3i(x, y, z), x <= hi[0] and y <= hi[1] and z <= hi[2]


@wp.kernel
def count_sphere_cells(
    # State in:
    sphere_pos_in: wp.array[wp.vec3],
    # In:
    sphere_bound: wp.array[float],
    sphere_level: wp.array[wp.int32],
    epsilon: float,
    cell_size: wp.vec2,
    num_buckets: int,
    # Out:
    bucket_count: wp.array[wp.int32],
):
    """One thread per (sphere, cell of its range) (launch (S, 27): a range of level 0 or 1 spans
    at most 3 cells an axis): the cell's bucket counted (``bucket_count`` accumulated, all zero
    before). One atomic a thread, none in series."""
    s, c = wp.tid()
    level = sphere_level[s]
    if level == 0 or level == 1:
        cell, inside = sphere_cell(sphere_pos_in[s], sphere_bound[s], level, epsilon, cell_size, c)
        if inside:
            wp.atomic_add(bucket_count, bucket_of(cell, level, num_buckets), 1)


@wp.kernel
def scatter_sphere_cells(
    # State in:
    sphere_pos_in: wp.array[wp.vec3],
    # In:
    sphere_bound: wp.array[float],
    sphere_level: wp.array[wp.int32],
    epsilon: float,
    cell_size: wp.vec2,
    num_buckets: int,
    bucket_start: wp.array[wp.int32],
    # Out:
    bucket_count: wp.array[wp.int32],
    cell_spheres: wp.array[wp.int32],
    cell_sphere_balls: wp.array[wp.vec4],
):
    """One thread per (sphere, cell of its range) (launch (S, 27)): the sphere written into the
    cell's bucket range (``bucket_start``: the exclusive scan of the counts): its index in
    ``cell_spheres`` and its centre and bound [m] in ``cell_sphere_balls`` (read by the face
    pass without a gather); ``bucket_count`` is counted down to zero."""
    s, c = wp.tid()
    level = sphere_level[s]
    if level == 0 or level == 1:
        p = sphere_pos_in[s]
        bound = sphere_bound[s]
        cell, inside = sphere_cell(p, bound, level, epsilon, cell_size, c)
        if inside:
            bk = bucket_of(cell, level, num_buckets)
            slot = bucket_start[bk] + wp.atomic_sub(bucket_count, bk, 1) - 1
            cell_spheres[slot] = s
            cell_sphere_balls[slot] = wp.vec4(p[0], p[1], p[2], bound)


@wp.func
def test_sphere(
    s: int, p: wp.vec3, bound: float, f: int, a: wp.vec3, b: wp.vec3, e: wp.vec3, lo: wp.vec3, hi: wp.vec3,
    epsilon: float, sphere_reach: wp.array[float], best_key: wp.array[wp.int64],
):
    if box_distance(p, lo, hi) < bound + epsilon:
        dist, w, wn = face_candidate(p, a, b, e, epsilon)
        reach = sphere_reach[s]
        if dist < reach:
            wp.atomic_min(best_key, s, face_key(dist, reach, f))


@wp.kernel
def find_closest_in_sphere_cells(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    # State in:
    sim_time_in: wp.array[wp.float64],
    sphere_pos_in: wp.array[wp.vec3],
    # In:
    fps: wp.float64,
    mode: int,
    interpolate: int,
    epsilon: float,
    cell_size: wp.vec2,
    num_buckets: int,
    sphere_reach: wp.array[float],
    sphere_bound: wp.array[float],
    bucket_start: wp.array[wp.int32],
    cell_spheres: wp.array[wp.int32],
    cell_sphere_balls: wp.array[wp.vec4],
    level_count: wp.array[wp.int32],
    every_face_spheres: wp.array[wp.int32],
    # Out:
    best_key: wp.array[wp.int64],
):
    """One thread per face: the triangle at the step's time tests the spheres listed in the
    cells its box overlaps at each level that has spheres (each once: in the first cell shared
    by its range and the face's; an entry of another cell in the same bucket is skipped, one of
    another level at most tested again) and the spheres of ``every_face_spheres``; a candidate
    within the sphere's bound and closer than its reach puts its ``face_key`` into the sphere's
    atomic minimum ``best_key`` (NO_KEY before the pass)."""
    f = wp.tid()
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    a, b, e = interpolated_triangle(frames, indices, f, k0, k1, alpha)
    lo = wp.min(wp.min(a, b), e)
    hi = wp.max(wp.max(a, b), e)
    for level in range(2):
        if level_count[level] > 0:
            inv_h = 1.0 / level_cell_size(cell_size, level)
            c_lo = cell_of(lo, inv_h)
            c_hi = cell_of(hi, inv_h)
            for x in range(c_lo[0], c_hi[0] + 1):
                for y in range(c_lo[1], c_hi[1] + 1):
                    for z in range(c_lo[2], c_hi[2] + 1):
                        bk = bucket_of(wp.vec3i(x, y, z), level, num_buckets)
                        for i in range(bucket_start[bk], bucket_start[bk + 1]):
                            ball = cell_sphere_balls[i]
                            p = wp.vec3(ball[0], ball[1], ball[2])
                            s_lo, s_hi = sphere_cells(p, ball[3], epsilon, cell_size, level)
                            # the first cell the two ranges share
                            if (wp.max(s_lo[0], c_lo[0]) == x and wp.max(s_lo[1], c_lo[1]) == y
                                    and wp.max(s_lo[2], c_lo[2]) == z and x <= s_hi[0] and y <= s_hi[1]
                                    and z <= s_hi[2]):
                                test_sphere(cell_spheres[i], p, ball[3], f, a, b, e, lo, hi, epsilon, sphere_reach,
                                            best_key)
    for j in range(level_count[2]):
        s = every_face_spheres[j]
        test_sphere(s, sphere_pos_in[s], sphere_bound[s], f, a, b, e, lo, hi, epsilon, sphere_reach, best_key)
