"""Stage 0 (preprocessing): topology conversion, varying-topology frames -> one fixed template.

Per-vertex work of :mod:`dynmesh_warp.convert`. The template side (positions, CSR vertex
adjacency, Laplacian coordinates) has the template's size and stays allocated for the whole
sequence; the input side is a ``wp.Mesh`` built per frame (its topology varies). Closest-point
queries reuse :func:`kernels.geometry.project_points_to_mesh` / ``closest_point_on_triangle``.

Adjacency is CSR: the neighbours of vertex ``i`` are ``neighbors[offsets[i]:offsets[i+1]]``.
All positions and displacements are in scene units (metres by convention).
"""

import warp as wp


@wp.kernel
def evaluate_barycentric_points(
    # In:
    points: wp.array[wp.vec3],
    indices: wp.array[wp.int32],
    face: wp.array[wp.int32],
    bary: wp.array[wp.vec3],
    fallback: wp.array[wp.vec3],
    # Out:
    out: wp.array[wp.vec3],
):
    """Position of each query on its face: w0 p[i0] + w1 p[i1] + w2 p[i2].

    points (N,) [m] mesh vertices; indices (3M,) flat triangles; face (Q,) face index or -1;
    bary (Q,) weights of the face's vertices; fallback (Q,) [m] used where face < 0;
    out (Q,) [m].
    """
    i = wp.tid()
    f = face[i]
    if f < 0:
        out[i] = fallback[i]
        return
    w = bary[i]
    out[i] = (
        w[0] * points[indices[3 * f + 0]]
        + w[1] * points[indices[3 * f + 1]]
        + w[2] * points[indices[3 * f + 2]]
    )


@wp.kernel
def blend_points(
    # In:
    a: wp.array[wp.vec3],
    b: wp.array[wp.vec3],
    weight_a: float,
    # Out:
    out: wp.array[wp.vec3],
):
    """out = weight_a * a + (1 - weight_a) * b (re-anchoring blend). a, b, out (N,) [m]."""
    i = wp.tid()
    out[i] = weight_a * a[i] + (1.0 - weight_a) * b[i]


@wp.kernel
def compute_laplacian_coordinates(
    # In:
    points: wp.array[wp.vec3],
    offsets: wp.array[wp.int32],
    neighbors: wp.array[wp.int32],
    # Out:
    delta: wp.array[wp.vec3],
):
    """Uniform Laplacian coordinates: delta_i = p_i - mean of its neighbours.

    points (N,) [m]; offsets (N+1,), neighbors (E,) CSR adjacency; delta (N,) [m]
    (zero for isolated vertices).
    """
    i = wp.tid()
    s = offsets[i]
    e = offsets[i + 1]
    if e <= s:
        delta[i] = wp.vec3(0.0)
        return
    acc = wp.vec3(0.0)
    for k in range(s, e):
        acc += points[neighbors[k]]
    delta[i] = points[i] - acc / float(e - s)


@wp.kernel
def compute_closest_displacements(
    # In:
    points: wp.array[wp.vec3],
    closest: wp.array[wp.vec3],
    face: wp.array[wp.int32],
    pull_sum: wp.array[wp.vec3],
    pull_weight: wp.array[float],
    pull_fraction: float,
    # Out:
    disp: wp.array[wp.vec3],
    weight: wp.array[float],
):
    """Data term of the regularized fit: where each vertex wants to move, and how sure it is.

    Forward term: closest point on the target minus the vertex. Backward ("pull") term: the
    mean offset of the target points whose closest point on the template lies on faces around
    this vertex (pull_sum / pull_weight), mixed in with ``pull_fraction`` where any exists.
    points, closest (N,) [m]; face (N,) -1 when the forward query failed; pull_sum (N,) [m],
    pull_weight (N,) barycentric weight sums; disp (N,) [m]; weight (N,) 1 where there is data,
    0 where there is none (the smoothing then fills the displacement in from neighbours).
    """
    i = wp.tid()
    d = wp.vec3(0.0)
    w = float(0.0)
    if face[i] >= 0:
        d = closest[i] - points[i]
        w = 1.0
    pw = pull_weight[i]
    if pw > 1.0e-6 and pull_fraction > 0.0:
        dp = pull_sum[i] / pw
        if w > 0.0:
            d = (1.0 - pull_fraction) * d + pull_fraction * dp
        else:
            d = dp
        w = 1.0
    disp[i] = d
    weight[i] = w


