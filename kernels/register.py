"""Stage 0 (preprocessing): embedded-deformation-graph registration (the ``graph`` strategy).

Per-vertex and per-correspondence work of :mod:`dynmesh_warp.deform_graph`. A template of N
vertices is driven by K graph nodes (K << N): node j has a rest position g_j, a rotation R_j and
a current position p_j; template vertex i with rest position T_i follows its ``k`` nodes

    X_i = sum_a w_ia (R_{n_ia} (T_i - g_{n_ia}) + p_{n_ia})          (linear in p for fixed R)

(``node_index`` / ``node_weight`` (N*k,): nodes n_ia and weights w_ia, sum_a w_ia = 1).

The data term is two-sided: every template vertex pulls towards its closest point on the input
frame (forward) and every input vertex pulls its closest point on the deformed template
(backward), each correspondence kept only when the normals agree. The Gauss-Newton / local-global
system in the node positions p is dense K x K; its data part is accumulated here with atomics:

    system (K*K,)   sum over correspondences of weight * a a^T (a: the row's node coefficients)
    rhs    (K,)     sum of weight * a (target - X_fixed)   [m], X_fixed = X - sum_b a_b p_b

All positions in scene units (metres by convention); weights dimensionless.
"""

import warp as wp


@wp.func
def triangle_normal(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), f: int) -> wp.vec3:
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
    rest_points: wp.array(dtype=wp.vec3),
    node_rest: wp.array(dtype=wp.vec3),
    node_index: wp.array(dtype=wp.int32),
    node_weight: wp.array(dtype=float),
    k: int,
    # In:
    node_rotation: wp.array(dtype=wp.mat33),
    node_position: wp.array(dtype=wp.vec3),
    # Out:
    points: wp.array(dtype=wp.vec3),
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
    mesh_points: wp.array(dtype=wp.vec3),
    mesh_indices: wp.array(dtype=wp.int32),
    queries: wp.array(dtype=wp.vec3),
    query_normals: wp.array(dtype=wp.vec3),
    max_dist: float,
    min_cos: float,
    # Out:
    closest: wp.array(dtype=wp.vec3),
    face: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
    weight: wp.array(dtype=float),
    dist: wp.array(dtype=float),
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


@wp.func
def fixed_part(
    points: wp.array(dtype=wp.vec3),
    node_index: wp.array(dtype=wp.int32),
    node_weight: wp.array(dtype=float),
    k: int,
    node_position: wp.array(dtype=wp.vec3),
    i: int,
) -> wp.vec3:
    """X_i minus its part linear in the node positions: X_i - sum_a w_ia p_a [m]."""
    s = points[i]
    for a in range(k):
        s -= node_weight[i * k + a] * node_position[node_index[i * k + a]]
    return s


@wp.kernel
def accumulate_forward_system(
    # Model:
    node_index: wp.array(dtype=wp.int32),
    node_weight: wp.array(dtype=float),
    k: int,
    num_nodes: int,
    # In:
    points: wp.array(dtype=wp.vec3),
    node_position: wp.array(dtype=wp.vec3),
    target: wp.array(dtype=wp.vec3),
    weight: wp.array(dtype=float),
    scale: float,
    # Out (accumulated):
    system: wp.array(dtype=float),
    rhs: wp.array(dtype=wp.vec3),
):
    """Normal equations of sum_i scale * weight_i |sum_a w_ia p_a + s_i - target_i|^2 in p.

    points (N,) current X [m]; target, weight (N,); system (K*K,) row-major; rhs (K,) [m].
    """
    i = wp.tid()
    c = scale * weight[i]
    if c == 0.0:
        return
    r = target[i] - fixed_part(points, node_index, node_weight, k, node_position, i)
    for a in range(k):
        ja = node_index[i * k + a]
        wa = node_weight[i * k + a]
        wp.atomic_add(rhs, ja, c * wa * r)
        for b in range(k):
            jb = node_index[i * k + b]
            wp.atomic_add(system, ja * num_nodes + jb, c * wa * node_weight[i * k + b])


@wp.kernel
def accumulate_backward_system(
    # Model:
    template_indices: wp.array(dtype=wp.int32),
    node_index: wp.array(dtype=wp.int32),
    node_weight: wp.array(dtype=float),
    k: int,
    num_nodes: int,
    # In:
    points: wp.array(dtype=wp.vec3),
    node_position: wp.array(dtype=wp.vec3),
    frame_points: wp.array(dtype=wp.vec3),
    face: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
    weight: wp.array(dtype=float),
    scale: float,
    # Out (accumulated):
    system: wp.array(dtype=float),
    rhs: wp.array(dtype=wp.vec3),
):
    """Normal equations of sum_q scale * weight_q |sum_c b_qc X_{v_c}(p) - q|^2 in p, X_v(p)
    the skinned template vertex v of face(q); the row's node coefficients are
    b_qc w_{v_c a} over the 3 x k (vertex, node) pairs (repeated nodes add up).

    frame_points (Q,) [m]; face, bary, weight (Q,) from find_correspondences (frame -> template).
    """
    q = wp.tid()
    c = scale * weight[q]
    f = face[q]
    if c == 0.0 or f < 0:
        return
    bw = bary[q]
    s = wp.vec3(0.0)
    for u in range(3):
        v = template_indices[3 * f + u]
        s += bw[u] * fixed_part(points, node_index, node_weight, k, node_position, v)
    r = frame_points[q] - s
    for u in range(3):
        vu = template_indices[3 * f + u]
        for a in range(k):
            ja = node_index[vu * k + a]
            ca = bw[u] * node_weight[vu * k + a]
            if ca == 0.0:
                continue
            wp.atomic_add(rhs, ja, c * ca * r)
            for u2 in range(3):
                vb = template_indices[3 * f + u2]
                for b in range(k):
                    cb = bw[u2] * node_weight[vb * k + b]
                    if cb != 0.0:
                        wp.atomic_add(system, ja * num_nodes + node_index[vb * k + b], c * ca * cb)


@wp.kernel
def accumulate_rotation_covariance(
    # Model:
    rest_points: wp.array(dtype=wp.vec3),
    node_rest: wp.array(dtype=wp.vec3),
    node_index: wp.array(dtype=wp.int32),
    node_weight: wp.array(dtype=float),
    k: int,
    # In:
    node_position: wp.array(dtype=wp.vec3),
    target: wp.array(dtype=wp.vec3),
    weight: wp.array(dtype=float),
    scale: float,
    # Out (accumulated):
    covariance: wp.array(dtype=wp.mat33),
):
    """Data part of each node's rotation fit (the local step of as-rigid-as-possible):
    covariance_j += scale * weight_i * w_ij (target_i - p_j) (T_i - g_j)^T over its vertices,
    so that R_j = argmax tr(R^T covariance_j) maps rest offsets onto target offsets.

    covariance (K,) [m^2]; target, weight (N,) from find_correspondences (template -> frame).
    """
    i = wp.tid()
    c = scale * weight[i]
    if c == 0.0:
        return
    t = rest_points[i]
    y = target[i]
    for a in range(k):
        j = node_index[i * k + a]
        w = node_weight[i * k + a]
        wp.atomic_add(covariance, j, c * w * wp.outer(y - node_position[j], t - node_rest[j]))
