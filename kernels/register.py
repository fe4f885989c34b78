"""Stage 0 (preprocessing): embedded-deformation-graph registration (the ``graph`` strategy).

Per-vertex and per-correspondence work of :mod:`dynmesh_warp.deform_graph`. A template of N
vertices is driven by K graph nodes (K << N): node j has a rest position g_j, a rotation R_j and
a current position p_j; template vertex i with rest position T_i follows its ``k`` nodes

    X_i = sum_a w_ia (R_{n_ia} (T_i - g_{n_ia}) + p_{n_ia})          (linear in p for fixed R)

(``node_index`` / ``node_weight`` (N*k,): nodes n_ia and weights w_ia, sum_a w_ia = 1).

The data term is two-sided: every template vertex pulls towards its closest point on the input
frame (forward) and every input vertex pulls its closest point on the deformed template
(backward), each correspondence kept only when the normals agree. For fixed rotations the
energy is quadratic in the node positions p, with one K x K matrix shared by the x, y and z
columns. Its sparsity pattern is fixed by the template (node pairs that share a template face),
so it is stored in CSR form (``row_offsets`` (K+1,), ``columns`` (nnz,) sorted per row) and
accumulated here with atomics:

    values (nnz,)   sum over correspondences of scale * weight * a a^T (a: the row's node
                    coefficients), plus the graph Laplacian and the damping
    rhs    (K,)     sum of scale * weight * a (target - X_fixed)   [m], X_fixed = X - sum_b a_b p_b

then solved on the device by Jacobi-preconditioned conjugate gradients (one launch for the
whole solve: one block of threads on CUDA, a serial loop on the CPU; no host round trip), and
the rotations are updated per node (polar part of the rotation covariance, ``wp.svd3``).
Correspondence weights are normalised on the device: ``weight_sum`` (2,) holds the forward and
backward weight totals, each side's scale is
0.5 / max(total, 1) (the two directions are means, weighted equally, as in the Chamfer distance).

All positions in scene units (metres by convention); weights dimensionless.
"""

import warp as wp

MAX_NODES_PER_VERTEX = 8  # the largest ``k`` (nodes per vertex) the kernels accept
MAX_ROW_NODES = wp.constant(3 * MAX_NODES_PER_VERTEX)  # distinct nodes of one template face


@wp.func
def triangle_normal(points: wp.array[wp.vec3], indices: wp.array[wp.int32], f: int) -> wp.vec3:
    """Unit normal of face f (counter-clockwise), zero for a degenerate face."""
    a = points[indices[3 * f + 0]]
    b = points[indices[3 * f + 1]]
    c = points[indices[3 * f + 2]]
    n = wp.cross(b - a, c - a)
    ln = wp.length(n)
    if ln > 0.0:
        return n / ln
    return wp.vec3(0.0)


@wp.kernel
def skin_vertices(
    # Model:
    rest_points: wp.array[wp.vec3],
    node_rest: wp.array[wp.vec3],
    node_index: wp.array[wp.int32],
    node_weight: wp.array[float],
    k: int,
    # In:
    node_rotation: wp.array[wp.mat33],
    node_position: wp.array[wp.vec3],
    # Out:
    points: wp.array[wp.vec3],
):
    """Embedded deformation: X_i = sum_a w_ia (R_a (T_i - g_a) + p_a).

    rest_points (N,) T [m]; node_rest (K,) g [m]; node_index, node_weight (N*k,);
    node_rotation (K,) R; node_position (K,) p [m]; points (N,) X [m].
    """
    i = wp.tid()
    t = rest_points[i]
    x = wp.vec3(0.0)
    for a in range(k):
        j = node_index[i * k + a]
        w = node_weight[i * k + a]
        x += w * (node_rotation[j] * (t - node_rest[j]) + node_position[j])
    points[i] = x


