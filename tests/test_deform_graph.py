"""The ``graph`` conversion strategy: deformation graph construction and its kernels against
NumPy references, and coverage on an articulated motion."""

import numpy as np
import warp as wp

from dynmesh_warp.deform_graph import GraphFitter, build_deformation_graph, polar_rotations
from dynmesh_warp.scenes import icosphere

DEV = "cpu"


def test_graph_weights_and_nodes():
    V, F = icosphere(3, 1.0)
    g = build_deformation_graph(V, F, spacing=0.4, k=4)
    assert 4 <= g.num_nodes < len(V)
    assert np.allclose(g.node_weight.sum(axis=1), 1.0, atol=1e-5)
    assert (g.node_weight >= 0).all()
    # every vertex within 2 x spacing (in space) of one of its nodes
    d = np.linalg.norm(V[:, None] - g.node_rest[g.node_index], axis=2).min(axis=1)
    assert d.max() <= 2 * 0.4 + 1e-6
    assert len(g.edges) > 0


def test_skinning_kernel_matches_numpy():
    V, F = icosphere(2, 1.0)
    g = build_deformation_graph(V, F, spacing=0.5, k=4)
    rng = np.random.default_rng(0)
    R = polar_rotations(rng.normal(size=(g.num_nodes, 3, 3)))
    P = g.node_rest + 0.1 * rng.normal(size=(g.num_nodes, 3))
    fit = GraphFitter(g, V, F, wp.get_device(DEV), 10.0, {"max_normal_angle": 60.0})
    X = fit.skin(R, P).numpy()
    idx, w = g.node_index, g.node_weight
    ref = np.einsum("nk,nkab,nkb->na", w, R[idx], V[:, None] - g.node_rest[idx]) + np.einsum(
        "nk,nka->na", w, P[idx])
    assert np.allclose(X, ref, atol=1e-5)


def test_graph_fit_recovers_a_rigid_motion():
    V, F = icosphere(3, 0.5)
    V = (V * (1.0 + 0.15 * np.sin(4 * V[:, :1]))).astype(np.float32)  # not rotationally symmetric
    a = 0.15
    Rg = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    V1 = V @ Rg.T + np.array([0.05, 0.02, 0.0])
    dev = wp.get_device(DEV)
    g = build_deformation_graph(V, F, spacing=0.25, k=4)
    fit = GraphFitter(g, V, F, dev, 10.0, {"max_normal_angle": 60.0})
    pts = wp.array(V1.astype(np.float32), dtype=wp.vec3, device=dev)
    idx = wp.array(F.reshape(-1), dtype=wp.int32, device=dev)
    from dynmesh_warp.remesh import vertex_normals

    fn = wp.array(vertex_normals(V1, F).astype(np.float32), dtype=wp.vec3, device=dev)
    frame = (wp.Mesh(points=pts, indices=idx), pts, idx, fn)
    R0 = np.repeat(np.eye(3)[None], g.num_nodes, 0)
    from dynmesh_warp.convert import nearest_surface

    before = nearest_surface((V1, F), V, device=DEV).dist.mean()
    R, P = fit.fit(frame, R0, g.node_rest.copy(), 10, 10.0, 0.3, 0.01)
    X = fit.points.numpy()
    assert nearest_surface((V1, F), X, device=DEV).dist.mean() < 0.3 * before
