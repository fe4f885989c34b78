"""Topology conversion: a varying-topology sequence (a new mesh per frame, e.g. DG-Mesh's
marching cubes output) -> a fixed-topology sequence (one template, moving vertices).

Public API
----------
``nearest_surface(mesh, points, device=None, max_dist=None) -> NearestSurfaceResult``
    Batched closest point on a triangle mesh (``wp.Mesh`` or ``(V, F)``): closest point,
    face, barycentric weights of the face's vertices, distance; NumPy arrays.

``to_fixed_topology(seq, strategy="graph", template=None, device=None, progress=False,
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
    re-anchored frames, per-frame time, coverage, web, segments.

``to_piecewise_fixed(seq, strategy="graph", ..., **options)``
    The same, with a new template (a segment) where one cannot follow the input (a web across
    parts it fused, a lost part; option ``max_segments``): the fixed sequence when one holds,
    else a varying one whose frames share faces within each segment (docs/conversion.md).

``web_fraction(X, F, X_key, V_ref, F_ref)``
    The fraction of a converted surface's area stretched across a gap of the input.

CLI: ``python -m dynmesh_warp.convert IN OUT --strategy tracking|projection|regularized
[--template MESH] [--device cpu] [--reanchor-interval 50] [--tracked-weight 0.8] [--fmt ply]``.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import os
import re
import shutil
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from .choices import DEFAULT_FRAME_ORDER, DEFAULT_STRATEGY, STRATEGIES, FrameOrder, values
from .conversion_options import options_for
from .convert_journal import ConversionJournal, frame_digest
from .deform_graph import (GraphFitter, GraphFrame, build_deformation_graph, extrapolate_rotations, node_groups, rim_array,
                           rotation_from_vector)
from .geometry import (distinct_faces, face_areas, fit_group_motions, flat_faces, mesh_orientation, orient_faces,
                       signed_volume, surface_area, weld_vertices, winding_inconsistent, winding_numbers)
from .kernels import convert as kc
from .kernels import register as kr
from .kernels.geometry import project_points_to_mesh
from .metrics import chamfer_distance
from .mesh_formats import file_problem
from .sequence import FPS_RANGE, FixedTopologySequence, MeshDataError, VaryingTopologySequence, validate_mesh

__all__ = [
    "STRATEGIES",
    "NearestSurfaceResult",
    "ConversionInfo",
    "nearest_surface",
    "vertex_adjacency",
    "to_fixed_topology",
    "to_piecewise_fixed",
    "web_fraction",
    "surface_deviation",
    "main",
]


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
    """The length of the bounding box's diagonal of points V (N, 3) [units of V]."""
    if not len(V):
        return 0.0
    # per coordinate over a transposed copy: the same numbers as V.max(axis=0) - V.min(axis=0),
    # 30x faster (NumPy reduces an (N, 3) array's axis 0 with strided steps; convert asks this of
    # every frame, ~1,300 times for 200 frames: 0.7 s of the GPU conversion's 9 s)
    C = np.ascontiguousarray(np.asarray(V).reshape(-1, 3).T)
    return float(np.linalg.norm(C.max(axis=1) - C.min(axis=1)))


class _Frame(tuple):
    """An input frame on the device as the strategies take it: (wp.Mesh, points, indices), with
    ``closed`` (no edge of one face only), computed from the host faces when first asked."""

    def __new__(cls, mesh, pts, idx, faces):
        self = super().__new__(cls, (mesh, pts, idx))
        self._faces, self._closed = faces, None
        return self

    @property
    def faces(self) -> np.ndarray:
        """The host faces (M, 3) the frame was made from."""
        return self._faces

    @property
    def closed(self) -> bool:
        if self._closed is None:
            self._closed = _open_edges(self._faces) == 0
        return self._closed

    @property
    def known_closed(self) -> bool | None:
        """``closed`` if it was asked (or told) already, else None (not computed here)."""
        return self._closed

    @known_closed.setter
    def known_closed(self, closed: bool):
        """Tell the frame whether it is closed, found by a caller's own pass over its edges."""
        self._closed = bool(closed)


def _device_frame(V: np.ndarray, F: np.ndarray, device) -> _Frame:
    """A mesh on the device as the strategies take an input frame: (wp.Mesh, points, indices)."""
    pts = wp.array(np.ascontiguousarray(V, np.float32), dtype=wp.vec3, device=device)
    idx = wp.array(np.ascontiguousarray(F, np.int32).reshape(-1), dtype=wp.int32, device=device)
    return _Frame(wp.Mesh(points=pts, indices=idx), pts, idx, F)


def _wp_mesh(V: np.ndarray, F: np.ndarray, device) -> wp.Mesh:
    return _device_frame(V, F, device)[0]


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
    """What a conversion did.

    key_frame: the input frame the template was taken from (or matched to); frames were
    converted from it forward to the end, then from it backward to frame 0.
    reanchored_frames: frames where tracking blended in the template projection or a tracking
    strategy restarted from a stored state; recovered_frames: ``(frame, source)`` pairs of those
    restarts (source: "previous frame", "frame K", "template").
    coverage: per frame (in input order), the 99.5th percentile of the distance of the input
    frame's vertices to the converted surface, as a fraction of the frame's bbox diagonal: a
    body part the conversion lost shows here (a restart trigger and the user's warning).
    coverage_tail: the same distances' 99.9th percentile: a thin part's tip (fewer than 0.5 %
    of the vertices) that the fit left behind shows here and not in ``coverage`` (reported and
    warned about; the fit does not steer by it).
    frame_seconds: wall time per frame (host + kernels), in input order.
    topology_events: ``(frame, description)`` where the input's topology (connected parts,
    genus) differs from the previous frame's: parts touching or separating, a hole closing.
    ``to_fixed_topology`` keeps one template through them: the fixed topology follows parts into
    contact; what it cannot do is tear a part the template has fused (it leaves a ``web``), which
    is why the key frame is the one with the most surface (parts most apart), and why
    :func:`to_piecewise_fixed` starts a new template at such an event.
    key_trials: ``(key frame, mean coverage, score ([m^2] Chamfer, [m] moving), seconds)`` of every run when the run
    from the automatic key frame covered frames poorly, drifted, or moves a part in static
    surroundings, and the conversion was run again from other key frames (``key_candidates``);
    the kept run is the one of least score (its key is ``key_frame``). Empty when there was one
    run. key_score: what the score is: ``"chamfer"``, the mean Chamfer distance to the input
    (:func:`_chamfer_to_input`), or ``"moving"`` when the first run found a moving part
    (``moving_part``), the mean of the largest 0.5 % of the distances from the input's moving
    points to the output (:func:`_moving_score`: the static surroundings would outweigh the
    subject in the Chamfer distance).
    floater_webs: frames whose web (above ``POOR_WEB``) is pulled by small separate parts of the
    input (most of such a part's vertices nearest to stretched faces): floaters of a
    reconstruction, which ``far_part_area`` leaves out (off by default); the summary says so.
    floater_retry: the ``floater_webs`` of a first run, when the conversion was run again with
    ``far_part_area`` = ``FLOATER_AREA`` (option ``floater_retry``) and that run, less poor, was
    kept (its ``ignored_parts`` name what it left out); floater_retry_rejected: it ran and was not.
    welded: ``(frame, vertices)`` for input frames with vertices at one position (a triangle
    soup, seams), welded into one before the conversion (so the template of such a key frame is
    a connected mesh).
    turned_outward: input frames wound inside out (closed, all faces inward), turned before the
    conversion (the fit compares normals).
    rewound: ``(frame, faces flipped)`` for input frames wound inconsistently (faces flipped at
    random), made consistent piece by piece before the conversion (``geometry.orient_faces``).
    dropped_unused: ``(frame, vertices, faces)`` for input frames holding vertices that no face
    uses (left over after a face filter, stray points) or faces that repeat a vertex: dropped
    before the conversion, so they neither pull the template nor count in the coverage, the
    scale check or the template (whose faces are then the key frame's without them).
    ignored_parts: ``{frame: (parts, vertices)}``: small input parts left out of that frame's
    fit and coverage because they lie wholly far from the converted surface (options
    ``far_part_area``, ``far_part_gap``): floaters of a reconstruction, for which the template
    has no part (pulled, they would grow a spike from it).
    flipped: per frame, the fraction of the converted surface's area whose faces point against
    the input surface nearest to them (a fold-over: the surface doubled back on itself, as a new
    user's waving flag did on 6 of 24 frames, 13 % of its area, silently).
    frame_motion: per frame t, how far the converted surface moved from frame t - 1: the 99th
    percentile of its vertices' displacements (at most 4,096 of them) over the frame's bbox
    diagonal; 0 at the first frame and where a template segment starts. A frame far above its
    neighbours' is a jump (a restart's new start, a slide along the surface), which the physics
    sees as the surface moving that far in one frame (a new user's spheres were thrown at 30 m/s).
    input_motion: per frame t, how far the input itself moved from frame t - 1: the 99th
    percentile of the distances of the input vertices (at most 4,096) of the neighbouring frame
    fitted just before (t - 1 on the forward pass, t + 1 on the backward) to the other frame's
    surface, over the diagonal; 0 at the first frame (measured in the frame loop on the frame's
    own BVH). A jump the input makes too is real motion, not warned of (a new user's capture that
    moves 0.4 m in one frame was warned of as a restart); converted vertices moving far more than
    the input's surface slide along it (the summary's slide line).
    input_dropouts: ``(frame, distance, agreement)`` of the input frames (runs of up to
    ``DROPOUT_FRAMES``) that lack surface both frames either side of their run have (a
    reconstruction's dropout: a new user's leg missing from one frame): the smaller of the two
    ends' 99th-percentile distances to the frame's surface, and the ends' own distance to each
    other (fractions of the diagonal). The output follows the input there (:func:`_input_dropouts`)
    unless the option ``bridge_dropouts`` (on by default) bridged it: bridged_frames lists the
    frames whose output is blended from the two frames either side of their run (after a dropout
    the frame loop found, the next frame's fit started from the frame before it).
    missing_parts: ``(first, last, lost)`` of the runs of input frames that lack a part the frame
    next to the run has, where no bridge reaches (:func:`_missing_parts`; ``lost``: the fraction of
    the surface area that went): runs of more than ``DROPOUT_FRAMES`` frames (blending that many
    would blend away the motion of the rest too) and runs that reach the first or last frame (a
    part that enters or leaves). The template keeps the part: the output presses it onto what is
    left there, and the summary says so.
    area_ratio: per frame, the converted surface's area over the input's (the result's frames;
    above ``POOR_AREA``, a crumpled surface: a new user's balloon, converted from its inflated
    frame, had 2.0-2.4x the input's area on its 16 deflated frames while the vertex Chamfer
    distance called it 13 % better than the input).
    web: per frame, the fraction of the converted surface's area that spans a gap of the input
    (:func:`web_fraction`: faces stretched across where the input has no surface, e.g. parts the
    template fused that the input pulls apart); a web shows here, not in the coverage.
    buried: per frame, the fraction of the converted surface's area stretched far from a closed
    input but inside its body: the walls of parts the template keeps apart where the input has
    them in contact or merged (two bodies touching, a hand on a hip). Not the web (no sphere
    outside meets them, so the summary notes them instead of warning), or a template crumpled
    inside the body; restarts and new segments count them with the web.
    rejected_cuts: ``(start, stop)`` of the frames :func:`to_piecewise_fixed` converted again with
    a template of their own and did not keep (the new template fitted no better).
    segments: ``(start, stop, key frame, template vertices)`` per template (stop exclusive): one
    for :func:`to_fixed_topology`; several when :func:`to_piecewise_fixed` started new templates.
    seconds_all: wall time of the whole call [s], the runs whose frames were not kept (other key
    frames, segments tried and replaced) included; ``frame_seconds`` counts the kept frames only.
    open_edges: per segment (in the order of ``segments``), how many of its template's edges
    belong to one face only: the rim of a hole or of a sheet, which every output frame of that
    segment keeps (the summary says so; a sphere can pass through a hole).
    moving_part: ``(diagonal [m], template vertices in its box)`` of the part of the template
    that moves, when it is much smaller than the whole (a static floor or background) and set
    the graph's node spacing within its box (option ``adaptive_spacing``: the vertices counted
    here get the finer spacing); None otherwise.
    """

    strategy: str
    options: dict
    num_frames: int
    num_vertices: int
    reanchored_frames: list = field(default_factory=list)
    frame_seconds: list = field(default_factory=list)
    key_frame: int = 0
    recovered_frames: list = field(default_factory=list)
    coverage: list = field(default_factory=list)
    coverage_tail: list = field(default_factory=list)
    topology_events: list = field(default_factory=list)
    first_frame: int = 0  # the result holds input frames first_frame.. (not 0 only when stopped early)
    repaired_frames: list = field(default_factory=list)
    unrecovered_frames: list = field(default_factory=list)
    key_trials: list = field(default_factory=list)
    dropped_unused: list = field(default_factory=list)
    welded: list = field(default_factory=list)
    turned_outward: list = field(default_factory=list)
    rewound: list = field(default_factory=list)
    floater_webs: list = field(default_factory=list)
    floater_retry: list = field(default_factory=list)
    floater_retry_rejected: bool = False
    ignored_parts: dict = field(default_factory=dict)
    web: list = field(default_factory=list)
    buried: list = field(default_factory=list)
    flipped: list = field(default_factory=list)
    area_ratio: list = field(default_factory=list)
    frame_motion: list = field(default_factory=list)
    input_motion: list = field(default_factory=list)
    input_dropouts: list = field(default_factory=list)
    missing_parts: list = field(default_factory=list)
    bridged_frames: list = field(default_factory=list)
    rejected_cuts: list = field(default_factory=list)
    segments: list = field(default_factory=list)
    open_edges: list = field(default_factory=list)
    seconds_all: float = 0.0
    moving_part: tuple | None = None
    key_score: str = ""


def web_fraction(X: np.ndarray, F: np.ndarray, X_key: np.ndarray, V_ref: np.ndarray, F_ref: np.ndarray,
                 device=None, stretch: float | None = None, gap: float | None = None,
                 with_buried: bool = False) -> float | tuple:
    """The fraction of the surface (X, F)'s area that spans a gap of (V_ref, F_ref): faces whose
    longest edge is more than ``stretch`` x its length in ``X_key`` (the same faces at the key
    frame) and whose centroid lies farther than ``gap`` x (V_ref, F_ref)'s bbox diagonal from
    it. The other side of the coverage: when the template fused two parts that the input later
    pulls apart, the fit keeps a web of stretched faces across the gap; its vertices all lie on
    the input, so the coverage and a vertex Chamfer distance stay good, but a sphere would land
    on it. A part the input merely lost (a thin tip a frame's reconstruction dropped) is far
    from the input but not stretched, and does not count. Where (V_ref, F_ref) is closed, such
    faces whose centroid lies inside it are not the web but *buried* (the walls of parts in
    contact: no sphere outside meets them; inside by the winding number, :func:`winding_numbers`);
    ``with_buried`` returns (web, buried). Defaults: WEB_STRETCH, WEB_GAP."""
    stretch = WEB_STRETCH if stretch is None else stretch
    gap = WEB_GAP if gap is None else gap
    F = np.asarray(F)
    area = face_areas(X, F)
    total = float(area.sum())
    cand = np.flatnonzero(_longest_edges(X, F) > stretch * np.maximum(_longest_edges(X_key, F), 1e-30))
    if not total > 0 or cand.size == 0:
        return (0.0, 0.0) if with_buried else 0.0
    cen = np.asarray(X, np.float64)[F[cand]].mean(axis=1)
    far = nearest_surface((V_ref, F_ref), cen, device=device).dist > gap * _bbox_diag(np.asarray(V_ref))
    inside = np.zeros(far.shape, bool)
    if far.any() and _open_edges(F_ref) == 0:
        inside[far] = np.abs(winding_numbers(V_ref, F_ref, cen[far])) > 0.5  # either winding
    web, buried = (float(area[cand][far & ~inside].sum() / total), float(area[cand][far & inside].sum() / total))
    return (web, buried) if with_buried else web


def _longest_edges(V, F) -> np.ndarray:
    """(M,) the longest edge of each triangle of (V, F) [units of V]."""
    tri = np.asarray(V, np.float64)[np.asarray(F).reshape(-1, 3)]
    return np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)


def _keep_faces(v: np.ndarray, f: np.ndarray, keep: np.ndarray) -> tuple:
    """(vertices, faces) of the faces ``keep`` (a mask) and only the vertices they use, the faces
    renumbered (int32) in the kept vertices' order."""
    used = np.zeros(len(v), bool)
    used[f[keep].ravel()] = True
    remap = np.cumsum(used) - 1
    return v[used], remap[f[keep]].astype(np.int32)


