"""The cells collider (face clusters in a uniform grid rebuilt every step) against the refit
reference, and its static data (k-d clusters, grid capacity) against NumPy."""

import numpy as np
import pytest

from dynmesh_warp.face_cells import build_face_cells, kd_clusters, use_cells_collider
from dynmesh_warp.scenes import grid_sheet, pulsing_blob, wave_bowl
from dynmesh_warp.sequence import FixedTopologySequence
from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, World, surface_model_class
from conftest import TEST_DEVICE


def _worlds(seq, pos, vel, radius, t0, colliders, **params):
    out = []
    for col in colliders:
        model = Model(SurfaceModel(seq, TEST_DEVICE, playback="loop", interpolate=True),
                      SphereModel(radius, 1.0, TEST_DEVICE), PhysicsParams(auto_substeps=False, **params))
        w = World(model, State(model, pos, vel, t0=t0), collider="refit" if col == "cells" else col)
        out.append(use_cells_collider(w) if col == "cells" else w)
    return out


@pytest.fixture(params=[1, 0], ids=["nearest_first", "walk_order"])
def order(request, monkeypatch):
    """Both query orders (face_cells.CELLS_NEAREST_FIRST) give the reference's contacts."""
    import dynmesh_warp.face_cells as face_cells

    monkeypatch.setattr(face_cells, "CELLS_NEAREST_FIRST", request.param)
    return request.param


def _contacts_at(w):
    w.update_surface()
    w.collider.update(w.model, w.state, w.ctx)
    w.collider.collide(w.model, w.state, w.contacts, w.ctx)
    return w.contacts.numpy()


def _assert_same_contacts(c, c_ref, pos):
    m = c_ref["face"] >= 0
    np.testing.assert_array_equal(c["face"] >= 0, m)
    np.testing.assert_allclose(c["point"][m], c_ref["point"][m], atol=2e-5)
    np.testing.assert_allclose(c["depth"][m], c_ref["depth"][m], atol=2e-5)
    far = m & (np.linalg.norm(pos - c_ref["point"], axis=1) > 1e-3)
    np.testing.assert_allclose(c["normal"][far], c_ref["normal"][far], atol=2e-3)
    np.testing.assert_allclose(c["velocity"][m], c_ref["velocity"][m],
                               atol=2e-3 * max(1.0, np.abs(c_ref["velocity"]).max()))
    return int(m.sum())


def _wave_sheet(n=120, frames=6, amplitude=0.05):
    V0, F = grid_sheet(n, 2.0)
    V = np.repeat(V0[None], frames, 0).astype(np.float32)
    for t in range(frames):
        V[t, :, 2] = amplitude * np.sin(3 * V0[:, 0] + 2 * np.pi * t / frames)
    return FixedTopologySequence(V, F, fps=24.0, name="sheet")


def test_kd_clusters_hold_every_face_once_in_compact_leaves():
    """Every face in exactly one cluster, at most K a cluster, each cluster's faces first; on a
    regular sheet every cluster is a compact patch (its box no more than ~2x a square of K
    faces' area; a Morton run spanned the sheet)."""
    seq = _wave_sheet(n=61, frames=2)
    K = 16
    cl = kd_clusters(seq.V[0][seq.F].mean(axis=1), K)
    assert len(cl) % K == 0
    real = cl[cl >= 0]
    np.testing.assert_array_equal(np.sort(real), np.arange(len(seq.F)))
    leaves = cl.reshape(-1, K)
    for leaf in leaves:  # padding only after the faces
        k = int((leaf >= 0).sum())
        assert k >= 1 and (leaf[:k] >= 0).all() and (leaf[k:] < 0).all()
    edge = 2.0 / 60
    side = np.sqrt(K / 2) * edge  # a square patch of K triangles
    for leaf in leaves:
        tri = seq.V[0][seq.F[leaf[leaf >= 0]]]
        ext = np.ptp(tri.reshape(-1, 3), axis=0)
        assert ext[:2].max() <= 2.5 * side + edge, ext


