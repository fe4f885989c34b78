"""Stage 2: per-face geometry and closest-point (NearestSurface) queries."""

import warp as wp


@wp.kernel
def compute_face_normals(
    # In:
    points: wp.array[wp.vec3],
    indices: wp.array[wp.int32],
    # Out:
    face_normals: wp.array[wp.vec3],
):
    """Unit normal of each triangle, (p1 - p0) x (p2 - p0) normalized; zero for degenerate faces.

    points (N,) [m]; indices (3M,) flat triangle list; face_normals (M,) unit vectors.
    """
    f = wp.tid()
    p0 = points[indices[3 * f + 0]]
    p1 = points[indices[3 * f + 1]]
    p2 = points[indices[3 * f + 2]]
    n = wp.cross(p1 - p0, p2 - p0)
    ln = wp.length(n)
    if ln > 0.0:
        face_normals[f] = n / ln
    else:
        face_normals[f] = wp.vec3(0.0)


@wp.func
def closest_point_on_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Barycentric weights (wa, wb, wc) of the point of triangle abc closest to p.

    Ericson, Real-Time Collision Detection, 5.1.5 (Voronoi regions).
    """
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.vec3(0.0, 1.0, 0.0)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return wp.vec3(1.0 - v, v, 0.0)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.vec3(0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return wp.vec3(1.0 - w, 0.0, w)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3(0.0, 1.0 - w, w)
    denom = va + vb + vc
    if denom <= 0.0:
        # degenerate triangle: fall back to its first vertex
        return wp.vec3(1.0, 0.0, 0.0)
    inv = 1.0 / denom
    v = vb * inv
    w = vc * inv
    return wp.vec3(1.0 - v - w, v, w)


@wp.kernel
def project_points_to_mesh(
    # In:
    mesh: wp.uint64,
    queries: wp.array[wp.vec3],
    max_dist: float,
    # Out:
    closest: wp.array[wp.vec3],
    face: wp.array[wp.int32],
    bary: wp.array[wp.vec3],
    dist: wp.array[float],
):
    """NearestSurface: closest point on a mesh for each query point (BVH query).

    queries (Q,) [m]; closest (Q,) [m]; face (Q,) index, -1 when nothing within max_dist;
    bary (Q,) weights of the face's vertices (i0, i1, i2), summing to 1; dist (Q,) [m].
    """
    i = wp.tid()
    p = queries[i]
    q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
    if q.result:
        c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        closest[i] = c
        face[i] = q.face
        bary[i] = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)
        dist[i] = wp.length(p - c)
    else:
        closest[i] = p
        face[i] = -1
        bary[i] = wp.vec3(0.0)
        dist[i] = max_dist
