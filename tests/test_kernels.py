"""Kernel tests against independent references (NumPy brute force, trimesh), on Warp's CPU.

- compute_face_normals vs trimesh face normals; degenerate faces give exactly zero.
- closest_point_on_triangle (through a small test kernel) and project_points_to_mesh
  (NearestSurface on a wp.Mesh) vs a brute-force point-triangle distance over ALL triangles.
- a refit BVH answers like a freshly built one (and like brute force) after deformation.
- update_frame_vertices (frame index, blend, velocity, playback modes) vs NumPy, and the
  host twin frame_pair_host vs the device.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
import warp as wp

from conftest import project_to_mesh
from reference import brute_closest_points, brute_nearest, closest_on_triangles
from dynmesh_warp import scenes
from dynmesh_warp.kernels.frames import update_frame_vertices
from dynmesh_warp.kernels.geometry import closest_point_on_triangle, compute_face_normals
from dynmesh_warp.world import PLAYBACK_MODES, frame_pair_host


@wp.kernel
def eval_closest_on_triangles(
    # inputs
    p: wp.array(dtype=wp.vec3),
    a: wp.array(dtype=wp.vec3),
    b: wp.array(dtype=wp.vec3),
    c: wp.array(dtype=wp.vec3),
    # outputs
    weights: wp.array(dtype=wp.vec3),
):
    """Test-only wrapper: barycentric weights of the closest point of triangle i to p[i]."""
    i = wp.tid()
    weights[i] = closest_point_on_triangle(p[i], a[i], b[i], c[i])


def _face_normals(V, F, device):
    pts = wp.array(V, dtype=wp.vec3, device=device)
    idx = wp.array(np.asarray(F, np.int32).reshape(-1), dtype=wp.int32, device=device)
    out = wp.zeros(len(F), dtype=wp.vec3, device=device)
    wp.launch(compute_face_normals, dim=len(F), inputs=[pts, idx], outputs=[out], device=device)
    return out.numpy()


# ---------------------------------------------------------------------------------------------
# face normals
# ---------------------------------------------------------------------------------------------


def test_face_normals_match_trimesh(deformed_icosphere, device):
    V, F = deformed_icosphere
    n = _face_normals(V, F, device)
    ref = trimesh.Trimesh(V.astype(np.float64), F, process=False).face_normals
    np.testing.assert_allclose(n, ref, atol=2e-5)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    # closed and outward: every normal agrees with the direction from the centre
    centroids = V[F].mean(axis=1)
    assert (np.einsum("ij,ij->i", n, centroids) > 0).all()


def test_face_normals_degenerate_faces_are_zero_not_nan(device):
    V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], np.float32)
    F = np.array([[0, 1, 2],   # collinear
                  [0, 0, 3],   # repeated vertex
                  [0, 1, 3]],  # valid, normal +z
                 np.int32)
    n = _face_normals(V, F, device)
    assert np.isfinite(n).all()
    np.testing.assert_array_equal(n[:2], 0.0)
    np.testing.assert_allclose(n[2], [0, 0, 1], atol=1e-7)


# ---------------------------------------------------------------------------------------------
# closest point on one triangle
# ---------------------------------------------------------------------------------------------


def test_closest_point_on_triangle_matches_brute_force(device):
    rng = np.random.default_rng(3)
    K = 4000
    A, B, C = (rng.normal(size=(K, 3)) for _ in range(3))
    # include thin slivers and points around the triangle in every Voronoi region
    A[:200] = B[:200] + 1e-3 * rng.normal(size=(200, 3))
    centre = (A + B + C) / 3
    P = centre + 1.5 * rng.normal(size=(K, 3))
    arr = lambda x: wp.array(x.astype(np.float32), dtype=wp.vec3, device=device)  # noqa: E731
    w = wp.zeros(K, dtype=wp.vec3, device=device)
    Af, Bf, Cf, Pf = (x.astype(np.float32).astype(np.float64) for x in (A, B, C, P))
    wp.launch(eval_closest_on_triangles, dim=K, inputs=[arr(P), arr(A), arr(B), arr(C)], outputs=[w], device=device)
    w = w.numpy().astype(np.float64)
    # valid barycentric weights
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-5)
    assert (w > -1e-5).all()
    got = w[:, :1] * Af + w[:, 1:2] * Bf + w[:, 2:] * Cf
    ref = closest_on_triangles(Pf, Af, Bf, Cf)
    d_got = np.linalg.norm(Pf - got, axis=1)
    d_ref = np.linalg.norm(Pf - ref, axis=1)
    # the closest point is unique on a triangle, so the points must agree, not only distances
    scale = 1.0 + np.linalg.norm(Pf - centre, axis=1)
    assert np.max(np.abs(d_got - d_ref) / scale) < 2e-5
    assert np.max(np.linalg.norm(got - ref, axis=1) / scale) < 5e-3  # slivers are ill-conditioned
    assert np.median(np.linalg.norm(got - ref, axis=1)) < 1e-5


def test_closest_point_vertex_edge_face_regions(device):
    a, b, c = np.array([0, 0, 0.0]), np.array([1, 0, 0.0]), np.array([0, 1, 0.0])
    P = np.array([
        [-1, -1, 0.3],   # vertex a region
        [2, -0.5, 0.0],  # vertex b region
        [-0.2, 3, 1.0],  # vertex c region
        [0.5, -1, 0.0],  # edge ab
        [1, 1, -2.0],    # edge bc
        [-1, 0.5, 0.0],  # edge ca
        [0.2, 0.3, 5.0],  # face interior
    ])
    expect = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5],
                       [0.5, 0.2, 0.3]])
    K = len(P)
    rep = lambda x: wp.array(np.repeat(x[None], K, 0).astype(np.float32), dtype=wp.vec3, device=device)  # noqa: E731
    w = wp.zeros(K, dtype=wp.vec3, device=device)
    wp.launch(eval_closest_on_triangles, dim=K,
              inputs=[wp.array(P.astype(np.float32), dtype=wp.vec3, device=device), rep(a), rep(b), rep(c)],
              outputs=[w], device=device)
    np.testing.assert_allclose(w.numpy(), expect, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# NearestSurface over a whole mesh
# ---------------------------------------------------------------------------------------------


def _check_against_brute(V, F, Q, closest, face, bary, dist, tol=2e-5):
    V64 = V.astype(np.float64)
    cp_all = brute_closest_points(Q, V64[F[:, 0]], V64[F[:, 1]], V64[F[:, 2]])  # (Q, M, 3), ALL faces
    d_all = np.linalg.norm(cp_all - Q[:, None], axis=-1)
    f_ref = d_all.argmin(axis=1)
    d_ref = d_all[np.arange(len(Q)), f_ref]
    p_ref = cp_all[np.arange(len(Q)), f_ref]
    assert (face >= 0).all() and (face < len(F)).all()
    # distances equal to float tolerance (the face may differ only on ties)
    np.testing.assert_allclose(dist, d_ref, atol=tol)
    # barycentrics are valid and reproduce the returned closest point on the returned face
    np.testing.assert_allclose(bary.sum(axis=1), 1.0, atol=1e-5)
    assert (bary > -1e-4).all()
    recon = np.einsum("qk,qkj->qj", bary.astype(np.float64), V64[F[face]])
    np.testing.assert_allclose(recon, closest, atol=tol)
    np.testing.assert_allclose(np.linalg.norm(Q - recon, axis=1), d_ref, atol=tol)
    # the returned face is one of the faces at the minimum distance (ties: shared edges/vertices)
    near_min = d_all <= d_all.min(axis=1, keepdims=True) + tol
    assert near_min[np.arange(len(Q)), face].all()
    # where the closest POINT is unique (all near-minimal faces reach the same point), it matches
    spread = np.array([np.ptp(cp_all[i, near_min[i]], axis=0).max() for i in range(len(Q))])
    unique = spread < 1e-5
    assert unique.mean() > 0.75  # the check is not vacuous
    np.testing.assert_allclose(closest[unique], p_ref[unique], atol=1e-4)


def test_project_points_to_mesh_matches_brute_force(deformed_icosphere, device):
    V, F = deformed_icosphere
    rng = np.random.default_rng(11)
    # points inside, outside, and near the surface
    dirs = rng.normal(size=(600, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    Q = dirs * rng.uniform(0.2, 2.5, size=(600, 1))
    Q = Q.astype(np.float32).astype(np.float64)
    mesh = wp.Mesh(points=wp.array(V, dtype=wp.vec3, device=device),
                   indices=wp.array(F.reshape(-1), dtype=wp.int32, device=device))
    closest, face, bary, dist = project_to_mesh(mesh, Q, device)
    _check_against_brute(V, F, Q, closest, face, bary, dist)


def test_project_points_to_mesh_open_random_surface(device):
    """An open, non-convex sheet with random heights (many edge/vertex-region answers)."""
    V, F = scenes.grid_sheet(12, 2.0)
    rng = np.random.default_rng(5)
    V = V.copy()
    V[:, 2] = rng.normal(0, 0.15, len(V))
    V[:, :2] += rng.uniform(-0.03, 0.03, (len(V), 2))
    Q = rng.uniform([-1.6, -1.6, -0.8], [1.6, 1.6, 0.8], size=(500, 3)).astype(np.float32).astype(np.float64)
    mesh = wp.Mesh(points=wp.array(V, dtype=wp.vec3, device=device),
                   indices=wp.array(F.reshape(-1), dtype=wp.int32, device=device))
    closest, face, bary, dist = project_to_mesh(mesh, Q, device)
    _check_against_brute(V, F, Q, closest, face, bary, dist)


def test_project_points_to_mesh_respects_max_dist(deformed_icosphere, device):
    V, F = deformed_icosphere
    mesh = wp.Mesh(points=wp.array(V, dtype=wp.vec3, device=device),
                   indices=wp.array(F.reshape(-1), dtype=wp.int32, device=device))
    rng = np.random.default_rng(2)
    Q = rng.uniform(-3, 3, size=(300, 3))
    d_ref, _, _ = brute_nearest(Q.astype(np.float32).astype(np.float64), V.astype(np.float64), F)
    max_dist = 0.5
    closest, face, bary, dist = project_to_mesh(mesh, Q, device, max_dist=max_dist)
    far = d_ref > max_dist + 1e-4
    near = d_ref < max_dist - 1e-4
    assert far.any() and near.any()
    assert (face[far] == -1).all()
    np.testing.assert_allclose(dist[far], max_dist)
    np.testing.assert_allclose(closest[far], Q[far], atol=1e-6)
    assert (face[near] >= 0).all()
    np.testing.assert_allclose(dist[near], d_ref[near], atol=2e-5)


# ---------------------------------------------------------------------------------------------
# refit == fresh build after deformation
# ---------------------------------------------------------------------------------------------


def _update_vertices(frames, t, fps, mode, interpolate, points, velocities, device):
    sim_time = wp.array([t], dtype=wp.float64, device=device)
    wp.launch(update_frame_vertices, dim=frames.shape[1],
              inputs=[frames, sim_time, float(fps), int(mode), int(interpolate)],
              outputs=[points, velocities], device=device)
    return points.numpy(), velocities.numpy()


def test_refit_after_deformation_matches_fresh_build(device):
    seq = scenes.wave_bowl(n=24, frames=12)
    frames = wp.array(seq.V, dtype=wp.vec3, device=device)
    idx = wp.array(seq.F.reshape(-1), dtype=wp.int32, device=device)
    points = wp.array(seq.V[0], dtype=wp.vec3, device=device)
    vel = wp.zeros(seq.num_vertices, dtype=wp.vec3, device=device)
    mesh = wp.Mesh(points=points, indices=idx)
    rng = np.random.default_rng(8)
    Q = rng.uniform([-1.1, -1.1, -0.2], [1.1, 1.1, 0.8], size=(250, 3)).astype(np.float32).astype(np.float64)
    before = project_to_mesh(mesh, Q, device)[3]
    for t in (0.13, 5.5 / seq.fps, 0.37):  # several deformations in a row
        P, _ = _update_vertices(frames, t, seq.fps, PLAYBACK_MODES["loop"], True, points, vel, device)
        mesh.refit()
        fresh = wp.Mesh(points=wp.array(P, dtype=wp.vec3, device=device), indices=idx)
        r_refit = project_to_mesh(mesh, Q, device)
        r_fresh = project_to_mesh(fresh, Q, device)
        np.testing.assert_allclose(r_refit[3], r_fresh[3], atol=1e-6)
        same_face = r_refit[1] == r_fresh[1]
        assert same_face.mean() > 0.8  # may differ only on ties (equal distances, checked above)
        np.testing.assert_allclose(r_refit[0][same_face], r_fresh[0][same_face], atol=1e-5)
        _check_against_brute(P, seq.F, Q, *r_refit)
    # the deformation was large enough that a stale BVH would have changed the answers
    assert np.abs(before - r_refit[3]).max() > 0.02


# ---------------------------------------------------------------------------------------------
# frame index / interpolation / playback
# ---------------------------------------------------------------------------------------------


def _reference_frame_pair(t, fps, T, mode):
    s = t * fps
    k = math.floor(s)
    alpha = s - k

    def wrap(j):
        if mode == "clamp":
            return min(max(j, 0), T - 1)
        if mode == "pingpong":
            seq = list(range(T)) + list(range(T - 2, 0, -1))  # 0..T-1..1, period 2(T-1)
            return seq[j % len(seq)]
        return j % T

    return wrap(k), wrap(k + 1), alpha


FPS = 4.0  # a power of two: frame boundaries k / FPS are exact in float32 and float64
TIMES = [0.0, 0.1, 0.25, 0.5, 0.6, 0.99, 1.0, 1.1, 1.25, 1.3, 1.74, 1.75, 2.0, 2.6, 3.5, 4.3, 7.0]


@pytest.mark.parametrize("mode", ["loop", "clamp", "pingpong"])
@pytest.mark.parametrize("interpolate", [True, False])
def test_update_frame_vertices_matches_numpy(mode, interpolate, device):
    rng = np.random.default_rng(4)
    T, N = 6, 37  # duration T / FPS = 1.5 s; TIMES run well past the end
    V = rng.normal(size=(T, N, 3)).astype(np.float32)
    frames = wp.array(V, dtype=wp.vec3, device=device)
    points = wp.zeros(N, dtype=wp.vec3, device=device)
    vel = wp.zeros(N, dtype=wp.vec3, device=device)
    for t in TIMES:
        P, U = _update_vertices(frames, t, FPS, PLAYBACK_MODES[mode], interpolate, points, vel, device)
        k0, k1, alpha = _reference_frame_pair(t, FPS, T, mode)
        a, b = V[k0].astype(np.float64), V[k1].astype(np.float64)
        P_ref = a + alpha * (b - a) if interpolate else a
        U_ref = (b - a) * FPS if k1 != k0 else np.zeros_like(a)
        np.testing.assert_allclose(P, P_ref, atol=1e-5, err_msg=f"t={t} mode={mode}")
        np.testing.assert_allclose(U, U_ref, atol=1e-4, err_msg=f"t={t} mode={mode}")
        assert frame_pair_host(t, FPS, T, PLAYBACK_MODES[mode]) == pytest.approx((k0, k1, alpha))


def test_update_frame_vertices_on_boundaries_exact(device):
    """Exactly on frame k's start the position is frame k itself (interpolated or not)."""
    rng = np.random.default_rng(6)
    T, N = 5, 10
    V = rng.normal(size=(T, N, 3)).astype(np.float32)
    frames = wp.array(V, dtype=wp.vec3, device=device)
    points = wp.zeros(N, dtype=wp.vec3, device=device)
    vel = wp.zeros(N, dtype=wp.vec3, device=device)
    for k in range(2 * T + 1):
        for interp in (True, False):
            P, U = _update_vertices(frames, k / FPS, FPS, PLAYBACK_MODES["loop"], interp, points, vel, device)
            np.testing.assert_array_equal(P, V[k % T])
            np.testing.assert_allclose(U, (V[(k + 1) % T] - V[k % T]) * FPS, rtol=1e-6, atol=1e-5)


