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

This module is the one import path of the names above; the work is done by its internal modules
(docs/architecture.md, layer 5): ``convert_base`` (closest points, :class:`ConversionInfo`),
``convert_report`` (the thresholds, :func:`conversion_summary`), ``convert_input`` (the input's
analyses), ``convert_segments`` (the piecewise segments), ``convert_fit`` (the converter and its
frame loop) and ``convert_cli`` (the command line's plumbing).
"""

from __future__ import annotations

import contextvars
import re
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

from .choices import DEFAULT_STRATEGY, STRATEGIES
from .cli import interruptible_main, set_stop_hint
from .conversion_options import options_for
from .convert_base import (ConversionInfo, ConversionStopped, NearestSurfaceResult, _bbox_diag, _fitting, _longest_edges,
                           _open_edges, _stop_before_fitting, nearest_surface, stopping_early,
                           vertex_adjacency)
from .convert_cli import (_FILE_SUFFIXES, _FOLDER_FRAMES, FrameEstimate, _beside_path, _duration, _holds_output,
                          _keeping_journal, _open_journal, _parser, _remove_output, _same_path, _say_frame_numbers,
                          input_frame_numbers)
from .convert_fit import FRAME_TIMER, _convert_from_key, _journaling, run_labelled
from .convert_input import (MOVING_FRAMES, _CACHE, _bridge_dropouts, _chamfer_to_input, _check_repeats, _check_scales,
                            _drop_small_parts, _drop_unused, _floater_webs, _input_dropouts, _key_candidates, _key_frame,
                            _key_retry_reason, _missing_parts, _moving_points, _moving_score, _input_checked, _tiny_parts,
                            _topology_events)
from .convert_journal import ConversionJournal
from .convert_report import (CUT_WEB, DROPOUT_FRAMES, FLOATER_AREA, POOR_WEB, WEB_GAP, WEB_STRETCH, _badness, _cut_badness,
                             _stretched_far, conversion_summary, slide_ratio)
from .convert_segments import _join_segments, _slice_result, _split_segments
from .geometry import face_areas, has_area, winding_numbers
from .kernels import convert as kc
from .kernels import register as kr
from .mesh_formats import file_problem
from .metrics import _offset_centre
from .sequence import FPS_RANGE, FixedTopologySequence, MeshDataError, VaryingTopologySequence, carried, validate_mesh

#: True while the ``convert`` CLI runs a conversion: its stages (the key trials) are said on stderr
#: without the progress bar too (``progress`` alone is the Python API's switch)
_STAGE_NOTES: contextvars.ContextVar[bool] = contextvars.ContextVar("convert_stage_notes", default=False)

__all__ = [
    "STRATEGIES",
    "NearestSurfaceResult",
    "ConversionStopped",
    "stopping_early",
    "ConversionInfo",
    "nearest_surface",
    "vertex_adjacency",
    "to_fixed_topology",
    "to_piecewise_fixed",
    "web_fraction",
    "surface_deviation",
    "conversion_summary",
    "slide_ratio",
    "main",
]


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
    moved, tpl, centre = _moved_near_origin(seq, template)
    with _journaling(journal), _fitting():
        res = _to_fixed(moved, strategy, tpl, device, progress, should_stop, None, **options)
    return _with_colors(_moved_back(res, centre), seq, device)


#: an input farther from the origin than this many times its size is converted near the origin
#: (:func:`_moved_near_origin`): a capture studio's ball 2,900 sizes away slid 2.3 % of the diagonal
#: (0.4 % at the origin), 870 away 0.9 %, 290 away 0.5 %. Nearer, float32 rounds to under 1e-5 of the
#: size, and moving the input changes only rounding, which a chaotic fit can still turn into another
#: result: chickenCrossing (5 sizes away) moved lost its worst frame by 7.6 % instead of 6.3 %
FAR_FROM_ORIGIN = 100.0


def _moved_near_origin(seq, template):
    """``(seq, template, centre)``: where the input's frames (and a given ``(V, F)`` template) lie
    farther from the origin than FAR_FROM_ORIGIN x their size (``metrics._offset_centre``), the frames and
    template moved by -centre (in float64, then float32) and that centre; else as given and None.
    The fit computes in float32, and far from the origin its rounding is a large part of the motion:
    a new user's ball of 100 mm, 10^6 mm away, had its vertices slide 2.3 % of the diagonal by the
    last frame (0.4 % at the origin), unsaid. The output is moved back (:func:`_moved_back`), so it
    keeps the input's coordinates. Only the frames' bounds are read unless the input is moved."""
    if template is not None and not isinstance(template, (tuple, list)):
        return seq, template, None  # (a template file: read inside, as given)
    if not isinstance(seq, (FixedTopologySequence, VaryingTopologySequence, list, tuple)) or (
            isinstance(seq, (list, tuple)) and not seq):
        return seq, template, None  # (what _as_varying refuses, refused there)
    try:
        # (the frames as given: a list of (V, F) is made a sequence, and checked, inside; twice was once too many)
        verts = ([np.asarray(seq.V).reshape(-1, 3)] if isinstance(seq, FixedTopologySequence)
                 else [V for V, _ in (seq.frames if isinstance(seq, VaryingTopologySequence) else seq)])
        verts += [] if template is None else [template[0]]
        bounds = []
        for V in verts:
            a = np.asarray(V)
            if a.ndim != 2 or a.shape[1] != 3 or not a.size or a.dtype.kind not in "fiu":
                return seq, template, None  # (the conversion's own checks name what is wrong)
            bounds += [a.min(axis=0), a.max(axis=0)]
    except (TypeError, ValueError):
        return seq, template, None
    bounds = np.asarray(bounds, np.float64)
    if not np.isfinite(bounds).all():
        return seq, template, None
    centre = _offset_centre(bounds, factor=FAR_FROM_ORIGIN)
    if centre is None:
        return seq, template, None
    vseq = _as_varying(seq)

    def moved_by(V):
        return (np.asarray(V, np.float64) - centre).astype(np.float32)

    moved = VaryingTopologySequence([(moved_by(V), F) for V, F in vseq.frames], **carried(vseq),
                                    frame_sources=vseq.frame_sources, colors=vseq.colors)
    return moved, None if template is None else (moved_by(template[0]), template[1]), centre


def _moved_back(res, centre):
    """``res`` with its vertices moved by +centre (float64, then float32): the input's coordinates."""
    if centre is None:
        return res
    if isinstance(res, FixedTopologySequence):
        res.V = (np.asarray(res.V, np.float64) + centre).astype(np.float32)
    else:
        res.frames = [((np.asarray(V, np.float64) + centre).astype(np.float32), F) for V, F in res.frames]
    return res


def _with_colors(res, seq, device):
    """``res`` with the input's vertex colours (``seq.colors``, of frame 0's vertices) carried to its
    frame 0: each output vertex takes the colour at its closest point on the input's frame 0
    (barycentric over that face's corners). Unchanged when the input has none."""
    C = getattr(seq, "colors", None)
    if C is None:
        return res
    V0, F0 = seq.frame(0)
    near = nearest_surface((V0, F0), res.frame(0)[0], device=device, source=seq.source or seq.name)
    res.colors = np.einsum("nk,nkc->nc", near.bary, C[np.asarray(F0)[near.face]]).astype(np.float32)
    return res


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
    vseq, unused, welded, turned, rewound = _drop_unused(vseq, should_stop)
    vseq, removed_parts = _drop_small_parts(vseq, float(o["min_part_area"]))
    for t, (v, f) in enumerate(vseq.frames):
        if not has_area(v, f):  # a new user's points on a line: converted with "coverage 1400 %", exit 0
            src = vseq.frame_sources[t] if vseq.frame_sources else where
            raise MeshDataError(f"{src}, frame {t}: every face has zero area (its corners on one line or point): "
                                "no surface to convert")
    T = vseq.num_frames
    device = wp.get_device(device)
    off_scale = _check_scales(vseq, float(o["scale_tolerance"]))
    _check_repeats(vseq)
    _stop_before_fitting(should_stop)
    K = _key_frame(vseq, o["key_frame"], template is not None, off_scale)
    _stop_before_fitting(should_stop)
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
            if progress or _STAGE_NOTES.get():  # the run goes on: say why, and for how long about
                why = _key_retry_reason(res.conversion.coverage, K, part) or "always_try_keys"
                took = float(np.sum(res.conversion.frame_seconds))
                print(f"conversion: the run from key frame {K}: {why}; trying key frames "
                      f"{', '.join(map(str, trials))} (key_candidates): about {_duration(took * len(trials))} more, "
                      f"the first run took {_duration(took)}", file=sys.stderr, flush=True)
            key_score = "chamfer" if moving is None else "moving"

            def trial(k, r):  # (key frame, mean coverage, score, seconds)
                score = _chamfer_to_input(r, vseq, device) if moving is None else _moving_score(r, vseq, moving, device)
                return (k, float(np.mean(r.conversion.coverage)), score, float(np.sum(r.conversion.frame_seconds)))

            tried = [trial(K, res)]
            best = tried[0][2]
            for k in trials:
                if should_stop is not None and should_stop():
                    break
                with run_labelled(f"trying key frame {k}"):
                    r = _convert_from_key(vseq, strategy, o, k, None, device, progress, should_stop, where)
                if len(r.conversion.coverage) < T:  # stopped during this run: keep the finished ones
                    break
                tried.append(trial(k, r))
                if tried[-1][2] < best:
                    res, best = r, tried[-1][2]
            res.conversion.key_trials, res.conversion.key_score = tried, key_score
        info = res.conversion
        info.dropped_unused, info.welded, info.turned_outward, info.rewound = unused, welded, turned, rewound
        info.removed_parts = removed_parts
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
    info.tiny_parts = [_tiny_parts(res.V[info.key_frame - info.first_frame], res.F)]
    fl = info.floater_webs
    if fl and bool(o["floater_retry"]) and not (should_stop is not None and should_stop()):
        # the web reaches out to small separate input parts: floaters, by that evidence (a real thin
        # part's fragments meet unstretched faces); converted again without them, kept if less poor
        if progress:
            print(f"conversion: the web on frame(s) {', '.join(map(str, fl[:8]))} reaches out to small separate "
                  f"input parts (floaters?); converting again without them (far_part_area={FLOATER_AREA})",
                  file=sys.stderr, flush=True)
        with _input_checked():
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
    coverage exceeds POOR_COVERAGE (a lost part) or its web fraction exceeds CUT_WEB (the
    template fused parts the input has pulled apart, :func:`web_fraction`; twice the POOR_WEB that
    the summary warns of, so that a borderline web does not flip the segments). At the first poor
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
    moved, tpl, centre = _moved_near_origin(seq, template)
    with _journaling(journal), _fitting():
        res = _to_piecewise(moved, strategy, tpl, device, progress, should_stop, options)
    res = _with_colors(_moved_back(res, centre), seq, device)
    res.conversion.seconds_all = time.perf_counter() - start
    return res


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
            sub = VaryingTopologySequence(list(vseq.frames[lo:hi]), **carried(vseq),
                                          frame_sources=vseq.frame_sources[lo:hi] if vseq.frame_sources else None)
            what = f"frames {lo}..{hi - 1} with a template of their own"
            if not progress and _STAGE_NOTES.get():  # (the progress bar says it in its label)
                print(f"conversion: {what} (a segment tried where one template could not follow)", file=sys.stderr,
                      flush=True)
            with run_labelled(what), _input_checked():  # (its checks would number the input's frames from lo)
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
        return bool((web[t] > CUT_WEB and web[t - 1] > CUT_WEB)
                    or (t - row >= 0 and all(far[t - j] > CUT_WEB for j in range(row))))

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
        if new is not None and _cut_badness(new.conversion)[:b + 1 - a].max() < _cut_badness(first.conversion)[a:].max():
            keep = _slice_result(first, 0, a, 0)
            left = _split_segments(0, keep, events, limit - 1, convert)
            segs = left + _split_segments(a, new, events, limit - len(left), convert)
            return _join_segments(vseq, sorted(segs, key=lambda x: x[0]), first.conversion, events)
        # the new template is not better there: one template for every frame, as without the stop
        with run_labelled("every frame with one template, as the segment was no better"), _input_checked():
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


# --------------------------------------------------------------------------- CLI


@interruptible_main
def main(argv=None) -> int:
    p = _parser()
    a = p.parse_args(argv)
    from .cli import checking_stops, quiet_warp, stop_reason

    quiet_warp(a.device)
    from .animation_formats import VERTEX_ONLY_EXTENSIONS, find_topology, written_topology
    from .io import ANIMATED_FILE_OUTPUTS, MESH_EXTENSIONS, load_sequence, save_sequence
    from .mesh_formats import UNREAD_ANIMATIONS
    from .outputs import OutputKind, check_output
    from .sequence_layouts import npz_holds_faces

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
    if a.as_is:  # nothing is fitted: the fit's settings would be ignored, unsaid
        fit = [f"--{k}" for k, v in (("template", a.template), ("key-frame", a.key_frame), ("resume", a.resume))
               if v not in (None, False)] + (["--option / a strategy option"] if opts else [])
        if fit:
            p.error(f"--as-is writes the input as it is; {', '.join(fit)} set(s) a fit: leave one out")
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
        elif (Path(a.input).suffix.lower() in VERTEX_ONLY_EXTENSIONS and Path(a.input).is_file()
              and not npz_holds_faces(a.input)):
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
        numbers = input_frame_numbers(a.input, seq.num_frames)  # a folder input's file numbers: the output's files'
        if a.as_is:  # a format conversion: the frames as they are (a new user's sheet, re-fitted, folded over)
            if not isinstance(seq, FixedTopologySequence):
                raise ValueError(f"--as-is: {a.input} has varying topology (its frames' faces differ): a template "
                                 "has to be fitted; leave --as-is out")
            save_sequence(seq, a.output, fmt=a.fmt, overwrite=replace,
                          status=None if numbers is None else {"frame_numbers": numbers})
            journal.remove()
            print(f"wrote {a.output}: {seq.num_frames} frames x {seq.num_vertices} vertices, {seq.num_faces} faces, "
                  "as they are (--as-is: no template fitted)")
            return 0
        if isinstance(seq, FixedTopologySequence):
            print(f"note: {a.input} already has fixed topology ({seq.num_frames} frames); converting it "
                  "anyway (it can be simulated as it is; --as-is writes it as it is, a format conversion)",
                  file=sys.stderr)
            seq = seq.to_varying()
        _say_frame_numbers(seq)
        # an animation file holds one set of faces: one template; else new templates (segments)
        # where one cannot follow the input (to_piecewise_fixed; max_segments)
        one_file = out_suffix in ANIMATED_FILE_OUTPUTS
        run = to_fixed_topology if one_file else to_piecewise_fixed
        notes = _STAGE_NOTES.set(True)  # the key trials are said with --no-progress too (a new user's
        # octopus ran 57 s, then 445 s in all, unsaid); the progress bar is what --no-progress leaves out
        estimate = FrameEstimate(device, a.strategy)
        timer = FRAME_TIMER.set(estimate)
        set_stop_hint(estimate.stop_hint)
        # Ctrl-C / SIGTERM: stop between frames, write the frames done; before the first, at once
        with checking_stops(), stopping_early(), _keeping_journal(journal):
            try:
                res = run(seq, strategy=a.strategy, template=a.template, device=device,
                          progress=not a.no_progress, should_stop=stop_reason, journal=journal, **opts)
            finally:
                _STAGE_NOTES.reset(notes)
                FRAME_TIMER.reset(timer)
                set_stop_hint(None)
            # a stop after every frame was converted (during the key-frame trials, the floater
            # retry or the segments) still counts: the output is the run so far, not the one an
            # uninterrupted run would have written
            reason = stop_reason()
            first = res.conversion.first_frame
            status = {"complete": not reason, "frames": res.num_frames, "input_frames": seq.num_frames,
                      "first_frame": first,
                      "interrupted_by": reason, "strategy": a.strategy,
                      "segments": [list(x) for x in res.conversion.segments]}
            if numbers is not None:
                status["frame_numbers"] = numbers[first:first + res.num_frames]
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
    except ConversionStopped as e:  # a signal during the input's checks or the set-up: nothing fitted to write
        import signal

        print(f"interrupted by {e.reason} before any frame was fitted: nothing written"
              + (f"; the same command with --resume goes on from the {n} frame fits done ({journal.folder})"
                 if journal is not None and (n := journal.frames()) else ""), file=sys.stderr)
        return 128 + int(getattr(signal, str(e.reason), signal.SIGINT))
    except (MeshDataError, FileNotFoundError, ValueError, TypeError, OSError) as e:
        from .outputs import WRITE_ERRNOS, write_error_text

        full = isinstance(e, OSError) and e.errno in WRITE_ERRNOS  # a full disk, a file-size limit, ...
        if isinstance(e, OSError) and not isinstance(e, (FileNotFoundError, ValueError)) and not full:
            raise  # another OSError (OutputExistsError is a ValueError too: said as before)
        print(write_error_text(e) if full else f"error: {e}", file=sys.stderr)
        if journal is not None and journal.frames():
            print(f"note: the {journal.frames()} frame fits done are kept in {journal.folder}: mend the cause and give "
                  "the same command with --resume to go on from them", file=sys.stderr)
        return 1 if full else 2
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

    if res.fps != DEFAULT_FPS and out_suffix in (".anime", ".pc2"):
        # a new user's --fps 30 to a folder read back at 24 fps without a word (a folder's manifest
        # keeps it since: the note said it was lost, a later user's)
        print(f"note: {written} does not store the frame rate ({res.fps:g} fps): it reads back at {DEFAULT_FPS:g} unless "
              "given (--fps, surface.fps); a .npz, .mdd or .glb output keeps it", file=sys.stderr)
    if one_file and (_stretched_far(res.conversion) > POOR_WEB).any():
        print(f"note: a {out_suffix} file holds one template; a .npz or folder output would start new ones "
              "where this one is stretched (segments)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
