"""Geometric accuracy of topology conversion, in the layout of the paper's Table 1.

For each scene (a fixed-topology ground-truth sequence, e.g. /work/shared/data/*.npz):

1. the ground truth is resampled in time to ``--num-frames`` frames
   (:func:`dynmesh_warp.remesh.resample_time`) and re-meshed per frame by marching cubes into
   a varying-topology sequence (:func:`dynmesh_warp.remesh.remesh_sequence`), or a given
   varying-topology sequence is loaded (``--inputs``);
2. every conversion strategy of :data:`dynmesh_warp.convert.STRATEGIES` turns it into a
   fixed-topology (or piecewise-fixed) sequence as ``convert`` writes it
   (:func:`dynmesh_warp.convert.to_piecewise_fixed`);
3. each row (varying input, temporal tracking, template projection, the project's own
   strategy) is compared frame by frame with the ground-truth frame of the same index under
   each protocol of :data:`dynmesh_warp.metrics.PROTOCOLS`.

Outputs (atomic writes) in ``--out``: ``results.json`` (raw per-frame values, config,
timings), ``table_<protocol>.md`` / ``.csv`` (CD in 1e-3, EMD in 1e-1, % change against the
varying input) and ``chart_<protocol>.png`` (bar chart).

A folder of predicted meshes can be compared with a folder of ground-truth meshes with
``--compare GT_DIR PRED_DIR``: files are paired by the integer frame index in their names
(:func:`dynmesh_warp.io.frame_index_from_name`), never by lexicographic order.

Example (GPU, full): ``python -m dynmesh_warp.evaluate /work/shared/data/{horse_gallop,
horse_collapse,pcow}.npz --num-frames 200 --device cuda --out eval_out``.
"""

from __future__ import annotations

import csv
import io as _io
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from . import metrics as M
from .geometry import bbox_diagonal
from .outputs import atomic_path, atomic_write_bytes, atomic_write_json
from .sequence import FixedTopologySequence, MeshDataError, VaryingTopologySequence, carried

__all__ = [
    "ROW_LABELS",
    "row_label",
    "pair_frames_by_index",
    "evaluate_rows",
    "evaluate_folders",
    "evaluate_scene",
    "surface_velocity_error",
    "surface_drift",
    "summarize",
    "format_markdown",
    "main",
]

ROW_LABELS = {
    "varying": "Varying-topology input",
    "tracking": "Temporal tracking",
    "projection": "Template projection",
}


def row_label(key: str) -> str:
    """Table label of a row: the paper's names for the baselines, 'Ours (<strategy>)' else."""
    return ROW_LABELS.get(key, f"Ours ({key})")


# --------------------------------------------------------------------------- frame pairing


def pair_frames_by_index(gt_names, pred_names, strict: bool = True):
    """Pair two lists of frame file names by the integer index in each name.

    Returns [(index, gt_name, pred_name)] sorted by index. Indices present on one side only
    raise MeshDataError when ``strict`` (naming them), else are skipped. Two names with the
    same index on one side always raise.
    """
    from .io import frame_index_from_name

    def index(names, side):
        out = {}
        for n in names:
            i = frame_index_from_name(n)
            if i in out:
                raise MeshDataError(f"{side}: two files have frame index {i}: {out[i]} and {n}")
            out[i] = n
        return out

    g, p = index(gt_names, "ground truth"), index(pred_names, "prediction")
    only_g, only_p = sorted(set(g) - set(p)), sorted(set(p) - set(g))
    if strict and (only_g or only_p):
        hint = ""
        if len(g) == len(p):
            hint = (f"; both have {len(g)} frames (numbered from {min(g)} and from {min(p)}): "
                    "--pair order pairs them by position")
        raise MeshDataError(
            f"frames do not pair up by index: only in ground truth {only_g[:10]}, "
            f"only in prediction {only_p[:10]}{hint}")
    return [(i, g[i], p[i]) for i in sorted(set(g) & set(p))]


def pair_frames_by_order(gt_names, pred_names):
    """Pair the k-th ground-truth frame with the k-th predicted frame (both in index order),
    e.g. for frames numbered from 1 on one side and from 0 on the other. Returns
    [(k, gt_name, pred_name)]; raises MeshDataError when the counts differ."""
    if len(gt_names) != len(pred_names):
        raise MeshDataError(f"--pair order needs as many predicted frames as ground-truth frames "
                            f"({len(pred_names)} vs {len(gt_names)})")
    return [(k, g, p) for k, (g, p) in enumerate(zip(gt_names, pred_names))]


# --------------------------------------------------------------------------- evaluation