@wp.kernel
def scatter_surface_pulls(
    # In:
    template_mesh: wp.uint64,
    template_indices: wp.array[wp.int32],
    targets: wp.array[wp.vec3],
    max_dist: float,
    # Out:
    pull_sum: wp.array[wp.vec3],
    pull_weight: wp.array[float],
):
    """Backward data term: each target point pulls the template face closest to it.

    For target point q with closest point c = sum_k w_k x_k on template face (i0, i1, i2),
    adds w_k (q - c) to pull_sum[i_k] and w_k to pull_weight[i_k] (atomic).
    template_mesh: wp.Mesh over the current template positions; template_indices (3M,);
    targets (Q,) [m] input-frame vertices; pull_sum (N,) [m]; pull_weight (N,). Zero both first.
    """
    j = wp.tid()
    q = targets[j]
    r = wp.mesh_query_point_no_sign(template_mesh, q, max_dist)
    if not r.result:
        return
    c = wp.mesh_eval_position(template_mesh, r.face, r.u, r.v)
    d = q - c
    w0 = r.u
    w1 = r.v
    w2 = 1.0 - r.u - r.v
    i0 = template_indices[3 * r.face + 0]
    i1 = template_indices[3 * r.face + 1]
    i2 = template_indices[3 * r.face + 2]
    wp.atomic_add(pull_sum, i0, w0 * d)
    wp.atomic_add(pull_sum, i1, w1 * d)
    wp.atomic_add(pull_sum, i2, w2 * d)
    wp.atomic_add(pull_weight, i0, w0)
    wp.atomic_add(pull_weight, i1, w1)
    wp.atomic_add(pull_weight, i2, w2)


@wp.kernel
def smooth_vectors_laplacian(
    # In:
    values: wp.array[wp.vec3],
    weight: wp.array[float],
    offsets: wp.array[wp.int32],
    neighbors: wp.array[wp.int32],
    lam: float,
    # Out:
    out: wp.array[wp.vec3],
    out_weight: wp.array[float],
):
    """One Jacobi step of confidence-weighted Laplacian smoothing of a vector field.

    out_i = (1 - lam) v_i + lam * mean_j v_j over neighbours with data (weight > 0);
    a vertex without data (weight 0) takes the mean of its neighbours with data.
    values (N,) [m] displacements; weight (N,) 0/1 data flags; offsets (N+1,), neighbors (E,)
    CSR; lam in [0, 1]; out (N,) [m]; out_weight (N,) updated flags (data spreads one ring).
    """
    i = wp.tid()
    s = offsets[i]
    e = offsets[i + 1]
    acc = wp.vec3(0.0)
    cnt = float(0.0)
    for k in range(s, e):
        j = neighbors[k]
        if weight[j] > 0.0:
            acc += values[j]
            cnt += 1.0
    v = values[i]
    if weight[i] > 0.0:
        if cnt > 0.0:
            out[i] = (1.0 - lam) * v + lam * acc / cnt
        else:
            out[i] = v
        out_weight[i] = 1.0
    else:
        if cnt > 0.0:
            out[i] = acc / cnt
            out_weight[i] = 1.0
        else:
            out[i] = v
            out_weight[i] = 0.0


@wp.kernel
def add_displacements(
    # In:
    points: wp.array[wp.vec3],
    disp: wp.array[wp.vec3],
    scale: float,
    # Out:
    out: wp.array[wp.vec3],
):
    """out = points + scale * disp. points, disp, out (N,) [m] (out may alias points)."""
    i = wp.tid()
    out[i] = points[i] + scale * disp[i]


@wp.kernel
def accumulate_vertex_normals(
    # In:
    points: wp.array[wp.vec3],
    indices: wp.array[wp.int32],
    # Out:
    normals: wp.array[wp.vec3],
):
    """Area-weighted vertex normals (unnormalized): adds (p1-p0)x(p2-p0) of each face to its
    three vertices. points (N,) [m]; indices (3M,); normals (N,) [m^2], zero it first."""
    f = wp.tid()
    i0 = indices[3 * f + 0]
    i1 = indices[3 * f + 1]
    i2 = indices[3 * f + 2]
    n = wp.cross(points[i1] - points[i0], points[i2] - points[i0])
    wp.atomic_add(normals, i0, n)
    wp.atomic_add(normals, i1, n)
    wp.atomic_add(normals, i2, n)