@wp.kernel
def find_correspondences(
    # In:
    mesh: wp.uint64,
    mesh_points: wp.array[wp.vec3],
    mesh_indices: wp.array[wp.int32],
    queries: wp.array[wp.vec3],
    query_normals: wp.array[wp.vec3],
    max_dist: float,
    min_cos: float,
    # Out:
    closest: wp.array[wp.vec3],
    face: wp.array[wp.int32],
    bary: wp.array[wp.vec3],
    weight: wp.array[float],
    dist: wp.array[float],
):
    """Closest point on ``mesh`` for each query, kept where the normals agree. Used both ways:
    template -> frame (mesh: the frame) and frame -> template (mesh: the template, refit).

    mesh: wp.Mesh over mesh_points / mesh_indices (3M,); queries, query_normals (Q,) [m] /
    normals (any length); closest (Q,) [m] (the query itself if nothing was found); face (Q,)
    or -1; bary (Q,) weights of the face's vertices; weight (Q,) 1 where the face normal and
    the query normal agree (dot of the unit vectors >= min_cos), else 0; dist (Q,) [m] to the
    surface whatever the normals (max_dist if nothing was found).
    """
    i = wp.tid()
    x = queries[i]
    r = wp.mesh_query_point_no_sign(mesh, x, max_dist)
    if not r.result:
        closest[i] = x
        face[i] = -1
        bary[i] = wp.vec3(0.0)
        weight[i] = 0.0
        dist[i] = max_dist
        return
    c = wp.mesh_eval_position(mesh, r.face, r.u, r.v)
    closest[i] = c
    face[i] = r.face
    bary[i] = wp.vec3(r.u, r.v, 1.0 - r.u - r.v)
    dist[i] = wp.length(c - x)
    n = triangle_normal(mesh_points, mesh_indices, r.face)
    w = 0.0
    if wp.dot(n, wp.normalize(query_normals[i])) >= min_cos:
        w = 1.0
    weight[i] = w


@wp.kernel
def gather_face_normals(
    # In:
    points: wp.array[wp.vec3],
    indices: wp.array[wp.int32],
    face: wp.array[wp.int32],
    # Out:
    normal: wp.array[wp.vec3],
):
    """The unit normal of each query's face (``triangle_normal``): the planes of point-to-plane
    rows (:func:`accumulate_rigid_system`) whose target is a face of the mesh (points, indices).

    points (P,) [m]; indices (3M,); face (Q,) a face index or -1; normal (Q,) zero for -1 or a
    degenerate face (such rows are skipped by the accumulation).
    """
    i = wp.tid()
    f = face[i]
    n = wp.vec3(0.0)
    if f >= 0:
        n = triangle_normal(points, indices, f)
    normal[i] = n


#: a closest point counts as on a face's edge (or corner) when its weight of the opposite corner
#: is below this (or its own weight above 1 minus it); Warp's closest-point query puts points of
#: an edge's region exactly on it, up to float32 rounding
RIM_BARY = wp.constant(1.0e-4)


@wp.kernel
def reject_rim_pairs(
    # Model:
    face_rim: wp.array[wp.int32],
    # In:
    face: wp.array[wp.int32],
    bary: wp.array[wp.vec3],
    # Out:
    weight_out: wp.array[float],
):
    """Zero the weight of each correspondence whose closest point lies on the searched mesh's rim
    (an edge of one face only, or a vertex of one): on a partial scan, or a template taken from
    one, a point beyond the part both surfaces show finds the rim as its closest point and pulls
    the fit sideways along the surface (Turk & Levoy 1994 leave such pairs out when aligning
    range scans).

    face_rim (M,) :func:`dynmesh_warp.geometry.face_rim_flags` of the searched mesh; face, bary
    (Q,) from :func:`find_correspondences`; weight_out (Q,) in place.
    """
    i = wp.tid()
    f = face[i]
    if f < 0:
        return
    flags = face_rim[f]
    if flags == 0:
        return
    b = bary[i]
    for k in range(3):
        if ((flags >> k) & 1) != 0 and b[k] < RIM_BARY:
            weight_out[i] = 0.0
        if ((flags >> (3 + k)) & 1) != 0 and b[k] > 1.0 - RIM_BARY:
            weight_out[i] = 0.0


