"""Stage 3 (cells path): contact against the interpolated surface through a uniform grid of face
clusters rebuilt every step (issue 14: many spheres on a large, fast-moving mesh).

The faces are cut once into clusters of at most ``cluster_size`` faces (the leaves of a k-d tree
over their centroids: compact patches; ``dynmesh_warp.face_cells``), each cluster into sub-boxes
of ``sub_size`` faces, and the vertices renumbered in the order the clusters use them. Every
step: the vertices blended at the current time in that order (``blend_cluster_points``: a
cluster's corners lie together in memory), each sub-box's box (``compute_sub_bounds``), each
cluster's box and the cells it overlaps counted (``count_cluster_cells``), a scan, and each
cluster listed in those cells (``scatter_cluster_cells``: contiguous cell lists), then one thread
per sphere walks the cells of its query box, the clusters, sub-boxes and faces within its bound
(``collide_sphere_cells``). Nothing of the swept boxes' frame-interval size enters: the boxes
are the triangles' at the step's own time, so a resting sphere meets a few clusters however
fast the surface moves. No BVH, no tree walk, no per-step vertex buffer.

The closest-feature rule is the swept search's (``keep_closest``: the pseudo-normal over faces
tied within epsilon, as ``wp.mesh_query_point_sign_normal``), so the contacts equal the refit
path's.
"""

import warp as wp

from .collide import contact_reach
from .frames import blend_pair
from .swept import box_distance, face_candidate, keep_closest, seed_closest, write_swept_contact

# CUDA fast math, as the other contact kernels (docs/physics.md, "Fast math")
wp.set_module_options({"fast_math": True})

#: an empty box's corner (a cluster of padding only never occurs; kept safe)
EMPTY_BOX = wp.constant(1.0e30)
#: the nearest-first order's buffer of sub-boxes a sphere defers (more are evaluated at once)
DEFER_SLOTS = 16
vec_defer_dist = wp.types.vector(length=DEFER_SLOTS, dtype=wp.float32)
vec_defer_index = wp.types.vector(length=DEFER_SLOTS, dtype=wp.int32)


@wp.func
def cell_coord(x: wp.vec3, grid_origin: wp.vec3, grid_dims: wp.vec3i, inv_cell: float) -> wp.vec3i:
    """The grid cell holding x, clamped to the grid (the float is clamped before the cast)."""
    q = (x - grid_origin) * inv_cell
    return wp.vec3i(
        int(wp.clamp(wp.floor(q[0]), 0.0, float(grid_dims[0] - 1))),
        int(wp.clamp(wp.floor(q[1]), 0.0, float(grid_dims[1] - 1))),
        int(wp.clamp(wp.floor(q[2]), 0.0, float(grid_dims[2] - 1))),
    )


@wp.func
def cell_index(x: int, y: int, z: int, grid_dims: wp.vec3i) -> int:
    """Linear index of cell (x, y, z), x fastest."""
    return (z * grid_dims[1] + y) * grid_dims[0] + x


@wp.func
def same_cell(a: wp.vec3i, b: wp.vec3i) -> bool:
    return a[0] == b[0] and a[1] == b[1] and a[2] == b[2]


@wp.kernel
def blend_cluster_points(
    # Model:
    frames: wp.array2d[wp.vec3],
    vertex_order: wp.array[wp.int32],
    # State in:
    sim_time_in: wp.array[wp.float64],
    # In:
    fps: wp.float64,
    mode: int,
    interpolate: int,
    # Out:
    cluster_points: wp.array[wp.vec3],
):
    """The vertices at the current blend in cluster order: cluster_points[j] is vertex
    vertex_order[j] (N,) of frames (T, N) [m], blended as ``interpolated_triangle`` blends it
    (the same values)."""
    j = wp.tid()
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    v = vertex_order[j]
    cluster_points[j] = wp.lerp(frames[k0, v], frames[k1, v], alpha)


@wp.func
def slot_triangle(cluster_points: wp.array[wp.vec3], cluster_indices: wp.array[wp.int32], slot: int):
    """The current corners of a cluster slot's face (``cluster_points`` in cluster order)."""
    return (cluster_points[cluster_indices[3 * slot + 0]], cluster_points[cluster_indices[3 * slot + 1]],
            cluster_points[cluster_indices[3 * slot + 2]])