def test_interpolated_positions_are_continuous_across_the_loop_seam(device):
    rng = np.random.default_rng(9)
    T, N, fps = 8, 20, 24.0
    V = rng.normal(size=(T, N, 3)).astype(np.float32)
    frames = wp.array(V, dtype=wp.vec3, device=device)
    points = wp.zeros(N, dtype=wp.vec3, device=device)
    vel = wp.zeros(N, dtype=wp.vec3, device=device)
    period = T / fps
    eps = 1e-5
    before, _ = _update_vertices(frames, period - eps, fps, PLAYBACK_MODES["loop"], True, points, vel, device)
    after, _ = _update_vertices(frames, period + eps, fps, PLAYBACK_MODES["loop"], True, points, vel, device)
    np.testing.assert_allclose(before, V[0], atol=1e-3)
    np.testing.assert_allclose(after, V[0], atol=1e-3)


def _device_frame_pairs(times, fps, T, mode, device):
    """(k0, k1) the kernel uses at each time, read back from a sequence whose frame k has all
    vertices at (k, 0, 0): interpolate off gives k0; the velocity gives k1 - k0."""
    V = np.zeros((T, 1, 3), np.float32)
    V[:, 0, 0] = np.arange(T)
    frames = wp.array(V, dtype=wp.vec3, device=device)
    points = wp.zeros(1, dtype=wp.vec3, device=device)
    vel = wp.zeros(1, dtype=wp.vec3, device=device)
    out = []
    for t in times:
        P, U = _update_vertices(frames, t, fps, mode, False, points, vel, device)
        k0 = int(round(P[0, 0]))
        out.append((k0, k0 + int(round(U[0, 0] / fps))))
    return out