@wp.func
def fixed_part(
    points: wp.array[wp.vec3],
    node_index: wp.array[wp.int32],
    node_weight: wp.array[float],
    k: int,
    node_position: wp.array[wp.vec3],
    i: int,
) -> wp.vec3:
    """X_i minus its part linear in the node positions: X_i - sum_a w_ia p_a [m]."""
    s = points[i]
    for a in range(k):
        s -= node_weight[i * k + a] * node_position[node_index[i * k + a]]
    return s


@wp.func
def find_slot(row_offsets: wp.array[wp.int32], columns: wp.array[wp.int32], row: int, col: int) -> int:
    """Index of entry (row, col) in the CSR arrays (binary search; -1 if not in the pattern)."""
    lo = row_offsets[row]
    hi = row_offsets[row + 1] - 1
    while lo <= hi:
        mid = (lo + hi) // 2
        c = columns[mid]
        if c == col:
            return mid
        if c < col:
            lo = mid + 1
        else:
            hi = mid - 1
    return -1


@wp.func
def add_entry(row_offsets: wp.array[wp.int32], columns: wp.array[wp.int32], row: int, col: int,
              v: float, values: wp.array[float]):
    """values[(row, col)] += v (atomic); an entry outside the pattern is dropped (never happens for
    the pattern of ``deform_graph.system_pattern``; the guard keeps a write in bounds)."""
    s = find_slot(row_offsets, columns, row, col)
    if s >= 0:
        wp.atomic_add(values, s, v)


@wp.func
def side_scale(weight_sum: wp.array[float], side: int) -> float:
    """0.5 / max(total weight of one side, 1): each direction of the data term is a mean."""
    return 0.5 / wp.max(weight_sum[side], 1.0)


@wp.kernel
def sum_correspondence_weights(
    # In:
    weight: wp.array[float],
    side: int,
    # Out (accumulated):
    weight_sum: wp.array[float],
):
    """weight_sum[side] += sum of weight[:dim] (launch with the live count: the array may be
    longer)."""
    i = wp.tid()
    w = weight[i]
    if w != 0.0:
        wp.atomic_add(weight_sum, side, w)


@wp.kernel
def accumulate_forward_system(
    # Model:
    node_index: wp.array[wp.int32],
    node_weight: wp.array[float],
    k: int,
    row_offsets: wp.array[wp.int32],
    columns: wp.array[wp.int32],
    # In:
    points: wp.array[wp.vec3],
    node_position: wp.array[wp.vec3],
    target: wp.array[wp.vec3],
    weight: wp.array[float],
    weight_sum: wp.array[float],
    # Out (accumulated):
    values: wp.array[float],
    rhs: wp.array[wp.vec3],
):
    """Normal equations of sum_i s_f weight_i |sum_a w_ia p_a + X_fixed_i - target_i|^2 in p,
    s_f = side_scale(weight_sum, 0).

    points (N,) current X [m]; target, weight (N,) from find_correspondences (template ->
    frame); values (nnz,) CSR, dimensionless; rhs (K,) [m].
    """
    i = wp.tid()
    c = side_scale(weight_sum, 0) * weight[i]
    if c == 0.0:
        return
    r = target[i] - fixed_part(points, node_index, node_weight, k, node_position, i)
    for a in range(k):
        ja = node_index[i * k + a]
        wa = node_weight[i * k + a]
        if wa == 0.0:
            continue
        wp.atomic_add(rhs, ja, c * wa * r)
        for b in range(k):
            wb = node_weight[i * k + b]
            if wb != 0.0:
                add_entry(row_offsets, columns, ja, node_index[i * k + b], c * wa * wb, values)


