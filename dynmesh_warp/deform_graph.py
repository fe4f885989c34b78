"""Embedded deformation graph (Sumner, Schmid & Pauly, SIGGRAPH 2007) for the ``graph``
conversion strategy: a template tracked through a sequence as a deforming surface with few
degrees of freedom, so that a limb moves as a whole instead of sliding vertex by vertex.

``build_deformation_graph(V, F, spacing, k=4) -> DeformationGraph``
    Nodes: template vertices picked by farthest-point sampling until every vertex lies within
    ``spacing`` of a node, per connected component, then more nodes until every vertex is within
    2 x ``spacing`` of one along the surface (geodesic, Dijkstra on the edge graph). Each vertex
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
prediction. Each iteration: correspondences (kernels), the dense K x K normal equations in p
(accumulated by kernels, solved by Cholesky on the host in float64), then the rotations
(local step: polar part of the rotation covariance, edges + data, batched SVD).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .kernels import register as kr


__all__ = ["DeformationGraph", "build_deformation_graph", "GraphFitter", "polar_rotations",
           "extrapolate_rotations"]


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


def _farthest_points(P: np.ndarray, spacing: float, start: int) -> list:
    d = np.full(len(P), np.inf)
    out = []
    i = start
    while True:
        out.append(i)
        d = np.minimum(d, np.linalg.norm(P - P[i], axis=1))
        i = int(np.argmax(d))
        if d[i] <= spacing:
            return out


def build_deformation_graph(V, F, spacing: float, k: int = 4, max_nodes: int = 4000) -> DeformationGraph:
    """The embedded deformation graph of mesh (V, F) (module docstring).

    Args:
        spacing: node spacing [m] (farthest-point sampling radius).
        k: nodes per vertex (>= 1).
        max_nodes: refuse (ValueError) a spacing that would need more nodes than this.
    """
    from scipy.sparse.csgraph import connected_components, dijkstra
    from scipy.spatial import cKDTree

    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    n = len(V)
    if not spacing > 0:
        raise ValueError(f"node spacing must be > 0, got {spacing}")
    k = int(k)
    if k < 1:
        raise ValueError(f"nodes per vertex must be >= 1, got {k}")
    G = _edge_graph(V, F)
    ncomp, labels = connected_components(G, directed=False)
    used = np.zeros(n, bool)
    used[F.reshape(-1)] = True
    nodes = []
    for c in range(ncomp):
        idx = np.flatnonzero((labels == c) & used)
        if len(idx) == 0:
            continue
        sub = _farthest_points(V[idx], spacing, 0)
        nodes.extend(idx[sub].tolist())
        if len(nodes) > max_nodes:
            raise ValueError(f"deformation graph: node spacing {spacing:.4g} needs more than {max_nodes} "
                             "nodes; raise the spacing")
    # geodesic coverage: every vertex within 2 x spacing of a node along the surface
    for _ in range(max_nodes):
        dist = dijkstra(G, directed=False, indices=nodes, min_only=True)
        dist[~used] = 0.0
        far = int(np.argmax(dist))
        if dist[far] <= 2.0 * spacing:
            break
        nodes.append(far)
    nodes = np.asarray(nodes, np.int64)
    K = len(nodes)
    if K > max_nodes:
        raise ValueError(f"deformation graph: node spacing {spacing:.4g} needs more than {max_nodes} nodes; "
                         "raise the spacing")
    # k+1 geodesically nearest nodes per vertex (chunks of sources, limited search radius)
    limit = 4.0 * spacing
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
                            e.astype(np.int64), float(spacing))


def polar_rotations(C: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotations R maximising tr(R^T C_j) (C = sum y x^T: R x ~ y), det +1."""
    U, _, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    U = U.copy()
    U[:, :, 2] *= d[:, None]
    return U @ Vt


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
    a = gamma * ang
    Kx = np.zeros_like(D)
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = axis[:, 2], -axis[:, 1], axis[:, 0]
    Dg = np.eye(3) + np.sin(a)[:, None, None] * Kx + (1 - np.cos(a))[:, None, None] * (Kx @ Kx)
    return Dg @ R1