def test_grid_capacity_bounds_every_steps_entries():
    """The static capacity (from the frames' cluster boxes) bounds the (cluster, cell) entries
    listed at any time of the loop, and each cluster's box from the kernel equals NumPy's box of
    its faces blended at that time."""
    seq = _wave_sheet(n=40, frames=5, amplitude=0.2)
    pos = np.array([[0.0, 0.0, 1.0]], np.float32)
    (w,) = _worlds(seq, pos, None, np.array([0.05], np.float32), 0.0, ["cells"])
    cc = w.collider
    faces = cc.cells.cluster_faces.reshape(-1, cc.cells.cluster_size)
    for t in np.linspace(0.0, seq.num_frames / seq.fps, 17):
        w.set_time(float(t))
        w.collider.update(w.model, w.state, w.ctx)
        assert int(cc.cell_count.numpy().sum()) <= cc.cells.capacity
        V, F = w.model.surface.host_mesh_at(float(t))
        lo, hi = cc.cluster_lower.numpy(), cc.cluster_upper.numpy()
        for c in range(0, len(faces), 7):
            tri = V[F[faces[c][faces[c] >= 0]]].reshape(-1, 3)
            np.testing.assert_allclose(lo[c], tri.min(axis=0), atol=1e-6)
            np.testing.assert_allclose(hi[c], tri.max(axis=0), atol=1e-6)
        # and each cluster is listed in every cell its box overlaps
        start, count, lists = cc.cell_start.numpy(), cc.cell_count.numpy(), cc.cell_clusters.numpy()
        o, dims, cell = cc.cells.grid_origin, cc.cells.grid_dims, cc.cells.cell
        for c in range(0, len(faces), 11):
            a = np.clip(np.floor((lo[c] - o) / cell).astype(int), 0, dims - 1)
            b = np.clip(np.floor((hi[c] - o) / cell).astype(int), 0, dims - 1)
            for z in range(a[2], b[2] + 1):
                for y in range(a[1], b[1] + 1):
                    for x in range(a[0], b[0] + 1):
                        g = (z * dims[1] + y) * dims[0] + x
                        assert c in lists[start[g]:start[g] + count[g]]


@pytest.mark.parametrize("make_seq", [lambda: wave_bowl(n=24, frames=12), lambda: pulsing_blob(subdivisions=2, frames=12)])
def test_cells_contacts_equal_refit_reference(make_seq, order):
    seq = make_seq()
    rng = np.random.default_rng(3)
    S = 64
    checked = 0
    for trial in range(5):
        t0 = float(rng.uniform(0, seq.num_frames / seq.fps * 1.5))  # includes loop wrap
        k = int(np.floor(t0 * seq.fps))
        a = t0 * seq.fps - k
        V = (1 - a) * seq.V[k % seq.num_frames] + a * seq.V[(k + 1) % seq.num_frames]
        pos = V[rng.integers(0, len(V), S)] + rng.normal(scale=0.04, size=(S, 3))
        pos[:4] = [[50.0, 0, 0], [0, -40.0, 0], [0, 0, 30.0], [-1e3, 1e3, 0]]  # far outside the grid
        vel = rng.normal(scale=0.5, size=(S, 3))
        radius = rng.uniform(0.02, 0.06, S).astype(np.float32)
        ref, cells = _worlds(seq, pos, vel, radius, t0, ["refit", "cells"])
        c_ref, c = _contacts_at(ref), _contacts_at(cells)
        checked += _assert_same_contacts(c, c_ref, pos)
        assert (c["face"][:4] < 0).all()
    assert checked > 50


def test_cells_with_hundreds_of_faces_per_sphere_and_a_fast_surface(order):
    """A fine sheet moving ~3 cm a step (far more than its 1.7 cm triangles) and wide spheres:
    each sphere's query spans many cells and clusters; the contacts equal the refit reference's
    at several times, and after the cells world stepped 60 times its trajectories follow it."""
    seq = _wave_sheet(n=120, frames=4, amplitude=0.3)
    rng = np.random.default_rng(5)
    S = 24
    xy = rng.uniform(-0.8, 0.8, (S, 2))
    z = 0.3 * np.sin(3 * xy[:, 0]) + rng.uniform(-0.03, 0.15, S)
    pos = np.c_[xy, z].astype(np.float32)
    vel = rng.normal(scale=0.3, size=(S, 3)).astype(np.float32)
    radius = rng.uniform(0.03, 0.12, S).astype(np.float32)
    checked = 0
    for t0 in (0.0, 0.013, 0.071):
        ref, cells = _worlds(seq, pos, vel, radius, t0, ["refit", "cells"])
        checked += _assert_same_contacts(_contacts_at(cells), _contacts_at(ref), pos)
    assert checked >= 6