@wp.kernel
def accumulate_backward_system(
    # Model:
    template_indices: wp.array[wp.int32],
    node_index: wp.array[wp.int32],
    node_weight: wp.array[float],
    k: int,
    row_offsets: wp.array[wp.int32],
    columns: wp.array[wp.int32],
    # In:
    points: wp.array[wp.vec3],
    node_position: wp.array[wp.vec3],
    frame_points: wp.array[wp.vec3],
    face: wp.array[wp.int32],
    bary: wp.array[wp.vec3],
    weight: wp.array[float],
    weight_sum: wp.array[float],
    # Out (accumulated):
    values: wp.array[float],
    rhs: wp.array[wp.vec3],
):
    """Normal equations of sum_q s_b weight_q |sum_c b_qc X_{v_c}(p) - q|^2 in p, X_v(p) the
    skinned template vertex v of face(q), s_b = side_scale(weight_sum, 1); the row's node
    coefficients are b_qc w_{v_c a} over the 3 x k (vertex, node) pairs (repeated nodes merged first:
    at most MAX_ROW_NODES distinct).

    frame_points (Q,) [m]; face, bary, weight (Q,) from find_correspondences (frame -> template).
    """
    q = wp.tid()
    c = side_scale(weight_sum, 1) * weight[q]
    f = face[q]
    if c == 0.0 or f < 0:
        return
    bw = bary[q]
    # the row's distinct nodes and their coefficients (the face's vertices share most nodes)
    ids = wp.vector(length=MAX_ROW_NODES, dtype=wp.int32)
    coef = wp.vector(length=MAX_ROW_NODES, dtype=float)
    m = int(0)
    s = wp.vec3(0.0)
    for u in range(3):
        v = template_indices[3 * f + u]
        s += bw[u] * fixed_part(points, node_index, node_weight, k, node_position, v)
        for a in range(k):
            ca = bw[u] * node_weight[v * k + a]
            if ca == 0.0:
                continue
            j = node_index[v * k + a]
            found = int(-1)
            for t in range(m):
                if ids[t] == j:
                    found = t
            if found >= 0:
                coef[found] = coef[found] + ca
            else:
                ids[m] = j
                coef[m] = ca
                m += 1
    r = frame_points[q] - s
    for a in range(m):
        wp.atomic_add(rhs, ids[a], c * coef[a] * r)
        for b in range(m):
            add_entry(row_offsets, columns, ids[a], ids[b], c * coef[a] * coef[b], values)


@wp.kernel
def begin_graph_system(
    # Model:
    slot_row: wp.array[wp.int32],
    columns: wp.array[wp.int32],
    laplacian: wp.array[float],
    # In:
    position_prior: wp.array[wp.vec3],
    node_hold: wp.array[float],
    stiffness_weight: wp.array[float],
    damping_weight: float,
    # Out:
    values: wp.array[float],
    rhs: wp.array[wp.vec3],
    covariance: wp.array[wp.mat33],
    weight_sum: wp.array[float],
):
    """Start an iteration's system with its data-independent part, in one launch (dim = nnz):
    values = stiffness_weight[0] * laplacian (the graph's ARAP term) + (damping_weight + 1e-12) on
    the diagonal (a node with no data and no edge stays solvable); rhs = (damping_weight +
    node_hold) * prior (the damping term damping_weight |p - prior|^2 and node j's hold
    node_hold_j |p_j - prior_j|^2, (K,) [m]; ``node_hold`` (K,) enters the CG kernels' operator
    as a per-node diagonal, not the shared values); covariance = 0 (K,);
    weight_sum = 0 (2,). The data terms are accumulated on top.

    slot_row, columns, laplacian (nnz,): the row, column and graph-Laplacian value of each slot;
    stiffness_weight (1,): the iteration's weight per directed edge (a device array, so that one
    captured iteration serves every level of the stiffness schedule).
    """
    s = wp.tid()
    v = stiffness_weight[0] * laplacian[s]
    if slot_row[s] == columns[s]:
        v += damping_weight + 1.0e-12
    values[s] = v
    if s < rhs.shape[0]:
        rhs[s] = (damping_weight + node_hold[s]) * position_prior[s]
        covariance[s] = wp.mat33(0.0)
    if s == 0:
        weight_sum[0] = 0.0
        weight_sum[1] = 0.0


