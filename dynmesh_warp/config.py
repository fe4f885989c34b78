"""Scene description (YAML) and its validation, with pydantic.

See ``docs/scene.md`` for the schema. Relative paths are resolved against the YAML file's
folder. Unknown keys, wrong types and missing files are reported with the YAML path of the
offending field (for example ``physics.dt: Input should be greater than 0``).
"""

from __future__ import annotations

import functools
import math
import types
import typing
from pathlib import Path
from typing import Literal, Optional, Union

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .choices import (
    DEFAULT_COLLIDER,
    DEFAULT_FRAME_ORDER,
    DEFAULT_NEWTON_SOLVER,
    DEFAULT_COLOR_SOURCE,
    DEFAULT_ORIENTATION,
    DEFAULT_PLAYBACK,
    DEFAULT_REBUILD_EVERY,
    DEFAULT_SPHERE_BODY,
    DEFAULT_STRATEGY,
    DEFAULT_UP_AXIS,
    Collider,
    FrameOrder,
    SphereBody,
    NewtonSolver,
    ColorSource,
    Orientation,
    Playback,
    RebuildEvery,
    Strategy,
    SweptSearch,
    UpAxis,
)
from .mesh_formats import MESH_EXTENSIONS, UNREAD_ANIMATIONS, file_problem
from .sequence import FPS_RANGE

__all__ = ["SceneConfig", "SceneError", "load_scene_config", "scene_config", "apply_overrides", "DEFAULT_SCENE",
           "DEFAULT_SCENE_FILE",
           "parse_assignment", "Vec3", "PhysicsCore", "load_yaml",
           "DEFAULT_MAX_SUBSTEPS", "DEFAULT_MAX_TOTAL_SUBSTEPS"]

Vec3 = tuple[float, float, float]

#: default bound on sub-steps per physics step (physics.max_substeps; measured, see docs/scene.md)
DEFAULT_MAX_SUBSTEPS = 64
#: default bound on the sub-steps of a whole run (run.max_total_substeps; see docs/scene.md)
DEFAULT_MAX_TOTAL_SUBSTEPS = 10_000_000


#: the largest envs.time_offset [s]: ~30 years; far beyond it a clock's step (1/240 s) is lost
#: to float64 rounding and every env would see one frozen frame
MAX_TIME_OFFSET = 1.0e9

class SceneError(ValueError):
    """The scene file is missing, unreadable or does not match the schema."""


@functools.lru_cache(maxsize=None)
def _numeric(annotation) -> bool:
    """Whether a field's type holds only numbers (int, float, None, tuples of them: Vec3); once
    per type (the validator asks on every field of every validation)."""
    if annotation in (int, float):
        return True
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return bool(args) and all(_numeric(a) for a in args)
    if origin is tuple:
        return all(_numeric(a) for a in typing.get_args(annotation) if a is not Ellipsis)
    return False


class _Strict(BaseModel):
    # every float of a scene (and of PhysicsParams) must be finite: NaN/inf are refused naming the field
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_booleans_for_numbers(cls, v, info):
        """A boolean where a number goes is refused (``spheres.count: true`` ran one sphere; a
        new user's). Quoted numbers stay accepted: YAML reads ``1e-3`` as a string."""
        field = cls.model_fields.get(info.field_name)
        if field is not None and _numeric(field.annotation):
            for x in (v if isinstance(v, (list, tuple)) else (v,)):
                if isinstance(x, bool):
                    raise ValueError(f"a number is expected, not the boolean {str(x).lower()}")
        return v


class ConversionConfig(_Strict):
    """Turn a varying-topology input into a fixed-topology mesh before simulating."""

    strategy: Strategy = DEFAULT_STRATEGY
    template: Optional[str] = None  # a mesh file; default: the key frame (options.key_frame; auto: largest area)
    #: the strategy's options (conversion_options: names, defaults and ranges), checked here
    options: dict = Field(default_factory=dict)

    @field_validator("options")
    @classmethod
    def _check_options(cls, v: dict, info):
        from .conversion_options import options_for

        try:
            options_for(info.data.get("strategy", DEFAULT_STRATEGY), **v)
        except (TypeError, ValueError) as e:  # TypeError (unknown name) too: pydantic reports ValueErrors
            raise ValueError(str(e)) from None
        return v


#: the largest ``surface.upsample`` (frames played per input frame)
MAX_UPSAMPLE = 100


