"""Host geometry of one triangle mesh shared by every module (NumPy, float64): face areas, the
signed volume and the one orientation rule. Bottom layer: imports nothing from the package."""

from __future__ import annotations

import numpy as np

__all__ = ["face_areas", "surface_area", "signed_volume", "orient_outward", "mesh_orientation"]


def face_areas(V, F) -> np.ndarray:
    """(M,) area of each triangle of (V (N, 3), F (M, 3)) [units of V squared]."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F)
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def surface_area(V, F) -> float:
    """Total area of the mesh."""
    return float(face_areas(V, F).sum())


def signed_volume(V, F) -> float:
    """Volume enclosed by the triangles, positive when they face outward (divergence theorem),
    taken about the vertex centroid so that a small hole biases it little."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F)
    V = V - V[np.unique(F)].mean(axis=0)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def orient_outward(V, F) -> np.ndarray:
    """``F``, with every face flipped when the signed volume is negative (a closed mesh whose
    triangles face inward); the same rule as :func:`mesh_orientation`."""
    return np.ascontiguousarray(F[:, ::-1]) if signed_volume(V, F) < 0 else F


def mesh_orientation(V, F, max_boundary: float = 0.01) -> str:
    """How the triangles of a mesh face.

    ``"outward"`` / ``"inward"``: a closed mesh, or one with a few small holes (at most
    ``max_boundary`` of its edges on a boundary, as in a scan or reconstruction), with
    consistent winding; the sign of its volume about the vertex centroid decides.
    ``"open"``: more boundary than that (a sheet, a terrain), or an edge shared by more than two
    faces: no inside to tell. ``"inconsistent"``: two faces run through a shared edge in the same
    direction."""
    F = np.asarray(F, np.int64)
    directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    n = int(max(int(F.max()) + 1, 1))
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    if np.any(counts > 2) or np.count_nonzero(counts == 1) > max_boundary * len(counts):
        return "open"
    if len(np.unique(directed[:, 0] * n + directed[:, 1])) != len(directed):
        return "inconsistent"
    return "outward" if signed_volume(V, F) > 0 else "inward"