@wp.kernel
def accumulate_graph_rhs(
    # Model:
    edge_from: wp.array[wp.int32],
    edge_to: wp.array[wp.int32],
    rest_offset: wp.array[wp.vec3],
    # In:
    node_rotation: wp.array[wp.mat33],
    stiffness_weight: wp.array[float],
    # Out (accumulated):
    rhs: wp.array[wp.vec3],
):
    """Right-hand side of the ARAP graph term w sum_e |p_l - p_j - R_j (g_l - g_j)|^2 over directed
    edges e = (j -> l), w = stiffness_weight[0] (1,): rhs_l += w R_j d_e, rhs_j -= w R_j d_e.

    edge_from, edge_to (2E,) both directions of every edge; rest_offset (2E,) g_l - g_j [m].
    """
    e = wp.tid()
    j = edge_from[e]
    d = stiffness_weight[0] * (node_rotation[j] * rest_offset[e])
    wp.atomic_add(rhs, edge_to[e], d)
    wp.atomic_sub(rhs, j, d)


@wp.func
def csr_multiply_row(
    row_offsets: wp.array[wp.int32],
    columns: wp.array[wp.int32],
    values: wp.array[float],
    x: wp.array[wp.vec3],
    row: int,
) -> wp.vec3:
    s = wp.vec3(0.0)
    for e in range(row_offsets[row], row_offsets[row + 1]):
        s += values[e] * x[columns[e]]
    return s


@wp.func
def next_direction(
    preconditioned: wp.array[wp.vec3],
    direction_a: wp.array[wp.vec3],
    direction_b: wp.array[wp.vec3],
    beta: float,
    it: int,
    row: int,
) -> wp.vec3:
    """CG iteration ``it``'s search direction at ``row``: z + beta p, p the last iteration's (in
    buffer b on even iterations, a on odd ones); z alone on the first iteration."""
    if it == 0:
        return preconditioned[row]
    if it % 2 == 0:
        return preconditioned[row] + beta * direction_b[row]
    return preconditioned[row] + beta * direction_a[row]


@wp.kernel
def solve_conjugate_gradient_block(
    # Model:
    row_offsets: wp.array[wp.int32],
    columns: wp.array[wp.int32],
    diagonal_slot: wp.array[wp.int32],
    # In:
    values: wp.array[float],
    node_hold: wp.array[float],
    rhs: wp.array[wp.vec3],
    iterations: int,
    relative_tolerance: float,
    # Out (in place / scratch):
    solution_in: wp.array[wp.vec3],
    residual: wp.array[wp.vec3],
    preconditioned: wp.array[wp.vec3],
    direction_a: wp.array[wp.vec3],
    direction_b: wp.array[wp.vec3],
    product: wp.array[wp.vec3],
    residual_dot: wp.array[float],
):
    """The preconditioned CG of solve_conjugate_gradient_serial, by one block of threads
    (``wp.launch_tiled``, dim 1): each thread owns the rows lane, lane + block, ...; the three
    dot products of an iteration are block sums (``wp.tile_sum``), which also order the block's
    memory, so one launch does every iteration (the two launches an iteration it replaces cost
    ~7 us each on an H200 for ~1 us of work). The search direction p' = z + beta p is formed on
    the fly in the product and written to the other of two buffers (a thread reads its
    neighbours' p while writing its own p'). Stops once rz <= tol^2 rz_0. residual_dot
    (iterations + 1,) [m^2]: rz per iteration, the entries after the last one left as they were
    (zeroed before)."""
    _blk, lane = wp.tid()
    nthreads = wp.block_dim()
    K = row_offsets.shape[0] - 1
    part = float(0.0)
    for i in range(lane, K, nthreads):
        r = rhs[i] - csr_multiply_row(row_offsets, columns, values, solution_in, i) - node_hold[i] * solution_in[i]
        z = r / (values[diagonal_slot[i]] + node_hold[i])
        residual[i] = r
        preconditioned[i] = z
        part += wp.dot(r, z)
    rz0 = wp.tile_sum(wp.tile(part))[0]
    if lane == 0:
        residual_dot[0] = rz0
    rz = rz0
    beta = float(0.0)
    for it in range(iterations):
        if rz <= relative_tolerance * relative_tolerance * rz0 or rz <= 0.0:
            return
        # p' = z + beta p (p: buffer a on even iterations), q = A p'
        part = float(0.0)
        for i in range(lane, K, nthreads):
            s = wp.vec3(0.0)
            for e in range(row_offsets[i], row_offsets[i + 1]):
                s += values[e] * next_direction(preconditioned, direction_a, direction_b, beta, it, columns[e])
            p = next_direction(preconditioned, direction_a, direction_b, beta, it, i)
            s += node_hold[i] * p
            if it % 2 == 0:
                direction_a[i] = p
            else:
                direction_b[i] = p
            product[i] = s
            part += wp.dot(p, s)
        pq = wp.tile_sum(wp.tile(part))[0]
        if pq <= 0.0:
            return
        alpha = rz / pq
        part = float(0.0)
        for i in range(lane, K, nthreads):
            p = direction_a[i]
            if it % 2 == 1:
                p = direction_b[i]
            solution_in[i] = solution_in[i] + alpha * p
            r = residual[i] - alpha * product[i]
            residual[i] = r
            z = r / (values[diagonal_slot[i]] + node_hold[i])
            preconditioned[i] = z
            part += wp.dot(r, z)
        rz_new = wp.tile_sum(wp.tile(part))[0]
        if lane == 0:
            residual_dot[it + 1] = rz_new
        beta = rz_new / rz
        rz = rz_new


