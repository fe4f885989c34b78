"""The conversion's fit (``convert``): the per-frame converter of every strategy
(:class:`_Converter`), the frame loop from the key frame forward then backward, the repair of
poor runs, the per-frame records and the journal hooks (``convert --resume``)."""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import time

import numpy as np
import warp as wp

from .convert_base import (ConversionInfo, _Frame, _bbox_diag, _device_frame, _longest_edges, _mark_fitted,
                           _stop_before_fitting, _stride, vertex_adjacency)
from .convert_input import (_check_reach, _dropout_run, _far_parts, _frame_areas, _frame_motion, _key_frame_floaters,
                            _node_spacing, _same_frame)
from .convert_journal import ConversionJournal, frame_digest
from .convert_report import DROPOUT_FRAMES, JUMP_WINDOW, POOR_WEB, WEB_GAP, WEB_STRETCH
from .deform_graph import (GraphFitter, GraphFrame, build_deformation_graph, extrapolate_rotations, node_groups, rim_array,
                           rotation_from_vector)
from .geometry import fit_group_motions
from .kernels import convert as kc
from .kernels import register as kr
from .kernels.geometry import project_points_to_mesh
from .sequence import FixedTopologySequence, carried


class _Coverage(float):
    """A fit's coverage [m] (:meth:`_Converter.coverage`: the 99.5th percentile of the input's
    distances to it) that carries ``tail``, their 99.9th percentile [m]. A float, so the fit's
    comparisons use the coverage; the tail travels with the kept fit's score to
    ``ConversionInfo.coverage_tail``."""

    def __new__(cls, value: float, tail: float):
        self = super().__new__(cls, value)
        self.tail = float(tail)
        return self


