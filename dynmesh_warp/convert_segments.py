"""Piecewise-fixed conversion (``convert.to_piecewise_fixed``): where a run should start a new
template (a segment), slicing a result, and joining the segments' results into one sequence."""

from __future__ import annotations

import dataclasses

import numpy as np

from .convert_base import ConversionInfo
from .convert_report import _cut_badness
from .sequence import FixedTopologySequence, VaryingTopologySequence, carried


def _segment_cut(info, events: list, lo: int) -> tuple | None:
    """The frames (a, b) (absolute, b exclusive) a run over frames lo.. should convert again with
    a template of their own, or None: from the first poor frame after the key frame, the range
    from the input's last topology change at or before it to the end; else, before the key
    frame, from frame lo to the first topology change after the last poor frame."""
    bad = np.flatnonzero(_cut_badness(info) > 1.0) + lo
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
    if new is None or _cut_badness(new.conversion).max() >= _cut_badness(res.conversion)[a - lo:b - lo].max():
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
    out = FixedTopologySequence(res.V[i:j], res.F, **carried(res))
    out.conversion = dataclasses.replace(info, num_frames=j - i, key_frame=info.key_frame - i,
                                         coverage=list(info.coverage[i:j]), web=list(info.web[i:j]),
                                         coverage_tail=list(info.coverage_tail[i:j]), flipped=list(info.flipped[i:j]),
                                         off_input=list(info.off_input[i:j]),
                                         area_ratio=list(info.area_ratio[i:j]),
                                         frame_motion=[0.0] + list(info.frame_motion[i + 1:j]),
                                         input_motion=[0.0] + list(info.input_motion[i + 1:j]),
                                         buried=list(info.buried[i:j]), rejected_cuts=list(info.rejected_cuts),
                                         frame_seconds=list(info.frame_seconds[i:j]),
                                         missing_parts=_parts_within(info.missing_parts, i, j, len(info.coverage)),
                                         **_frame_fields(info, -i, i, j))
    return out


def _parts_within(parts: list, i: int, j: int, n: int) -> list:
    """The runs of ``missing_parts`` (``(first, last, lost)`` over a result's frames 0..n-1) that
    lie in frames i..j-1 together with the frames next to them that have the part (a run from the
    result's first frame or to its last has none on that side), counted from i: what a slice of
    the result can say (a run whose neighbour went to another segment is that segment's cut)."""
    return [(a - i, b - i, lost) for a, b, lost in parts
            if i <= a and b < j and (a == 0 or a - 1 >= i) and (b == n - 1 or b + 1 < j)]


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
    out = VaryingTopologySequence(frames, **carried(vseq))
    first = segs[0][1].conversion
    info = ConversionInfo(first.strategy, first.options, vseq.num_frames,
                          max(r.num_vertices for _, r in segs), key_frame=first.key_frame + segs[0][0])
    for lo, r in segs:
        c = r.conversion
        info.coverage += c.coverage
        info.coverage_tail += c.coverage_tail
        info.flipped += c.flipped
        info.off_input += c.off_input
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
        info.tiny_parts += c.tiny_parts
    info.key_score = "+".join(sorted({r.conversion.key_score for _, r in segs} - {""}))
    info.topology_events, info.dropped_unused, info.welded = list(events), whole.dropped_unused, whole.welded
    info.turned_outward, info.input_dropouts, info.rewound = whole.turned_outward, whole.input_dropouts, whole.rewound
    info.removed_parts = whole.removed_parts
    # each segment's own (its template's): the whole first run's named runs the segments split
    # apart (a new user's floater on frames 3-5 of 12, a segment of its own, was still said to be
    # missing from frames 0-2 and "pressed onto what is left" by a template that had no part there)
    info.missing_parts = [(a + lo, b + lo, lost) for lo, r in segs
                          for a, b, lost in _parts_within(r.conversion.missing_parts, 0, r.num_frames, r.num_frames)
                          if (a > 0 or lo == 0) and (b < r.num_frames - 1 or lo + r.num_frames == vseq.num_frames)]
    out.conversion = info
    return out