@wp.kernel
def solve_conjugate_gradient_serial(
    # Model:
    row_offsets: wp.array[wp.int32],
    columns: wp.array[wp.int32],
    diagonal_slot: wp.array[wp.int32],
    # In:
    values: wp.array[float],
    node_hold: wp.array[float],
    rhs: wp.array[wp.vec3],
    iterations: int,
    relative_tolerance: float,
    # Out (in place / scratch):
    solution_in: wp.array[wp.vec3],
    residual: wp.array[wp.vec3],
    preconditioned: wp.array[wp.vec3],
    direction: wp.array[wp.vec3],
    product: wp.array[wp.vec3],
    residual_dot: wp.array[float],
):
    """Jacobi-preconditioned CG on (A + diag(node_hold)) kron I3 x = rhs, warm-started from
    solution_in, as one serial launch (dim 1) for the CPU device: Warp's CPU backend runs a
    launch's threads one after another anyway. The system is A (K x K, CSR) times the (K, 3)
    unknowns, one CG over all three columns; ``node_hold`` (K,) is zero unless the fit holds
    nodes (then the same arithmetic as without it). Stops once rz <= tol^2 rz_0. residual_dot
    (iterations + 1,) [m^2]: rz per iteration, the entries after the last one left 0."""
    K = row_offsets.shape[0] - 1
    rz0 = float(0.0)
    for i in range(K):
        r = rhs[i] - csr_multiply_row(row_offsets, columns, values, solution_in, i) - node_hold[i] * solution_in[i]
        z = r / (values[diagonal_slot[i]] + node_hold[i])
        residual[i] = r
        preconditioned[i] = z
        direction[i] = z
        rz0 += wp.dot(r, z)
    residual_dot[0] = rz0
    rz = rz0
    for it in range(iterations):
        if rz <= relative_tolerance * relative_tolerance * rz0 or rz <= 0.0:
            return
        pq = float(0.0)
        for i in range(K):
            s = csr_multiply_row(row_offsets, columns, values, direction, i) + node_hold[i] * direction[i]
            product[i] = s
            pq += wp.dot(direction[i], s)
        if pq <= 0.0:
            return
        alpha = rz / pq
        rz_new = float(0.0)
        for i in range(K):
            solution_in[i] = solution_in[i] + alpha * direction[i]
            r = residual[i] - alpha * product[i]
            residual[i] = r
            z = r / (values[diagonal_slot[i]] + node_hold[i])
            preconditioned[i] = z
            rz_new += wp.dot(r, z)
        residual_dot[it + 1] = rz_new
        beta = rz_new / rz
        for i in range(K):
            direction[i] = preconditioned[i] + beta * direction[i]
        rz = rz_new