class _Converter:
    """Template-side device arrays, allocated once; one wp.Mesh per input frame."""

    def __init__(self, TV: np.ndarray, TF: np.ndarray, device, max_dist: float, opts: dict, node_spacing=None):
        """``node_spacing``: the graph's node spacing [m] (``graph`` only), a float or one per
        template vertex, from :func:`_node_spacing`."""
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
        # (M,) each face's longest edge in the template [m] (the web's reference)
        self.key_edge = arr(_longest_edges(TV, TF).astype(np.float32), float)
        self.web_area = wp.zeros(3, dtype=float, device=d)
        self.fold_area = wp.zeros(3, dtype=float, device=d)
        self.last_off = 0.0  # the fraction of the converted surface off the input at the last flipped()
        self.last_area = 0.0  # the converted surface's area [m^2] at the last flipped()
        self.last_buried = 0.0  # the buried fraction of the last web() call
        self.first = True  # the next frame is the first one converted (starts from the template)
        # the next frame repeats the input frame fitted before it exactly (set by the frame loop)
        self.input_repeats = False
        self.frame_coverage = None  # set by a step that already measured its result's coverage [m]
        self.frame_web = None  # ... and its (web, buried) fractions
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
            # the whole-template rigid ICP (rigid_align): one part, its rows' planes the target faces'
            self.rigid_system = wp.zeros((2, 29), dtype=float, device=d)
            self.one_part = wp.zeros(n, dtype=wp.int32, device=d)
            self.part_center = wp.zeros(1, dtype=wp.vec3, device=d)
            self.plane_normal = wp.zeros(n, dtype=wp.vec3, device=d)
            self.unit_weight = wp.full(n, 1.0, dtype=float, device=d)
            self.vertex_ids = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=d)
            self.score_fwd = wp.zeros(1, dtype=float, device=d)
            self.score_bwd = wp.zeros(1, dtype=float, device=d)
            self.bank = []  # (frame, positions (N,) wp.vec3, centroid (3,)) of earlier results
            self.reinit_sources = []  # (frame, source frame or -1 = template)
        if opts.get("strategy") == "graph":
            self.graph = build_deformation_graph(TV, TF, node_spacing, int(opts["nodes_per_vertex"]))
            self.gf = GraphFitter(self.graph, TV, TF, d, self.max_dist, opts)
            self.history = []  # graph states (R, P) of the last two frames
            self.scores = []  # coverage [m] of the frames converted so far
            self.graph_bank = []  # (frame, R, P) every bank_interval frames: restart candidates
            self.recovered = []  # (frame, what it restarted from)
            self.failed_restart = None  # coverage [m] of the last restart that found nothing better
            self.frame_states = {}  # frame -> graph state (R, P) of its result (the repair pass, rewind)
            self.restarts_failed = []  # frames whose restart candidates all fitted worse

    # --- sequence control
    def rewind(self, X: np.ndarray, t_from: int, t_before: int | None):
        """Go on from frame t_from's result X (N,3): the backward pass after the forward one
        (t_from the key frame, t_before the frame after it), or past a bridged input dropout (the
        frame before it, and the one before that). The graph strategy predicts from frames
        t_before and t_from (the pass continues their motion)."""
        self._set_result(X)
        self.first = False
        if self.opts.get("strategy") == "graph":
            fs = self.frame_states
            self.history = ([fs[t_before]] if t_before in fs else []) + [fs[t_from]]

    def _set_result(self, X: np.ndarray) -> None:
        """self.X <- X (N, 3) [m] from the host."""
        self.X.assign(wp.array(np.ascontiguousarray(X, np.float32), dtype=wp.vec3, device=self.device))

    def web(self, frame, diag: float) -> float:
        """:func:`web_fraction` of the converted surface (self.X) against the input ``frame``
        (its wp.Mesh, already built for the fit), relative to the template; ``diag``: the
        frame's bbox diagonal [m]. Stretched faces far from a closed input but inside it (the
        buried walls of parts in contact, which no sphere outside meets) are not the web: their
        fraction goes to ``last_buried``. One launch, three floats back; a second only where a
        frame has far stretched faces and its closedness was not known yet (asked then, kept)."""
        known = frame.known_closed
        total, web, buried = self._web_areas(frame, diag, int(bool(known)))
        if known is None and web > 0 and frame.closed:
            total, web, buried = self._web_areas(frame, diag, 1)
        self.last_buried = float(buried / total) if total > 0 else 0.0
        return float(web / total) if total > 0 else 0.0

    def _web_areas(self, frame, diag: float, closed: int) -> np.ndarray:
        self.web_area.zero_()
        wp.launch(kc.measure_web_area, dim=self.nf,
                  inputs=[self.TF, self.key_edge, self.X, frame[0].id, WEB_STRETCH, WEB_GAP * diag, closed],
                  outputs=[self.web_area], device=self.device)
        return self.web_area.numpy()

    def flipped(self, frame, diag: float) -> float:
        """The fraction of the converted surface's area (self.X) whose faces point against the
        input ``frame``'s surface nearest to them (within ``WEB_GAP`` x ``diag``; a fold-over),
        :func:`~dynmesh_warp.kernels.convert.measure_flipped_area`; the fraction with no input point
        within that gap goes to ``last_off``. One launch, three floats back."""
        self.fold_area.zero_()
        wp.launch(kc.measure_flipped_area, dim=self.nf, inputs=[self.TF, self.X, frame[0].id, WEB_GAP * diag],
                  outputs=[self.fold_area], device=self.device)
        total, flipped, off = self.fold_area.numpy()
        self.last_area = float(total)
        self.last_off = float(off / total) if total > 0 else 0.0
        return float(flipped / total) if total > 0 else 0.0

    def coverage(self, frame) -> "_Coverage":
        """99.5th percentile of the distance of the frame's vertices to the converted surface
        (the template at self.X) [m], carrying their 99.9th as ``tail``."""
        m, pts, idx = frame
        q = pts.shape[0]
        # a BVH built on a copy of X (rebuilt, not refit: a tree refit far from the pose it was
        # built on answers slowly; the copy keeps the tree's points apart from X)
        mesh = wp.Mesh(points=wp.clone(self.X), indices=self.TF)
        dist = wp.empty(q, dtype=float, device=self.device)
        wp.launch(kc.measure_distances_to_mesh, dim=q, inputs=[mesh.id, pts, self.max_dist], outputs=[dist],
                  device=self.device)
        return _Coverage(*np.percentile(dist.numpy(), (99.5, 99.9)))

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
        self.project(frame, self.T if self.first else self.X, self.X)
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
            self.part_center.assign(center[None].astype(np.float32))
            wp.launch(kr.gather_face_normals, dim=n, inputs=[pts, idx, self.face], outputs=[self.plane_normal], device=d)
            self.rigid_system.zero_()
            wp.launch(kr.accumulate_rigid_system, dim=n,
                      inputs=[self.one_part, self.part_center, self.X, self.closest, self.plane_normal, self.unit_weight,
                              self.vertex_ids, 0], outputs=[self.rigid_system], device=d)
            s = self.rigid_system.numpy()[0].astype(np.float64)
            A = np.zeros((6, 6))
            A[np.triu_indices(6)] = s[:21]
            A = A + np.triu(A, 1).T
            b = -s[21:27]  # the rows' residual is (x - closest) . n: the step solves A xi = -J e
            A = A + np.diag(1e-3 * np.trace(A) / 6.0 + 1e-12 + 1e-3 * np.diag(A))
            try:
                xi = np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                return
            if not np.isfinite(xi).all():
                return
            R = rotation_from_vector(xi[:3]).astype(np.float32)
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
        if thr <= 0 or self.first:
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

    def _graph_frame(self, frame: _Frame) -> GraphFrame:
        m, pts, idx = frame
        fn = wp.zeros(pts.shape[0], dtype=wp.vec3, device=self.device)
        wp.launch(kc.accumulate_vertex_normals, dim=idx.shape[0] // 3, inputs=[pts, idx], outputs=[fn],
                  device=self.device)
        # the rim matters to the rigid start where the surfaces are partial views; found only where
        # the template is open (a partial scan's), as it costs a host pass over the frame's edges
        # (which also tells whether the frame is closed: not asked again)
        rim = None
        if self.gf.face_rim is not None and frame.known_closed is not True:
            rim = rim_array(frame.faces, self.device)
            frame.known_closed = rim is None
        return GraphFrame(m, pts, idx, fn, rim)

    def _graph_finish(self, frame, R, P):
        """The fine stage on the full-resolution template after the graph fit (R, P): the smooth
        two-sided fit and the relaxation of ``regularized``. Returns the coverage [m]."""
        self.gf.skin(R, P)
        wp.copy(self.X, self.gf.points)
        for _ in range(int(self.opts["iterations"])):
            self.fit_nonrigid(frame)
        self.relax_and_project(frame)
        return self.coverage(frame)

    def static_nodes(self, frame, diag: float) -> np.ndarray:
        """(K,) bool: the graph nodes held still this frame. A node is static where the input
        surface did not move since the frame fitted before: every template vertex bound to the
        node or to a node within STATIC_RINGS graph edges of it lies, where the last fit left it
        (self.X), within ``static_tolerance`` x the diagonal of this frame's surface (a surface
        moving along itself somewhere, a translating ball's band around its direction of motion,
        moves across itself next to it). Distances cannot tell a still surface from one sliding
        along itself, so each connected region of static nodes is then held only where
        :func:`_still_regions` finds the moving parts around it cannot be carrying it. None before
        two frames are fitted (no motion of the moving parts yet)."""
        g = self.graph
        if len(self.history) < 2:
            return np.zeros(g.num_nodes, bool)
        m = frame[0]
        n = self.X.shape[0]
        dist = wp.empty(n, dtype=float, device=self.device)
        tol = float(self.opts["static_tolerance"]) * diag
        wp.launch(kc.measure_distances_to_mesh, dim=n, inputs=[m.id, self.X, 2.0 * tol], outputs=[dist],
                  device=self.device)
        moved = dist.numpy() > tol
        idx, w = g.node_index.reshape(n, -1), g.node_weight.reshape(n, -1)
        own = np.zeros(g.num_nodes, bool)
        own[idx[moved[:, None] & (w > 0)]] = True
        e = np.asarray(g.edges, np.int64).reshape(-1, 2)
        static = ~_grow_nodes(own, e, STATIC_RINGS)  # a node next to a moving one within STATIC_RINGS edges moves
        return self._still_regions(static, own, e, frame, tol) if static.any() else static

    def _still_regions(self, static, own, e, frame, tol: float) -> np.ndarray:
        """``static`` (K,) less the regions (connected sets of static nodes over the graph's edges
        ``e``) that the moving parts around them may be carrying along themselves. Around a
        region: the nodes within STATIC_RINGS + 2 edges of it whose own vertices moved (``own``).
        Its moving parts: their connected groups whose nodes moved a median over 2 x ``tol``
        (meters) between the last two fitted frames (slower ones are a fit's noise: a whole
        body moving under the tolerance has no moving part, and nothing pulls it). Each part's
        nodes near the region, and all nodes around it together, give a rigid motion (their
        motion between the last two frames, Kabsch); a region that one of them moves by a median
        over ``tol`` while keeping it on this frame's surface (99th percentile of the distances
        under half that move) may be moving with them, along itself: a cylinder sliding along
        its axis with its caps, a box spinning in the plane of its faces with its sides, a walker's
        torso with its shoulders. Held: a region with a moving part around it, and no such motion
        (a still torso turned by the legs' swing would leave its surface)."""
        g, m, n = self.graph, frame[0], self.X.shape[0]
        (_, P0), (_, P1) = self.history[-2:]
        reg, mov = node_groups(g, static), node_groups(g, own)
        idx, w = g.node_index.reshape(n, -1), g.node_weight.reshape(n, -1)
        owner = idx[np.arange(n), np.argmax(w, axis=1)]  # each vertex's heaviest node
        X = self.X.numpy()
        out = static.copy()
        for r in np.unique(reg[static]):
            region = static & (reg == r)
            around = _grow_nodes(region, e, STATIC_RINGS + 2) & own
            parts = [c for c in np.unique(mov[around])
                     if np.median(np.linalg.norm(P1[mov == c] - P0[mov == c], axis=1)) > 2.0 * tol]
            if not parts:
                out[region] = False
                continue
            xr = X[region[owner]]
            for S in [around & (mov == c) for c in parts] + [around]:
                if S.sum() < 3:
                    continue
                c0 = P0[S].mean(axis=0)
                Rm, tm, _ = fit_group_motions(P0[S] - c0, P1[S], np.zeros(int(S.sum()), np.int64), 1)
                moved = (xr - c0) @ Rm[0].T + tm[0]
                step = float(np.median(np.linalg.norm(moved - xr, axis=1)))
                if step <= tol:
                    continue  # it would not move the region: no sign against holding it
                d = wp.empty(len(moved), dtype=float, device=self.device)
                wp.launch(kc.measure_distances_to_mesh, dim=len(moved),
                          inputs=[m.id, wp.array(moved.astype(np.float32), dtype=wp.vec3, device=self.device),
                                  4.0 * step], outputs=[d], device=self.device)
                if float(np.percentile(d.numpy(), 99)) <= 0.5 * step:
                    out[region] = False  # it may move with them, along itself
                    break
        return out

    def rigid_nodes(self, init: tuple, moved: tuple, static) -> tuple:
        """The start (R, P) of each graph node: the rigidly aligned one (``moved``, from
        GraphFitter.rigid_align, a rigid motion per part of the template) for the nodes of the
        parts with no node held still this frame (``static`` (K,) bool, the static hold's, or
        None), else the prediction (``init``). A part with a still region is not moving as a
        whole: a rigid motion that fits its moving regions in part (legs swinging in opposite
        phase read as a turn of the whole figure) would turn the still region with them (the
        still, round torso between the legs, which fits the frame as well turned)."""
        if static is None or not static.any():
            return tuple(moved)
        part = self.gf.node_part
        take = ~np.isin(part, part[static])
        return np.where(take[:, None, None], moved[0], init[0]), np.where(take[:, None], moved[1], init[1])

    def step_graph(self, frame, t):
        o, gf = self.opts, self.gf
        gframe = self._graph_frame(frame)
        diag = _bbox_diag(frame[1].numpy())
        rest = (np.repeat(np.eye(3)[None], gf.K, axis=0), self.graph.node_rest.copy())
        hold = None
        static = None
        if float(o["static_hold"]) > 0:
            static = self.static_nodes(frame, diag)
        gam = float(o["predict"])
        if not self.history:
            init = rest
        elif len(self.history) == 1 or gam == 0 or self.input_repeats:
            # an input frame that repeats the one before it shows no motion: none is predicted
            # (along a surface that looks the same the data cannot take a predicted velocity back:
            # a new user's ball that had stopped kept turning 3.7 degrees a frame over 15 repeated
            # frames, a draped cloth flowed 1 % of the diagonal a frame)
            init = self.history[-1]
        else:
            (R0, P0), (R1, P1) = self.history[-2:]
            # constant velocity overshoots where the motion reverses (a wing beat, a leg's stride):
            # the prediction scaled by k / (n - 1) from 0 (the previous pose) to 1, the start
            # pose with the lowest two-sided fit score kept
            n = int(o["predict_candidates"])
            best = None
            for k in range(n):
                g = gam * (k / (n - 1) if n > 1 else 1.0)
                cand = (extrapolate_rotations(R0, R1, g), P1 + g * (P1 - P0))
                sc = self.fit_score(frame, gf.skin(*cand)) if n > 1 else 0.0
                if best is None or sc < best[0]:
                    best = (sc, cand)
            init = best[1]
        if self.history and int(o["rigid_iterations"]) > 0:
            *moved, aligned = gf.rigid_align(gframe, *init, int(o["rigid_iterations"]), RIGID_STEP * diag)
            if not aligned:
                init = self.rigid_nodes(init, moved, static)
        if static is not None and static.any():
            # a still part starts where it was and is held there (the constant-velocity prediction
            # carried a drift the data cannot see on from frame to frame)
            R1, P1 = self.history[-1]
            init = (np.where(static[:, None, None], R1, init[0]), np.where(static[:, None], P1, init[1]))
            hold = np.where(static, float(o["static_hold"]) / gf.K, 0.0)
        its, lam0, lam1, mu = (int(o["graph_iterations"]), float(o["stiffness"]), float(o["stiffness_end"]),
                               float(o["damping"]))
        R, P = gf.fit(gframe, *init, its, lam0, lam1, mu, hold=hold)
        score = self._graph_finish(frame, R, P)
        # large motion: a fit that still leaves the input uncovered gets more rounds (each a new
        # stiffness schedule from where it stands) while they improve the coverage by 10 %
        for _ in range(int(o["refine_rounds"])):
            if score <= float(o["restart_threshold"]) * diag:
                break
            X_prev = wp.clone(self.X)
            R2, P2 = gf.fit(gframe, R, P, its, lam0, lam1, mu)
            sc = self._graph_finish(frame, R2, P2)
            if sc >= score:  # no better: keep the last result
                wp.copy(self.X, X_prev)
                break
            improved = sc < 0.9 * score
            R, P, score = R2, P2, sc
            if not improved:
                break
        restarted = False
        # drift control: a fit that leaves part of the input uncovered (well above this sequence's
        # coverage so far), or that stretches faces across a gap of the input (a web: the other
        # side's residual), restarts from stored states and keeps the least poor
        thr = float(o["restart_threshold"]) * diag
        floor = 3.0 * float(np.median(self.scores)) if len(self.scores) >= 3 else 0.0
        web_on = bool(o["restart_on_web"]) and thr > 0

        def badness(sc):  # (> 1: poor, (its web, buried) or None) of the fit in self.X, whose coverage is sc [m]
            b = sc / max(thr, floor) if thr > 0 else 0.0
            if not web_on:
                return b, None
            w = self.web(frame, diag)
            # buried faces count as much as the web here: besides the walls of parts in contact,
            # they are a template crumpled inside the body, which a restart mends (a new user's
            # droplet: 12 % of its area inside on 5 frames when they did not count)
            return max(b, (w + self.last_buried) / POOR_WEB), (w, self.last_buried)

        bad, web = badness(score)
        poor = bad > 1.0
        if not poor:
            self.failed_restart = None
        # after a restart that found nothing better (e.g. the input changed topology and no
        # state of this template covers it), try again only once the fit is 1.5x worse still
        retry = self.failed_restart is None or bad > 1.5 * self.failed_restart
        if poor and retry and self.history:
            best = (bad, None, R, P, wp.clone(self.X), score, web)
            cands = [("previous frame", self.history[-1], False)]
            cands += [(f"frame {tb}", (Rb, Pb), True) for tb, Rb, Pb in self.graph_bank[-3:]]
            cands.append(("template", rest, True))
            cen = frame[1].numpy().mean(axis=0)
            starts = []
            for name, (Rc, Pc), shift in cands:
                if shift:
                    Pc = Pc + (cen - gf.skin(Rc, Pc).numpy().mean(axis=0))
                starts.append((name, Rc, Pc))
            keep = int(o["restart_fits"])
            if 0 < keep < len(starts):  # fit only the starts that already fit the frame best
                pre = [self.fit_score(frame, gf.skin(Rc, Pc)) for _, Rc, Pc in starts]
                starts = best_starts(starts, pre, keep)
            for name, Rc, Pc in starts:
                R2, P2 = gf.fit(gframe, Rc, Pc, its, lam0, lam1, mu)
                sc = self._graph_finish(frame, R2, P2)
                b, w = badness(sc)
                if b < best[0]:
                    best = (b, name, R2, P2, wp.clone(self.X), sc, w)
            if best[1] is not None:  # the winner gets a second round of iterations, at the final stiffness
                R2, P2 = gf.fit(gframe, best[2], best[3], its, lam1, lam1, mu)
                sc = self._graph_finish(frame, R2, P2)
                b, w = badness(sc)
                if b < best[0]:
                    best = (b, best[1], R2, P2, wp.clone(self.X), sc, w)
            before = bad
            bad, name, R, P, X, score, web = best
            wp.copy(self.X, X)
            if name is not None:
                restarted = True
                self.recovered.append((t, name))
            if bad < 0.9 * before:
                self.failed_restart = None
            else:  # nothing fitted clearly better (10 %): do not retry on every frame
                self.failed_restart = bad
                if name is None:  # no start fitted better at all (a better one is a recovered frame)
                    self.restarts_failed.append(t)
        self._commit_graph(t, R, P, score)
        self.frame_coverage = score
        self.frame_web = web  # (web, buried) measured on the kept fit (None: not measured here)
        return restarted

    def _commit_graph(self, t: int, R: np.ndarray, P: np.ndarray, score: float) -> None:
        """Frame t's graph state (R, P) and coverage [m] into the sequence's memory: the history
        the next frame predicts from, the states the repair pass and rewind go back to, the bank
        of restart candidates (:meth:`step_graph`, and :meth:`replay_step` for a journal's frame)."""
        self.scores.append(score)
        self.history = (self.history + [(R, P)])[-2:]
        self.frame_states[t] = (R, P)
        k = int(self.opts["bank_interval"])
        if k > 0 and t % k == 0:
            self.graph_bank.append((t, R.copy(), P.copy()))

    # --- the journal (convert --resume; convert_journal)
    def step_record(self, t: int) -> dict:
        """What the last step (frame t) changed in this converter besides the result self.X, as
        NumPy arrays for a journal record: :meth:`replay_step` applies it again."""
        s = self.opts.get("strategy")
        if s == "graph":
            R, P = self.frame_states[t]
            # few members (a record is written while the fit goes on: each costs the writer time)
            rec = {"R": R, "P": P, "graph": np.array([
                self.scores[-1], np.nan if self.failed_restart is None else self.failed_restart,
                bool(self.restarts_failed) and self.restarts_failed[-1] == t], np.float64)}
            if self.recovered and self.recovered[-1][0] == t:
                rec["recovered"] = np.str_(self.recovered[-1][1])
            return rec
        if s == "regularized":
            src = self.reinit_sources[-1][1] if self.reinit_sources and self.reinit_sources[-1][0] == t else -2
            return {"reinit_source": np.int64(src)}
        return {}

    def replay_step(self, t: int, X: np.ndarray, rec: dict) -> None:
        """Frame t as the step left it, from a journal record (:meth:`step_record`) and the
        result X (N, 3): the converter goes on as if it had fitted the frame."""
        self._set_result(X)
        self.frame_coverage = self.frame_web = None
        s = self.opts.get("strategy")
        if s == "graph":
            score, failed, restart_failed = (float(x) for x in rec["graph"])
            self._commit_graph(t, np.asarray(rec["R"]), np.asarray(rec["P"]), score)
            if "recovered" in rec:
                self.recovered.append((t, str(rec["recovered"])))
            if restart_failed:
                self.restarts_failed.append(t)
            self.failed_restart = None if np.isnan(failed) else failed
        elif s == "regularized":
            if int(rec["reinit_source"]) != -2:
                self.reinit_sources.append((t, int(rec["reinit_source"])))
            self.remember(t)

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