@pytest.mark.parametrize("fps", [24.0, 30.0, 48.0, 240.0])
def test_a_clock_summed_from_dt_starts_each_frame_on_its_boundary(fps, device):
    """The world's clock adds dt each step, so a step meant to start at k / fps mostly starts a
    few ulps before it (dt = 1 / 240: on 60 % of the boundary steps, a new user found). The pair
    is then still (k, k + 1), on the device and on the host, not (k - 1, k) at alpha ~ 1, whose
    velocity is the previous interval's; a time a step after a boundary is unchanged."""
    T, dt = 1000, 1.0 / 240.0
    per = round(1.0 / (fps * dt)) if fps * dt < 1 else 1
    t, times, want = 0.0, [], []
    for n in range(1, 600):
        t += dt  # float64, as the world's clock
        if n % per == 0:
            times += [t, t + 0.5 * dt]
            want += [n // per, n // per]
    below = sum(math.floor(x * fps) < k for x, k in zip(times[::2], want[::2]))
    assert below > 0.3 * len(want) / 2  # the case: most of these sums land below the boundary
    host = [frame_pair_host(x, fps, T, PLAYBACK_MODES["clamp"]) for x in times]
    assert [h[0] for h in host] == want
    assert all(0.0 <= h[2] < 1e-6 for h in host[::2])
    assert _device_frame_pairs(times, fps, T, PLAYBACK_MODES["clamp"], device) == [(k, k + 1) for k in want]


@pytest.mark.parametrize("mode", ["loop", "clamp", "pingpong"])
def test_frame_pair_host_matches_device(mode, device):
    T = 7
    fps = 24.0
    rng = np.random.default_rng(1)
    # away from boundaries (float32 rounding of t * fps cannot flip the frame)
    k = rng.integers(0, 5 * T, 60)
    times = (k + rng.uniform(0.01, 0.99, 60)) / fps
    dev = _device_frame_pairs(times, fps, T, PLAYBACK_MODES[mode], device)
    host = [frame_pair_host(float(t), fps, T, PLAYBACK_MODES[mode])[:2] for t in times]
    assert dev == host
