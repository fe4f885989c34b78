"""Host geometry of one triangle mesh shared by every module (NumPy, float64): face areas, the
signed volume and the one orientation rule. Bottom layer: imports nothing from the package."""

from __future__ import annotations

import numpy as np

__all__ = ["face_areas", "surface_area", "signed_volume", "orient_outward", "mesh_orientation", "motion_groups",
           "fit_group_motions", "rotation_to_wxyz"]


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


def motion_groups(V, F, groups: int, frames: int = 16, sample: int = 20000, iterations: int = 12,
                  seed: int = 0) -> np.ndarray:
    """(M,) int64 group of each face of the animated mesh (V (T, N, 3), F (M, 3)): k-means, with
    farthest-point seeds, of the faces' centroid trajectories over up to ``frames`` evenly spaced
    frames, so faces that move together (a limb segment) share a group. Fitted on at most
    ``sample`` faces, then every face goes to its nearest centre. ``groups`` is capped at M; the
    labels are 0..K-1 with no empty group. Used to stream bound Gaussians as rigidly moving
    groups (the viewer)."""
    V = np.asarray(V, np.float64)
    V = V[None] if V.ndim == 2 else V
    F = np.asarray(F)
    T, M = V.shape[0], len(F)
    K = int(max(1, min(groups, M)))
    sub = V[np.unique(np.linspace(0, T - 1, min(T, max(1, frames))).round().astype(int))]
    X = sub[:, F].mean(axis=2).transpose(1, 0, 2).reshape(M, -1)  # (M, 3t) trajectories
    rng = np.random.default_rng(seed)
    fit = X if M <= sample else X[rng.choice(M, sample, replace=False)]

    def nearest(P, C):
        out = np.empty(len(P), np.int64)
        cc = (C * C).sum(1)
        for a in range(0, len(P), 4096):
            out[a:a + 4096] = (cc[None] - 2.0 * P[a:a + 4096] @ C.T).argmin(1)
        return out

    seeds = [int(rng.integers(len(fit)))]
    d = ((fit - fit[seeds[0]]) ** 2).sum(1)
    for _ in range(K - 1):
        j = int(d.argmax())
        seeds.append(j)
        d = np.minimum(d, ((fit - fit[j]) ** 2).sum(1))
    C = fit[seeds].copy()
    for _ in range(iterations):
        lab = nearest(fit, C)
        cnt = np.bincount(lab, minlength=K)
        for j in range(X.shape[1]):
            C[:, j] = np.where(cnt > 0, np.bincount(lab, fit[:, j], K) / np.maximum(cnt, 1), C[:, j])
    lab = nearest(X, C)
    return np.unique(lab, return_inverse=True)[1].astype(np.int64)  # no empty group


def fit_group_motions(ref_local, points, labels, groups: int):
    """Best rigid motion of each group (Kabsch): ``ref_local`` (G, 3) reference positions, each
    relative to its group's reference centroid; ``points`` (G, 3) the same points now; ``labels``
    (G,) their groups in [0, groups). Returns (R (K, 3, 3), t (K, 3), err (G,)): points ≈
    R[label] @ ref_local + t[label] (t is the group's current centroid), err each point's
    distance to its fit [units of points]."""
    ref = np.asarray(ref_local, np.float64)
    P = np.asarray(points, np.float64)
    lab = np.asarray(labels)
    K = int(groups)
    cnt = np.maximum(np.bincount(lab, minlength=K), 1).astype(np.float64)
    t = np.stack([np.bincount(lab, P[:, j], K) for j in range(3)], 1) / cnt[:, None]
    b = P - t[lab]
    H = np.empty((K, 3, 3))
    for i in range(3):
        for j in range(3):
            H[:, i, j] = np.bincount(lab, ref[:, i] * b[:, j], K)
    U, _, Vt = np.linalg.svd(H)
    D = np.ones((K, 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    D[D[:, 2] == 0, 2] = 1.0
    R = np.einsum("kji,kj,klj->kil", Vt, D, U)  # V diag(D) U^T
    err = np.linalg.norm(np.einsum("kij,kj->ki", R[lab], ref) + t[lab] - P, axis=1)
    return R, t, err


def rotation_to_wxyz(R) -> np.ndarray:
    """(K, 4) unit quaternions (w, x, y, z) of rotation matrices R (K, 3, 3)."""
    R = np.asarray(R, np.float64).reshape(-1, 3, 3)
    tr = np.trace(R, axis1=1, axis2=2)
    q = np.empty((len(R), 4))
    m = [R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]]
    c0 = tr > 0
    s = np.sqrt(np.maximum(tr + 1.0, 1e-30)) * 2.0
    q[c0] = np.stack([0.25 * s, (R[:, 2, 1] - R[:, 1, 2]) / s, (R[:, 0, 2] - R[:, 2, 0]) / s,
                      (R[:, 1, 0] - R[:, 0, 1]) / s], 1)[c0]
    for i, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
        ci = ~c0 & (m[i] >= m[a]) & (m[i] >= m[b])
        c0 = c0 | ci
        s = np.sqrt(np.maximum(1.0 + 2.0 * m[i] - tr, 1e-30)) * 2.0
        v = np.empty((len(R), 4))
        v[:, 0] = (R[:, b, a] - R[:, a, b]) / s
        v[:, 1 + i] = 0.25 * s
        v[:, 1 + a] = (R[:, a, i] + R[:, i, a]) / s
        v[:, 1 + b] = (R[:, b, i] + R[:, i, b]) / s
        q[ci] = v[ci]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)