def _grow_nodes(mask: np.ndarray, e: np.ndarray, rings: int) -> np.ndarray:
    """``mask`` (K,) bool grown by ``rings`` steps along the graph edges ``e`` (E, 2)."""
    out = mask.copy()
    for _ in range(rings):
        ring = out.copy()  # (set, not |=: a node on several edges is indexed more than once)
        ring[e[out[e[:, 1]], 0]] = True
        ring[e[out[e[:, 0]], 1]] = True
        out = ring
    return out


#: called as ``timer(seconds, done, frames)`` after each frame a run fits (not one taken from the
#: journal): that frame's wall time [s], the frames the run has done so far (fitted or taken from
#: the journal, this one included) and its number of frames. The ``convert`` CLI's estimate
#: (:class:`~dynmesh_warp.convert_cli.FrameEstimate`); it counted the reads of the frame list,
#: and the input's checks read three frames in one millisecond first (a new user's 24 frames of
#: 400k vertices, 28-62 s each, had no estimate)
FRAME_TIMER: contextvars.ContextVar = contextvars.ContextVar("convert_frame_timer", default=None)
#: what the run in progress is, said in its progress bar's label where it is not the first run (a
#: segment's frames with a template of their own): a new user's 10 frames showed four bare bars
RUN_LABEL: contextvars.ContextVar = contextvars.ContextVar("convert_run_label", default="")