class SurfaceConfig(_Strict):
    source: str = Field(default="builtin:wave_bowl", min_length=1)  # "" resolved to the scene's own folder
    params: dict = Field(default_factory=dict)  # keyword arguments of a built-in generator
    subdir: Optional[str] = None  # DG-Mesh scene folder: dynamic_mesh | mesh_gt
    topology: Optional[str] = None  # a vertex-only source's faces (.pc2/.mdd/.npy/npz): a mesh file (default: <stem>.*)
    animation: Optional[Union[str, int]] = None  # an animated .glb/.gltf source: the animation's name or index
    fps: Optional[float] = Field(default=None, ge=FPS_RANGE[0], le=FPS_RANGE[1])
    frame_order: FrameOrder = DEFAULT_FRAME_ORDER  # text_sorted: undo 1, 10, 11, ..., 2, ...
    playback: Playback = DEFAULT_PLAYBACK
    interpolate: bool = True
    # frames played per input frame, on a C1 curve through them (FixedTopologySequence.upsampled):
    # 1 plays the input as it is; 10 makes 24 fps data 240 fps (docs/physics.md, the data's frame rate)
    upsample: int = Field(default=1, ge=1, le=MAX_UPSAMPLE)
    up_axis: UpAxis = DEFAULT_UP_AXIS
    scale: float = Field(default=1.0, gt=0)
    translate: Vec3 = (0.0, 0.0, 0.0)
    # auto: a closed mesh whose triangles face inward is flipped (with a warning); keep; flip
    orientation: Orientation = DEFAULT_ORIENTATION
    conversion: Optional[ConversionConfig] = None


class SphereConfig(_Strict):
    position: Vec3
    velocity: Vec3 = (0.0, 0.0, 0.0)
    radius: float = Field(default=0.05, gt=0)
    mass: float = Field(default=1.0, ge=0)


class SpawnConfig(_Strict):
    """Spheres dropped above the surface's first frame at seeded random spots."""

    count: int = Field(default=5, ge=0)
    radius: float = Field(default=0.05, gt=0)
    mass: float = Field(default=1.0, ge=0)
    height: float = Field(default=0.3, ge=0)  # above the highest surface point [m]
    spread: float = Field(default=0.6, gt=0, le=1)  # fraction of the horizontal extent used
    seed: int = 0


#: the largest gravity a scene takes [m/s^2] (1,000 g)
MAX_GRAVITY = 1.0e4


#: ``physics.ground`` (the plane z = height) needs gravity within 45 degrees of -z (cos of that)
GROUND_GRAVITY_COS = math.cos(math.radians(45.0))


