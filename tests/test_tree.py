"""The implicit tree (kernels/tree.py): its refit against boxes computed in NumPy, its
nearest-first query against brute force over every face (NumPy) and against
wp.mesh_query_point_sign_normal (the refit collider's query), on random deforming meshes."""

import numpy as np
import pytest
import trimesh
import warp as wp

from reference import brute_closest_points, brute_nearest
from dynmesh_warp.kernels.tree import (allocate_implicit_tree, build_implicit_tree, find_closest_on_lerp_tree,
                                       find_closest_on_tree, refit_tree, update_tree_slot)


def _deforming_mesh(rng, subdivisions=3):
    """Two frames of a noisy sphere (a closed surface with folds in the noise) [m]."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    V0 = s.vertices * (1.0 + 0.15 * rng.standard_normal((len(s.vertices), 1)))
    V1 = V0 + 0.05 * rng.standard_normal(V0.shape) + np.array([0.1, 0.0, -0.05])
    return np.stack([V0, V1]).astype(np.float32), s.faces.astype(np.int32)


def _numpy_boxes(Vt, F, tree_faces, leaf_faces, depth):
    P = 1 << depth
    lo = np.full((2 * P, 3), 1e30, np.float32)
    hi = np.full((2 * P, 3), -1e30, np.float32)
    for leaf in range(P):
        f = tree_faces[leaf * leaf_faces:(leaf + 1) * leaf_faces]
        f = f[f >= 0]
        if f.size:
            pts = Vt[F[f]].reshape(-1, 3)
            lo[P + leaf], hi[P + leaf] = pts.min(0), pts.max(0)
    for i in range(P - 1, 0, -1):
        lo[i] = np.minimum(lo[2 * i], lo[2 * i + 1])
        hi[i] = np.maximum(hi[2 * i], hi[2 * i + 1])
    return lo, hi


@pytest.mark.parametrize("leaf_faces,levels_per_launch", [(1, 4), (4, 3), (3, 2)])
def test_tree_refit_equals_numpy_boxes(device, leaf_faces, levels_per_launch):
    """Every node's box after a refit at a blend equals the box of its faces' blended vertices
    (leaves) and the union of its children's (inner nodes), computed in NumPy; padding leaves
    stay empty; every face appears once in tree order."""
    rng = np.random.default_rng(1)
    frames, F = _deforming_mesh(rng)
    tree_faces, tree_indices, depth = build_implicit_tree(frames[0], F, leaf_faces)
    assert sorted(tree_faces[tree_faces >= 0].tolist()) == list(range(len(F)))
    assert (1 << depth) * leaf_faces >= len(F) > (1 << (depth - 1)) * leaf_faces or depth == 1
    P = 1 << depth
    lo = wp.zeros(2 * P, dtype=wp.vec3, device=device)
    hi = wp.zeros(2 * P, dtype=wp.vec3, device=device)
    alpha = 0.37
    refit_tree(wp.array(frames, dtype=wp.vec3, device=device), wp.array(tree_indices, device=device),
               wp.array(tree_faces, device=device), leaf_faces, depth, 0, 1, alpha, lo, hi, levels_per_launch)
    Vt = (1 - alpha) * frames[0] + alpha * frames[1]
    ref_lo, ref_hi = _numpy_boxes(Vt, F, tree_faces, leaf_faces, depth)
    np.testing.assert_allclose(lo.numpy()[1:], ref_lo[1:], atol=2e-6)
    np.testing.assert_allclose(hi.numpy()[1:], ref_hi[1:], atol=2e-6)


@wp.kernel
def _mesh_query(mesh: wp.uint64, points: wp.array[wp.vec3], reach: float, dist: wp.array[float],
                face: wp.array[wp.int32]):
    s = wp.tid()
    q = wp.mesh_query_point_sign_normal(mesh, points[s], reach)
    d = reach
    f = int(-1)
    if q.result:
        d = wp.length(points[s] - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
        f = q.face
    dist[s] = d
    face[s] = f


def test_tree_query_equals_brute_force_and_mesh_query(device):
    """Closest distance within reach of points near and far from a deforming surface, at a blend
    of two frames: equal to the brute-force closest point over every face (tests/reference.py) (and to reach
    with face -1 beyond it) and to wp.mesh_query_point_sign_normal's distance and face (ties:
    the faces found lie at the same distance)."""
    rng = np.random.default_rng(2)
    frames, F = _deforming_mesh(rng)
    alpha = 0.61
    Vt = ((1 - alpha) * frames[0] + alpha * frames[1]).astype(np.float32)
    dev = device
    tree = allocate_implicit_tree(frames[0], F, 4, dev)  # built at another pose
    depth, P, lo, hi = tree.depth, tree.num_leaves, tree.node_lower, tree.node_upper
    fr = wp.array(frames, dtype=wp.vec3, device=dev)
    ti, tf = tree.indices, tree.faces
    refit_tree(fr, ti, tf, 4, depth, 0, 1, alpha, lo, hi)
    # points: on / near the surface (both sides) and far away
    mesh_t = trimesh.Trimesh(Vt, F, process=False)
    on, _ = trimesh.sample.sample_surface(mesh_t, 300, seed=3)
    nrm = rng.standard_normal(on.shape)
    pts = np.concatenate([on + 0.05 * nrm, rng.uniform(-2.5, 2.5, (200, 3))]).astype(np.float32)
    reach = 0.3
    n = len(pts)
    d_tree = wp.zeros(n, dtype=float, device=dev)
    f_tree = wp.zeros(n, dtype=wp.int32, device=dev)
    wp.launch(find_closest_on_tree, n, inputs=[fr, ti, tf, lo, hi, 4, P, 0, 1, alpha,
                                               wp.array(pts, dtype=wp.vec3, device=dev), reach, 1e-6],
              outputs=[d_tree, f_tree], device=dev)
    d_tree, f_tree = d_tree.numpy(), f_tree.numpy()
    # brute force over every face
    d_bf, _, _ = brute_nearest(pts, Vt, F)
    within = d_bf < reach
    assert 100 < within.sum() < n  # both cases occur
    np.testing.assert_allclose(d_tree[within], d_bf[within], atol=2e-5)
    assert np.all(d_tree[~within] == np.float32(reach)) and np.all(f_tree[~within] == -1)
    assert np.all(f_tree[within] >= 0)
    # the face found lies at the found distance (a tie may pick another face than the brute force)
    fw = F[f_tree[within]]
    own = np.array([brute_closest_points(q[None], *(Vt[f][None] for f in fi.T))[0, 0]
                    for q, fi in zip(pts[within], fw)])
    np.testing.assert_allclose(np.linalg.norm(own - pts[within], axis=1), d_bf[within], atol=2e-5)
    # against the refit collider's query on the same blended vertices
    mesh = wp.Mesh(points=wp.array(Vt, dtype=wp.vec3, device=dev), indices=wp.array(F.ravel(), device=dev))
    d_m = wp.zeros(n, dtype=float, device=dev)
    f_m = wp.zeros(n, dtype=wp.int32, device=dev)
    wp.launch(_mesh_query, n, inputs=[mesh.id, wp.array(pts, dtype=wp.vec3, device=dev), reach],
              outputs=[d_m, f_m], device=dev)
    np.testing.assert_allclose(d_tree, d_m.numpy(), atol=2e-5)
    f_m = f_m.numpy()
    differ = np.flatnonzero(f_tree != f_m)
    assert differ.size < 0.2 * within.sum()
    for i in differ:  # a tie: the query's face lies at the same distance (a shared edge or vertex)
        a, b, c = (Vt[v][None] for v in F[f_m[i]])
        q = brute_closest_points(pts[i][None], a, b, c)[0, 0]
        assert abs(np.linalg.norm(q - pts[i]) - d_tree[i]) < 2e-5


@pytest.mark.parametrize("leaf_faces,swap", [(4, False), (3, True)])
def test_lerp_tree_query_equals_brute_force(device, leaf_faces, swap):
    """The interpolated-box query (boxes and triangles of two frames written once, a sub-step's
    surface bounded by their blend): distance within reach equal to brute force over every face
    of the blended surface (and reach, face -1, beyond it), the face found at that distance, for
    frames stored in either slot order; with seeds (random tree slots, the exact answer's slot,
    one level or five above the seed's leaf) the same distances."""
    rng = np.random.default_rng(5)
    frames, F = _deforming_mesh(rng)
    frames[1] += rng.standard_normal(frames[1].shape).astype(np.float32) * 0.1  # non-rigid: loose boxes
    alpha = 0.43
    Vt = ((1 - alpha) * frames[0] + alpha * frames[1]).astype(np.float32)
    dev = device
    tree = allocate_implicit_tree(frames[0], F, leaf_faces, dev)
    tree_faces, tree_indices, depth, P = tree.tree_faces, tree.tree_indices, tree.depth, tree.num_leaves
    fr = wp.array(frames, dtype=wp.vec3, device=dev)
    ti, tf, lo, hi = tree.indices, tree.faces, tree.node_lower, tree.node_upper
    boxes = wp.zeros(8 * P, dtype=wp.vec4, device=dev)
    tris = wp.zeros(2 * len(tree_indices), dtype=wp.vec3, device=dev)
    s0, s1 = (1, 0) if swap else (0, 1)
    update_tree_slot(fr, ti, tf, leaf_faces, depth, 0, s0, lo, hi, boxes, tris)
    update_tree_slot(fr, ti, tf, leaf_faces, depth, 1, s1, lo, hi, boxes, tris)
    mesh_t = trimesh.Trimesh(Vt, F, process=False)
    on, _ = trimesh.sample.sample_surface(mesh_t, 300, seed=6)
    pts = np.concatenate([on + 0.05 * rng.standard_normal(on.shape),
                          rng.uniform(-2.5, 2.5, (200, 3))]).astype(np.float32)
    n, reach = len(pts), 0.3
    d_bf, _, _ = brute_nearest(pts, Vt, F)
    within = d_bf < reach
    assert 100 < within.sum() < n

    def query(seeds, up):
        d = wp.zeros(n, dtype=float, device=dev)
        sl = wp.zeros(n, dtype=wp.int32, device=dev)
        f = wp.zeros(n, dtype=wp.int32, device=dev)
        wp.launch(find_closest_on_lerp_tree, n,
                  inputs=[tf, boxes, tris, leaf_faces, P, len(F), s0, s1, alpha, wp.array(pts, dtype=wp.vec3, device=dev),
                          wp.array(seeds.astype(np.int32), device=dev), up, reach, 1e-6],
                  outputs=[d, sl, f], device=dev)
        return d.numpy(), sl.numpy(), f.numpy()

    d, sl, f = query(np.full(n, -1), 0)
    np.testing.assert_allclose(d[within], d_bf[within], atol=2e-5)
    assert np.all(d[~within] == np.float32(reach)) and np.all(f[~within] == -1) and np.all(sl[~within] == -1)
    assert np.all(tree_faces[sl[within]] == f[within])
    own = np.array([brute_closest_points(q[None], *(Vt[v][None] for v in F[fi]))[0, 0]
                    for q, fi in zip(pts[within], f[within])])
    np.testing.assert_allclose(np.linalg.norm(own - pts[within], axis=1), d_bf[within], atol=2e-5)
    for seeds, up in [(rng.integers(-1, len(F), n), 0), (rng.integers(0, len(F), n), 5), (sl, 0), (sl, 1)]:
        ds, _, fs = query(seeds, up)
        np.testing.assert_allclose(ds, d, atol=2e-6)
        assert np.all((fs >= 0) == (f >= 0))


def test_build_refuses_bad_input():
    with pytest.raises(ValueError, match="no faces"):
        build_implicit_tree(np.zeros((3, 3)), np.zeros((0, 3), np.int32))
    with pytest.raises(ValueError, match="leaf_faces must be >= 1, got 0"):
        build_implicit_tree(np.zeros((3, 3)), np.array([[0, 1, 2]]), 0)
