"""Re-meshing a fixed-topology sequence into a varying one (dynmesh_warp.remesh). CPU."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
import warp as wp

from dynmesh_warp.convert import nearest_surface
from dynmesh_warp.remesh import remesh_sequence, resample_time
from dynmesh_warp.scenes import icosphere, pulsing_blob
from dynmesh_warp.sequence import FixedTopologySequence, VaryingTopologySequence

wp.config.quiet = True
DEV = "cpu"
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _signed_volume(V, F):
    a, b, c = (V[F[:, k]].astype(np.float64) for k in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0


def _check_close(Vin, Fin, Vout, Fout, h):
    d_out = nearest_surface((Vin, Fin), Vout, device=DEV).dist  # output vertices -> input surface
    d_in = nearest_surface((Vout, Fout), Vin, device=DEV).dist  # input vertices -> output surface
    assert d_out.max() < 0.5 * h, d_out.max() / h
    assert d_in.max() < 1.0 * h, d_in.max() / h


def test_remesh_close_to_input_and_outward():
    seq = pulsing_blob(subdivisions=3, frames=3)
    r = remesh_sequence(seq, resolution=40, device=DEV)
    h = r.grid_spacing
    assert isinstance(r, VaryingTopologySequence) and r.num_frames == 3
    for t in range(3):
        V, F = r.frames[t]
        assert not (len(V) == len(seq.V[t]) and np.array_equal(F, seq.F))  # a new triangulation
        _check_close(seq.V[t], seq.F, V, F, h)
        vol_in = _signed_volume(seq.V[t], seq.F)
        vol = _signed_volume(V, F)
        assert vol > 0 and vol == pytest.approx(vol_in, rel=0.02)
        m = trimesh.Trimesh(V, F, process=False)
        assert m.is_watertight and m.is_winding_consistent


def test_remesh_of_faces_on_grid_planes_is_a_closed_manifold():
    """An axis-aligned box's faces lie on the grid's planes (the grid starts at the bounding box
    and the longest side is a whole number of cells), so grid points lie exactly on the surface;
    marching cubes then made coincident vertices and edges shared by more than two faces (41
    open and 29 non-manifold edges on this slab, 2,366 repeated vertices). Counted as just outside, the result is one
    closed, consistently wound surface with no repeated vertex, close to the box."""
    from dynmesh_warp.remesh import grid_for, remesh_frame

    box = trimesh.creation.box(extents=[2.0, 2.0, 0.3]).subdivide().subdivide()
    V, F = box.vertices.astype(np.float32), box.faces.astype(np.int32)
    origin, h, dims = grid_for([V], 48)
    cells = (V[:, 0].min() - origin[0]) / h
    assert abs(cells - round(cells)) < 1e-6  # a face on a grid plane
    Vo, Fo = remesh_frame(V, F, origin, h, dims, device=DEV)
    assert len(np.unique(Vo, axis=0)) == len(Vo)
    edges = np.sort(np.concatenate([Fo[:, [0, 1]], Fo[:, [1, 2]], Fo[:, [2, 0]]]), axis=1)
    assert (np.unique(edges, axis=0, return_counts=True)[1] == 2).all()
    m = trimesh.Trimesh(Vo, Fo, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert _signed_volume(Vo, Fo) == pytest.approx(1.2, rel=0.02)
    assert nearest_surface((V, F), Vo, device=DEV).dist.max() < 0.5 * h
    assert nearest_surface((Vo, Fo), V, device=DEV).dist.max() < 1.5 * h  # marching cubes cuts the corners


def test_remesh_open_mesh_with_a_slit_uses_robust_sign():
    """A closed sphere with a small hole (a few faces removed): the winding-number sign still
    gives the closed, outward surface with the right volume."""
    V, F = icosphere(3, 0.5)
    top = np.argsort(-V[F].mean(axis=1)[:, 2])[:6]  # remove 6 faces around the north pole
    F_open = np.delete(F, top, axis=0)
    assert not trimesh.Trimesh(V, F_open, process=False).is_watertight
    seq = FixedTopologySequence(V[None], F_open)
    r = remesh_sequence(seq, resolution=40, device=DEV)
    Vo, Fo = r.frames[0]
    vol = _signed_volume(Vo, Fo)
    assert vol == pytest.approx(_signed_volume(V, F), rel=0.02)
    assert trimesh.Trimesh(Vo, Fo, process=False).is_watertight
    _check_close(V, F, Vo, Fo, r.grid_spacing)


def test_remesh_time_resampling_and_noise():
    seq = pulsing_blob(subdivisions=2, frames=4)
    Vi = resample_time(seq, 7)
    assert Vi.shape == (7,) + seq.V.shape[1:]
    np.testing.assert_allclose(Vi[0], seq.V[0])
    np.testing.assert_allclose(Vi[6], seq.V[3])
    np.testing.assert_allclose(Vi[1], seq.V[0] + 0.5 * (seq.V[1] - seq.V[0]), atol=1e-6)  # u = 0.5
    r = remesh_sequence(seq, resolution=24, num_frames=7, device=DEV)
    assert r.num_frames == 7
    assert r.fps == pytest.approx(seq.fps * 6 / 3)  # same duration
    _check_close(Vi[1], seq.F, *r.frames[1], r.grid_spacing)
    noisy = remesh_sequence(seq, resolution=24, num_frames=7, noise=0.1, seed=3, device=DEV)
    d = noisy.frames[1][0] - r.frames[1][0]
    assert d.std() == pytest.approx(0.1 * r.grid_spacing, rel=0.1)
    again = remesh_sequence(seq, resolution=24, num_frames=7, noise=0.1, seed=3, device=DEV)
    np.testing.assert_array_equal(again.frames[1][0], noisy.frames[1][0])


def test_remesh_bad_input():
    seq = pulsing_blob(subdivisions=1, frames=2)
    with pytest.raises(ValueError, match="resolution"):
        remesh_sequence(seq, resolution=2)
    with pytest.raises(ValueError, match="noise"):
        remesh_sequence(seq, resolution=16, noise=-1.0)
    with pytest.raises(ValueError, match="num_frames"):
        remesh_sequence(seq, resolution=16, num_frames=0)
    with pytest.raises(ValueError, match="fixed-topology"):
        remesh_sequence(seq.to_varying(), resolution=16, num_frames=5)


@pytest.mark.skipif(not (DATA / "horse_gallop.npz").exists(), reason="shared data not present")
def test_remesh_horse_gallop_with_hoof_slit():
    from dynmesh_warp.io import load_sequence

    seq = load_sequence(DATA / "horse_gallop.npz")
    one = FixedTopologySequence(seq.V[:1], seq.F)
    r = remesh_sequence(one, resolution=64, device=DEV)
    V, F = r.frames[0]
    ref = trimesh.Trimesh(seq.V[0], seq.F, process=False)
    assert not ref.is_watertight  # the slit
    vol = _signed_volume(V, F)
    assert vol > 0 and vol == pytest.approx(_signed_volume(seq.V[0], seq.F), rel=0.03)
    d_out = nearest_surface((seq.V[0], seq.F), V, device=DEV).dist
    assert d_out.max() < 0.5 * r.grid_spacing
