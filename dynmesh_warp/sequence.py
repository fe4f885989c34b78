"""Mesh sequences: fixed topology (one face array, per-frame vertices) and varying topology.

Both are plain NumPy containers on the host; the simulation uploads them to a Warp device.
Every constructor validates its data, so bad input fails here with a message naming the
source file and frame, never later inside a Warp kernel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "surface_vertices",
    "MeshDataError",
    "text_sorted_permutation",
    "detect_text_sorted_frames",
    "FixedTopologySequence",
    "VaryingTopologySequence",
    "upsampled_frames",
    "validate_mesh",
]


class MeshDataError(ValueError):
    """Invalid mesh or sequence data. The message names the source (file) and frame."""


class TopologyMismatchError(MeshDataError):
    """A varying-topology sequence asked to be fixed topology: ``frame`` (index) and ``source``
    differ from frame 0 in ``what`` ("vertex count" or "faces"); ``detail`` says how. The
    message is the summary followed by ``advice``."""

    def __init__(self, *, frame: int, source: str, what: str, detail: str, advice: str):
        self.frame, self.source, self.what, self.detail = frame, source, what, detail
        super().__init__(f"{self.summary}; {advice}")

    @property
    def summary(self) -> str:
        """One line without advice: '<source> (frame t): <detail>'."""
        return f"{self.source} (frame {self.frame}): {self.detail}"


def _where(source: str | None, frame: int | None) -> str:
    parts = []
    if source:
        parts.append(str(source))
    if frame is not None:
        parts.append(f"frame {frame}")
    return ", ".join(parts) if parts else "mesh"


#: the largest coordinate magnitude a mesh may have (in its own units). float32, the geometry's
#: precision, resolves 64 units there, and squared lengths of such coordinates overflow float32
#: (1e30 crashed the step); data beyond it is in a wrong unit or is garbage
MAX_COORDINATE = 1.0e9


def validate_mesh(
    vertices, faces, source: str | None = None, frame: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Check one triangle mesh and return it as (float32 (N,3), int32 (M,3)) arrays.

    Raises :class:`MeshDataError` for: vertices not (N,3), no vertices, NaN/inf coordinates or
    ones beyond ``MAX_COORDINATE``,
    faces not (M,3) integer triangles, no faces, and face indices outside [0, N).
    """
    where = _where(source, frame)
    V = np.asarray(vertices)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3:
        raise MeshDataError(f"{where}: vertices must have shape (N, 3), got {V.shape}")
    if V.shape[0] == 0:
        raise MeshDataError(f"{where}: mesh is empty (no vertices)")
    if not (np.issubdtype(V.dtype, np.integer) or np.issubdtype(V.dtype, np.floating)):
        raise MeshDataError(f"{where}: vertices must be real numbers, got dtype {V.dtype}")
    with np.errstate(over="ignore", invalid="ignore"):
        V32 = V.astype(np.float32)  # a finite float64 beyond float32's range becomes inf here
    ok = np.abs(V32) <= MAX_COORDINATE  # NaN compares False: bad too
    if not ok.all():  # (over the whole array first: ok.all(axis=1) is 10x slower)
        idx = np.flatnonzero(~ok.all(axis=1))
        raise MeshDataError(
            f"{where}: {idx.size} vertices have NaN/inf coordinates or ones beyond {MAX_COORDINATE:.0e} "
            f"(first: vertex {idx[0]}: {V[idx[0]].tolist()}): float32 geometry cannot resolve such a mesh; "
            "wrong units or garbage data?"
        )
    if F.ndim != 2 or F.shape[1] != 3:
        raise MeshDataError(
            f"{where}: faces must be triangles with shape (M, 3), got {F.shape}"
        )
    if F.shape[0] == 0:
        raise MeshDataError(f"{where}: mesh has no faces")
    if not np.issubdtype(F.dtype, np.integer):
        if np.issubdtype(F.dtype, np.floating) and np.all(np.mod(F, 1) == 0):
            F = F.astype(np.int64)
        else:
            raise MeshDataError(f"{where}: face indices must be integers, got dtype {F.dtype}")
    n = V.shape[0]
    lo, hi = int(F.min()), int(F.max())
    if lo < 0 or hi >= n:
        bad_face = int(np.flatnonzero(((F < 0) | (F >= n)).any(axis=1))[0])
        hint = ("; the indices look 1-based (as in OBJ files or MATLAB): subtract 1"
                if lo >= 1 and hi == n else "")
        raise MeshDataError(
            f"{where}: face indices out of range [0, {n}): face {bad_face} = "
            f"{F[bad_face].tolist()} (min index {lo}, max index {hi}){hint}"
        )
    ratio = _shorter_one_based(V32, F) if lo >= 1 else 0.0
    if ratio >= ONE_BASED_RATIO:
        raise MeshDataError(
            f"{where}: the face indices look 1-based (as in OBJ files or MATLAB): vertex 0 is in no face (min index "
            f"{lo}, max index {hi}), and with 1 subtracted the edges are {ratio:.1f}x shorter; subtract 1")
    return np.ascontiguousarray(V32), np.ascontiguousarray(F, dtype=np.int32)