@wp.kernel
def compute_sub_bounds(
    # Model:
    cluster_faces: wp.array[wp.int32],
    cluster_indices: wp.array[wp.int32],
    # In:
    cluster_points: wp.array[wp.vec3],
    sub_size: int,
    # Out:
    sub_lower: wp.array[wp.vec3],
    sub_upper: wp.array[wp.vec3],
):
    """Box of each sub-box's faces at the current blend (one thread a sub-box: its ``sub_size``
    slots). A sub-box of padding only is empty (lower > upper: never near).

    cluster_faces (C * K,) face indices, each cluster's faces first, then -1; cluster_indices
    (3 C K,) corners into cluster_points (N,) [m]; sub_lower / sub_upper (C K / sub_size,) [m].
    """
    q = wp.tid()
    lo = wp.vec3(EMPTY_BOX)
    hi = wp.vec3(-EMPTY_BOX)
    for k in range(sub_size):
        slot = q * sub_size + k
        if cluster_faces[slot] >= 0:
            a, b, e = slot_triangle(cluster_points, cluster_indices, slot)
            lo = wp.min(lo, wp.min(a, wp.min(b, e)))
            hi = wp.max(hi, wp.max(a, wp.max(b, e)))
    sub_lower[q] = lo
    sub_upper[q] = hi


@wp.kernel
def count_cluster_cells(
    # In:
    sub_lower: wp.array[wp.vec3],
    sub_upper: wp.array[wp.vec3],
    subs_per_cluster: int,
    grid_origin: wp.vec3,
    grid_dims: wp.vec3i,
    inv_cell: float,
    # Out:
    cluster_lower: wp.array[wp.vec3],
    cluster_upper: wp.array[wp.vec3],
    cell_count: wp.array[wp.int32],
):
    """Each cluster's box (its sub-boxes' union; cluster_lower / cluster_upper (C,) [m]), and one
    added to every cell it overlaps (cell_count (G,) zeroed before)."""
    c = wp.tid()
    lo = wp.vec3(EMPTY_BOX)
    hi = wp.vec3(-EMPTY_BOX)
    for j in range(subs_per_cluster):
        lo = wp.min(lo, sub_lower[c * subs_per_cluster + j])
        hi = wp.max(hi, sub_upper[c * subs_per_cluster + j])
    cluster_lower[c] = lo
    cluster_upper[c] = hi
    a = cell_coord(lo, grid_origin, grid_dims, inv_cell)
    b = cell_coord(hi, grid_origin, grid_dims, inv_cell)
    for z in range(a[2], b[2] + 1):
        for y in range(a[1], b[1] + 1):
            for x in range(a[0], b[0] + 1):
                wp.atomic_add(cell_count, cell_index(x, y, z, grid_dims), 1)


@wp.kernel
def scatter_cluster_cells(
    # In:
    cluster_lower: wp.array[wp.vec3],
    cluster_upper: wp.array[wp.vec3],
    grid_origin: wp.vec3,
    grid_dims: wp.vec3i,
    inv_cell: float,
    cell_start: wp.array[wp.int32],
    # Out:
    cell_fill: wp.array[wp.int32],
    cell_clusters: wp.array[wp.int32],
):
    """Each cluster writes its index into the list of every cell its box overlaps: cell g's list
    is cell_clusters[cell_start[g] : cell_start[g] + cell_count[g]] (cell_start the exclusive scan
    of count_cluster_cells' counts; cell_fill (G,) zeroed before). The order within a list is
    the atomics' (any: the search's result does not depend on it beyond exact ties)."""
    c = wp.tid()
    lo = cell_coord(cluster_lower[c], grid_origin, grid_dims, inv_cell)
    hi = cell_coord(cluster_upper[c], grid_origin, grid_dims, inv_cell)
    for z in range(lo[2], hi[2] + 1):
        for y in range(lo[1], hi[1] + 1):
            for x in range(lo[0], hi[0] + 1):
                g = cell_index(x, y, z, grid_dims)
                slot = cell_start[g] + wp.atomic_add(cell_fill, g, 1)
                if slot < cell_clusters.shape[0]:  # the capacity is a static bound (face_cells)
                    cell_clusters[slot] = c