@contextlib.contextmanager
def run_labelled(label: str):
    """Runs started within carry ``label`` in their progress bar (:data:`RUN_LABEL`)."""
    token = RUN_LABEL.set(label)
    try:
        yield
    finally:
        RUN_LABEL.reset(token)


#: the journal of the conversion under way (``journal`` of :func:`to_fixed_topology` /
#: :func:`to_piecewise_fixed`): every run it starts (:func:`_convert_from_key`) writes its frames there
_JOURNAL: contextvars.ContextVar[ConversionJournal | None] = contextvars.ContextVar("conversion_journal", default=None)


@contextlib.contextmanager
def _journaling(journal: ConversionJournal | None):
    """The runs inside write to ``journal`` (None: to the journal already set, if any)."""
    if journal is None:
        yield
        return
    token = _JOURNAL.set(journal)
    try:
        yield
    finally:
        _JOURNAL.reset(token)
        journal.close()  # every fit given to it is on disk when the conversion returns


#: the static hold's neighbourhood: a node is static when it and every node within this many
#: graph edges are. (Two rings were taken for a while to stop a translating ball's band from being
#: held; the cause was the rings' expansion, which dropped neighbours of nodes on several edges:
#: with it mended one ring keeps the ball's motion, 2.2 % of the diagonal a frame as without the
#: hold, and holds more of a still torso: 19.5 degrees of turn against 39 with two)
STATIC_RINGS = 1