#: faces whose indices all are >= 1 read as 1-based when 1 subtracted makes the mean edge this many
#: times shorter: a relabelling by one keeps the topology, so the geometry tells (a new user's
#: 1-based npz whose last vertex no face used loaded as a scrambled mesh: area 146 against 12.5)
ONE_BASED_RATIO = 1.5


def _shorter_one_based(V: np.ndarray, F: np.ndarray) -> float:
    """The mean edge length of the faces ``F`` over that of ``F - 1`` (``F`` >= 1)."""
    def mean_edge(G):
        a, b, c = (V[G[:, k]].astype(np.float64) for k in range(3))
        return float(np.mean(np.linalg.norm(a - b, axis=1) + np.linalg.norm(b - c, axis=1) + np.linalg.norm(c - a, axis=1)))

    shifted = mean_edge(F - 1)
    return mean_edge(F) / shifted if shifted > 0 else 0.0



#: the frame rates a sequence may have [frames/s]: a time-lapse to a high-speed camera. Outside it
#: the times k / fps overflow (a new user's --fps 1e300 wrote fps=inf, 1e-300 a .glb with
#: non-finite key times; both read back as errors). The scene's surface.fps and convert --fps too.
FPS_RANGE = (1.0e-4, 1.0e7)


def _checked_fps(fps, where: str) -> float:
    """``fps`` as a float, or a :class:`MeshDataError` naming ``where`` for anything but a number
    in :data:`FPS_RANGE` (a string or None too: float()'s own message named neither)."""
    try:
        value = float(fps)
    except (TypeError, ValueError):
        value = float("nan")
    if isinstance(fps, bool) or not (FPS_RANGE[0] <= value <= FPS_RANGE[1]):
        raise MeshDataError(f"{where}: fps must be a positive number, {FPS_RANGE[0]:g} to {FPS_RANGE[1]:g} "
                            f"frames/s, got {fps!r}")
    return value

