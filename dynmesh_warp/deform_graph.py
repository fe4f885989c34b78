"""Embedded deformation graph (Sumner, Schmid & Pauly, SIGGRAPH 2007) for the ``graph``
conversion strategy: a template tracked through a sequence as a deforming surface with few
degrees of freedom, so that a limb moves as a whole instead of sliding vertex by vertex.

``build_deformation_graph(V, F, spacing, k=4) -> DeformationGraph``
    Nodes: template vertices picked by farthest-point sampling until every vertex lies within
    ``spacing`` of a node, per connected component, then more nodes until every vertex is within
    2 x ``spacing`` of one along the surface (geodesic, Dijkstra on the edge graph). ``spacing``
    may be one per vertex (finer nodes where the surface moves, convert's ``adaptive_spacing``):
    each bound then holds with the vertex's own spacing. Each vertex
    binds to its ``k`` geodesically nearest nodes with Sumner's weights (1 - d / d_max)^2
    (d_max: the distance to the (k+1)-th nearest), so an arm vertex never binds to a torso node
    that is near in space but far along the surface. Nodes sharing a vertex are graph edges.

``GraphFitter``: the per-frame fit (device arrays allocated once). Unknowns: node rotations R_j
and positions p_j. Energy: a two-sided data term (template -> frame closest points and frame ->
template closest points, each kept only where the normals agree within ``max_normal_angle``;
the two directions are means, weighted equally, like the Chamfer distance they minimise), the
as-rigid-as-possible graph term sum_(j,l) |p_l - p_j - R_j (g_l - g_j)|^2 (mean over edges,
weight ``stiffness``, lowered geometrically from ``stiffness`` to ``stiffness_end`` over the
iterations: coarse, near-rigid motion first, then finer bending) and a small damping towards the
prediction. Each iteration, all on the device with no host round trip: correspondences, the
sparse K x K normal equations in p (fixed CSR pattern, accumulated by kernels), a
Jacobi-preconditioned conjugate-gradient solve warm-started from the current p (one captured
CUDA graph on the GPU), then the rotations (local step: the rotation closest to each node's
covariance, edges + data, by a robust polar iteration per node). ``fit`` reads the result back
once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import warp as wp

from .conversion_options import CG_ITERATIONS, CG_TOLERANCE  # the solve's defaults (one home)
from .geometry import face_rim_flags
from .kernels import register as kr


__all__ = ["DeformationGraph", "GraphFrame", "rim_array", "build_deformation_graph", "GraphFitter", "polar_rotations",
           "extrapolate_rotations", "rotation_from_vector", "node_groups", "system_pattern"]


class GraphFrame(NamedTuple):
    """An input frame on the device as :class:`GraphFitter` takes it: ``mesh`` a wp.Mesh over
    ``points`` (Q,) wp.vec3 [m] and ``indices`` (3M,) wp.int32; ``normals`` (Q,) wp.vec3 area-
    weighted vertex normals (any length); ``face_rim`` (M,) wp.int32 the faces' rim flags
    (:func:`dynmesh_warp.geometry.face_rim_flags`), None where the frame has no rim (closed)."""

    mesh: wp.Mesh
    points: wp.array
    indices: wp.array
    normals: wp.array
    face_rim: wp.array | None = None


def rim_array(F: np.ndarray, device) -> wp.array | None:
    """The rim flags of faces ``F`` (M, 3) on the device, None for a closed mesh (no rim)."""
    flags = face_rim_flags(F)
    return wp.array(flags, dtype=wp.int32, device=device) if flags.any() else None


@dataclass
class DeformationGraph:
    """node_vertex (K,) int64 template vertex of each node; node_rest (K, 3) float64 [m];
    node_index (N, k) int32 and node_weight (N, k) float32 (rows sum to 1; unused slots have
    weight 0 and repeat a valid node); edges (E, 2) int64 undirected node pairs (j < l);
    spacing [m]."""

    node_vertex: np.ndarray
    node_rest: np.ndarray
    node_index: np.ndarray
    node_weight: np.ndarray
    edges: np.ndarray
    spacing: float

    @property
    def num_nodes(self) -> int:
        return len(self.node_vertex)


def _edge_graph(V: np.ndarray, F: np.ndarray):
    from scipy.sparse import coo_matrix

    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).astype(np.int64)
    e = np.unique(np.sort(e, axis=1), axis=0)
    e = e[e[:, 0] != e[:, 1]]
    w = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1)
    w = np.maximum(w, 1e-12)  # zero-length edges still connect
    n = len(V)
    G = coo_matrix((np.concatenate([w, w]), (np.concatenate([e[:, 0], e[:, 1]]),
                                              np.concatenate([e[:, 1], e[:, 0]]))), shape=(n, n))
    return G.tocsr()


#: _farthest_points asks a k-d tree for the points near each new sample from this many points on
#: (fewer: a pass over all of them is cheaper than building it)
FPS_TREE_POINTS = 20_000


def _farthest_points(P: np.ndarray, spacing, start: int) -> list:
    """Farthest-point sampling of P from index ``start`` until every point lies within its
    ``spacing`` (a float or one per point) of a sample: each next sample is the point farthest
    from the samples relative to its own spacing."""
    from scipy.spatial import cKDTree

    P = np.asarray(P, np.float64).reshape(-1, 3)
    d = np.full(len(P), np.inf)
    x, y, z = np.ascontiguousarray(P.T)  # per coordinate: the same distances as
    # np.linalg.norm(P - P[i], axis=1), 3x faster
    spacing = np.broadcast_to(np.asarray(spacing, np.float64), d.shape)
    r = np.empty_like(d)
    tree, dmax = None, np.inf
    out = []
    i = start
    while True:
        out.append(i)
        if tree is None:  # the first sample (and every one of a small input): every point
            near = slice(None)
        else:  # only points nearer the new sample than the farthest one is from any: the others keep
            # their distance (a 105k-vertex template's 706 samples each passed over every point:
            # 9 % of its conversion on an H200); the same distances, bit for bit
            near = tree.query_ball_point(P[i], float(dmax) * (1.0 + 1e-9) + 1e-300, return_sorted=False)
            near = np.asarray(near, np.int64)
        dx, dy, dz = x[near] - x[i], y[near] - y[i], z[near] - z[i]
        d[near] = np.minimum(d[near], np.sqrt(dx * dx + dy * dy + dz * dz))
        r[near] = d[near] / spacing[near]
        if tree is None and len(P) >= FPS_TREE_POINTS:
            tree = cKDTree(P)
        if tree is not None:
            dmax = d.max()
        i = int(np.argmax(r))
        if r[i] <= 1.0:
            return out


def build_deformation_graph(V, F, spacing: float, k: int = 4, max_nodes: int = 4000) -> DeformationGraph:
    """The embedded deformation graph of mesh (V, F) (module docstring).

    Args:
        spacing: node spacing [m] (farthest-point sampling radius): a float, or (N,) one per vertex.
        k: nodes per vertex (1 .. kernels.register.MAX_NODES_PER_VERTEX).
        max_nodes: refuse (ValueError) a spacing that would need more nodes than this.
    """
    from scipy.sparse.csgraph import connected_components, dijkstra
    from scipy.spatial import cKDTree

    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    n = len(V)
    sp = np.asarray(spacing, np.float64)
    if sp.ndim > 1 or (sp.ndim == 1 and sp.shape[0] != n):
        raise ValueError(f"node spacing: one value or one per vertex ({n}), got shape {sp.shape}")
    if not (sp.size and np.all(np.isfinite(sp)) and np.all(sp > 0)):
        raise ValueError(f"node spacing must be > 0, got {spacing if sp.ndim == 0 else 'a value <= 0 or not finite'}")
    sp = np.broadcast_to(sp, (n,))
    spacing = float(sp.min())  # named in the errors below
    k = int(k)
    if not 1 <= k <= kr.MAX_NODES_PER_VERTEX:
        raise ValueError(f"nodes per vertex must lie in [1, {kr.MAX_NODES_PER_VERTEX}], got {k}")
    G = _edge_graph(V, F)
    ncomp, labels = connected_components(G, directed=False)
    used = np.zeros(n, bool)
    used[F.reshape(-1)] = True
    nodes = []
    for c in range(ncomp):
        idx = np.flatnonzero((labels == c) & used)
        if len(idx) == 0:
            continue
        sub = _farthest_points(V[idx], sp[idx], 0)
        nodes.extend(idx[sub].tolist())
        if len(nodes) > max_nodes:
            raise ValueError(f"deformation graph: node spacing {spacing:.4g} needs more than {max_nodes} "
                             "nodes; raise the spacing")
    # geodesic coverage: every vertex within 2 x its spacing of a node along the surface
    for _ in range(max_nodes):
        dist = dijkstra(G, directed=False, indices=nodes, min_only=True) / sp
        dist[~used] = 0.0
        far = int(np.argmax(dist))
        if dist[far] <= 2.0:
            break
        nodes.append(far)
    nodes = np.asarray(nodes, np.int64)
    K = len(nodes)
    if K > max_nodes:
        raise ValueError(f"deformation graph: node spacing {spacing:.4g} needs more than {max_nodes} nodes; "
                         "raise the spacing")
    # k+1 geodesically nearest nodes per vertex (chunks of sources, limited search radius)
    limit = 4.0 * float(sp.max())
    best_d = np.full((n, k + 1), np.inf)
    best_i = np.zeros((n, k + 1), np.int64)
    chunk = max(1, int(2e7 // max(n, 1)))
    for s in range(0, K, chunk):
        D = dijkstra(G, directed=False, indices=nodes[s:s + chunk], limit=limit).T  # (n, c)
        cd = np.concatenate([best_d, D], axis=1)
        ci = np.concatenate([best_i, np.broadcast_to(np.arange(s, s + D.shape[1]), D.shape)], axis=1)
        sel = np.argsort(cd, axis=1, kind="stable")[:, :k + 1]
        best_d = np.take_along_axis(cd, sel, 1)
        best_i = np.take_along_axis(ci, sel, 1)
    # vertices no node reaches along the surface (tiny components, unused vertices): nearest in space
    lost = ~np.isfinite(best_d[:, 0])
    if lost.any():
        kk = min(k + 1, K)
        dd, ii = cKDTree(V[nodes]).query(V[lost], k=kk)
        dd = dd.reshape(-1, kk)
        ii = ii.reshape(-1, kk)
        if kk < k + 1:
            dd = np.concatenate([dd, np.full((len(dd), k + 1 - kk), np.inf)], 1)
            ii = np.concatenate([ii, np.repeat(ii[:, :1], k + 1 - kk, 1)], 1)
        best_d[lost] = dd
        best_i[lost] = ii
    d = best_d[:, :k]
    dmax = best_d[:, k:k + 1]
    dmax = np.where(np.isfinite(dmax), dmax, np.where(np.isfinite(d), d, 0).max(axis=1, keepdims=True) * 1.5 + 1e-12)
    w = np.where(np.isfinite(d), np.clip(1.0 - d / dmax, 0.0, 1.0) ** 2, 0.0)
    zero = w.sum(axis=1) <= 0
    w[zero, 0] = 1.0  # a vertex at equal distance from all its nodes: the nearest one
    w /= w.sum(axis=1, keepdims=True)
    idx = best_i[:, :k].copy()
    idx[w == 0] = np.repeat(idx[:, :1], k, axis=1)[w == 0]
    # edges: node pairs sharing a vertex
    pairs = []
    for a in range(k):
        for b in range(a + 1, k):
            m = (w[:, a] > 0) & (w[:, b] > 0)
            pairs.append(np.stack([idx[m, a], idx[m, b]], 1))
    e = np.concatenate(pairs) if pairs else np.zeros((0, 2), np.int64)
    e = np.sort(e, axis=1)
    e = np.unique(e[e[:, 0] != e[:, 1]], axis=0) if len(e) else e
    return DeformationGraph(nodes, V[nodes].copy(), idx.astype(np.int32), w.astype(np.float32),
                            e.astype(np.int64), float(sp.max()))


def polar_rotations(C: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotations R maximising tr(R^T C_j) (C = sum y x^T: R x ~ y), det +1."""
    U, _, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    U = U.copy()
    U[:, :, 2] *= d[:, None]
    return U @ Vt


