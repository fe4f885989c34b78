"""Geometric accuracy metrics: surface sampling, Chamfer distance (CD), Earth Mover's distance (EMD).

Two evaluation protocols are defined (see docs/evaluation.md and :data:`PROTOCOLS`):

- ``dgmesh``: the DG-Mesh evaluation (Liu et al. 2024, ``dgmesh/mesh_evaluation.py``):
  CD on all mesh *vertices*, squared L2 nearest-neighbour distance, mean over the points of
  each direction, the two directions averaged; EMD = approxmatch cost on 8,192 area-weighted
  surface samples per mesh, divided by the number of points.
- ``paper``: 10,000 area-weighted surface samples per mesh; the same CD convention (squared,
  mean per direction, directions averaged) and the same approxmatch EMD, both on the samples.

Host functions here are thin wrappers over the kernels in :mod:`dynmesh_warp.kernels.metrics`.
Point inputs are (N, 3) arrays in scene units; distances come back in those units (CD in
units^2 for the squared convention).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from .kernels import metrics as K
from .sequence import MAX_COORDINATE, MeshDataError, validate_mesh

__all__ = [
    "PROTOCOLS",
    "Protocol",
    "ChamferResult",
    "sample_surface",
    "kernel_seed",
    "nearest_neighbors",
    "chamfer_distance",
    "approxmatch_emd",
    "exact_emd",
    "evaluate_mesh_pair",
    "mesh_vertices",
    "CD_SCALE",
    "EMD_SCALE",
]

#: Reported CD = raw CD / CD_SCALE (i.e. in units of 1e-3), EMD = raw / EMD_SCALE (1e-1).
CD_SCALE = 1.0e-3
EMD_SCALE = 1.0e-1

#: the scene sizes (the two clouds' common bbox diagonal, in their units) where approxmatch is
#: within 1.6x of the exact EMD (1.3x from 1 to 20; docs/evaluation.md); outside them it warns
EMD_SCALE_RANGE = (0.5, 40.0)

#: approxmatch levels of Fan et al. 2017 (tf_approxmatch_g.cu): -4^j for j = 7..-1, then 0.
APPROXMATCH_LEVELS = tuple([-(4.0**j) for j in range(7, -2, -1)] + [0.0])


@dataclass(frozen=True)
class Protocol:
    """How a (ground truth, prediction) mesh pair is turned into CD and EMD numbers."""

    name: str
    cd_points: str  # "vertices" or "samples"
    cd_samples: int  # samples per mesh for CD when cd_points == "samples"
    emd_samples: int  # samples per mesh for the approxmatch EMD
    squared: bool  # CD on squared L2 distances
    description: str


PROTOCOLS = {
    "dgmesh": Protocol(
        "dgmesh", "vertices", 0, 8192, True,
        "CD: all mesh vertices, squared L2 NN distance, mean per direction, average of the two "
        "directions. EMD: approxmatch (Fan et al. 2017) on 8,192 area-weighted samples per mesh, "
        "cost / 8192.",
    ),
    "paper": Protocol(
        "paper", "samples", 10000, 10000, True,
        "10,000 area-weighted samples per mesh. CD: squared L2 NN distance, mean per direction, "
        "average of the two directions. EMD: approxmatch on the same samples, cost / 10000.",
    ),
}


def _device(device):
    return wp.get_device(device)


def _kernel_points(a: np.ndarray, centre=None) -> np.ndarray:
    """Checked points (:func:`_checked_points`) as the kernels take them: float32, less ``centre``
    (float64) when given (:func:`_offset_centre`)."""
    if centre is not None:
        a = np.asarray(a, np.float64) - centre
    return np.ascontiguousarray(a, dtype=np.float32)


def _bounds(*sets) -> tuple[np.ndarray, np.ndarray]:
    """The point sets' common bounding box (lo, hi), float64."""
    lo = np.min([np.min(np.asarray(s, np.float64), axis=0) for s in sets], axis=0)
    hi = np.max([np.max(np.asarray(s, np.float64), axis=0) for s in sets], axis=0)
    return lo, hi


def _offset_centre(*sets, factor: float = 1.0) -> np.ndarray | None:
    """The midpoint of the point sets' common bounding box (float64) where it lies farther from the
    origin than ``factor`` x the box's diagonal, else None: the kernels compute in float32, and far from the
    origin its rounding is a large part of the distances (a new user's 2,000 points with 3 mm of
    noise, offset 10^6: CD 10.9x the float64 one, 0.16x at 10^7; EMD +50 %). CD and EMD do not
    change with a translation; near the origin the points are taken as they are (bit for bit)."""
    lo, hi = _bounds(*sets)
    c = 0.5 * (lo + hi)
    return c if np.abs(c).max() > factor * np.linalg.norm(hi - lo) else None