class PhysicsCore(_Strict):
    """Physics settings shared by the scene's ``physics:`` section and the Python API's
    :class:`~dynmesh_warp.world.PhysicsParams`: one place for their types, ranges and defaults
    (validated on construction and on assignment; NaN/inf refused)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)

    dt: float = Field(default=1.0 / 240.0, gt=0)
    substeps: int = Field(default=1, ge=1)
    # the most sub-steps per step the sub-step rule may reach (None: no bound); see docs/scene.md
    max_substeps: Optional[int] = Field(default=DEFAULT_MAX_SUBSTEPS, ge=1)
    auto_substeps: bool = True
    gravity: Vec3 = (0.0, 0.0, -9.81)
    restitution: float = Field(default=0.3, ge=0, le=1)
    friction: float = Field(default=0.5, ge=0)
    rest_speed: float = Field(default=0.2, ge=0)
    margin: float = Field(default=1.0e-3, ge=0)
    # how the swept collider searches a sphere's faces (None: the device's default,
    # choices.DEFAULT_SWEPT_SEARCH); docs/physics.md#the-swept-collider
    swept_search: Optional[SweptSearch] = None
    # what a sphere is as a body: point (no rotation), solid or shell (friction spins it, so it
    # rolls); docs/physics.md#rolling
    sphere_body: SphereBody = DEFAULT_SPHERE_BODY

    @field_validator("gravity")
    @classmethod
    def _gravity_within_bound(cls, g):
        # a new user's [0, 0, -3e38] ran with exit 0 and positions of 1e37 m
        if math.hypot(*g) > MAX_GRAVITY:
            raise ValueError(f"|gravity| {math.hypot(*g):.3g} m/s^2 is over {MAX_GRAVITY:g} m/s^2 (the scene is in "
                             "metres and seconds: 9.81 is Earth's)")
        return g

    @model_validator(mode="after")
    def _substeps_within_bound(self):
        if self.max_substeps is not None and self.substeps > self.max_substeps:
            raise ValueError(f"substeps {self.substeps} exceeds max_substeps {self.max_substeps} (the work "
                             "budget, see docs/scene.md); lower substeps, or raise max_substeps (null: no bound)")
        return self


#: the ``physics:`` keys only the built-in world reads: a scene with a ``newton:`` section warns of them
NEWTON_IGNORES = frozenset({"collider", "rebuild_every", "rest_speed", "margin", "swept_search", "sphere_body"})


class PhysicsConfig(PhysicsCore):
    ground: Optional[Union[float, Literal["auto"]]] = None  # ground plane z = height [m]; auto: lowest surface point
    collider: Collider = DEFAULT_COLLIDER
    rebuild_every: RebuildEvery = DEFAULT_REBUILD_EVERY

    @model_validator(mode="after")
    def _ground_across_gravity(self):
        # the ground is the plane z = height; under gravity along -y it stood parallel to the fall
        # and stopped nothing (a new user's sphere fell 19 m past it, its "fell past" note hushed)
        g = self.gravity
        n = math.hypot(*g)
        if self.ground is not None and n > 0 and -g[2] < GROUND_GRAVITY_COS * n:
            raise ValueError(f"ground: the ground is the plane z = height, for gravity along -z; gravity "
                             f"{list(g)} is {math.degrees(math.acos(max(-1.0, min(1.0, -g[2] / n)))):.0f} degrees from -z "
                             "(y-up data: surface.up_axis: y turns it z-up, with gravity [0, 0, -9.81]; or ground: null)")
        return self


#: placeholders allowed in ``run.output`` (filled from the scene's fields of the same name)
OUTPUT_PLACEHOLDERS = ("name",)


class RunConfig(_Strict):
    duration: Optional[float] = Field(default=5.0, gt=0)
    steps: Optional[int] = Field(default=None, ge=1)
    output: str = "out/{name}"
    record_every: int = Field(default=4, ge=1)
    # bound on steps x sub-steps of the whole run (None: no bound); the run stops before it starts
    max_total_substeps: Optional[int] = Field(default=DEFAULT_MAX_TOTAL_SUBSTEPS, ge=1)

    @field_validator("output")
    @classmethod
    def _placeholders_known(cls, v):
        import string

        valid = ", ".join("{" + k + "}" for k in OUTPUT_PLACEHOLDERS)
        try:
            fields = [f for _, f, _, _ in string.Formatter().parse(v) if f is not None]
        except ValueError as e:
            raise ValueError(f"{v!r}: {e} (write {{{{ and }}}} for literal braces; placeholders: {valid})") from None
        for f in fields:
            if f not in OUTPUT_PLACEHOLDERS:
                raise ValueError(f"{v!r}: unknown placeholder {{{f}}}; valid: {valid}")
        if not v.strip():
            raise ValueError("must be a non-empty folder path")
        return v

    @model_validator(mode="after")
    def _one_length(self):
        # both given: steps won without a word (the CLI refuses --duration with --steps)
        if {"duration", "steps"} <= self.model_fields_set and self.duration is not None and self.steps is not None:
            raise ValueError(f"give the run's length once: run.duration ({self.duration:g} s) or run.steps "
                             f"({self.steps}), not both (null the other)")
        return self


class GaussiansConfig(_Strict):
    """Rendering Gaussians bound to the surface (see docs/rendering.md)."""

    splats: Optional[str] = None  # a 3DGS .ply in the scene frame, bound to the first frame
    count: int = Field(default=20000, ge=0)  # generated on the surface when splats is null
    color: Vec3 = (0.75, 0.72, 0.68)  # RGB in [0, 1] of generated Gaussians where colors says so
    colors: ColorSource = DEFAULT_COLOR_SOURCE  # mesh: the surface's own vertex colours where it has them
    opacity: float = Field(default=0.9, gt=0, lt=1)
    seed: int = 0


class NewtonBodyConfig(_Strict):
    """A Newton body or articulated model on the surface (``newton:`` section; docs/newton.md)."""

    type: Literal["box", "sphere", "capsule", "mjcf", "urdf", "usd"]
    position: Vec3 = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)  # quaternion (x, y, z, w)
    velocity: Vec3 = (0.0, 0.0, 0.0)  # initial linear velocity of a box / sphere / capsule [m/s]
    half_extents: Optional[Vec3] = None  # box [m]
    radius: Optional[float] = Field(default=None, gt=0)  # sphere, capsule [m]
    half_height: Optional[float] = Field(default=None, gt=0)  # capsule, along its local z [m]
    density: float = Field(default=1000.0, gt=0)  # [kg/m^3]
    file: Optional[str] = None  # model file of mjcf / urdf / usd
    floating: bool = True  # free base (False: fixed to the world)
    options: dict = Field(default_factory=dict)  # more keyword arguments of add_mjcf / add_urdf / add_usd
    label: Optional[str] = None

    @field_validator("rotation")
    @classmethod
    def _unit_quaternion(cls, q):
        n = math.sqrt(sum(float(x) * float(x) for x in q))
        if not math.isfinite(n) or n < 1e-6:  # [0, 0, 0, 0] ran as the identity, unsaid
            raise ValueError(f"must be a rotation quaternion (x, y, z, w) of length 1, got {list(q)}")
        return tuple(float(x) / n for x in q)

    @model_validator(mode="after")
    def _fields_for_type(self):
        need = {"box": ["half_extents"], "sphere": ["radius"], "capsule": ["radius", "half_height"],
                "mjcf": ["file"], "urdf": ["file"], "usd": ["file"]}[self.type]
        missing = [k for k in need if getattr(self, k) is None]
        if missing:
            raise ValueError(f"a {self.type} body needs {', '.join(missing)}")
        if self.half_extents is not None and min(self.half_extents) <= 0:
            raise ValueError(f"half_extents must all be > 0, got {list(self.half_extents)}")
        unused = [k for k in ("half_extents", "radius", "half_height", "file")
                  if getattr(self, k) is not None and k not in need]
        if unused:
            raise ValueError(f"a {self.type} body does not use {', '.join(unused)}")
        # fields of the other kind of body, set: refused (a new user's were taken and dropped unsaid)
        primitive = self.type in ("box", "sphere", "capsule")
        if primitive and not self.floating:
            raise ValueError(f"floating: false fixes a model file's base (mjcf / urdf / usd); a {self.type} is always "
                             "a free body (it fell); a static obstacle belongs in the surface")
        if primitive and self.options:
            raise ValueError(f"options are keyword arguments of add_mjcf / add_urdf / add_usd; a {self.type} takes none")
        if not primitive and any(float(v) != 0.0 for v in self.velocity):
            raise ValueError(f"velocity is a box / sphere / capsule's initial velocity; a {self.type} model's bodies "
                             "start at rest (it was dropped)")
        if not primitive and "density" in self.model_fields_set:
            raise ValueError(f"density applies to a box / sphere / capsule; a {self.type} model's bodies keep the "
                             "file's masses (it was dropped)")
        return self


class NewtonConfig(_Strict):
    """Simulate the bodies with the Newton engine instead of the built-in sphere world."""

    solver: NewtonSolver = DEFAULT_NEWTON_SOLVER
    solver_options: dict = Field(default_factory=dict)  # keyword arguments of the solver
    bodies: list[NewtonBodyConfig] = Field(default_factory=list)
    include_spheres: bool = True  # the scene's ``spheres`` become Newton spheres too
    surface_mu: Optional[float] = Field(default=None, ge=0)  # default: physics.friction


class EnvsConfig(_Strict):
    """Batched environments (docs/envs.md): ``count`` copies of the scene's spheres, each env on
    the shared surface at its own clock. count 1 (the default) runs the single world."""

    count: int = Field(default=1, ge=1)
    #: each env's start time [s]: "random" (uniform over one playback of the sequence) or a number
    time_offset: Union[Literal["random"], float] = "random"
    #: each env's playback rate, uniform in [lo, hi] (1 = real time)
    rate: tuple[float, float] = (1.0, 1.0)
    seed: int = 0

    @field_validator("rate")
    @classmethod
    def _rate_ok(cls, v):
        lo, hi = v
        if not (0.0 <= lo <= hi):
            raise ValueError(f"must be [lo, hi] with 0 <= lo <= hi, got {list(v)}")
        return v

    @field_validator("time_offset")
    @classmethod
    def _offset_ok(cls, v):
        if v != "random" and not (math.isfinite(v) and v >= 0.0):  # -5 started every clock at -5 s
            raise ValueError(f"must be 'random' or a start time >= 0 [s], got {v!r}")
        if v != "random" and v > MAX_TIME_OFFSET:  # 1e30 froze every clock (t + dt == t), unsaid
            raise ValueError(f"must be at most {MAX_TIME_OFFSET:g} s (far beyond it float64 rounding loses the "
                             f"clocks' steps: 1e30 froze every env on one frame), got {v!r}")
        return v

    @model_validator(mode="after")
    def _batched_only(self):
        # count 1 runs the single world, which has one clock at 0 and rate 1: said, not dropped
        set_here = sorted(self.model_fields_set & {"time_offset", "rate"})
        if self.count == 1 and set_here and (self.time_offset != "random" and self.time_offset != 0.0
                                              or self.rate != (1.0, 1.0)):
            import warnings

            warnings.warn(f"envs.{', envs.'.join(set_here)}: only for batched envs (envs.count > 1, run --envs N); "
                          "with envs.count 1 the single world runs from t = 0 at rate 1", UserWarning, stacklevel=2)
        return self


class SceneConfig(_Strict):
    name: str = "scene"
    device: Optional[str] = None
    surface: SurfaceConfig = Field(default_factory=SurfaceConfig)
    spheres: Union[list[SphereConfig], SpawnConfig] = Field(default_factory=SpawnConfig)
    physics: PhysicsConfig = Field(default_factory=PhysicsConfig)
    run: RunConfig = Field(default_factory=RunConfig)
    gaussians: GaussiansConfig = Field(default_factory=GaussiansConfig)
    newton: Optional[NewtonConfig] = None  # run the bodies in Newton (docs/newton.md)
    envs: EnvsConfig = Field(default_factory=EnvsConfig)  # batched environments (docs/envs.md)
    base_dir: Optional[str] = Field(default=None, exclude=True)
    source_file: Optional[str] = Field(default=None, exclude=True)  # the YAML file, if any

    @field_validator("name")
    @classmethod
    def _name_ok(cls, v):
        # the name fills run.output's {name}: "out/.." would write over the folder above the outputs
        if not v or any(c in v for c in "/\\") or v in (".", "..") or any(ord(c) < 32 for c in v):
            raise ValueError("must be a non-empty name without path separators or control characters, "
                             "and not '.' or '..'")
        return v

    def resolve(self, p: str | None) -> Path | None:
        if p is None:
            return None
        try:
            path = Path(p).expanduser()
        except RuntimeError as e:  # "~nobody/x": no such user
            raise ValueError(f"{p}: cannot expand '~' ({e})") from None
        if not path.is_absolute() and self.base_dir:
            path = Path(self.base_dir) / path
        return path

    def inputs(self) -> list[Path]:
        """Every file or folder the scene reads (outputs must not touch them): the scene file,
        surface.source and .topology, surface.conversion.template, gaussians.splats, newton body files."""
        out = []
        if self.base_dir and self.source_file:
            out.append(Path(self.source_file))
        if not self.surface.source.startswith("builtin:"):
            out.append(self.resolve(self.surface.source))
        if self.surface.topology:
            out.append(self.resolve(self.surface.topology))
        if self.surface.conversion and self.surface.conversion.template:
            out.append(self.resolve(self.surface.conversion.template))
        if self.gaussians.splats:
            out.append(self.resolve(self.gaussians.splats))
        out += [self.resolve(b.file) for b in (self.newton.bodies if self.newton else []) if b.file]
        return out

    def output_path(self, output=None) -> Path:
        """The run's output folder: ``output`` if given, else ``run.output`` with ``{name}`` filled in."""
        return Path(output).expanduser() if output else self.resolve(self.run.output.format(**self.placeholders()))

    def placeholders(self) -> dict:
        return {k: getattr(self, k) for k in OUTPUT_PLACEHOLDERS}

    @model_validator(mode="after")
    def _files_exist(self):
        src = self.surface.source
        if not src.startswith("builtin:"):
            path = self.resolve(src)
            if not path.exists():
                raise ValueError(f"surface.source: file or folder not found: {path}")
        if self.surface.topology:
            from .animation_formats import CACHE_EXTENSIONS, VERTEX_ONLY_EXTENSIONS

            if src.startswith("builtin:") or Path(src).suffix.lower() not in VERTEX_ONLY_EXTENSIONS:
                raise ValueError(f"surface.topology: only for a vertex-only source (a point cache "
                                 f"{', '.join(CACHE_EXTENSIONS)}, an .npy or an npz of vertices), but surface.source "
                                 f"is {src!r}")
            topology = self.resolve(self.surface.topology)
            if why := file_problem(topology):
                raise ValueError(f"surface.topology: {why}: {topology}")
        if self.surface.animation is not None and (src.startswith("builtin:")
                                                    or Path(src).suffix.lower() not in (".glb", ".gltf")):
            raise ValueError(f"surface.animation: only for an animated .glb / .gltf source, but surface.source "
                             f"is {src!r}")
        if self.surface.conversion and self.surface.conversion.template:
            t = self.resolve(self.surface.conversion.template)
            if why := file_problem(t):
                raise ValueError(f"surface.conversion.template: {why}: {t}")
        if self.gaussians.splats and (why := file_problem(self.resolve(self.gaussians.splats))):
            raise ValueError(f"gaussians.splats: {why}: {self.resolve(self.gaussians.splats)}")
        if self.gaussians.splats and Path(self.gaussians.splats).suffix.lower() != ".ply":
            # run took an npz here and render refused it later (a new user's)
            raise ValueError(f"gaussians.splats: a 3D Gaussian splatting .ply is expected, got {self.gaussians.splats!r}")
        for i, b in enumerate(self.newton.bodies if self.newton else []):
            if b.file and (why := file_problem(self.resolve(b.file))):
                raise ValueError(f"newton.bodies.{i}.file: {why}: {self.resolve(b.file)}")
        return self


