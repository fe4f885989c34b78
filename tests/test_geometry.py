"""Host geometry (dynmesh_warp.geometry, convert's bounding box, the graph's sampling) against
independent references: trimesh's areas and volume, NumPy's row-wise forms."""

import numpy as np
import trimesh

from dynmesh_warp import geometry
from dynmesh_warp.convert_base import _bbox_diag
from dynmesh_warp.deform_graph import _farthest_points


def _blob(seed=0):
    m = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(seed)
    V = m.vertices * (1 + 0.2 * rng.random((len(m.vertices), 1))) * [1.0, 0.6, 1.7] + [3.0, -2.0, 0.5]
    return V, np.asarray(m.faces)


def test_face_areas_and_volume_match_trimesh():
    V, F = _blob()
    ref = trimesh.Trimesh(V, F, process=False)
    np.testing.assert_allclose(geometry.face_areas(V, F), ref.area_faces, rtol=1e-12)
    assert np.isclose(geometry.surface_area(V, F), ref.area, rtol=1e-12)
    assert np.isclose(geometry.signed_volume(V, F), ref.volume, rtol=1e-9)
    assert np.isclose(geometry.signed_volume(V, F[:, ::-1]), -ref.volume, rtol=1e-9)  # wound inward
    # float32 input and an unused vertex (left out of the centroid) change nothing
    V2 = np.vstack([V, [[100.0, 100.0, 100.0]]]).astype(np.float32)
    assert np.isclose(geometry.signed_volume(V2, F), ref.volume, rtol=1e-5)


def test_bbox_diag_matches_rowwise_form():
    rng = np.random.default_rng(1)
    for V in (rng.normal(size=(1000, 3)).astype(np.float32), rng.normal(size=(7, 3)) * 1e3):
        assert _bbox_diag(V) == float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    assert _bbox_diag(np.zeros((0, 3))) == 0.0


def test_farthest_points_cover_every_point_within_its_spacing():
    rng = np.random.default_rng(2)
    P = rng.random((3000, 3))
    spacing = np.where(P[:, 0] < 0.5, 0.08, 0.2)
    idx = _farthest_points(P, spacing, 0)
    d = np.linalg.norm(P[:, None, :] - P[idx][None, :, :], axis=2).min(axis=1)
    assert np.all(d <= spacing)
    assert len(set(idx)) == len(idx)
    # finer spacing where asked: the left half holds most samples
    assert np.mean(P[idx, 0] < 0.5) > 0.7


def test_winding_inconsistent_matches_a_set_of_directed_edges():
    """``winding_inconsistent`` (one sort of the directed edges; convert's rewinding and
    ``mesh_orientation`` ask it) against a Python set of (i, j) pairs, on an icosphere with no,
    one and many faces flipped, and on faces with large indices."""
    import trimesh

    from dynmesh_warp.geometry import winding_inconsistent

    F0 = np.asarray(trimesh.creation.icosphere(subdivisions=2).faces, np.int64)
    rng = np.random.default_rng(0)
    for flip in (0, 1, 40):
        F = F0.copy()
        idx = rng.choice(len(F), flip, replace=False)
        F[idx] = F[idx][:, ::-1]
        for G in (F, F + 10**6):
            seen, repeated = set(), False
            for a, b, c in G.tolist():
                for e in ((a, b), (b, c), (c, a)):
                    repeated |= e in seen
                    seen.add(e)
            assert winding_inconsistent(G) == repeated == (flip > 0)
    assert not winding_inconsistent(np.zeros((0, 3), np.int64))