#: the rigid start (option rigid_iterations) stops at a step that moves less than this fraction of
#: the frame's diagonal (and turns less than 2e-3 rad); where its first step already does, the
#: prediction is kept as it is (most frames of a smooth motion)
RIGID_STEP = 1e-3


def _frame_for_fit(vseq, t: int, K: int, o: dict, X_ref, TF: np.ndarray, device, info, frame=None) -> tuple:
    """Input frame t as the fit sees it: without small parts far from ``X_ref`` (the converted
    neighbour frame it is tracked from; :func:`_far_parts`, noted in ``info.ignored_parts``),
    at the key frame without its floaters (:func:`_key_frame_floaters`: the template is that
    frame), and elsewhere as it is while ``far_part_area`` is 0 (``frame``: ``vseq.frames[t]``
    when the caller has it)."""
    v, f = vseq.frames[t] if frame is None else frame
    if t == K:
        v2, f2, parts, nv = _key_frame_floaters(vseq, K, o, device)
    elif float(o.get("far_part_area", 0.0)) <= 0:
        return v, f
    else:
        v2, f2, parts, nv = _far_parts(v, f, X_ref, TF, float(o["far_part_area"]), float(o["far_part_gap"]), device)
    if parts:
        info.ignored_parts[t] = (parts, nv)
    else:
        info.ignored_parts.pop(t, None)
    return v2, f2


