"""The options of each conversion strategy as typed models (issue 13): one home for their
defaults and ranges, used by ``to_fixed_topology``, ``convert --option`` and the scene schema
(``surface.conversion.options``), so a bad option is reported the same way everywhere and at
the boundary where it enters (the scene file, the command line, the library call).

``ConversionOptions`` is a discriminated union on ``strategy`` (pydantic); ``options_for`` checks
a strategy's options and returns its model. Lengths are fractions of the template's bbox
diagonal; angles in degrees. docs/conversion.md says what each option does.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, TypeAdapter, ValidationError

from .choices import STRATEGIES
from .kernels.register import MAX_NODES_PER_VERTEX

__all__ = ["ProjectionOptions", "TrackingOptions", "RegularizedOptions", "GraphOptions", "ConversionOptions",
           "options_for", "option_defaults", "CG_ITERATIONS", "CG_TOLERANCE"]

#: the graph fit's per-iteration linear solve (conjugate gradients, warm-started): iteration cap
#: and relative-residual tolerance (one home; deform_graph.GraphFitter takes them from here)
CG_ITERATIONS = 32
CG_TOLERANCE = 1e-5


def _no_bool(v):
    if isinstance(v, bool):
        raise ValueError("a boolean is not a number")
    return v


def _key_frame(v):
    if v is None or (isinstance(v, str) and v == "auto"):
        return v
    if isinstance(v, bool) or not isinstance(v, int) and not (hasattr(v, "__index__") and not isinstance(v, float)):
        raise ValueError("not a frame index")
    return int(v)


Int = Annotated[int, BeforeValidator(_no_bool)]
#: the most iterations, rounds, passes or candidates any count option takes: far above any useful
#: setting (the defaults are 1-16), low enough that a frame always ends (a new user's
#: ``--iterations 1000000000`` ran on past a SIGTERM, which stops at the next frame)
MAX_COUNT = 10_000
#: a count of iterations (rounds, passes, candidates): a whole number up to MAX_COUNT
Count = Annotated[int, BeforeValidator(_no_bool), Field(le=MAX_COUNT)]
Float = Annotated[float, BeforeValidator(_no_bool)]
Fraction = Annotated[float, BeforeValidator(_no_bool), Field(ge=0.0, le=1.0)]
KeyFrame = Annotated[Union[Literal["auto"], int, None], BeforeValidator(_key_frame)]


class _Options(BaseModel):
    """Options every strategy takes."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    #: the template must lie mostly within this distance of the first frame (fraction of its diagonal)
    max_template_distance: Float = Field(0.25, gt=0.0)
    #: frames whose bbox diagonal differs from the median by more than this factor are warned about
    scale_tolerance: Float = Field(4.0, gt=0.0)
    #: the frame the template comes from and tracking starts at: "auto" (largest surface area, with the
    #: rules of ``convert_input._key_frame``: a finer frame of about that area is preferred) or an index
    key_frame: KeyFrame = "auto"
    #: the most templates ``to_piecewise_fixed`` (and ``convert``) may use: a new one starts where
    #: one template cannot follow the input (a web across parts it fused, a lost part); 1: one
    #: template for every frame (``to_fixed_topology`` always keeps one)
    max_segments: Int = Field(4, ge=1)
    #: input parts (connected components) with less than this fraction of the frame's surface area
    #: that lie wholly farther than ``far_part_gap`` from the previous converted frame are left out
    #: of the fit (floaters: the template has no part for them, a pull would grow a spike); 0 (the
    #: default): never, since fragments of a thin part the fit has lost look the same and their
    #: pull is what recovers it (docs/conversion.md#floaters); 0.05 for floater-laden input
    far_part_area: Fraction = 0.0
    #: with far_part_area 0: when the web of some frames reaches out to small separate input parts
    #: (convert._floater_webs: a floater pulls a spike of stretched faces, a real part's fragment
    #: does not), convert again with far_part_area = convert.FLOATER_AREA and keep the less poor run
    floater_retry: bool = True
    #: input frames (up to convert.DROPOUT_FRAMES in a row) that lack surface the frames either
    #: side both have (ConversionInfo.input_dropouts: a reconstruction's dropout, a new user's leg
    #: cut off one frame) are bridged in the output: their converted frames are blended from the
    #: two either side (the part kept, no jump), and the fit of the frame after them starts from
    #: the frame before them; false: the output follows the input
    bridge_dropouts: bool = True
    #: the gap for ``far_part_area`` (fraction of the converted mesh's bbox diagonal)
    far_part_gap: Float = Field(0.10, gt=0.0)
    #: input parts (connected components) with less than this fraction of their frame's surface
    #: area are removed from every frame before the conversion, wherever they lie (a
    #: reconstruction's debris: a new user's 200 tetrahedra of 1 cm a frame all became flying
    #: template parts); the largest part of a frame never is. 0 (the default): none, since thin
    #: parts break into small fragments at a reconstruction's error (docs/conversion.md#floaters)
    min_part_area: Fraction = 0.0
    #: bit-identical results from run to run on a GPU: the conversion kernels' float atomic sums
    #: are reduced in a fixed order (Warp's deterministic mode, RUN_TO_RUN: the same GPU model).
    #: The CPU is deterministic either way. Off by default: 4.3-4.9x the time on an H100 (200
    #: frames of a 10k-vertex template: 28-32 s against 6.6-6.8 s). docs/conversion.md
    #: ("Speed with larger templates, and repeatability on the GPU")
    deterministic: bool = False