@wp.kernel
def relax_points_tangentially(
    # In:
    points: wp.array[wp.vec3],
    normals: wp.array[wp.vec3],
    rest_points: wp.array[wp.vec3],
    rest_delta: wp.array[wp.vec3],
    offsets: wp.array[wp.int32],
    neighbors: wp.array[wp.int32],
    step: float,
    # Out:
    out: wp.array[wp.vec3],
):
    """Restore the template's vertex distribution, moving vertices only within the tangent plane.

    Per vertex, fit the rotation R_i best mapping the template one-ring edges onto the current
    ones (polar part of sum_j (x_j - x_i)(t_j - t_i)^T, via SVD; as-rigid-as-possible local
    step), take the target x*_i = mean_j x_j + R_i delta_i (delta_i = the template's Laplacian
    coordinate), and move by step * (x*_i - x_i) with its normal component removed.
    points (N,) [m]; normals (N,) area-weighted vertex normals (any length); rest_points (N,)
    [m] template; rest_delta (N,) [m] template Laplacian coordinates; offsets (N+1,),
    neighbors (E,) CSR; step in [0, 1]; out (N,) [m] (must not alias points).
    """
    i = wp.tid()
    s = offsets[i]
    e = offsets[i + 1]
    x = points[i]
    if e <= s:
        out[i] = x
        return
    t = rest_points[i]
    S = wp.mat33(0.0)
    acc = wp.vec3(0.0)
    for k in range(s, e):
        j = neighbors[k]
        xj = points[j]
        acc += xj
        S += wp.outer(xj - x, rest_points[j] - t)
    mean = acc / float(e - s)
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(S, U, sig, V)
    R = U * wp.transpose(V)
    if wp.determinant(R) < 0.0:
        # reflection: flip the axis of the smallest singular value
        c = wp.vec3(U[0, 2], U[1, 2], U[2, 2])
        R = R - 2.0 * wp.outer(c, wp.vec3(V[0, 2], V[1, 2], V[2, 2]))
    target = mean + R * rest_delta[i]
    m = target - x
    n = normals[i]
    ln = wp.length(n)
    if ln > 0.0:
        n = n / ln
        m = m - wp.dot(m, n) * n
    out[i] = x + step * m


@wp.kernel
def project_points_along_normals(
    # In:
    mesh: wp.uint64,
    points: wp.array[wp.vec3],
    normals: wp.array[wp.vec3],
    max_dist: float,
    slack: float,
    # Out:
    out: wp.array[wp.vec3],
    dist: wp.array[float],
):
    """Move each point onto the mesh along its normal line, else to the closest point.

    Casts rays along +n and -n (n = normalized normals[i]) and takes the nearer hit h; the hit
    is used when |h - p| <= slack * (closest-point distance) + 1e-9 (a ray that grazes far
    away is rejected), otherwise the closest point is used. Along-normal projection avoids
    the tangential sliding of plain closest-point projection (clumping in concave regions).
    mesh: target wp.Mesh; points (N,) [m]; normals (N,) any length; max_dist [m]; slack >= 1;
    out (N,) [m] (the input point where nothing lies within max_dist); dist (N,) [m] moved.
    """
    i = wp.tid()
    p = points[i]
    q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
    if not q.result:
        out[i] = p
        dist[i] = max_dist
        return
    c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    dc = wp.length(c - p)
    best = c
    bestd = dc
    n = normals[i]
    ln = wp.length(n)
    if ln > 0.0:
        n = n / ln
        lim = slack * dc + 1.0e-9
        tbest = lim
        found = int(0)
        h1 = wp.mesh_query_ray(mesh, p, n, lim)
        if h1.result and h1.t <= tbest:
            tbest = h1.t
            found = 1
        h2 = wp.mesh_query_ray(mesh, p, -n, lim)
        if h2.result and h2.t < tbest:
            tbest = h2.t
            found = -1
        if found != 0:
            best = p + float(found) * tbest * n
            bestd = tbest
    out[i] = best
    dist[i] = bestd


@wp.kernel
def transform_points_rigid(
    # In:
    points: wp.array[wp.vec3],
    rotation: wp.mat33,
    center: wp.vec3,
    translation: wp.vec3,
    # Out:
    out: wp.array[wp.vec3],
):
    """out = rotation (p - center) + center + translation. points, out (N,) [m] (may alias)."""
    i = wp.tid()
    out[i] = rotation * (points[i] - center) + center + translation


@wp.func
def distance_to_mesh(mesh: wp.uint64, p: wp.vec3, max_dist: float) -> float:
    """Unsigned distance of p to the mesh surface [m]; max_dist when nothing lies within it."""
    q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
    d = max_dist
    if q.result:
        d = wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - p)
    return d