#: the packaged YAML of the built-in default scene (``python -m dynmesh_warp.run`` with no scene)
DEFAULT_SCENE_FILE = Path(__file__).with_name("default_scene.yaml")


_MISMATCH = {"list_type", "dict_type", "model_type", "model_attributes_type", "tuple_type"}


def _is_branch_tag(x) -> bool:
    """pydantic's name of a union branch in an error location (``SpawnConfig``,
    ``list[SphereConfig]``, ``literal['auto']``, ``float``), not a field name."""
    return isinstance(x, str) and (x[:1].isupper() or "[" in x or x in ("float", "int", "str", "bool"))


def _format_errors(err: ValidationError, origin: str) -> str:
    """One line per problem, at the field path. For a union field (``spheres``: a list or a
    mapping) the branch the user did not mean ("should be a valid list") is left out when the
    other branch has a more specific error, and alternatives at one path are joined."""
    errs = []
    for e in err.errors():
        loc = [x for x in e["loc"] if not _is_branch_tag(x)]
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"].removeprefix("Value error, ")
        key = str(loc[-1]) if loc else ""
        if e["type"] == "extra_forbidden" and ":" in key and not key.endswith(":"):
            # YAML reads {count:40} as the key "count:40" (a new user's --set spheres={count:40,radius:0.03})
            k, v = key.split(":", 1)
            msg += f" (YAML needs a space after the colon: {k}: {v})"
        errs.append((".".join(str(x) for x in loc), e["type"], msg,  # "": the scene's own checks name their field
                     any(_is_branch_tag(x) for x in e["loc"])))
    keep = [
        e for e in errs
        if not (e[3] and e[1] in _MISMATCH and any(
            f is not e and f[1] not in _MISMATCH and (f[0] + ".").startswith(e[0] + ".") for f in errs))
    ]
    merged: dict[str, list[str]] = {}
    for loc, _, msg, _ in keep:
        if msg not in merged.setdefault(loc, []):
            merged[loc].append(msg)
    at = {loc: f"{loc}: " if loc else "" for loc in merged}
    if len(merged) == 1:  # one problem: one line
        (loc, msgs), = merged.items()
        return f"{origin}: {at[loc]}{'; or: '.join(msgs)}"
    lines = [f"{origin}: invalid scene"]
    lines += [f"  {at[loc]}{'; or: '.join(msgs)}" for loc, msgs in merged.items()]
    return "\n".join(lines)


