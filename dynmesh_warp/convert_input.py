"""Analyses of the conversion's input (``convert``): its frames' scale and repeats, the
automatic key frame, separate parts and floaters, topology events, dropouts and missing parts,
the moving points and the key trials' candidates and scores; cleaning a frame of unused vertices."""

from __future__ import annotations

import contextlib
import warnings

import numpy as np

from .convert_base import (_bbox_diag, _edge_keys, _longest_edges, _open_edges, _stop_before_fitting, _stride, _wp_mesh,
                           nearest_surface)
from .convert_report import (DROPOUT_AGREE, DROPOUT_FRAMES, DROPOUT_LEAST, DROPOUT_OPEN_EDGES, DROPOUT_RATIO, DROPOUT_VOLUME,
                             FLOATER_AREA, JUMP_WINDOW, MOVING_SCORE_TAIL, POOR_COVERAGE, POOR_WEB, TINY_PART_AREA,
                             WEB_STRETCH, _dropout_runs, _stretched_far)
from .geometry import (distinct_faces, face_areas, mesh_orientation, orient_faces, signed_volume, surface_area,
                       weld_vertices, winding_inconsistent)
from .metrics import chamfer_distance
from .sequence import FixedTopologySequence, MeshDataError, VaryingTopologySequence, carried


def _keep_faces(v: np.ndarray, f: np.ndarray, keep: np.ndarray) -> tuple:
    """(vertices, faces) of the faces ``keep`` (a mask) and only the vertices they use, the faces
    renumbered (int32) in the kept vertices' order."""
    used = np.zeros(len(v), bool)
    used[f[keep].ravel()] = True
    remap = np.cumsum(used) - 1
    return v[used], remap[f[keep]].astype(np.int32)


def _tiny_parts(v: np.ndarray, f: np.ndarray) -> int:
    """How many parts of (v, f) (a template at its key frame) have under ``TINY_PART_AREA`` of its
    area (``ConversionInfo.tiny_parts``)."""
    return int(_small_parts(v, np.asarray(f), TINY_PART_AREA)[3].size)


def _drop_small_parts(vseq: VaryingTopologySequence, frac: float):
    """(vseq without the parts of each frame under ``frac`` of its surface area (never a frame's
    largest), [(frame, parts, vertices removed)]): the option ``min_part_area``. Frames without
    such parts are kept as they are; ``frac`` 0: the input as it is."""
    if frac <= 0:
        return vseq, []
    frames, removed = [], []
    for t, (v, f) in enumerate(vseq.frames):
        _k, _vp, lab, small = _small_parts(v, np.asarray(f), frac)
        if small.size:
            v2, f2 = _keep_faces(v, np.asarray(f), ~np.isin(lab, small))
            removed.append((t, int(small.size), len(v) - len(v2)))
            v, f = v2, f2
        frames.append((v, f))
    if not removed:
        return vseq, []
    return VaryingTopologySequence(frames, **carried(vseq), frame_sources=vseq.frame_sources), removed