def evaluate_rows(gt_frames, rows: dict, frames, protocols=("dgmesh", "paper"), emd_frames=None,
                  seed: int = 0, device=None, progress: bool = False, desc: str = "", should_stop=None) -> dict:
    """Compare each row's frames with the ground truth at the same frame index.

    gt_frames: indexable of (V, F) by frame index; rows: {key: indexable of (V, F)};
    frames: frame indices to evaluate; emd_frames: the subset that also gets EMD (default all).
    Frame t is sampled with seed ``seed + 2 t`` (ground truth) and ``seed + 2 t + 1``
    (prediction), the same ground-truth samples for every row.
    Returns {key: {protocol: {'frames', 'cd', 'cd_gt_to_pred', 'cd_pred_to_gt', 'emd_frames',
    'emd'}}} with raw values (scene units; CD squared).
    Frames are evaluated in order, every row's frame t before frame t + 1; ``should_stop``
    (checked before each row's frame) ends it early: each row's ``frames`` then lists the
    frames it has values for.
    """
    frames = [int(t) for t in frames]
    emd_set = set(frames if emd_frames is None else (int(t) for t in emd_frames))
    out = {k: {p: {"frames": frames, "cd": [], "cd_gt_to_pred": [], "cd_pred_to_gt": [],
                   "emd_frames": [], "emd": [], "degenerate_frames": []}
                for p in protocols} for k in rows}
    jobs = [(k, t) for t in frames for k in rows]
    it = jobs
    if progress:
        from tqdm import tqdm

        it = tqdm(jobs, desc=f"metrics {desc}".strip(), unit="frame")
    done = {k: [] for k in rows}
    for k, t in it:
        if should_stop is not None and should_stop():
            if hasattr(it, "close"):
                it.close()
            for kk in out:
                for p in protocols:
                    out[kk][p]["frames"] = list(done[kk])
            break
        done[k].append(t)
        for p in protocols:
            r = M.evaluate_mesh_pair(gt_frames[t], rows[k][t], p, seed=seed + 2 * t, device=device,
                                     emd=t in emd_set, source=f"{desc} {k} frame {t}".strip())
            d = out[k][p]
            d["cd"].append(r["cd"])
            d["cd_gt_to_pred"].append(r["cd_gt_to_pred"])
            d["cd_pred_to_gt"].append(r["cd_pred_to_gt"])
            if r["degenerate_prediction"]:
                d["degenerate_frames"].append(t)
            if r["emd"] is not None:
                d["emd_frames"].append(t)
                d["emd"].append(r["emd"])
    for k in out:
        for p in protocols:
            d = out[k][p]
            d["cd_mean"] = float(np.mean(d["cd"])) if d["cd"] else None
            d["emd_mean"] = float(np.mean(d["emd"])) if d["emd"] else None
    return out


#: ``--compare`` warns when a prediction's first frame is this many times larger or smaller than
#: the ground truth's (bounding-box diagonals): meshes in other units (mm against m) or of
#: another scene, whose distances would be meaningless
SCALE_MISMATCH = 10.0


def _warn_other_units(what: str, V, gt_V, gt_name, stacklevel: int = 3) -> None:
    """Warn when ``what``'s vertices ``V`` (the compared mesh, named in ``what``) and the ground
    truth's ``gt_V`` (named ``gt_name``) differ in size (bounding-box diagonal) by SCALE_MISMATCH
    or more."""
    d_gt, d = (bbox_diagonal(x) for x in (gt_V, V))
    ratio = d / d_gt if d_gt > 0 else np.inf
    if not (1.0 / SCALE_MISMATCH < ratio < SCALE_MISMATCH):
        warnings.warn(f"{what} is {d:.4g} across, the ground truth's ({gt_name}) {d_gt:.4g} ({ratio:.3g}x): other "
                      "units (mm against m?) or another scene; the distances compare them as they are",
                      stacklevel=stacklevel)


def _check_scales(index, gt_file, pred_file) -> float:
    """Warn when the paired first frames differ in size by SCALE_MISMATCH or more; returns the
    ground truth's frame's bounding-box diagonal (:func:`~dynmesh_warp.geometry.bbox_diagonal`)."""
    from .io import read_mesh

    gt_V = read_mesh(gt_file)[0]
    _warn_other_units(f"--compare: the prediction's frame {index} ({pred_file})", read_mesh(pred_file)[0],
                      gt_V, gt_file, stacklevel=4)
    return bbox_diagonal(gt_V)


def evaluate_folders(gt_dir, pred_dir, protocols=("dgmesh", "paper"), frame_stride: int = 1,
                     emd: bool = True, seed: int = 0, device=None, progress: bool = False,
                     pair: str = "index", should_stop=None, emd_stride: int | None = None) -> dict:
    """Compare a folder of predicted meshes with a folder of ground-truth meshes, pairing files
    by the integer frame index in their names (``pair="index"``) or by position in index order
    (``pair="order"``). ``emd_stride`` K: EMD only on the pairs at positions 0, K, 2K, ... of the
    paired list (as the CLI's estimate counts them; it was ignored here, and EMD ran on every
    pair: a new user's). Returns {'pairs': [(index, gt, pred)], 'results':
    evaluate_rows(...)['prediction'], 'gt_diagonal': the first ground-truth frame's bounding-box
    diagonal (its units; None without pairs)} (frames are the paired indices)."""
    from .io import read_mesh
    from .sequence_layouts import list_frame_files

    gt_files = [str(p) for p in list_frame_files(Path(gt_dir))]  # in index order
    pred_files = [str(p) for p in list_frame_files(Path(pred_dir))]
    if pair not in ("index", "order"):
        raise ValueError(f"pair must be 'index' or 'order', got {pair!r}")
    pairing = pair_frames_by_index if pair == "index" else pair_frames_by_order
    pairs = pairing(gt_files, pred_files)
    fs = max(1, int(frame_stride))
    at = range(0, len(pairs), fs)  # each evaluated pair's position in the whole paired list
    pairs = pairs[::fs]

    class _Lazy(dict):
        def __init__(self, col):
            super().__init__()
            self.col = col

        def __missing__(self, t):
            name = next(p[self.col] for p in pairs if p[0] == t)
            return read_mesh(name)

    idx = [p[0] for p in pairs]
    diagonal = _check_scales(*pairs[0]) if pairs else None
    emd_frames = [] if not emd else None if not emd_stride else \
        [t for t, k in zip(idx, at) if k % int(emd_stride) == 0]
    res = evaluate_rows(_Lazy(1), {"prediction": _Lazy(2)}, idx, protocols,
                        emd_frames=emd_frames, seed=seed, device=device,
                        progress=progress, desc=Path(pred_dir).name, should_stop=should_stop)
    return {"pairs": pairs, "results": res["prediction"], "gt_diagonal": diagonal}


def _carried(gt: FixedTopologySequence, near, t: int) -> np.ndarray:
    """The GT surface points ``near`` found (a :func:`~dynmesh_warp.convert.nearest_surface`
    result on a GT frame: faces and barycentric weights) at GT frame ``t`` [m], float64 (Q, 3)."""
    tri = np.asarray(gt.V[t], np.float64)[np.asarray(gt.F)[near.face]]
    return np.einsum("qk,qkj->qj", near.bary.astype(np.float64), tri)