class DuplicateKeyError(yaml.YAMLError):
    """A YAML mapping gives one key twice."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """A safe YAML loader that refuses a key given twice in one mapping (PyYAML keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                continue  # the base loader reports unhashable keys
            if key in seen:
                raise DuplicateKeyError(
                    f"duplicate key {key!r} (lines {seen[key] + 1} and {key_node.start_mark.line + 1}); "
                    "a key may appear once per mapping")
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str):
    """Parse YAML with the safe loader, refusing duplicate keys."""
    return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)


#: the built-in default scene as a mapping (read once from :data:`DEFAULT_SCENE_FILE`)
DEFAULT_SCENE = load_yaml(DEFAULT_SCENE_FILE.read_text())


def parse_assignment(item, origin: str, expected: str) -> tuple[list[str], object]:
    """``"key.path=value"`` -> (["key", "path"], value parsed as YAML; "" when empty). A
    :class:`SceneError` naming ``origin`` and the item for a missing ``=`` or key (with the
    ``expected`` form) or a value that is not YAML."""
    key, sep, text = str(item).partition("=")
    parts = key.strip().split(".")
    if not sep or not all(p.strip() for p in parts):
        raise SceneError(f"{origin} {item!r}: expected {expected}")
    indexed = next((p for p in parts if "[" in p or "]" in p), None)
    if indexed is not None:  # a list item: not a key path (it read as an unknown key at the top)
        raise SceneError(f"{origin} {item!r}: {indexed.strip()!r} addresses a list item, which {origin} cannot set; "
                         "edit the list in the scene file (or set the whole list: KEY.PATH=[...])")
    try:
        value = load_yaml(text) if text.strip() else ""
    except yaml.YAMLError as e:
        raise SceneError(f"{origin} {item!r}: the value is not valid YAML ({' '.join(str(e).split())})") from None
    return parts, value