def test_cells_world_matches_refit_world_trajectories():
    """Over 240 steps (24 frame changes; the grid rebuilt every step)."""
    seq = wave_bowl(n=24, frames=12)
    rng = np.random.default_rng(0)
    pos = np.c_[rng.uniform(-0.5, 0.5, (6, 2)), np.full(6, 0.5)]
    ref, cells = _worlds(seq, pos, None, np.full(6, 0.06, np.float32), 0.0, ["refit", "cells"])
    touched = 0
    for _ in range(240):
        ref.step()
        cells.step()
        f_ref, f_c = ref.contacts.face.numpy(), cells.contacts.face.numpy()
        np.testing.assert_array_equal(f_c >= 0, f_ref >= 0)
        touched += int((f_c >= 0).sum())
    np.testing.assert_allclose(cells.sphere_positions(), ref.sphere_positions(), atol=1e-3)
    assert touched > 50


def test_cells_find_the_outside_beyond_a_sharp_edge(order):
    """The pseudo-normal over tied faces (a 6-degree wedge's edge), as the refit reference."""
    h = np.tan(np.radians(3.0))
    ring = np.array([[1.0, 0.0], [0.0, h], [0.0, -h]])
    V0 = np.array([[x, y, z] for z in (-0.5, 0.5) for x, y in ring], np.float32)
    F = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5], [0, 2, 1], [3, 4, 5]], np.int32)
    seq = FixedTopologySequence(np.stack([V0, V0]), F, fps=24.0, name="wedge")
    d = np.array([0.01, 0.02, 0.03, 0.015])
    pos = np.c_[1.0 + d, np.array([0.5, -0.5, 0.6, -0.4]) * d, np.zeros(4)].astype(np.float32)
    radius = np.full(4, 0.05, np.float32)
    ref, cells = _worlds(seq, pos, None, radius, 0.0, ["refit", "cells"])
    c_ref, c = _contacts_at(ref), _contacts_at(cells)
    assert (c_ref["face"] >= 0).all()
    np.testing.assert_allclose(c["depth"], c_ref["depth"], atol=1e-5)
    np.testing.assert_allclose(c["normal"], c_ref["normal"], atol=1e-4)


def test_grid_keeps_to_its_most_cells():
    """``max_cells`` bounds the grid it builds (the cell edge grows until it fits; the grid spans
    the vertices' box plus half a cell each side, which the bound counts)."""
    seq = _wave_sheet(n=100, frames=3)
    for most in (1 << 10, 1 << 14, 1 << 22):
        fc = build_face_cells(seq.V, seq.F, 32, 1.0, most)
        assert fc.num_cells <= most
        assert (fc.grid_origin + fc.grid_dims * fc.cell >= seq.V.reshape(-1, 3).max(axis=0)).all()
        assert (fc.grid_origin <= seq.V.reshape(-1, 3).min(axis=0)).all()


def test_build_face_cells_refuses_a_cluster_size_below_two():
    seq = _wave_sheet(n=5, frames=2)
    with pytest.raises(ValueError, match="cluster_size 1"):
        build_face_cells(seq.V, seq.F, 1, 1.0, 1 << 10)


def test_cells_collider_refuses_a_varying_surface_and_plays_a_single_face():
    """Put into a varying-topology world it is refused by name (it reads one face array); a
    one-triangle surface (one cluster, one sub-box) gives the refit reference's contact."""
    from dynmesh_warp.scenes import torus_to_sphere

    seq = torus_to_sphere(frames=4, resolution=12)
    model = Model(surface_model_class(seq)(seq, TEST_DEVICE), SphereModel([0.05], 1.0, TEST_DEVICE), PhysicsParams())
    w = World(model, State(model, np.array([[0.0, 0.0, 3.0]])), collider="rebuild")
    with pytest.raises(ValueError, match="varying-topology surface"):
        use_cells_collider(w)
    V = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]] * 2, np.float32)
    tri = FixedTopologySequence(V, np.array([[0, 1, 2]], np.int32), fps=24.0, name="tri")
    pos = np.array([[0.2, 0.2, 0.03], [0.2, 0.2, -0.03], [2.0, 2.0, 0.0]], np.float32)
    ref, cells = _worlds(tri, pos, None, np.full(3, 0.05, np.float32), 0.0, ["refit", "cells"])
    c_ref, c = _contacts_at(ref), _contacts_at(cells)
    assert (c_ref["face"] == [0, 0, -1]).all()
    _assert_same_contacts(c, c_ref, pos)
