"""Independent NumPy references (vectorised brute force, float64) the tests compare the kernels
with: closest points on triangles, nearest surface points, the surface of a sequence at a time,
a height field's height, the winding number. Pure NumPy, no Warp."""

from __future__ import annotations

import math

import numpy as np


def brute_closest_points(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Closest point on each triangle (A[j],B[j],C[j]) to each point P[i]: (Q, M, 3) float64."""
    return closest_on_triangles(np.asarray(P, np.float64)[:, None, :],
                                *(np.asarray(x, np.float64)[None] for x in (A, B, C)))



def closest_on_triangles(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Closest point of triangle (A, B, C) to P, all (..., 3) broadcastable, float64.

    Written independently of the engine: minimise over the interior projection (when inside)
    and the three clamped edge projections, which covers every Voronoi region.
    """
    P, A, B, C = (np.asarray(x, np.float64) for x in (P, A, B, C))

    def seg(a, b):
        ab = b - a
        t = np.einsum("...k,...k->...", P - a, ab) / np.maximum(np.einsum("...k,...k->...", ab, ab), 1e-300)
        t = np.clip(t, 0.0, 1.0)
        return a + t[..., None] * ab

    n = np.cross(B - A, C - A)
    nn = np.einsum("...k,...k->...", n, n)
    nn_safe = np.maximum(nn, 1e-300)
    proj = P - (np.einsum("...k,...k->...", P - A, n) / nn_safe)[..., None] * n
    # inside test via signed areas of the sub-triangles
    s0 = np.einsum("...k,...k->...", np.cross(B - proj, C - proj), n)
    s1 = np.einsum("...k,...k->...", np.cross(C - proj, A - proj), n)
    s2 = np.einsum("...k,...k->...", np.cross(A - proj, B - proj), n)
    inside = (s0 >= 0) & (s1 >= 0) & (s2 >= 0) & (nn > 0)
    cands = [seg(A, B), seg(B, C), seg(C, A)]
    best = cands[0]
    bd = np.linalg.norm(P - best, axis=-1)
    for c in cands[1:]:
        d = np.linalg.norm(P - c, axis=-1)
        better = d < bd
        best = np.where(better[..., None], c, best)
        bd = np.where(better, d, bd)
    dproj = np.linalg.norm(P - proj, axis=-1)
    use = inside & (dproj < bd)
    return np.where(use[..., None], proj, best)



def brute_nearest(P: np.ndarray, V: np.ndarray, F: np.ndarray):
    """Brute-force nearest surface point over ALL triangles: (dist (Q,), face (Q,), point (Q,3))."""
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    out_d, out_f, out_p = [], [], []
    for chunk in np.array_split(np.asarray(P), max(1, len(P) // 64)):
        cp = brute_closest_points(chunk, A, B, C)
        d = np.linalg.norm(cp - np.asarray(chunk, np.float64)[:, None, :], axis=-1)
        j = d.argmin(axis=1)
        out_d.append(d[np.arange(len(chunk)), j])
        out_f.append(j)
        out_p.append(cp[np.arange(len(chunk)), j])
    return np.concatenate(out_d), np.concatenate(out_f), np.concatenate(out_p)



def surface_at(seq, t: float, mode: str = "loop") -> np.ndarray:
    """NumPy reference of the interpolated vertices at time t (loop or clamp playback)."""
    s = t * seq.fps
    k = math.floor(s)
    a = s - k
    T = seq.num_frames
    if mode == "clamp":
        k0, k1 = min(k, T - 1), min(k + 1, T - 1)
    else:
        k0, k1 = k % T, (k + 1) % T
    return seq.V[k0].astype(np.float64) * (1 - a) + seq.V[k1].astype(np.float64) * a



def grid_height(V: np.ndarray, n: int, size: float, xy: np.ndarray) -> np.ndarray:
    """Height of a grid_sheet-topology height field at points xy (K,2), from its two triangles
    per cell ((v00, v10, v11) for u >= w, (v00, v11, v01) otherwise); NaN off the sheet."""
    h = size / (n - 1)
    g = (xy + size / 2) / h
    i = np.clip(np.floor(g[:, 0]).astype(int), 0, n - 2)
    j = np.clip(np.floor(g[:, 1]).astype(int), 0, n - 2)
    u, w = g[:, 0] - i, g[:, 1] - j
    z = V[:, 2]
    z00, z10, z01, z11 = z[j * n + i], z[j * n + i + 1], z[(j + 1) * n + i], z[(j + 1) * n + i + 1]
    lower = z00 + u * (z10 - z00) + w * (z11 - z10)
    upper = z00 + w * (z01 - z00) + u * (z11 - z01)
    out = np.where(u >= w, lower, upper)
    off = (np.abs(xy) > size / 2).any(axis=1)
    return np.where(off, np.nan, out)



def winding_number(V: np.ndarray, F: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Generalised winding number of points P (Q,3) w.r.t. a closed mesh (van Oosterom-Strackee
    solid angles summed over all faces): ~1 inside an outward-oriented mesh, ~0 outside."""
    V = np.asarray(V, np.float64)
    P = np.asarray(P, np.float64)
    a, b, c = (V[F[:, i]][None] - P[:, None] for i in range(3))  # (Q, M, 3)
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    dot = lambda x, y: np.einsum("qmk,qmk->qm", x, y)  # noqa: E731
    num = dot(a, np.cross(b, c))
    den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
    return 2.0 * np.arctan2(num, den).sum(axis=1) / (4 * np.pi)