def _checked_points(x, name: str) -> np.ndarray:
    a = np.asarray(x)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name}: points must have shape (N, 3), got {a.shape}")
    if a.shape[0] == 0:
        raise ValueError(f"{name}: point set is empty")
    if not np.isfinite(a).all():
        bad = int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])
        raise ValueError(f"{name}: point {bad} has NaN/inf coordinates")
    far = ~(np.abs(a) <= MAX_COORDINATE).all(axis=1)
    if far.any():  # float32 (the kernels') would turn it inf, or its squared distances (a new user's 1e20: 3e38)
        bad = int(np.flatnonzero(far)[0])
        raise ValueError(f"{name}: point {bad} {a[bad].tolist()} lies beyond +-{MAX_COORDINATE:g} "
                         "(sequence.MAX_COORDINATE: wrong units or garbage)")
    return a


# ----------------------------------------------------------------------------- sampling


def kernel_seed(seed) -> int:
    """A seed for a Warp kernel's random stream (a signed 32-bit int, non-negative): seeds in
    [0, 2**31) as they are; any other integer mixed, all its bits, by NumPy's SeedSequence, so that
    2**32 + 5 or 2**40 do not alias 5 or 0 (their low bits were taken; a new user's finding)."""
    s = int(seed)
    if 0 <= s < 1 << 31:
        return s
    return int(np.random.SeedSequence(abs(s), spawn_key=(1 if s < 0 else 0,)).generate_state(1)[0]) & 0x7FFFFFFF


def sample_surface(V, F, num_points: int, seed: int = 0, device=None,
                   return_faces: bool = False, source: str | None = None):
    """Area-weighted uniform random points on a triangle mesh, reproducible for a seed.

    V (N,3), F (M,3) are validated first (bad faces raise MeshDataError naming ``source``).
    Returns float32 (num_points, 3) samples (and int32 face ids when return_faces).
    Raises MeshDataError when the mesh has zero total area.
    """
    V, F = validate_mesh(V, F, source)
    if int(num_points) <= 0:
        raise ValueError(f"num_points must be positive, got {num_points}")
    dev = _device(device)
    V64 = V.astype(np.float64)
    area = 0.5 * np.linalg.norm(
        np.cross(V64[F[:, 1]] - V64[F[:, 0]], V64[F[:, 2]] - V64[F[:, 0]]), axis=1)
    total = area.sum()
    if not total > 0:
        raise MeshDataError(f"{source or 'mesh'}: total surface area is zero, cannot sample")
    cdf = np.cumsum(area) / total
    cdf[-1] = 1.0
    n = int(num_points)
    samples = wp.empty(n, dtype=wp.vec3, device=dev)
    faces = wp.empty(n, dtype=wp.int32, device=dev)
    wp.launch(K.sample_surface_points, dim=n,
              inputs=[wp.array(V, dtype=wp.vec3, device=dev),
                      wp.array(F.reshape(-1), dtype=wp.int32, device=dev),
                      wp.array(cdf.astype(np.float32), dtype=float, device=dev),
                      kernel_seed(seed)],
              outputs=[samples, faces], device=dev)
    if return_faces:
        return samples.numpy(), faces.numpy()
    return samples.numpy()


# ---------------------------------------------------------------------- nearest neighbours


def nearest_neighbors(queries, targets, device=None):
    """Exact nearest target of each query: (dist_sq float32 (Q,), index int32 (Q,)).

    Targets go into a BVH as degenerate triangles (i, i, i) of a ``wp.Mesh``; the kernel
    :func:`dynmesh_warp.kernels.metrics.find_nearest_points_bvh` asks for the closest face
    with no distance limit, so every query gets its exact nearest point however far it is.
    """
    q, t = _checked_points(queries, "queries"), _checked_points(targets, "targets")
    c = _offset_centre(q, t)
    q, t = _kernel_points(q, c), _kernel_points(t, c)
    dev = _device(device)
    tq = wp.array(q, dtype=wp.vec3, device=dev)
    tt = wp.array(t, dtype=wp.vec3, device=dev)
    tri = wp.array(np.repeat(np.arange(len(t), dtype=np.int32), 3), dtype=wp.int32, device=dev)
    mesh = wp.Mesh(points=tt, indices=tri)
    idx = wp.empty(len(q), dtype=wp.int32, device=dev)
    d2 = wp.empty(len(q), dtype=float, device=dev)
    wp.launch(K.find_nearest_points_bvh, dim=len(q), inputs=[mesh.id, tq, tt],
              outputs=[idx, d2], device=dev)
    return d2.numpy(), idx.numpy()