def surface_vertices(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """The vertices of V (N, 3) (or (T, N, 3): of every frame) that a face of F (M, 3) uses: the
    surface's points. Exporters leave stray vertices no face uses; they are no surface, so the
    surface's extent, a spawn's drop height and the ground plane come from these (a new user's
    stray point at z = 20 spawned the spheres 20 m up; one at x = 1e5 called a 2.8 m sheet
    "1e+05 m across"). V itself (no copy) when every vertex is used."""
    V = np.asarray(V)
    used = np.zeros(V.shape[-2], bool)
    used[np.asarray(F).reshape(-1)] = True
    return V if used.all() else V[..., used, :]


def upsampled_frames(num_frames: int, factor: int, playback: str) -> int:
    """How many frames :meth:`FixedTopologySequence.upsampled` makes of ``num_frames`` (>= 2):
    ``num_frames * factor`` under ``loop`` (the seam back to the first frame filled too), else
    ``(num_frames - 1) * factor + 1``."""
    return num_frames * factor if playback == "loop" else (num_frames - 1) * factor + 1


def _check_up_axis(up_axis, where: str) -> None:
    if up_axis not in (None, "y", "z"):
        raise MeshDataError(f"{where}: up_axis must be 'y', 'z' or None (as its source says), got {up_axis!r}")


def unit_colors(C, integer_max: float | None = None) -> np.ndarray:
    """Colours as float32 in [0, 1]: integers over their type's maximum (uint8 over 255, uint16 over
    65535; ``integer_max`` for integers held in floats), floats as they are, or over 255 where any
    exceeds 1 and none 255 (0..255 written as floats); NaN as 0. The one rule of the colour readers
    and of a sequence's ``colors`` (an npz's uint16 or 0..255 float colours read white before)."""
    C = np.asarray(C)
    if np.issubdtype(C.dtype, np.integer):
        integer_max = float(np.iinfo(C.dtype).max) if integer_max is None else integer_max
    C = np.asarray(C, np.float64)
    if integer_max is not None:
        C = C / integer_max
    elif C.size and np.nanmax(C) > 1.0 and np.nanmax(C) <= 255.0:
        C = C / 255.0
    return np.clip(np.nan_to_num(C, nan=0.0), 0.0, 1.0).astype(np.float32)


def _checked_colors(colors, num_vertices: int, where: str):
    """``colors`` as float32 (N, 3) in [0, 1] (:func:`unit_colors`) for frame 0's ``num_vertices``
    vertices, or None."""
    if colors is None:
        return None
    C = np.asarray(colors)
    if C.ndim != 2 or C.shape[1] not in (3, 4) or len(C) != num_vertices:
        raise MeshDataError(f"{where}: colors must have shape ({num_vertices}, 3), one RGB per vertex of frame 0, "
                            f"got {C.shape}")
    if not (np.issubdtype(C.dtype, np.number) and not np.issubdtype(C.dtype, np.complexfloating)) \
            or not np.isfinite(C).all():
        raise MeshDataError(f"{where}: colors hold NaN, inf or non-numbers")
    if C.dtype == np.bool_ or (np.issubdtype(C.dtype, np.integer) and C.min() < 0):
        raise MeshDataError(f"{where}: colors must be unsigned integers or floats, got {C.dtype} with negatives")
    return np.ascontiguousarray(unit_colors(C[:, :3]))


def carried(seq, **changed) -> dict:
    """The keyword arguments that describe ``seq`` (``fps``, ``name``, ``source``, ``up_axis``)
    for a new sequence made from its frames, ``changed`` replacing some:
    ``FixedTopologySequence(V, F, **carried(seq))``. The one list of them: a copy that named its
    fields by hand lost the up axis (a glTF's +Y up, read as z-up after re-meshing), and a field added
    here is carried by every copy. Per-frame ``frame_sources`` are not carried (a copy may take other
    frames): pass them where the frames are the same. Nor are ``colors`` (per vertex of frame 0): pass
    ``colors=seq.colors`` where frame 0's vertices are the same."""
    out = {"fps": seq.fps, "name": seq.name, "source": seq.source, "up_axis": seq.up_axis}
    unknown = set(changed) - set(out)
    if unknown:
        raise TypeError(f"carried: unknown field(s) {sorted(unknown)}; it carries {sorted(out)}")
    out.update(changed)
    return out


@dataclass(repr=False)
class FixedTopologySequence:
    """An animated triangle mesh whose faces are the same in every frame.

    Attributes:
        V: vertex positions, float32 (T, N, 3), scene units (metres by convention).
        F: triangle indices, int32 (M, 3), shared by every frame.
        fps: reconstruction frame rate f_recon in frames per second (frame k covers
            t in [k/fps, (k+1)/fps)).
        name: a label for logs and outputs.
        source: where it came from (file or folder), used in error messages.
        up_axis: the axis V's "up" is along, where known ("y" or "z"; None: as ``source`` says,
            ``io.stored_up_axis``); a scene's surface is "z" (``scene.prepare_surface``).
        colors: per-vertex RGB, float32 (N, 3) in [0, 1] (the mesh file's own vertex colours), or
            None; the colour of generated Gaussians (docs/rendering.md).
    """

    V: np.ndarray
    F: np.ndarray
    fps: float = 24.0
    name: str = "sequence"
    source: str | None = None
    up_axis: str | None = None
    colors: np.ndarray | None = None

    def __post_init__(self):
        where = self.source or self.name
        V = np.asarray(self.V)
        if V.ndim != 3 or V.shape[-1] != 3:
            raise MeshDataError(f"{where}: V must have shape (T, N, 3), got {V.shape}")
        if V.shape[0] == 0:
            raise MeshDataError(f"{where}: sequence has no frames")
        if V.shape[1] == 0:
            raise MeshDataError(f"{where}: mesh is empty (no vertices)")
        _, F = validate_mesh(V[0], self.F, where, 0)
        with np.errstate(over="ignore", invalid="ignore"):
            V32 = np.ascontiguousarray(V, dtype=np.float32)  # beyond float32's range -> inf
        finite = (np.abs(V32) <= MAX_COORDINATE).all(axis=(1, 2))  # NaN compares False
        if not finite.all():
            t = int(np.flatnonzero(~finite)[0])
            validate_mesh(V[t], F, where, t)  # raises, naming the frame
        self.V = V32
        self.F = F
        self.fps = _checked_fps(self.fps, where)
        _check_up_axis(self.up_axis, where)
        self.colors = _checked_colors(self.colors, V.shape[1], where)

    def __repr__(self) -> str:
        return (f"FixedTopologySequence(name={self.name!r}, frames={self.num_frames}, "
                f"vertices={self.num_vertices}, faces={self.num_faces}, fps={self.fps})")

    @property
    def num_frames(self) -> int:
        return int(self.V.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.V.shape[1])

    @property
    def num_faces(self) -> int:
        return int(self.F.shape[0])

    @property
    def duration(self) -> float:
        """Length in seconds: num_frames / fps."""
        return self.num_frames / self.fps

    def frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        return self.V[k], self.F

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo (3,), hi (3,)) over every frame's surface vertices (those a face uses:
        :func:`surface_vertices`)."""
        V = surface_vertices(self.V, self.F)
        return V.min(axis=(0, 1)), V.max(axis=(0, 1))

    def max_vertex_speed(self) -> float:
        """Largest vertex speed between consecutive frames, in units per second."""
        if self.num_frames < 2:
            return 0.0
        d = np.linalg.norm(np.diff(self.V, axis=0), axis=-1)
        return float(d.max() * self.fps)

    def upsampled(self, factor: int, playback: str = "loop") -> "FixedTopologySequence":
        """The same motion at ``factor`` × the frame rate, on a C¹ curve through the frames
        (uniform Catmull-Rom: the cubic Hermite curve whose velocity at frame k is
        (V[k+1] − V[k−1]) · fps / 2), so that the step's straight lines between the new frames
        follow a motion whose velocity does not jump at the input's frame boundaries.

        Every input frame is kept (new frame ``factor * k`` is frame k) and a motion quadratic in
        time is reproduced exactly between them. ``playback`` (``loop``, ``clamp`` or
        ``pingpong``, as the scene plays it) decides the ends: ``loop`` also fills the interval
        from the last frame back to the first and takes its neighbours across it (T · factor
        frames); ``clamp`` repeats the end frames as their own neighbours and ``pingpong``
        reflects them (velocity 0 at the turn): (T − 1) · factor + 1 frames. Float64 inside,
        float32 out. ``factor`` 1, or a single frame, gives the sequence back unchanged."""
        factor = int(factor)
        if factor < 1:
            raise ValueError(f"upsampled: factor must be an integer >= 1, got {factor}")
        if playback not in ("loop", "clamp", "pingpong"):
            raise ValueError(f"upsampled: playback must be loop, clamp or pingpong, got {playback!r}")
        T = self.num_frames
        if factor == 1 or T < 2:
            return self
        intervals = T if playback == "loop" else T - 1  # k -> k + 1
        out = np.empty((upsampled_frames(T, factor, playback), self.num_vertices, 3), np.float32)
        for k in range(intervals):  # one interval at a time: float64 work of a few frames only
            j = np.arange(k - 1, k + 3)  # its four frames
            if playback == "loop":
                j = np.mod(j, T)
            elif playback == "clamp":
                j = np.clip(j, 0, T - 1)
            else:  # pingpong: reflected at both ends (frame -1 is frame 1, frame T is frame T - 2)
                j = np.abs(j)
                j = np.where(j > T - 1, 2 * (T - 1) - j, j)
            p0, p1, p2, p3 = self.V[j].astype(np.float64)
            # uniform Catmull-Rom in Hermite form: p1 + m1 s + (3 d - 2 m1 - m2) s^2 + (m1 + m2 - 2 d) s^3,
            # d = p2 - p1, m1 = (p2 - p0) / 2, m2 = (p3 - p1) / 2 (tangents per frame interval)
            d, m1, m2 = p2 - p1, 0.5 * (p2 - p0), 0.5 * (p3 - p1)
            a2, a3 = 3.0 * d - 2.0 * m1 - m2, m1 + m2 - 2.0 * d
            for i in range(factor):  # the new frames at s = i / factor of the interval
                s = i / factor
                out[k * factor + i] = p1 + s * (m1 + s * (a2 + s * a3))
        if playback != "loop":
            out[-1] = self.V[-1]
        return FixedTopologySequence(out, self.F, **carried(self, fps=self.fps * factor), colors=self.colors)

    def reordered(self, order) -> "FixedTopologySequence":
        """A copy with frames taken in ``order`` (indices into the stored frames)."""
        order = np.asarray(order, dtype=np.int64)
        return FixedTopologySequence(self.V[order], self.F, **carried(self), colors=self.colors)

    def to_varying(self) -> "VaryingTopologySequence":
        return VaryingTopologySequence([(v, self.F) for v in self.V], **carried(self), colors=self.colors)


@dataclass(repr=False)
class VaryingTopologySequence:
    """An animated mesh whose vertex count and faces may change every frame.

    Attributes:
        frames: list of (V_t float32 (N_t, 3), F_t int32 (M_t, 3)) per frame.
        fps: frame rate in frames per second.
        name, source: labels for logs and error messages.
        up_axis: as :class:`FixedTopologySequence`'s.
        colors: per-vertex RGB of frame 0's vertices, float32 (N_0, 3) in [0, 1], or None (a
            conversion carries them to its template: docs/conversion.md).
    """

    frames: list = field(default_factory=list)
    fps: float = 24.0
    name: str = "sequence"
    source: str | None = None
    frame_sources: list | None = None  # optional per-frame file names for messages
    up_axis: str | None = None
    colors: np.ndarray | None = None

    def __post_init__(self):
        where = self.source or self.name
        if len(self.frames) == 0:
            raise MeshDataError(f"{where}: sequence has no frames")
        checked = []
        for t, pair in enumerate(self.frames):
            src = self.frame_sources[t] if self.frame_sources else where
            if not isinstance(pair, (tuple, list)) or len(pair) != 2:
                raise MeshDataError(f"{src}: frame {t}: frames must be a list of (V, F) pairs, one per frame "
                                    f"(got {type(pair).__name__}"
                                    f"{' of length ' + str(len(pair)) if hasattr(pair, '__len__') else ''})")
            v, f = pair
            checked.append(validate_mesh(v, f, src, t))
        self.frames = checked
        self.fps = _checked_fps(self.fps, where)
        _check_up_axis(self.up_axis, where)
        self.colors = _checked_colors(self.colors, len(checked[0][0]), where)

    def __repr__(self) -> str:
        nv = [len(v) for v, _ in self.frames]
        return (f"VaryingTopologySequence(name={self.name!r}, frames={self.num_frames}, "
                f"vertices={min(nv)}..{max(nv)}, fps={self.fps})")

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def duration(self) -> float:
        return self.num_frames / self.fps

    def frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        return self.frames[k]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo (3,), hi (3,)) over every frame's surface vertices (those a face uses:
        :func:`surface_vertices`)."""
        pts = [surface_vertices(v, f) for v, f in self.frames]
        return np.min([v.min(axis=0) for v in pts], axis=0), np.max([v.max(axis=0) for v in pts], axis=0)

    def is_fixed_topology(self) -> bool:
        """True when every frame has the first frame's vertex count and face array."""
        V0, F0 = self.frames[0]
        return all(v.shape == V0.shape and f.shape == F0.shape and np.array_equal(f, F0)
                   for v, f in self.frames[1:])

    def segments(self) -> list:
        """``(start, stop)`` frame ranges (stop exclusive) over which the topology stays fixed:
        maximal runs of consecutive frames with the same vertex count and face array (a
        piecewise-fixed sequence, as ``convert`` writes when one template cannot follow every
        frame). A truly varying sequence has one run per frame; a fixed one, one run."""
        runs, start = [], 0
        for t in range(1, self.num_frames):
            (v0, f0), (v1, f1) = self.frames[t - 1], self.frames[t]
            if not (len(v0) == len(v1) and f0.shape == f1.shape and np.array_equal(f0, f1)):
                runs.append((start, t))
                start = t
        runs.append((start, self.num_frames))
        return runs

    def interrupted_segments(self, runs: list | None = None) -> list:
        """The ``(start, stop)`` segments (``runs``, default :meth:`segments`) whose frames either
        side share one topology (the same vertex count and faces before and after: A, B, A). The
        piecewise-fixed output ``convert`` writes never comes back to a template it left; a
        capture's frame that lost faces (a file cut short at a line's end) reads so (a new user's
        folder played that frame with a quarter of its faces, unsaid)."""
        runs = self.segments() if runs is None else runs
        out = []
        for (a, b), (c, _), (d, _) in zip(runs[1:-1], runs[:-2], runs[2:]):
            (v0, f0), (v1, f1) = self.frames[c], self.frames[d]
            if len(v0) == len(v1) and f0.shape == f1.shape and np.array_equal(f0, f1):
                out.append((a, b))
        return out

    def is_piecewise_fixed(self, runs: list | None = None) -> bool:
        """At most half as many segments (``runs``, default :meth:`segments`) as frames: the
        piecewise-fixed output ``convert`` writes, not a new mesh every frame."""
        return len(self.segments() if runs is None else runs) <= self.num_frames // 2

    def to_fixed(self) -> FixedTopologySequence:
        """Stack into a fixed-topology sequence; raises if the frames disagree."""
        V0, F0 = self.frames[0]
        where = self.source or self.name
        src0 = self.frame_sources[0] if self.frame_sources else where
        for t, (v, f) in enumerate(self.frames):
            src = self.frame_sources[t] if self.frame_sources else where
            if v.shape[0] != V0.shape[0]:
                raise TopologyMismatchError(
                    frame=t, source=str(src), what="vertex count",
                    detail=f"{v.shape[0]} vertices but frame 0 ({src0}) has {V0.shape[0]}",
                    advice="a fixed-topology sequence needs the same vertex count in every frame")
            if f.shape != F0.shape or not np.array_equal(f, F0):
                raise TopologyMismatchError(
                    frame=t, source=str(src), what="faces",
                    detail=(f"faces differ from frame 0 ({src0}) ({len(f)} vs {len(F0)} faces)" if len(f) != len(F0)
                            else f"faces differ from frame 0 ({src0}): the same number ({len(f)}), other "
                                 f"vertex indices (first at face {int(np.flatnonzero((f != F0).any(axis=1))[0])})"),
                    advice="a fixed-topology sequence needs identical faces in every frame (convert a "
                           "varying-topology one with dynmesh_warp.convert)")
        return FixedTopologySequence(np.stack([v for v, _ in self.frames]), F0, **carried(self), colors=self.colors)