def _drop_unused(vseq: VaryingTopologySequence, should_stop=None):
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
    conversion ~0.5 s); a sheet is turned up along the input's up axis (``io.sequence_up_axis``).
    Raises MeshDataError for a frame left without faces."""
    from .io import sequence_up_axis  # noqa: PLC0415 (reads the source's kind only where asked)

    frames, dropped, welded, turned, rewound = [], [], [], [], []
    T = vseq.num_frames
    # a sheet is turned up against gravity along the input's own up axis (a glTF's +Y), not +Z
    up = (0.0, 1.0, 0.0) if sequence_up_axis(vseq) == "y" else (0.0, 0.0, 1.0)
    rewind = any(winding_inconsistent(vseq.frames[t][1]) for t in sorted({0, T // 2, T - 1}) if t < T)
    for t, (v, f) in enumerate(vseq.frames):
        _stop_before_fitting(should_stop)  # seconds a frame on large input (a new user's 400k vertices)
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
            f2, report = orient_faces(v, f, up)
            if report["rewound"]:
                rewound.append((t, int(report["rewound"])))
                f = np.ascontiguousarray(f2, dtype=np.asarray(f).dtype)
        if _inside_out(v, f):
            f = np.ascontiguousarray(f[:, ::-1])
            turned.append(t)
        frames.append((v, f))
    if not dropped and not welded and not turned and not rewound:
        return vseq, dropped, welded, turned, rewound
    return (VaryingTopologySequence(frames, **carried(vseq), frame_sources=vseq.frame_sources),
            dropped, welded, turned, rewound)


def _inside_out(v: np.ndarray, f: np.ndarray) -> bool:
    """The frame is closed, consistently wound and faces inward (``mesh_orientation`` "inward").
    Its edge tables cost ~0.1 s a 10k-vertex frame, 20 s for 200 frames (the conversion's whole
    GPU budget is 10 s): asked only when the frame's signed volume, the same one that rule ends
    with (one pass over the faces), is negative."""
    return signed_volume(v, f) < 0 and mesh_orientation(v, f) == "inward"


#: the input checks' warnings (regular expressions for ``warnings.filterwarnings``): the scale
#: check's and the repeated frames'
SCALE_WARNING = r".*: frames of very different scale"
REPEAT_WARNING = r".*: frame\(s\) .* repeat the frame before them exactly"


@contextlib.contextmanager
def _input_checked():
    """A run over frames the first run's input checks have seen already (a segment's trial, the
    whole sequence again, the floater retry): no second warning. A trial's would number the input's
    frames from its own first frame (a new user's "frame(s) 3 repeat" for the input's frame 12)."""
    with warnings.catch_warnings():
        for message in (SCALE_WARNING, REPEAT_WARNING):
            warnings.filterwarnings("ignore", message=message)
        yield


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
    starts where the parts are most separate: among the frames with as many parts as any
    (:func:`_most_separate`, parts of at least ``FLOATER_AREA`` of the area), the largest. Where
    most frames are closed, a frame with a hole is not taken; nor a frame more than
    ``KEY_AREA_TOLERANCE`` below its window's median area (a coarser remesh); and a frame of about
    the same area with ``KEY_FINER`` x the vertices or more is preferred. Never one of ``off_scale`` (:func:`_check_scales`)."""
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
        t = apart = _most_separate(seq, order, ok, t)
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
        t = int(fine) if nv[fine] >= KEY_FINER * nv[t] and ok(fine) else t
        # the window's or the finer frame only where its parts are as far apart
        return t if t == apart or _separation(seq, t) >= _separation(seq, apart) else apart
    if isinstance(key, bool) or not isinstance(key, (int, np.integer)) or not -T <= int(key) < T:
        raise ValueError(f"key_frame must be 'auto' or a frame index in [{-T}, {T - 1}] "
                         f"(the sequence has {T} frames), got {key!r}")
    return int(key) % T


def _separation(seq: VaryingTopologySequence, u: int) -> int:
    """How far apart frame u's parts are, for the key frame's choice: its parts of at least
    ``FLOATER_AREA`` of its area each (parts touching fuse into one; a thin part the reconstruction
    broke, a floater, an eye, is smaller and not counted). The genus (a loop closed by two limbs of
    one part touching) is not asked: a marching-cubes surface's small tunnels come and go from frame
    to frame. Found once per frame."""
    def find():
        v, f = seq.frames[u]
        f = np.asarray(f, np.int64).reshape(-1, 3)
        k, _, _, small = _small_parts(v, f, FLOATER_AREA)
        unused = len(v) - int(np.count_nonzero(np.bincount(f.ravel(), minlength=len(v))))
        return int(k - unused - len(small))  # a vertex no face uses is no part

    return _once(seq, ("separation", int(u)), find)


def _most_separate(seq: VaryingTopologySequence, order, ok, t: int) -> int:
    """``t``, or where the input's parts are farther apart than at t (:func:`_separation`, on
    ``_sample_frames`` and t), the first frame of ``order`` (largest area first) with them as far
    apart. A fixed template can follow two parts into contact but not tear one part into two: a new
    user's two fingers, bent until their tips touched, were largest (stretched) where fused, and the
    template from there kept a web between the tips on every frame after (1.8-2.6 % of the area,
    under the web's threshold). Few frames are asked: the sample, then the order up to a frame as
    separate."""
    best = max([_separation(seq, u) for u in _sample_frames(seq.num_frames) if ok(u)] + [_separation(seq, t)])
    if _separation(seq, t) >= best:
        return t
    return next(int(u) for u in order if ok(int(u)) and _separation(seq, int(u)) >= best)


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


def _same_frame(a: tuple, b: tuple) -> bool:
    """Whether two input frames (V, F) are the same mesh, vertex for vertex and face for face."""
    return np.array_equal(a[1], b[1]) and np.array_equal(a[0], b[0])  # (False for other shapes)


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
    out = FixedTopologySequence(V, res.F, **carried(res))
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


#: the automatic key frame (:func:`_key_frame`): a window's middle frame more than this fraction
#: below the window's median area is not taken (a hole, a coarser remesh), nor is a frame when one
#: of about its area (within this fraction) has KEY_FINER x its vertices. The protocol's inputs
#: (5 sequences at 1 % error, r96; 5 noise-free at r192) keep their key frames.
KEY_AREA_TOLERANCE = 0.02
KEY_FINER = 2.0
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