@wp.kernel
def accumulate_rotation_covariance(
    # Model:
    rest_points: wp.array[wp.vec3],
    node_rest: wp.array[wp.vec3],
    node_index: wp.array[wp.int32],
    node_weight: wp.array[float],
    k: int,
    # In:
    node_position: wp.array[wp.vec3],
    target: wp.array[wp.vec3],
    weight: wp.array[float],
    weight_sum: wp.array[float],
    # Out (accumulated):
    covariance: wp.array[wp.mat33],
):
    """Data part of each node's rotation fit (the local step of as-rigid-as-possible):
    covariance_j += s_f weight_i w_ij (target_i - p_j) (T_i - g_j)^T over its vertices
    (s_f = side_scale(weight_sum, 0)), so that R_j = argmax tr(R^T covariance_j) maps rest
    offsets onto target offsets.

    covariance (K,) [m^2]; target, weight (N,) from find_correspondences (template -> frame).
    """
    i = wp.tid()
    c = side_scale(weight_sum, 0) * weight[i]
    if c == 0.0:
        return
    t = rest_points[i]
    y = target[i]
    for a in range(k):
        j = node_index[i * k + a]
        w = node_weight[i * k + a]
        wp.atomic_add(covariance, j, c * w * wp.outer(y - node_position[j], t - node_rest[j]))


@wp.kernel
def accumulate_edge_covariance(
    # Model:
    edge_from: wp.array[wp.int32],
    edge_to: wp.array[wp.int32],
    rest_offset: wp.array[wp.vec3],
    # In:
    node_position: wp.array[wp.vec3],
    stiffness_weight: wp.array[float],
    # Out (accumulated):
    covariance: wp.array[wp.mat33],
):
    """Graph part of the rotation fit: covariance_j += w (p_l - p_j) (g_l - g_j)^T per directed
    edge (j -> l) [m^2], w = stiffness_weight[0] (1,)."""
    e = wp.tid()
    j = edge_from[e]
    cur = node_position[edge_to[e]] - node_position[j]
    wp.atomic_add(covariance, j, stiffness_weight[0] * wp.outer(cur, rest_offset[e]))


@wp.kernel
def update_node_rotations(
    # In:
    covariance: wp.array[wp.mat33],
    # Out (in place):
    node_rotation_in: wp.array[wp.mat33],
):
    """R_j = the rotation maximising tr(R^T C_j), C_j = covariance_j + (1e-3 |covariance_j|_F +
    1e-12) R_j (a small pull towards the current rotation keeps nodes with little data stable).

    Computed by the iteration of Mueller et al., "A Robust Method to Extract the Rotational Part
    of Deformations" (MIG 2016), warm-started from the current R_j: each step rotates R by
    omega = sum_c (r_c x a_c) / (|sum_c r_c . a_c| + eps) (r_c, a_c: columns of R and C), up to
    32 steps, always a proper rotation. (``wp.svd3``'s U V^T was off by 1e-2 for covariances
    with singular values 66 : 17 : 1, so it is not used.)
    """
    j = wp.tid()
    C = covariance[j]
    n = float(0.0)
    for a in range(3):
        for b in range(3):
            n += C[a, b] * C[a, b]
    R0 = node_rotation_in[j]
    C = C + (1.0e-3 * wp.sqrt(n) + 1.0e-12) * R0
    C = C / (1.001 * wp.sqrt(n) + 1.0e-12)  # unit scale: the thresholds below are relative
    q = wp.quat_from_matrix(R0)
    q = wp.normalize(q)
    for _it in range(32):
        R = wp.quat_to_matrix(q)
        num = wp.vec3(0.0)
        den = float(0.0)
        for c in range(3):
            rc = wp.vec3(R[0, c], R[1, c], R[2, c])
            ac = wp.vec3(C[0, c], C[1, c], C[2, c])
            num += wp.cross(rc, ac)
            den += wp.dot(rc, ac)
        omega = num / (wp.abs(den) + 1.0e-9)
        w = wp.length(omega)
        if w < 1.0e-7:
            break
        q = wp.normalize(wp.quat_from_axis_angle(omega / w, w) * q)
    node_rotation_in[j] = wp.quat_to_matrix(q)