class _FineStage(BaseModel):
    """The full-resolution refinement ``regularized`` and ``graph`` share."""

    smooth_iterations: Count = Field(10, ge=0)
    smooth_weight: Fraction = 0.5
    pull_fraction: Fraction = 0.5
    relax_iterations: Count = Field(3, ge=0)
    relax_step: Fraction = 1.0
    normal_slack: Float = Field(3.0, ge=1.0)


class ProjectionOptions(_Options):
    strategy: Literal["projection"] = "projection"


class TrackingOptions(_Options):
    strategy: Literal["tracking"] = "tracking"
    #: re-project onto the frame every this many frames (0 or None: never)
    reanchor_interval: Annotated[Int, BeforeValidator(lambda v: 0 if v is None else v), Field(ge=0)] = 50
    tracked_weight: Fraction = 0.8


class RegularizedOptions(_Options, _FineStage):
    strategy: Literal["regularized"] = "regularized"
    iterations: Count = Field(3, ge=0)
    rigid_iterations: Count = Field(3, ge=0)
    reinit_threshold: Float = Field(0.005, ge=0.0)
    max_iterations: Count = Field(6, ge=0)
    refine_threshold: Float = Field(0.002, ge=0.0)
    bank_interval: Int = Field(5, ge=0)
    reinit_samples: Int = Field(1024, ge=1)


