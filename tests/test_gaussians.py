"""Gaussians bound to mesh faces, on Warp's CPU, against independent NumPy/SciPy references.

- update_gaussians vs a NumPy re-implementation of the binding (face frame, sqrt-area scale,
  barycentric centre + normal offset, R_face R_local, R diag(s^2) R^T) on a non-rigid deformation.
- a random rigid motion + uniform scale of the mesh moves every Gaussian exactly like the mesh:
  centre = s R c0 + t, covariance = s^2 R C0 R^T, world scale = s * scale0.
- covariances = R diag(s^2) R^T with R from the output quaternions (SciPy).
- bind_splats picks the nearest face (brute force over all faces) and reproduces the cloud.
- generation is area-weighted (chi-square-free binomial bound), seeded, inside the faces,
  coloured from vertex colours.
- the float16 viewer covariance clamp keeps thin Gaussians positive definite.
- the post-step hook keeps the Gaussians on the World's current surface.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scipy.spatial.transform import Rotation

from reference import brute_closest_points, brute_nearest
from dynmesh_warp.gaussians import bind_splats, generate_gaussians, quat_xyzw_to_wxyz
from dynmesh_warp.splat_io import SplatCloud


def _arr(V, device):
    return wp.array(np.asarray(V, np.float32), dtype=wp.vec3, device=device)


def _idx(F, device):
    return wp.array(np.asarray(F, np.int32).reshape(-1), dtype=wp.int32, device=device)


def numpy_update(V, F, face, bary, offset, local_xyzw, local_scale):
    """Independent float64 reference of the binding."""
    V = V.astype(np.float64)
    p0, p1, p2 = (V[F[face, k]] for k in range(3))
    a = p1 - p0
    n = np.cross(a, p2 - p0)
    e1 = a / np.linalg.norm(a, axis=1, keepdims=True)
    e3 = n / np.linalg.norm(n, axis=1, keepdims=True)
    e2 = np.cross(e3, e1)
    Rf = np.stack([e1, e2, e3], axis=2)  # columns
    sf = np.sqrt(0.5 * np.linalg.norm(n, axis=1))
    c = bary[:, :1] * p0 + bary[:, 1:2] * p1 + bary[:, 2:] * p2 + (offset * sf)[:, None] * e3
    Rw = Rf @ Rotation.from_quat(local_xyzw).as_matrix()
    s = local_scale * sf[:, None]
    cov = Rw @ (s[:, :, None] ** 2 * np.eye(3)) @ np.transpose(Rw, (0, 2, 1))
    return c, Rw, s, cov


def _random_cloud(V, F, G, rng, spread=0.05):
    """World splats near the surface: random centres, rotations, anisotropic scales."""
    f = rng.integers(0, len(F), G)
    b = rng.dirichlet([1, 1, 1], G)
    P = np.einsum("gk,gkc->gc", b, V[F[f]]) + rng.normal(0, spread, (G, 3))
    q = Rotation.random(G, random_state=rng.integers(1 << 31)).as_quat()  # xyzw
    scales = np.exp(rng.uniform(np.log(1e-3), np.log(5e-2), (G, 3)))
    return SplatCloud.from_activated(P, scales, quat_xyzw_to_wxyz(q) * 2.5, rng.random((G, 3)), rng.random(G))


def _binding_np(g):
    b = g.binding
    return (b.face.numpy(), b.bary.numpy().astype(np.float64), b.offset.numpy().astype(np.float64),
            b.local_rotation.numpy().astype(np.float64), b.local_scale.numpy().astype(np.float64))


@pytest.fixture
def bound(deformed_icosphere, rng, device):
    V, F = deformed_icosphere
    cloud = _random_cloud(V, F, 300, rng)
    return V, F, cloud, bind_splats(cloud, V, F, device=device)


def test_update_matches_numpy_on_nonrigid_deformation(bound, rng, device):
    V, F, _, g = bound
    V1 = (V * (1 + 0.3 * rng.random((len(V), 1))) + rng.normal(0, 0.05, V.shape)).astype(np.float32)
    g.update(_arr(V1, device), _idx(F, device))
    c, Rw, s, cov = numpy_update(V1, F, *_binding_np(g))
    out = g.numpy()
    np.testing.assert_allclose(out["centers"], c, atol=2e-5)
    np.testing.assert_allclose(out["scales"], s, rtol=2e-5, atol=1e-8)
    np.testing.assert_allclose(Rotation.from_quat(out["rotations_xyzw"]).as_matrix(), Rw, atol=2e-5)
    np.testing.assert_allclose(out["covariances"], cov, atol=1e-6 * np.abs(cov).max())


def test_rigid_motion_and_uniform_scale_carry_gaussians_exactly(bound, rng, device):
    V, F, _, g = bound
    g.update(_arr(V, device), _idx(F, device))
    out0 = g.numpy()
    R = Rotation.random(random_state=3).as_matrix()
    s, t = 1.7, np.array([0.4, -1.2, 2.0])
    V1 = (s * V.astype(np.float64) @ R.T + t).astype(np.float32)
    g.update(_arr(V1, device), _idx(F, device))
    out1 = g.numpy()
    c0 = out0["centers"].astype(np.float64)
    np.testing.assert_allclose(out1["centers"], s * c0 @ R.T + t, atol=3e-5)
    C0 = out0["covariances"].astype(np.float64)
    np.testing.assert_allclose(out1["covariances"], s**2 * R @ C0 @ R.T, atol=2e-6 * np.abs(s**2 * C0).max())
    np.testing.assert_allclose(out1["scales"], s * out0["scales"], rtol=3e-5)
    R0 = Rotation.from_quat(out0["rotations_xyzw"]).as_matrix()
    np.testing.assert_allclose(Rotation.from_quat(out1["rotations_xyzw"]).as_matrix(), R @ R0, atol=3e-5)
    # same barycentric point + same normal offset (in face scales) in the moved face
    face, bary, off, _, _ = _binding_np(g)
    n1 = np.cross(V1[F[face, 1]] - V1[F[face, 0]], V1[F[face, 2]] - V1[F[face, 0]]).astype(np.float64)
    sf1 = np.sqrt(0.5 * np.linalg.norm(n1, axis=1))
    foot = np.einsum("gk,gkc->gc", bary, V1[F[face]].astype(np.float64))
    np.testing.assert_allclose(out1["centers"], foot + (off * sf1)[:, None] * n1 / (2 * sf1[:, None] ** 2), atol=3e-5)


def test_covariance_is_R_diag_s2_RT(bound, device):
    V, F, _, g = bound
    g.update(_arr(V, device), _idx(F, device))
    out = g.numpy()
    R = Rotation.from_quat(out["rotations_xyzw"].astype(np.float64)).as_matrix()
    s = out["scales"].astype(np.float64)
    ref = np.einsum("gij,gj,gkj->gik", R, s**2, R)
    np.testing.assert_allclose(out["covariances"], ref, atol=1e-6 * np.abs(ref).max())
    assert np.allclose(np.linalg.norm(out["rotations_xyzw"], axis=1), 1.0, atol=1e-5)


def test_bind_picks_nearest_face_and_reproduces_rest_cloud(bound, device):
    V, F, cloud, g = bound
    P = cloud.positions.astype(np.float64)
    dmin, _, _ = brute_nearest(P, V, F)
    face = g.binding.face.numpy()
    A, B, C = V[F[face, 0]], V[F[face, 1]], V[F[face, 2]]
    cp = np.stack([brute_closest_points(P[i:i + 1], A[i:i + 1], B[i:i + 1], C[i:i + 1])[0, 0] for i in range(len(P))])
    d_chosen = np.linalg.norm(P - cp, axis=1)
    np.testing.assert_allclose(d_chosen, dmin, atol=2e-5)
    # at the rest pose the bound Gaussians are the input cloud
    g.update(_arr(V, device), _idx(F, device))
    out = g.numpy()
    np.testing.assert_allclose(out["centers"], P, atol=2e-5)
    R = Rotation.from_quat(np.roll(cloud.rotations_wxyz(), -1, axis=1)).as_matrix()
    ref = np.einsum("gij,gj,gkj->gik", R, cloud.scales() ** 2, R)
    np.testing.assert_allclose(out["covariances"], ref, atol=1e-5 * np.abs(ref).max())
    np.testing.assert_allclose(g.binding.rgb, cloud.rgb(), atol=1e-6)


def test_generation_area_weighted_seeded_and_coloured(device):
    # two triangles, areas 1:3
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 1], [5, 0, 1], [2, 1, 1]], np.float32)
    F = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
    colors = np.random.default_rng(0).random((6, 3))
    n = 20000
    g = generate_gaussians(V, F, count=n, seed=5, vertex_colors=colors, device=device)
    face = g.binding.face.numpy()
    # systematic sampling: each face gets its area share to within one Gaussian (no clumping)
    assert abs(int((face == 1).sum()) - 0.75 * n) <= 1
    b = g.binding.bary.numpy().astype(np.float64)
    assert (b >= -1e-6).all() and np.allclose(b.sum(1), 1, atol=1e-5)
    # uniform inside the face: mean barycentric -> (1/3, 1/3, 1/3)
    assert np.abs(b.mean(0) - 1 / 3).max() < 0.01
    np.testing.assert_allclose(g.binding.rgb, np.einsum("gk,gkc->gc", b, colors[F[face]]), atol=1e-5)
    g2 = generate_gaussians(V, F, count=n, seed=5, device=device)
    assert np.array_equal(g2.binding.face.numpy(), face)
    g3 = generate_gaussians(V, F, count=n, seed=6, device=device)
    assert not np.array_equal(g3.binding.bary.numpy(), g.binding.bary.numpy())  # the seed moves the samples
    # centres lie on the surface, discs are flat along the face normal
    g.update(_arr(V, device), _idx(F, device))
    out = g.numpy()
    assert np.allclose(out["centers"][face == 1, 2], 1.0, atol=1e-6)
    assert np.allclose(out["centers"][face == 0, 2], 0.0, atol=1e-6)
    assert np.allclose(out["covariances"][:, 2, 2], (0.1 * out["scales"][:, 0]) ** 2, rtol=1e-4)
    with pytest.raises(ValueError, match="vertex_colors"):
        generate_gaussians(V, F, count=10, vertex_colors=colors[:3], device=device)


def test_float16_clamp_keeps_thin_gaussians_positive_definite(device, rng):
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    F = np.array([[0, 1, 2]], np.int32)
    G = 200
    q = Rotation.random(G, random_state=1).as_quat()
    scales = np.tile([0.05, 0.02, 1e-7], (G, 1))
    cloud = SplatCloud.from_activated(rng.random((G, 3)) * 0.3, scales, quat_xyzw_to_wxyz(q), np.ones((G, 3)),
                                      np.full(G, 0.5))
    g = bind_splats(cloud, V, F, device=device)
    g.update(_arr(V, device), _idx(F, device))
    cov = g.numpy()["covariances"]
    naive = cov[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]].astype(np.float16)

    def full(tri):
        t = tri.astype(np.float64)
        return np.stack([t[:, [0, 1, 2]], t[:, [1, 3, 4]], t[:, [2, 4, 5]]], axis=1)

    assert (np.linalg.eigvalsh(full(naive))[:, 0] <= 0).any()  # the problem is real
    min_scale = 1e-3
    clamped = g.splat_covariances_f16(min_scale=min_scale, min_ratio=0.05)
    ev = np.linalg.eigvalsh(full(clamped))
    assert (ev[:, 0] > 0).all()
    # clamped smallest variance = (0.05 * 0.05)^2 = 2.5e-3 smax^2; float16 rounding moves an
    # eigenvalue by at most 3 * 2^-11 * smax^2 ~ 1.5e-3 smax^2
    smax2 = 0.05**2
    assert (ev[:, 0] > 0.9e-3 * smax2).all() and (ev[:, 0] < 4.1e-3 * smax2).all()
    np.testing.assert_allclose(np.sqrt(ev[:, 2]), 0.05, rtol=2e-3)


def test_viewer_covariances_of_huge_splats_stay_in_float16(device):
    """A 300 m background splat (log-scale 5.7, a real capture's) was sent to the viewer as inf
    (float16 holds 65,504): its std devs are clamped to F16_MAX_STD, finite and positive definite;
    small splats are unchanged."""
    from dynmesh_warp.kernels.gaussians import F16_MAX_STD
    from dynmesh_warp.scenes import grid_sheet

    V, F = grid_sheet(6, 1.0)
    cloud = SplatCloud.from_activated(centers=[[0.2, 0.2, 0.01], [0.5, 0.5, 0.01]],
                                      scales=[[300.0, 300.0, 1.0], [0.01, 0.02, 0.005]],
                                      rotations_wxyz=[[1, 0, 0, 0], [1, 0, 0, 0]], rgb=[[1, 0, 0]] * 2,
                                      opacities=[0.5, 0.5])
    g = bind_splats(cloud, V, F, device=device)
    g.update(_arr(V, device), _idx(F, device))
    c = g.splat_covariances_f16(min_scale=1e-4, min_ratio=0.0).astype(np.float64)
    assert np.isfinite(c).all()
    np.testing.assert_allclose(c[0, [0, 3, 5]], [float(F16_MAX_STD) ** 2, float(F16_MAX_STD) ** 2, 1.0], rtol=2e-3)
    np.testing.assert_allclose(c[1, [0, 3, 5]], [1e-4, 4e-4, 2.5e-5], rtol=2e-3)


def test_post_step_hook_follows_world_surface(device):
    from dynmesh_warp import load_scene_config
    from dynmesh_warp.gaussians import gaussians_for_world
    from dynmesh_warp.scene import build_world

    cfg = load_scene_config(data={"name": "t", "surface": {"source": "builtin:pulsing_blob", "params": {"subdivisions": 2}},
                                  "spheres": {"count": 2, "radius": 0.08}, "gaussians": {"count": 500, "seed": 2}})
    world = build_world(cfg, device=device)
    g = gaussians_for_world(world, cfg)
    assert g.count == 500
    for _ in range(7):
        world.step()
    V = world.state.points.numpy()
    F = world.model.surface.sequence.F
    c, _, _, cov = numpy_update(V, F, *_binding_np(g))
    np.testing.assert_allclose(g.numpy()["centers"], c, atol=2e-5)
    first = world.model.surface.sequence.V[0]
    assert np.abs(V - first).max() > 1e-3  # the surface did move
    # and where the surface moves between steps: reset() and set_time() (a new user's splats stayed
    # where the last step left them while the spheres and the surface went back to t = 0)
    for move in (world.reset, lambda: world.set_time(0.13)):
        move()
        V = world.surface_points().numpy()
        c, _, _, _ = numpy_update(V, F, *_binding_np(g))
        np.testing.assert_allclose(g.numpy()["centers"], c, atol=2e-5)
    assert np.abs(V - first).max() > 1e-3


def test_shading_follows_the_surface_normal(device):
    """shaded_rgb: Gaussians on a flat sheet (normal +z) are fully lit by light along -z and get
    the ambient term alone for light along x; on a tilted sheet the factor is |cos| of the tilt."""
    from dynmesh_warp.gaussians import shaded_rgb
    from dynmesh_warp.scenes import grid_sheet

    V, F = grid_sheet(8, 1.0)
    g = generate_gaussians(V, F, count=200, seed=1, color=(0.8, 0.6, 0.4), device=device)
    g.update(wp.array(V, dtype=wp.vec3, device=device), wp.array(F.reshape(-1), dtype=wp.int32, device=device))
    np.testing.assert_allclose(shaded_rgb(g, (0, 0, -1)), g.binding.rgb, atol=1e-4)
    np.testing.assert_allclose(shaded_rgb(g, (1, 0, 0)), 0.35 * g.binding.rgb, atol=1e-4)
    tilt = np.radians(30.0)
    Rx = Rotation.from_rotvec([tilt, 0, 0]).as_matrix()
    g.update(wp.array((V @ Rx.T).astype(np.float32), dtype=wp.vec3, device=device),
             wp.array(F.reshape(-1), dtype=wp.int32, device=device))
    np.testing.assert_allclose(shaded_rgb(g, (0, 0, -1)), (0.35 + 0.65 * np.cos(tilt)) * g.binding.rgb, atol=1e-3)


def test_gaussians_for_world_names_what_to_call_for_another_simulation():
    """gaussians_for_world attaches to a World's step hooks; a simulation without them (a
    NewtonWorld failed with AttributeError 'Model' object has no attribute 'surface') gets a
    TypeError naming gaussians_for_surface."""
    from types import SimpleNamespace

    from dynmesh_warp.gaussians import gaussians_for_world

    newtonish = SimpleNamespace(model=SimpleNamespace(), surface=SimpleNamespace(sequence=None), device="cpu")
    with pytest.raises(TypeError, match=r"a SimpleNamespace takes no step hooks; use gaussians_for_surface\(world"):
        gaussians_for_world(newtonish)


def test_splats_bound_far_from_their_mesh_are_warned_of():
    """Splats in another frame than the mesh (a new user's y-up capture: the mesh turned z-up by
    surface.up_axis, the splats not) bound 2 m off a 2 m mesh without a word; now warned of, naming
    the fields that turn the mesh only. Splats on the surface say nothing."""
    import warnings

    from dynmesh_warp.scenes import icosphere

    V, F = icosphere(2, 1.0)
    rng = np.random.default_rng(0)
    G = 200
    on = V[rng.integers(0, len(V), G)] * 1.01
    q = rng.normal(size=(G, 4))
    mk = lambda P: SplatCloud.from_activated(P, np.full((G, 3), 0.01), q, rng.random((G, 3)),  # noqa: E731
                                            np.full(G, 0.5))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bind_splats(mk(on), V, F, device="cpu")
    with pytest.warns(UserWarning, match=r"splats lie far from the mesh .* surface\.up_axis, scale and translate"):
        bind_splats(mk(on + [0.0, 0.0, 3.0]), V, F, device="cpu")


def test_a_splat_by_a_face_without_area_binds_to_a_face_with_one():
    """A reconstruction's face whose corners sit at one point at the rest pose (it opens later):
    a splat nearest it was bound to it, kept no size (std dev 0: invisible) and moved onto a
    corner (a new user's). Faces without area are left out of the binding: the rest pose is
    reproduced (centre and std dev), and the splat follows a face with an area."""
    from dynmesh_warp.gaussians import bind_splats
    from dynmesh_warp.splat_io import SplatCloud

    n = 11
    g = np.linspace(-1, 1, n)
    X, Y = np.meshgrid(g, g)
    Fg = [[i * n + j, i * n + j + 1, i * n + j + n + 1] for i in range(n - 1) for j in range(n - 1)]
    Fg += [[i * n + j, i * n + j + n + 1, i * n + j + n] for i in range(n - 1) for j in range(n - 1)]
    p = np.array([0.05, 0.05, 0.02])
    V0 = np.concatenate([np.c_[X.ravel(), Y.ravel(), np.zeros(n * n)], [p, p, p]]).astype(np.float32)
    F = np.concatenate([Fg, [[n * n, n * n + 1, n * n + 2]]]).astype(np.int32)
    idx = wp.array(F.reshape(-1), dtype=wp.int32, device="cpu")
    for c in (p, p + [0.0, 0.0, 0.01]):
        cloud = SplatCloud.from_activated(centers=[c], scales=[[0.01, 0.01, 0.01]], rotations_wxyz=[[1, 0, 0, 0]],
                                          rgb=[[1, 0, 0]], opacities=[0.9])
        gs = bind_splats(cloud, V0, F, device="cpu")
        assert gs.binding.face.numpy()[0] != len(F) - 1  # not the face without area
        gs.update(wp.array(V0, dtype=wp.vec3, device="cpu"), idx)
        st = gs.numpy()
        np.testing.assert_allclose(st["centers"][0], c, atol=1e-6)
        np.testing.assert_allclose(st["scales"][0], 0.01, rtol=1e-5)
    with pytest.raises(ValueError, match="every face of the mesh has zero area"):
        bind_splats(cloud, np.zeros((3, 3), np.float32) + [0.0, 0.0, 1.0], np.array([[0, 1, 2]]), device="cpu")