def text_sorted_permutation(num_frames: int, start: int = 1) -> np.ndarray:
    """Frame order that undoes a text sort of the frame numbers start..start+T-1.

    A sequence assembled from files sorted as text stores frame numbers in the order
    1, 10, 11, ..., 19, 2, 20, ...; ``V[text_sorted_permutation(T, 1)]`` puts them back in
    numeric order.
    """
    labels = sorted(str(i) for i in range(start, start + num_frames))
    return np.argsort([int(x) - start for x in labels], kind="stable")


def detect_text_sorted_frames(V: np.ndarray, max_vertices: int = 2000) -> int | None:
    """If the frames of V (T, N, 3) look text-sorted, the first frame number (0 or 1), else None.

    The reordered sequence must move at most half as much per frame, on average, as the
    stored one (measured on up to ``max_vertices`` vertices).
    """
    T = V.shape[0]
    if T < 11:  # 1..10 is the first count where a text sort differs from a numeric one
        return None
    sel = np.linspace(0, V.shape[1] - 1, min(max_vertices, V.shape[1])).astype(np.int64)
    W = V[:, sel].astype(np.float64)

    def mean_step(X):
        return float(np.linalg.norm(np.diff(X, axis=0), axis=-1).mean())

    stored = mean_step(W)
    best, best_start = stored, None
    for start in (0, 1):
        m = mean_step(W[text_sorted_permutation(T, start)])
        if m < 0.5 * best:
            best, best_start = m, start
    return best_start