@dataclasses.dataclass
class _PerFrame:
    """The per-frame figures of one conversion run, (T,) each, by input frame: wall time [s], and
    the fractions that ``ConversionInfo`` reports (coverage, coverage_tail, web, buried, flipped),
    and the converted area [m^2]."""

    seconds: np.ndarray
    coverage: np.ndarray
    tail: np.ndarray
    web: np.ndarray
    buried: np.ndarray
    flipped: np.ndarray
    area: np.ndarray
    off: np.ndarray
    input_motion: np.ndarray

    @classmethod
    def zeros(cls, T: int) -> "_PerFrame":
        return cls(*(np.zeros(T) for _ in dataclasses.fields(cls)))


#: the per-frame figures a journal record keeps (:func:`_convert_frames`), in its ``figures``
#: followed by the input's motion and whether the frame was re-anchored ("off" last: a journal
#: written before it was measured replays without it, 0)
_PER_FRAME_RECORD = ("seconds", "coverage", "tail", "web", "buried", "flipped", "area", "off")


def _record_fit(conv, frame, diag: float, pf: _PerFrame, t: int) -> None:
    """Frame t's coverage, tail, web, buried and flipped fractions of the fit in ``conv.X`` into
    ``pf`` (the coverage and web measured on the kept fit when the fit did)."""
    cov = conv.frame_coverage if conv.frame_coverage is not None else conv.coverage(frame)
    pf.coverage[t], pf.tail[t] = cov / max(diag, 1e-12), cov.tail / max(diag, 1e-12)
    pf.web[t], pf.buried[t] = conv.frame_web if conv.frame_web is not None else (conv.web(frame, diag), conv.last_buried)
    conv.frame_coverage = conv.frame_web = None
    pf.flipped[t] = conv.flipped(frame, diag)
    pf.area[t], pf.off[t] = conv.last_area, conv.last_off


#: how far (x the diagonal) :func:`_input_motion` looks for the other frame's surface
INPUT_MOTION_REACH = 1.0e4


def _input_motion(frame, points, diag: float, device) -> float:
    """How far the input surface moved between a neighbouring frame and ``frame``: the 99th
    percentile of the neighbour's sampled vertices ``points`` (device) distances to ``frame``'s
    surface, over the diagonal ``diag`` (``ConversionInfo.input_motion``; one launch on the
    frame's own BVH). Looked for up to INPUT_MOTION_REACH diagonals: it stopped at one, so a body
    moving two diagonals a frame read as 1, and its output, which followed it, as sliding 2.8x
    along it (a new user's)."""
    dist = wp.empty(points.shape[0], dtype=float, device=device)
    wp.launch(kc.measure_distances_to_mesh, dim=points.shape[0],
              inputs=[frame[0].id, points, float(INPUT_MOTION_REACH * diag)], outputs=[dist], device=device)
    return float(np.percentile(dist.numpy(), 99)) / max(diag, 1e-12)


def _motion_sample(v: np.ndarray, device):
    """At most 4,096 of a frame's vertices on the device (for :func:`_input_motion`)."""
    return wp.array(np.ascontiguousarray(v[::_stride(len(v), 4096)], np.float32), dtype=wp.vec3, device=device)