class GraphOptions(_Options, _FineStage):
    strategy: Literal["graph"] = "graph"
    # the deformation graph (dynmesh_warp.deform_graph)
    node_spacing: Float = Field(0.03, gt=0.0, le=1.0)
    #: node spacing from the diagonal of the part that moves (within its box) where that part is
    #: much smaller than the whole template: a capture's static floor or background otherwise
    #: coarsens the graph on the subject (docs/conversion.md, "A static floor in the capture")
    adaptive_spacing: bool = True
    nodes_per_vertex: Int = Field(4, ge=1, le=MAX_NODES_PER_VERTEX)
    graph_iterations: Count = Field(8, ge=1)
    #: at most this many more graph iterations in all: a level of the stiffness schedule is held
    #: while its last iteration still moved a node by more than converge_tolerance x the node
    #: spacing (large motion between frames: a new user's fast banana +57 % -> +2 % CD; issue 12's
    #: protocol pcow +9 -> +4 %, chicken's coverage lost 11.2 -> 7.9 %, the rest unchanged;
    #: docs/conversion.md, "Held stiffness levels"); 0: the schedule alone
    converge_iterations: Count = Field(16, ge=0)
    converge_tolerance: Float = Field(0.3, gt=0.0)
    #: the rigid start: each part of the template (a connected piece of the graph) moved from its
    #: predicted pose by the rigid motion that fits it to the frame (symmetric point-to-plane ICP)
    #: before the graph fit, so that a turning body does not lag and slide along its surface; kept
    #: only along what the part's surface shows, where it fits clearly better, and not for a part
    #: the static hold holds (docs/conversion.md, "The rigid start"): Gauss-Newton steps at most (0: off)
    rigid_iterations: Count = Field(6, ge=0)
    stiffness: Float = Field(10.0, ge=0.0)
    stiffness_end: Float = Field(0.3, ge=0.0)
    damping: Float = Field(0.01, ge=0.0)
    #: the static hold (0: off): where the input surface did not move between the frame before
    #: and this one (every template vertex of a node and of the nodes within STATIC_RINGS graph
    #: edges lies, as the last fit left it, within static_tolerance x the diagonal of this frame's
    #: surface), and no rigid motion of the moving parts around that still region would carry it
    #: along its own surface (convert._Converter._still_regions), the node starts from where it was
    #: (not the constant-velocity prediction) and is held there with this weight (per node, as
    #: damping). A new user's still torso turned 53 degrees with its legs swinging (22 held); the
    #: first hold, without the region test, also froze surfaces that move along themselves (a long
    #: cylinder along its axis: slide 1.2 -> 13 % of the diagonal; now 1.2 %). On by default since
    #: the region test (issue 12's protocol the same or within a point of CD, docs/conversion.md,
    #: "Still parts")
    static_hold: Float = Field(1.0, ge=0.0)
    static_tolerance: Float = Field(0.004, ge=0.0)
    max_normal_angle: Float = Field(60.0, ge=0.0, le=180.0)
    predict: Float = Field(1.0, ge=0.0)
    #: start poses tried per frame: the prediction scaled by k / (n - 1), k = 0 .. n - 1 (0: the
    #: previous pose), the one with the lowest two-sided fit score kept (1: the prediction alone)
    predict_candidates: Count = Field(1, ge=1)
    #: samples per side of that score
    reinit_samples: Int = Field(1024, ge=1)
    restart_threshold: Float = Field(0.02, ge=0.0)
    #: the drift control also restarts a frame whose fit stretches more than convert.POOR_WEB of
    #: its area across a gap of the input (the web: the residual of the other side, which the
    #: coverage does not see); candidates are then ranked by the worse of the two. docs/conversion.md
    restart_on_web: bool = True
    #: restart candidates fitted in full: the ones whose start pose already fits the frame best
    #: (two-sided score); 0: every candidate (previous pose, the last 3 banked states, the template).
    #: 2 (was 0): the same accuracy on every sequence of issue 12's protocol (pcow +38 -> +36 %,
    #: others unchanged; noise-free too) and 14 % less time on the restart-heavy speed input (CPU:
    #: 181 -> 156 s for 200 frames); 1 lost pcow (+60 %). docs/conversion.md
    restart_fits: Count = Field(2, ge=0)
    refine_rounds: Count = Field(2, ge=0)
    #: when the run from the automatic key frame leaves frames poorly covered (coverage above
    #: convert.POOR_COVERAGE on convert.KEY_RETRY_POOR_FRAMES of them) or its coverage drifts
    #: away from the key frame (convert.DRIFT_RATIO), the conversion is run
    #: again from this many key frames spread
    #: evenly over the sequence (frame T (i + 1/2) / n) and the run with the least mean Chamfer
    #: distance to the input frames is kept (a GT-free score that ranks the runs like their true
    #: error; docs/conversion.md);
    #: 0: never. Not with a chosen key_frame or a given template.
    key_candidates: Count = Field(4, ge=0)
    #: run the key-frame trials whatever the first run's coverage (an accurate mode, off by
    #: default: ~5x the time where the first run covers every frame). Issue 12's protocol, CPU,
    #: 1 % error: CD vs the input +0 / +2 / +5 / +7 / -2 % (gallop, collapse, pcow, chicken,
    #: figure); the defaults, whose drift trigger runs the trials on collapse and pcow only,
    #: -1 / +2 / +5 / +7 / -2 %; docs/conversion.md
    always_try_keys: bool = False
    # bidirectional repair: re-track runs of poorly covered frames from the other side (off: on
    # pcow it lowered the worst uncovered vertex 13.6 -> 12.3 % but not the CD, +58 -> +60 %)
    repair_passes: Count = Field(0, ge=0)
    #: coverage above which a frame is poor; 0: max(restart_threshold, 2 x the median)
    repair_threshold: Float = Field(0.0, ge=0.0)
    bank_interval: Int = Field(10, ge=0)
    cg_iterations: Count = Field(CG_ITERATIONS, ge=1)
    cg_tolerance: Float = Field(CG_TOLERANCE, ge=0.0)
    # fine stage: 6 iterations (was 4), the backward (coverage) pull alone where a vertex has
    # one, each smoothed by 1 pass (was 3; 10 before that), one tangential relaxation (was 3).
    # Issue 12's protocol, CPU, each sequence from its automatic key frame (docs/conversion.md):
    # 4 -> 6 iterations with 3 -> 1 passes: chicken_crossing +14.2 -> +11.4 %, pcow +35.8 ->
    # +30.2 %, horse_collapse +10.0 -> +8.9 %, horse_gallop +1.2 -> +0.8 %, figure -2.3 -> -2.4 %
    # (at 0-20 % more time); the round before: chicken +24 -> +14 %, pcow +67 -> +38 %
    iterations: Count = Field(6, ge=0)
    pull_fraction: Fraction = 1.0
    smooth_iterations: Count = Field(1, ge=0)
    # no tangential relaxation (was 1): it slid vertices off the parts the backward pull had
    # just reached. Issue 12's protocol, CPU, with the drift trigger of the key trials: 1 % error
    # CD vs the input (horse_gallop, horse_collapse, pcow, chicken, figure) and the speed input
    # in docs/conversion.md ("No tangential relaxation")
    relax_iterations: Count = Field(0, ge=0)