def _drop_unused(vseq: VaryingTopologySequence):
    """(vseq cleaned, [(frame, vertices dropped, faces dropped)], [(frame, vertices welded)],
    [frames turned outward], [(frame, faces flipped)] rewound):
    vertices at one position welded into one (:func:`~dynmesh_warp.geometry.weld_vertices`: a
    triangle soup, or seams, would otherwise be thousands of separate parts to the fit and to the
    topology report), then faces that repeat a vertex (no area in any pose), faces listed again
    (either winding: the template would carry them twice) and vertices no face uses dropped. The
    input is not modified; frames needing none of it are kept as they are. Last, a frame wound
    inside out (closed, consistently wound, negative volume: :func:`~dynmesh_warp.geometry.mesh_orientation`
    "inward") has all its faces turned: the fit compares normals (``max_normal_angle``), so a
    reversed frame among outward ones lost its correspondences (found by a new user: +37 % area
    on such frames, no warning). First, where the input's first, middle or last frame is wound
    inconsistently (faces flipped at random, as some exporters and repair tools leave them), every
    such frame is made consistent piece by piece (:func:`~dynmesh_warp.geometry.orient_faces`;
    ``rewound``): the fit compares normals, and the output takes the key frame's faces (a new
    user's input with 30 % of its faces flipped came out so, every output face the key frame's,
    and the summary blamed a fold-over). Checked on those three frames only unless one of them
    is (a directed-edge sort a frame, ~2 ms for 20k faces, would cost the 200-frame GPU
    conversion ~0.5 s). Raises MeshDataError for a frame left without faces."""
    frames, dropped, welded, turned, rewound = [], [], [], [], []
    T = vseq.num_frames
    rewind = any(winding_inconsistent(vseq.frames[t][1]) for t in sorted({0, T // 2, T - 1}) if t < T)
    for t, (v, f) in enumerate(vseq.frames):
        v, f, merged = weld_vertices(v, np.asarray(f))
        if merged:
            welded.append((t, merged))
        keep = np.zeros(len(f), bool)
        keep[distinct_faces(f)[1]] = True  # not a face that repeats a vertex, nor one listed again
        if not (keep.all() and np.bincount(f.reshape(-1), minlength=len(v)).all()):  # else the usual frame
            if not keep.any():
                src = vseq.frame_sources[t] if vseq.frame_sources else (vseq.source or vseq.name)
                raise MeshDataError(f"{src}, frame {t}: every face repeats a vertex (no surface)")
            v2, f2 = _keep_faces(v, f, keep)
            dropped.append((t, len(v) - len(v2), len(f) - len(f2)))
            v, f = v2, f2
        if rewind and winding_inconsistent(f):
            f2, report = orient_faces(v, f)
            if report["rewound"]:
                rewound.append((t, int(report["rewound"])))
                f = np.ascontiguousarray(f2, dtype=np.asarray(f).dtype)
        if _inside_out(v, f):
            f = np.ascontiguousarray(f[:, ::-1])
            turned.append(t)
        frames.append((v, f))
    if not dropped and not welded and not turned and not rewound:
        return vseq, dropped, welded, turned, rewound
    return VaryingTopologySequence(frames, fps=vseq.fps, name=vseq.name, source=vseq.source,
                                   frame_sources=vseq.frame_sources), dropped, welded, turned, rewound


def _inside_out(v: np.ndarray, f: np.ndarray) -> bool:
    """The frame is closed, consistently wound and faces inward (``mesh_orientation`` "inward").
    Its edge tables cost ~0.1 s a 10k-vertex frame, 20 s for 200 frames (the conversion's whole
    GPU budget is 10 s): asked only when the frame's signed volume, the same one that rule ends
    with (one pass over the faces), is negative."""
    return signed_volume(v, f) < 0 and mesh_orientation(v, f) == "inward"


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
        self.fold_area = wp.zeros(2, dtype=float, device=d)
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
        :func:`~dynmesh_warp.kernels.convert.measure_flipped_area`. One launch, two floats back."""
        self.fold_area.zero_()
        wp.launch(kc.measure_flipped_area, dim=self.nf, inputs=[self.TF, self.X, frame[0].id, WEB_GAP * diag],
                  outputs=[self.fold_area], device=self.device)
        total, flipped = self.fold_area.numpy()
        self.last_area = float(total)
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


def _as_varying(seq) -> VaryingTopologySequence:
    if isinstance(seq, VaryingTopologySequence):
        return seq
    if isinstance(seq, FixedTopologySequence):
        return seq.to_varying()
    if isinstance(seq, (list, tuple)):
        return VaryingTopologySequence(list(seq), name="frames", source="frames")
    raise TypeError(f"expected a VaryingTopologySequence, FixedTopologySequence or a list of (V, F), "
                    f"got {type(seq).__name__}")


def set_deterministic(on: bool, nodes_per_vertex: int = 4) -> None:
    """Compile the conversion's kernel modules (``kernels.convert``, ``kernels.register``) in
    Warp's deterministic mode (RUN_TO_RUN: their float atomic sums reduced in a fixed order, so
    a GPU run repeats bit for bit) or in the normal one. Switching recompiles the two modules
    once; every build stays in Warp's kernel cache. No effect on the CPU's results, which are
    deterministic either way.

    Warp records each atomic call of a thread; a thread that loops over atomics needs the bound
    given: the graph system's rows (k + k^2 for a template vertex's k nodes, m + m^2 for a
    frame point's m <= 3k distinct nodes; the rigid fits' 29 sums a row fit under it) and, for
    ``kernels.convert``, 42 (above its kernels' largest count of atomics a thread)."""
    det = wp.DeterministicMode.RUN_TO_RUN if on else wp.DeterministicMode.NOT_GUARANTEED
    m = min(int(kr.MAX_ROW_NODES), 3 * int(nodes_per_vertex))
    bounds = {kc: 6 * 6 + 6, kr: max(nodes_per_vertex + nodes_per_vertex ** 2, m + m * m)}
    for mod, records in bounds.items():
        want = {"deterministic": det, "deterministic_max_records": records if on else 0}
        have = wp.get_module_options(mod)
        if any(have.get(key) != value for key, value in want.items()):
            wp.set_module_options(want, module=mod)


def _resolve_options(strategy: str, options: dict) -> dict:
    """The strategy's options, checked and with the defaults filled in
    (:func:`dynmesh_warp.conversion_options.options_for`), as a dict with ``strategy``."""
    return options_for(strategy, **options).model_dump()


#: the start of the scale check's warning (a regular expression for ``warnings.filterwarnings``)
SCALE_WARNING = r".*: frames of very different scale"


@contextlib.contextmanager
def _scale_checked():
    """A run over frames the first run's scale check has seen already: no second warning."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=SCALE_WARNING)
        yield


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


#: a frame whose size (the square root of its surface area) is over this factor from both of its
#: neighbours' (geometric mean), where they agree within NEIGHBOUR_AGREE, is warned of (other units)
NEIGHBOUR_SCALE = 1.5
NEIGHBOUR_AGREE = 1.15


def _check_scales(seq: VaryingTopologySequence, tol: float) -> tuple:
    """Warn of frames whose bounding-box diagonal is over ``tol`` x or under 1 / ``tol`` x the
    median frame's (other units, a broken frame); returns them (never a key frame: a template
    from a frame in millimetres among metres crumpled every output frame, and its trial still won
    the ranking, a new user's)."""
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
            "the gap (mixed units or a broken frame?); they are not taken as the key frame", UserWarning, stacklevel=3)
    # a lone frame in other units within tol (inches among cm, 2.54x; feet among metres, 3.28x):
    # its size (the square root of its area, which a floater or a lost limb changes little) against
    # both neighbours, which agree with each other (a new user's frame x2.54 was blamed on the fit)
    size = np.sqrt(_frame_areas(seq))
    lone = []
    for t in range(1, len(size) - 1):
        p, n = size[t - 1], size[t + 1]
        if t in bad or min(p, n) <= 0 or max(p, n) > NEIGHBOUR_AGREE * min(p, n):
            continue
        r = size[t] / np.sqrt(p * n)
        if r > NEIGHBOUR_SCALE or r < 1.0 / NEIGHBOUR_SCALE:
            lone.append((t, r))
    if lone:
        show = ", ".join(f"{t} (x{r:.3g})" for t, r in lone[:10])
        warnings.warn(f"{seq.source or seq.name}: frame(s) {show} differ in size from both neighbours (the square "
                      f"root of the surface area, against frames t - 1 and t + 1, which agree): other units or a "
                      "broken frame? They are not taken as the key frame", UserWarning, stacklevel=3)
    return tuple(sorted({int(t) for t in bad} | {t for t, _ in lone}))


def _check_repeats(seq: VaryingTopologySequence) -> None:
    """Warn of frames that repeat the frame before them exactly (the same vertices and faces: a
    stalled or duplicated capture) in a reconstruction (not every frame of one topology: an
    animated mesh may pause, holding frames exactly): the surface stands still for a frame and
    then moves twice as far, which the physics feels as a jump in surface velocity (a new user's
    duplicated frame 13 showed only as a 10x motion in the summary)."""
    fr = seq.frames
    if all(np.array_equal(f, fr[0][1]) for _, f in fr[1:]):  # (array_equal: False for other shapes)
        return  # one topology: an animated mesh may hold still for frames (a pause); a reconstruction cannot
    rep = [t for t in range(1, len(fr)) if _same_frame(fr[t], fr[t - 1])]
    if rep and len(rep) < seq.num_frames - 1:  # a capture that never moves is not a repeat
        show = ", ".join(map(str, rep[:10])) + (f" and {len(rep) - 10} more" if len(rep) > 10 else "")
        warnings.warn(f"{seq.source or seq.name}: frame(s) {show} repeat the frame before them exactly (a stalled "
                      "or duplicated capture?): the surface stands still there and then moves twice as far",
                      UserWarning, stacklevel=3)


def _key_frame(seq: VaryingTopologySequence, key, has_template: bool, off_scale=()) -> int:
    """The frame the template comes from (or is matched to). "auto": frame 0 with a given
    template; otherwise the frame of largest surface area (median over 3 consecutive frames
    against single-frame noise): limbs held apart, not fused by the reconstruction. A fixed
    template can follow two parts into contact but cannot tear one part into two, so tracking
    starts where the parts are most separate. Where most frames are closed, a frame with a hole
    is not taken; nor a frame more than ``KEY_AREA_TOLERANCE`` below its window's median area
    (a coarser remesh); and a frame of about the same area with ``KEY_FINER`` x the vertices or
    more is preferred. Never one of ``off_scale`` (:func:`_check_scales`)."""
    T = seq.num_frames
    if key is None or (isinstance(key, str) and key == "auto"):
        if has_template or T < 3:
            return 0
        a = _frame_areas(seq)
        med = np.array([np.median(a[max(0, t - 1):t + 2]) for t in range(T)])
        # where most frames are closed, the template is too: a frame with a hole gave every
        # output frame its hole (a new user's blob); and where most frames have no small separate
        # part, neither does the template: a floater's extra area made its frame the key, and the
        # floater went to every output frame, crushed onto the body where the input had none (a
        # new user's). Asked lazily, from the largest area down.
        ok = _key_frame_fit(seq, off_scale)
        order = np.argsort(-med, kind="stable")
        t = next((int(u) for u in order if ok(u)),
                 next((int(u) for u in order if int(u) not in off_scale), int(order[0])))
        tol = KEY_AREA_TOLERANCE
        window = [u for u in range(max(0, t - 1), min(T, t + 2)) if ok(u)]
        if a[t] < (1.0 - tol) * med[t]:
            # the window is the best, its middle frame is not: a coarser remesh, a hole (a new
            # user's 500-vertex frame between two of 4,000 became every frame's template, +82 %
            # CD): the window's frame of the median area
            t = min(window, key=lambda u: abs(a[u] - med[t]))
        # a frame of about the same area (within tol, alone and in its window) with at least
        # KEY_FINER x the vertices: the finer template (every output frame has its resolution)
        nv = np.array([len(v) for v, _ in seq.frames])
        near = [u for u in range(T) if min(a[u], med[u]) >= (1.0 - tol) * a[t]]
        fine = max(near, key=lambda u: (nv[u], med[u]), default=t)
        return int(fine) if nv[fine] >= KEY_FINER * nv[t] and ok(fine) else t
    if isinstance(key, bool) or not isinstance(key, (int, np.integer)) or not -T <= int(key) < T:
        raise ValueError(f"key_frame must be 'auto' or a frame index in [{-T}, {T - 1}] "
                         f"(the sequence has {T} frames), got {key!r}")
    return int(key) % T


def _key_frame_fit(seq: VaryingTopologySequence, off_scale=()):
    """:func:`_find_key_frame_fit`, found once per conversion of ``seq`` (the key frame's choice
    and the key trials ask it; its answers are kept as they are asked)."""
    return _once(seq, ("key frame fit", tuple(sorted(int(u) for u in off_scale))),
                 lambda: _find_key_frame_fit(seq, off_scale))


def _find_key_frame_fit(seq: VaryingTopologySequence, off_scale=()):
    """``ok(u)``: whether frame u may be the key frame (the template's source). Where most frames
    are closed, a frame with a hole may not; where most frames have no small separate part
    (``_has_small_part``: a floater), a frame with one may not; nor one of ``off_scale``. "Most"
    is judged on ``_sample_frames``, and on every frame where the sample is split (floaters on
    every third frame met a sample at frames 0, 3, 6, ... as 5 of 9: "most have one", a floater's
    frame became the key and the floaters every frame's; a new user's). Each test asked lazily."""
    T = seq.num_frames
    sample = _sample_frames(T)
    checks = {"closed": lambda u: _open_edges(seq.frames[u][1]) == 0,
              "no small part": lambda u: not _has_small_part(*seq.frames[u])}
    seen = {name: {u: test(u) for u in sample} for name, test in checks.items()}
    needed = []
    for name, test in checks.items():
        votes = list(seen[name].values())
        if 0 < sum(votes) < len(votes):  # split: every frame votes
            seen[name].update({u: test(u) for u in range(T) if u not in seen[name]})
            votes = list(seen[name].values())
        if 2 * sum(votes) >= len(votes):
            needed.append(name)
    off = set(int(u) for u in off_scale)

    def ok(u):
        if u in off:
            return False
        for name in needed:
            if u not in seen[name]:
                seen[name][u] = checks[name](u)
            if not seen[name][u]:
                return False
        return True

    return ok


def _small_parts(v: np.ndarray, f: np.ndarray, area_frac: float) -> tuple:
    """``(parts, each vertex's part, each face's part, small)``: the connected parts of (v, f)
    and those (``small``, an index array) with less than ``area_frac`` of the surface area, the
    largest part never among them."""
    k, vert_part = _part_labels(f, len(v))
    lab = vert_part[f[:, 0]]  # each face's part
    if k < 2:
        return k, vert_part, lab, np.zeros(0, np.int64)
    part_area = np.bincount(lab, weights=face_areas(v, f), minlength=k)
    has_faces = np.bincount(lab, minlength=k) > 0  # a vertex no face uses is a part without area
    small = np.flatnonzero((part_area < area_frac * part_area.sum()) & has_faces)
    return k, vert_part, lab, small[small != np.argmax(part_area)]


def _has_small_part(V: np.ndarray, F: np.ndarray) -> bool:
    """Whether the mesh has a connected part of less than ``FLOATER_AREA`` of its area (a
    reconstruction's floater, a fragment)."""
    return bool(_small_parts(V, np.asarray(F, np.int64).reshape(-1, 3), FLOATER_AREA)[3].size)


def _edge_keys(F: np.ndarray) -> np.ndarray:
    """The edges (0,1), (1,2), (2,0) of every face of ``F`` (M, 3) int64, each as one sorted
    int64 key min * n + max (n: the vertex count the faces imply): an edge shared by k faces
    appears k times in a row."""
    n = int(F.max()) + 1
    a, b = F.T.ravel(), F[:, [1, 2, 0]].T.ravel()
    return np.sort(np.minimum(a, b) * n + np.maximum(a, b))


def _has_area(V: np.ndarray, F: np.ndarray, chunk: int = 4096) -> bool:
    """Whether some face of (V, F) is not flat (:func:`~dynmesh_warp.geometry.flat_faces`),
    looked for a chunk of faces at a time (a real mesh answers in the first)."""
    F = np.asarray(F).reshape(-1, 3)
    return any(not flat_faces(V, F[s:s + chunk]).all() for s in range(0, len(F), chunk))


def _open_edges(F: np.ndarray) -> int:
    """How many edges of the faces ``F`` belong to one face only (a hole's or a sheet's rim)."""
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if not len(F):
        return 0
    key = _edge_keys(F)
    first = np.r_[True, key[1:] != key[:-1]]
    counts = np.diff(np.r_[np.flatnonzero(first), key.size])
    return int(np.count_nonzero(counts == 1))


def _topology(F: np.ndarray) -> tuple:
    """(connected parts, genus) of a closed triangle mesh given by its faces (genus from the
    Euler characteristic per part: chi = V - E + F = 2 parts - 2 genus; approximate for open
    meshes). Vertices no face uses are not counted (each would be a part of its own)."""
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if not len(F):
        return 0, 0
    n = int(F.max()) + 1
    used = np.zeros(n, bool)
    used[F.ravel()] = True
    ne = int(np.count_nonzero(np.diff(_edge_keys(F)))) + 1
    c = _part_labels(F, n)[0] - int(n - used.sum())  # unused vertices: parts of their own
    chi = int(used.sum()) - ne + len(F)
    return c, max(0, (2 * c - chi) // 2)


def _topology_events(seq: VaryingTopologySequence) -> list:
    """``(frame, text)`` for every frame whose (parts, genus) differs from the previous frame's."""
    ev, prev = [], None
    for t, (_v, f) in enumerate(seq.frames):
        cur = _topology(f)
        if prev is not None and cur != prev:
            what = []
            if cur[0] != prev[0]:
                what.append(f"parts {prev[0]} -> {cur[0]}")
            if cur[1] != prev[1]:
                what.append(f"genus {prev[1]} -> {cur[1]}")
            ev.append((t, ", ".join(what)))
        prev = cur
    return ev


def _check_reach(TV, TF, V0, F0, limit: float, device, frame: int = 0):
    diag = _bbox_diag(V0)
    d = nearest_surface((V0, F0), TV, device=device).dist
    far = d > limit * diag
    frac = float(far.mean())
    if frac > 0.5:
        raise MeshDataError(
            f"template: {100 * frac:.0f}% of its {len(TV)} vertices lie farther than "
            f"{limit:g} x frame {frame}'s bounding-box diagonal ({limit * diag:.4g}) from frame {frame}'s surface "
            f"(median distance {np.median(d):.4g}); the template does not describe this sequence "
            "(other units, other placement?)")
    if frac > 0.05:
        warnings.warn(
            f"template: {100 * frac:.0f}% of its vertices lie farther than {limit:g} x frame {frame}'s "
            f"bounding-box diagonal from frame {frame}'s surface", UserWarning, stacklevel=3)


def _part_labels(F: np.ndarray, n: int) -> tuple:
    """(number of parts, part of each of the n vertices) of the faces F (parts: connected
    components of the edge graph; a vertex no face uses is a part of its own)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(F, np.int64)
    a = F.T.ravel()
    b = F[:, [1, 2, 0]].T.ravel()
    g = sp.csr_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n))
    return connected_components(g, directed=False)


def _far_parts(v: np.ndarray, f: np.ndarray, X: np.ndarray, TF: np.ndarray, area_frac: float, gap_frac: float,
               device) -> tuple:
    """The input frame (v, f) without its small parts far from the previous converted frame
    (X on the template faces TF): parts of less than ``area_frac`` of the frame's surface area
    whose every vertex lies farther than ``gap_frac`` x X's bbox diagonal from X's surface (a
    floater of the reconstruction: the template has no part for it). The largest part is always
    kept. Returns (v, f, parts dropped, vertices dropped); (v, f, 0, 0) when none."""
    if area_frac <= 0:
        return v, f, 0, 0
    k, vert_part, lab, small = _small_parts(v, f, area_frac)
    if small.size == 0:
        return v, f, 0, 0
    in_small = np.isin(lab, small)
    verts = np.unique(f[in_small])
    d = nearest_surface((X, TF), v[verts], device=device).dist
    near = np.zeros(k, bool)
    near[vert_part[verts][d <= gap_frac * max(_bbox_diag(X), 1e-12)]] = True
    drop = small[~near[small]]
    if drop.size == 0:
        return v, f, 0, 0
    v2, f2 = _keep_faces(v, f, ~np.isin(lab, drop))
    return v2, f2, int(drop.size), len(v) - len(v2)


#: a poor web frame counts as pulled by a floater when a separate input part of less than this
#: fraction of the frame's area has most of its vertices nearest to stretched faces
FLOATER_AREA = 0.05


def _floater_webs(vseq, res, device, far_gap: float) -> list:
    """The frames of ``res`` (a full run over ``vseq``'s frames) whose web (with buried faces) is above ``POOR_WEB``
    and is pulled by a small separate input part: more than half of that part's vertices have
    their nearest converted point on a face stretched more than ``WEB_STRETCH`` x since the key
    frame, and every vertex of it lies farther than ``far_gap`` x the diagonal from the faces that
    are not. A fragment of a real thin part lies by the rest of that part instead."""
    info = res.conversion
    out = []
    poor = np.flatnonzero(_stretched_far(info) > POOR_WEB)  # as the restarts count
    if not poor.size or info.first_frame != 0 or len(info.coverage) != vseq.num_frames:
        return out
    key_edge = _longest_edges(res.V[info.key_frame], res.F)
    for t in poor.tolist():
        v, f = vseq.frames[t]
        k, vert_part, lab, small = _small_parts(v, f, FLOATER_AREA)
        if not small.size:
            continue
        verts = np.unique(f[np.isin(lab, small)])
        hit = nearest_surface((res.V[t], res.F), v[verts], device=device).face
        stretched = _longest_edges(res.V[t], res.F) > WEB_STRETCH * key_edge
        on_web = np.bincount(vert_part[verts], weights=stretched[np.maximum(hit, 0)] & (hit >= 0), minlength=k)
        count = np.bincount(vert_part[verts], minlength=k)
        pulled = small[on_web[small] > 0.5 * np.maximum(count[small], 1)]
        if not pulled.size or stretched.all():
            continue
        # ... and detached: every vertex of the part farther than far_part_gap from the faces that
        # are not stretched (a fragment of a real part lies by the rest of that part)
        keep = ~stretched
        gap = float(far_gap) * max(_bbox_diag(res.V[t]), 1e-12)
        pv = verts[np.isin(vert_part[verts], pulled)]
        d = nearest_surface((res.V[t], res.F[keep]), v[pv], device=device).dist
        near = np.zeros(k, bool)
        near[vert_part[pv][d <= gap]] = True
        if np.any(~near[pulled]):
            out.append(t)
    return out


def _key_frame_floaters(vseq, K: int, o: dict, device) -> tuple:
    """Key frame K without its floaters: small parts (under ``far_part_area`` of its area, or
    ``FLOATER_AREA`` while that is 0) lying farther than ``far_part_gap`` x its diagonal from the
    rest of it, which no neighbouring frame (K - 1, K + 1) has any surface near either — or with
    ``far_part_area`` on, all such far small parts. Kept, such a part became a template part that
    no other frame has, dragged about as flying surface (a new user's 12-vertex fragment of
    reconstruction debris jumped 1.2 m between frames: 29 m/s for the physics). A small separate
    part that persists (a ball, a part of a real object) is kept. Returns (v, f, parts, vertices);
    asked by the template's making and by the key frame's fit, found once per sequence object."""
    area_opt, gap = float(o.get("far_part_area", 0.0)), float(o.get("far_part_gap", 0.0))
    return _once(vseq, ("key frame floaters", K, area_opt, gap),
                 lambda: _find_key_frame_floaters(vseq, K, area_opt, gap, device))


def _find_key_frame_floaters(vseq, K: int, area_opt: float, gap: float, device) -> tuple:
    """The body of :func:`_key_frame_floaters`."""
    v, f = vseq.frames[K]
    _, vert_part, lab, small = _small_parts(v, f, area_opt if area_opt > 0 else FLOATER_AREA)
    if not small.size or gap <= 0:
        return v, f, 0, 0
    in_small = np.isin(lab, small)
    verts = np.unique(f[in_small])
    reach = gap * max(_bbox_diag(v), 1e-12)

    def near(mesh):  # per part: has a vertex within reach of mesh
        d = nearest_surface(mesh, v[verts], device=device).dist
        hit = np.zeros(int(vert_part.max()) + 1, bool)
        hit[vert_part[verts][d <= reach]] = True
        return hit

    drop = small[~near((v, f[~in_small]))[small]]  # far from the rest of the frame
    if drop.size and area_opt <= 0:  # ... and, with the filter off, in no neighbouring frame
        for u in (K - 1, K + 1):
            if drop.size and 0 <= u < vseq.num_frames:
                drop = drop[~near(vseq.frames[u])[drop]]
    if drop.size == 0:
        return v, f, 0, 0
    v2, f2 = _keep_faces(v, f, ~np.isin(lab, drop))
    return v2, f2, int(drop.size), len(v) - len(v2)


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
    input_motion: np.ndarray

    @classmethod
    def zeros(cls, T: int) -> "_PerFrame":
        return cls(*(np.zeros(T) for _ in dataclasses.fields(cls)))


#: the per-frame figures a journal record keeps (:func:`_convert_frames`), in its ``figures``
#: followed by the input's motion and whether the frame was re-anchored
_PER_FRAME_RECORD = ("seconds", "coverage", "tail", "web", "buried", "flipped", "area")


def _record_fit(conv, frame, diag: float, pf: _PerFrame, t: int) -> None:
    """Frame t's coverage, tail, web, buried and flipped fractions of the fit in ``conv.X`` into
    ``pf`` (the coverage and web measured on the kept fit when the fit did)."""
    cov = conv.frame_coverage if conv.frame_coverage is not None else conv.coverage(frame)
    pf.coverage[t], pf.tail[t] = cov / max(diag, 1e-12), cov.tail / max(diag, 1e-12)
    pf.web[t], pf.buried[t] = conv.frame_web if conv.frame_web is not None else (conv.web(frame, diag), conv.last_buried)
    conv.frame_coverage = conv.frame_web = None
    pf.flipped[t] = conv.flipped(frame, diag)
    pf.area[t] = conv.last_area


def _input_motion(frame, points, diag: float, device) -> float:
    """How far the input surface moved between a neighbouring frame and ``frame``: the 99th
    percentile of the neighbour's sampled vertices ``points`` (device) distances to ``frame``'s
    surface, over the diagonal ``diag`` (``ConversionInfo.input_motion``; one launch on the
    frame's own BVH)."""
    dist = wp.empty(points.shape[0], dtype=float, device=device)
    wp.launch(kc.measure_distances_to_mesh, dim=points.shape[0], inputs=[frame[0].id, points, float(diag)],
              outputs=[dist], device=device)
    return float(np.percentile(dist.numpy(), 99)) / max(diag, 1e-12)


def _motion_sample(v: np.ndarray, device):
    """At most 4,096 of a frame's vertices on the device (for :func:`_input_motion`)."""
    return wp.array(np.ascontiguousarray(v[::_stride(len(v), 4096)], np.float32), dtype=wp.vec3, device=device)


def _same_frame(a: tuple, b: tuple) -> bool:
    """Whether two input frames (V, F) are the same mesh, vertex for vertex and face for face."""
    return np.array_equal(a[1], b[1]) and np.array_equal(a[0], b[0])  # (False for other shapes)


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

        order = tqdm(order, desc=f"convert ({strategy})", unit="frame")
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
            if not np.isfinite(out[t]).all():
                raise RuntimeError(f"{where}: conversion ({strategy}) produced NaN/inf at frame {t}; "
                                   "the input frame may be degenerate")
            if journal is not None:
                figures = [getattr(pf, name)[t] for name in _PER_FRAME_RECORD]
                figures += [pf.input_motion[m] if m < T else 0.0, reanchored]
                journal.write(index, t, raw[t], X=out[t], figures=np.array(figures, np.float64), **change)
        samples = {K: samples.get(K), t: _motion_sample(v, device)} if t != K else {K: _motion_sample(v, device)}
        conv.first = False
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


def to_fixed_topology(seq, strategy: str = DEFAULT_STRATEGY, template=None, device=None, progress: bool = False,
                      should_stop=None, journal: ConversionJournal | None = None, **options) -> FixedTopologySequence:
    """Convert a varying-topology sequence into a fixed-topology one on ``template``'s faces.

    Args:
        seq: a :class:`VaryingTopologySequence` (or a fixed one, or a list of (V, F) frames).
        strategy: one of :data:`STRATEGIES` (module docstring); default ``"graph"``.
        template: ``(V, F)`` mesh or a mesh file path; default: the first frame.
        device: Warp device (default: Warp's default device).
        progress: show a tqdm progress bar over frames.
        should_stop: a callable checked between frames (e.g. the CLI's Ctrl-C flag); once true
            the conversion ends after the frames done so far (at least the first): the result
            then holds frames 0..k-1 only.
        journal: a :class:`~dynmesh_warp.convert_journal.ConversionJournal`: every frame fitted is
            written to it as it is done, and the frames it holds from an interrupted conversion of
            the same input and options are taken from it instead of fitted (``convert --resume``).
        **options: strategy options (module docstring); unknown names raise TypeError.

    Returns:
        FixedTopologySequence with the template's faces, the input's fps and name, and a
        ``conversion`` attribute (:class:`ConversionInfo`); fewer frames than the input only
        after ``should_stop``.

    Raises:
        MeshDataError: an empty/invalid frame or template (naming it), a template out of the
            surface's reach. Warns (UserWarning) about frames of very different scale.
    """
    with _journaling(journal):
        return _to_fixed(seq, strategy, template, device, progress, should_stop, None, **options)


def _to_fixed(seq, strategy, template, device, progress, should_stop, stop_forward, **options):
    """:func:`to_fixed_topology`, with ``stop_forward`` (:func:`_convert_frames`) for
    :func:`to_piecewise_fixed`'s first run."""
    vseq = _as_varying(seq)
    vseq.__dict__.pop(_CACHE, None)  # found afresh (the caller may have changed its frames since)
    try:
        return _to_fixed_run(vseq, seq, strategy, template, device, progress, should_stop, stop_forward, **options)
    finally:
        vseq.__dict__.pop(_CACHE, None)  # nothing of it stays on the caller's sequence


def _to_fixed_run(vseq, seq, strategy, template, device, progress, should_stop, stop_forward, **options):
    """The body of :func:`_to_fixed` (``vseq``: ``seq`` as a varying sequence)."""
    start = time.perf_counter()
    o = _resolve_options(strategy, options)
    set_deterministic(bool(o["deterministic"]), int(o.get("nodes_per_vertex", 4)))
    where = vseq.source or vseq.name
    for t, (v, f) in enumerate(vseq.frames):  # frames may have been mutated after construction
        src = vseq.frame_sources[t] if vseq.frame_sources else where
        validate_mesh(v, f, src, t)
    vseq, unused, welded, turned, rewound = _drop_unused(vseq)
    for t, (v, f) in enumerate(vseq.frames):
        if not _has_area(v, f):  # a new user's points on a line: converted with "coverage 1400 %", exit 0
            src = vseq.frame_sources[t] if vseq.frame_sources else where
            raise MeshDataError(f"{src}, frame {t}: every face has zero area (its corners on one line or point): "
                                "no surface to convert")
    T = vseq.num_frames
    device = wp.get_device(device)
    off_scale = _check_scales(vseq, float(o["scale_tolerance"]))
    _check_repeats(vseq)
    K = _key_frame(vseq, o["key_frame"], template is not None, off_scale)
    given = template is not None
    if given:
        if isinstance(template, (str, bytes)) or hasattr(template, "__fspath__"):
            from .io import read_mesh

            template = read_mesh(template)
        try:
            tv, tf = template
        except (TypeError, ValueError):
            raise MeshDataError("template: expected a (V, F) pair or a mesh file path") from None
        template = validate_mesh(tv, tf, "template")
    # the topology report is host work that does not steer the conversion: a worker thread does
    # it while the main thread waits on the device (NumPy and SciPy release the GIL in its sorts)
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="topology")
    try:
        topology = pool.submit(_topology_events, vseq)
        res = _convert_from_key(vseq, strategy, o, K, template, device, progress, should_stop, where, stop_forward)
        trials = _key_candidates(vseq, o, K, given, res, off_scale=off_scale)
        part, moving = res.conversion.moving_part, None
        if trials and part is not None:
            # with static surroundings the Chamfer distance is mostly theirs: the moving points
            # rank; unless they show on fewer than MOVING_FRAMES of the frames (what comes and
            # goes, as a reconstruction's floaters do, is no subject in static surroundings)
            moving = _moving_points(vseq, device)
            if sum(len(m) > 0 for m in moving) < MOVING_FRAMES * T:
                part = moving = None
                trials = _key_candidates(vseq, o, K, given, res, moving_part=None, off_scale=off_scale)
        if trials:
            if progress:  # the run goes on: say why
                why = _key_retry_reason(res.conversion.coverage, K, part) or "always_try_keys"
                print(f"conversion: the run from key frame {K}: {why}; trying key frames "
                      f"{', '.join(map(str, trials))} (key_candidates)", file=sys.stderr, flush=True)
            key_score = "chamfer" if moving is None else "moving"

            def trial(k, r):  # (key frame, mean coverage, score, seconds)
                score = _chamfer_to_input(r, vseq, device) if moving is None else _moving_score(r, vseq, moving, device)
                return (k, float(np.mean(r.conversion.coverage)), score, float(np.sum(r.conversion.frame_seconds)))

            tried = [trial(K, res)]
            best = tried[0][2]
            for k in trials:
                if should_stop is not None and should_stop():
                    break
                r = _convert_from_key(vseq, strategy, o, k, None, device, progress, should_stop, where)
                if len(r.conversion.coverage) < T:  # stopped during this run: keep the finished ones
                    break
                tried.append(trial(k, r))
                if tried[-1][2] < best:
                    res, best = r, tried[-1][2]
            res.conversion.key_trials, res.conversion.key_score = tried, key_score
        info = res.conversion
        info.dropped_unused, info.welded, info.turned_outward, info.rewound = unused, welded, turned, rewound
        if float(o["far_part_area"]) <= 0:
            info.floater_webs = _floater_webs(vseq, res, device, float(o["far_part_gap"]))
        info.input_dropouts = _input_dropouts(vseq, info, device)
        info.missing_parts = _missing_parts(vseq, info, device, off_scale)
        if info.input_dropouts and bool(o["bridge_dropouts"]):
            res = _bridge_dropouts(res, info)
        res.all_topology_events = topology.result()  # every frame's (to_piecewise_fixed after a forward stop)
        info.topology_events = [e for e in res.all_topology_events
                                if info.first_frame <= e[0] < info.first_frame + len(info.coverage)]
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
    info.segments = [(info.first_frame, info.first_frame + res.num_frames, info.key_frame, res.num_vertices)]
    info.open_edges = [_open_edges(res.F)]
    fl = info.floater_webs
    if fl and bool(o["floater_retry"]) and not (should_stop is not None and should_stop()):
        # the web reaches out to small separate input parts: floaters, by that evidence (a real thin
        # part's fragments meet unstretched faces); converted again without them, kept if less poor
        if progress:
            print(f"conversion: the web on frame(s) {', '.join(map(str, fl[:8]))} reaches out to small separate "
                  f"input parts (floaters?); converting again without them (far_part_area={FLOATER_AREA})",
                  file=sys.stderr, flush=True)
        retry = _to_fixed(seq, strategy, template, device, progress, should_stop, stop_forward,
                          **{**options, "far_part_area": FLOATER_AREA})
        r = retry.conversion
        if len(r.coverage) < len(info.coverage):
            pass  # stopped by the caller during the second run: the first, complete, is kept
        elif _badness(r).max() < _badness(info).max():
            r.floater_retry = fl
            res = retry
        else:
            info.floater_retry_rejected = True
    res.conversion.seconds_all = time.perf_counter() - start
    return res


def to_piecewise_fixed(seq, strategy: str = DEFAULT_STRATEGY, template=None, device=None, progress: bool = False,
                       should_stop=None, journal: ConversionJournal | None = None, **options):
    """Convert like :func:`to_fixed_topology`, starting a new template where one template cannot
    follow the input: a piecewise-fixed sequence (issue 12's topology segments).

    The run from the automatic key frame is checked frame by frame: a frame is poor when its
    coverage exceeds POOR_COVERAGE (a lost part) or its web fraction exceeds POOR_WEB (the
    template fused parts the input has pulled apart, :func:`web_fraction`). At the first poor
    frame on either side of the key frame, the frames from the input's last topology change
    before it (from that frame itself when there is none) to the end on that side are converted
    again with a template of their own (their automatic key frame), and the new segment is kept
    when its worst frame is better than those frames were: at most ``max_segments`` segments
    (option), each checked again. A given ``template`` or ``key_frame`` keeps one template.
    The first run's forward pass ends at the second poor web frame in a row (the frames after it
    go to the new template when it is better; when it is not, the whole sequence is converted
    again with one template, the run without the stop), so that the common cut does not fit
    those frames twice.

    Returns:
        the :class:`FixedTopologySequence` of :func:`to_fixed_topology` when one template holds
        (the common case); else a :class:`VaryingTopologySequence` whose frames share one face
        array within each segment (``seq.segments()`` finds them again after a save and load,
        and the physics rebuilds its BVH once per segment). Either way ``result.conversion``
        (:class:`ConversionInfo`) lists the ``segments``.
    """
    start = time.perf_counter()
    with _journaling(journal):
        res = _to_piecewise(seq, strategy, template, device, progress, should_stop, options)
    res.conversion.seconds_all = time.perf_counter() - start
    return res


def _input_dropouts(vseq, info, device) -> list:
    """``ConversionInfo.input_dropouts`` of a run (``info``, frames from ``info.first_frame``):
    those its frame loop found (already in ``info.input_dropouts``: :func:`_convert_frames` looks
    for them while ``bridge_dropouts`` is on) and the other runs of up to DROPOUT_FRAMES frames
    :func:`_dropout_run` finds, each checked where the ``input_motion`` at either end of the run
    stands out from its neighbours' over ``JUMP_WINDOW`` frames either side (``input_motion[t]``
    is the motion between frames t - 1 and t, measured from t - 1 forward of the key frame and
    from t before it: a part that vanishes shows at the run's first frame, or after its last)."""
    m = np.asarray(info.input_motion, float)
    lo, out = info.first_frame, list(info.input_dropouts)
    found = {d[0] for d in out}
    for i in range(1, len(m) - 1):
        for k in range(1, DROPOUT_FRAMES + 1):
            if i + k >= len(m) or any(lo + j in found for j in range(i, i + k)):
                break
            near = np.r_[m[max(1, i - JUMP_WINDOW):i], m[i + k + 1:i + k + 1 + JUMP_WINDOW]]
            run = _dropout_run(vseq, lo + i - 1, lo + i + k, max(m[i], m[i + k]), near, device)
            if run:
                out.extend(run)
                found.update(d[0] for d in run)
                break
    # the motion was measured from the key frame outwards, so a key frame inside a run (a user's
    # --key-frame) shows no spike: the runs that hold it are tested without one
    K = info.key_frame
    for k in range(1, DROPOUT_FRAMES + 1):
        runs = (_dropout_run(vseq, a - 1, a + k, 1.0, (), device) for a in range(K - k + 1, K + 1)
                if lo + 1 <= a and a + k < lo + len(m) and not found & set(range(a, a + k)))
        run = next((r for r in runs if r), None)
        if run:
            out.extend(run)
            break
    return sorted(out)


def _far_p99(vseq, src: int, mesh, diag: float, device) -> float:
    """The 99th percentile of at most 4,096 of input frame ``src``'s vertices' distances to
    ``mesh`` (a wp.Mesh or a frame), over ``diag``."""
    v = vseq.frames[src][0]
    return float(np.percentile(nearest_surface(mesh, v[::_stride(len(v), 4096)], device=device).dist, 99)) / diag


def _nearly_closed(F: np.ndarray) -> bool:
    """A closed surface, up to a defect or two (a new user's marching cubes: one open edge):
    open edges at most DROPOUT_OPEN_EDGES x the faces."""
    return _open_edges(F) <= DROPOUT_OPEN_EDGES * len(F)


def _missing_parts(vseq, info, device, off_scale=()) -> list:
    """``ConversionInfo.missing_parts``: ``(first, last, lost)`` of the runs of input frames
    (absolute indices) that lack a part the frame next to the run has, where the bridge of
    :func:`_dropout_run` cannot reach: runs of more than DROPOUT_FRAMES frames (a new user's arm
    gone for six frames while the body moved on) and runs that reach the first or the last frame
    (a part that enters or leaves, or a dropout there; no frame on that side). The frames either
    side of a long run differ by the motion between them, so, unlike :func:`_dropout_run`, each
    end of a run is checked against its own neighbour only: the surface area changes there by
    ``lost`` (the fraction of the larger of the two), over DROPOUT_LEAST and DROPOUT_RATIO x the
    median area change of the ``JUMP_WINDOW`` frames either side; every frame of the run keeps
    under the neighbour's area less half of ``lost`` (and a run between two frames comes back by
    at least half of it); the neighbour lies over DROPOUT_LEAST of the diagonal from the run's
    end frame (99th pct.), DROPOUT_RATIO x farther than the other way (a part went; nothing moved
    away); and where both are closed, at least DROPOUT_VOLUME x as large a fraction of the volume
    went as of the area (a part folded flat onto the body keeps its volume). Runs that hold one of
    ``info.input_dropouts`` are left to it, and so are runs with a frame of ``off_scale`` in them or
    next to them (:func:`_check_scales` warns of those: a frame in other units changes the area
    too). The frames' areas first (:func:`_frame_areas`); two queries per end that passes them."""
    lo, T = info.first_frame, len(info.coverage)
    if T < 3:
        return []
    area = _frame_areas(vseq)[lo:lo + T]  # (found once per conversion)
    step = area[1:] / np.maximum(area[:-1], 1e-30) - 1.0  # step[i]: from frame i to i + 1 (relative)
    short = {d[0] - lo for d in info.input_dropouts} | {t - lo for t in off_scale}

    def stands_out(i):
        near = np.abs(np.r_[step[max(0, i - JUMP_WINDOW):i], step[i + 1:i + 1 + JUMP_WINDOW]])
        return abs(step[i]) > DROPOUT_LEAST and (not near.size or abs(step[i]) > DROPOUT_RATIO * float(np.median(near)))

    def lacks(full, part):  # input frame ``part`` lacks surface (and volume) that frame ``full`` has
        fv, pv = vseq.frames[lo + full], vseq.frames[lo + part]
        if _nearly_closed(fv[1]) and _nearly_closed(pv[1]):
            vol = abs(signed_volume(*fv))
            if 1.0 - abs(signed_volume(*pv)) / max(vol, 1e-30) < DROPOUT_VOLUME * (1.0 - area[part] / area[full]):
                return False
        diag = max(_bbox_diag(fv[0]), _bbox_diag(pv[0]), 1e-12)
        gone = _far_p99(vseq, lo + full, pv, diag, device)
        return gone > DROPOUT_LEAST and DROPOUT_RATIO * _far_p99(vseq, lo + part, fv, diag, device) < gone

    def found(s, e, full, lost):  # the run s..e (relative) lacks the part of frame ``full``
        return (not short & set(range(min(s, full), max(e, full) + 1))
                and bool((area[s:e + 1] <= area[full] * (1.0 - 0.5 * lost)).all()) and lacks(full, s if full < s else e))

    out, i = [], 0
    rise = np.flatnonzero((step > 0) & np.array([stands_out(k) for k in range(len(step))]))
    if rise.size:  # a run from the first frame: the area rises into the frames after it
        e = int(rise[0])
        lost = 1.0 - float(area[e] / area[e + 1])
        if found(0, e, e + 1, lost):
            out.append((lo, lo + e, lost))
            i = e + 1
    while i < len(step):
        s = i + 1  # a run from frame s: the area falls into it
        if not (step[i] < 0 and stands_out(i)):
            i += 1
            continue
        lost = -float(step[i])
        e = next((e for e in range(s, T - 1) if area[e] > area[i] * (1.0 - 0.5 * lost)
                  or (step[e] >= 0.5 * lost and stands_out(e))), T - 1)
        if ((e == T - 1 or e - s + 1 > DROPOUT_FRAMES) and found(s, e, i, lost)
                and (e == T - 1 or lacks(e + 1, e))):
            out.append((lo + s, lo + e, lost))
            i = e + 1
        else:
            i += 1
    return out


def _dropout_run(vseq, p: int, n: int, spike: float, near, device) -> list | None:
    """``[(t, gone, agree)]`` for the input frames t strictly between p and n (either order) when
    they are a dropout, else None: frames p and n agree (``agree``: the 99th percentile of at
    most 4,096 of one's vertices' distances to the other's surface, the smaller way) and each
    frame t between lacks a part both have: both lie farther than DROPOUT_LEAST from t's surface
    (``gone``, the smaller of the two), over DROPOUT_AGREE x farther than from each other, while
    t's own surface lies DROPOUT_RATIO x nearer to p's or n's than that (t lacks a part; it did not
    move away), and t has less surface area than p and n and, where the three are closed, lost
    DROPOUT_VOLUME x as large a fraction of their volume (a part folded flat onto the body keeps
    its volume). Fractions of the larger diagonal of p and n (the same for (p, n) and (n, p)).
    Checked only where ``spike``, the ``input_motion`` where the part went, is over
    DROPOUT_LEAST and over DROPOUT_RATIO x the median of ``near`` (its neighbours' motion): the
    area and volume on the host first, then two queries for the agreement, then a BVH and three
    queries per frame."""
    near = np.asarray(near, float)
    T = vseq.num_frames
    if (not (0 <= min(p, n) and max(p, n) < T and abs(n - p) >= 2) or spike <= DROPOUT_LEAST
            or (near.size and spike <= DROPOUT_RATIO * np.median(near))):
        return None

    # what the ends have and a frame lacks is surface, and for closed surfaces volume too: a part
    # folded flat onto the body (a new user's arm slapped down for a frame: its remeshed contact
    # lost 4 % of the area and none of the volume) or a sheet's edge folded back (no area lost)
    # is motion, not a dropout. Host sums over the faces: checked before any query
    run = range(min(p, n) + 1, max(p, n))
    least_area = min(surface_area(*vseq.frames[e]) for e in (p, n))
    def closed(e):
        return _nearly_closed(vseq.frames[e][1])

    ends_closed = closed(p) and closed(n)
    least_volume = min(abs(signed_volume(*vseq.frames[e])) for e in (p, n)) if ends_closed else 0.0
    for t in run:
        lost = 1.0 - surface_area(*vseq.frames[t]) / max(least_area, 1e-30)
        if lost <= 0.0:
            return None
        if ends_closed and closed(t):
            if 1.0 - abs(signed_volume(*vseq.frames[t])) / max(least_volume, 1e-30) < DROPOUT_VOLUME * lost:
                return None
    diag = max(_bbox_diag(vseq.frames[p][0]), _bbox_diag(vseq.frames[n][0]), 1e-12)
    # either way, the smaller: the same for (p, n) and (n, p)
    agree = min(_far_p99(vseq, p, vseq.frames[n], diag, device), _far_p99(vseq, n, vseq.frames[p], diag, device))
    if DROPOUT_AGREE * agree >= spike:  # the ends differ as much as the part is gone (the first
        return None  # frame's gone is at most its spike): motion
    out = []
    for t in run:
        here = _wp_mesh(*vseq.frames[t], device)  # asked by both ends: one BVH
        gone = min(_far_p99(vseq, p, here, diag, device), _far_p99(vseq, n, here, diag, device))
        # and the frame's own surface lies on p's or n's (it lacks a part, it adds none: a frame
        # moved away as a whole is the input's jump, not a dropout); the nearer in time first
        if not (gone > DROPOUT_LEAST and gone > DROPOUT_AGREE * agree):
            return None
        ends = sorted((p, n), key=lambda e: abs(e - t))
        if not any(DROPOUT_RATIO * _far_p99(vseq, t, vseq.frames[e], diag, device) < gone for e in ends):
            return None
        out.append((t, gone, agree))
    return out


def _dropout_runs(frames) -> list:
    """The runs ``(first, last)`` of consecutive frames in ``frames`` (dropout frames)."""
    runs = []
    for t in sorted(set(frames)):
        if runs and t == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], t)
        else:
            runs.append((t, t))
    return runs


def _bridge_dropouts(res, info):
    """``res`` with each run of ``info.input_dropouts`` inside its frames replaced by the
    converted frames either side, blended linearly in time (the same template: vertex-wise; one
    frame: their mean), listed in ``info.bridged_frames``; ``frame_motion`` measured again. The
    frames' other per-frame figures stay the fit's, but for ``web`` and ``buried``, set to 0: they
    described the fit the bridge replaced (its part pressed into what is left: "buried", which
    made those frames poor and the segment cut undid the bridge; a new user's arm occluded for 4
    frames came out of ``convert`` in two segments, the arm lost on those frames, where
    :func:`to_fixed_topology` bridged it)."""
    V = np.array(res.V, copy=True)
    for a, b in _dropout_runs({d[0] for d in info.input_dropouts}):
        i, j = a - 1 - info.first_frame, b + 1 - info.first_frame
        if 0 <= i and j < len(V):
            for t in range(a, b + 1):
                w = (t - (a - 1)) / (b + 2 - a)
                V[t - info.first_frame] = (1.0 - w) * V[i] + w * V[j]
                info.bridged_frames.append(t)
                for figure in (info.web, info.buried):
                    if len(figure) == len(V):
                        figure[t - info.first_frame] = 0.0
    out = FixedTopologySequence(V, res.F, fps=res.fps, name=res.name, source=res.source)
    out.conversion = info
    info.frame_motion = _frame_motion(out.V)
    return out


def _frame_motion(V: np.ndarray, most: int = 4096) -> list:
    """``ConversionInfo.frame_motion`` of the frames V (T, N, 3) of one template."""
    V = np.asarray(V)[:, ::_stride(V.shape[1], most)]
    out = [0.0]
    for t in range(1, len(V)):
        d = np.linalg.norm(V[t] - V[t - 1], axis=1)
        out.append(float(np.percentile(d, 99)) / max(_bbox_diag(V[t]), 1e-12))
    return out


def slide_ratio(info) -> tuple[float | None, np.ndarray]:
    """(the median over frames of ``frame_motion`` / max(``input_motion``, SLIDE_FLOOR), or None
    without such frames; the per-frame ratios, NaN where a frame has no motion figure: the first
    frame and where a segment starts)."""
    m, i = np.asarray(info.frame_motion, float), np.asarray(info.input_motion, float)
    r = np.full(m.shape, np.nan)
    if m.size != i.size or m.size < 2:
        return None, r
    ok = m > 0
    r[ok] = m[ok] / np.maximum(i[ok], SLIDE_FLOOR)
    return (float(np.median(r[ok])) if ok.any() else None), r


def _jumps(motion) -> np.ndarray:
    """The frames whose ``frame_motion`` is over ``JUMP_RATIO`` x the median of their neighbours'
    (``JUMP_WINDOW`` either side, segment starts left out) and over ``JUMP_LEAST`` of the diagonal."""
    m = np.asarray(motion, float)
    out = []
    for t in np.flatnonzero(m > JUMP_LEAST):
        near = np.r_[m[max(0, t - JUMP_WINDOW):t], m[t + 1:t + 1 + JUMP_WINDOW]]
        near = near[near > 0]
        if near.size and m[t] > JUMP_RATIO * float(np.median(near)):
            out.append(int(t))
    return np.array(out, int)


#: the attribute of the sequence being converted that holds what :func:`_once` found (emptied at
#: the start and end of each :func:`_to_fixed`, so it never outlives a conversion)
_CACHE = "_conversion_cache"


def _once(seq: VaryingTopologySequence, key: tuple, make):
    """``make()``, found once per conversion of ``seq`` and ``key``."""
    cache = seq.__dict__.setdefault(_CACHE, {})
    if key not in cache:
        cache[key] = make()
    return cache[key]


def _frame_areas(seq: VaryingTopologySequence) -> np.ndarray:
    """Each frame's surface area (T,) (the key frame's choice and every run's converted area ratio
    ask), found once per conversion."""
    return _once(seq, ("frame areas", seq.num_frames), lambda: np.array([surface_area(v, f) for v, f in seq.frames]))


def _to_piecewise(seq, strategy, template, device, progress, should_stop, options: dict):
    """The body of :func:`to_piecewise_fixed` (which times it)."""
    o = _resolve_options(strategy, options)
    vseq = _as_varying(seq)
    T = vseq.num_frames
    limit = int(o["max_segments"])
    if limit <= 1 or template is not None or o["key_frame"] not in ("auto", None):
        return to_fixed_topology(vseq, strategy, template, device, progress, should_stop, **options)
    runs = {}

    def convert(lo, hi):  # frames lo..hi-1 with a template of their own; None when stopped meanwhile
        if (lo, hi) not in runs:
            sub = VaryingTopologySequence(list(vseq.frames[lo:hi]), fps=vseq.fps, name=vseq.name, source=vseq.source)
            with _scale_checked():  # this run's check would number the input's frames from lo
                r = to_fixed_topology(sub, strategy, None, device, progress, should_stop, **options)
            runs[lo, hi] = r if len(r.conversion.coverage) == hi - lo else None
        return runs[lo, hi]

    def stopped():
        return should_stop is not None and bool(should_stop())

    # the first run ends its forward pass at the second poor web frame in a row: the frames after
    # it would be converted again with a new template (the common cut), so they are not fitted
    # twice. Frames poor by their buried faces end it at the (DROPOUT_FRAMES + 2)-th while
    # dropouts are bridged: the part a dropout's frames lack is pressed into what is left
    # ("buried") until the loop reaches the frame after them and bridges them (a new user's arm
    # occluded for 4 frames: the pass ended inside the dropout, and the cut gave the frames from
    # it a template without the arm)
    row = 2 + (DROPOUT_FRAMES if bool(o["bridge_dropouts"]) else 0)

    def stop_forward(t, web, buried):
        far = web + buried
        return bool((web[t] > POOR_WEB and web[t - 1] > POOR_WEB)
                    or (t - row >= 0 and all(far[t - j] > POOR_WEB for j in range(row))))

    first = _to_fixed(vseq, strategy, None, device, progress, should_stop, stop_forward, **options)
    events = first.all_topology_events
    res = first
    if len(first.conversion.coverage) < T and not stopped():  # the forward pass stopped at frame b
        K, b = first.conversion.key_frame, first.num_frames - 1
        ev = [t for t, _ in events if K < t <= b]
        a = max(ev) if ev else b
        new = convert(a, T)
        if new is None and stopped():  # stopped by the caller meanwhile: the frames 0..b done
            return first
        if new is not None and _badness(new.conversion)[:b + 1 - a].max() < _badness(first.conversion)[a:].max():
            keep = _slice_result(first, 0, a, 0)
            left = _split_segments(0, keep, events, limit - 1, convert)
            segs = left + _split_segments(a, new, events, limit - len(left), convert)
            return _join_segments(vseq, sorted(segs, key=lambda x: x[0]), first.conversion, events)
        # the new template is not better there: one template for every frame, as without the stop
        with _scale_checked():
            res = to_fixed_topology(vseq, strategy, None, device, progress, should_stop, **options)
        if len(res.conversion.coverage) < len(first.conversion.coverage):
            # stopped by the caller during that run: the first run's frames 0..b are more (a new
            # user's stop kept 1 frame of the rerun and threw the first run's 7 away)
            return first
        if new is not None:
            res.conversion.rejected_cuts.append((a, T))
    if len(res.conversion.coverage) < T:  # stopped by the caller
        return res
    segs = _split_segments(0, res, events, limit, convert)
    return segs[0][1] if len(segs) == 1 else _join_segments(vseq, segs, res.conversion, events)


def _stretched_far(info) -> np.ndarray:
    """Per frame, the fraction of the converted area on stretched faces far from the input, outside
    it (``web``) or inside it (``buried``): what the restarts, the segment cuts and the floater
    check weigh (a template crumpled inside the body is mended by them too)."""
    return np.asarray(info.web, float) + (np.asarray(info.buried, float) if len(info.buried) else 0.0)


def _badness(info) -> np.ndarray:
    """Per frame, how poor the fit is: max(coverage / POOR_COVERAGE, :func:`_stretched_far` /
    POOR_WEB); > 1 is poor."""
    return np.maximum(np.asarray(info.coverage, float) / POOR_COVERAGE, _stretched_far(info) / POOR_WEB)


def _segment_cut(info, events: list, lo: int) -> tuple | None:
    """The frames (a, b) (absolute, b exclusive) a run over frames lo.. should convert again with
    a template of their own, or None: from the first poor frame after the key frame, the range
    from the input's last topology change at or before it to the end; else, before the key
    frame, from frame lo to the first topology change after the last poor frame."""
    bad = np.flatnonzero(_badness(info) > 1.0) + lo
    K, hi = lo + info.key_frame, lo + len(info.coverage)
    after, before = bad[bad > K], bad[bad < K]
    if after.size:
        b = int(after[0])
        ev = [t for t, _ in events if K < t <= b]
        return (max(ev) if ev else b), hi
    if before.size:
        b = int(before[-1])
        ev = [t for t, _ in events if b < t <= K]
        return lo, (min(ev) if ev else b + 1)
    return None


def _split_segments(lo: int, res, events: list, budget: int, convert) -> list:
    """``[(start, result)]`` covering ``res``'s frames (which start at input frame lo): ``res``
    itself, or split where :func:`_segment_cut` says and the new run is better (at most
    ``budget`` pieces; each piece is checked again)."""
    hi = lo + res.num_frames
    cut = _segment_cut(res.conversion, events, lo) if budget > 1 else None
    if cut is None or cut == (lo, hi):
        return [(lo, res)]
    a, b = cut
    new = convert(a, b)
    if new is None or _badness(new.conversion).max() >= _badness(res.conversion)[a - lo:b - lo].max():
        if new is not None:  # the cut does not help: said in the summary
            res.conversion.rejected_cuts.append((a, b))
        return [(lo, res)]  # the cut does not help (or the run was stopped): one template here
    keep_lo, keep_hi = (lo, a) if a > lo else (b, hi)
    left = _split_segments(keep_lo, _slice_result(res, keep_lo, keep_hi, lo), events, budget - 1, convert)
    right = _split_segments(a, new, events, budget - len(left), convert)
    return sorted(left + right, key=lambda x: x[0])


def _slice_result(res, a: int, b: int, lo: int):
    """The frames a..b-1 (absolute; ``res`` starts at input frame lo) of a conversion result,
    its per-frame info sliced to match (frame indices become relative to the slice)."""
    info = res.conversion
    i, j = a - lo, b - lo
    out = FixedTopologySequence(res.V[i:j], res.F, fps=res.fps, name=res.name, source=res.source)
    out.conversion = dataclasses.replace(info, num_frames=j - i, key_frame=info.key_frame - i,
                                         coverage=list(info.coverage[i:j]), web=list(info.web[i:j]),
                                         coverage_tail=list(info.coverage_tail[i:j]), flipped=list(info.flipped[i:j]),
                                         area_ratio=list(info.area_ratio[i:j]),
                                         frame_motion=[0.0] + list(info.frame_motion[i + 1:j]),
                                         input_motion=[0.0] + list(info.input_motion[i + 1:j]),
                                         buried=list(info.buried[i:j]), rejected_cuts=list(info.rejected_cuts),
                                         frame_seconds=list(info.frame_seconds[i:j]), **_frame_fields(info, -i, i, j))
    return out


def _frame_fields(info, shift: int, lo: int | None = None, hi: int | None = None) -> dict:
    """``info``'s fields that name frames, each frame index moved by ``shift`` (those of frames
    lo..hi-1 only, when given; the key trials' key frames all): what a slice of a result or a
    segment placed in a longer sequence carries."""
    def kept(t):
        return lo is None or lo <= t < hi

    out = {name: [t + shift for t in getattr(info, name) if kept(t)]
           for name in ("reanchored_frames", "repaired_frames", "unrecovered_frames", "floater_webs",
                        "floater_retry", "bridged_frames")}
    out["recovered_frames"] = [(t + shift, src) for t, src in info.recovered_frames if kept(t)]
    out["ignored_parts"] = {t + shift: x for t, x in info.ignored_parts.items() if kept(t)}
    out["key_trials"] = [(k + shift, *rest) for k, *rest in info.key_trials]
    return out


def _join_segments(vseq, segs: list, whole, events: list) -> VaryingTopologySequence:
    """One sequence of the segments' frames (``[(start, result)]``, in order), each segment's
    frames sharing its template's face array; ``conversion`` merges the segments' infos (frame
    indices absolute) with the input's topology ``events`` and the first run's (``whole``)
    dropped vertices."""
    frames = [(v, r.F) for _, r in segs for v in r.V]
    out = VaryingTopologySequence(frames, fps=vseq.fps, name=vseq.name, source=vseq.source)
    first = segs[0][1].conversion
    info = ConversionInfo(first.strategy, first.options, vseq.num_frames,
                          max(r.num_vertices for _, r in segs), key_frame=first.key_frame + segs[0][0])
    for lo, r in segs:
        c = r.conversion
        info.coverage += c.coverage
        info.coverage_tail += c.coverage_tail
        info.flipped += c.flipped
        info.area_ratio += c.area_ratio
        info.frame_motion += c.frame_motion
        info.input_motion += c.input_motion
        info.web += c.web
        info.buried += c.buried
        info.rejected_cuts += [x for x in c.rejected_cuts if x not in info.rejected_cuts]
        info.frame_seconds += c.frame_seconds
        for name, value in _frame_fields(c, lo).items():
            if isinstance(value, dict):
                getattr(info, name).update(value)
            else:
                getattr(info, name).extend(value)
        info.segments.append((lo, lo + r.num_frames, c.key_frame + lo, r.num_vertices))
        info.open_edges += c.open_edges
    info.key_score = "+".join(sorted({r.conversion.key_score for _, r in segs} - {""}))
    info.topology_events, info.dropped_unused, info.welded = list(events), whole.dropped_unused, whole.welded
    info.turned_outward, info.input_dropouts, info.rewound = whole.turned_outward, whole.input_dropouts, whole.rewound
    info.missing_parts = whole.missing_parts
    out.conversion = info
    return out


def _stride(n: int, most: int) -> int:
    """The k for which every k-th of n points is at most ``most`` of them (at least 1)."""
    return max(-(-n // most), 1)


def _chamfer_to_input(res, vseq, device) -> float:
    """A run's GT-free score among key trials: the mean over frames of the converted frame's
    Chamfer distance to the input frame (vertices, squared, the DG-Mesh convention) [m^2]. Both
    directions: a run that leaves input parts uncovered and one whose vertices bunch or fold
    away from the input pay for it. Over pcow's runs from 9 key frames it ranks them like their
    true CD with Spearman 0.98; the one-sided mean coverage 0.73, and that chose +30 % over
    +13 % between two runs 0.75 % apart (docs/conversion.md)."""
    def few(P):  # at most SCORE_POINTS points, by a fixed stride: the same subset for every run
        return P[::_stride(len(P), SCORE_POINTS)]

    return float(np.mean([chamfer_distance(few(res.V[t]), few(vseq.frames[res.conversion.first_frame + t][0]),
                                           squared=True, device=device).value for t in range(len(res.V))]))


def _moving_points(vseq, device) -> list:
    """Per input frame, the indices of its moving points: of at most ``SCORE_POINTS`` vertices
    (a fixed stride), those farther than ``MOVING_GAP`` x the frame's bbox diagonal from one of
    the frames :func:`_sample_frames` spreads over the sequence (as :func:`_node_spacing` finds
    the template's moving part). The static surroundings of a subject have none; the same
    points for every key trial (they come from the input alone)."""
    T = vseq.num_frames
    samples = _sample_frames(T)
    meshes = {s: _wp_mesh(*vseq.frames[s], device) for s in samples}
    lo = np.min([v.min(axis=0) for v, _ in vseq.frames], axis=0)  # the box of every frame (no copy of them all)
    hi = np.max([v.max(axis=0) for v, _ in vseq.frames], axis=0)
    reach = 10.0 * max(float(np.linalg.norm(hi - lo)), 1e-6)
    out = []
    for t, (v, _) in enumerate(vseq.frames):
        idx = np.arange(0, len(v), _stride(len(v), SCORE_POINTS))
        far = MOVING_GAP * _bbox_diag(v)
        moves = np.zeros(len(idx), bool)
        for s, mesh in meshes.items():
            if s != t:
                moves |= nearest_surface(mesh, v[idx], device=device, max_dist=reach).dist > far
        out.append(idx[moves])
    return out


def _moving_distances(res, vseq, moving: list, device) -> list:
    """Per frame of run ``res``, the distances from the input frame's moving points
    (:func:`_moving_points`) to the converted surface [m] (empty where a frame has none)."""
    out = []
    for t in range(len(res.V)):
        v, idx = vseq.frames[res.conversion.first_frame + t][0], moving[res.conversion.first_frame + t]
        out.append(nearest_surface((res.V[t], res.F), v[idx], device=device).dist if len(idx) else np.zeros(0))
    return out


def _tail_mean(d: np.ndarray, fraction: float) -> float:
    """The mean of the largest ``fraction`` of ``d`` (at least one value; 0 when empty)."""
    if not len(d):
        return 0.0
    n = max(1, int(np.ceil(fraction * len(d))))
    return float(np.mean(np.partition(d, len(d) - n)[len(d) - n:]))


def _moving_score(res, vseq, moving: list, device) -> float:
    """A run's GT-free score among key trials when the capture has static surroundings (a
    floor, a background): the mean of the largest ``MOVING_SCORE_TAIL`` (0.5 %) of the
    distances from the input frames' moving points (:func:`_moving_points`) to the converted
    surface, pooled over every frame [m] (0 without moving points). The surroundings fit alike
    in every run and, being most of the frame, would outweigh the subject in
    :func:`_chamfer_to_input`; a limb the run lost leaves its input points far from the output
    here. Pooled and cut to the tail, a limb lost on a few frames counts as it does on every
    frame: a mean over frames would dilute it by the frames and the subject's other points
    (docs/conversion.md, "Ranking the key trials")."""
    return _moving_score_of(_moving_distances(res, vseq, moving, device))


def _moving_score_of(distances: list) -> float:
    """:func:`_moving_score` of a run's per-frame moving-point distances (:func:`_moving_distances`)."""
    return _tail_mean(np.concatenate(distances), MOVING_SCORE_TAIL)


def _key_candidates(vseq, o: dict, K: int, given: bool, res, moving_part=..., off_scale=()) -> list:
    """The key frames to try after the run from the automatic key frame ``K`` (``res``): when
    that run is complete, :func:`_key_retry_reason` finds it worth retrying (or always, with
    ``always_try_keys``) and the key frame was not chosen by the user, :func:`_candidate_keys`.
    ``moving_part``: the run's (default), or None where its moving part is no subject in static
    surroundings (:data:`MOVING_FRAMES`)."""
    T = vseq.num_frames
    info = res.conversion
    part = info.moving_part if moving_part is ... else moving_part
    if (given or o["key_frame"] not in ("auto", None) or T < 3 or len(info.coverage) < T
            or (_key_retry_reason(info.coverage, K, part) is None and not o.get("always_try_keys"))):
        return []
    return _candidate_keys(T, int(o.get("key_candidates", 0) or 0), K, _key_frame_fit(vseq, off_scale))


def _candidate_keys(T: int, n: int, K: int, ok=lambda u: True) -> list:
    """The ``n`` key frames the trials try besides ``K`` in T frames: spread evenly (frame
    T (i + 1/2) / n), each frame that may not be a key frame (``ok`` false: :func:`_key_frame_fit`)
    moved to the nearest frame that may (the earlier of two as near), K and repeats left out.
    ``ok`` is asked from each spread frame outwards only (its tests cost a pass over a frame)."""

    def nearest(k):
        for d in range(T):
            for u in (k - d, k + d):
                if 0 <= u < T and ok(u):
                    return u
        return None

    keys = [nearest(min(T - 1, int(T * (i + 0.5) / n))) for i in range(max(n, 0))]
    if any(k is None for k in keys):
        return []
    return [k for i, k in enumerate(keys) if k != K and k not in keys[:i]]


def _key_retry_reason(coverage, K: int, moving_part=None) -> str | None:
    """Why a run from key frame ``K`` with these per-frame coverages (fractions of the bbox
    diagonal) and this ``moving_part`` (:func:`_node_spacing`) is worth repeating from other key
    frames, in words; None when it is not. Two GT-free signs: at least KEY_RETRY_POOR_FRAMES
    frames poorly covered (> POOR_COVERAGE: a lost part; one in a run of at most
    KEY_RETRY_SHORT frames), or drift: the 90th percentile of the
    frames' coverage above both DRIFT_FLOOR and
    DRIFT_RATIO x the mean coverage of the frames next to the key frame (within DRIFT_NEIGHBOURS,
    the key itself excluded), where the template is fresh and the coverage is the input's own
    fitting floor. Drift without a lost part is what a run from a badly placed key frame does
    when no frame crosses POOR_COVERAGE (pcow at 1 % error, no tangential relaxation: key 163
    covers every frame within 3.1 %, CD +21 %; key 25 +5 %; docs/conversion.md). A third reason,
    not a sign of a poor fit: a ``moving_part`` in static surroundings, which hide a lost limb
    from both signs (docs/conversion.md, "Ranking the key trials on the moving points")."""
    cov = np.asarray(coverage, float)
    poor = int(np.count_nonzero(cov > POOR_COVERAGE))
    if poor >= (1 if cov.size <= KEY_RETRY_SHORT else KEY_RETRY_POOR_FRAMES):
        return f"{poor} frame{'s' if poor > 1 else ''} poorly covered"
    if cov.size >= 2 * DRIFT_NEIGHBOURS + 1:  # shorter: too short to tell drift from motion
        near = np.r_[cov[max(0, K - DRIFT_NEIGHBOURS):K], cov[K + 1:K + 1 + DRIFT_NEIGHBOURS]]
        p90, floor = float(np.percentile(cov, 90)), float(np.mean(near))
        if p90 > DRIFT_FLOOR and p90 > DRIFT_RATIO * floor:
            return (f"coverage drifted ({100 * p90:.2f}% of the diagonal on the worst tenth of the frames, "
                    f"{100 * floor:.2f}% next to the key frame)")
    if moving_part is not None:
        return (f"its moving part ({moving_part[0]:.3g} across, in the input's units) has static surroundings, which "
                "hide its coverage (the runs are ranked on the moving points)")
    return None


#: a template vertex "moves" when some sampled input frame lies farther than this fraction of
#: the template's diagonal from it (well above a reconstruction's error, ~1 % RMS)
MOVING_GAP = 0.05
#: the moving part's box sets the node spacing only when its diagonal is below this fraction of
#: the template's (a floor or background much larger than the subject)
MOVING_PART_MAX = 0.6
#: input frames sampled to find what moves
MOVING_SAMPLES = 8
#: at most about this many points of the template and of each sampled frame are asked
MOVING_POINTS = 8192
#: fewer moving vertices than this fraction of the template's: nothing moves (noise)
MOVING_MIN = 0.002
#: the key trials are ranked on the moving points (:func:`_moving_points`) only when they show on
#: at least this fraction of the frames (a subject in static surroundings: 87-100 % of the frames
#: on seven floor scenes; floaters on three frames of ten do not count)
MOVING_FRAMES = 0.5
#: the key trials' moving score (:func:`_moving_score`) is the mean of this largest fraction of
#: the moving points' distances to the output, pooled over the frames. Measured on seven floor
#: scenes' stored key runs (CPU; docs/conversion.md): the best run that lost a part on 3 or more
#: frames scores 1.44-1.46x the best that lost one on at most 1 (the mean squared distance over
#: frames, the previous score: 1.11x on one scene, which GPU noise then flipped); 0.3-1 % gave
#: 1.31x or more
MOVING_SCORE_TAIL = 0.005
#: the finer spacing is at least this fraction of the coarse one (a small moving part would
#: otherwise ask for more nodes than the graph may have)
MOVING_SPACING_MIN = 0.25


def _sample_frames(T: int) -> list:
    """The frames that tell what moves: ``MOVING_SAMPLES`` + 1 spread evenly over T frames."""
    return sorted(set(np.linspace(0, T - 1, min(MOVING_SAMPLES + 1, T)).round().astype(int).tolist()))


def _node_spacing(vseq, K: int, TV: np.ndarray, TF: np.ndarray, o: dict, device) -> tuple:
    """The graph's node spacing for template TV (key frame K): (spacing, moving part).

    ``node_spacing`` x the template's bbox diagonal, unless (``adaptive_spacing``) the part of
    the template that moves is much smaller than the whole, as a subject on a static floor or in
    front of a static background is: then ``node_spacing`` x the moving part's diagonal for the
    vertices within its box (grown by the coarse spacing; at least ``MOVING_SPACING_MIN`` x the
    coarse spacing), the coarse spacing elsewhere, so the
    static part neither coarsens the subject's graph nor fills the node budget. A vertex moves
    when one of ``MOVING_SAMPLES`` frames spread over the sequence lies farther than
    ``MOVING_GAP`` x the diagonal from it, or it is a corner of the template face nearest to
    such a frame's vertex that far from the template. Moving part: None, or ``(diagonal [m],
    template vertices in the grown box)``."""
    diag = max(_bbox_diag(TV), 1e-12)
    coarse = float(o["node_spacing"]) * diag
    T = vseq.num_frames
    if not o.get("adaptive_spacing", False) or T < 2:
        return coarse, None
    frames = [t for t in _sample_frames(T) if t != K]
    far = MOVING_GAP * diag
    moving = np.zeros(len(TV), bool)
    # both ways: a template vertex far from a frame, and the template face nearest to a frame
    # vertex far from the template (a foot that slides along the floor stays near the frame's
    # surface; the leg that spreads from it shows the other way); the second in one query. Above
    # MOVING_POINTS vertices, every k-th (a box needs no more; a large input stays quick)
    def stride(n):  # every k-th of n points: about MOVING_POINTS of them
        return _stride(n, MOVING_POINTS)

    ks = stride(len(TV))
    for t in frames:
        moving[::ks] |= nearest_surface(vseq.frames[t], TV[::ks], device=device).dist > far
    pts = np.concatenate([p[::stride(len(p))] for p in (vseq.frames[t][0] for t in frames)])
    back = nearest_surface((TV, TF), pts, device=device)
    hit = (back.dist > far) & (back.face >= 0)
    moving[TF[back.face[hit]].reshape(-1)] = True
    if moving.sum() < max(8, MOVING_MIN * len(TV) / ks):  # (of the vertices asked: every ks-th)
        return coarse, None
    lo, hi = TV[moving].min(axis=0), TV[moving].max(axis=0)
    mdiag = float(np.linalg.norm(hi - lo))
    if mdiag >= MOVING_PART_MAX * diag:
        return coarse, None
    inside = np.all((TV >= lo - coarse) & (TV <= hi + coarse), axis=1)
    fine = max(float(o["node_spacing"]) * mdiag, MOVING_SPACING_MIN * coarse)
    return np.where(inside, fine, coarse), (mdiag, int(inside.sum()))


def _convert_from_key(vseq, strategy: str, o: dict, K: int, template, device, progress, should_stop,
                      where, stop_forward=None) -> FixedTopologySequence:
    """One conversion run: the template is ``template`` (validated (V, F)) or key frame K's
    mesh, tracked from frame K to both ends."""
    T = vseq.num_frames
    if template is None:  # the key frame, without its floaters
        TV, TF = _key_frame_floaters(vseq, K, o, device)[:2]
    else:
        TV, TF = template
    TV = np.ascontiguousarray(TV, np.float32)
    TF = np.ascontiguousarray(TF, np.int32)
    if template is not None:
        _check_reach(TV, TF, *vseq.frames[K], float(o["max_template_distance"]), device, K)
    all_diag = max(max(_bbox_diag(v) for v, _ in vseq.frames), _bbox_diag(TV), 1e-6)
    spacing, moving = _node_spacing(vseq, K, TV, TF, o, device) if strategy == "graph" else (None, None)
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
        info.area_ratio, info.input_motion = info.area_ratio[lo:hi + 1], info.input_motion[lo:hi + 1]
    res = FixedTopologySequence(out[lo:hi + 1], TF, fps=vseq.fps, name=vseq.name, source=vseq.source)
    info.frame_motion = _frame_motion(res.V)
    info.input_motion[0] = 0.0  # (the frame before lo is not in the result)
    res.conversion = info
    return res


# --------------------------------------------------------------------------- CLI

#: the automatic key frame (:func:`_key_frame`): a window's middle frame more than this fraction
#: below the window's median area is not taken (a hole, a coarser remesh), nor is a frame when one
#: of about its area (within this fraction) has KEY_FINER x its vertices. The protocol's inputs
#: (5 sequences at 1 % error, r96; 5 noise-free at r192) keep their key frames.
KEY_AREA_TOLERANCE = 0.02
KEY_FINER = 2.0
POOR_COVERAGE = 0.05  # coverage (fraction of the bbox diagonal) above which a frame counts as poorly fit
#: the coverage's tail (its 99.9th percentile, ``ConversionInfo.coverage_tail``) above which a
#: frame is warned about (a thin part's tip left behind): issue 12's 3 % of the diagonal. At 1 %
#: error it flagged 5 of chicken_crossing's 7 frames that lost a tip by more than 3 % (and 1 that
#: lost < 2 %), 12 of pcow's 16, a fast-spinning figure's one, none on the horses or the figure
#: (docs/conversion.md, "Thin parts")
POOR_TAIL = 0.03
#: the fraction of the converted surface's area turned against the input (``ConversionInfo.
#: flipped``: a fold-over) above which the summary notes the frames: a new user's waving flag
#: folded back on 6 of 24 frames, 11-19 % (its other frames < 1 %); white noise on the input's
#: vertices gave up to 4 %; the protocol's horse_gallop (1 % error) grows from 0 at its key frame
#: to 11 %, and a body of thin spines read 16 % with no fold: a note, not a warning
#: (docs/conversion.md, "Folds")
POOR_FLIPPED = 0.12
#: converted area over the input's (``area_ratio``) above which the summary warns of a crumpled
#: surface: a new user's balloon converted from its inflated frame read 2.0-2.4x on its deflated
#: frames; the issue-12 protocol's sequences peak at 1.03-1.43x (CPU, 1 % error; docs/conversion.md)
POOR_AREA = 1.5
#: a frame whose converted surface moved (``frame_motion``) over JUMP_RATIO x the median of its
#: JUMP_WINDOW neighbours either side, and over JUMP_LEAST of the diagonal, is warned of as a jump
JUMP_RATIO = 3.0
JUMP_WINDOW = 5
JUMP_LEAST = 0.05
#: ... unless the input moved (``input_motion``) at least this fraction of that there
JUMP_INPUT = 0.5
#: the slide (:func:`slide_ratio`): the median over frames of the converted vertices' motion
#: (``frame_motion``) over the input surface's (``input_motion``, at least SLIDE_FLOOR of the
#: diagonal: a still input's noise). A template that follows the surface reads 1-1.5x (issue 12's
#: gallop 1.4, figure 1.2, pcow 1.5; CPU); one that slides along it more: horse_collapse and
#: chicken_crossing 2.05 (their surface velocity errs 2.6x and 3.5x the GT's own motion), a new
#: user's merging balls 4.5x at the frames they swap over. Over SLIDE_WARN the summary warns.
SLIDE_FLOOR = 0.002
SLIDE_WARN = 2.0
#: ... and names the frames whose ratio is over SLIDE_FRAME where the vertices moved over
#: JUMP_LEAST of the diagonal: a local slide (a new user's closing hand, 4.8x where its fingers
#: met the palm; the merging balls 4.5x) under a median that stays low (1.8x, 1.4x). The protocol's
#: sequences that follow their surface peak at gallop 2.2, figure 1.6, pcow 3.9 (CPU)
SLIDE_FRAME = 4.0
#: a dropout (:func:`_dropout_run`): up to DROPOUT_FRAMES input frames that the frames either side
#: both lie over DROPOUT_LEAST of the diagonal from (99th pct.), while each lies DROPOUT_RATIO x
#: nearer to one of them than that (and where its motion stands out DROPOUT_RATIO x)
DROPOUT_LEAST = 0.02
DROPOUT_RATIO = 3.0
DROPOUT_FRAMES = 4
#: ... over DROPOUT_AGREE x farther than the frames either side lie from each other (those are up
#: to DROPOUT_FRAMES + 1 frames apart, so they differ by more motion than one frame's neighbours;
#: ordinary motion gives about 0.5x: the frames either side are farther apart than from it)
DROPOUT_AGREE = 1.5
#: ... and each frame of the run has less surface area than both frames either side and, where
#: all three are closed, lost at least DROPOUT_VOLUME x as large a fraction of their volume as of
#: their area. A new user's missing arm, leg, antenna or half body: the volume fraction lost is
#: 0.4-0.6x the area fraction (a small ball beside a big one, whose area is larger for its
#: volume: 0.25x); an arm slapped flat onto the body for a frame (real motion, which the rest of
#: the rule took for a dropout): 4 % of the area (the remeshed contact), 0 % volume; a sheet's
#: edge folded back, or legs tucked up: no area lost (CPU, docs/conversion.md)
DROPOUT_VOLUME = 0.1
#: ... where "closed" allows open edges up to this fraction of the faces (welded marching-cubes
#: output of an arm held out had one open edge, which switched the volume test off and let the
#: arm folded flat onto the torso pass; a hole where a part was cut off has many more)
DROPOUT_OPEN_EDGES = 0.001
#: a web (:func:`web_fraction`): faces whose longest edge grew more than WEB_STRETCH x since the
#: key frame and whose centroid lies farther than WEB_GAP x the input's bbox diagonal from the
#: input; a frame whose web covers more than POOR_WEB of the converted surface's area counts as
#: poorly fit (docs/conversion.md: how these were set)
WEB_STRETCH = 3.0
WEB_GAP = 0.05
POOR_WEB = 0.01
#: poorly covered frames (each named by the poor-fit warning) from which the graph conversion
#: tries other key frames (``key_candidates``): a lone poor frame is an outlier, two or more a
#: lost part. Was 2 % of the frames (and 2): pcow's first run on the CPU with this round's
#: fine-stage defaults had 4 of 204 poor frames (1.96 %), stayed at +28 % CD where the retry
#: gives +11 % (docs/conversion.md); the 200-frame speed input has 0-1 (coverage max 4.4-4.5 %
#: on the H100)
KEY_RETRY_POOR_FRAMES = 2
#: a sequence of at most this many frames tries other key frames on one poorly covered frame:
#: there the trials cost seconds, one frame is 5 % or more of the run, and the drift sign needs
#: 2 DRIFT_NEIGHBOURS + 1 frames. A new user's 10-frame input (chicken_crossing every 12th
#: frame, re-meshed at 40) kept a run with one frame at 7.0 %; its trials keep 2.8 % (2.6 s)
KEY_RETRY_SHORT = 20
#: the drift trigger of the key trials (:func:`_key_retry_reason`): the 90th percentile of the
#: frames' coverage over DRIFT_RATIO x its mean next to the key frame (DRIFT_NEIGHBOURS frames
#: each side) and over DRIFT_FLOOR (1 % of the diagonal: the reconstruction error level issue
#: 12's protocol adds; a fit within it is not worth five runs). Issue 12's sequences, CPU, no
#: tangential relaxation: the ratio is 2.4 / 3.1 on pcow / horse_collapse (the trials find
#: +21 -> +5 % / +7 -> +2 %), 1.4-1.5 on the others (horse_gallop, chicken_crossing, the figure:
#: their automatic key is already the best or within 1 %); docs/conversion.md
DRIFT_RATIO = 2.0
DRIFT_NEIGHBOURS = 5
DRIFT_FLOOR = 0.01
#: points per side of a frame in the key trials' Chamfer score (larger frames by a fixed stride:
#: the score only ranks runs of the same input, and a 10^6-vertex frame would cost seconds on
#: the CPU for each frame of each run)
SCORE_POINTS = 20000


def _frames_text(frames, limit: int = 12) -> str:
    """``"a, b, c"`` of the first ``limit`` frames, `` ...`` after them when there are more."""
    frames = list(frames)
    return ", ".join(map(str, frames[:limit])) + (" ..." if len(frames) > limit else "")


def conversion_summary(info: ConversionInfo) -> list:
    """Lines that tell the user what a conversion did and where it may have failed: key frame
    (or the segments), time, coverage (worst frame), recovered frames, topology changes, the
    web; warning lines (starting "warning:") for frames whose coverage exceeds POOR_COVERAGE or
    whose web exceeds POOR_WEB."""
    T = info.num_frames
    cov = np.asarray(info.coverage, float)
    segs = info.segments if len(info.segments) > 1 else []
    if segs:
        lines = [f"conversion ({info.strategy}): {len(segs)} templates (segments; the physics rebuilds its BVH "
                 "once per segment): " + ", ".join(f"frames {a}..{b - 1} from frame {k} ({n} vertices)"
                                                    for a, b, k, n in segs)
                 + f"; {sum(info.frame_seconds):.2f} s"]
        if info.seconds_all > sum(info.frame_seconds):
            lines[0] += f" ({info.seconds_all:.2f} s in all, with the runs the segments replaced)"
    else:
        lines = [f"conversion ({info.strategy}): template from frame {info.key_frame}, tracked "
                 + (f"frames {info.key_frame}..{T - 1} then {info.key_frame - 1}..0" if info.key_frame
                    else f"0..{T - 1}") + f"; {sum(info.frame_seconds):.2f} s"]
    if info.key_trials:
        tried = ", ".join(f"{k} ({100 * c:.2f}%, {d:.3g})" for k, c, d, _ in info.key_trials)
        score, why = {"chamfer": ("mean Chamfer distance to the input", "the first run covered frames poorly or "
                                  "drifted"),
                      "moving": (f"mean of the largest {100 * MOVING_SCORE_TAIL:g} % of the input's moving points' "
                                 "distances to the output, in the input's units", "the moving part has static surroundings"),
                      }.get(info.key_score, ("score", "per segment"))
        lines.append(f"key frames tried (mean coverage, {score}), as {why}: {tried}; kept {info.key_frame}; "
                     f"{sum(x[3] for x in info.key_trials):.2f} s in all")
    if info.moving_part is not None:
        lines.append(f"the moving part ({info.moving_part[0]:.4g} across, in the input's units; {info.moving_part[1]} "
                     "template vertices in its box) "
                     "is much smaller than the whole (a static floor or background): its graph nodes are spaced "
                     "from its own size (option adaptive_spacing)")
    tail = np.asarray(info.coverage_tail, float)

    def mean_and_worst(label, x):  # "label: mean m%, worst w% at frame t" of per-frame fractions
        w = int(np.argmax(x))
        return f"{label}: mean {100 * x.mean():.2f}%, worst {100 * x[w]:.2f}% at frame {w}"

    if cov.size:
        lines.append(mean_and_worst("coverage (99.5th pct. input -> converted distance / bbox diagonal)", cov))
    if tail.size == cov.size and tail.size:  # the worst case next to the mean: a thin part's tip
        lines.append(mean_and_worst("farthest input surface (99.9th pct., a thin part's tip shows here)", tail))
    rec = info.recovered_frames or [(t, "") for t in info.reanchored_frames]
    if rec:
        shown = _frames_text(f"{t}" + (f" (from {src})" if src else "") for t, src in rec)
        lines.append(f"recovered/re-anchored {len(rec)} frame(s): {shown}")
    if info.repaired_frames:
        r = info.repaired_frames
        lines.append(f"repair pass (re-tracked from the other side) improved {len(r)} frame(s): "
                     f"{_frames_text(r)}")
    if info.unrecovered_frames:
        u = info.unrecovered_frames
        lines.append(f"restart found no better fit at {len(u)} frame(s): {_frames_text(u)}")
    ig = info.ignored_parts
    if ig:
        fr = sorted(ig)
        lines.append(f"note: left out {sum(p for p, _ in ig.values())} small input part(s) lying far from the "
                     f"converted surface (floaters?) on {len(fr)} frame(s): {_frames_text(fr)}"
                     "; they have no part in the template")
    we = info.welded
    if we:
        lines.append(f"note: welded {sum(x[1] for x in we)} input vertices that repeat another's position (a "
                     f"triangle soup or seams) in {len(we)} frame(s) (first: frame {we[0][0]})")
    rw = info.rewound
    if rw:
        lines.append(f"note: {len(rw)} input frame(s) wound inconsistently ({sum(x[1] for x in rw)} faces ran "
                     f"against their neighbours; first: frame {rw[0][0]}, {rw[0][1]} faces): made consistent piece by "
                     "piece before the fit (the output's faces are the key frame's)")
    to = info.turned_outward
    if to:
        lines.append(f"note: turned the faces of {len(to)} input frame(s) wound inside out (closed, facing inward) "
                     f"outward before the fit: {_frames_text(to)}")
    un = info.dropped_unused
    if un:
        lines.append(f"note: dropped {sum(x[1] for x in un)} input vertices that no face uses and "
                     f"{sum(x[2] for x in un)} faces that repeat a vertex or another face, in {len(un)} frame(s) (first: "
                     f"frame {un[0][0]}); they add no surface")
    rims = [(s, n) for s, n in zip(info.segments, info.open_edges) if n]
    if rims:
        where = ("the template is" if len(info.segments) == 1 else
                 "the templates of frames " + ", ".join(f"{a}..{b - 1}" for (a, b, _k, _n), _ in rims)
                 + (" are" if len(rims) > 1 else " is"))
        lines.append(f"note: {where} open: {', '.join(str(n) for _, n in rims)} edges on the rim of a hole or a "
                     "sheet's border (as its key frame has them); every output frame keeps them, and a sphere can "
                     "pass through a hole")
    ev = info.topology_events
    if ev:
        shown = ", ".join(f"{t} ({what})" for t, what in ev[:8])
        lines.append(f"input topology changes at {len(ev)} frame(s): {shown}" + (" ..." if len(ev) > 8 else "")
                     + (f"; {len(segs)} segments" if segs else "; one template kept through them (1 segment)"))
    fl = np.asarray(info.flipped, float)
    if fl.size == cov.size and fl.size and fl.max() > 0:
        lines.append(mean_and_worst("faces turned against the input (fraction of the converted area; a fold-over)", fl))
        folds = np.flatnonzero(fl > POOR_FLIPPED)
        if folds.size:  # a note, not a warning: thin parts read as much (docs/conversion.md, Folds)
            lines.append(f"note: over {100 * POOR_FLIPPED:.0f}% of the converted surface faces against the input on "
                         f"{folds.size} frame(s) ({_frames_text(folds)}): a fold-over (a sheet's free edge doubled "
                         "back), or many thin parts, which read so too; look at those frames")
    if info.input_dropouts:
        t, gone, agree = max(info.input_dropouts, key=lambda d: d[1])
        a, b = next(r for r in _dropout_runs(d[0] for d in info.input_dropouts) if r[0] <= t <= r[1])
        lines.append(f"note: input frame(s) {_frames_text([d[0] for d in info.input_dropouts])} lack surface that the "
                     f"frames either side both have (frame {t}: {100 * gone:.1f}% of the diagonal away, where frames "
                     f"{a - 1} and {b + 1} agree within {100 * agree:.1f}%): a reconstruction's dropout (or a part that "
                     "really withdraws into the body for a moment)? "
                     + (f"Bridged: the output at {_frames_text(info.bridged_frames)} is blended from the frames either "
                        "side (option bridge_dropouts)" if info.bridged_frames else
                        "The output follows the input there, and a sphere resting on the missing part falls through it"))
        if info.key_frame in {d[0] for d in info.input_dropouts}:  # (a new user's --key-frame inside a run)
            lines.append(f"warning: the key frame {info.key_frame} is one of those frames: the template, made from it, "
                         "lacks the part on every frame; choose another key frame (--key-frame)")
    last = info.first_frame + len(info.coverage) - 1
    for a, b, lost in info.missing_parts:
        if a == info.first_frame:
            which = (f"input frames {a}-{b} (the first {b - a + 1}) lack a part that frame {b + 1} and those after it "
                     f"have (the surface's area {100 * lost:.0f}% smaller before frame {b + 1}): a part that enters, or a "
                     "reconstruction's dropout at the start?")
        elif b == last:
            which = (f"input frames {a}-{b} (the last {b - a + 1}) lack a part that frame {a - 1} and those before it "
                     f"have (the surface's area {100 * lost:.0f}% smaller from frame {a}): a part that leaves, or a "
                     "reconstruction's dropout at the end?")
        else:
            which = (f"input frames {a}-{b} ({b - a + 1} frames) lack a part that frames {a - 1} and {b + 1} have (the "
                     f"surface's area {100 * lost:.0f}% smaller from frame {a}, back at frame {b + 1}): a "
                     f"reconstruction's dropout longer than the {DROPOUT_FRAMES} frames that are bridged (or a part "
                     "withdrawn into the body)?")
        lines.append(f"note: {which} One template keeps the part: the output presses it onto what is left there, a "
                     "sphere resting on it falls through, and the surface jumps where the fit loses or regains it")
        if a <= info.key_frame <= b:
            lines.append(f"warning: the key frame {info.key_frame} is one of frames {a}-{b}: the template, made from "
                         "it, lacks the part on every frame; choose another key frame (--key-frame)")
    m = np.asarray(info.frame_motion, float)
    jumps = _jumps(m) if m.size == cov.size else np.zeros(0, int)
    if jumps.size and len(info.input_motion) == cov.size:  # the input's own jump is motion, not a fault
        jumps = jumps[np.asarray(info.input_motion, float)[jumps] < JUMP_INPUT * m[jumps]]
    if jumps.size:
        w = int(jumps[np.argmax(m[jumps])])
        drop = {d[0] - info.first_frame for d in info.input_dropouts}  # (jumps count from the first frame)
        for a, b, _ in info.missing_parts:  # (the fits either side of such a run may restart a frame late)
            drop |= set(range(a - 1 - info.first_frame, b + 2 - info.first_frame))
        after = [int(t) for t in jumps if t in drop or t - 1 in drop]
        lines.append(f"warning: the converted surface jumps at {jumps.size} frame(s) ({_frames_text(jumps)}): at frame "
                     f"{w} its vertices move {100 * m[w]:.1f}% of the diagonal from frame {w - 1} (99th pct.), over "
                     f"{JUMP_RATIO:g}x the frames around it, where the input moved less than half as far (a restarted "
                     "fit, or the template sliding along the surface"
                     + (f"; at {_frames_text(after)} the input's dropout noted above" if after else "")
                     + "); the physics sees the surface move that far in one frame and throws what touches it")
    slide, per = slide_ratio(info) if m.size == cov.size else (None, None)
    if slide is not None:
        worst = int(np.nanargmax(per))
        lines.append(f"motion: the converted vertices move a median {slide:.2f}x as far a frame as the input's surface "
                     f"(99th pct. each; {per[worst]:.1f}x at frame {worst}); about 1-1.5x where the template follows "
                     "the surface")
        local = np.flatnonzero((np.nan_to_num(per) > SLIDE_FRAME) & (m > JUMP_LEAST))
        if slide > SLIDE_WARN or local.size:
            frames = f"on {local.size} frame(s): {_frames_text(local)}"
            if slide > SLIDE_WARN:
                said = f"its vertices move a median {slide:.2f}x as far as the surface, over {SLIDE_WARN:g}x"
                said += f"; over {SLIDE_FRAME:g}x {frames}" if local.size else ""
            else:
                said = f"its vertices move over {SLIDE_FRAME:g}x as far as the surface {frames}; a median {slide:.2f}x"
            lines.append(f"warning: the converted surface slides along the input's ({said}): the physics feels that as "
                         "surface velocity, and friction drags what rests on it; a tangential motion the input cannot "
                         "show (a spinning round part, a twist) reads so too")
    ar = np.asarray(info.area_ratio, float)
    crumpled = np.flatnonzero(ar > POOR_AREA) if ar.size == cov.size else np.zeros(0, int)
    if crumpled.size:
        w = int(np.argmax(ar))
        lines.append(f"warning: the converted surface has {ar[w]:.2f}x the input's area at frame {w} (over "
                     f"{POOR_AREA:g}x on {crumpled.size} frame(s): {_frames_text(crumpled)}): crumpled, as a template "
                     "from a larger pose is when compressed into a smaller one (the vertex Chamfer distance reads the "
                     "extra vertices as better); a key frame among those frames (--key-frame N) may follow them "
                     "better")
    web = np.asarray(info.web, float)
    if web.size and web.max() > 0:
        w = int(np.argmax(web))
        lines.append(f"web (converted surface stretched across gaps of the input, fraction of its area): worst "
                     f"{100 * web[w]:.2f}% at frame {w}, on {int(np.count_nonzero(web))} frame(s)")
    poor_web = np.flatnonzero(web > POOR_WEB)
    if poor_web.size:
        if info.rejected_cuts:
            # (a cut tried inside one of several segments: those segments stay; it said "so one was
            # kept" beside "3 segments", a new user's)
            kept = "so one was kept" if not segs else f"so the {len(segs)} templates above were kept"
            then = (("; a new template from frame " if len(info.rejected_cuts) == 1 else "; new templates from frames ")
                    + ", ".join(str(a) for a, _ in info.rejected_cuts) + " fitted no better where tried, " + kept)
        elif segs:
            then = ""
        else:
            then = "; new templates (segments) start there when convert writes a .npz or a folder with max_segments > 1"
        lines.append(f"warning: web on {poor_web.size} frame(s) ({_frames_text(poor_web)}): over "
                     f"{100 * POOR_WEB:.0f}% of the converted surface is stretched across a gap outside the input "
                     "(parts the template fused have moved apart, or the fit lost its way there; a sphere would land "
                     "on it)" + then)
    bu = np.asarray(info.buried, float)
    if bu.size and bu.max() > POOR_WEB:
        deep = np.flatnonzero(bu > POOR_WEB)
        lines.append(f"note: on {deep.size} frame(s) ({_frames_text(deep)}) up to {100 * bu.max():.1f}% of the "
                     "converted surface lies inside the input's body, away from its surface: the walls of parts in "
                     "contact or merged there, or the template crumpled inside; no sphere outside meets them, but the "
                     "mesh is not the input's surface there")
    if info.floater_retry:
        fr = info.floater_retry
        lines.append(f"note: the first run's web on {len(fr)} frame(s) ({_frames_text(fr)}) reached out to small "
                     "separate input parts (floaters of the reconstruction?); converted again leaving such parts "
                     f"out (far_part_area={FLOATER_AREA}), "
                     "which fitted better: kept")
    fl = info.floater_webs
    if fl:
        lines.append(f"warning: on {len(fl)} of these frame(s) ({_frames_text(fl)}) the web reaches out to small "
                     "separate parts of the input (floaters of the reconstruction?): " + (
                         f"a run leaving them out (far_part_area={FLOATER_AREA}) fitted no better, so this one was kept"
                         if info.floater_retry_rejected else
                         f"--option far_part_area={FLOATER_AREA} leaves such parts out of the fit")
                     + " (docs/conversion.md, Floaters)")
    tips = np.flatnonzero((tail > POOR_TAIL) & (cov <= POOR_COVERAGE)) if tail.size == cov.size else []
    if len(tips):
        lines.append(f"warning: on {len(tips)} frame(s) ({_frames_text(tips)}) a small part of the input surface (at "
                     f"least 0.1 % of its vertices: a thin part's tip? floaters?) lies farther than "
                     f"{100 * POOR_TAIL:.0f}% of the diagonal from the converted mesh: the template did not "
                     "follow it there (docs/conversion.md, Thin parts)")
    bad = np.flatnonzero(cov > POOR_COVERAGE)
    if bad.size:
        lines.append(f"warning: poor fit on {bad.size} frame(s) ({_frames_text(bad)}): input surface farther than "
                     f"{100 * POOR_COVERAGE:.0f}% of the diagonal from the converted mesh (a lost part?)"
                     + ("; try --strategy graph" if info.strategy != "graph" else "; try another --key-frame")
                     + ("; if the input has floaters (small separate blobs off the surface), --option "
                        "far_part_area=0.05 leaves them out" if not float(info.options.get("far_part_area", 0) or 0)
                        else ""))
    return lines



class _TimedFrames(list):
    """The frames of a sequence being converted, noting when the converter asks for each: after
    the second frame (the first includes compilation) it prints an estimate when the whole
    conversion will take more than ``limit_s``, naming faster options. Values are unchanged."""

    def __init__(self, frames, device, strategy: str, limit_s: float = 60.0):
        super().__init__(frames)
        self.device, self.strategy, self.limit_s = str(device), strategy, limit_s
        self.t1 = None
        self.calls = 0
        self.done = False

    def __getitem__(self, t):
        if isinstance(t, int) and not self.done:
            self.calls += 1  # frames are asked for in conversion order (from the key frame)
            if self.calls == 2:
                self.t1 = time.perf_counter()
            elif self.calls == 3:
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


def _say_frame_numbers(seq) -> None:
    """A note when the input's files are numbered otherwise than 0, 1, ...: the messages (key
    frame, poor frames, segments) count the frames in the input's order from 0."""
    from .sequence_layouts import frame_index_from_name

    src = getattr(seq, "frame_sources", None)
    if not src:
        return
    try:
        numbers = [frame_index_from_name(f) for f in (src[0], src[-1])]
    except MeshDataError:
        return
    if numbers != [0, len(src) - 1]:
        print(f"note: frames are counted 0..{len(src) - 1} in the input's order: frame 0 is {Path(src[0]).name}, "
              f"frame {len(src) - 1} is {Path(src[-1]).name}", file=sys.stderr)


#: the names ``convert`` writes into a folder output (and finds an earlier run's frames by)
_FOLDER_FRAMES = ("frame_*.ply", "frame_*.obj")


def _holds_output(output) -> bool:
    """Whether ``output`` holds a sequence already: the file exists, or the folder has frames."""
    p = Path(output).expanduser()
    return p.is_file() or (p.is_dir() and any(any(p.glob(pattern)) for pattern in _FOLDER_FRAMES))


def _beside_path(output, name: str = "partial") -> Path:
    """Where ``convert`` writes when ``output`` holds a sequence it may not replace (an
    interrupted run's frames; ``name`` "new": a run whose output appeared during the work):
    :func:`~dynmesh_warp.outputs.beside_path`, also skipping names whose point-cache faces file
    (``<stem>.obj``) is taken, so nothing there is replaced."""
    from .animation_formats import written_topology
    from .outputs import beside_path

    def faces_taken(q):
        faces = written_topology(q)
        return faces is not None and faces.exists()

    return beside_path(output, name, faces_taken)


def _same_path(a, b) -> bool:
    return Path(os.path.realpath(Path(a).expanduser())) == Path(os.path.realpath(Path(b).expanduser()))


def _remove_output(path: Path) -> None:
    """Remove a partial output this tool wrote (a file, with a point cache's faces; or a folder's
    listed files and its manifest, the folder too when that leaves it empty)."""
    from .animation_formats import written_topology
    from .outputs import MANIFEST, read_manifest

    if path.is_dir():
        for name in read_manifest(path) | {MANIFEST}:
            (path / name).unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            path.rmdir()
        return
    faces = written_topology(path)
    path.unlink(missing_ok=True)
    if faces is not None:
        faces.unlink(missing_ok=True)


def _open_journal(a, opts: dict, inputs: list) -> ConversionJournal:
    """The journal of this command's conversion (``convert_journal``): the interrupted one's with
    ``--resume``; else a new one, refused where an interrupted conversion's journal is there."""
    from .convert_journal import fit_count, journal_path, read_journal

    folder = journal_path(a.output)
    real = lambda q: None if q is None else os.path.realpath(Path(q).expanduser())  # noqa: E731
    identity = {"input": real(a.input), "template": real(a.template), "topology": real(a.topology),
                "strategy": a.strategy, "options": opts, "fps": a.fps, "frame_order": a.frame_order}
    if a.resume:
        if not os.path.lexists(folder):
            raise ValueError(f"--resume: no interrupted conversion of {a.output} to go on with ({folder} is not there)")
        return ConversionJournal(folder, identity, resume=True)
    if os.path.lexists(folder):
        read_journal(folder)  # a folder of that name that is no journal is named as such
        n = fit_count(folder)
        if n == 0:  # killed before its first fit was written: nothing to go on from
            shutil.rmtree(folder, ignore_errors=True)
            return ConversionJournal(folder, identity)
        raise ValueError(f"output {a.output}: an interrupted conversion of it left {n} frame fits in {folder}; give "
                         "--resume to go on from them, or remove that folder to start over")
    return ConversionJournal(folder, identity)


@contextlib.contextmanager
def _keeping_journal(journal: ConversionJournal):
    """A journal with no frame fitted is removed however the conversion ends (nothing to go on from)."""
    try:
        yield
    finally:
        journal.close()
        if not journal.frames():
            journal.remove()


@interruptible_main
def main(argv=None) -> int:
    from .cli import Parser

    p = Parser(
        prog="python -m dynmesh_warp.convert",
        description="Convert a varying-topology mesh sequence into a fixed-topology one.")
    p.add_argument("input", help="sequence: .npz, a folder of per-frame meshes (.obj, .ply, .off, ...), a DG-Mesh "
                   "scene folder, an animated .glb/.gltf, or a point cache (.pc2, .mdd, .anime; docs/data.md)")
    p.add_argument("output", help="output .npz; a .pc2 or .mdd point cache (its faces written as <stem>.obj), "
                                  ".anime, or an animated .glb (morph targets); or a folder (frame_XXXX.ply/.obj, "
                                  "see --fmt)")
    p.add_argument("--strategy", choices=STRATEGIES, default=DEFAULT_STRATEGY,
                   help=f"conversion strategy (default {DEFAULT_STRATEGY}; docs/conversion.md)")
    p.add_argument("--template", default=None,
                   help="template mesh file (default: the key frame, see --key-frame)")
    p.add_argument("--topology", default=None,
                   help="faces of a vertex-only input (a .pc2/.mdd point cache, .npy, or an npz of vertices): a mesh "
                        "file with as many vertices (default: the mesh of the same name next to it)")
    p.add_argument("--key-frame", default=None,
                   help="frame the template comes from and tracking starts at, forward then backward "
                        "(default 'auto': the frame of largest surface area; frame 0 with --template)")
    p.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (as run, evaluate and render)")
    p.add_argument("--reanchor-interval", type=int, default=None, help="tracking: frames between re-anchors (0: never)")
    p.add_argument("--tracked-weight", type=float, default=None, help="tracking: weight of the tracked positions at a re-anchor")
    p.add_argument("--iterations", type=int, default=None, help="regularized: outer iterations per frame")
    p.add_argument("--smooth-iterations", type=int, default=None, help="regularized: displacement smoothing steps")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="a strategy option (repeatable), e.g. --option refine_rounds=0 --option iterations=2 "
                        "(the graph strategy's fast settings; docs/conversion.md lists the options)")
    p.add_argument("--fmt", default=None, choices=["ply", "obj"], help="per-frame format for a folder output (default ply)")
    p.add_argument("--fps", type=float, default=None, help="override the input frame rate")
    p.add_argument("--frame-order", choices=values(FrameOrder), default=DEFAULT_FRAME_ORDER.value,
                   help="an npz input's frames: text_sorted undoes a text sort (1, 10, 11, ..., 2, ...; "
                        "numbering from 1 for a varying-topology npz); auto: where detected (fixed topology "
                        "only); docs/data.md")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output (in a folder: only files this tool wrote; others are kept)")
    p.add_argument("--resume", action="store_true",
                   help="go on with an interrupted conversion of this output from the frames it had fitted (its "
                        "journal, <output>.convert-journal); give the same input and options")
    a = p.parse_args(argv)
    from .cli import checking_stops, quiet_warp, stop_reason

    quiet_warp(a.device)
    from .animation_formats import VERTEX_ONLY_EXTENSIONS, find_topology, written_topology
    from .io import ANIMATED_FILE_OUTPUTS, MESH_EXTENSIONS, load_sequence, save_sequence
    from .mesh_formats import UNREAD_ANIMATIONS
    from .outputs import OutputKind, check_output

    opts = {}
    if a.key_frame is not None:
        try:
            opts["key_frame"] = a.key_frame if a.key_frame == "auto" else int(a.key_frame)
        except ValueError:
            p.error(f"--key-frame: expected 'auto' or a frame index, got {a.key_frame!r}")
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
    from .config import SceneError, parse_assignment

    given = {}
    for item in a.option:
        try:
            parts, value = parse_assignment(item, "--option", "KEY=VALUE, e.g. --option refine_rounds=0")
        except SceneError as e:
            p.error(str(e))
        key = ".".join(parts).strip()
        if key in given:  # the last one won, unremarked (a new user's)
            p.error(f"--option {key}: given twice ({given[key]} and {item.strip()}); give it once")
        given[key] = item.strip()
        opts[key] = None if value == "" else value
    journal = None
    try:
        # everything is checked before the sequence is loaded: options, input, template, output
        try:
            _resolve_options(a.strategy, opts)
        except (TypeError, ValueError) as e:
            name, _, rest = str(e).partition(" ")
            if name in opts and any(item.partition("=")[0].strip() == name for item in a.option):
                raise ValueError(f"--option {name}: {rest}") from None
            if name in opts:
                raise ValueError(f"--{name.replace('_', '-')}: {rest}") from None
            raise ValueError(f"--strategy {a.strategy}: {e}") from None
        if a.fps is not None and not (FPS_RANGE[0] <= a.fps <= FPS_RANGE[1]):
            raise ValueError(f"--fps must be a frame rate of {FPS_RANGE[0]:g} to {FPS_RANGE[1]:g} frames/s, got {a.fps}")
        from .runtime import resolve_device

        device = resolve_device(a.device, "--device")
        if not Path(a.input).expanduser().exists():
            raise ValueError(f"input {a.input}: file or folder not found")
        if a.template is not None and (why := file_problem(a.template)):
            raise ValueError(f"--template {a.template}: {why} (a mesh file is expected)")
        inputs = [a.input] + ([a.template] if a.template else [])
        if a.topology is not None:
            if Path(a.input).suffix.lower() not in VERTEX_ONLY_EXTENSIONS or not Path(a.input).is_file():
                raise ValueError(f"--topology {a.topology}: only for a vertex-only input (a point cache "
                                 f"{', '.join(sorted(VERTEX_ONLY_EXTENSIONS))}), but the input is {a.input}")
            if why := file_problem(a.topology):
                raise ValueError(f"--topology {a.topology}: {why} (a mesh file is expected)")
            inputs.append(a.topology)
        elif Path(a.input).suffix.lower() in VERTEX_ONLY_EXTENSIONS and Path(a.input).is_file():
            try:  # a vertex-only input's faces are an input too (a cache output writes <stem>.obj)
                inputs.append(find_topology(a.input))
            except MeshDataError:
                pass  # none found: the load reports it
        out_suffix = Path(a.output).suffix.lower()
        journal = _open_journal(a, opts, inputs)
        partial = journal.partial() if journal.resumed else None
        # the partial output the interrupted run wrote in the output's place is replaced by the resumed one
        replace = a.overwrite or (partial is not None and _same_path(partial, a.output))
        if out_suffix == ".npz" or out_suffix in ANIMATED_FILE_OUTPUTS:
            if a.fmt:
                raise ValueError(f"--fmt {a.fmt}: applies to a folder output, not to {a.output}")
            check_output(a.output, kind="file", what="output", inputs=inputs, overwrite=replace,
                         suffixes={out_suffix}, holds=OutputKind.SEQUENCE)
            faces = written_topology(a.output)
            if faces is not None:  # a point cache's faces go next to it
                check_output(faces, kind="file", what=f"output {a.output}: its faces", inputs=inputs,
                             overwrite=replace, suffixes={".obj"}, holds=OutputKind.SEQUENCE)
        else:
            formats = (".npz file, a .pc2/.mdd/.anime or animated .glb file, or a folder (frames written as "
                       "frame_XXXX.ply, or .obj with --fmt obj)")
            if out_suffix == ".gltf":
                raise ValueError(f"output {a.output}: an animated glTF is written as one binary .glb file (morph "
                                 f"targets); give {Path(a.output).with_suffix('.glb').name}")
            if out_suffix in MESH_EXTENSIONS or out_suffix in _FILE_SUFFIXES:
                raise ValueError(f"output {a.output}: a sequence does not fit in one {out_suffix} file; give a "
                                 + formats)
            if out_suffix in UNREAD_ANIMATIONS:
                raise ValueError(f"output {a.output}: {UNREAD_ANIMATIONS[out_suffix].split(' (')[0]} files are not "
                                 "written; give a " + formats + ". A .pc2 or .mdd point cache with its .obj, or "
                                 "the .glb, imports into Blender, Maya, 3ds Max and Houdini")
            if out_suffix and not Path(a.output).is_dir() and re.fullmatch(r"\.[a-z0-9]{1,5}", out_suffix):
                # an unknown file-like name (a typo such as .nzp, or a format not written) became a
                # folder of frames with exit 0 (a new user's): refused; an existing folder is taken
                raise ValueError(f"output {a.output}: {out_suffix} is not a format convert writes; give a "
                                 + formats + " named without an extension (or create the folder first)")
            a.fmt = a.fmt or "ply"
            check_output(a.output, kind="folder", what="output", inputs=inputs, overwrite=replace,
                         writes=_FOLDER_FRAMES, holds=OutputKind.SEQUENCE)
        seq = load_sequence(a.input, fps=a.fps, topology=a.topology, frame_order=a.frame_order)
        if isinstance(seq, FixedTopologySequence):
            print(f"note: {a.input} already has fixed topology ({seq.num_frames} frames); converting it "
                  "anyway (it can be simulated as it is)", file=sys.stderr)
            seq = seq.to_varying()
        _say_frame_numbers(seq)
        seq.frames = _TimedFrames(seq.frames, device, a.strategy)
        # an animation file holds one set of faces: one template; else new templates (segments)
        # where one cannot follow the input (to_piecewise_fixed; max_segments)
        one_file = out_suffix in ANIMATED_FILE_OUTPUTS
        run = to_fixed_topology if one_file else to_piecewise_fixed
        with checking_stops(), _keeping_journal(journal):  # Ctrl-C / SIGTERM: stop between frames, write the frames done
            res = run(seq, strategy=a.strategy, template=a.template, device=device,
                      progress=not a.no_progress, should_stop=stop_reason, journal=journal, **opts)
            # a stop after every frame was converted (during the key-frame trials, the floater
            # retry or the segments) still counts: the output is the run so far, not the one an
            # uninterrupted run would have written
            reason = stop_reason()
            status = {"complete": not reason, "frames": res.num_frames, "input_frames": seq.num_frames,
                      "first_frame": res.conversion.first_frame,
                      "interrupted_by": reason, "strategy": a.strategy,
                      "segments": [list(x) for x in res.conversion.segments]}
            written, kept = a.output, None
            # the interrupted run's partial output in the output's place, unchanged during the work
            ours = partial is not None and _same_path(partial, a.output) and journal.partial() is not None
            if (reason or not a.overwrite) and _holds_output(a.output) and not ours:
                # an interrupted run never replaces what is there (an earlier, maybe complete,
                # output): the frames done go beside it; nor does a run without --overwrite whose
                # output appeared during the work (another run's: the check before the work passed)
                written, kept = _beside_path(a.output, "partial" if reason else "new"), a.output
            save_sequence(res, written, fmt=a.fmt, overwrite=a.overwrite or ours, status=status)
            if reason:
                journal.note_partial(written)
            else:
                if partial is not None and not _same_path(partial, written) and journal.partial() is not None:
                    _remove_output(partial)  # the interrupted run's partial output beside it: superseded
                journal.remove()
    except (MeshDataError, FileNotFoundError, ValueError, TypeError) as e:
        print(f"error: {e}", file=sys.stderr)
        if journal is not None and journal.frames():
            print(f"note: the {journal.frames()} frame fits done are kept in {journal.folder}: mend the cause and give "
                  "the same command with --resume to go on from them", file=sys.stderr)
        return 2
    if reason:
        stored = "status: complete false" if out_suffix == ".npz" or a.fmt else "a point cache or animation holds no status"
        later = ("; every frame was converted, but the later passes (key-frame trials, segments, the "
                 "floater retry) did not finish: an uninterrupted run may differ") if res.num_frames == seq.num_frames else ""
        print(f"interrupted by {reason}: wrote {written} with input frames {res.conversion.first_frame}.."
              f"{res.conversion.first_frame + res.num_frames - 1} of 0..{seq.num_frames - 1} ({stored}){later}"
              + (f"; {kept}, which was there before, is unchanged" if kept else "")
              + (f"; the same command with --resume goes on from the {n} frame fits done ({journal.folder})"
                 if (n := journal.frames()) else ""), file=sys.stderr)
        import signal

        return 128 + int(getattr(signal, reason, signal.SIGINT))
    segs = res.conversion.segments
    if kept:
        print(f"warning: {kept} appeared during the work (another run's?) and is kept unchanged (no --overwrite); "
              f"this run's output is {written}", file=sys.stderr)
    if len(segs) > 1:
        print(f"wrote {written}: {res.num_frames} frames in {len(segs)} segments of fixed topology ("
              + ", ".join(f"{n} vertices" for *_, n in segs) + ")")
    else:
        print(f"wrote {written}: {res.num_frames} frames x {res.num_vertices} vertices, {res.num_faces} faces")
    for line in conversion_summary(res.conversion):
        print(line)
    from .io import DEFAULT_FPS

    if res.fps != DEFAULT_FPS and (a.fmt or out_suffix in (".anime", ".pc2")):
        # a new user's --fps 30 to a folder read back at 24 fps without a word
        print(f"note: {written} does not store the frame rate ({res.fps:g} fps): it reads back at {DEFAULT_FPS:g} unless "
              "given (--fps, surface.fps); a .npz, .mdd or .glb output keeps it", file=sys.stderr)
    if one_file and (_stretched_far(res.conversion) > POOR_WEB).any():
        print(f"note: a {out_suffix} file holds one template; a .npz or folder output would start new ones "
              "where this one is stretched (segments)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