@dataclass(frozen=True)
class ChamferResult:
    """Chamfer distance between point sets A and B.

    a_to_b: mean over A of the (squared, if squared) distance to the nearest point of B;
    b_to_a: the same from B to A; value = (a_to_b + b_to_a) / 2 (the DG-Mesh convention).
    """

    a_to_b: float
    b_to_a: float
    squared: bool

    @property
    def value(self) -> float:
        return 0.5 * (self.a_to_b + self.b_to_a)

    @property
    def sum(self) -> float:
        """a_to_b + b_to_a (the convention of e.g. PointFlow's emd_cd 'CD')."""
        return self.a_to_b + self.b_to_a


def chamfer_distance(a, b, squared: bool = True, device=None) -> ChamferResult:
    """Chamfer distance between point sets a (N,3) and b (M,3), exact nearest neighbours.

    squared=True uses squared L2 distances (units^2), False plain L2 (units). Means are
    taken in float64 over the per-point float32 distances.
    """
    a, b = _checked_points(a, "a"), _checked_points(b, "b")  # checked under the names of this call
    d_ab, _ = nearest_neighbors(a, b, device)
    d_ba, _ = nearest_neighbors(b, a, device)
    d_ab = d_ab.astype(np.float64)
    d_ba = d_ba.astype(np.float64)
    if not squared:
        d_ab, d_ba = np.sqrt(d_ab), np.sqrt(d_ba)
    return ChamferResult(float(d_ab.mean()), float(d_ba.mean()), bool(squared))


# -------------------------------------------------------------------------------------- EMD


def approxmatch_emd(xyz1, xyz2, device=None, return_details: bool = False):
    """EMD of Fan et al. 2017: approxmatch soft assignment, then sum(match * |x1 - x2|) / n.

    xyz1, xyz2: (n, 3) point sets of equal size (the DG-Mesh evaluation passes ground truth
    first). Runs the 10 levels -4^7 ... -4^-1, 0 of the original on ``device``. Distances are
    UNSQUARED, so the result is in scene units. O(n^2) work per level.

    With return_details, returns (emd, details) where details holds 'match' ((n, n) float32,
    match[l, k] between xyz2[l] and xyz1[k]; only stored for n <= 4096), 'remain_left' and
    'remain_right' (unassigned mass after the last level) and 'cost' (the undivided cost).
    """
    x1, x2 = _checked_points(xyz1, "xyz1"), _checked_points(xyz2, "xyz2")
    lo, hi = _bounds(x1, x2)
    diag = float(np.linalg.norm(hi - lo))
    c = _offset_centre(np.stack([lo, hi]))  # (the box's corners have the clouds' box)
    x1, x2 = _kernel_points(x1, c), _kernel_points(x2, c)
    n, m = len(x1), len(x2)
    lo, hi = EMD_SCALE_RANGE
    if n > 1 and not lo <= diag <= hi:
        warnings.warn(f"approxmatch EMD of clouds {diag:.3g} units across: its levels are absolute (1/units^2), and "
                      f"outside {lo:g}-{hi:g} units it is far from the exact EMD (over 1.6x; 3x at 0.13 and 254 "
                      f"units, docs/evaluation.md); scale the meshes by about {2.5 / diag:.3g} to compare with "
                      "scenes of unit size, and compare EMDs only at one scale", stacklevel=2)
    if n != m:
        raise ValueError(
            f"approxmatch_emd needs point sets of equal size (as the DG-Mesh evaluation), "
            f"got {n} and {m}")
    dev = _device(device)
    a1 = wp.array(x1, dtype=wp.vec3, device=dev)
    a2 = wp.array(x2, dtype=wp.vec3, device=dev)
    remain_l = wp.full(n, 1.0, dtype=float, device=dev)  # multiL = 1 for n == m
    remain_r = wp.full(m, 1.0, dtype=float, device=dev)
    ratio_l = wp.zeros(n, dtype=float, device=dev)
    ratio_r = wp.zeros(m, dtype=float, device=dev)
    cost_l = wp.zeros(n, dtype=float, device=dev)
    store = bool(return_details and n <= 4096)
    match = wp.zeros((m, n) if store else (1, 1), dtype=float, device=dev)
    for level in APPROXMATCH_LEVELS:
        wp.launch(K.compute_approxmatch_ratio_left, dim=n,
                  inputs=[a1, a2, remain_r, remain_l, float(level)], outputs=[ratio_l], device=dev)
        wp.launch(K.compute_approxmatch_ratio_right, dim=m,
                  inputs=[a1, a2, ratio_l, float(level)], outputs=[remain_r, ratio_r], device=dev)
        wp.launch(K.accumulate_approxmatch_left, dim=n,
                  inputs=[a1, a2, ratio_l, ratio_r, float(level), int(store)],
                  outputs=[remain_l, cost_l, match], device=dev)
    cost = float(cost_l.numpy().astype(np.float64).sum())
    emd = cost / n
    if not return_details:
        return emd
    return emd, {
        "match": match.numpy() if store else None,
        "remain_left": remain_l.numpy(),
        "remain_right": remain_r.numpy(),
        "cost": cost,
    }


