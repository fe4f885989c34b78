"""Closed choices and their defaults, each defined once (docs/architecture.md, "One vocabulary").

Every closed choice of the project is one ``str`` enum here; its default sits next to it. The
scene schema (:mod:`dynmesh_warp.config`) types its fields with these enums, the CLIs derive their
``choices=`` and defaults from them (:func:`values`), and kernels receive the integer code of a
member where they branch on it (:data:`PLAYBACK_CODES`). ``tests/test_choices.py`` checks that the
schema and every CLI's help derive from this module.

A member compares equal to its value (``Collider.SWEPT == "swept"``) and prints as it
(``f"{Collider.SWEPT}"`` is ``swept``), so plain strings keep working in the Python API.

Bottom layer: imports nothing from the package.
"""

from __future__ import annotations

import enum

__all__ = ["StrEnum", "Collider", "SweptSearch", "RebuildEvery", "Playback", "FrameOrder", "Orientation", "UpAxis",
           "Strategy", "NewtonSolver", "Rasteriser", "ColorSource", "DEFAULT_COLOR_SOURCE", "SphereBody",
           "DEFAULT_SPHERE_BODY", "SPHERE_INERTIA",
           "PLAYBACK_CODES", "DEFAULT_RASTERISER", "DEFAULT_COLLIDER",
           "DEFAULT_REBUILD_EVERY", "REFIT_BVH", "SEED_PREVIOUS_FACE", "SEED_REFIT_QUERY",
           "DEFAULT_SWEPT_SEARCH", "DEFAULT_BATCH_SWEPT_SEARCH", "SWEPT_MEASURED_SEARCHES", "SWEPT_FACES_MAX_SPHERES",
           "SPHERE_GRID_BUCKETS_PER_SPHERE", "SPHERE_GRID_CELL_SCALE", "SPHERE_GRID_LEVEL_SCALE",
           "SPHERE_GRID_SERIAL_RESOLVE",
           "SWEPT_RESOLVE_THREADS", "SWEPT_TILE_THREADS",
           "DEFAULT_PLAYBACK",
           "DEFAULT_FRAME_ORDER", "DEFAULT_ORIENTATION", "DEFAULT_UP_AXIS", "Y_UP_FORMATS", "DEFAULT_STRATEGY",
           "DEFAULT_NEWTON_SOLVER", "STRATEGIES", "values", "parse", "device_kind"]


class StrEnum(str, enum.Enum):
    """``enum.StrEnum`` for Python 3.10 too: members are strings that print as their value."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, spec: str) -> str:
        return format(str(self.value), spec)


class Collider(StrEnum):
    """How contacts find the deforming surface (docs/physics.md)."""

    #: swept when interpolating and the candidate lists are expected to fit, else refit
    FIXED = "fixed"
    #: the vertex buffer and the BVH are refit every sub-step (the reference)
    REFIT = "refit"
    #: a BVH over each face's box across the frame interval, refit once per frame
    SWEPT = "swept"
    #: a new BVH every sub-step or frame (varying topology)
    REBUILD = "rebuild"


class SweptSearch(StrEnum):
    """How the swept collider searches a sphere's faces each step (docs/physics.md#the-swept-collider)."""

    #: one thread per sphere walks its box query (the CPU's path)
    SERIAL = "serial"
    #: one thread block per sphere walks the query together and reduces (the CUDA default)
    TILED = "tiled"
    #: one thread per sphere; a sphere with more candidate faces than a budget is handed to a
    #: thread block (batched worlds only: docs/envs.md)
    HYBRID = "hybrid"
    #: one thread per face tests every sphere (no BVH walk: few spheres on large meshes; single
    #: worlds only)
    FACES = "faces"
    #: one thread block per sphere walks the cells of a uniform grid of its env's frame pair
    #: (contiguous cell lists, no tree walk; batched worlds only: docs/envs.md)
    GRID = "grid"
    #: the spheres binned every step in a hashed grid by their search radius, one thread per face
    #: tests the spheres of the cells its triangle overlaps (no BVH walk, no refit: many spheres
    #: on large meshes; single worlds only)
    SPHERE_GRID = "sphere_grid"


class RebuildEvery(StrEnum):
    """When the rebuild collider builds its BVH: every sub-step; when the held frame changes; or
    when the topology changes (a new segment of a piecewise-fixed sequence, every frame of a
    truly varying one), refitting it in between."""

    STEP = "step"
    FRAME = "frame"
    SEGMENT = "segment"


class Playback(StrEnum):
    """Times past the last frame."""

    #: ``loop`` where the animation repeats (its last frame about as near its first as two
    #: frames within it are), else ``clamp`` (the last frame held): resolved on the sequence by
    #: ``world.resolve_playback`` before anything plays it
    AUTO = "auto"
    LOOP = "loop"
    CLAMP = "clamp"
    PINGPONG = "pingpong"