def surface_velocity_error(gt: FixedTopologySequence, pred, device=None) -> dict:
    """How far the converted surface's velocity is from the ground truth's: per frame pair
    (t, t + 1) within one template segment of ``pred`` (a fixed-topology sequence, or a
    piecewise-fixed one), each predicted vertex's displacement against the GT's displacement at
    the GT point nearest to it at frame t (that point's face and barycentric weights carried to
    frame t + 1). A template sliding along a GT surface that does not move counts in full: that
    is the surface velocity a sphere in contact feels (the friction of the contact), which
    neither the Chamfer distance nor coverage sees (a new user's two merging balls came out with
    their vertices swapped over: spheres thrown at 30 m/s by the sliding surface).

    Returns ``{"pairs": [per pair {"p50", "p99", "max", "gt_p99"} or None across a segment
    change], "p50_mean", "p99_mean", "p99_max", "p99_worst_pair", "max", "max_worst_pair",
    "gt_p99_mean"}``: the errors' median, 99th percentile and maximum over the vertices, and the GT's own displacement's 99th
    percentile at those points for scale; fractions of the GT frame's bbox diagonal per frame
    (x fps x diagonal: a speed). Without a pair inside a segment the summary figures are None."""
    from .convert import nearest_surface

    pairs = []
    for t in range(min(gt.num_frames, pred.num_frames) - 1):
        (V0, F0), (V1, F1) = pred.frame(t), pred.frame(t + 1)
        if len(V0) != len(V1) or np.shape(F0) != np.shape(F1) or not np.array_equal(F0, F1):
            pairs.append(None)
            continue
        diag = max(float(np.linalg.norm(np.ptp(gt.V[t], axis=0))), 1e-30)
        r = nearest_surface((gt.V[t], gt.F), V0, device=device)
        u = _carried(gt, r, t + 1) - r.closest  # the GT's displacement there
        e = np.linalg.norm(np.asarray(V1, np.float64) - np.asarray(V0, np.float64) - u, axis=1) / diag
        pairs.append({"p50": float(np.median(e)), "p99": float(np.percentile(e, 99)), "max": float(e.max()),
                      "gt_p99": float(np.percentile(np.linalg.norm(u, axis=1), 99)) / diag})
    done = [(t, p) for t, p in enumerate(pairs) if p is not None]
    out = {"pairs": pairs, "p50_mean": None, "p99_mean": None, "p99_max": None, "p99_worst_pair": None, "max": None,
           "max_worst_pair": None, "gt_p99_mean": None}
    if done:
        e99, emax = (np.array([p[k] for _, p in done]) for k in ("p99", "max"))
        out.update(p50_mean=float(np.mean([p["p50"] for _, p in done])),
                   p99_mean=float(e99.mean()), p99_max=float(e99.max()), p99_worst_pair=done[int(e99.argmax())][0],
                   max=float(emax.max()), max_worst_pair=done[int(emax.argmax())][0],
                   gt_p99_mean=float(np.mean([p["gt_p99"] for _, p in done])))
    return out


def _segment_runs(pred) -> list:
    """``(start, stop, key frame)`` per template segment of a converted sequence: its
    ``conversion.segments`` when it has them; for a sequence loaded from a complete ``convert``
    output, the segments its status records (:func:`_stored_segments`); else the runs of one
    topology anchored at their first frame."""
    info = getattr(pred, "conversion", None)
    segs = [(int(a), int(b), int(k)) for a, b, k, *_ in getattr(info, "segments", None) or []]
    if segs:
        return segs
    runs = pred.segments() if hasattr(pred, "segments") else [(0, pred.num_frames)]
    return _stored_segments(pred, runs) or [(a, b, a) for a, b in runs]


def _stored_segments(pred, runs) -> list:
    """The ``(start, stop, key frame)`` segments that the complete ``convert`` output ``pred`` was
    loaded from records in its status (``"segments"``), where they tile the sequence's own runs
    of one topology; else ``[]``. A loaded output had no ``conversion``, so its segments were
    anchored at their first frames instead of their key frames (a new user's thrown ball read a
    drift p99 of 57 % instead of 19.8 %)."""
    from .outputs import read_status

    src = getattr(pred, "source", None)
    try:
        status = (read_status(src) if src else None) or {}
        segs = [(int(a), int(b), int(k)) for a, b, k, *_ in status.get("segments") or []]
    except (OSError, TypeError, ValueError):  # not a path, or not segments: the runs as they are
        return []
    if not status.get("complete") or not segs:
        return []
    if [(a, b) for a, b, _ in segs] != [(int(a), int(b)) for a, b in runs] or any(not a <= k < b for a, b, k in segs):
        return []
    return segs


def surface_drift(gt: FixedTopologySequence, pred, device=None) -> dict:
    """How far the converted vertices have slid from the GT surface points they stood on: each
    vertex of a template segment of ``pred`` is attached, at the segment's key frame, to the GT
    point nearest to it (face and barycentric weights), and at every frame t of the segment its
    distance to that point carried to frame t by the GT is measured. A template that follows the
    surface stays near 0 (the fit's own per-frame error); one that slides a little each frame
    drifts ever further, which the per-pair velocity error (:func:`surface_velocity_error`) sees
    only as a small error every pair (a new user's twisting cylinder: its base came out turned
    156° about the axis with every per-frame figure fine).

    Returns ``{"frames": [per frame {"p50", "p99", "max"} (None outside the GT's frames)],
    "p50_mean", "p50_max", "p99_mean", "p99_max", "p99_worst_frame", "max"}``: over the vertices,
    fractions of the GT frame's bbox diagonal."""
    from .convert import nearest_surface

    T = min(gt.num_frames, pred.num_frames)
    frames = [None] * T
    for a, b, k in _segment_runs(pred):
        if not a <= k < min(b, T):
            continue
        r = nearest_surface((gt.V[k], gt.F), pred.frame(k)[0], device=device)
        for t in range(a, min(b, T)):
            P = _carried(gt, r, t)
            diag = max(float(np.linalg.norm(np.ptp(gt.V[t], axis=0))), 1e-30)
            d = np.linalg.norm(np.asarray(pred.frame(t)[0], np.float64) - P, axis=1) / diag
            frames[t] = {"p50": float(np.median(d)), "p99": float(np.percentile(d, 99)), "max": float(d.max())}
    done = [(t, f) for t, f in enumerate(frames) if f is not None]
    out = {"frames": frames, "p50_mean": None, "p50_max": None, "p99_mean": None, "p99_max": None,
           "p99_worst_frame": None, "max": None}
    if done:
        p50, p99 = (np.array([f[q] for _, f in done]) for q in ("p50", "p99"))
        out.update(p50_mean=float(p50.mean()), p50_max=float(p50.max()), p99_mean=float(p99.mean()),
                   p99_max=float(p99.max()), p99_worst_frame=done[int(p99.argmax())][0],
                   max=float(max(f["max"] for _, f in done)))
    return out


