"""The conversion's report: the thresholds a converted frame is judged by (poor coverage, webs,
jumps, slides, dropouts; the run's segment cuts and key trials judge by the same ones), the
per-frame measures of a :class:`~dynmesh_warp.convert_base.ConversionInfo` they apply to, and
:func:`conversion_summary`, the lines ``convert`` prints. :func:`conversion_summary` and
:func:`slide_ratio` are re-exported by :mod:`dynmesh_warp.convert`, their canonical import path."""

from __future__ import annotations

import numpy as np

from .convert_base import ConversionInfo


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
#: a frame over POOR_FLIPPED whose converted area is also over FOLD_AREA x the input's (and not over
#: POOR_AREA, warned of on its own) is warned of as folded or crumpled: a new user's waving cloth
#: read 21-27 % flipped at 1.27-1.38x the input's area, and a squeezed balloon 13 % at 1.34x, with a
#: note only; the thin parts that read as many flipped faces with no fold have about the input's area
FOLD_AREA = 1.2
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
#: a new template segment (``convert.to_piecewise_fixed``) is tried only where a frame's web is over
#: CUT_WEB, twice the POOR_WEB that is warned of: a template change costs every correspondence (and
#: Gaussians' binding) at the cut, and webs just over POOR_WEB are where the decision flipped. The
#: same 8 frames gave 1 template, and 3 (one of them a single frame's, open) when moved by one float32
#: ulp or scaled to millimetres; one frame extracted at 4x the resolution gave 4 (a new user's). The
#: cuts that mended topology events had webs of 7-8 % (tests/test_segments.py)
CUT_WEB = 2 * POOR_WEB
#: a frame whose converted surface has more than this fraction of its area off the input (no
#: input point within WEB_GAP x the diagonal of a face's centroid) besides its web and buried
#: faces, and no dropout there, is warned of: the fit lost the input unstretched (a new user's
#: propeller at 90 degrees a frame, crumpled inside its body: 1.4-7.5 % on 9 of 16 frames)
POOR_OFF = 0.01
#: a poor web frame counts as pulled by a floater when a separate input part of less than this
#: fraction of the frame's area has most of its vertices nearest to stretched faces
FLOATER_AREA = 0.05
#: a template part under this fraction of the template's area is tiny: where a template holds
#: TINY_PARTS or more (debris of a reconstruction, not a body's parts), the summary names the
#: option ``min_part_area`` (a new user's 200 tetrahedra of 1 cm a frame, all kept as parts; the
#: protocol's inputs at 1 % error have up to 23 in a frame, fragments of thin parts: chicken_crossing)
TINY_PART_AREA = 0.001
TINY_PARTS = 50
#: the key trials' moving score (:func:`_moving_score`) is the mean of this largest fraction of
#: the moving points' distances to the output, pooled over the frames. Measured on seven floor
#: scenes' stored key runs (CPU; docs/conversion.md): the best run that lost a part on 3 or more
#: frames scores 1.44-1.46x the best that lost one on at most 1 (the mean squared distance over
#: frames, the previous score: 1.11x on one scene, which GPU noise then flipped); 0.3-1 % gave
#: 1.31x or more
MOVING_SCORE_TAIL = 0.005


def _dropout_runs(frames) -> list:
    """The runs ``(first, last)`` of consecutive frames in ``frames`` (dropout frames)."""
    runs = []
    for t in sorted(set(frames)):
        if runs and t == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], t)
        else:
            runs.append((t, t))
    return runs


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


def _stretched_far(info) -> np.ndarray:
    """Per frame, the fraction of the converted area on stretched faces far from the input, outside
    it (``web``) or inside it (``buried``): what the restarts, the segment cuts and the floater
    check weigh (a template crumpled inside the body is mended by them too)."""
    return np.asarray(info.web, float) + (np.asarray(info.buried, float) if len(info.buried) else 0.0)


def _badness(info, web_limit: float = POOR_WEB) -> np.ndarray:
    """Per frame, how poor the fit is: max(coverage / POOR_COVERAGE, :func:`_stretched_far` /
    web_limit); > 1 is poor."""
    return np.maximum(np.asarray(info.coverage, float) / POOR_COVERAGE, _stretched_far(info) / web_limit)