class FrameOrder(StrEnum):
    """Order of the frames of an npz (docs/data.md)."""

    STORED = "stored"
    #: undo a text sort (1, 10, 11, ..., 2, ...) of the frame names
    TEXT_SORTED = "text_sorted"
    AUTO = "auto"


class Orientation(StrEnum):
    """Triangle orientation of a loaded surface: ``auto`` winds each piece consistently, turns a
    closed one outward and a sheet up (``geometry.orient_faces``); ``keep``; ``flip`` all."""

    AUTO = "auto"
    KEEP = "keep"
    FLIP = "flip"


class ColorSource(StrEnum):
    """Where generated Gaussians take their colour (docs/rendering.md): ``mesh``: the surface's own
    vertex colours where its file has them (interpolated), else ``gaussians.color``; ``uniform``:
    ``gaussians.color`` everywhere."""

    MESH = "mesh"
    UNIFORM = "uniform"


DEFAULT_COLOR_SOURCE = ColorSource.MESH


class SphereBody(StrEnum):
    """What a sphere is as a body (docs/physics.md, "Rolling"): how friction shares its impulse
    between the sphere's travel and its spin."""

    #: a point mass with a radius: no rotation, friction acts on the centre's velocity alone (a
    #: ball on a slope slides or sticks, a sliding block's law)
    POINT = "point"
    #: a solid ball (moment of inertia 2/5 m r^2): friction spins it, so it rolls
    SOLID = "solid"
    #: a thin spherical shell (2/3 m r^2)
    SHELL = "shell"


#: the default body: the point mass every release so far had (its results unchanged)
DEFAULT_SPHERE_BODY = SphereBody.POINT
#: each body's moment of inertia over m r^2; 0: the body does not rotate (the kernels' code)
SPHERE_INERTIA = {SphereBody.POINT: 0.0, SphereBody.SOLID: 0.4, SphereBody.SHELL: 2.0 / 3.0}


class UpAxis(StrEnum):
    """The loaded data's up axis (the scene is z-up): ``auto`` is ``y`` for formats whose
    specification fixes +Y up (glTF: ``.glb``/``.gltf``, a file or a folder of them), else ``z``."""

    AUTO = "auto"
    Z = "z"
    Y = "y"


#: file formats whose specification fixes +Y up (what ``up_axis: auto`` reads as y-up)
Y_UP_FORMATS = (".glb", ".gltf")


class Strategy(StrEnum):
    """Topology conversion strategies (dynmesh_warp.convert, docs/conversion.md)."""

    PROJECTION = "projection"
    TRACKING = "tracking"
    REGULARIZED = "regularized"
    #: the embedded deformation graph (best on every sequence of docs/evaluation.md)
    GRAPH = "graph"


class Rasteriser(StrEnum):
    """How the splat renderer composites a tile's sorted splats (docs/rendering.md)."""

    #: one thread per pixel reads the tile's splats from global memory (the CPU's rasteriser)
    PER_PIXEL = "per_pixel"
    #: one block per tile stages the splats in shared memory in batches (the CUDA default;
    #: on the CPU a block is one thread, which walks the tile's pixels in turn: correct, slower)
    SHARED = "shared"


class NewtonSolver(StrEnum):
    """Newton solvers the adapter can create (docs/newton.md)."""

    XPBD = "xpbd"
    SEMI_IMPLICIT = "semi_implicit"
    FEATHERSTONE = "featherstone"
    VBD = "vbd"
    MUJOCO = "mujoco"


DEFAULT_COLLIDER = Collider.FIXED
#: the rasteriser per device kind: measured on an H100, 1080p, 100k Gaussians, the shared-memory
#: rasteriser is 2.3x / 1.9x the per-pixel one at the default / a sparse density (docs/rendering.md)
DEFAULT_RASTERISER = {"cpu": Rasteriser.PER_PIXEL, "cuda": Rasteriser.SHARED}
#: a new BVH only when the topology changes (the same contacts as one per sub-step, up to ties
#: between equally close faces); "step" is the per-step baseline of the benchmarks
DEFAULT_REBUILD_EVERY = RebuildEvery.SEGMENT
#: the refit collider's ``wp.Mesh`` BVH per device kind: (constructor, primitives per leaf).
#: On CUDA SAH (built on the host at load: +0.8 s at 10^6 vertices) over Warp's default LBVH:
#: its refit is half as long and its queries faster, the refit step +32-67 % on an H100
#: (10^5-10^6 vertices x 5-10^5 spheres; docs/physics.md, bench_step --refit-bvh)
REFIT_BVH = {"cpu": ("sah", 4), "cuda": ("sah", 4)}
#: whether the serial swept search (one thread per sphere: the single world's and the batch's)
#: evaluates each sphere's previous contact face first, per device kind. It tightens the box
#: prune from the first candidate: on the 2-core CPU the batch's landing window +38-70 % and
#: the paper scene +13 %; on an H100 the serial search lost 10-30 % with it (one more chain of
#: dependent loads per thread before the walk) and the tiled ones nothing, so CUDA does not
#: seed (docs/physics.md)
SEED_PREVIOUS_FACE = {"cpu": True, "cuda": False}
#: whether the refit collider's query reaches no farther than each sphere's previous contact face
#: (+ twice Warp's tie epsilon) instead of its whole reach, per device kind (docs/physics.md)
SEED_REFIT_QUERY = {"cpu": True, "cuda": True}
#: the swept collider's search per device kind (a CPU thread block is one thread: serial there)
DEFAULT_SWEPT_SEARCH = {"cpu": SweptSearch.SERIAL, "cuda": SweptSearch.TILED}
#: the searches ``collider: fixed`` measures as candidates per device kind (none: the default)
SWEPT_MEASURED_SEARCHES = {"cpu": (), "cuda": (SweptSearch.TILED, SweptSearch.SERIAL, SweptSearch.FACES,
                                               SweptSearch.SPHERE_GRID)}
