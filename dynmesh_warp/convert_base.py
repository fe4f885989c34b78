"""What every stage of the topology conversion (``convert``) shares: the batched closest point
on a mesh (:func:`nearest_surface`), a frame's arrays on the device, :class:`ConversionInfo` (what a
conversion reports), and small mesh measures (bounding-box diagonal, open edges, longest edges).
The public names here are re-exported by :mod:`dynmesh_warp.convert`, their canonical import path."""

from __future__ import annotations

import contextlib
import contextvars
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .geometry import bbox_diagonal
from .kernels.geometry import project_points_to_mesh
from .sequence import MeshDataError, validate_mesh


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


_bbox_diag = bbox_diagonal  # (the conversion's name for it)


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


# --------------------------------------------------------------------------- ConversionInfo


class ConversionStopped(RuntimeError):
    """``should_stop`` was true before the conversion had fitted a frame (during the input's
    checks or the converter's set-up, which take minutes on large frames: a new user's SIGINT was
    acted on 159 s later, past a scheduler's grace period): there is nothing to return.
    ``reason``: what ``should_stop`` returned (the CLI's signal name)."""

    def __init__(self, reason):
        self.reason = reason
        super().__init__(f"conversion stopped ({reason}) before any frame was fitted")


#: ``[fitted]`` of the conversion under way: set by the public calls (:func:`_fitting`), marked by
#: the frame loop at its first frame (fitted or taken from a journal); None outside a conversion
_FITTED: contextvars.ContextVar = contextvars.ContextVar("conversion_fitted", default=None)


@contextlib.contextmanager
def _fitting():
    """A conversion's span for :func:`_stop_before_fitting` (a nested call joins the outer one)."""
    if _FITTED.get() is not None:
        yield
        return
    token = _FITTED.set([False])
    try:
        yield
    finally:
        _FITTED.reset(token)


def _mark_fitted() -> None:
    flag = _FITTED.get()
    if flag is not None:
        flag[0] = True


#: whether a stop before the first frame ends the conversion at once (:func:`stopping_early`: the
#: CLIs); the Python API's default keeps its promise of at least the first frame
_STOP_EARLY: contextvars.ContextVar[bool] = contextvars.ContextVar("conversion_stop_early", default=False)


@contextlib.contextmanager
def stopping_early():
    """Conversions inside check ``should_stop`` during the input's checks and the converter's
    set-up too, and raise :class:`ConversionStopped` there (``convert`` and ``evaluate`` run so)."""
    token = _STOP_EARLY.set(True)
    try:
        yield
    finally:
        _STOP_EARLY.reset(token)


def _stop_before_fitting(should_stop) -> None:
    """Inside :func:`stopping_early`, raise :class:`ConversionStopped` when ``should_stop`` is true
    and the conversion under way has fitted no frame yet (after that, the frame loop stops between
    frames and keeps them)."""
    flag = _FITTED.get()
    if should_stop is None or not _STOP_EARLY.get() or (flag is not None and flag[0]):
        return
    reason = should_stop()
    if reason:
        raise ConversionStopped(reason)


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
    removed_parts: ``(frame, parts, vertices)`` for input frames whose parts under the option
    ``min_part_area`` of their area were removed before the conversion (debris).
    tiny_parts: per segment (in the order of ``segments``), how many of its template's parts
    each have under ``convert_report.TINY_PART_AREA`` of its area (at its key frame).
    ignored_parts: ``{frame: (parts, vertices)}``: small input parts left out of that frame's
    fit and coverage because they lie wholly far from the converted surface (options
    ``far_part_area``, ``far_part_gap``): floaters of a reconstruction, for which the template
    has no part (pulled, they would grow a spike from it).
    flipped: per frame, the fraction of the converted surface's area whose faces point against
    the input surface nearest to them (a fold-over: the surface doubled back on itself, as a new
    user's waving flag did on 6 of 24 frames, 13 % of its area, silently).
    off_input: per frame, the fraction of the converted surface's area whose faces have no point of
    the input within ``WEB_GAP`` of the diagonal of their centroid (the web and the buried faces
    among them, and any surface the fit put off the input unstretched: a new user's propeller
    turning 90 degrees a frame was crumpled inside its body on 9 of 16 frames, up to 7.5 %, with
    web and buried under 0.5 %); a part the input lacks on a frame (a dropout) is off it too.
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
    removed_parts: list = field(default_factory=list)
    tiny_parts: list = field(default_factory=list)
    web: list = field(default_factory=list)
    buried: list = field(default_factory=list)
    flipped: list = field(default_factory=list)
    off_input: list = field(default_factory=list)
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


def _longest_edges(V, F) -> np.ndarray:
    """(M,) the longest edge of each triangle of (V, F) [units of V]."""
    tri = np.asarray(V, np.float64)[np.asarray(F).reshape(-1, 3)]
    return np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)


def _edge_keys(F: np.ndarray) -> np.ndarray:
    """The edges (0,1), (1,2), (2,0) of every face of ``F`` (M, 3) int64, each as one sorted
    int64 key min * n + max (n: the vertex count the faces imply): an edge shared by k faces
    appears k times in a row."""
    n = int(F.max()) + 1
    a, b = F.T.ravel(), F[:, [1, 2, 0]].T.ravel()
    return np.sort(np.minimum(a, b) * n + np.maximum(a, b))


def _open_edges(F: np.ndarray) -> int:
    """How many edges of the faces ``F`` belong to one face only (a hole's or a sheet's rim)."""
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if not len(F):
        return 0
    key = _edge_keys(F)
    first = np.r_[True, key[1:] != key[:-1]]
    counts = np.diff(np.r_[np.flatnonzero(first), key.size])
    return int(np.count_nonzero(counts == 1))


def _stride(n: int, most: int) -> int:
    """The k for which every k-th of n points is at most ``most`` of them (at least 1)."""
    return max(-(-n // most), 1)