ConversionOptions = Annotated[Union[ProjectionOptions, TrackingOptions, RegularizedOptions, GraphOptions],
                              Field(discriminator="strategy")]
_ADAPTER = TypeAdapter(ConversionOptions)
_MODELS = {m.model_fields["strategy"].default: m
           for m in (ProjectionOptions, TrackingOptions, RegularizedOptions, GraphOptions)}
assert set(_MODELS) == set(STRATEGIES)


def _domain(field) -> str:
    """What a field accepts, in words, from its annotation and constraints."""
    lo = hi = None
    lo_open = hi_open = False
    for m in field.metadata:
        if getattr(m, "ge", None) is not None:
            lo = m.ge
        if getattr(m, "gt", None) is not None:
            lo, lo_open = m.gt, True
        if getattr(m, "le", None) is not None:
            hi = m.le
        if getattr(m, "lt", None) is not None:
            hi, hi_open = m.lt, True
    if field.annotation is bool:
        return "be true or false"
    if field.annotation is int:
        kind = "be an integer"
    elif field.annotation is float:
        kind = "be a finite number"
    else:
        return "be 'auto' or a frame index"
    if field.annotation is int and lo is not None and hi == MAX_COUNT:  # a count: what it is, then the cap
        return f"{kind} {'>' if lo_open else '>='} {lo:g} (at most {hi:g})"
    if lo is not None and hi is not None:
        return f"lie in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{kind} {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"{kind} {'<' if hi_open else '<='} {hi:g}"
    return kind


def options_for(strategy, /, **options) -> GraphOptions | RegularizedOptions | TrackingOptions | ProjectionOptions:
    """The options of ``strategy`` (a :class:`~dynmesh_warp.choices.Strategy` or its name), the
    defaults filled in. Raises ``ValueError`` for an unknown strategy or a value out of its
    range ("<name> must lie in [0, 1], got 2"), ``TypeError`` for an option the strategy does
    not have (naming the valid ones)."""
    strategy = str(getattr(strategy, "value", strategy))
    if strategy not in _MODELS:
        raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    model = _MODELS[strategy]
    unknown = sorted(set(options) - set(model.model_fields) | ({"strategy"} & set(options)))
    if unknown:
        import difflib

        valid = sorted(k for k in model.model_fields if k != "strategy")
        near = [m for u in unknown for m in difflib.get_close_matches(u, valid, n=1)]  # refine_round: refine_rounds
        raise TypeError(f"to_fixed_topology(strategy={strategy!r}): unknown option(s) {unknown}"
                        + (f"; did you mean {', '.join(near)}?" if near else "") + f"; valid: {valid}")
    try:
        return _ADAPTER.validate_python({"strategy": strategy, **options})
    except ValidationError as e:
        err = e.errors()[0]
        name = str(err["loc"][1]) if len(err["loc"]) > 1 else "options"
        field = model.model_fields.get(name)
        what = _domain(field) if field is not None else "be valid"
        raise ValueError(f"{name} must {what}, got {options.get(name)!r}") from None


def option_defaults(strategy) -> dict:
    """The default options of ``strategy`` as a dict (``strategy`` included)."""
    return options_for(strategy).model_dump()