@wp.func
def closest_in_sub_box(
    frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], cluster_faces: wp.array[wp.int32],
    cluster_indices: wp.array[wp.int32], cluster_points: wp.array[wp.vec3], sub_size: int, q: int,
    p: wp.vec3, epsilon: float, seed_face: int,
    min_dist: float, min_face: int, min_w: wp.vec3, acc_n: wp.vec3,
):
    """``keep_closest`` over the faces of sub-box q (slots q * sub_size ...; the padding ends it)."""
    for k in range(sub_size):
        slot = q * sub_size + k
        f = cluster_faces[slot]
        if f < 0:  # the cluster's padding: its faces come first
            break
        if f != seed_face:
            a, b, e = slot_triangle(cluster_points, cluster_indices, slot)
            dist, w, wn = face_candidate(p, a, b, e, epsilon)
            min_dist, min_face, min_w, acc_n = keep_closest(dist, f, w, wn, epsilon, min_dist, min_face, min_w, acc_n)
    return min_dist, min_face, min_w, acc_n


@wp.func
def closest_in_cells(
    frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], cluster_faces: wp.array[wp.int32],
    cluster_indices: wp.array[wp.int32], cluster_points: wp.array[wp.vec3], cluster_size: int, sub_size: int,
    sub_lower: wp.array[wp.vec3], sub_upper: wp.array[wp.vec3],
    cluster_lower: wp.array[wp.vec3], cluster_upper: wp.array[wp.vec3],
    cell_count: wp.array[wp.int32], cell_start: wp.array[wp.int32], cell_clusters: wp.array[wp.int32],
    grid_origin: wp.vec3, grid_dims: wp.vec3i, inv_cell: float,
    k0: int, k1: int, alpha: float, p: wp.vec3, reach: float, epsilon: float, seed_face: int, nearest_first: int,
):
    """Closest feature of the interpolated surface within ``reach`` of p, over the clusters listed
    in the cells of p's query box (the seed's distance, or ``reach``, + epsilon). A cluster listed
    in several of them is evaluated in one only; the order of the cells changes which clusters
    are skipped, never the result. A cell, cluster or sub-box whose box is farther than the
    closest so far + epsilon is skipped unevaluated, so the result is that of evaluating every
    face within reach (as ``closest_on_swept_bvh``). ``nearest_first`` 1: the sub-boxes that
    pass are deferred (up to DEFER_SLOTS, any more evaluated at once) and evaluated nearest
    first after the walk, so the first sets a tight bound for the rest."""
    min_dist, min_face, min_w, acc_n = seed_closest(frames, indices, k0, k1, alpha, p, reach, epsilon, seed_face)
    ext = wp.vec3(min_dist + epsilon)
    qlo = (p - ext - grid_origin) * inv_cell
    qhi = (p + ext - grid_origin) * inv_cell
    inside = int(1)
    for i in range(3):
        if qhi[i] < 0.0 or qlo[i] >= float(grid_dims[i]):
            inside = 0
    nsub = cluster_size / sub_size
    defer_dist = vec_defer_dist()
    defer_index = vec_defer_index()
    deferred = int(0)
    if inside == 1:
        lo = cell_coord(p - ext, grid_origin, grid_dims, inv_cell)
        hi = cell_coord(p + ext, grid_origin, grid_dims, inv_cell)
        home = cell_coord(p, grid_origin, grid_dims, inv_cell)
        nx = hi[0] - lo[0] + 1
        ny = hi[1] - lo[1] + 1
        edge = 1.0 / inv_cell
        slack = wp.vec3(1.0e-4 * edge)
        # the cell holding p first (its clusters are the likeliest nearest: the bound falls
        # early), then the rest of the query box's cells, z, y, x
        for it in range(-1, (hi[2] - lo[2] + 1) * ny * nx):
            cell = home
            if it >= 0:
                cell = wp.vec3i(lo[0] + it % nx, lo[1] + (it / nx) % ny, lo[2] + it / (nx * ny))
            # a cell farther than the closest so far (+ epsilon) holds no cluster evaluated in it
            # that could be nearer: the cell a cluster is evaluated in is, axis by axis, at
            # least as near p's as the cell holding the cluster's point nearest p (the cell's box
            # grown by 1e-4 of its edge (slack): the float rounding of the cell a point is counted in)
            cell_lo = grid_origin + wp.vec3(float(cell[0]), float(cell[1]), float(cell[2])) * edge
            near = box_distance(p, cell_lo - slack, cell_lo + wp.vec3(edge) + slack) < min_dist + epsilon
            if it < 0 or (near and not same_cell(cell, home)):
                g = cell_index(cell[0], cell[1], cell[2], grid_dims)
                start = cell_start[g]
                for j in range(start, start + cell_count[g]):
                    c = cell_clusters[j]
                    clo = cluster_lower[c]
                    chi = cluster_upper[c]
                    if box_distance(p, clo, chi) < min_dist + epsilon:
                        # a cluster is evaluated in one cell only: of its cells within the query
                        # box, the nearest to p's (whichever order the cells are met in)
                        own = wp.max(cell_coord(clo, grid_origin, grid_dims, inv_cell), lo)
                        top = wp.min(cell_coord(chi, grid_origin, grid_dims, inv_cell), hi)
                        if same_cell(cell, wp.min(wp.max(home, own), top)):
                            for sb in range(nsub):
                                q = c * nsub + sb
                                sd = box_distance(p, sub_lower[q], sub_upper[q])
                                if sd < min_dist + epsilon:
                                    if nearest_first != 0 and deferred < DEFER_SLOTS:
                                        defer_dist[deferred] = sd
                                        defer_index[deferred] = q
                                        deferred += 1
                                    else:
                                        min_dist, min_face, min_w, acc_n = closest_in_sub_box(
                                            frames, indices, cluster_faces, cluster_indices, cluster_points, sub_size,
                                            q, p, epsilon, seed_face, min_dist, min_face, min_w, acc_n)
        # the deferred sub-boxes nearest first: the first sets a tight bound that prunes the rest
        while deferred > 0:
            best = int(0)
            for j in range(1, deferred):
                if defer_dist[j] < defer_dist[best]:
                    best = j
            if defer_dist[best] >= min_dist + epsilon:
                break
            q = defer_index[best]
            deferred -= 1
            defer_dist[best] = defer_dist[deferred]
            defer_index[best] = defer_index[deferred]
            min_dist, min_face, min_w, acc_n = closest_in_sub_box(
                frames, indices, cluster_faces, cluster_indices, cluster_points, sub_size, q, p, epsilon, seed_face,
                min_dist, min_face, min_w, acc_n)
    return min_dist, min_face, min_w, acc_n