def apply_overrides(raw: dict, overrides, origin: str = "--set") -> dict:
    """``raw`` with each ``"key.path=value"`` of ``overrides`` set (the value parsed as YAML:
    ``physics.dt=0.002``, ``surface.playback=pingpong``, ``physics.gravity=[0, 0, -3]``,
    ``physics.ground=null``); intermediate mappings are created. The schema then validates the
    result, naming the field. A :class:`SceneError` for an override that cannot be applied."""
    raw = dict(raw)
    for item in overrides or ():
        parts, value = parse_assignment(item, origin, "KEY.PATH=VALUE, e.g. physics.dt=0.002")
        node = raw
        for depth, part in enumerate(parts[:-1]):
            child = node.get(part)
            if child is None:
                child = {}
            elif not isinstance(child, dict):
                where = ".".join(parts[:depth + 1])
                raise SceneError(f"{origin} {item!r}: {where} is a {type(child).__name__}, not a section")
            node[part] = child = dict(child)
            node = child
        node[parts[-1]] = value
    return raw


def scene_config(scene, default=None) -> SceneConfig:
    """The :class:`SceneConfig` of what a library call was given as its scene: a SceneConfig, a
    scene YAML's path or a dict of its sections (``None``: ``default``, a dict, else the
    built-in default scene); anything else is a ``TypeError`` naming what it got (a new user's
    path or dict failed with an AttributeError)."""
    if isinstance(scene, SceneConfig):
        return scene
    if scene is None:
        return load_scene_config(data=default)
    if isinstance(scene, dict):
        return load_scene_config(data=scene)
    if isinstance(scene, (str, Path)):
        return load_scene_config(scene)
    raise TypeError(f"scene: expected a SceneConfig (load_scene_config), a scene YAML's path or a dict of its "
                    f"sections, got {type(scene).__name__}")