def _convert_frames(vseq, conv, step, K: int, progress: bool, should_stop, info, strategy: str, where: str, TV,
                    TF, stop_forward=None, journal=None):
    """The frame loop of to_fixed_topology: the key frame forward to the end, then backward to
    frame 0. ``stop_forward(t, web, buried)`` (the per-frame figures so far), asked after each
    frame t > K: true ends the forward pass there (the backward pass still runs). ``journal``: the
    run's :class:`~dynmesh_warp.convert_journal.RunJournal`: each frame fitted is written to it, and
    a frame it holds is taken from it instead of fitted. Returns (out (T, N, 3), lo, hi (the
    converted frames lo..hi), the per-frame figures (:class:`_PerFrame`))."""
    T = vseq.num_frames
    device = conv.device
    out = np.empty((T, len(TV), 3), np.float32)
    pf = _PerFrame.zeros(T)
    # the key frame forward to the end, then backward from it to frame 0
    order = list(range(K, T)) + list(range(K - 1, -1, -1))
    if progress:
        from tqdm import tqdm

        label = RUN_LABEL.get()
        order = tqdm(order, desc=f"convert ({strategy}{', ' + label if label else ''})", unit="frame")
    lo = hi = None  # the converted frames lo..hi (contiguous: the key frame forward, then backward)
    forward = True
    done = 0  # frames done (fitted, or taken from the journal) so far: a frame's place in the journal
    samples = {}  # the sampled vertices (device) of the key frame and the last frame fitted
    raw = {}  # the input frames (V, F) fitted last, by frame
    bridge = bool(info.options["bridge_dropouts"])
    for t in order:
        if lo is not None and should_stop is not None and should_stop():
            break
        if t > K and not forward:
            continue
        t0 = time.perf_counter()
        if t == K - 1:
            conv.rewind(out[K], K, K + 1)
        s = 1 if t > K else -1  # the pass's direction (the key frame: either)
        # the frames just passed a dropout (they lack a part: host work on the input and the
        # motion measured so far)? Then this one starts from the frame before them, as if they
        # were not there (their output is bridged afterwards)
        p = _loop_dropout(vseq, pf.input_motion, t, s, K, device, info) if bridge and abs(t - K) >= 2 else None
        if p is not None:
            conv.rewind(out[p], p, p - s)
        ref = None if t == K else out[t - s] if p is None else out[p]
        # a frame that repeats the input frame fitted before it exactly (a stalled capture, an
        # animation on twos): the fit starts where it was (graph: no predicted motion)
        raw[t] = vseq.frames[t]
        u = raw.get(t - s if p is None else p)
        conv.input_repeats = t != K and u is not None and _same_frame(raw[t], u)
        raw = {k: raw[k] for k in raw if k == K or abs(k - t) <= DROPOUT_FRAMES + 1}  # the backward pass starts at K
        v, f = _frame_for_fit(vseq, t, K, info.options, ref, TF, device, info, raw[t])
        index = done
        done += 1
        rec = journal.replay(index, t, raw[t]) if journal is not None else None
        m = max(t, t - s)  # where the input's motion from the neighbour fitted before is stored
        if rec is not None:  # fitted before the interruption: the journal's result and state change
            out[t] = rec["X"]
            conv.replay_step(t, out[t], rec)
            *figures, motion, reanchored = (float(x) for x in rec["figures"])
            if reanchored:
                info.reanchored_frames.append(t)
            for name, x in zip(_PER_FRAME_RECORD, figures):
                getattr(pf, name)[t] = x
            if samples.get(t - s) is not None:
                pf.input_motion[m] = motion
        else:
            frame = _device_frame(v, f, device)
            reanchored = bool(step(frame, t))
            if reanchored:
                info.reanchored_frames.append(t)
            change = conv.step_record(t) if journal is not None else None
            diag = _bbox_diag(v)
            _record_fit(conv, frame, diag, pf, t)
            # the input's own motion from the neighbour fitted before (t - 1 forward, t + 1 backward;
            # stored at the later frame of the two)
            near = samples.get(t - s)
            if near is not None:
                pf.input_motion[m] = _input_motion(frame, near, diag, device)
            out[t] = conv.X.numpy()
            pf.seconds[t] = time.perf_counter() - t0
            timer = FRAME_TIMER.get()
            if timer is not None:
                timer(float(pf.seconds[t]), done, T)
            if not np.isfinite(out[t]).all():
                raise RuntimeError(f"{where}: conversion ({strategy}) produced NaN/inf at frame {t}; "
                                   "the input frame may be degenerate")
            if journal is not None:
                figures = [getattr(pf, name)[t] for name in _PER_FRAME_RECORD]
                figures += [pf.input_motion[m] if m < T else 0.0, reanchored]
                journal.write(index, t, raw[t], X=out[t], figures=np.array(figures, np.float64), **change)
        samples = {K: samples.get(K), t: _motion_sample(v, device)} if t != K else {K: _motion_sample(v, device)}
        conv.first = False
        _mark_fitted()
        lo, hi = (t, t) if lo is None else (min(lo, t), max(hi, t))
        if t > K and stop_forward is not None and stop_forward(t, pf.web, pf.buried):
            forward = False
    if hasattr(order, "close"):
        order.close()
    return out, lo, hi, pf


def _loop_dropout(vseq, m: np.ndarray, u: int, s: int, K: int, device, info) -> int | None:
    """The frame loop, about to fit frame u in direction ``s`` (+1 forward, -1 backward from key
    frame K): when the up to DROPOUT_FRAMES frames it passed last are a dropout
    (:func:`_dropout_run` between the frame before them and u; added to ``info.input_dropouts``),
    the frame before them (the one to go on from), else None. ``m`` holds the ``input_motion``
    measured so far: the run's first frame (in the pass's order) stands out from those before."""
    for k in range(1, DROPOUT_FRAMES + 1):
        first, p = u - k * s, u - (k + 1) * s
        if (p - K) * s < 0:  # the run would reach the key frame (or past it)
            break
        spike = m[first] if s > 0 else m[first + 1]
        near = m[max(K + 1, first - JUMP_WINDOW):first] if s > 0 else m[first + 2:first + 2 + JUMP_WINDOW]
        run = _dropout_run(vseq, p, u, spike, near, device)
        if run:  # (a longer run may take in a frame found alone before: it is listed once)
            found = {d[0] for d in info.input_dropouts}
            info.input_dropouts.extend(d for d in run if d[0] not in found)
            return p
    return None


def best_starts(starts: list, scores, keep: int) -> list:
    """The ``keep`` starts with the lowest scores, in their original order (ties: the earlier
    first); all of them when ``keep`` is 0 or not smaller than their number."""
    if keep <= 0 or keep >= len(starts):
        return list(starts)
    return [starts[i] for i in sorted(np.argsort(np.asarray(scores, float), kind="stable")[:keep])]


def _poor_runs(coverage: np.ndarray, K: int, threshold: float) -> list:
    """Runs of frames whose coverage is poor (> threshold), each with the good frame to re-track
    it from, on the side it was not tracked from: ``(anchor, frames in re-track order)``. Frames
    after the key frame K were tracked forward, so a run there is re-tracked backward from the
    good frame after it; frames before K were tracked backward, so forward from the one before."""
    T = len(coverage)
    poor = coverage > threshold
    runs, t = [], 0
    while t < T:
        if not poor[t] or t == K:
            t += 1
            continue
        a = t
        while t + 1 < T and poor[t + 1] and t + 1 != K and (t + 1 < K) == (a < K):
            t += 1
        b = t
        if a > K and b + 1 < T and not poor[b + 1]:
            runs.append((b + 1, list(range(b, a - 1, -1))))
        elif b < K and a - 1 >= 0 and not poor[a - 1]:
            runs.append((a - 1, list(range(a, b + 1))))
        t += 1
    return runs