@wp.kernel
def measure_node_motion(
    # In:
    node_position: wp.array[wp.vec3],
    position_prev: wp.array[wp.vec3],
    # Out (accumulated):
    moved: wp.array[float],
):
    """moved[0] = max over nodes j of |node_position_j - position_prev_j| [m] (the caller zeroes
    it): how far the last graph iteration moved a node (the held-level test of ``fit``)."""
    j = wp.tid()
    wp.atomic_max(moved, 0, wp.length(node_position[j] - position_prev[j]))


@wp.kernel
def accumulate_rigid_system(
    # Model:
    element_part: wp.array[wp.int32],
    part_center: wp.array[wp.vec3],
    # In:
    moving: wp.array[wp.vec3],
    fixed: wp.array[wp.vec3],
    plane_normal: wp.array[wp.vec3],
    weight: wp.array[float],
    element: wp.array[wp.int32],
    side: int,
    # Out (accumulated):
    rigid_system: wp.array2d[float],
):
    """Gauss-Newton normal equations, per part of the template, of sum_i weight_i
    ((moving_i - fixed_i) . n_i)^2 in a small rigid motion of each part (rotation vector omega
    [rad] about its ``part_center``, translation tau [m]: x -> x + omega x (x - center) + tau),
    n_i = plane_normal_i normalised. Row i belongs to part element_part[element[i]] (``element``: a
    template vertex or face; rows with element -1, a zero normal or a zero weight are skipped).
    Row i: J = [(moving_i - center) x n_i, n_i], residual e = (moving_i - fixed_i) . n_i [m].

    moving, fixed, plane_normal, weight, element (dim,) (launch with the live count);
    rigid_system (2 x parts, 29): row 2 part + ``side`` += the upper triangle of sum w J J^T
    (21 entries, row by row), sum w J e (6), sum w (1), sum w e^2 (1) [m^2].
    """
    i = wp.tid()
    w = weight[i]
    nl = wp.length(plane_normal[i])
    el = element[i]
    if w == 0.0 or nl == 0.0 or el < 0:
        return
    p = element_part[el]
    row = 2 * p + side
    n = plane_normal[i] / nl
    x = moving[i]
    c = wp.cross(x - part_center[p], n)
    J = wp.vector(c[0], c[1], c[2], n[0], n[1], n[2])
    e = wp.dot(x - fixed[i], n)
    s = int(0)
    for a in range(6):
        for b in range(a, 6):
            wp.atomic_add(rigid_system, row, s, w * J[a] * J[b])
            s += 1
    for a in range(6):
        wp.atomic_add(rigid_system, row, 21 + a, w * J[a] * e)
    wp.atomic_add(rigid_system, row, 27, w)
    wp.atomic_add(rigid_system, row, 28, w * e * e)


@wp.kernel
def accumulate_node_residuals(
    # Model:
    node_index: wp.array[wp.int32],
    k: int,
    # In:
    points: wp.array[wp.vec3],
    target: wp.array[wp.vec3],
    normals: wp.array[wp.vec3],
    weight: wp.array[float],
    # Out (accumulated):
    node_residual: wp.array[wp.vec2],
):
    """Per graph node, the plane distances of the template vertices whose nearest node it is
    (node_index[k i], the first of vertex i's k nodes): node_residual[j] += (w_i e_i^2, w_i) with
    e_i = (points_i - target_i) . n_i [m], n_i = normals_i normalised; vertices with a zero
    weight or normal are skipped.

    node_index (N k,); points, target, normals, weight (N,); node_residual (K,) [m^2, 1], zero it first.
    """
    i = wp.tid()
    w = weight[i]
    nl = wp.length(normals[i])
    if w == 0.0 or nl == 0.0:
        return
    e = wp.dot(points[i] - target[i], normals[i] / nl)
    wp.atomic_add(node_residual, node_index[k * i], wp.vec2(w * e * e, w))