def _solve_sparse_spd(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve A x = b for the graph's sparse, symmetric positive definite normal matrix (K,K)
    with a sparse LU (single-threaded SuperLU: a dense multithreaded LAPACK solve of this size
    slows down 50x when the cores are busy, e.g. next to Warp's CPU kernels)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    try:
        return splu(sp.csc_matrix(A)).solve(b)
    except RuntimeError:  # exactly singular (no data, no damping): least squares
        return np.linalg.lstsq(A, b, rcond=None)[0]


class GraphFitter:
    """Device arrays and host solve of the graph fit (module docstring)."""

    def __init__(self, graph: DeformationGraph, TV: np.ndarray, TF: np.ndarray, device, max_dist: float,
                 opts: dict):
        self.g = graph
        self.device = d = device
        self.opts = opts
        self.max_dist = float(max_dist)
        self.n = len(TV)
        self.K = graph.num_nodes
        self.k = graph.node_index.shape[1]
        arr = lambda a, dt: wp.array(a, dtype=dt, device=d)  # noqa: E731
        self.rest_points = arr(np.ascontiguousarray(TV, np.float32), wp.vec3)
        self.indices = arr(np.ascontiguousarray(TF, np.int32).reshape(-1), wp.int32)
        self.node_rest = arr(graph.node_rest.astype(np.float32), wp.vec3)
        self.node_index = arr(graph.node_index.reshape(-1), wp.int32)
        self.node_weight = arr(graph.node_weight.reshape(-1), float)
        K, n = self.K, self.n
        self.node_rotation = wp.empty(K, dtype=wp.mat33, device=d)
        self.node_position = wp.empty(K, dtype=wp.vec3, device=d)
        self.points = wp.empty(n, dtype=wp.vec3, device=d)
        # the template BVH: built on the predicted pose by rebuild() at the start of every fit
        # (a tree refit far from the pose it was built on answers queries slowly)
        self.mesh_points = wp.empty(n, dtype=wp.vec3, device=d)
        self.tmesh = None
        self.normals = wp.zeros(n, dtype=wp.vec3, device=d)
        self.target = wp.empty(n, dtype=wp.vec3, device=d)
        self.fface = wp.empty(n, dtype=wp.int32, device=d)
        self.fbary = wp.empty(n, dtype=wp.vec3, device=d)
        self.fweight = wp.empty(n, dtype=float, device=d)
        self.fdist = wp.empty(n, dtype=float, device=d)
        self.system = wp.zeros(K * K, dtype=float, device=d)
        self.rhs = wp.zeros(K, dtype=wp.vec3, device=d)
        self.covariance = wp.zeros(K, dtype=wp.mat33, device=d)
        self._frame_cap = 0
        # host: ARAP graph term (directed both ways), constant Laplacian
        e = graph.edges
        self.ej = np.concatenate([e[:, 0], e[:, 1]])
        self.el = np.concatenate([e[:, 1], e[:, 0]])
        g = graph.node_rest
        self.rest_offset = g[self.el] - g[self.ej]  # (2E, 3)
        L = np.zeros((K, K))
        np.add.at(L, (self.ej, self.ej), 1.0)
        np.add.at(L, (self.el, self.el), 1.0)
        np.add.at(L, (self.ej, self.el), -1.0)
        np.add.at(L, (self.el, self.ej), -1.0)
        self.L = L
        self.num_edges = max(len(self.ej), 1)

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

    def skin(self, R: np.ndarray, P: np.ndarray, out=None):
        """Template positions for node rotations R (K,3,3) and positions P (K,3) -> ``out``
        (default self.points); also refits the template BVH and the vertex normals."""
        d = self.device
        self.node_rotation.assign(wp.array(R.astype(np.float32), dtype=wp.mat33, device=d))
        self.node_position.assign(wp.array(P.astype(np.float32), dtype=wp.vec3, device=d))
        out = self.points if out is None else out
        wp.launch(kr.skin_vertices, dim=self.n,
                  inputs=[self.rest_points, self.node_rest, self.node_index, self.node_weight, self.k,
                          self.node_rotation, self.node_position], outputs=[out], device=d)
        return out

    def rebuild(self, R: np.ndarray, P: np.ndarray):
        """Rebuild the template BVH on the template skinned by (R, P)."""
        wp.copy(self.mesh_points, self.skin(R, P))
        self.tmesh = wp.Mesh(points=self.mesh_points, indices=self.indices)

    def _update_template(self):
        from .kernels import convert as kc

        wp.copy(self.mesh_points, self.points)
        self.tmesh.refit()
        self.normals.zero_()
        wp.launch(kc.accumulate_vertex_normals, dim=len(self.indices) // 3, inputs=[self.points, self.indices],
                  outputs=[self.normals], device=self.device)

    def correspondences(self, frame, min_cos: float):
        """Forward and backward correspondences for the current self.points."""
        m, pts, idx, fnormals = frame
        d = self.device
        self._update_template()
        wp.launch(kr.find_correspondences, dim=self.n,
                  inputs=[m.id, pts, idx, self.points, self.normals, self.max_dist, min_cos],
                  outputs=[self.target, self.fface, self.fbary, self.fweight, self.fdist], device=d)
        self._find_backward(frame, self.points, min_cos)

    def _find_backward(self, frame, X, min_cos: float):
        """Frame -> template correspondences against the template BVH (already refit to X)."""
        m, pts, idx, fnormals = frame
        q = pts.shape[0]
        self._frame_arrays(q)
        wp.launch(kr.find_correspondences, dim=q,
                  inputs=[self.tmesh.id, X, self.indices, pts, fnormals, self.max_dist, min_cos],
                  outputs=[self.bclosest, self.bface, self.bbary, self.bweight, self.bdist], device=self.device)

    # ------------------------------------------------------------------ the fit
    def fit(self, frame, R: np.ndarray, P: np.ndarray, iterations: int, stiffness: float,
            stiffness_end: float, damping: float):
        """Fit node rotations/positions to the frame, starting from (R, P) (float64 (K,3,3), (K,3)),
        which also serve as the damping's prior. Returns the fitted (R, P); self.points holds
        the skinned template."""
        o = self.opts
        d = self.device
        K, n = self.K, self.n
        min_cos = float(np.cos(np.radians(float(o["max_normal_angle"]))))
        R = R.copy()
        P = P.copy()
        P_prior = P.copy()
        q = frame[1].shape[0]
        its = max(int(iterations), 1)
        lams = np.geomspace(max(stiffness, 1e-12), max(stiffness_end, 1e-12), its) if its > 1 else [stiffness_end]
        self.rebuild(R, P)
        for it in range(its):
            lam = float(lams[it])
            self.skin(R, P)
            self.correspondences(frame, min_cos)
            fw = self.fweight.numpy()
            bw = self.bweight.numpy()[:q]
            nf = max(float(fw.sum()), 1.0)
            nb = max(float(bw.sum()), 1.0)
            self.system.zero_()
            self.rhs.zero_()
            wp.launch(kr.accumulate_forward_system, dim=n,
                      inputs=[self.node_index, self.node_weight, self.k, K, self.points, self.node_position,
                              self.target, self.fweight, 0.5 / nf], outputs=[self.system, self.rhs], device=d)
            wp.launch(kr.accumulate_backward_system, dim=q,
                      inputs=[self.indices, self.node_index, self.node_weight, self.k, K, self.points,
                              self.node_position, frame[1], self.bface, self.bbary, self.bweight, 0.5 / nb],
                      outputs=[self.system, self.rhs], device=d)
            A = self.system.numpy().astype(np.float64).reshape(K, K)
            b = self.rhs.numpy().astype(np.float64)
            # ARAP graph term: (lam / E) sum |p_l - p_j - R_j (g_l - g_j)|^2
            wr = lam / self.num_edges
            dvec = np.einsum("eab,eb->ea", R[self.ej], self.rest_offset)
            rb = np.zeros((K, 3))
            np.add.at(rb, self.el, dvec)
            np.add.at(rb, self.ej, -dvec)
            A += wr * self.L
            b += wr * rb
            # damping towards the prior
            wd = damping / K
            A[np.diag_indices(K)] += wd + 1e-12
            b += wd * P_prior
            A = 0.5 * (A + A.T)
            P = _solve_sparse_spd(A, b)
            # local step: rotations from the edges and the data, regularised towards the old R
            self.node_position.assign(wp.array(P.astype(np.float32), dtype=wp.vec3, device=d))
            self.covariance.zero_()
            wp.launch(kr.accumulate_rotation_covariance, dim=n,
                      inputs=[self.rest_points, self.node_rest, self.node_index, self.node_weight, self.k,
                              self.node_position, self.target, self.fweight, 0.5 / nf],
                      outputs=[self.covariance], device=d)
            C = self.covariance.numpy().astype(np.float64)
            cur = P[self.el] - P[self.ej]
            Ce = np.einsum("ea,eb->eab", cur, self.rest_offset) * wr
            np.add.at(C, self.ej, Ce)
            scale = np.linalg.norm(C, axis=(1, 2))
            C += (1e-3 * scale + 1e-12)[:, None, None] * R
            R = polar_rotations(C)
        self.skin(R, P)
        return R, P
