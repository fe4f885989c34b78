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


# --------------------------------------------------------------------------- coverage through a motion


def _coverage_max(gt_V, V, F):
    """Largest distance of a ground-truth vertex to the converted surface (nearest_surface is
    checked against brute force in test_convert)."""
    from dynmesh_warp.convert import nearest_surface

    return float(nearest_surface((V, F), gt_V, device=DEV).dist.max())


def test_graph_keeps_swinging_arms_covered_through_the_motion():
    """Jumping jacks (arms swing ~150 degrees up from the torso), re-meshed by marching cubes
    every frame: the graph strategy keeps every ground-truth vertex near the converted surface
    on every frame; plain tracking, on the same input, loses the arms (so the check can fail)."""
    from dynmesh_warp.convert import to_fixed_topology
    from dynmesh_warp.remesh import remesh_sequence
    from dynmesh_warp.scenes import articulated_figure

    gt = articulated_figure(frames=14, resolution=40)
    var = remesh_sequence(gt, resolution=48, device=DEV)
    diag = float(np.linalg.norm(np.ptp(gt.V[0], axis=0)))
    inp = max(_coverage_max(gt.V[t], *var.frames[t]) for t in range(gt.num_frames)) / diag
    res = {s: to_fixed_topology(var, strategy=s, device=DEV) for s in ("graph", "tracking")}
    worst = {s: [_coverage_max(gt.V[t], r.V[t], r.F) / diag for t in range(gt.num_frames)]
             for s, r in res.items()}
    assert max(worst["graph"]) < inp + 0.02, (inp, worst["graph"])
    assert max(worst["tracking"]) > max(worst["graph"]) + 0.05, worst
    info = res["graph"].conversion
    assert len(info.coverage) == gt.num_frames and np.isfinite(info.coverage).all()
    # the template comes from the key frame: its converted vertices are that frame's vertices
    K = info.key_frame
    assert np.allclose(res["graph"].V[K], var.frames[K][0], atol=1e-3 * diag)


def test_measure_distances_kernel_matches_brute_force():
    from conftest import brute_nearest

    from dynmesh_warp.kernels import convert as kc

    V, F = icosphere(2, 1.0)
    rng = np.random.default_rng(1)
    Q = rng.normal(size=(300, 3)).astype(np.float32) * 0.8
    pts = wp.array(V, dtype=wp.vec3, device=DEV)
    m = wp.Mesh(points=pts, indices=wp.array(F.reshape(-1), dtype=wp.int32, device=DEV))
    out = wp.empty(len(Q), dtype=float, device=DEV)
    wp.launch(kc.measure_distances_to_mesh, dim=len(Q), inputs=[m.id, wp.array(Q, dtype=wp.vec3, device=DEV), 10.0],
              outputs=[out], device=DEV)
    ref = brute_nearest(Q, V, F)[0]
    assert np.allclose(out.numpy(), ref, atol=1e-5)
    # nothing within max_dist -> max_dist
    wp.launch(kc.measure_distances_to_mesh, dim=len(Q), inputs=[m.id, wp.array(Q + 100, dtype=wp.vec3, device=DEV),
              1.0], outputs=[out], device=DEV)
    assert np.allclose(out.numpy(), 1.0)