#: the per-strategy motion figures ``summarize`` averages over scenes and ``format_markdown``
#: notes under the table: (the conversion's entry, the row's mean key, the entry's figure
#: averaged, the row's worst key, the entry's figure maximised, the note's text)
_MOTION_FIGURES = (
    ("surface_velocity", "velocity_p99", "p99_mean", "velocity_p99_worst", "p99_max",
     "Surface velocity against the ground truth's (`surface_velocity_error`: each converted vertex's displacement "
     "per frame against the GT's at its nearest GT point, 99th percentile over the vertices, fraction of the "
     "diagonal; mean over frame pairs / worst pair): "),
    ("surface_drift", "drift_p50", "p50_mean", "drift_p99_worst", "p99_max",
     "Drift from the ground truth's surface points (`surface_drift`: each converted vertex's distance to the GT "
     "point it stood on at its segment's key frame, carried by the GT; fraction of the diagonal; the median "
     "vertex's, mean over frames / the 99th percentile's worst frame): "),
)


def _ground_truth(path: str, num_frames: int | None, frame_order: str = "stored") -> FixedTopologySequence:
    from .io import load_sequence

    # a DG-Mesh scene folder: its ground truth is mesh_gt/ (load_sequence prefers the reconstruction,
    # dynamic_mesh/, which failed here as varying topology: a new user's)
    subdir = "mesh_gt" if Path(path).is_dir() and (Path(path) / "mesh_gt").is_dir() else None
    seq = load_sequence(path, kind="fixed", frame_order=frame_order, subdir=subdir)
    if num_frames is not None and num_frames != seq.num_frames:
        from .remesh import resample_time

        V = resample_time(seq, num_frames)
        fps = seq.fps * (num_frames - 1) / max(seq.num_frames - 1, 1) if seq.num_frames > 1 else seq.fps
        seq = FixedTopologySequence(V, seq.F, **carried(seq, fps=fps))
    return seq


def evaluate_scene(gt_path, input_path=None, num_frames: int | None = None, resolution: int = 96,
                   noise: float = 0.0, strategies=None, protocols=("dgmesh", "paper"),
                   frame_stride: int = 1, emd_stride: int | None = None, emd: bool = True,
                   seed: int = 0, device=None, progress: bool = True, options=None,
                   frame_order: str = "stored", should_stop=None) -> dict | None:
    """Remesh (or load) one scene, convert it with every strategy, evaluate every row.

    should_stop: checked between frames (conversion, metrics; the CLI's Ctrl-C): stopped before
    the metrics it returns None; during them, the rows' frames so far, with ``"interrupted":
    true``. Re-meshing has no frame boundaries here: a CLI's signal raises there (cli.raising_stops).

    frame_order: "text_sorted" undoes a text sort of the ground truth's frames (see io.load_sequence).

    emd_stride: EMD only on frames that are multiples of it (default: every evaluated frame).
    options: {strategy: {option: value}} passed to the conversion: ``to_piecewise_fixed``, what
    ``convert`` writes to a .npz or a folder (new templates where one cannot follow the input;
    ``max_segments`` 1: one template, ``to_fixed_topology``). The row was one template before, not
    what convert writes (a new user's four balls: 2 segments and no web from convert, a web on 2.6 %
    of the area in evaluate's row).
    Returns a JSON-ready dict (see module docstring).
    """
    from .convert import STRATEGIES, ConversionStopped, to_piecewise_fixed

    strategies = list(STRATEGIES if strategies is None else strategies)
    options = options or {}
    timing = {}
    t0 = time.perf_counter()
    gt = _ground_truth(str(gt_path), num_frames, frame_order)
    stopped = should_stop if should_stop is not None else (lambda: False)
    if input_path is None:
        from .cli import raising_stops
        from .remesh import remesh_sequence

        with raising_stops():
            varying = remesh_sequence(gt, resolution=resolution, noise=noise, seed=seed, device=device,
                                      progress=progress)
    else:
        from .io import load_sequence

        varying = load_sequence(input_path, kind="varying")
        if not isinstance(varying, VaryingTopologySequence):
            varying = varying.to_varying()
    if varying.num_frames != gt.num_frames:
        raise MeshDataError(
            f"{input_path or 'remesh'}: {varying.num_frames} input frames but the ground truth "
            f"{gt_path} has {gt.num_frames} (after --num-frames); they are paired by index")
    if input_path is not None:  # a ground truth in mm against an input in m compared silently (a new user's)
        _warn_other_units(f"--inputs: the input's frame 0 ({input_path})", varying.frames[0][0], gt.V[0], gt_path)
    timing["prepare_s"] = time.perf_counter() - t0
    rows = {"varying": varying.frames}
    conv_info = {}
    for s in strategies:
        if stopped():
            return None
        t0 = time.perf_counter()
        try:
            fixed = to_piecewise_fixed(varying, strategy=s, device=device, progress=progress, should_stop=should_stop,
                                       **options.get(s, {}))
        except ConversionStopped:  # stopped during the conversion's checks or set-up, before its first frame
            return None
        if fixed.num_frames < varying.num_frames:
            return None
        timing[f"convert_{s}_s"] = time.perf_counter() - t0
        rows[s] = [fixed.frame(t) for t in range(fixed.num_frames)]
        info = getattr(fixed, "conversion", None)
        conv_info[s] = {"options": dict(getattr(info, "options", {}) or {}),
                        "segments": [list(x) for x in getattr(info, "segments", []) or []],
                        "reanchored_frames": list(getattr(info, "reanchored_frames", []) or []),
                        "surface_velocity": surface_velocity_error(gt, fixed, device),
                        "surface_drift": surface_drift(gt, fixed, device)}
    frames = list(range(0, gt.num_frames, max(1, int(frame_stride))))
    if not emd:
        emd_frames = []
    elif emd_stride:
        emd_frames = [t for t in frames if t % int(emd_stride) == 0]
    else:
        emd_frames = frames
    gt_frames = [gt.frame(t) for t in range(gt.num_frames)]
    t0 = time.perf_counter()
    if stopped():
        return None
    res = evaluate_rows(gt_frames, rows, frames, protocols, emd_frames, seed=seed, device=device,
                        progress=progress, desc=gt.name, should_stop=should_stop)
    timing["metrics_s"] = time.perf_counter() - t0
    nv = [len(v) for v, _ in varying.frames]
    return {
        "scene": gt.name, "ground_truth": str(gt_path), "input": str(input_path) if input_path else
        f"remesh_sequence(resolution={resolution}, noise={noise}, seed={seed})",
        "num_frames": gt.num_frames, "gt_vertices": int(gt.num_vertices), "gt_diagonal": bbox_diagonal(gt.V[0]),
        "input_vertices_min_max": [int(min(nv)), int(max(nv))],
        "frames": frames, "emd_frames": emd_frames, "rows": res, "conversion": conv_info,
        "timing": timing,
        # stopped during the metrics: some row lacks some of the frames
        "interrupted": any(len(res[k][p]["frames"]) < len(frames) for k in res for p in protocols),
    }