def is_sequence_path(path) -> bool:
    """Whether ``path`` names a mesh sequence rather than a scene YAML: a folder, or a file (not
    .yaml / .yml) with an extension a sequence or mesh reader takes (docs/data.md), or of an
    animation format that is not read (Alembic, FBX, USD, ...: the sequence's loader says so and
    what to export; read as YAML, an empty .abc played the default scene with exit 0, a new user's)."""
    from .animation_formats import ANIMATION_EXTENSIONS, VERTEX_ONLY_EXTENSIONS

    path = Path(path).expanduser()
    suffix = path.suffix.lower()
    return path.is_dir() or (path.is_file() and suffix not in (".yaml", ".yml")
                             and (suffix in VERTEX_ONLY_EXTENSIONS or suffix in ANIMATION_EXTENSIONS
                                  or suffix in MESH_EXTENSIONS or suffix in UNREAD_ANIMATIONS))


def sequence_scene(path) -> dict:
    """The scene of a mesh sequence on its own (:func:`is_sequence_path`): the schema's defaults
    around it (five 5 cm spheres dropped on frame 0), named after it."""
    path = Path(path).expanduser().resolve()
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:  # the schema takes text ("<scene dict>: surface.source: Input should be a valid string")
        raise SceneError(f"{str(path)!r}: the file's name is not valid UTF-8 (the scene's "
                         "paths are text); rename it") from None
    return {"name": path.stem or "sequence", "surface": {"source": str(path)}}


def scene_source(scene) -> dict:
    """``load_scene_config``'s arguments for the CLIs' positional ``scene`` (``run``, ``render``):
    a YAML file as it is; a mesh sequence (:func:`is_sequence_path`) becomes a scene of its own
    (:func:`sequence_scene`: five 5 cm spheres dropped on frame 0, unless ``--set`` says otherwise;
    the CLI says so with :func:`say_sequence_scene` once the scene is loaded)."""
    if scene is None:
        return {"path": None}
    path = Path(scene).expanduser()
    if is_sequence_path(path):
        return {"path": None, "data": sequence_scene(path)}
    return {"path": path}


def say_sequence_scene(scene, cfg: SceneConfig) -> None:
    """The note on stderr for a mesh sequence given where a scene goes (:func:`scene_source`): the
    spheres the loaded scene ``cfg`` has (its ``--set`` applied: a new user's 40 spheres were said
    as 5) and how to change the rest (docs/scene.md). Nothing for a scene file."""
    import sys

    if scene is None or not is_sequence_path(scene) or Path(scene).suffix.lower() in UNREAD_ANIMATIONS:
        return  # (not for a format that is not read: its loader's error follows)
    sp = cfg.spheres
    if isinstance(sp, SpawnConfig):
        what = f"{sp.count} sphere{'s' if sp.count != 1 else ''} of radius {sp.radius:g} m dropped on it"
    else:
        what = f"the {len(sp)} sphere{'s' if len(sp) != 1 else ''} of spheres:"
    up = getattr(cfg.surface.up_axis, "value", cfg.surface.up_axis)
    axis = ("up axis auto: y for glTF, else z; other data: --set surface.up_axis=y or z" if up == "auto" else
            f"up axis {up}, as set")  # (it said auto where --set surface.up_axis=y had been given: a new user's)
    print(f"note: {scene} is a mesh sequence, not a scene file: playing it with {what} "
          f"({axis}; more in a scene YAML, docs/scene.md)", file=sys.stderr)