def rotation_from_vector(v: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by |v| radians about v, (..., 3) -> (..., 3, 3) float64; the
    identity where |v| < 1e-12."""
    v = np.asarray(v, np.float64)
    a = np.linalg.norm(v, axis=-1)
    k = np.divide(v, a[..., None], out=np.zeros_like(v), where=a[..., None] >= 1e-12)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = k[..., 2], -k[..., 1], k[..., 0]
    return np.eye(3) + np.sin(a)[..., None, None] * K + (1.0 - np.cos(a))[..., None, None] * (K @ K)


def extrapolate_rotations(R0: np.ndarray, R1: np.ndarray, gamma: float) -> np.ndarray:
    """R1 advanced by gamma times the step R0 -> R1 (constant angular velocity), (K, 3, 3)."""
    D = R1 @ np.transpose(R0, (0, 2, 1))
    if gamma == 1.0:
        return polar_rotations(D @ R1)
    # axis-angle of D, scaled
    cos = np.clip((np.trace(D, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    ang = np.arccos(cos)
    axis = np.stack([D[:, 2, 1] - D[:, 1, 2], D[:, 0, 2] - D[:, 2, 0], D[:, 1, 0] - D[:, 0, 1]], 1)
    s = np.linalg.norm(axis, axis=1, keepdims=True)
    axis = np.divide(axis, s, out=np.zeros_like(axis), where=s > 1e-12)
    return rotation_from_vector(axis * (gamma * ang)[:, None]) @ R1


def system_pattern(graph: DeformationGraph, TF: np.ndarray) -> tuple:
    """CSR sparsity pattern of the fit's K x K system: node pairs bound to one template vertex
    (forward term, graph edges) or to one template face (backward term), and the diagonal.
    Returns (row_offsets (K+1,), columns (nnz,)) int32, columns sorted within each row."""
    K = graph.num_nodes
    NI = graph.node_index.astype(np.int64)
    keys = [np.arange(K, dtype=np.int64) * (K + 1)]
    e = graph.edges.astype(np.int64)
    keys += [e[:, 0] * K + e[:, 1], e[:, 1] * K + e[:, 0]]

    def pairs(groups):  # (m, g) node groups -> unique keys of all ordered pairs in a group
        # neighbouring vertices and faces share their nodes: the distinct groups first (a 105k-vertex
        # template's 231k faces have a few thousand), then their pairs (np.unique of every face's
        # 144 keys was 10 % of its conversion on an H200)
        groups = np.unique(np.sort(groups, axis=1), axis=0)
        a = np.repeat(groups, groups.shape[1], axis=1)
        b = np.tile(groups, (1, groups.shape[1]))
        return np.unique(a * K + b)

    step = max(1, 2_000_000 // max(NI.shape[1] ** 2, 1))
    for s in range(0, len(NI), step):
        keys.append(pairs(NI[s:s + step]))
    TF = np.asarray(TF, np.int64).reshape(-1, 3)
    step = max(1, 2_000_000 // max((3 * NI.shape[1]) ** 2, 1))
    for s in range(0, len(TF), step):
        keys.append(pairs(NI[TF[s:s + step]].reshape(-1, 3 * NI.shape[1])))
    keys = np.unique(np.concatenate(keys))
    rows, cols = keys // K, keys % K
    offsets = np.zeros(K + 1, np.int64)
    np.add.at(offsets, rows + 1, 1)
    return np.cumsum(offsets).astype(np.int32), cols.astype(np.int32)


#: the stiff first part of the schedule whose levels may be held (``fit``; options
#: converge_iterations, converge_tolerance), a fraction of its levels: the first half (a new
#: user's fast banana at 1 % error, CPU: +2.0 / +2.6 / +3.8 % CD holding all / half / a quarter
#: of the levels; its ping-pong twin +12 / +17 / +13 %, within the fit's spread) costs half the
#: read-backs of all of them (a GPU sync each)
HELD_LEVELS = 0.5

#: threads of the one block that solves the CG on CUDA (each owns every CG_BLOCK_THREADS-th row
#: of the K x K system; K is at most the graph's max_nodes, 4,000 by default)
CG_BLOCK_THREADS = 256


#: rigid_align: a part's step leaves out the directions of its 6 x 6 system (rotations scaled by
#: the part's size) whose eigenvalue is under this fraction of the largest (a motion the part's
#: surface does not see: a round part turning about its axis, a capsule about its own), and the
#: fewest partners a part needs each way to be moved
RIGID_CONDITION = 0.02
RIGID_MIN_ROWS = 12
#: rigid_align keeps a part's motion only where it lowers the part's two-sided mean squared plane
#: distance below this factor of the start's
RIGID_GAIN = 0.8
#: ... and not where it fits many of its nodes clearly worse and few better (:func:`_worse_in_places`:
#: at least RIGID_WORSE_NODES, over RIGID_WORSE_SHARE of them, twice the better ones; a node
#: worse: its mean squared plane distance over RIGID_WORSE x the start's plus the part's median).
#: A new user's fast arm on a still body, one connected surface: the body turned up to 47 degrees
#: with the arm, 26-70 % of the nodes worse and 2.2-7x the better ones; parts turning as one at
#: 1 % error: at most 5.5 % worse; pcow's body leaving its legs behind: 16-21 % worse, 1-1.4x the
#: better; chicken_crossing's 3-13-node parts: a node or two either way (the noise)
RIGID_WORSE = 4.0
RIGID_WORSE_SHARE = 0.15
RIGID_WORSE_NODES = 3


def _observable_step(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(P, 6) Gauss-Newton steps -H^-1 g of P rigid systems (H (P, 6, 6), g (P, 6); unknowns:
    rotation vector [rad], translation [m]) within each one's observable directions: the rotation
    is scaled by the part's size L (L^2 = tr H_rot / tr H_trans), and the directions whose
    eigenvalue is under RIGID_CONDITION x the largest are left out (no step along them)."""
    tt = np.maximum(np.trace(H[:, 3:, 3:], axis1=1, axis2=2), 1e-30)
    L = np.sqrt(np.maximum(np.trace(H[:, :3, :3], axis1=1, axis2=2), 1e-30) / tt)
    sc = np.ones((len(H), 6))
    sc[:, :3] = 1.0 / L[:, None]
    Hs = H * sc[:, :, None] * sc[:, None, :]
    lam, U = np.linalg.eigh(Hs)
    keep = lam > RIGID_CONDITION * lam[:, -1:]
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    step = -np.einsum("pij,pj,pkj,pk->pi", U, inv, U, g * sc)
    return step * sc


def _worse_in_places(start: np.ndarray, end: np.ndarray, part: np.ndarray, parts: int) -> np.ndarray:
    """(parts,) bool: the parts whose rigid motion fits many of their nodes clearly worse than the
    start and few clearly better: at least RIGID_WORSE_NODES nodes and over RIGID_WORSE_SHARE of
    the part's clearly worse, and at least twice as many as clearly better. ``start``, ``end``
    (K, 2) :meth:`GraphFitter._node_residuals` at the start and the end; ``part`` (K,) each
    node's part. A node fits clearly worse where its mean squared plane distance ends over
    RIGID_WORSE x the start's plus the part's median start (the reconstruction error's level: a
    node that started on the exact surface by chance is not counted), clearly better the other
    way round; nodes with no partners at either end are left out. A part that turns as one fits
    better or alike everywhere, and a body turning with its limbs lagging fits the body better
    and the limbs worse; one rigid motion fitted to a fast limb on a still body (one connected
    surface) fits the limb better and the larger body worse."""
    has = (start[:, 1] > 0) & (end[:, 1] > 0)
    b = start[:, 0] / np.maximum(start[:, 1], 1e-30)
    a = end[:, 0] / np.maximum(end[:, 1], 1e-30)
    out = np.zeros(parts, bool)
    for p in np.unique(part[has]):
        sel = has & (part == p)
        floor = np.median(b[sel])
        worse = int(np.sum(a[sel] > RIGID_WORSE * b[sel] + floor))
        better = int(np.sum(b[sel] > RIGID_WORSE * a[sel] + floor))
        out[p] = worse >= RIGID_WORSE_NODES and worse > RIGID_WORSE_SHARE * sel.sum() and worse >= 2 * better
    return out


def node_groups(graph: DeformationGraph, mask: np.ndarray | None = None) -> np.ndarray:
    """(K,) int64: the connected group of each node over the graph's edges between nodes in
    ``mask`` ((K,) bool; None: all, the template's parts). A node outside the mask is a group of
    its own."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    K = graph.num_nodes
    e = np.asarray(graph.edges, np.int64).reshape(-1, 2)
    if mask is not None:
        e = e[mask[e[:, 0]] & mask[e[:, 1]]]
    if K == 0:
        return np.zeros(0, np.int64)
    a = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(K, K))
    return connected_components(a, directed=False)[1].astype(np.int64)


class GraphFitter:
    """Device arrays and the device-side solve of the graph fit (module docstring).

    Every iteration runs on the device with no host round trip: correspondences, the sparse
    normal equations (CSR, fixed pattern), a Jacobi-preconditioned CG warm-started from the
    current positions (``cg_iterations`` iterations at most, relative tolerance ``cg_tolerance``;
    one launch per solve) and the per-node rotation update. ``fit`` reads the
    result back once."""

    def __init__(self, graph: DeformationGraph, TV: np.ndarray, TF: np.ndarray, device, max_dist: float,
                 opts: dict):
        self.g = graph
        self.device = d = wp.get_device(device)
        self.opts = opts
        self.max_dist = float(max_dist)
        self.n = len(TV)
        self.K = graph.num_nodes
        self.k = graph.node_index.shape[1]
        self.cg_iterations = max(int(opts.get("cg_iterations", CG_ITERATIONS)), 1)
        self.cg_tolerance = float(opts.get("cg_tolerance", CG_TOLERANCE))
        arr = lambda a, dt: wp.array(a, dtype=dt, device=d)  # noqa: E731
        self.rest_points = arr(np.ascontiguousarray(TV, np.float32), wp.vec3)
        self.indices = arr(np.ascontiguousarray(TF, np.int32).reshape(-1), wp.int32)
        self.face_rim = rim_array(TF, d)  # the template's rim (an open template), None if closed
        self.node_rest = arr(graph.node_rest.astype(np.float32), wp.vec3)
        self.node_index = arr(graph.node_index.reshape(-1), wp.int32)
        self.node_weight = arr(graph.node_weight.reshape(-1), float)
        K, n = self.K, self.n
        self.node_rotation = wp.empty(K, dtype=wp.mat33, device=d)
        self.node_position = wp.empty(K, dtype=wp.vec3, device=d)
        self.position_prior = wp.empty(K, dtype=wp.vec3, device=d)
        self.position_prev = wp.empty(K, dtype=wp.vec3, device=d)  # before the last iteration (convergence)
        self.moved = wp.zeros(1, dtype=float, device=d)
        # rigid_align: the template's parts (connected pieces of the graph), the normal equations of each
        self.node_part = node_groups(graph)
        self.num_parts = int(self.node_part.max()) + 1 if K else 0
        vpart = self.node_part[graph.node_index[:, 0]]
        self.vertex_part = arr(vpart.astype(np.int32), wp.int32)
        self.face_part = arr(vpart[np.asarray(TF).reshape(-1, 3)[:, 0]].astype(np.int32), wp.int32)
        self.vertex_ids = arr(np.arange(n, dtype=np.int32), wp.int32)
        self.part_center = wp.zeros(max(self.num_parts, 1), dtype=wp.vec3, device=d)
        self.rigid_system = wp.zeros((2 * max(self.num_parts, 1), 29), dtype=float, device=d)
        self.node_residual = wp.zeros(max(self.K, 1), dtype=wp.vec2, device=d)
        self.points = wp.empty(n, dtype=wp.vec3, device=d)
        # the template BVH: built on the predicted pose by rebuild() at the start of every fit
        # (a tree refit far from the pose it was built on answers queries slowly)
        self.mesh_points = wp.empty(n, dtype=wp.vec3, device=d)
        self.tmesh = None
        self._tree_pose = None  # (R, P) the tree was built on and left unmoved, else None
        self.normals = wp.zeros(n, dtype=wp.vec3, device=d)
        self.target = wp.empty(n, dtype=wp.vec3, device=d)
        self.fface = wp.empty(n, dtype=wp.int32, device=d)
        self.fbary = wp.empty(n, dtype=wp.vec3, device=d)
        self.fweight = wp.empty(n, dtype=float, device=d)
        self.fdist = wp.empty(n, dtype=float, device=d)
        self.weight_sum = wp.zeros(2, dtype=float, device=d)
        self.stiffness = wp.zeros(1, dtype=float, device=d)  # this iteration's graph weight per directed edge
        self.covariance = wp.zeros(K, dtype=wp.mat33, device=d)
        # the static hold (convert's static_hold): per node, a weight towards the fit's start
        self.node_hold = wp.zeros(K, dtype=float, device=d)
        self._holding = False
        self._frame_cap = 0
        # the K x K system: fixed CSR pattern, graph Laplacian per slot
        offsets, cols = system_pattern(graph, TF)
        rows = np.repeat(np.arange(K, dtype=np.int32), np.diff(offsets))
        self.nnz = len(cols)
        e = graph.edges
        ej = np.concatenate([e[:, 0], e[:, 1]]).astype(np.int64)
        el = np.concatenate([e[:, 1], e[:, 0]]).astype(np.int64)
        # slots are sorted by row * K + column, so a slot is found by binary search of that key
        slot_key = rows.astype(np.int64) * K + cols
        lap_values = np.zeros(self.nnz, np.float64)
        for a, b, v in ((ej, ej, 1.0), (el, el, 1.0), (ej, el, -1.0), (el, ej, -1.0)):
            np.add.at(lap_values, np.searchsorted(slot_key, a * K + b), v)
        self.row_offsets = arr(offsets, wp.int32)
        self.columns = arr(cols, wp.int32)
        self.slot_row = arr(rows, wp.int32)
        self.laplacian = arr(lap_values.astype(np.float32), float)
        diag = np.searchsorted(slot_key, np.arange(K, dtype=np.int64) * (K + 1))
        self.diagonal_slot = arr(diag.astype(np.int32), wp.int32)
        self.values = wp.zeros(self.nnz, dtype=float, device=d)
        self.rhs = wp.zeros(K, dtype=wp.vec3, device=d)
        self.edge_from = arr(ej.astype(np.int32) if len(ej) else np.zeros(0, np.int32), wp.int32)
        self.edge_to = arr(el.astype(np.int32) if len(el) else np.zeros(0, np.int32), wp.int32)
        g = graph.node_rest
        self.rest_offset = arr((g[el] - g[ej]).astype(np.float32).reshape(-1, 3), wp.vec3)
        self.num_edges = max(len(ej), 1)
        # CG work arrays
        self.residual = wp.zeros(K, dtype=wp.vec3, device=d)
        self.preconditioned = wp.zeros(K, dtype=wp.vec3, device=d)
        self.direction = (wp.zeros(K, dtype=wp.vec3, device=d), wp.zeros(K, dtype=wp.vec3, device=d))
        self.product = wp.zeros(K, dtype=wp.vec3, device=d)
        self.residual_dot = wp.zeros(self.cg_iterations + 1, dtype=float, device=d)

    # ------------------------------------------------------------------ building blocks
    def _frame_arrays(self, q: int):
        if q > self._frame_cap:
            d = self.device
            self._frame_cap = q
            self.bclosest = wp.empty(q, dtype=wp.vec3, device=d)
            self.bface = wp.empty(q, dtype=wp.int32, device=d)
            self.bbary = wp.empty(q, dtype=wp.vec3, device=d)
            self.bweight = wp.empty(q, dtype=float, device=d)
            self.bdist = wp.empty(q, dtype=float, device=d)

    def set_state(self, R: np.ndarray, P: np.ndarray):
        """Upload node rotations R (K,3,3) and positions P (K,3) to the device."""
        d = self.device
        self.node_rotation.assign(wp.array(np.asarray(R, np.float32), dtype=wp.mat33, device=d))
        self.node_position.assign(wp.array(np.asarray(P, np.float32), dtype=wp.vec3, device=d))

    def get_state(self) -> tuple:
        """The device's node rotations and positions as float64 (K,3,3), (K,3)."""
        return self.node_rotation.numpy().astype(np.float64), self.node_position.numpy().astype(np.float64)

    def skin(self, R: np.ndarray | None = None, P: np.ndarray | None = None):
        """Template positions (self.points) for node rotations R (K,3,3) and positions P (K,3),
        uploaded first when given (default: the device state)."""
        if R is not None:
            self.set_state(R, P)
        wp.launch(kr.skin_vertices, dim=self.n,
                  inputs=[self.rest_points, self.node_rest, self.node_index, self.node_weight, self.k,
                          self.node_rotation, self.node_position], outputs=[self.points], device=self.device)
        return self.points

    def rebuild(self):
        """Rebuild the template BVH on the template skinned by the device state."""
        wp.copy(self.mesh_points, self.skin())
        self.tmesh = wp.Mesh(points=self.mesh_points, indices=self.indices)
        self._tree_pose = None

    def _rebuild_unless_built_on(self, R: np.ndarray, P: np.ndarray):
        """:meth:`rebuild` (the state set to R, P already), unless the tree stands on exactly this
        pose: :meth:`rigid_align` found the start aligned and left its tree built on it (one
        build a frame saved, ~6 ms for 20k faces on the CPU; the same tree, so the same result)."""
        kept = self._tree_pose
        if kept is None or not (np.array_equal(kept[0], R) and np.array_equal(kept[1], P)):
            self.rebuild()
        self._tree_pose = None

    def _update_template(self):
        from .kernels import convert as kc

        wp.copy(self.mesh_points, self.points)
        self.tmesh.refit()
        self.normals.zero_()
        wp.launch(kc.accumulate_vertex_normals, dim=len(self.indices) // 3, inputs=[self.points, self.indices],
                  outputs=[self.normals], device=self.device)

    def correspondences(self, frame: GraphFrame, min_cos: float, reject_rim: bool = False):
        """Forward and backward correspondences for the current self.points. ``reject_rim``: on an
        open frame or template, the pairs whose closest point lies on the searched mesh's rim are
        left out (``kr.reject_rim_pairs``; the rigid start's, see :meth:`rigid_align`)."""
        d = self.device
        self._update_template()
        wp.launch(kr.find_correspondences, dim=self.n,
                  inputs=[frame.mesh.id, frame.points, frame.indices, self.points, self.normals, self.max_dist, min_cos],
                  outputs=[self.target, self.fface, self.fbary, self.fweight, self.fdist], device=d)
        if reject_rim and frame.face_rim is not None:
            wp.launch(kr.reject_rim_pairs, dim=self.n, inputs=[frame.face_rim, self.fface, self.fbary],
                      outputs=[self.fweight], device=d)
        self._find_backward(frame, self.points, min_cos, reject_rim)

    def _find_backward(self, frame: GraphFrame, X, min_cos: float, reject_rim: bool = False):
        """Frame -> template correspondences against the template BVH (already refit to X)."""
        q = frame.points.shape[0]
        self._frame_arrays(q)
        wp.launch(kr.find_correspondences, dim=q,
                  inputs=[self.tmesh.id, X, self.indices, frame.points, frame.normals, self.max_dist, min_cos],
                  outputs=[self.bclosest, self.bface, self.bbary, self.bweight, self.bdist], device=self.device)
        if reject_rim and self.face_rim is not None:
            wp.launch(kr.reject_rim_pairs, dim=q, inputs=[self.face_rim, self.bface, self.bbary],
                      outputs=[self.bweight], device=self.device)

    def assemble(self, frame, stiffness_weight: float | None, damping_weight: float):
        """The normal equations in the node positions (values, rhs) for the current
        correspondences and rotations: two-sided data term, ARAP graph term with weight
        ``stiffness_weight`` per directed edge (None: the device's ``stiffness`` as set before),
        damping towards ``position_prior``."""
        d, n = self.device, self.n
        q = frame[1].shape[0]
        if stiffness_weight is not None:
            self.stiffness.fill_(float(stiffness_weight))
        # graph and damping terms, zeroed covariance and weight sums: one launch (nnz >= K)
        wp.launch(kr.begin_graph_system, dim=self.nnz,
                  inputs=[self.slot_row, self.columns, self.laplacian, self.position_prior, self.node_hold,
                          self.stiffness, damping_weight],
                  outputs=[self.values, self.rhs, self.covariance, self.weight_sum],
                  device=d)
        wp.launch(kr.sum_correspondence_weights, dim=n, inputs=[self.fweight, 0], outputs=[self.weight_sum],
                  device=d)
        wp.launch(kr.sum_correspondence_weights, dim=q, inputs=[self.bweight, 1], outputs=[self.weight_sum],
                  device=d)
        wp.launch(kr.accumulate_forward_system, dim=n,
                  inputs=[self.node_index, self.node_weight, self.k, self.row_offsets, self.columns, self.points,
                          self.node_position, self.target, self.fweight, self.weight_sum],
                  outputs=[self.values, self.rhs], device=d)
        wp.launch(kr.accumulate_backward_system, dim=q,
                  inputs=[self.indices, self.node_index, self.node_weight, self.k, self.row_offsets, self.columns,
                          self.points, self.node_position, frame[1], self.bface, self.bbary, self.bweight,
                          self.weight_sum], outputs=[self.values, self.rhs], device=d)
        if len(self.edge_from):
            wp.launch(kr.accumulate_graph_rhs, dim=len(self.edge_from),
                      inputs=[self.edge_from, self.edge_to, self.rest_offset, self.node_rotation, self.stiffness],
                      outputs=[self.rhs], device=d)

    def solve(self, serial: bool | None = None):
        """node_position <- the solution of the assembled system (CG warm-started from it, at
        most ``cg_iterations`` iterations, stopping at the tolerance). On the CPU (``serial``
        default) one serial launch; on CUDA one block of CG_BLOCK_THREADS threads
        (``solve_conjugate_gradient_block``: one launch for every iteration)."""
        if serial is None:
            serial = not self.device.is_cuda
        self.residual_dot.zero_()
        if serial:
            wp.launch(kr.solve_conjugate_gradient_serial, dim=1,
                      inputs=[self.row_offsets, self.columns, self.diagonal_slot, self.values, self.node_hold,
                              self.rhs, self.cg_iterations, self.cg_tolerance],
                      outputs=[self.node_position, self.residual, self.preconditioned, self.direction[0],
                               self.product, self.residual_dot], device=self.device)
            return
        wp.launch_tiled(kr.solve_conjugate_gradient_block, dim=[1],
                        inputs=[self.row_offsets, self.columns, self.diagonal_slot, self.values, self.node_hold,
                                self.rhs, self.cg_iterations, self.cg_tolerance],
                        outputs=[self.node_position, self.residual, self.preconditioned, self.direction[0],
                                 self.direction[1], self.product, self.residual_dot],
                        block_dim=CG_BLOCK_THREADS, device=self.device)

    def solve_residual(self) -> float:
        """Relative preconditioned residual sqrt(rz_final / rz_0) of the last solve (host read)."""
        rz = self.residual_dot.numpy()
        done = np.flatnonzero(rz > 0)
        return float(np.sqrt(rz[done[-1]] / rz[0])) if len(done) and rz[0] > 0 else 0.0

    def update_rotations(self, stiffness_weight: float | None):
        """Local step: per-node rotations from the data and the edges, at the current positions
        (after :meth:`assemble`, which zeroes the covariance and sums the weights);
        ``stiffness_weight`` None: the device's ``stiffness`` as set before."""
        d = self.device
        if stiffness_weight is not None:
            self.stiffness.fill_(float(stiffness_weight))
        # covariance was zeroed by assemble()'s first launch
        wp.launch(kr.accumulate_rotation_covariance, dim=self.n,
                  inputs=[self.rest_points, self.node_rest, self.node_index, self.node_weight, self.k,
                          self.node_position, self.target, self.fweight, self.weight_sum],
                  outputs=[self.covariance], device=d)
        if len(self.edge_from):
            wp.launch(kr.accumulate_edge_covariance, dim=len(self.edge_from),
                      inputs=[self.edge_from, self.edge_to, self.rest_offset, self.node_position, self.stiffness],
                      outputs=[self.covariance], device=d)
        wp.launch(kr.update_node_rotations, dim=self.K, inputs=[self.covariance], outputs=[self.node_rotation],
                  device=d)

    # ------------------------------------------------------------------ the fit
    def fit(self, frame, R: np.ndarray, P: np.ndarray, iterations: int, stiffness: float,
            stiffness_end: float, damping: float, hold=None):
        """Fit node rotations/positions to the frame, starting from (R, P) (float64 (K,3,3), (K,3)),
        which also serve as the damping's prior. ``hold``: (K,) per-node weights of a further pull
        towards the start (:meth:`set_hold`; None: none). Returns the fitted (R, P) (float64);
        self.points holds the skinned template."""
        o = self.opts
        min_cos = float(np.cos(np.radians(float(o["max_normal_angle"]))))
        its = max(int(iterations), 1)
        lams = np.geomspace(max(stiffness, 1e-12), max(stiffness_end, 1e-12), its) if its > 1 else [stiffness_end]
        self.set_state(R, P)
        wp.copy(self.position_prior, self.node_position)
        self._rebuild_unless_built_on(R, P)
        wd = float(damping) / self.K
        self.set_hold(hold)

        iterate = self._iteration(frame, min_cos, wd)

        extra = int(o.get("converge_iterations", 0) or 0)
        tol = float(o.get("converge_tolerance", 0.0) or 0.0) * float(np.min(self.g.spacing))
        # each stiffness level of the schedule is held (iterated again) while its iteration still
        # moved a node by more than converge_tolerance x the node spacing, up to
        # converge_iterations in all: large motion between frames needs the stiff levels
        # converged before the stiffness falls (one read-back of the nodes per check)
        done = 0
        held = int(np.ceil(HELD_LEVELS * its))
        for it in range(its):
            while True:
                check = extra > done and it < held
                if check:
                    wp.copy(self.position_prev, self.node_position)
                iterate(lams[it])
                if not check or self._moved() <= tol:
                    break
                done += 1
        self.skin()
        return self.get_state()

    def rigid_align(self, frame, R: np.ndarray, P: np.ndarray, iterations: int, min_step: float,
                    min_turn: float = 2e-3) -> tuple:
        """(R, P) with each part of the template (a connected piece of the graph) moved by the rigid
        motion that best fits it to the frame: symmetric point-to-plane ICP, Gauss-Newton on 6
        rigid unknowns per part, at most ``iterations`` (each: correspondences both ways as the
        fit's, a frame vertex counted for the part its closest template point lies on; the
        normal equations summed on the device, solved per part on the host), until every part's
        step turns less than ``min_turn`` [rad] and moves less than ``min_step`` [m]. A template
        vertex's plane is its own normal, a frame vertex's the frame's. The fit's point-to-point
        closest points move a surface along itself only part of the way per iteration (a body
        turning between frames: the template lags behind and slides); the planes' linearisation
        finds a rigid turn in a few steps. A step leaves out the directions the part's own surface
        cannot see (:func:`_observable_step`: a round part turning about its axis) rather than
        take them from the noise, and a part keeps its motion only where it lowers its two-sided
        mean squared plane distance below RIGID_GAIN of the start's and does not fit many of its
        nodes clearly worse and few better (:func:`_worse_in_places`: a fast limb on a still body).
        Pairs whose closest point lies on a rim are left out (``correspondences``' reject_rim: a
        partial scan's other edge). Returns float64 (K,3,3), (K,3) and
        whether the first step was already below both bounds everywhere (the start was as good
        as rigidly aligned; R, P are then returned as given)."""
        pts, fnormals = frame.points, frame.normals
        min_cos = float(np.cos(np.radians(float(self.opts["max_normal_angle"]))))
        R, P = np.asarray(R, np.float64), np.asarray(P, np.float64)
        C, part = self.num_parts, self.node_part
        if C == 0:
            return R, P, True
        cnt = np.maximum(np.bincount(part, minlength=C), 1)
        c = np.stack([np.bincount(part, P[:, a], C) for a in range(3)], 1) / cnt[:, None]
        self.part_center.assign(c.astype(np.float32))
        Rr, tr = np.repeat(np.eye(3)[None], C, 0), np.zeros((C, 3))
        iu = np.triu_indices(6)
        self.set_state(R, P)
        self.rebuild()

        def moved():
            return np.einsum("kij,kjl->kil", Rr[part], R), np.einsum("kij,kj->ki", Rr[part], P - c[part]) + c[part] + tr[part]

        energy = []  # per iteration: each part's two-sided mean squared plane distance [m^2]
        node_res = []  # per node, at the start and at the pose measured last (_node_residuals)
        for it in range(int(iterations) + 1):
            self.correspondences(frame, min_cos, reject_rim=True)
            self.rigid_system.zero_()
            for side, (dim, moving, fixed, normal, weight, element, owner) in enumerate((
                    (self.n, self.points, self.target, self.normals, self.fweight, self.vertex_ids, self.vertex_part),
                    (pts.shape[0], self.bclosest, pts, fnormals, self.bweight, self.bface, self.face_part))):
                wp.launch(kr.accumulate_rigid_system, dim=dim,
                          inputs=[owner, self.part_center, moving, fixed, normal, weight, element, side],
                          outputs=[self.rigid_system], device=self.device)
            S = self.rigid_system.numpy().astype(np.float64).reshape(C, 2, 29)
            W = S[:, :, 27]
            s = 0.5 / np.maximum(W, 1.0)  # each side a mean, the two weighted equally (as the fit's data term)
            energy.append((s * S[:, :, 28]).sum(axis=1))
            if it == int(iterations):
                node_res.append(self._node_residuals())
                break  # the last pose measured only
            seen = np.all(W >= RIGID_MIN_ROWS, axis=1)  # parts with partners both ways
            H = np.zeros((C, 6, 6))
            g = np.zeros((C, 6))
            for side in (0, 1):
                Hs = np.zeros((C, 6, 6))
                Hs[:, iu[0], iu[1]] = S[:, side, :21]
                H += s[:, side, None, None] * (Hs + np.triu(Hs, 1).transpose(0, 2, 1))
                g += s[:, side, None] * S[:, side, 21:27]
            d = np.zeros((C, 6))
            if seen.any():
                d[seen] = _observable_step(H[seen], g[seen])
            small = np.all((np.linalg.norm(d[:, :3], axis=1) < min_turn) & (np.linalg.norm(d[:, 3:], axis=1) < min_step))
            if small and it == 0:
                self._tree_pose = (R.copy(), P.copy())  # the tree stands on the start (fit() reuses it)
                return R, P, True
            if it == 0 or small:
                node_res.append(self._node_residuals())
            if small:
                break  # converged: the pose measured last is the one it ends on
            dR = rotation_from_vector(d[:, :3])  # x -> Rr (x - c) + c + tr, per part (unseen: d = 0)
            Rr, tr = dR @ Rr, np.einsum("pij,pj->pi", dR, tr) + d[:, 3:]
            self.skin(*moved())
        # a part keeps its rigid motion only where that fits it clearly better than the start (a
        # round part's turn fitted to the error of a reconstruction only fits it a little better)
        back = ~(energy[-1] < RIGID_GAIN * energy[0]) | _worse_in_places(node_res[0], node_res[-1], part, C)
        Rr[back], tr[back] = np.eye(3), 0.0
        return (*moved(), False)

    def _node_residuals(self) -> np.ndarray:
        """(K, 2) per node: the weighted sum of the squared plane distances [m^2] of the template
        vertices it is the nearest node of (forward correspondences, as last found) and their
        weight (one launch, K x 2 floats back)."""
        self.node_residual.zero_()
        wp.launch(kr.accumulate_node_residuals, dim=self.n,
                  inputs=[self.node_index, self.k, self.points, self.target, self.normals, self.fweight],
                  outputs=[self.node_residual], device=self.device)
        return self.node_residual.numpy().astype(np.float64)

    def _iteration(self, frame, min_cos: float, wd: float):
        """``iterate(lam)``: one iteration of the fit at stiffness ``lam`` (skin, correspondences,
        the system, the solve, the rotations). On CUDA its launches are captured once per fit
        (the frame and the template's tree stay for the fit) and replayed, the stiffness set
        in ``stiffness`` before each replay: ~20 launches' host time once instead of each
        iteration. Not in Warp's deterministic mode (its atomics' records need their own
        buffers)."""
        def launches():
            self.skin()
            self.correspondences(frame, min_cos)
            self.assemble(frame, None, wd)
            self.solve()
            self.update_rotations(None)

        def iterate(lam):
            self.stiffness.fill_(float(lam) / self.num_edges)
            if graph is None:
                launches()
            else:
                wp.capture_launch(graph)

        graph = None
        det = wp.get_module_options(kr).get("deterministic", wp.DeterministicMode.NOT_GUARANTEED)
        if self.device.is_cuda and det == wp.DeterministicMode.NOT_GUARANTEED:
            from .kernels import convert as kc

            self._frame_arrays(frame[1].shape[0])  # no allocation inside the capture
            # load only these modules before capturing: force_module_load would load (on a cold
            # cache, compile) every Warp module imported in the process, Newton's included
            wp.load_module(kr, device=self.device)
            wp.load_module(kc, device=self.device)
            with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
                launches()
            graph = cap.graph
        return iterate

    def set_hold(self, weights):
        """node_hold <- ``weights`` (K,) [per node, as the damping's weight]: node j is also held
        towards the fit's start (``position_prior``) with that weight; None or all zero: no hold
        (the solve then does exactly what it did without it)."""
        w = None if weights is None else np.asarray(weights, np.float32).reshape(-1)
        if w is None or not np.any(w > 0):
            if self._holding:
                self.node_hold.zero_()
                self._holding = False
            return
        self.node_hold.assign(w)
        self._holding = True

    def _moved(self) -> float:
        """The largest node displacement [m] of the last iteration (position_prev -> node_position):
        one launch and one float back."""
        self.moved.zero_()
        wp.launch(kr.measure_node_motion, dim=self.K, inputs=[self.node_position, self.position_prev],
                  outputs=[self.moved], device=self.device)
        return float(self.moved.numpy()[0])