# --------------------------------------------------------------------------- tables


def summarize(scenes: list, protocol: str) -> dict:
    """Per-row averages over scenes and % change against the varying input for one protocol.
    Returns {'scenes': [names], 'rows': {key: {'label', 'per_scene': {scene: {'cd', 'emd'}},
    'cd', 'emd', 'cd_change_pct', 'emd_change_pct'}}} with raw values."""
    keys = list(scenes[0]["rows"])
    out = {"scenes": [s["scene"] for s in scenes], "rows": {}}
    for k in keys:
        per = {s["scene"]: {"cd": s["rows"][k][protocol]["cd_mean"],
                            "emd": s["rows"][k][protocol]["emd_mean"]} for s in scenes}
        cds = [v["cd"] for v in per.values() if v["cd"] is not None]
        emds = [v["emd"] for v in per.values() if v["emd"] is not None]
        out["rows"][k] = {"label": row_label(k), "per_scene": per,
                          "cd": float(np.mean(cds)) if cds else None,
                          "emd": float(np.mean(emds)) if len(emds) == len(per) else None}
        for figure, mean_key, mean_of, worst_key, worst_of, _ in _MOTION_FIGURES:
            got = [s.get("conversion", {}).get(k, {}).get(figure) for s in scenes]
            if k != "varying" and got and all(g and g.get(mean_of) is not None for g in got):
                out["rows"][k][mean_key] = float(np.mean([g[mean_of] for g in got]))
                out["rows"][k][worst_key] = float(max(g[worst_of] for g in got))
    base = out["rows"].get("varying")
    for k, r in out["rows"].items():
        for m in ("cd", "emd"):
            b = base[m] if base else None
            r[f"{m}_change_pct"] = (100.0 * (r[m] - b) / b) if (b and r[m] is not None) else None
    return out


def _fmt(x, scale, digits=3):
    return "–" if x is None else f"{x / scale:.{digits}f}"


def _pct(x):
    return "–" if x is None else f"{x:+.1f}%"


def _table_rows(summary: dict):
    scenes = summary["scenes"]
    header = ["Method"]
    for s in scenes:
        header += [f"{s} CD", f"{s} EMD"]
    header += ["Avg CD", "Avg EMD", "CD change", "EMD change"]
    body = []
    for k, r in summary["rows"].items():
        row = [r["label"]]
        for s in scenes:
            row += [_fmt(r["per_scene"][s]["cd"], M.CD_SCALE), _fmt(r["per_scene"][s]["emd"], M.EMD_SCALE)]
        row += [_fmt(r["cd"], M.CD_SCALE), _fmt(r["emd"], M.EMD_SCALE),
                "–" if k == "varying" else _pct(r["cd_change_pct"]),
                "–" if k == "varying" else _pct(r["emd_change_pct"])]
        body.append(row)
    return header, body


def format_markdown(summary: dict, protocol: str, note: str = "") -> str:
    header, body = _table_rows(summary)
    lines = [f"Protocol `{protocol}`: {M.PROTOCOLS[protocol].description}",
             "CD in units of 1e-3 (squared distance, in the ground truth's units), EMD in units of 1e-1 "
             "(its units); change = "
             "(row - varying input) / varying input, on the averages.", ""]
    if note:
        lines += [note, ""]
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "---|" * len(header))
    lines += ["| " + " | ".join(r) + " |" for r in body]
    for _, mean_key, _, worst_key, _, text in _MOTION_FIGURES:
        parts = [f"{r['label']} {100 * r[mean_key]:.2f}% / {100 * r[worst_key]:.2f}%"
                 for r in summary["rows"].values() if mean_key in r]
        if parts:
            lines += ["", text + "; ".join(parts)]
    return "\n".join(lines) + "\n"


