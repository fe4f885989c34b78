"""Topology conversion: a varying-topology sequence (a new mesh per frame, e.g. DG-Mesh's
marching cubes output) -> a fixed-topology sequence (one template, moving vertices).

Public API
----------
``nearest_surface(mesh, points, device=None, max_dist=None) -> NearestSurfaceResult``
    Batched closest point on a triangle mesh (``wp.Mesh`` or ``(V, F)``): closest point,
    face, barycentric weights of the face's vertices, distance; NumPy arrays.

``to_fixed_topology(seq, strategy="tracking", template=None, device=None, progress=False,
**options) -> FixedTopologySequence``
    Strategies (see docs/conversion.md):

    * ``"projection"``: every frame independently, each template vertex goes to its closest
      point on that frame's surface (barycentric interpolation on the closest face).
    * ``"tracking"``: start from the template, move each vertex to the closest point of the
      next frame's surface, frame after frame; every ``reanchor_interval`` frames (default 50;
      0 = never) blend ``tracked_weight`` (default 0.8) of the tracked positions with
      ``1 - tracked_weight`` of the direct template projection.
    * ``"regularized"``: tracking with a smooth displacement field, a two-sided data term and a
      tangential, rotation-aware relaxation towards the template's vertex distribution, then
      projection along normals; restarts from a bank of earlier results (or the template) when
      the fit to a frame is poor (a jump), and iterates more on large motion. Options:
      ``iterations`` (3), ``smooth_iterations`` (10), ``smooth_weight`` (0.5),
      ``pull_fraction`` (0.5), ``relax_iterations`` (3), ``relax_step`` (1.0),
      ``normal_slack`` (3.0), ``rigid_iterations`` (3), ``reinit_threshold`` (0.005),
      ``bank_interval`` (5), ``reinit_samples`` (1024), ``max_iterations`` (6),
      ``refine_threshold`` (0.002); thresholds are fractions of the frame's bbox diagonal.

    Common options: ``max_template_distance`` (0.25: the template must lie mostly within this
    fraction of frame 0's bounding-box diagonal from frame 0's surface), ``scale_tolerance``
    (4.0: warn about frames whose bounding-box diagonal differs from the median by more than
    this factor).

    The result carries ``result.conversion`` (a :class:`ConversionInfo`): strategy, options,
    re-anchored frames, per-frame time.

CLI: ``python -m dynmesh_warp.convert IN OUT --strategy tracking|projection|regularized
[--template MESH] [--device cpu] [--reanchor-interval 50] [--tracked-weight 0.8] [--fmt ply]``.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from .kernels import convert as kc
from .kernels.geometry import project_points_to_mesh
from .sequence import FixedTopologySequence, MeshDataError, VaryingTopologySequence, validate_mesh

__all__ = [
    "STRATEGIES",
    "NearestSurfaceResult",
    "ConversionInfo",
    "nearest_surface",
    "vertex_adjacency",
    "to_fixed_topology",
    "surface_deviation",
    "main",
]

STRATEGIES = ("projection", "tracking", "regularized", "graph")

_DEFAULTS = {
    "projection": {},
    "tracking": {"reanchor_interval": 50, "tracked_weight": 0.8},
    "regularized": {
        "iterations": 3,
        "smooth_iterations": 10,
        "smooth_weight": 0.5,
        "pull_fraction": 0.5,
        "relax_iterations": 3,
        "relax_step": 1.0,
        "normal_slack": 3.0,
        "rigid_iterations": 3,
        "reinit_threshold": 0.005,
        "max_iterations": 6,
        "refine_threshold": 0.002,
        "bank_interval": 5,
        "reinit_samples": 1024,
    },
    "graph": {
        # deformation graph (dynmesh_warp.deform_graph); lengths: fractions of the template's bbox diagonal
        "node_spacing": 0.05,
        "nodes_per_vertex": 4,
        "graph_iterations": 10,
        "stiffness": 10.0,
        "stiffness_end": 0.3,
        "damping": 0.01,
        "max_normal_angle": 60.0,
        "predict": 1.0,
        "restart_threshold": 0.02,
        "bank_interval": 10,
        # fine stage on the full-resolution template: "regularized"'s steps, 2 iterations
        "iterations": 2,
    },
}
_DEFAULTS["graph"].update({k: _DEFAULTS["regularized"][k] for k in (
    "smooth_iterations", "smooth_weight", "pull_fraction", "relax_iterations", "relax_step", "normal_slack")})
_COMMON = {"max_template_distance": 0.25, "scale_tolerance": 4.0}


# --------------------------------------------------------------------------- NearestSurface


@dataclass
class NearestSurfaceResult:
    """Closest points on a mesh. closest (Q,3) float32 [m]; face (Q,) int32, -1 where nothing
    lies within max_dist; bary (Q,3) float32 weights of the face's vertices F[face] (sum 1);
    dist (Q,) float32 [m] (max_dist where face is -1)."""

    closest: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    dist: np.ndarray


def _bbox_diag(V: np.ndarray) -> float:
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))) if len(V) else 0.0


def _wp_mesh(V: np.ndarray, F: np.ndarray, device) -> wp.Mesh:
    pts = wp.array(np.ascontiguousarray(V, np.float32), dtype=wp.vec3, device=device)
    idx = wp.array(np.ascontiguousarray(F, np.int32).reshape(-1), dtype=wp.int32, device=device)
    return wp.Mesh(points=pts, indices=idx)


def nearest_surface(mesh, points, device=None, max_dist: float | None = None,
                    source: str = "mesh") -> NearestSurfaceResult:
    """Closest point on ``mesh`` for every point (NearestSurface, one BVH query per point).

    Args:
        mesh: a ``wp.Mesh`` or a ``(V (N,3), F (M,3))`` pair (validated; bad faces raise
            :class:`MeshDataError` naming ``source``).
        points: (Q, 3) query points [m].
        device: Warp device (default: the mesh's device, else Warp's default).
        max_dist: search radius [m]; default: unbounded (10 x the diagonal of the box holding
            the mesh and the points, so every query finds its closest point).
    """
    P = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    if not np.isfinite(P).all():
        raise MeshDataError(f"{source}: query points contain NaN/inf")
    if isinstance(mesh, wp.Mesh):
        m = mesh
        device = m.device
        Vm = m.points.numpy()
    else:
        Vm, Fm = validate_mesh(mesh[0], mesh[1], source)
        device = wp.get_device(device)
        m = _wp_mesh(Vm, Fm, device)
    if max_dist is None:
        both = np.concatenate([Vm, P]) if len(P) else Vm
        max_dist = 10.0 * max(_bbox_diag(both), 1e-6)
    q = wp.array(P, dtype=wp.vec3, device=device)
    n = len(P)
    closest = wp.empty(n, dtype=wp.vec3, device=device)
    face = wp.empty(n, dtype=wp.int32, device=device)
    bary = wp.empty(n, dtype=wp.vec3, device=device)
    dist = wp.empty(n, dtype=float, device=device)
    if n:
        wp.launch(project_points_to_mesh, dim=n, inputs=[m.id, q, float(max_dist)],
                  outputs=[closest, face, bary, dist], device=device)
    return NearestSurfaceResult(closest.numpy(), face.numpy(), bary.numpy(), dist.numpy())


def vertex_adjacency(F: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR one-ring adjacency of a triangle mesh: (offsets int32 (N+1,), neighbors int32 (E,)),
    the neighbours of vertex i being neighbors[offsets[i]:offsets[i+1]] (sorted, unique)."""
    F = np.asarray(F, np.int64)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    e = np.unique(e[e[:, 0] != e[:, 1]], axis=0)
    counts = np.bincount(e[:, 0], minlength=num_vertices)
    offsets = np.zeros(num_vertices + 1, np.int32)
    np.cumsum(counts, out=offsets[1:])
    return offsets, e[:, 1].astype(np.int32)