def exact_emd(xyz1, xyz2) -> float:
    """Exact EMD for equal-size sets: optimal one-to-one assignment (SciPy Hungarian solver)
    minimising the sum of UNSQUARED distances, divided by n. A reference for small n."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial.distance import cdist

    x1 = _checked_points(xyz1, "xyz1").astype(np.float64)
    x2 = _checked_points(xyz2, "xyz2").astype(np.float64)
    if len(x1) != len(x2):
        raise ValueError(f"exact_emd needs point sets of equal size, got {len(x1)} and {len(x2)}")
    D = cdist(x1, x2)
    r, c = linear_sum_assignment(D)
    return float(D[r, c].sum() / len(x1))


# ------------------------------------------------------------------------------ protocols


def mesh_vertices(V, F) -> np.ndarray:
    """The vertices DG-Mesh's vertex CD counts: ``trimesh.load`` processes a mesh file, which keeps
    the vertices its faces use, once per position (rounded to 8 decimals, the first kept; trimesh's
    ``merge_vertices``). A vertex no face uses was counted (a new user's 400 left over from a
    removed floater's faces: CD 5.4e-4 for the exact surface, DG-Mesh's 0)."""
    used = np.flatnonzero(np.bincount(np.asarray(F, np.int64).ravel(), minlength=len(V)))
    _, first = np.unique(np.round(np.asarray(V, np.float64)[used], 8), axis=0, return_index=True)
    return np.asarray(V)[used[np.sort(first)]]


def evaluate_mesh_pair(gt, pred, protocol: str = "dgmesh", seed: int = 0, device=None,
                       emd: bool = True, source: str | None = None) -> dict:
    """CD and EMD of a predicted mesh against a ground-truth mesh under a named protocol.

    gt, pred: (V, F) tuples. Sampling is seeded: gt uses ``seed``, pred ``seed + 1``
    (independent draws, as two independent ``trimesh.sample`` calls in DG-Mesh).
    Returns raw values: {'cd', 'cd_gt_to_pred', 'cd_pred_to_gt', 'emd' (None when emd=False),
    'degenerate_prediction'}. A prediction of zero total area (collapsed) is sampled at its
    vertices (uniformly, with replacement) and flagged with degenerate_prediction=True.
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}; choose one of {sorted(PROTOCOLS)}")
    P = PROTOCOLS[protocol]
    Vg, Fg = validate_mesh(*gt, source=f"{source or ''} ground truth".strip())
    Vp, Fp = validate_mesh(*pred, source=f"{source or ''} prediction".strip())
    c = _offset_centre(gt[0], pred[0])  # (far from the origin: centred before float32, as the points)
    if c is not None:
        Vg = (np.asarray(gt[0], np.float64) - c).astype(np.float32)
        Vp = (np.asarray(pred[0], np.float64) - c).astype(np.float32)
    out = {"degenerate_prediction": False}
    src_g, src_p = f"{source or ''} ground truth".strip(), f"{source or ''} prediction".strip()

    def samples(n):
        g = sample_surface(Vg, Fg, n, seed, device, source=src_g)
        try:
            p = sample_surface(Vp, Fp, n, seed + 1, device, source=src_p)
        except MeshDataError as e:
            if "area is zero" not in str(e):
                raise
            # a collapsed prediction (all faces degenerate) has no surface to sample: use its
            # vertices, drawn uniformly with replacement, and flag the result
            out["degenerate_prediction"] = True
            p = Vp[np.random.default_rng(seed + 1).integers(0, len(Vp), n)]
        return g, p

    if P.cd_points == "vertices":
        cg, cp = mesh_vertices(Vg, Fg), mesh_vertices(Vp, Fp)
    else:
        cg, cp = samples(P.cd_samples)
    c = chamfer_distance(cg, cp, squared=P.squared, device=device)
    out["cd"] = c.value
    out["cd_gt_to_pred"] = c.a_to_b
    out["cd_pred_to_gt"] = c.b_to_a
    out["emd"] = None
    if emd:
        if P.cd_points == "samples" and P.cd_samples == P.emd_samples:
            eg, ep = cg, cp
        else:
            eg, ep = samples(P.emd_samples)
        out["emd"] = approxmatch_emd(eg, ep, device)  # ground truth first, as DG-Mesh
    return out