def format_csv(summary: dict) -> str:
    header, body = _table_rows(summary)
    buf = _io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    w.writerows(body)
    return buf.getvalue()


def write_chart(summary: dict, protocol: str, path) -> bool:
    """Bar chart of CD and EMD per scene and average, one bar per row. False without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    groups = summary["scenes"] + ["average"]
    keys = list(summary["rows"])
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, m, scale, unit in ((axes[0], "cd", M.CD_SCALE, "CD (1e-3)"),
                               (axes[1], "emd", M.EMD_SCALE, "EMD (1e-1)")):
        width = 0.8 / len(keys)
        plotted = []
        for j, k in enumerate(keys):
            r = summary["rows"][k]
            vals = [r["per_scene"][s][m] for s in summary["scenes"]] + [r[m]]
            vals = [np.nan if v is None else v / scale for v in vals]
            plotted += vals
            ax.bar(np.arange(len(groups)) + (j - (len(keys) - 1) / 2) * width, vals, width,
                   label=r["label"])
        ax.set_xticks(np.arange(len(groups)))
        ax.set_xticklabels(groups, rotation=15)
        finite = np.asarray(plotted, float)
        finite = finite[np.isfinite(finite)]
        if finite.size and (finite > 0).all():
            ax.set_yscale("log")  # values span orders of magnitude between rows
            unit += ", log scale"
        ax.set_ylabel(unit)
        ax.set_title(f"{m.upper()} ({protocol} protocol, lower is better)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)
    return True


#: names ``evaluate`` writes into ``--out`` (a foreign file of such a name is never replaced)
EVAL_OUTPUTS = ("table_*.md", "table_*.csv", "chart_*.png", "results.json", "compare.json")

#: approxmatch EMD on the CPU, measured: ~96 s per mesh pair at 8,192 samples (bench/results/metrics_cpu.json,
#: 2-core VM); the cost grows with the square of the samples. On an H200: 0.026 s.
EMD_CPU_S_8192 = 96.0


def _frames_done(scene: dict) -> str:
    """How many frames a scene's rows were evaluated on (a range when an interruption left them uneven)."""
    n = sorted({len(p["frames"]) for r in scene["rows"].values() for p in r.values()}) or [len(scene["frames"])]
    return str(n[0]) if len(n) == 1 else f"{n[0]}-{n[-1]}"


def write_outputs(out_dir, scenes: list, protocols, config: dict, interrupted: dict | None = None) -> dict:
    """Write the tables, charts and results.json into ``out_dir`` (each file atomically). The
    CLI passes the temporary folder of an :class:`~dynmesh_warp.outputs.OutputFolder`, renamed
    onto ``--out`` at the end (or after an interruption, with the scenes done so far).
    ``interrupted``: what was left out (results.json's ``"interrupted"``, a line in the tables)."""
    out_dir = Path(out_dir)
    summaries = {p: summarize(scenes, p) for p in protocols}
    strides = {(tuple(s["frames"]), tuple(s["emd_frames"])) for s in scenes}
    note = "; ".join(
        f"{s['scene']}: CD on {_frames_done(s)} of {s['num_frames']} frames "
        f"(stride {config.get('frame_stride', 1)}), EMD on {len(s['emd_frames'])} frames"
        + (f", ground truth {s['gt_diagonal']:.4g} units across (bounding-box diagonal, frame 0)"
           if s.get("gt_diagonal") is not None else "")
        for s in scenes) if len(strides) else ""
    if interrupted:
        note = (f"INTERRUPTED by {interrupted['signal']}: partial results ({interrupted['note']})"
                + (f"; {note}" if note else ""))
    for p in protocols:
        atomic_write_bytes(out_dir / f"table_{p}.md", format_markdown(summaries[p], p, note).encode())
        atomic_write_bytes(out_dir / f"table_{p}.csv", format_csv(summaries[p]).encode())
        write_chart(summaries[p], p, out_dir / f"chart_{p}.png")
    doc = {"config": config, "machine": platform.node(), "platform": platform.platform(),
           "device": str(config.get("device")), "units": {"cd": "squared scene units (raw)",
           "emd": "scene units (raw)", "table_cd_scale": M.CD_SCALE, "table_emd_scale": M.EMD_SCALE},
           "protocols": {p: M.PROTOCOLS[p].description for p in protocols},
           "summary": summaries, "scenes": scenes, "interrupted": interrupted}
    atomic_write_json(out_dir / "results.json", doc)
    return doc


# --------------------------------------------------------------------------- CLI


def _check_options(a, ap_error) -> list:
    """Every option and path of ``evaluate`` checked before any data is loaded; returns the
    inputs (ground truth, --inputs, --compare folders). Raises ValueError with one line."""
    from .convert import STRATEGIES

    def positive_int(name, v, least):
        if v < least:
            raise ValueError(f"--{name} must be an integer >= {least}, got {v}")

    positive_int("num-frames", a.num_frames, 0)
    if a.num_frames == 1:
        raise ValueError("--num-frames 1: resampling needs at least 2 frames (0 keeps the ground truth's)")
    positive_int("resolution", a.resolution, 8)
    positive_int("frame-stride", a.frame_stride, 1)
    positive_int("emd-stride", a.emd_stride, 0)
    positive_int("seed", a.seed, 0)
    if not (np.isfinite(a.noise) and a.noise >= 0):
        raise ValueError(f"--noise must be a finite number >= 0 (grid spacings), got {a.noise}")
    for st in a.strategies or []:
        if st not in STRATEGIES:
            raise ValueError(f"--strategies {st}: unknown strategy; valid: {', '.join(STRATEGIES)}")
    if a.compare:
        if a.scenes:
            raise ValueError("give either scenes or --compare GT_DIR PRED_DIR, not both")
        # options of the scene mode were ignored here without a word (a new user's)
        for flag, given in (("--num-frames", a.num_frames), ("--strategies", a.strategies)):
            if given:
                raise ValueError(f"{flag} applies to a ground-truth scene, not to --compare (which evaluates the "
                                 "files as they are; --frame-stride and --emd-stride thin them)")
        for d in a.compare:
            p = Path(d).expanduser()
            if not p.is_dir():
                raise ValueError(f"--compare {d}: " + ("a file, not a folder of per-frame meshes (a sequence file is "
                                                       "a ground-truth scene: evaluate GT --inputs PRED)"
                                                       if p.is_file() else "folder not found"))
        return list(a.compare)
    if not a.scenes:
        ap_error("give scenes to evaluate, or --compare GT_DIR PRED_DIR")
    if a.inputs is not None and len(a.inputs) != len(a.scenes):
        raise ValueError(f"--inputs needs one path per scene ({len(a.scenes)}), got {len(a.inputs)}")
    for what, paths in (("scene", a.scenes), ("--inputs", a.inputs or [])):
        for x in paths:
            if not Path(x).expanduser().exists():
                raise ValueError(f"{what} {x}: file or folder not found")
    return list(a.scenes) + list(a.inputs or [])