def surface_deviation(V, F, V_ref, F_ref, device=None) -> dict:
    """Distances between two surfaces, via :func:`nearest_surface` in both directions.

    Returns ``to_ref`` (mean distance of V's vertices to the reference surface), ``from_ref``
    (mean distance of the reference vertices to the surface (V, F)), ``chamfer`` (the mean of
    the two), ``max_to_ref`` and ``max_from_ref``; all in scene units.
    """
    a = nearest_surface((V_ref, F_ref), V, device=device).dist
    b = nearest_surface((V, F), V_ref, device=device).dist
    return {"to_ref": float(a.mean()), "from_ref": float(b.mean()),
            "chamfer": 0.5 * float(a.mean() + b.mean()),
            "max_to_ref": float(a.max()), "max_from_ref": float(b.max())}


# --------------------------------------------------------------------------- converter


@dataclass
class ConversionInfo:
    """What a conversion did. reanchored_frames: frames where tracking blended in the template
    projection; frame_seconds: wall time per frame (host + kernels)."""

    strategy: str
    options: dict
    num_frames: int
    num_vertices: int
    reanchored_frames: list = field(default_factory=list)
    frame_seconds: list = field(default_factory=list)


class _Converter:
    """Template-side device arrays, allocated once; one wp.Mesh per input frame."""

    def __init__(self, TV: np.ndarray, TF: np.ndarray, device, max_dist: float, opts: dict):
        self.device = device
        self.opts = opts
        self.max_dist = float(max_dist)
        n = len(TV)
        self.n = n
        self.nf = len(TF)
        d = device
        arr = lambda a, dt: wp.array(a, dtype=dt, device=d)  # noqa: E731
        self.T = arr(TV, wp.vec3)
        self.TF = arr(TF.reshape(-1), wp.int32)
        self.X = wp.clone(self.T)
        self.P = wp.empty(n, dtype=wp.vec3, device=d)
        self.tmp = wp.empty(n, dtype=wp.vec3, device=d)
        self.closest = wp.empty(n, dtype=wp.vec3, device=d)
        self.face = wp.empty(n, dtype=wp.int32, device=d)
        self.bary = wp.empty(n, dtype=wp.vec3, device=d)
        self.dist = wp.empty(n, dtype=float, device=d)
        if opts.get("strategy") in ("regularized", "graph"):
            off, nb = vertex_adjacency(TF, n)
            self.offsets = arr(off, wp.int32)
            self.neighbors = arr(nb if len(nb) else np.zeros(1, np.int32), wp.int32)
            self.delta_T = wp.empty(n, dtype=wp.vec3, device=d)
            wp.launch(kc.compute_laplacian_coordinates, dim=n, inputs=[self.T, self.offsets, self.neighbors],
                      outputs=[self.delta_T], device=d)
            self.disp = wp.empty(n, dtype=wp.vec3, device=d)
            self.disp2 = wp.empty(n, dtype=wp.vec3, device=d)
            self.w = wp.empty(n, dtype=float, device=d)
            self.w2 = wp.empty(n, dtype=float, device=d)
            self.pull_sum = wp.zeros(n, dtype=wp.vec3, device=d)
            self.pull_weight = wp.zeros(n, dtype=float, device=d)
            self.normals = wp.zeros(n, dtype=wp.vec3, device=d)
            self.T_center = TV.mean(axis=0)
            self.Xm = wp.clone(self.T)  # points of the template-topology BVH (refit per use)
            self.tmesh = wp.Mesh(points=self.Xm, indices=self.TF)
            self.system = wp.zeros(42, dtype=float, device=d)
            self.score_fwd = wp.zeros(1, dtype=float, device=d)
            self.score_bwd = wp.zeros(1, dtype=float, device=d)
            self.bank = []  # (frame, positions (N,) wp.vec3, centroid (3,)) of earlier results
            self.reinit_sources = []  # (frame, source frame or -1 = template)
        if opts.get("strategy") == "graph":
            from .deform_graph import GraphFitter, build_deformation_graph

            self.graph = build_deformation_graph(TV, TF, float(opts["node_spacing"]) * max(_bbox_diag(TV), 1e-12),
                                                 int(opts["nodes_per_vertex"]))
            self.gf = GraphFitter(self.graph, TV, TF, d, self.max_dist, opts)
            self.history = []  # graph states (R, P) of the last two frames
            self.graph_bank = []  # (frame, R, P) every bank_interval frames: restart candidates
            self.recovered = []  # (frame, what it restarted from)
            self.coverage = []  # per frame: 99.5th percentile of input -> output distance [m]

    # --- building blocks
    def project(self, frame, src, dst):
        """dst = closest point of src on the frame surface (barycentric evaluation)."""
        m, pts, idx = frame
        wp.launch(project_points_to_mesh, dim=self.n, inputs=[m.id, src, self.max_dist],
                  outputs=[self.closest, self.face, self.bary, self.dist], device=self.device)
        wp.launch(kc.evaluate_barycentric_points, dim=self.n, inputs=[pts, idx, self.face, self.bary, src],
                  outputs=[dst], device=self.device)

    def _normals(self, X):
        self.normals.zero_()
        wp.launch(kc.accumulate_vertex_normals, dim=self.nf, inputs=[X, self.TF], outputs=[self.normals],
                  device=self.device)

    # --- strategies, one frame each; return True when the frame was re-anchored
    def step_projection(self, frame, t):
        self.project(frame, self.T, self.X)
        return False

    def step_tracking(self, frame, t):
        self.project(frame, self.T if t == 0 else self.X, self.X)
        k = int(self.opts["reanchor_interval"])
        if t > 0 and k > 0 and t % k == 0:
            self.project(frame, self.T, self.P)
            wp.launch(kc.blend_points, dim=self.n, inputs=[self.X, self.P, float(self.opts["tracked_weight"])],
                      outputs=[self.tmp], device=self.device)
            wp.copy(self.X, self.tmp)
            return True
        return False

    def rigid_align(self, frame, iterations: int):
        """Point-to-plane ICP of the whole template (damped Gauss-Newton, 6x6 solve on host)."""
        d, n = self.device, self.n
        m, pts, idx = frame
        for _ in range(iterations):
            wp.launch(project_points_to_mesh, dim=n, inputs=[m.id, self.X, self.max_dist],
                      outputs=[self.closest, self.face, self.bary, self.dist], device=d)
            center = self.X.numpy().mean(axis=0)
            self.system.zero_()
            wp.launch(kc.accumulate_point_to_plane_system, dim=n,
                      inputs=[self.X, wp.vec3(*center), self.closest, self.face, pts, idx],
                      outputs=[self.system], device=d)
            s = self.system.numpy().astype(np.float64)
            A, b = s[:36].reshape(6, 6), s[36:]
            A = A + np.diag(1e-3 * np.trace(A) / 6.0 + 1e-12 + 1e-3 * np.diag(A))
            try:
                xi = np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                return
            if not np.isfinite(xi).all():
                return
            R = _rotation_from_vector(xi[:3])
            wp.launch(kc.transform_points_rigid, dim=n,
                      inputs=[self.X, wp.mat33(*R.reshape(-1)), wp.vec3(*center), wp.vec3(*xi[3:])],
                      outputs=[self.X], device=d)
            if np.linalg.norm(xi[3:]) < 1e-7 * self.max_dist and np.linalg.norm(xi[:3]) < 1e-7:
                return

    def fit_score(self, frame, X, shift=(0.0, 0.0, 0.0)) -> float:
        """Two-sided mean distance between the template at positions X + shift and the frame,
        on about ``reinit_samples`` points per side: template vertices -> frame surface and
        frame vertices -> template surface (BVH refit)."""
        d, n = self.device, self.n
        m, pts, idx = frame
        ns = max(int(self.opts["reinit_samples"]), 1)
        s1, s2 = max(1, n // ns), max(1, pts.shape[0] // ns)
        k1, k2 = (n - 1) // s1 + 1, (pts.shape[0] - 1) // s2 + 1
        self.score_fwd.zero_()
        self.score_bwd.zero_()
        sh = wp.vec3(*[float(x) for x in shift])
        wp.launch(kc.sum_distances_to_mesh, dim=k1, inputs=[m.id, X, s1, sh, self.max_dist],
                  outputs=[self.score_fwd], device=d)
        wp.copy(self.Xm, X)
        self.tmesh.refit()
        wp.launch(kc.sum_distances_to_mesh, dim=k2, inputs=[self.tmesh.id, pts, s2, -sh, self.max_dist],
                  outputs=[self.score_bwd], device=d)
        return 0.5 * (float(self.score_fwd.numpy()[0]) / k1 + float(self.score_bwd.numpy()[0]) / k2)

    def reinitialize(self, frame, t) -> bool:
        """Robust restart after a jump: when the tracked (rigidly aligned) template fits frame t
        worse than ``reinit_threshold`` x its bbox diagonal (two-sided mean distance), try every
        stored earlier result and the template, each as is and moved onto the frame's centroid,
        and restart from the best one if it fits better. Returns True when it restarted."""
        o = self.opts
        thr = float(o["reinit_threshold"])
        if thr <= 0 or t == 0:
            return False
        V = frame[1].numpy()
        diag = _bbox_diag(V)
        cur = self.fit_score(frame, self.X)
        if cur <= thr * diag:
            return False
        cen_f = V.mean(axis=0)
        best = (cur, None, None, None)
        cands = self.bank + [(-1, self.T, self.T_center)]
        for tb, arr, cen in cands:
            for shift in (np.zeros(3), cen_f - cen):
                sc = self.fit_score(frame, arr, shift)
                if sc < best[0]:
                    best = (sc, tb, arr, shift)
        if best[2] is None:
            return False
        wp.copy(self.X, best[2])
        sh = best[3]
        wp.launch(kc.transform_points_rigid, dim=self.n,
                  inputs=[self.X, wp.mat33(*np.eye(3, dtype=np.float32).reshape(-1)), wp.vec3(0.0, 0.0, 0.0),
                          wp.vec3(*[float(x) for x in sh])], outputs=[self.X], device=self.device)
        self.rigid_align(frame, max(3 * int(o["rigid_iterations"]), 1))
        self.reinit_sources.append((t, int(best[1])))
        return True

    def remember(self, t):
        """Store frame t's result in the bank of restart candidates (every bank_interval frames)."""
        k = int(self.opts["bank_interval"])
        if float(self.opts["reinit_threshold"]) > 0 and k > 0 and t % k == 0:
            self.bank.append((t, wp.clone(self.X), self.X.numpy().mean(axis=0)))

    def step_regularized(self, frame, t):
        o = self.opts
        m, pts, idx = frame
        if int(o["rigid_iterations"]) > 0:
            self.rigid_align(frame, int(o["rigid_iterations"]))
        restarted = self.reinitialize(frame, t)
        for _ in range(int(o["iterations"]) * (2 if restarted else 1)):
            self.fit_nonrigid(frame)
        # large motion: keep iterating while the fit is poor and still improving
        extra = int(o["max_iterations"]) - int(o["iterations"])
        if extra > 0 and float(o["refine_threshold"]) > 0:
            diag = _bbox_diag(pts.numpy())
            sc = self.fit_score(frame, self.X)
            for _ in range(extra):
                if sc <= float(o["refine_threshold"]) * diag:
                    break
                wp.copy(self.P, self.X)
                self.fit_nonrigid(frame)
                sc2 = self.fit_score(frame, self.X)
                if sc2 > 0.95 * sc:
                    if sc2 > sc:
                        wp.copy(self.X, self.P)
                    break
                sc = sc2
        self.relax_and_project(frame)
        self.remember(t)
        return restarted

    def _graph_frame(self, frame):
        m, pts, idx = frame
        fn = wp.zeros(pts.shape[0], dtype=wp.vec3, device=self.device)
        wp.launch(kc.accumulate_vertex_normals, dim=idx.shape[0] // 3, inputs=[pts, idx], outputs=[fn],
                  device=self.device)
        return (m, pts, idx, fn)

    def _coverage(self, gframe, X) -> float:
        """99.5th percentile of the distance of the frame's vertices to the template at X [m]."""
        return float(np.percentile(self.gf.coverage_distances(gframe, X), 99.5))

    def step_graph(self, frame, t):
        from .deform_graph import extrapolate_rotations

        o, gf = self.opts, self.gf
        gframe = self._graph_frame(frame)
        diag = _bbox_diag(frame[1].numpy())
        rest = (np.repeat(np.eye(3)[None], gf.K, axis=0), self.graph.node_rest.copy())
        gam = float(o["predict"])
        if not self.history:
            init = rest
        elif len(self.history) == 1 or gam == 0:
            init = self.history[-1]
        else:
            (R0, P0), (R1, P1) = self.history[-2:]
            init = (extrapolate_rotations(R0, R1, gam), P1 + gam * (P1 - P0))
        its, lam0, lam1, mu = (int(o["graph_iterations"]), float(o["stiffness"]), float(o["stiffness_end"]),
                               float(o["damping"]))
        R, P = gf.fit(gframe, *init, its, lam0, lam1, mu)
        score = self._coverage(gframe, gf.points)
        restarted = False
        thr = float(o["restart_threshold"]) * diag
        if thr > 0 and score > thr and self.history:
            cands = [("previous frame", self.history[-1], False)]
            cands += [(f"frame {tb}", (Rb, Pb), True) for tb, Rb, Pb in self.graph_bank]
            cands.append(("template", rest, True))
            cen = frame[1].numpy().mean(axis=0)
            best = (score, None, R, P)
            for name, (Rc, Pc), shift in cands:
                if shift:
                    Pc = Pc + (cen - gf.skin(Rc, Pc).numpy().mean(axis=0))
                R2, P2 = gf.fit(gframe, Rc, Pc, 2 * its, lam0, lam1, mu)
                sc = self._coverage(gframe, gf.points)
                if sc < best[0]:
                    best = (sc, name, R2, P2)
            if best[1] is not None:
                _, name, R, P = best
                restarted = True
                self.recovered.append((t, name))
            gf.skin(R, P)
        wp.copy(self.X, gf.points)
        for _ in range(int(o["iterations"])):
            self.fit_nonrigid(frame)
        self.relax_and_project(frame)
        self.coverage.append(self._coverage(gframe, self.X))
        self.history = (self.history + [(R, P)])[-2:]
        k = int(o["bank_interval"])
        if k > 0 and t % k == 0:
            self.graph_bank.append((t, R.copy(), P.copy()))
        return restarted

    def fit_nonrigid(self, frame):
        """One iteration of the smooth two-sided data term (forward closest points + backward
        pulls, confidence-weighted Laplacian smoothing of the displacements)."""
        o, d, n = self.opts, self.device, self.n
        m, pts, idx = frame
        wp.launch(project_points_to_mesh, dim=n, inputs=[m.id, self.X, self.max_dist],
                  outputs=[self.closest, self.face, self.bary, self.dist], device=d)
        self.pull_sum.zero_()
        self.pull_weight.zero_()
        if o["pull_fraction"] > 0:
            wp.copy(self.Xm, self.X)
            self.tmesh.refit()
            wp.launch(kc.scatter_surface_pulls, dim=pts.shape[0],
                      inputs=[self.tmesh.id, self.TF, pts, self.max_dist],
                      outputs=[self.pull_sum, self.pull_weight], device=d)
        wp.launch(kc.compute_closest_displacements, dim=n,
                  inputs=[self.X, self.closest, self.face, self.pull_sum, self.pull_weight,
                          float(o["pull_fraction"])], outputs=[self.disp, self.w], device=d)
        for _s in range(int(o["smooth_iterations"])):
            wp.launch(kc.smooth_vectors_laplacian, dim=n,
                      inputs=[self.disp, self.w, self.offsets, self.neighbors, float(o["smooth_weight"])],
                      outputs=[self.disp2, self.w2], device=d)
            self.disp, self.disp2 = self.disp2, self.disp
            self.w, self.w2 = self.w2, self.w
        wp.launch(kc.add_displacements, dim=n, inputs=[self.X, self.disp, 1.0], outputs=[self.X], device=d)

    def relax_and_project(self, frame):
        """Tangential ARAP-style relaxation and projection along normals onto the frame."""
        o, d, n = self.opts, self.device, self.n
        m, pts, idx = frame
        for _r in range(max(int(o["relax_iterations"]), 1)):
            self._normals(self.X)
            if int(o["relax_iterations"]) > 0:
                wp.launch(kc.relax_points_tangentially, dim=n,
                          inputs=[self.X, self.normals, self.T, self.delta_T, self.offsets, self.neighbors,
                                  float(o["relax_step"])], outputs=[self.tmp], device=d)
            else:
                wp.copy(self.tmp, self.X)
            wp.launch(kc.project_points_along_normals, dim=n,
                      inputs=[m.id, self.tmp, self.normals, self.max_dist, float(o["normal_slack"])],
                      outputs=[self.X, self.dist], device=d)


def _rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by angle |w| about w / |w| (float32 (3,3))."""
    a = float(np.linalg.norm(w))
    if a < 1e-12:
        return np.eye(3, dtype=np.float32)
    k = w / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return (np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K).astype(np.float32)


def _as_varying(seq) -> VaryingTopologySequence:
    if isinstance(seq, VaryingTopologySequence):
        return seq
    if isinstance(seq, FixedTopologySequence):
        return seq.to_varying()
    if isinstance(seq, (list, tuple)):
        return VaryingTopologySequence(list(seq), name="frames", source="frames")
    raise TypeError(f"expected a VaryingTopologySequence, FixedTopologySequence or a list of (V, F), "
                    f"got {type(seq).__name__}")


def _resolve_options(strategy: str, options: dict) -> dict:
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    allowed = {**_COMMON, **_DEFAULTS[strategy]}
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise TypeError(f"to_fixed_topology(strategy={strategy!r}): unknown option(s) {unknown}; "
                        f"valid: {sorted(allowed)}")
    o = {**allowed, **options}
    if strategy == "tracking":
        ri = o["reanchor_interval"]
        if ri is None:
            ri = 0
        if int(ri) != ri or ri < 0:
            raise ValueError(f"reanchor_interval must be an integer >= 0 (0: never), got {ri!r}")
        o["reanchor_interval"] = int(ri)
        w = float(o["tracked_weight"])
        if not 0.0 <= w <= 1.0:
            raise ValueError(f"tracked_weight must lie in [0, 1], got {w!r}")
        o["tracked_weight"] = w
    if strategy == "regularized":
        for k in ("iterations", "smooth_iterations", "relax_iterations", "rigid_iterations", "bank_interval",
                  "max_iterations"):
            if int(o[k]) != o[k] or o[k] < 0:
                raise ValueError(f"{k} must be an integer >= 0, got {o[k]!r}")
        if int(o["reinit_samples"]) != o["reinit_samples"] or o["reinit_samples"] < 1:
            raise ValueError(f"reinit_samples must be an integer >= 1, got {o['reinit_samples']!r}")
        for k in ("reinit_threshold", "refine_threshold"):
            if not float(o[k]) >= 0:
                raise ValueError(f"{k} must be >= 0 (0: off), got {o[k]!r}")
        for k in ("smooth_weight", "pull_fraction", "relax_step"):
            if not 0.0 <= float(o[k]) <= 1.0:
                raise ValueError(f"{k} must lie in [0, 1], got {o[k]!r}")
        if float(o["normal_slack"]) < 1.0:
            raise ValueError(f"normal_slack must be >= 1, got {o['normal_slack']!r}")
    if not float(o["max_template_distance"]) > 0:
        raise ValueError(f"max_template_distance must be > 0, got {o['max_template_distance']!r}")
    o["strategy"] = strategy
    return o


def _check_scales(seq: VaryingTopologySequence, tol: float):
    diags = np.array([_bbox_diag(v) for v, _ in seq.frames])
    med = float(np.median(diags))
    if med <= 0:
        raise MeshDataError(f"{seq.source or seq.name}: every frame is degenerate (zero-size bounding box)")
    ratio = diags / med
    bad = np.flatnonzero((ratio > tol) | (ratio < 1.0 / tol))
    if bad.size:
        show = ", ".join(f"{int(t)} (x{ratio[t]:.3g})" for t in bad[:10])
        more = f" and {bad.size - 10} more" if bad.size > 10 else ""
        warnings.warn(
            f"{seq.source or seq.name}: frames of very different scale: bounding-box diagonal vs the "
            f"median {med:.4g} in frame(s) {show}{more}; converted vertices will be pulled across "
            "the gap (mixed units or a broken frame?)", UserWarning, stacklevel=3)


def _check_reach(TV, TF, V0, F0, limit: float, device):
    diag = _bbox_diag(V0)
    d = nearest_surface((V0, F0), TV, device=device).dist
    far = d > limit * diag
    frac = float(far.mean())
    if frac > 0.5:
        raise MeshDataError(
            f"template: {100 * frac:.0f}% of its {len(TV)} vertices lie farther than "
            f"{limit:g} x frame 0's bounding-box diagonal ({limit * diag:.4g}) from frame 0's surface "
            f"(median distance {np.median(d):.4g}); the template does not describe this sequence "
            "(other units, other placement?)")
    if frac > 0.05:
        warnings.warn(
            f"template: {100 * frac:.0f}% of its vertices lie farther than {limit:g} x frame 0's "
            f"bounding-box diagonal from frame 0's surface", UserWarning, stacklevel=3)


def to_fixed_topology(seq, strategy: str = "tracking", template=None, device=None, progress: bool = False,
                      should_stop=None, **options) -> FixedTopologySequence:
    """Convert a varying-topology sequence into a fixed-topology one on ``template``'s faces.

    Args:
        seq: a :class:`VaryingTopologySequence` (or a fixed one, or a list of (V, F) frames).
        strategy: ``"projection"``, ``"tracking"`` or ``"regularized"`` (module docstring).
        template: ``(V, F)`` mesh or a mesh file path; default: the first frame.
        device: Warp device (default: Warp's default device).
        progress: show a tqdm progress bar over frames.
        should_stop: a callable checked between frames (e.g. the CLI's Ctrl-C flag); once true
            the conversion ends after the frames done so far (at least the first): the result
            then holds frames 0..k-1 only.
        **options: strategy options (module docstring); unknown names raise TypeError.

    Returns:
        FixedTopologySequence with the template's faces, the input's fps and name, and a
        ``conversion`` attribute (:class:`ConversionInfo`); fewer frames than the input only
        after ``should_stop``.

    Raises:
        MeshDataError: an empty/invalid frame or template (naming it), a template out of the
            surface's reach. Warns (UserWarning) about frames of very different scale.
    """
    o = _resolve_options(strategy, options)
    vseq = _as_varying(seq)
    where = vseq.source or vseq.name
    for t, (v, f) in enumerate(vseq.frames):  # frames may have been mutated after construction
        src = vseq.frame_sources[t] if vseq.frame_sources else where
        validate_mesh(v, f, src, t)
    if template is None:
        TV, TF = vseq.frames[0]
    else:
        if isinstance(template, (str, bytes)) or hasattr(template, "__fspath__"):
            from .io import read_mesh

            template = read_mesh(template)
        try:
            tv, tf = template
        except (TypeError, ValueError):
            raise MeshDataError("template: expected a (V, F) pair or a mesh file path") from None
        TV, TF = validate_mesh(tv, tf, "template")
    TV = np.ascontiguousarray(TV, np.float32)
    TF = np.ascontiguousarray(TF, np.int32)
    device = wp.get_device(device)
    _check_scales(vseq, float(o["scale_tolerance"]))
    if template is not None:
        _check_reach(TV, TF, *vseq.frames[0], float(o["max_template_distance"]), device)

    all_diag = max(max(_bbox_diag(v) for v, _ in vseq.frames), _bbox_diag(TV), 1e-6)
    conv = _Converter(TV, TF, device, 10.0 * all_diag, o)
    step = getattr(conv, f"step_{strategy}")
    T = vseq.num_frames
    out = np.empty((T, len(TV), 3), np.float32)
    info = ConversionInfo(strategy, {k: v for k, v in o.items() if k != "strategy"}, T, len(TV))
    frames = range(T)
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, desc=f"convert ({strategy})", unit="frame")
    done = T
    for t in frames:
        if t > 0 and should_stop is not None and should_stop():
            done = t
            break
        t0 = time.perf_counter()
        v, f = vseq.frames[t]
        pts = wp.array(v, dtype=wp.vec3, device=device)
        idx = wp.array(f.reshape(-1), dtype=wp.int32, device=device)
        m = wp.Mesh(points=pts, indices=idx)
        if step((m, pts, idx), t):
            info.reanchored_frames.append(t)
        out[t] = conv.X.numpy()
        info.frame_seconds.append(time.perf_counter() - t0)
        if not np.isfinite(out[t]).all():
            raise RuntimeError(f"{where}: conversion ({strategy}) produced NaN/inf at frame {t}; "
                               "the input frame may be degenerate")
    if hasattr(frames, "close"):
        frames.close()
    res = FixedTopologySequence(out[:done], TF, fps=vseq.fps, name=vseq.name, source=vseq.source)
    res.conversion = info
    return res


# --------------------------------------------------------------------------- CLI


class _TimedFrames(list):
    """The frames of a sequence being converted, noting when the converter asks for each: after
    the second frame (the first includes compilation) it prints an estimate when the whole
    conversion will take more than ``limit_s``, naming faster options. Values are unchanged."""

    def __init__(self, frames, device, strategy: str, limit_s: float = 60.0):
        super().__init__(frames)
        self.device, self.strategy, self.limit_s = str(device), strategy, limit_s
        self.t1 = None
        self.done = False

    def __getitem__(self, t):
        if isinstance(t, int) and not self.done:
            if t == 1 and self.t1 is None:
                self.t1 = time.perf_counter()
            elif t >= 2 and self.t1 is not None:
                self.done = True
                per = time.perf_counter() - self.t1
                total = per * len(self)
                if total > self.limit_s:
                    faster = [] if self.device.startswith("cuda") else ["--device cuda (a GPU)"]
                    if self.strategy != "projection":
                        faster.append("--strategy projection (fastest, least accurate)")
                    _note(f"estimate: {per:.1f} s per frame, about {_duration(total)} for {len(self)} frames on "
                          f"{self.device}" + (f"; faster: {', '.join(faster)}" if faster else ""))
        return super().__getitem__(t)


def _duration(s: float) -> str:
    return f"{s / 3600:.1f} h" if s >= 5400 else f"{s / 60:.0f} min" if s >= 90 else f"{s:.0f} s"


def _note(msg: str) -> None:
    try:
        from tqdm import tqdm

        tqdm.write(msg, file=sys.stderr)
    except ImportError:  # pragma: no cover
        print(msg, file=sys.stderr)


#: suffixes an output path must not have: a folder of frames is written without an extension
_FILE_SUFFIXES = {".json", ".txt", ".csv", ".zip", ".npy", ".png", ".yaml", ".yml", ".h5", ".pkl"}


from .cli import interruptible_main  # noqa: E402 (the CLI section's own import)


@interruptible_main
def main(argv=None) -> int:
    from .cli import Parser

    p = Parser(
        prog="python -m dynmesh_warp.convert",
        description="Convert a varying-topology mesh sequence into a fixed-topology one.")
    p.add_argument("input", help="sequence: .npz, folder of per-frame meshes, DG-Mesh scene folder")
    p.add_argument("output", help="output .npz, or a folder (frame_XXXX.ply/.obj, see --fmt)")
    p.add_argument("--strategy", choices=STRATEGIES, default="tracking")
    p.add_argument("--template", default=None, help="template mesh file (default: the first frame)")
    p.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0")
    p.add_argument("--reanchor-interval", type=int, default=None, help="tracking: frames between re-anchors (0: never)")
    p.add_argument("--tracked-weight", type=float, default=None, help="tracking: weight of the tracked positions at a re-anchor")
    p.add_argument("--iterations", type=int, default=None, help="regularized: outer iterations per frame")
    p.add_argument("--smooth-iterations", type=int, default=None, help="regularized: displacement smoothing steps")
    p.add_argument("--fmt", default=None, choices=["ply", "obj"], help="per-frame format for a folder output (default ply)")
    p.add_argument("--fps", type=float, default=None, help="override the input frame rate")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output (in a folder: only files this tool wrote; others are kept)")
    a = p.parse_args(argv)
    from .cli import checking_stops, quiet_warp, stop_reason

    quiet_warp(a.device)
    from .io import MESH_EXTENSIONS, load_sequence, save_sequence
    from .outputs import check_output

    opts = {}
    for k in ("reanchor_interval", "tracked_weight"):
        if getattr(a, k) is not None:
            if a.strategy != "tracking":
                p.error(f"--{k.replace('_', '-')} applies to --strategy tracking")
            opts[k] = getattr(a, k)
    for k in ("iterations", "smooth_iterations"):
        if getattr(a, k) is not None:
            if a.strategy != "regularized":
                p.error(f"--{k.replace('_', '-')} applies to --strategy regularized")
            opts[k] = getattr(a, k)
    try:
        # everything is checked before the sequence is loaded: options, input, template, output
        try:
            _resolve_options(a.strategy, opts)
        except (TypeError, ValueError) as e:
            raise ValueError(f"--{str(e).split(' ', 1)[0].replace('_', '-')}: {str(e).split(' ', 1)[-1]}") from None
        if a.fps is not None and not (np.isfinite(a.fps) and a.fps > 0):
            raise ValueError(f"--fps must be a positive, finite frame rate, got {a.fps}")
        from .scene import resolve_device

        device = resolve_device(a.device, "--device")
        if not Path(a.input).expanduser().exists():
            raise ValueError(f"input {a.input}: file or folder not found")
        if a.template is not None and not Path(a.template).expanduser().is_file():
            raise ValueError(f"--template {a.template}: file not found")
        inputs = [a.input] + ([a.template] if a.template else [])
        out_suffix = Path(a.output).suffix.lower()
        if out_suffix == ".npz":
            if a.fmt:
                raise ValueError(f"--fmt {a.fmt}: applies to a folder output, not to {a.output}")
            check_output(a.output, kind="file", what="output", inputs=inputs, overwrite=a.overwrite,
                         suffixes={".npz"})
        else:
            if out_suffix in MESH_EXTENSIONS or out_suffix in _FILE_SUFFIXES:
                raise ValueError(f"output {a.output}: a sequence does not fit in one {out_suffix} file; give a "
                                 ".npz file, or a folder (frames written as frame_XXXX.ply, or .obj with --fmt obj)")
            a.fmt = a.fmt or "ply"
            check_output(a.output, kind="folder", what="output", inputs=inputs, overwrite=a.overwrite,
                         writes=("frame_*.ply", "frame_*.obj"))
        seq = load_sequence(a.input, fps=a.fps)
        if isinstance(seq, FixedTopologySequence):
            print(f"note: {a.input} already has fixed topology ({seq.num_frames} frames); converting it "
                  "anyway (it can be simulated as it is)", file=sys.stderr)
            seq = seq.to_varying()
        seq.frames = _TimedFrames(seq.frames, device, a.strategy)
        with checking_stops():  # Ctrl-C / SIGTERM: stop between frames, write the frames done
            res = to_fixed_topology(seq, strategy=a.strategy, template=a.template, device=device,
                                    progress=True, should_stop=stop_reason, **opts)
            reason = stop_reason() if res.num_frames < seq.num_frames else None
            status = {"complete": not reason, "frames": res.num_frames, "input_frames": seq.num_frames,
                      "interrupted_by": reason, "strategy": a.strategy}
            save_sequence(res, a.output, fmt=a.fmt, overwrite=a.overwrite, status=status)
    except (MeshDataError, FileNotFoundError, ValueError, TypeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if reason:
        print(f"interrupted by {reason} after frame {res.num_frames - 1} of {seq.num_frames}: wrote {a.output} with "
              f"frames 0..{res.num_frames - 1} (status: complete false)", file=sys.stderr)
        import signal

        return 128 + int(getattr(signal, reason, signal.SIGINT))
    info = res.conversion
    print(f"wrote {a.output}: {res.num_frames} frames x {res.num_vertices} vertices, {res.num_faces} faces "
          f"({a.strategy}; {sum(info.frame_seconds):.2f} s"
          + (f"; re-anchored at {info.reanchored_frames}" if info.reanchored_frames else "") + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