@wp.kernel
def collide_sphere_cells(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    cluster_faces: wp.array[wp.int32],
    cluster_indices: wp.array[wp.int32],
    # State in:
    sim_time_in: wp.array[wp.float64],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    cluster_points: wp.array[wp.vec3],
    sub_lower: wp.array[wp.vec3],
    sub_upper: wp.array[wp.vec3],
    cluster_lower: wp.array[wp.vec3],
    cluster_upper: wp.array[wp.vec3],
    cell_count: wp.array[wp.int32],
    cell_start: wp.array[wp.int32],
    cell_clusters: wp.array[wp.int32],
    grid_origin: wp.vec3,
    grid_dims: wp.vec3i,
    inv_cell: float,
    cluster_size: int,
    sub_size: int,
    nearest_first: int,
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
    """Contact of each sphere with the surface interpolated at sim_time_in (the outputs of
    ``collide_sphere_mesh``), one thread per sphere walking its query box's grid cells. The
    sphere's previous contact face (``contact_face``, read before it is written) is evaluated
    first and bounds the query box; ``epsilon`` [m] is the pseudo-normal's tie distance."""
    s = wp.tid()
    p = sphere_pos_in[s]
    r = sphere_radius[s]
    reach = contact_reach(r, sphere_vel_in[s], extra_speed, dt, margin)
    k0, k1, alpha = blend_pair(sim_time_in[0], fps, frames.shape[0], mode, interpolate)
    min_dist, min_face, min_w, acc_n = closest_in_cells(
        frames, indices, cluster_faces, cluster_indices, cluster_points, cluster_size, sub_size, sub_lower, sub_upper,
        cluster_lower, cluster_upper, cell_count, cell_start, cell_clusters, grid_origin, grid_dims, inv_cell,
        k0, k1, alpha, p, reach, epsilon, contact_face[s], nearest_first)
    write_swept_contact(s, p, r, reach, min_dist, min_face, min_w, acc_n, frames, indices, k0, k1, alpha, fps,
                        contact_face, contact_point, contact_normal, contact_depth, contact_velocity)