def _emd_estimate(a, device: str) -> str | None:
    """A line estimating the EMD time on the CPU when it exceeds a minute, naming faster options."""
    if a.no_emd or str(device).startswith("cuda"):
        return None
    from .convert import STRATEGIES

    rows = 1 + len(a.strategies or STRATEGIES)
    pairs = 0
    for sc in (a.scenes if not a.compare else [a.compare[0]]):
        n = a.num_frames
        if not n:
            try:
                from .io import load_sequence

                seq = load_sequence(sc) if not a.compare else None
                n = seq.num_frames if seq is not None else len([p for p in Path(sc).iterdir() if not p.name.startswith(".")])
            except Exception:  # noqa: BLE001 (the evaluation itself reports a bad input)
                return None
        frames = range(0, n, max(1, a.frame_stride))
        emd = [t for t in frames if not a.emd_stride or t % a.emd_stride == 0]
        pairs += len(emd) * (1 if a.compare else rows)
    secs = sum(pairs * EMD_CPU_S_8192 * (M.PROTOCOLS[p].emd_samples / 8192) ** 2 for p in a.protocol)
    if secs <= 60:
        return None
    h = secs / 3600
    return (f"estimate: EMD on the CPU takes ~{EMD_CPU_S_8192:.0f} s per frame pair (8,192 samples): "
            f"{pairs} pairs x {len(a.protocol)} protocol(s), about {h:.1f} h" if h >= 1 else
            f"estimate: EMD on the CPU takes ~{EMD_CPU_S_8192:.0f} s per frame pair (8,192 samples): "
            f"{pairs} pairs x {len(a.protocol)} protocol(s), about {secs / 60:.0f} min") + (
            "; faster: --device cuda (a GPU), --emd-stride K (EMD on every K-th frame), --no-emd")


from .cli import interruptible_main  # noqa: E402 (the CLI section's own import)


def _kept_note(out, folder) -> str:
    """Words for an output written beside ``out`` (:class:`~dynmesh_warp.outputs.OutputFolder`'s
    ``written``), else ""."""
    if folder.written == folder.path:
        return ""
    return f"; {out} holds an earlier output or files another run wrote meanwhile: kept as it is"