def _repair_poor_runs(vseq, conv, out, pf: _PerFrame, K: int, o: dict, should_stop, TF, info) -> list:
    """Bidirectional repair (``graph``): re-track every run of poorly covered frames from the good
    frame on its other side, keeping per frame whichever result covers the input better. Up to
    ``repair_passes`` passes (each sees the previous one's coverage). Returns the improved frames."""
    device = conv.device
    repaired = set()
    for _ in range(int(o["repair_passes"])):
        med = float(np.median(pf.coverage))
        thr = float(o["repair_threshold"]) or max(float(o["restart_threshold"]), 2.0 * med)
        runs = _poor_runs(pf.coverage, K, thr)
        if not runs:
            break
        for anchor, frames in runs:
            if should_stop is not None and should_stop():
                return sorted(repaired)
            step = 1 if frames[0] > anchor else -1
            prev = anchor - step
            conv.rewind(out[anchor], anchor, prev)
            conv.failed_restart = None
            for t in frames:
                t0 = time.perf_counter()
                v, f = _frame_for_fit(vseq, t, K, o, out[t - step], TF, device, info)
                old_state = conv.frame_states.get(t)
                frame = _device_frame(v, f, device)
                conv.step_graph(frame, t)
                diag = _bbox_diag(v)
                if conv.frame_coverage / max(diag, 1e-12) < pf.coverage[t]:
                    _record_fit(conv, frame, diag, pf, t)
                    out[t] = conv.X.numpy()
                    repaired.add(t)
                else:
                    conv.frame_coverage = conv.frame_web = None
                    if old_state is not None:
                        conv.frame_states[t] = old_state  # keep the better state for later anchors
                pf.seconds[t] += time.perf_counter() - t0
    return sorted(repaired)


def _convert_from_key(vseq, strategy: str, o: dict, K: int, template, device, progress, should_stop,
                      where, stop_forward=None) -> FixedTopologySequence:
    """One conversion run: the template is ``template`` (validated (V, F)) or key frame K's
    mesh, tracked from frame K to both ends."""
    T = vseq.num_frames
    _stop_before_fitting(should_stop)
    if template is None:  # the key frame, without its floaters
        TV, TF = _key_frame_floaters(vseq, K, o, device)[:2]
    else:
        TV, TF = template
    TV = np.ascontiguousarray(TV, np.float32)
    TF = np.ascontiguousarray(TF, np.int32)
    if template is not None:
        _check_reach(TV, TF, *vseq.frames[K], float(o["max_template_distance"]), device, K)
    all_diag = max(max(_bbox_diag(v) for v, _ in vseq.frames), _bbox_diag(TV), 1e-6)
    _stop_before_fitting(should_stop)
    spacing, moving = _node_spacing(vseq, K, TV, TF, o, device) if strategy == "graph" else (None, None)
    _stop_before_fitting(should_stop)
    conv = _Converter(TV, TF, device, 10.0 * all_diag, o, spacing)
    step = getattr(conv, f"step_{strategy}")
    info = ConversionInfo(strategy, {k: v for k, v in o.items() if k != "strategy"}, T, len(TV), key_frame=K)
    info.moving_part = moving
    journal = _JOURNAL.get()
    if journal is not None:  # this run's identity: what its frames' results depend on besides the frames
        journal = journal.run({"strategy": strategy, "options": info.options, "key_frame": K, "frames": T,
                               "template": frame_digest(TV, TF), "spacing": frame_digest(np.asarray(spacing, float)),
                               "reach": frame_digest(np.float64(all_diag))})
    out, lo, hi, pf = _convert_frames(vseq, conv, step, K, progress, should_stop, info, strategy, where, TV, TF,
                                      stop_forward, journal)
    if strategy == "graph" and (lo, hi) == (0, T - 1) and int(o["repair_passes"]) > 0:
        info.repaired_frames = _repair_poor_runs(vseq, conv, out, pf, K, o, should_stop, TF, info)
    info.ignored_parts = {t: x for t, x in sorted(info.ignored_parts.items()) if lo <= t <= hi}
    info.frame_seconds = pf.seconds.tolist()
    info.coverage, info.coverage_tail = pf.coverage.tolist(), pf.tail.tolist()
    info.web, info.buried, info.flipped = pf.web.tolist(), pf.buried.tolist(), pf.flipped.tolist()
    info.off_input = pf.off.tolist()
    info.area_ratio = (pf.area / np.maximum(_frame_areas(vseq), 1e-30)).tolist()
    info.input_motion = pf.input_motion.tolist()
    info.reanchored_frames.sort()
    if hasattr(conv, "recovered"):
        info.recovered_frames = sorted(conv.recovered)
        info.unrecovered_frames = sorted(conv.restarts_failed)
    elif getattr(conv, "reinit_sources", None):
        info.recovered_frames = sorted((t, "template" if src < 0 else f"frame {src}")
                                       for t, src in conv.reinit_sources)
    info.first_frame = lo
    if (lo, hi) != (0, T - 1):  # stopped early: the frames converted so far
        info.frame_seconds, info.coverage = info.frame_seconds[lo:hi + 1], info.coverage[lo:hi + 1]
        info.web, info.coverage_tail = info.web[lo:hi + 1], info.coverage_tail[lo:hi + 1]
        info.flipped, info.buried = info.flipped[lo:hi + 1], info.buried[lo:hi + 1]
        info.off_input = info.off_input[lo:hi + 1]
        info.area_ratio, info.input_motion = info.area_ratio[lo:hi + 1], info.input_motion[lo:hi + 1]
    res = FixedTopologySequence(out[lo:hi + 1], TF, **carried(vseq))
    info.frame_motion = _frame_motion(res.V)
    info.input_motion[0] = 0.0  # (the frame before lo is not in the result)
    res.conversion = info
    return res