@wp.kernel
def measure_web_area(
    # Model:
    indices: wp.array[wp.int32],
    key_edge: wp.array[float],
    # In:
    points: wp.array[wp.vec3],
    mesh: wp.uint64,
    stretch: float,
    gap: float,
    closed: int,
    # Out:
    area_out: wp.array[float],
):
    """The web of a converted frame (``convert.web_fraction``), one thread per face:
    area_out[0] += the face's area; for a face whose longest edge exceeds ``stretch`` x key_edge
    (its longest edge in the template) and whose centroid has no point of the input ``mesh``
    within ``gap``: area_out[2] += its area when ``closed`` != 0 (the input is a closed surface)
    and the centroid lies inside it (``wp.mesh_query_point``'s sign: buried walls of parts in
    contact, which no sphere outside meets), else area_out[1] += its area (the web).

    indices (3M,) template faces; key_edge (M,) [m]; points (N,) converted vertices [m];
    mesh: the input frame's wp.Mesh; gap [m]; area_out (3,) [m^2], zeroed by the caller.
    """
    f = wp.tid()
    a = points[indices[3 * f]]
    b = points[indices[3 * f + 1]]
    c = points[indices[3 * f + 2]]
    area = 0.5 * wp.length(wp.cross(b - a, c - a))
    wp.atomic_add(area_out, 0, area)
    edge = wp.max(wp.max(wp.length(b - a), wp.length(c - b)), wp.length(a - c))
    if edge > stretch * key_edge[f]:
        centroid = (a + b + c) / 3.0
        q = wp.mesh_query_point_no_sign(mesh, centroid, gap)
        if not q.result:
            slot = int(1)
            if closed != 0:
                inside = wp.mesh_query_point(mesh, centroid, 1.0e30)
                if inside.result and inside.sign < 0.0:
                    slot = 2
            wp.atomic_add(area_out, slot, area)


@wp.kernel
def measure_flipped_area(
    # Model:
    indices: wp.array[wp.int32],
    # In:
    points: wp.array[wp.vec3],
    mesh: wp.uint64,
    gap: float,
    # Out:
    area_out: wp.array[float],
):
    """Faces of a converted frame turned against the input (``ConversionInfo.flipped``) or off it
    (``ConversionInfo.off_input``), one thread per face: area_out[0] += the face's area;
    area_out[1] += its area when the input ``mesh`` has a point within ``gap`` of its centroid and
    the face's normal points against the normal of the input face there (a fold-over: the
    converted surface doubled back on itself); area_out[2] += its area when the input has no point
    within ``gap`` of its centroid (the same query).

    indices (3M,) template faces; points (N,) converted vertices [m]; mesh: the input frame's
    wp.Mesh; gap [m]; area_out (3,) [m^2], zeroed by the caller.
    """
    f = wp.tid()
    a = points[indices[3 * f]]
    b = points[indices[3 * f + 1]]
    c = points[indices[3 * f + 2]]
    n = wp.cross(b - a, c - a)
    area = 0.5 * wp.length(n)
    wp.atomic_add(area_out, 0, area)
    q = wp.mesh_query_point_no_sign(mesh, (a + b + c) / 3.0, gap)
    if q.result:
        if wp.dot(n, wp.mesh_eval_face_normal(mesh, q.face)) < 0.0:
            wp.atomic_add(area_out, 1, area)
    else:
        wp.atomic_add(area_out, 2, area)


@wp.kernel
def measure_distances_to_mesh(
    # In:
    mesh: wp.uint64,
    points: wp.array[wp.vec3],
    max_dist: float,
    # Out:
    dist: wp.array[float],
):
    """Distance of each point to a mesh surface (coverage of a converted frame).

    mesh: wp.Mesh; points (Q,) [m]; max_dist [m] (a point with nothing within it gets max_dist);
    dist (Q,) [m] (at least Q entries).
    """
    k = wp.tid()
    dist[k] = distance_to_mesh(mesh, points[k], max_dist)


@wp.kernel
def sum_distances_to_mesh(
    # In:
    mesh: wp.uint64,
    points: wp.array[wp.vec3],
    stride: int,
    shift: wp.vec3,
    max_dist: float,
    # Out:
    total: wp.array[float],
):
    """Sum of the distances of a strided subset of points, translated, to a mesh (fit score).

    Thread k queries points[k * stride] + shift; launch with dim = ceil(N / stride).
    mesh: wp.Mesh; points (N,) [m]; stride >= 1; shift [m]; max_dist [m] (a point with nothing
    within it adds max_dist); total (1,) [m], zero it first (atomic add).
    """
    k = wp.tid()
    wp.atomic_add(total, 0, distance_to_mesh(mesh, points[k * stride] + shift, max_dist))
