"""Metrics: surface sampling, exact nearest neighbours / Chamfer, approxmatch EMD, protocols.

References are independent: SciPy cKDTree, SciPy Hungarian assignment, a float64 NumPy
transcription of the original approxmatch CUDA kernel, analytic sphere distances and a
hand-computed example.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from dynmesh_warp import metrics as M
from dynmesh_warp.sequence import MeshDataError


def approxmatch_numpy(x1, x2):
    """Float64 NumPy transcription of approxmatch + matchcost (tf_approxmatch_g.cu, n == m)."""
    x1 = np.asarray(x1, np.float64)
    x2 = np.asarray(x2, np.float64)
    D2 = ((x1[:, None, :] - x2[None, :, :]) ** 2).sum(-1)
    remL, remR = np.ones(len(x1)), np.ones(len(x2))
    match = np.zeros_like(D2)
    for j in range(7, -3, -1):
        level = 0.0 if j == -2 else -(4.0**j)
        W = np.exp(level * D2)
        ratioL = remL / (1e-9 + W @ remR)
        sumr = (W * ratioL[:, None]).sum(0) * remR
        ratioR = np.minimum(remR / (sumr + 1e-9), 1.0) * remR
        remR = np.maximum(0.0, remR - sumr)
        w = W * ratioL[:, None] * ratioR[None, :]
        match += w
        remL = np.maximum(0.0, remL - w.sum(1))
    return float((match * np.sqrt(D2)).sum() / len(x1)), match


# ------------------------------------------------------------------------------- sampling


def test_samples_lie_on_their_faces_and_follow_area(device):
    # two triangles, areas 1 : 3 (right triangles with legs 1,2 and 2,3 in the z=0 / x=5 planes)
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [5, 0, 0], [5, 2, 0], [5, 0, 3]], np.float32)
    F = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
    P, f = M.sample_surface(V, F, 20000, seed=3, device=device, return_faces=True)
    assert P.shape == (20000, 3) and P.dtype == np.float32
    # each sample is inside its face: barycentric coordinates in [0, 1]
    for k in (0, 1):
        a, b, c = V[F[k]].astype(np.float64)
        T = np.stack([b - a, c - a], axis=1)
        uv, res, *_ = np.linalg.lstsq(T, (P[f == k] - a).T, rcond=None)
        assert np.all(uv >= -1e-5) and np.all(uv.sum(0) <= 1 + 1e-5)
        assert np.abs(T @ uv + a[:, None] - P[f == k].T).max() < 1e-5  # on the plane
    frac = np.mean(f == 0)
    assert abs(frac - 0.25) < 0.015  # 1 / (1 + 3); binomial sd 0.003
    # uniform inside a face: mean of samples on face 1 is its centroid
    assert np.allclose(P[f == 1].mean(0), V[F[1]].mean(0), atol=0.03)


def test_sampling_is_seeded(device, deformed_icosphere):
    V, F = deformed_icosphere
    a = M.sample_surface(V, F, 500, seed=1, device=device)
    b = M.sample_surface(V, F, 500, seed=1, device=device)
    c = M.sample_surface(V, F, 500, seed=2, device=device)
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)


def test_sampling_rejects_bad_faces(device):
    V = np.zeros((3, 3), np.float32)
    with pytest.raises(MeshDataError, match="out of range"):
        M.sample_surface(V, np.array([[0, 1, 3]]), 10, device=device, source="bad.obj")
    with pytest.raises(MeshDataError, match="area is zero"):
        M.sample_surface(V, np.array([[0, 1, 2]]), 10, device=device)


# ------------------------------------------------------------------------ nearest neighbours


@pytest.mark.parametrize("layout", ["overlapping", "far_apart", "clustered"])
def test_nearest_neighbors_match_kdtree(device, rng, layout):
    a = rng.random((3000, 3))
    if layout == "overlapping":
        b = rng.random((2000, 3))
    elif layout == "far_apart":  # far queries: the BVH must still return the exact nearest
        b = rng.random((2000, 3)) * 0.3 + np.array([4.0, -3.0, 2.0])
    else:  # very uneven density: a dense blob plus sparse outliers
        b = np.concatenate([rng.normal(0.5, 0.01, (1900, 3)), rng.random((100, 3)) * 3 - 1])
    a = a.astype(np.float32)
    b = b.astype(np.float32)
    d2, idx = M.nearest_neighbors(a, b, device=device)
    ref_d, ref_i = cKDTree(b.astype(np.float64)).query(a.astype(np.float64))
    np.testing.assert_allclose(np.sqrt(d2), ref_d, rtol=1e-5, atol=1e-6)
    # indices agree except for exact distance ties
    diff = idx != ref_i
    if diff.any():
        np.testing.assert_allclose(
            np.linalg.norm(a[diff] - b[idx[diff]], axis=1), ref_d[diff], rtol=1e-6)


def test_chamfer_matches_kdtree_brute_force(device, rng):
    a = rng.normal(size=(2500, 3)).astype(np.float32)
    b = (rng.normal(size=(1700, 3)) * 1.3 + 0.2).astype(np.float32)
    c = M.chamfer_distance(a, b, device=device)
    dab = cKDTree(b.astype(np.float64)).query(a.astype(np.float64))[0]
    dba = cKDTree(a.astype(np.float64)).query(b.astype(np.float64))[0]
    assert c.a_to_b == pytest.approx(np.mean(dab**2), rel=1e-5)
    assert c.b_to_a == pytest.approx(np.mean(dba**2), rel=1e-5)
    assert c.value == pytest.approx(0.5 * (np.mean(dab**2) + np.mean(dba**2)), rel=1e-5)
    u = M.chamfer_distance(a, b, squared=False, device=device)
    assert u.value == pytest.approx(0.5 * (dab.mean() + dba.mean()), rel=1e-5)


def test_chamfer_of_mesh_with_itself_is_zero(device, deformed_icosphere):
    V, F = deformed_icosphere
    assert M.chamfer_distance(V, V, device=device).value == 0.0
    for protocol in ("dgmesh", "paper"):
        r = M.evaluate_mesh_pair((V, F), (V, F), protocol, device=device, emd=False)
        # dgmesh: identical vertex sets -> exactly 0; paper: independent samples of one
        # surface -> small but positive (sampling gap), far below the CD of a 10% scaling
        if protocol == "dgmesh":
            assert r["cd"] == 0.0
        else:
            off = M.evaluate_mesh_pair((V, F), (V * 1.1, F), protocol, device=device, emd=False)
            assert 0.0 < r["cd"] < 0.1 * off["cd"]


def test_chamfer_concentric_spheres_vertices_exact(device):
    # vertices of two concentric spheres sharing directions: nearest of each vertex is its
    # radial partner (|p - q|^2 = r1^2 + r2^2 - 2 r1 r2 cos(theta) is smallest at theta = 0)
    s = trimesh.creation.icosphere(subdivisions=3)
    U = np.asarray(s.vertices)
    r1, r2 = 1.0, 1.07
    c = M.chamfer_distance((U * r1).astype(np.float32), (U * r2).astype(np.float32), device=device)
    assert c.a_to_b == pytest.approx((r2 - r1) ** 2, rel=1e-4)
    assert c.b_to_a == pytest.approx((r2 - r1) ** 2, rel=1e-4)


def test_chamfer_concentric_spheres_samples_bounded(device):
    # independent samples pushed onto spheres r1, r2: every NN distance is >= |r1 - r2| and
    # <= |r1 - r2| + r2 * (angular covering radius of the r2 samples), measured with a KD-tree
    s = trimesh.creation.icosphere(subdivisions=4)
    r1, r2 = 1.0, 1.1
    A = M.sample_surface(s.vertices, s.faces, 6000, seed=0, device=device).astype(np.float64)
    B = M.sample_surface(s.vertices, s.faces, 6000, seed=1, device=device).astype(np.float64)
    A = r1 * A / np.linalg.norm(A, axis=1, keepdims=True)
    B = r2 * B / np.linalg.norm(B, axis=1, keepdims=True)
    d2, _ = M.nearest_neighbors(A, B, device=device)
    d = np.sqrt(d2.astype(np.float64))
    assert d.min() >= (r2 - r1) * (1 - 1e-4)
    ang = cKDTree(B / r2).query(A / r1)[0]  # chord to the angularly nearest sample
    assert np.all(d <= (r2 - r1) + r2 * ang.max() + 1e-5)
    c = M.chamfer_distance(A, B, squared=False, device=device)
    assert (r2 - r1) <= c.a_to_b < (r2 - r1) + 0.02


# -------------------------------------------------------------------------------------- EMD


def test_approxmatch_matches_transcription_of_original(device, rng):
    x = rng.random((300, 3)).astype(np.float32)
    y = (rng.random((300, 3)) * 0.8 + 0.1).astype(np.float32)
    emd, det = M.approxmatch_emd(x, y, device=device, return_details=True)
    ref, ref_match = approxmatch_numpy(x, y)
    assert emd == pytest.approx(ref, rel=1e-4)
    np.testing.assert_allclose(det["match"].T, ref_match, atol=1e-3)
    # the soft assignment is (almost) a full transport plan: marginals ~ 1
    np.testing.assert_allclose(det["match"].sum(0), 1.0, atol=1e-3)
    np.testing.assert_allclose(det["match"].sum(1), 1.0, atol=1e-3)


def test_approxmatch_identical_clouds_is_zero(device, rng):
    x = rng.random((512, 3)).astype(np.float32)
    # the soft assignment leaks a little mass to neighbours even at level -4^7, so the cost
    # is ~0 (3e-6 here, against ~0.1 for an unrelated cloud), as in the original
    emd = M.approxmatch_emd(x, x, device=device)
    assert emd < 1e-5
    assert emd == pytest.approx(approxmatch_numpy(x, x)[0], rel=1e-2, abs=1e-7)
    assert M.exact_emd(x, x) == 0.0


def test_approxmatch_close_to_exact_for_near_matched_clouds(device, rng):
    # clouds that correspond up to a small perturbation (a permuted, jittered copy)
    x = rng.random((256, 3)).astype(np.float32)
    y = (x + rng.normal(0, 0.01, x.shape))[rng.permutation(256)].astype(np.float32)
    approx, exact = M.approxmatch_emd(x, y, device=device), M.exact_emd(x, y)
    assert abs(approx / exact - 1) < 0.02


def test_approxmatch_is_an_upper_bound_of_exact(device):
    # unrelated clouds: approxmatch's soft plan costs more than the optimal assignment
    # (measured +20..35% at N=256-1024, see docs/evaluation.md), never less
    s = trimesh.creation.icosphere(subdivisions=3)
    a = M.sample_surface(s.vertices, s.faces, 256, seed=0, device=device)
    b = 1.1 * M.sample_surface(s.vertices, s.faces, 256, seed=1, device=device)
    approx, exact = M.approxmatch_emd(a, b, device=device), M.exact_emd(a, b)
    assert exact * (1 - 1e-4) <= approx < 1.5 * exact


def test_emd_rejects_unequal_sizes(device, rng):
    with pytest.raises(ValueError, match="equal size"):
        M.approxmatch_emd(rng.random((10, 3)), rng.random((11, 3)), device=device)
    with pytest.raises(ValueError, match="NaN"):
        M.approxmatch_emd(np.full((4, 3), np.nan), np.zeros((4, 3)), device=device)


def test_points_beyond_float32_range_are_refused_naming_the_set(device):
    """float64 points of 1e39 (inf in float32) or 1e20 (squared distances past float32's range)
    gave a finite 3e38 Chamfer distance with at most a NumPy warning (a new user's); refused as
    mesh vertices are (sequence.MAX_COORDINATE), naming the argument of the call."""
    for big in (1e39, 1e20, 2e9):
        far = np.array([[big, 0.0, 0.0], [0.0, 0.0, 0.0]])
        with pytest.raises(ValueError, match=r"^b: point 0 .* lies beyond \+-1e\+09"):
            M.chamfer_distance(np.zeros((2, 3)), far, device=device)
        with pytest.raises(ValueError, match=r"^xyz1: point 0 .* lies beyond"):
            M.approxmatch_emd(far, np.zeros((2, 3)), device=device)
    d = M.chamfer_distance(np.array([[1e8, 0.0, 0.0]]), np.zeros((1, 3)), device=device)  # within: fine
    assert d.value == pytest.approx(1e16, rel=1e-6)


# ------------------------------------------------------------------------------ protocols


def test_dgmesh_protocol_arithmetic_hand_computed(device):
    gt = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]]))
    pred = (np.array([[0, 0, 0], [1, 0, 0], [0, 3, 0], [0, 0, 2]], np.float32),
            np.array([[0, 1, 2], [0, 1, 3]]))
    # gt -> pred squared NN: 0, 0, 1 (from (0,1,0) to (0,0,0))  -> mean 1/3
    # pred -> gt squared NN: 0, 0, 4 ((0,3,0)->(0,1,0)), 4 ((0,0,2)->(0,0,0)) -> mean 2
    r = M.evaluate_mesh_pair(gt, pred, "dgmesh", device=device, emd=False)
    assert r["cd_gt_to_pred"] == pytest.approx(1 / 3)
    assert r["cd_pred_to_gt"] == pytest.approx(2.0)
    assert r["cd"] == pytest.approx(7 / 6)  # averaged over the two directions, not summed


@pytest.mark.parametrize("protocol,n", [("dgmesh", 8192), ("paper", 10000)])
def test_protocol_emd_inputs(device, deformed_icosphere, monkeypatch, protocol, n):
    # spy on approxmatch (8192^2 work is a benchmark, not a unit test): the protocol must pass
    # n seeded area-weighted samples of the ground truth first, then of the prediction
    V, F = deformed_icosphere
    W = V + np.float32(0.05)
    seen = {}

    def spy(x1, x2, device=None):
        seen["x1"], seen["x2"] = np.asarray(x1), np.asarray(x2)
        return 0.125

    monkeypatch.setattr(M, "approxmatch_emd", spy)
    r = M.evaluate_mesh_pair((V, F), (W, F), protocol, seed=4, device=device)
    assert r["emd"] == 0.125
    np.testing.assert_array_equal(seen["x1"], M.sample_surface(V, F, n, seed=4, device=device))
    np.testing.assert_array_equal(seen["x2"], M.sample_surface(W, F, n, seed=5, device=device))
    if protocol == "paper":  # CD on the same samples: compare with a KD-tree on them
        da = cKDTree(seen["x2"]).query(seen["x1"])[0]
        db = cKDTree(seen["x1"]).query(seen["x2"])[0]
        assert r["cd"] == pytest.approx(0.5 * (np.mean(da**2) + np.mean(db**2)), rel=1e-5)


def test_unknown_protocol(device, deformed_icosphere):
    V, F = deformed_icosphere
    with pytest.raises(ValueError, match="unknown protocol"):
        M.evaluate_mesh_pair((V, F), (V, F), "nope", device=device)


def test_sampling_seeds_use_every_bit(device):
    """sample_surface kept a seed's low 31 bits (2**31 + 5 gave seed 5's points, -1 gave
    2**31 - 1's: a new user's); seeds below 2**31 are as before."""
    s = trimesh.creation.icosphere(subdivisions=2)
    V, F = np.asarray(s.vertices), np.asarray(s.faces)
    pts = {k: M.sample_surface(V, F, 64, seed=k, device=device) for k in (5, 2**31 + 5, 2**31 - 1, -1)}
    assert not np.array_equal(pts[5], pts[2**31 + 5]) and not np.array_equal(pts[2**31 - 1], pts[-1])
    np.testing.assert_array_equal(M.sample_surface(V, F, 64, seed=-1, device=device), pts[-1])
    assert M.kernel_seed(5) == 5 and 0 <= M.kernel_seed(2**40) < 2**31


def test_cd_and_emd_do_not_change_far_from_the_origin(device, rng):
    """CD and EMD do not change with a translation. The kernels compute in float32, and a new
    user's points offset by 10^6 gave a CD 10.9x the float64 one (0.16x at 10^7) and an EMD +50 %;
    far from the origin the points are centred in float64 first (the reference: SciPy's k-d tree
    and assignment in float64)."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial.distance import cdist

    a = rng.uniform(-1.0, 1.0, (600, 3))
    b = a + rng.normal(0.0, 3e-3, a.shape)
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    ref_cd = 0.5 * ((d_ab ** 2).mean() + (d_ba ** 2).mean())
    e = a[:256], b[:256]
    D = cdist(*e)
    r, c = linear_sum_assignment(D)
    near_emd = M.approxmatch_emd(*e, device=device)
    assert near_emd < 1.1 * D[r, c].mean()
    for offset in (1e5, 1e6, 1e7):
        shift = np.array([offset, -0.5 * offset, 3.0])
        np.testing.assert_allclose(M.chamfer_distance(a + shift, b + shift, device=device).value, ref_cd, rtol=1e-4)
        np.testing.assert_allclose(M.approxmatch_emd(e[0] + shift, e[1] + shift, device=device), near_emd, rtol=1e-3)
    # a mesh pair far away: the vertex CD of two spheres of radius 1 and 1.1 (every vertex 0.1 off)
    s = trimesh.creation.icosphere(subdivisions=3)
    far = np.array([2e6, 0.0, 0.0])
    out = M.evaluate_mesh_pair((s.vertices + far, s.faces), (1.1 * s.vertices + far, s.faces), "dgmesh", emd=False,
                               device=device)
    np.testing.assert_allclose(out["cd"], 0.01, rtol=1e-4)


def test_dgmesh_vertex_cd_counts_the_vertices_trimesh_load_keeps(device, deformed_icosphere):
    """DG-Mesh's vertex CD reads its meshes with trimesh.load, which keeps the vertices its faces
    use, once per position: vertices no face uses were counted (a new user's 400 left over from a
    removed floater gave the exact surface a CD of 5.4e-4, DG-Mesh's 0). Oracle: trimesh's own
    processing."""
    V, F = deformed_icosphere
    junk = np.random.default_rng(3).uniform(-3.0, 3.0, (50, 3))
    soup = V[F.ravel()]  # every face's own three vertices (a triangle soup)
    pred = (np.vstack([soup, junk]), np.arange(len(F) * 3).reshape(-1, 3))
    kept = M.mesh_vertices(*pred)
    ref = trimesh.Trimesh(*pred, process=True).vertices
    assert len(kept) == len(ref) == len(V)
    np.testing.assert_array_equal(np.unique(kept, axis=0), np.unique(np.asarray(ref, np.float32), axis=0))
    assert M.evaluate_mesh_pair((V, F), pred, "dgmesh", emd=False, device=device)["cd"] < 1e-12


def test_approxmatch_warns_outside_the_scene_sizes_it_is_near_the_exact_emd(device, rng):
    """approxmatch's levels are absolute (1/units^2): for a scene in millimetres it is several
    times the exact EMD and no longer tells a good prediction from a bad one (docs/evaluation.md's
    table); it warns outside EMD_SCALE_RANGE, naming the scale, and not inside."""
    import warnings

    a = rng.uniform(-1.0, 1.0, (64, 3))
    b = a + rng.normal(0.0, 0.01, a.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        M.approxmatch_emd(a, b, device=device)
    for s in (1000.0, 0.05):
        with pytest.warns(UserWarning, match=r"units across: its levels are absolute .* scale the meshes by about"):
            M.approxmatch_emd(s * a, s * b, device=device)