def load_scene_config(path: str | Path | None = None, data: dict | None = None, overrides=None) -> SceneConfig:
    """Read and validate a scene YAML file (or a dict); ``None`` gives the built-in default scene.
    A mesh sequence's path (a folder of frames, an .npz, .anime, .glb, ...: :func:`is_sequence_path`)
    gives the scene of that sequence on its own, as ``run`` plays it (:func:`sequence_scene`).
    ``overrides``: ``"key.path=value"`` strings (or one such string) applied before validation
    (:func:`apply_overrides`, the CLI's ``--set``)."""
    if isinstance(overrides, str):  # one override: it was iterated character by character
        overrides = [overrides]
    if path is not None and data is None and is_sequence_path(path):  # as the CLI (it read an npz as YAML)
        path, data = None, sequence_scene(path)
    if path is None:
        raw = dict(DEFAULT_SCENE if data is None else data)
        origin, base = "<default scene>" if data is None else "<scene dict>", None
    else:
        path = Path(path)
        origin = str(path)
        if not path.is_file():
            why = file_problem(path)
            raise SceneError(f"{path}: scene file not found" if why == "file not found" else f"{path}: {why}, not a "
                             "scene file (a scene YAML, a sequence file or a folder of frames)")
        try:
            raw = load_yaml(path.read_text())
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
            raise SceneError(f"{path}: cannot read scene YAML: {' '.join(str(e).split())}") from None
        except RecursionError:
            raise SceneError(f"{path}: cannot read scene YAML: nested too deeply") from None
        except Exception as e:  # a constructor's own error, e.g. a bad !!timestamp
            raise SceneError(f"{path}: cannot read scene YAML ({type(e).__name__}: {e})") from None
        if raw is None:  # an empty file: the schema's defaults, said (it ran the built-in scene silently)
            import warnings

            warnings.warn(f"{path}: the scene file is empty: the built-in default scene (docs/scene.md)", stacklevel=2)
            raw = {}
        if not isinstance(raw, dict):
            raise SceneError(f"{path}: a scene file is a YAML mapping of sections (surface:, spheres:, physics:, ...; "
                             f"docs/scene.md), this file's top level is a {type(raw).__name__}. A mesh sequence is given "
                             "as its file (.npz, .obj, .ply, .glb, ...) or a folder of frames")
        raw.setdefault("name", path.stem)
        base = str(path.parent.resolve())
    if overrides:
        raw = apply_overrides(raw, overrides)
        origin += " (with --set " + ", ".join(map(str, overrides)) + ")"
    try:
        return SceneConfig.model_validate({**raw, "base_dir": base,
                                           "source_file": None if path is None else str(path)})
    except ValidationError as e:
        raise SceneError(_format_errors(e, origin)) from None
    except OSError as e:  # a path the system refuses (name too long ...) while checking files
        raise SceneError(f"{origin}: invalid scene: a file path cannot be used: {e}") from None


def spawn_positions(cfg: SpawnConfig, V0: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Seeded drop positions above the surface points ``V0`` (N, 3) along ``up`` (3,), the
    scene's up (against gravity): spread over the points' extent across ``up``, the lowest
    ``height`` + ``radius`` above their highest point along it, the others stacked 2.5 radii
    apart (a new user's y-up floor with gravity along -y had its spheres spawned along +z, beside
    the floor). Along +z the positions are the same as before ``up`` was a vector."""
    from .geometry import frame_across

    rng = np.random.default_rng(cfg.seed)
    u = np.asarray(up, np.float64).reshape(3)
    u = u / np.linalg.norm(u) if np.linalg.norm(u) > 0 else np.array([0.0, 0.0, 1.0])
    k = int(np.argmax(np.abs(u)))
    if abs(u[k]) == 1.0:  # along an axis: that axis's coordinate, in the data's own frame
        basis, P = None, V0
    else:  # a frame with up as its third axis
        basis = frame_across(u)
        P, k = np.asarray(V0, np.float64) @ basis.T, 2
    sign = 1.0 if basis is not None or u[k] > 0 else -1.0
    lo, hi = P.min(0), P.max(0)
    c = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo) * cfg.spread
    pos = c + (rng.random((cfg.count, 3)) * 2 - 1) * half
    top = hi[k] if sign > 0 else lo[k]
    pos[:, k] = top + sign * (cfg.height + cfg.radius + np.arange(cfg.count) * 2.5 * cfg.radius)
    if basis is not None:
        pos = pos @ basis
    return pos.astype(np.float32)