#: the face-parallel search is measured by ``fixed`` only up to this many spheres (its work is
#: faces x spheres per step), the sphere grid only above it
SWEPT_FACES_MAX_SPHERES = 64
#: the batched world's contact search per device kind by its sphere count (batch.BatchedWorld):
#: (up to this many spheres or None for any, search) rows, the first that fits. Measured on an
#: H100 (docs/envs.md): the grid search is 1.5-2x the best other search while the spheres land
#: on the horse (1 to 16,384 envs), and off the surface within 0.84-1.24x of them up to 1,024
#: envs; from 81,920 spheres on its blocks (one per sphere, most reading empty cells) lose to
#: serial off the surface (7,726 vs 24,458 steps/s), so serial beyond 32,768
DEFAULT_BATCH_SWEPT_SEARCH = {"cpu": ((None, SweptSearch.SERIAL),),
                              "cuda": ((32768, SweptSearch.GRID), (None, SweptSearch.SERIAL))}
#: threads per sphere of the tiled search
SWEPT_TILE_THREADS = 64
#: the sphere_grid search's hash table: buckets per sphere (rounded up to a power of two)
SPHERE_GRID_BUCKETS_PER_SPHERE = 8
#: the sphere_grid search's level-0 cell edge over the spheres' median (radius + margin)
SPHERE_GRID_CELL_SCALE = 4.0
#: the sphere_grid search's level-1 cell edge over level 0's
SPHERE_GRID_LEVEL_SCALE = 4.0
#: from this many spheres the sphere_grid search resolves its contacts one thread a sphere, below it
#: one block of SWEPT_RESOLVE_THREADS a sphere (H100: 10^5 spheres 153 -> 64 us, 1,000 10 -> 30 us)
SPHERE_GRID_SERIAL_RESOLVE = 16384
#: threads per sphere of the face-parallel search's second pass (the faces around the winning
#: face's three vertices, ~18 on a regular mesh, taken in parallel)
SWEPT_RESOLVE_THREADS = 32
#: a captured animation that does not repeat is held at its end, not swept back to its first
#: frame at hundreds of m/s (docs/physics.md, "Playback")
DEFAULT_PLAYBACK = Playback.AUTO
DEFAULT_FRAME_ORDER = FrameOrder.STORED
DEFAULT_ORIENTATION = Orientation.AUTO
DEFAULT_UP_AXIS = UpAxis.AUTO
DEFAULT_STRATEGY = Strategy.GRAPH
DEFAULT_NEWTON_SOLVER = NewtonSolver.XPBD

#: integer code of each playback mode, as the kernels branch on it (kernels/frames.py); ``auto``
#: has none: it is resolved to one of these on the sequence first
PLAYBACK_CODES = {Playback.LOOP: 0, Playback.CLAMP: 1, Playback.PINGPONG: 2}

#: the strategy names, in the enum's order
STRATEGIES = tuple(s.value for s in Strategy)


def values(choice: type[StrEnum]) -> list[str]:
    """The values of an enum, in order (argparse ``choices=``, messages)."""
    return [m.value for m in choice]


def device_kind(device) -> str:
    """The key of the per-device-kind tables here (``DEFAULT_SWEPT_SEARCH``, ``REFIT_BVH`` ...)
    for a Warp device: "cuda" or "cpu"."""
    return "cuda" if device.is_cuda else "cpu"


def parse(choice: type[StrEnum], value, field: str):
    """``value`` as a member of ``choice``; a ``ValueError`` naming ``field`` and the valid values."""
    try:
        return choice(value)
    except ValueError:
        raise ValueError(f"{field} must be one of {values(choice)}, got {value!r}") from None