@interruptible_main
def main(argv=None) -> int:
    from .choices import DEFAULT_FRAME_ORDER, FrameOrder, values
    from .cli import Parser

    ap = Parser(prog="python -m dynmesh_warp.evaluate", description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="*", help="ground-truth fixed-topology sequences (.npz / folder)")
    ap.add_argument("--inputs", nargs="*", default=None,
                    help="varying-topology inputs, one per scene (default: remesh the ground truth)")
    ap.add_argument("--compare", nargs=2, metavar=("GT_DIR", "PRED_DIR"),
                    help="compare two folders of meshes, paired by frame index (see --pair)")
    ap.add_argument("--pair", choices=["index", "order"], default="index",
                    help="--compare: pair files by the integer in their names (index) or by position (order)")
    ap.add_argument("--out", default="eval_out", help="output folder (default eval_out)")
    ap.add_argument("--protocol", nargs="+", default=["dgmesh", "paper"], choices=sorted(M.PROTOCOLS))
    ap.add_argument("--strategies", nargs="+", default=None, help="default: all of convert.STRATEGIES")
    ap.add_argument("--num-frames", type=int, default=0,
                    help="resample the ground truth to this many frames (default 0: keep its frames; "
                         "the paper's protocol uses 200)")
    ap.add_argument("--resolution", type=int, default=96, help="remesh grid resolution (longest side)")
    ap.add_argument("--noise", type=float, default=0.0, help="remesh vertex noise, in grid spacings")
    ap.add_argument("--frame-stride", type=int, default=1,
                    help="evaluate every k-th frame (the CD / EMD table; the surface velocity and drift, which "
                         "follow each vertex from frame to frame, always use every frame)")
    ap.add_argument("--emd-stride", type=int, default=0,
                    help="EMD only on frames that are multiples of this (0: every evaluated frame)")
    ap.add_argument("--no-emd", action="store_true", help="skip EMD")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frame-order", choices=values(FrameOrder), default=DEFAULT_FRAME_ORDER.value,
                    help="text_sorted: undo a text sort of the ground truth's frames (1, 10, 11, ..., 2, ...); "
                         "auto: only where detected")
    ap.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda (default: Warp's default)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace an existing --out folder (only files this tool wrote; others are kept)")
    a = ap.parse_args(argv)
    import signal

    from .cli import Interrupted, checking_stops, quiet_warp, signal_name, stop_reason

    quiet_warp(a.device)
    progress = not a.no_progress
    try:
        from .outputs import OutputFolder, OutputKind, check_output, entries
        from .runtime import resolve_device

        device = str(resolve_device(a.device, "--device"))
        inputs = _check_options(a, ap.error)
        check_output(a.out, kind="folder", what="--out", inputs=inputs, overwrite=a.overwrite, writes=EVAL_OUTPUTS,
                     holds=OutputKind.EVALUATION)
        checked = entries(a.out)  # what appears there during the work is not replaced (OutputFolder)
        note = _emd_estimate(a, device)
        if note:
            print(note, file=sys.stderr)
        if a.compare:
            with checking_stops():  # Ctrl-C / SIGTERM: stop between frames, write the frames done
                r = evaluate_folders(a.compare[0], a.compare[1], a.protocol, a.frame_stride, pair=a.pair,
                                     emd=not a.no_emd, seed=a.seed, device=device, progress=progress,
                                     should_stop=stop_reason, emd_stride=a.emd_stride or None)
                reason = stop_reason()
                done = len(r["results"][a.protocol[0]]["frames"])
                if reason and not done:
                    raise Interrupted(getattr(signal, reason))
                cmp_folder = OutputFolder(a.out, overwrite=a.overwrite, interrupted=bool(reason), checked=checked,
                                          holds=OutputKind.EVALUATION)
                with cmp_folder as tmp:
                    atomic_write_json(tmp / "compare.json", {
                        "ground_truth": a.compare[0], "prediction": a.compare[1], "device": device,
                        "pairs": r["pairs"], "results": r["results"], "gt_diagonal": r["gt_diagonal"],
                        "interrupted": {"signal": reason, "frames_done": done, "pairs": len(r["pairs"])}
                        if reason else None})
            if reason:
                print(f"interrupted by {reason} after {done} of {len(r['pairs'])} frame pairs: wrote "
                      f"{cmp_folder.written / 'compare.json'} with those (\"interrupted\" set)"
                      + _kept_note(a.out, cmp_folder), file=sys.stderr)
                return 128 + int(getattr(signal, reason))
            for p in a.protocol:
                d = r["results"][p]
                emd = "–" if d["emd_mean"] is None else f"{d['emd_mean'] / M.EMD_SCALE:.4f}"
                print(f"{p}: CD {d['cd_mean'] / M.CD_SCALE:.4f} (1e-3), EMD {emd} (1e-1) "
                      f"over {len(d['frames'])} frames")
            if r["gt_diagonal"] is not None:
                print(f"(CD in squared units of the ground truth, EMD in its units; its first frame is "
                      f"{r['gt_diagonal']:.4g} across, bounding-box diagonal)")
            if cmp_folder.written != cmp_folder.path:
                print(f"warning: wrote {cmp_folder.written}" + _kept_note(a.out, cmp_folder), file=sys.stderr)
            return 0
        config = {"argv": sys.argv[1:] if argv is None else list(argv), "device": device,
                  "num_frames": a.num_frames or None, "resolution": a.resolution, "noise": a.noise,
                  "frame_stride": a.frame_stride, "emd_stride": a.emd_stride, "emd": not a.no_emd,
                  "seed": a.seed, "protocols": a.protocol, "strategies": a.strategies,
                  "frame_order": a.frame_order}
        scenes = []
        folder = OutputFolder(a.out, overwrite=a.overwrite, checked=checked, holds=OutputKind.EVALUATION)
        reason, info = None, None
        from .convert import stopping_early

        # Ctrl-C / SIGTERM: stop between frames, keep what is done (a conversion's set-up: at once)
        with checking_stops(), stopping_early(), folder as tmp:
            for i, s in enumerate(a.scenes):
                t0 = time.perf_counter()
                try:
                    scene = evaluate_scene(
                        s, a.inputs[i] if a.inputs else None, num_frames=a.num_frames or None,
                        resolution=a.resolution, noise=a.noise, strategies=a.strategies,
                        protocols=a.protocol, frame_stride=a.frame_stride, emd_stride=a.emd_stride or None,
                        emd=not a.no_emd, seed=a.seed, device=device, progress=progress,
                        frame_order=a.frame_order, should_stop=stop_reason)
                except Interrupted as e:  # in a stage without frame boundaries (re-meshing)
                    if not scenes:
                        raise
                    scene, reason = None, signal_name(e.signum)
                reason = reason or stop_reason()
                if scene is not None:
                    scene["timing"]["total_s"] = time.perf_counter() - t0
                    scenes.append(scene)
                if reason:
                    if not scenes:  # nothing evaluated: no output, the old one stays
                        raise Interrupted(getattr(signal, reason))
                    partial = scene is not None and scene["interrupted"]
                    info = {"signal": reason,
                            "complete_scenes": [sc["scene"] for sc in scenes if not sc["interrupted"]],
                            "partial_scene": scene["scene"] if partial else None,
                            "not_evaluated": [str(x) for x in a.scenes[i + (1 if scene is not None else 0):]],
                            "note": (f"{scene['scene']}: the frames evaluated before the stop" if partial else
                                     f"stopped before the metrics of {s}" if scene is None else f"stopped after {s}")}
                    folder.interrupted = True  # an earlier output there stays: the partial one goes beside it
                    break
                write_outputs(tmp, scenes, a.protocol, config)  # partial results after each scene
                folder.keep_on_error = True  # an interruption later keeps the scenes done so far
            doc = write_outputs(tmp, scenes, a.protocol, config, interrupted=info)
        if reason:
            print(f"interrupted by {reason}: wrote {folder.written} with partial results ({info['note']}; "
                  f"results.json \"interrupted\" lists what is missing)" + _kept_note(a.out, folder), file=sys.stderr)
            return 128 + int(getattr(signal, reason))
        for p in a.protocol:
            print(format_markdown(doc["summary"][p], p))
        if folder.written != folder.path:
            print(f"warning: wrote {folder.written}" + _kept_note(a.out, folder), file=sys.stderr)
        return 0
    except (MeshDataError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
