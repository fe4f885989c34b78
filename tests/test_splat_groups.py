"""The viewer's grouped splat stream, on the host geometry it rests on (dynmesh_warp.geometry):
rotation -> quaternion against SciPy, the per-group Kabsch fit against known rigid motions, and
the motion grouping on a synthetic two-part articulated motion."""

from __future__ import annotations

import numpy as np
import pytest

from dynmesh_warp.geometry import fit_group_motions, motion_groups, rotation_to_wxyz


def test_rotation_to_wxyz_matches_scipy_including_half_turns():
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    R = Rotation.random(500, random_state=3)
    half = Rotation.from_rotvec(np.pi * np.eye(3))  # trace -1: the branches of the conversion
    mats = np.concatenate([R.as_matrix(), half.as_matrix(), np.eye(3)[None]])
    q = rotation_to_wxyz(mats)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    back = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(back, mats, atol=1e-12)


def test_fit_group_motions_recovers_rigid_motions_exactly():
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    rng = np.random.default_rng(0)
    K, G = 5, 400
    lab = rng.integers(0, K, G)
    P0 = rng.normal(size=(G, 3))
    cnt = np.bincount(lab, minlength=K)
    mean0 = np.stack([np.bincount(lab, P0[:, j], K) for j in range(3)], 1) / cnt[:, None]
    ref = P0 - mean0[lab]
    Rt = Rotation.random(K, random_state=1).as_matrix()
    tt = rng.normal(size=(K, 3))
    P1 = np.einsum("gij,gj->gi", Rt[lab], ref) + tt[lab]
    R, t, err = fit_group_motions(ref, P1, lab, K)
    np.testing.assert_allclose(R, Rt, atol=1e-9)
    np.testing.assert_allclose(t, tt, atol=1e-9)
    assert err.max() < 1e-9
    # a non-rigid change shows in the error of the points it moved
    P2 = P1.copy()
    P2[lab == 2] *= 1.1
    assert fit_group_motions(ref, P2, lab, K)[2][lab == 2].max() > 1e-3


def test_motion_groups_follow_the_motion_not_just_the_first_frame():
    """Two bars side by side: one still, one swinging about its end. On frame 0 they are one
    strip; grouping by the trajectories keeps every group on one bar where the bars part, so the
    groups' rigid fits are far better than grouping by frame-0 positions alone."""
    n = 40
    x = np.linspace(0.0, 1.0, n)
    bar = np.stack([np.repeat(x, 2), np.tile([0.0, 0.05], n), np.zeros(2 * n)], 1)  # a ladder of 2n vertices
    F = np.array([[2 * i, 2 * i + 1, 2 * i + 2] for i in range(n - 1)] + [[2 * i + 1, 2 * i + 3, 2 * i + 2]
                                                                         for i in range(n - 1)])
    F2 = np.concatenate([F, F + 2 * n])
    frames = []
    for a in np.linspace(0.0, 1.2, 12):
        c, s_ = np.cos(a), np.sin(a)
        moving = (bar + [0.0, 0.06, 0.0]) @ np.array([[c, 0, -s_], [0, 1, 0], [s_, 0, c]]).T
        frames.append(np.concatenate([bar, moving]))
    V = np.stack(frames)
    C = V[:, F2].mean(axis=2)

    def worst_fit(lab):
        K = lab.max() + 1
        mean0 = np.stack([np.bincount(lab, C[0][:, j], K) for j in range(3)], 1) / np.bincount(lab)[:, None]
        return max(fit_group_motions(C[0] - mean0[lab], C[t], lab, K)[2].max() for t in range(len(V)))

    by_motion, by_position = motion_groups(V, F2, 8), motion_groups(V[:1], F2, 8)
    assert by_motion.max() + 1 == 8
    half = len(F)
    far = C[0][:, 0] > 0.3  # where the swinging bar has left the still one
    mixed = [k for k in range(8) if (by_motion[:half][far[:half]] == k).any() and (by_motion[half:][far[half:]] == k).any()]
    assert not mixed, f"groups {mixed} hold faces of both bars where they are apart"
    assert worst_fit(by_motion) < 0.25 * worst_fit(by_position)
    assert motion_groups(V, F2, 10_000).max() + 1 == len(F2)  # capped at the face count, no empty group
