"""Stage: evaluation. Surface sampling, exact nearest neighbours (Chamfer) and the
multi-level soft "approxmatch" assignment of Fan et al. 2017 (EMD).

Host wrappers live in :mod:`dynmesh_warp.metrics`; these kernels allocate nothing.
"""

import warp as wp

# ------------------------------------------------------------------------------- sampling


@wp.kernel
def sample_surface_points(
    # In:
    points: wp.array[wp.vec3],
    indices: wp.array[wp.int32],
    face_cdf: wp.array[float],
    seed: int,
    # Out:
    samples: wp.array[wp.vec3],
    sample_face: wp.array[wp.int32],
):
    """Area-weighted uniform random points on a triangle mesh.

    points (N,) vertex positions [m]; indices (3M,) flat triangle list; face_cdf (M,)
    cumulative face area divided by the total area (last entry 1); seed: RNG seed, sample i
    uses the stream wp.rand_init(seed, i) so results do not depend on launch order.
    samples (S,) [m]; sample_face (S,) the face each sample lies on.
    A face is picked by binary search of u ~ U[0,1) in face_cdf, then a point uniformly inside
    it with the square-root barycentric map (r1' = sqrt(r1): w = (1-r1', r1'(1-r2), r1' r2)).
    """
    i = wp.tid()
    state = wp.rand_init(seed, i)
    u = wp.randf(state)
    r1 = wp.sqrt(wp.randf(state))
    r2 = wp.randf(state)
    m = face_cdf.shape[0]
    lo = int(0)
    hi = m - 1
    while lo < hi:  # first face whose cdf exceeds u
        mid = (lo + hi) // 2
        if face_cdf[mid] > u:
            hi = mid
        else:
            lo = mid + 1
    a = points[indices[3 * lo + 0]]
    b = points[indices[3 * lo + 1]]
    c = points[indices[3 * lo + 2]]
    samples[i] = (1.0 - r1) * a + r1 * (1.0 - r2) * b + r1 * r2 * c
    sample_face[i] = lo


# ------------------------------------------------------------------------ nearest neighbours


# ------------------------------------------------------------------ approxmatch (Fan et al.)
# One call of the three kernels below is one "level" of the approxmatch of
# Fan, Su, Guibas, "A Point Set Generation Network for 3D Object Reconstruction from a Single
# Image", CVPR 2017 (PointSetGeneration, tf_approxmatch_g.cu), with weights
# w(k, l) = exp(level * |x1_k - x2_l|^2). The host runs the levels level = -4^j for
# j = 7, 6, ..., -1 and then level = 0, in this order, as the original does.


@wp.kernel
def compute_approxmatch_ratio_left(
    # In:
    xyz1: wp.array[wp.vec3],
    xyz2: wp.array[wp.vec3],
    remain_right: wp.array[float],
    remain_left: wp.array[float],
    level: float,
    # Out:
    ratio_left: wp.array[float],
):
    """ratio_left[k] = remain_left[k] / (1e-9 + sum_l exp(level |x1_k - x2_l|^2) remain_right[l]).

    xyz1 (n,) [m]; xyz2 (m,) [m]; remain_right (m,), remain_left (n,) unassigned mass;
    level [1/m^2] (<= 0); ratio_left (n,).
    """
    k = wp.tid()
    x1 = xyz1[k]
    suml = float(1.0e-9)
    for l in range(xyz2.shape[0]):
        w = wp.exp(level * wp.length_sq(xyz2[l] - x1)) * remain_right[l]
        suml += w
    ratio_left[k] = remain_left[k] / suml


@wp.kernel
def compute_approxmatch_ratio_right(
    # In:
    xyz1: wp.array[wp.vec3],
    xyz2: wp.array[wp.vec3],
    ratio_left: wp.array[float],
    level: float,
    # Out:
    remain_right: wp.array[float],
    ratio_right: wp.array[float],
):
    """Right-side consumption of one level.

    sumr = remain_right[l] * sum_k exp(level |x1_k - x2_l|^2) ratio_left[k];
    ratio_right[l] = min(remain_right[l] / (sumr + 1e-9), 1) * remain_right[l];
    remain_right[l] = max(0, remain_right[l] - sumr)   (updated in place).
    xyz1 (n,) [m]; xyz2 (m,) [m]; ratio_left (n,); level [1/m^2]; remain_right, ratio_right (m,).
    """
    l = wp.tid()
    x2 = xyz2[l]
    sumr = float(0.0)
    for k in range(xyz1.shape[0]):
        w = wp.exp(level * wp.length_sq(x2 - xyz1[k])) * ratio_left[k]
        sumr += w
    rr = remain_right[l]
    sumr = sumr * rr
    consumption = wp.min(rr / (sumr + 1.0e-9), 1.0)
    ratio_right[l] = consumption * rr
    remain_right[l] = wp.max(0.0, rr - sumr)


@wp.kernel
def accumulate_approxmatch_left(
    # In:
    xyz1: wp.array[wp.vec3],
    xyz2: wp.array[wp.vec3],
    ratio_left: wp.array[float],
    ratio_right: wp.array[float],
    level: float,
    store_match: int,
    # Out:
    remain_left: wp.array[float],
    cost_left: wp.array[float],
    match: wp.array2d[float],
):
    """Add this level's matches of each left point; update its remaining mass and cost.

    w(k, l) = exp(level |x1_k - x2_l|^2) ratio_left[k] ratio_right[l];
    remain_left[k] = max(0, remain_left[k] - sum_l w(k, l))   (in place);
    cost_left[k] += sum_l w(k, l) |x1_k - x2_l|   (UNSQUARED distance, [m]);
    match[l, k] += w(k, l) when store_match != 0 (match is (m, n) as in the original; pass a
    (1, 1) dummy otherwise). xyz1 (n,), xyz2 (m,) [m]; ratio_left (n,); ratio_right (m,).
    Summing cost_left over k gives the original's match_cost (sum_kl match * distance) without
    the (m, n) matrix.
    """
    k = wp.tid()
    x1 = xyz1[k]
    rl = ratio_left[k]
    suml = float(0.0)
    cost = float(0.0)
    for l in range(xyz2.shape[0]):
        d2 = wp.length_sq(xyz2[l] - x1)
        w = wp.exp(level * d2) * rl * ratio_right[l]
        suml += w
        cost += w * wp.sqrt(d2)
        if store_match != 0:
            match[l, k] = match[l, k] + w
    remain_left[k] = wp.max(0.0, remain_left[k] - suml)
    cost_left[k] = cost_left[k] + cost


@wp.kernel
def find_nearest_points_bvh(
    # In:
    point_mesh: wp.uint64,
    queries: wp.array[wp.vec3],
    targets: wp.array[wp.vec3],
    # Out:
    nearest_index: wp.array[wp.int32],
    nearest_dist_sq: wp.array[float],
):
    """Exact nearest target point of each query through a BVH: ``point_mesh`` is a wp.Mesh
    whose triangle i is the degenerate (i, i, i) on targets[i], so its closest face is the
    nearest point (the BVH's box-distance pruning is exact).

    queries (Q,) [m]; targets (P,) [m]; nearest_index (Q,); nearest_dist_sq (Q,) [m^2].
    """
    i = wp.tid()
    p = queries[i]
    q = wp.mesh_query_point_no_sign(point_mesh, p, 3.0e38)
    j = int(-1)
    d = float(3.0e38)
    if q.result:
        j = q.face
        d = wp.length_sq(p - targets[j])
    nearest_index[i] = j
    nearest_dist_sq[i] = d