def _cut_badness(info) -> np.ndarray:
    """Per frame, how poor the fit is for a segment cut: :func:`_badness` with the web against
    CUT_WEB; > 1 tries a new template."""
    return _badness(info, CUT_WEB)


def _frames_text(frames, limit: int = 12) -> str:
    """``"a, b, c"`` of the first ``limit`` frames, `` ...`` after them when there are more."""
    frames = list(frames)
    return ", ".join(map(str, frames[:limit])) + (" ..." if len(frames) > limit else "")


#: the whole conversion's time is said beside the kept run's when it is over this factor of it
ALL_SECONDS_SHOWN = 1.2


def _dropout_frames(info: ConversionInfo) -> set:
    """The frames, counted from ``info.first_frame``, where the input lacks a part the template keeps:
    its dropouts, and its missing-part runs with a frame either side (the fits there may restart a
    frame late)."""
    lo = info.first_frame
    out = {d[0] - lo for d in info.input_dropouts}
    for a, b, _ in info.missing_parts:
        out |= set(range(a - 1 - lo, b + 2 - lo))
    return out


def _off_input_lines(info: ConversionInfo, T: int) -> list:
    """The summary's lines on the converted surface off the input (``ConversionInfo.off_input``):
    mean and worst; a warning where, besides the web and the buried faces (said on their own) and
    away from the input's dropouts and missing parts (a part the template keeps), over POOR_OFF of
    it is off the input."""
    off = np.asarray(info.off_input, float)
    if off.size != T or not off.size or off.max() <= 0:
        return []
    worst = int(np.argmax(off))
    lines = [f"off the input (converted surface farther than {100 * WEB_GAP:.0f}% of the diagonal from it, fraction of "
             f"its area): mean {100 * off.mean():.2f}%, worst {100 * off[worst]:.2f}% at frame {worst}"]
    stretched = np.zeros(T)
    for name in ("web", "buried"):
        x = np.asarray(getattr(info, name), float)
        if x.size == T:
            stretched += x
    known = _dropout_frames(info) | {t - info.first_frame for t in info.bridged_frames}
    poor = [t for t in np.flatnonzero(off - stretched > POOR_OFF) if int(t) not in known]
    if poor:
        lines.append(f"warning: off the input on {len(poor)} frame(s) ({_frames_text(poor)}): over {100 * POOR_OFF:.0f}% "
                     f"of the converted surface lies farther than {100 * WEB_GAP:.0f}% of the diagonal from the input, "
                     "unstretched (not a web): the fit lost the input there (crumpled into it, folded, or the motion "
                     "between frames too fast to follow), or the input lacks that surface there (a part out of view); "
                     "look at those frames (--key-frame, or a higher frame rate)")
    return lines


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
        if info.seconds_all > ALL_SECONDS_SHOWN * sum(info.frame_seconds):
            # the runs not kept (key trials, a segment's trial, a floater retry) and the analyses: a
            # new user's summary said 4.9 s of a conversion that took 10.7 s
            lines[0] += f" ({info.seconds_all:.2f} s in all, with the runs not kept)"
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
                     "is much smaller than the whole (a static floor or background, or a still body whose limbs alone "
                     "move): its graph nodes are spaced "
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
    rp = info.removed_parts
    if rp:
        lines.append(f"note: removed {sum(x[1] for x in rp)} input part(s) under min_part_area="
                     f"{float(info.options.get('min_part_area', 0)):g} of their frame's area ({sum(x[2] for x in rp)} "
                     f"vertices) from {len(rp)} frame(s) before the conversion; the figures here are against the "
                     "input without them (a real small part removed so shows in none of them)")
    tiny = max(info.tiny_parts, default=0)
    if tiny >= TINY_PARTS and not float(info.options.get("min_part_area", 0) or 0):
        lines.append(f"warning: the template keeps {tiny} tiny separate parts (each under {100 * TINY_PART_AREA:g}% of "
                     "its area): if they are a reconstruction's debris, they move as surface the spheres meet; "
                     f"--option min_part_area={TINY_PART_AREA:g} removes such parts from every frame before the "
                     "conversion")
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
        ar = np.asarray(info.area_ratio, float)
        if ar.size == fl.size and folds.size:  # with extra area: a fold or a crumple, warned of
            grown = folds[(ar[folds] > FOLD_AREA) & (ar[folds] <= POOR_AREA)]
            if grown.size:
                w = int(grown[np.argmax(fl[grown])])
                lines.append(f"warning: on {grown.size} frame(s) ({_frames_text(grown)}) over {100 * POOR_FLIPPED:.0f}% "
                             f"of the converted surface faces against the input and its area is over {FOLD_AREA:g}x the "
                             f"input's (frame {w}: {100 * fl[w]:.1f}%, {ar[w]:.2f}x): folded or crumpled there (a sheet "
                             "doubled back, a template from a larger pose squeezed into a smaller one); spheres meet "
                             "the folded layers. A key frame among those frames (--key-frame N) may follow them better")
                folds = np.setdiff1d(folds, grown)
        if folds.size:  # a note, not a warning: thin parts read as much (docs/conversion.md, Folds)
            lines.append(f"note: over {100 * POOR_FLIPPED:.0f}% of the converted surface faces against the input on "
                         f"{folds.size} frame(s) ({_frames_text(folds)}): a fold-over (a sheet's free edge doubled "
                         "back), parts of the template slid onto other parts (limbs trading places), or many thin "
                         "parts, which read so too; look at those frames")
    lines += _off_input_lines(info, cov.size)
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
            which = (f"input frames {a}-{b} (the first {b - a + 1}) lack a part that frame {b + 1} "
                     f"has (the surface's area {100 * lost:.0f}% smaller before frame {b + 1}): a part that enters, or a "
                     "reconstruction's dropout at the start?")
        elif b == last:
            which = (f"input frames {a}-{b} (the last {b - a + 1}) lack a part that frame {a - 1} "
                     f"has (the surface's area {100 * lost:.0f}% smaller from frame {a}): a part that leaves, or a "
                     "reconstruction's dropout at the end?")
        else:
            which = (f"input frames {a}-{b} ({b - a + 1} frames) lack a part that frames {a - 1} and {b + 1} have (the "
                     f"surface's area {100 * lost:.0f}% smaller from frame {a}, back at frame {b + 1}): a "
                     f"reconstruction's dropout longer than the {DROPOUT_FRAMES} frames that are bridged (or a part "
                     "withdrawn into the body)?")
        lines.append(f"note: {which} One template keeps the part: the output presses it onto what is left there, a "
                     "sphere resting on it falls through, and the surface jumps where the fit loses or regains it")
        key = next((k for s, e, k, _ in info.segments if s <= a < e), info.key_frame)  # the run's template's
        if a <= key <= b:
            lines.append(f"warning: the key frame {key} is one of frames {a}-{b}: the template, made from "
                         "it, lacks the part on every frame; choose another key frame (--key-frame)")
    m = np.asarray(info.frame_motion, float)
    jumps = _jumps(m) if m.size == cov.size else np.zeros(0, int)
    if jumps.size and len(info.input_motion) == cov.size:  # the input's own jump is motion, not a fault
        jumps = jumps[np.asarray(info.input_motion, float)[jumps] < JUMP_INPUT * m[jumps]]
    if jumps.size:
        w = int(jumps[np.argmax(m[jumps])])
        drop = _dropout_frames(info)  # (jumps count from the first frame)
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
    # the cuts tried and rejected: "a new template from frame 9", and what was kept (a cut tried inside
    # one of several segments: those segments stay; it said "so one was kept" beside "3 segments", a
    # new user's)
    cuts = (("a new template from frame " if len(info.rejected_cuts) == 1 else "new templates from frames ")
            + ", ".join(str(a) for a, _ in info.rejected_cuts))
    kept = "so one was kept" if not segs else f"so the {len(segs)} templates above were kept"
    if info.rejected_cuts and not poor_web.size:
        # tried where the fit was poor by its buried faces: said too (a new user's was not)
        lines.append(f"{cuts} (tried where the surface was pressed into the input or stretched across its gaps) "
                     f"fitted no better, {kept}")
    if poor_web.size:
        if info.rejected_cuts:
            then = f"; {cuts} fitted no better where tried, {kept}"
        elif segs:
            then = ""
        elif _stretched_far(info)[poor_web].max() <= CUT_WEB:
            then = (f"; a new template (segment) is tried only where it is over {100 * CUT_WEB:.0f}% (a template change "
                    "costs the correspondence there)")
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
