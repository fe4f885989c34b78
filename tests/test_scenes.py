"""Built-in scenes: the geometric properties their docstrings promise, checked with trimesh/NumPy."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dynmesh_warp import scenes
from dynmesh_warp.sequence import FixedTopologySequence, VaryingTopologySequence
from dynmesh_warp.world import SurfaceModel
from conftest import TEST_DEVICE


def _normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_grid_sheet_layout():
    V, F = scenes.grid_sheet(5, 2.0)
    assert V.shape == (25, 3) and F.shape == (32, 3)
    np.testing.assert_allclose(V.min(0), [-1, -1, 0]) and np.testing.assert_allclose(V.max(0), [1, 1, 0])
    np.testing.assert_allclose(_normals(V, F), np.tile([0, 0, 1.0], (32, 1)), atol=1e-7)
    m = trimesh.Trimesh(V, F, process=False)
    assert m.area == pytest.approx(4.0)
    assert m.is_winding_consistent


def test_wave_bowl_normals_up_and_seamless_loop():
    seq = scenes.wave_bowl(n=32, frames=24, fps=24.0)
    assert isinstance(seq, FixedTopologySequence) and seq.num_frames == 24
    for k in range(seq.num_frames):
        assert (_normals(seq.V[k].astype(np.float64), seq.F)[:, 2] > 0.5).all(), f"frame {k}"
    # a bowl: the rim is higher than the centre in every frame
    r = np.linalg.norm(seq.V[0, :, :2], axis=1)
    assert seq.V[:, r > 0.95, 2].min() > seq.V[:, r < 0.1, 2].max()
    # seamless loop: the step from the last frame back to frame 0 is like any other step
    steps = np.linalg.norm(np.diff(seq.V, axis=0), axis=-1).max(axis=1)  # (T-1,) largest per step
    seam = np.linalg.norm(seq.V[0] - seq.V[-1], axis=-1).max()
    assert steps.min() * 0.5 < seam < steps.max() * 1.2
    # and the playback model does not see a jump there
    surf = SurfaceModel(seq, TEST_DEVICE, playback="loop")
    assert surf.max_speed == pytest.approx(seq.max_vertex_speed(), rel=0.2)


def test_wave_bowl_is_a_height_field_of_the_grid():
    n = 16
    seq = scenes.wave_bowl(n=n, frames=6)
    V0, F0 = scenes.grid_sheet(n, 2.0)
    np.testing.assert_array_equal(seq.F, F0)
    np.testing.assert_allclose(seq.V[:, :, :2], np.broadcast_to(V0[:, :2], seq.V[:, :, :2].shape))


def test_pulsing_blob_watertight_outward_every_frame():
    seq = scenes.pulsing_blob(subdivisions=3, frames=12)
    centre = np.array([0.0, 0.0, 0.6])
    vols = []
    for k in range(seq.num_frames):
        m = trimesh.Trimesh(seq.V[k].astype(np.float64), seq.F, process=False)
        assert m.is_watertight and m.is_winding_consistent, f"frame {k}"
        assert m.volume > 0, f"frame {k}: inward-oriented"
        assert m.euler_number == 2
        n = _normals(m.vertices, seq.F)
        assert (np.einsum("ij,ij->i", n, m.triangles_center - centre) > 0).all()
        vols.append(m.volume)
    # it breathes: the volume changes by more than 10 % over the loop, around a 0.5 m sphere's
    assert (max(vols) - min(vols)) / np.mean(vols) > 0.1
    assert np.mean(vols) == pytest.approx(4 / 3 * np.pi * 0.5 ** 3, rel=0.25)
    # periodic: the seam step is like the others
    steps = np.linalg.norm(np.diff(seq.V, axis=0), axis=-1).max(axis=1)
    seam = np.linalg.norm(seq.V[0] - seq.V[-1], axis=-1).max()
    assert seam < steps.max() * 1.2


def test_torus_to_sphere_changes_topology_and_is_outward():
    seq = scenes.torus_to_sphere(frames=5, resolution=24)
    assert isinstance(seq, VaryingTopologySequence) and seq.num_frames == 5
    counts = [v.shape[0] for v, _ in seq.frames]
    assert len(set(counts)) > 1  # the vertex count changes
    assert not seq.is_fixed_topology()
    chis = []
    for k, (V, F) in enumerate(seq.frames):
        m = trimesh.Trimesh(V.astype(np.float64), F, process=True)  # merge duplicate MC vertices if any
        assert m.is_watertight, f"frame {k}"
        assert m.volume > 0, f"frame {k}: inward-oriented"
        chis.append(m.euler_number)
    assert chis[0] == 0  # torus (genus 1)
    assert chis[-1] == 2  # sphere (genus 0)
    # the last frame is the 0.5 m sphere around (0, 0, 0.6)
    V, F = seq.frames[-1]
    rad = np.linalg.norm(V - [0, 0, 0.6], axis=1)
    assert np.abs(rad - 0.5).max() < 0.05


def test_rigid_motion_is_rigid():
    v = np.array([0.1, 0.05, 0.0])
    seq = scenes.rigid_motion(frames=10, fps=24.0, angular_speed=0.5, velocity=v)
    V0 = seq.V[0].astype(np.float64)
    i, j = np.random.default_rng(0).integers(0, seq.num_vertices, (2, 200))
    d0 = np.linalg.norm(V0[i] - V0[j], axis=1)
    for k in range(seq.num_frames):
        Vk = seq.V[k].astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(Vk[i] - Vk[j], axis=1), d0, atol=1e-5)
        # rotation about z keeps z; the z-offset and the (x, y) norm about the moving axis persist
        np.testing.assert_allclose(Vk[:, 2] - V0[:, 2], v[2] * k / seq.fps, atol=1e-5)


def test_builtin_sequence_lookup():
    seq = scenes.builtin_sequence("wave_bowl", n=8, frames=3)
    assert seq.num_frames == 3 and seq.num_vertices == 64
    with pytest.raises(ValueError, match="wave_bowl"):  # lists the choices
        scenes.builtin_sequence("wavy_bowl")


def test_articulated_figure_sway_zero_keeps_the_body_in_place():
    """``sway=0`` drops the hop and the turn: the torso and head stay where frame 0 has them while
    the arms swing (the one-arm wave of bench/unseen_variants.py); the default sway moves them."""
    from dynmesh_warp.scenes import FIGURE_BONES, articulated_figure

    still = articulated_figure(frames=6, resolution=24, leg_swing=0.0, sway=0.0)
    moving = articulated_figure(frames=6, resolution=24, leg_swing=0.0)
    V0 = still.V[0]
    a, b, r = FIGURE_BONES["torso"]
    core = (np.abs(V0[:, 0]) < 0.5 * r) & (V0[:, 2] > a[2]) & (V0[:, 2] < b[2])  # the torso's middle
    assert core.sum() > 10
    assert np.abs(still.V[:, core] - V0[core]).max() < 1e-4  # (the arms' skinning weights reach it faintly)
    assert np.abs(moving.V[:, core] - moving.V[0][core]).max() > 0.05
    hand = np.argmin(V0[:, 2] - 10 * V0[:, 0])  # low on the +x side: the left hand
    assert np.linalg.norm(still.V[3, hand] - V0[hand]) > 0.3
    np.testing.assert_array_equal(still.F, moving.F)
