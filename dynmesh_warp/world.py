"""The physics world: rigid spheres against a deforming triangle mesh.

Static data lives in :class:`Model` (with :class:`SurfaceModel` and :class:`SphereModel`),
per-step data in :class:`State`, and the per-sphere contacts of the last step in
:class:`Contacts` — all ``wp.array``s on one device. :class:`World` owns one of each plus a
collider and advances them; on CUDA the fixed-topology step allocates nothing and reads
nothing back, so it is captured once as a CUDA graph and replayed.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Optional

import numpy as np
from pydantic import PrivateAttr
import warp as wp

from .kernels.collide import collide_sphere_mesh
from .kernels.frames import FRAME_SNAP, blend_segment_vertices, update_frame_vertices
from .kernels.geometry import compute_face_normals
from .kernels.integrate import integrate_spheres, pinch_memory
from .kernels.swept import (
    NO_KEY,
    collide_sphere_swept,
    collide_sphere_swept_tiled,
    compute_swept_bounds,
    detect_frame_change,
    find_closest_per_face,
    resolve_closest_per_sphere,
    resolve_closest_per_sphere_serial,
)
from .kernels.sphere_grid import (
    compute_sphere_bounds,
    count_sphere_cells,
    find_closest_in_sphere_cells,
    scatter_sphere_cells,
)
from .choices import (
    DEFAULT_COLLIDER,
    DEFAULT_PLAYBACK,
    DEFAULT_REBUILD_EVERY,
    DEFAULT_SWEPT_SEARCH,
    PLAYBACK_CODES,
    REFIT_BVH,
    SEED_PREVIOUS_FACE,
    SEED_REFIT_QUERY,
    SPHERE_GRID_BUCKETS_PER_SPHERE,
    SPHERE_INERTIA,
    SPHERE_GRID_CELL_SCALE,
    SPHERE_GRID_LEVEL_SCALE,
    SPHERE_GRID_SERIAL_RESOLVE,
    SWEPT_FACES_MAX_SPHERES,
    SWEPT_MEASURED_SEARCHES,
    SWEPT_RESOLVE_THREADS,
    SWEPT_TILE_THREADS,
    Collider,
    Playback,
    RebuildEvery,
    SweptSearch,
    device_kind,
    parse,
    values,
)
from .config import MAX_TIME_OFFSET, PhysicsCore
from .geometry import frame_across, points_inside, up_from_gravity
from .sequence import FixedTopologySequence, VaryingTopologySequence

__all__ = [
    "fallen_past_note",
    "physics_summary",
    "warn_spins_kept",
    "PhysicsParams",
    "WorkBudgetError",
    "check_substep_budget",
    "required_substeps",
    "SurfaceModel",
    "VaryingSurfaceModel",
    "SphereModel",
    "Model",
    "State",
    "Contacts",
    "World",
    "PLAYBACK_MODES",
    "surface_model",
    "surface_model_class",
    "frame_pair_host",
    "resolve_playback",
    "playback_note",
    "seam_jumps",
    "SEAM_REPEAT_RATIO",
]

#: playback name -> the integer code the kernels branch on (dynmesh_warp.choices.PLAYBACK_CODES)
PLAYBACK_MODES = {m.value: code for m, code in PLAYBACK_CODES.items()}
#: World.add_spheres checks new spheres against the closed surface up to this many sphere-face
#: pairs (host winding numbers, ~1 s at the budget); beyond it the check is skipped
WINDING_CHECK_BUDGET = 20_000_000


def _step_modules(with_hooks: bool):
    """Our kernel modules a step launches from (with the Gaussian binding hook's, if asked)."""
    from .kernels import collide, frames, gaussians, geometry, integrate, swept

    return (frames, geometry, collide, swept, integrate) + ((gaussians,) if with_hooks else ())


def _wrap_frame_host(k: int, num_frames: int, mode: int) -> int:
    if num_frames <= 1:
        return 0
    if mode == PLAYBACK_MODES["clamp"]:
        return min(max(k, 0), num_frames - 1)
    if mode == PLAYBACK_MODES["pingpong"]:
        period = 2 * (num_frames - 1)
        m = k % period
        return period - m if m >= num_frames else m
    return k % num_frames


def playback_cycle_host(num_frames: int, mode: int) -> float:
    """Host twin of the device ``kernels.envs.playback_cycle``: frames of one cycle of the
    playback (T for loop, 2 (T - 1) for pingpong, T - 1 for clamp; at least 1)."""
    T = float(num_frames)
    if mode == PLAYBACK_MODES["pingpong"]:
        return max(2.0 * (T - 1.0), 1.0)
    if mode == PLAYBACK_MODES["clamp"]:
        return max(T - 1.0, 1.0)
    return max(T, 1.0)


def frame_pair_host(time: float, fps: float, num_frames: int, mode: int = 0) -> tuple[int, int, float]:
    """Host twin of the device ``frame_pair``: (k, k+1) wrapped by playback mode, and alpha
    (a clock within ``FRAME_SNAP`` frames below a boundary is on it)."""
    s = time * fps
    kf = math.floor(s)
    if s - kf > 1.0 - FRAME_SNAP:
        kf += 1
    k = int(kf)
    return (_wrap_frame_host(k, num_frames, mode), _wrap_frame_host(k + 1, num_frames, mode), max(s - kf, 0.0))


class PhysicsParams(PhysicsCore):
    """Scalar physics settings (keyword arguments; validated on construction and assignment by
    the same pydantic model as the scene's ``physics:`` section, :class:`~dynmesh_warp.config.
    PhysicsCore`, which holds the defaults: a bad value raises a ``ValueError`` naming the field).

    dt: physics step [s]; substeps: sub-steps per step (each of dt/substeps); max_substeps:
    the most sub-steps the sub-step rule may reach (None: no bound; over it the world is not
    built, see :class:`WorkBudgetError`); gravity: [m/s^2]; restitution: normal coefficient of
    restitution in [0, 1]; friction: Coulomb coefficient; rest_speed: normal approach speed [m/s]
    below which an impact does not bounce; margin: extra contact query distance [m];
    auto_substeps: raise substeps so the surface moves less than half the smallest sphere radius
    per sub-step; swept_search: the swept collider's search (None: the device's default);
    sphere_body: ``point`` (no rotation), ``solid`` or ``shell`` (friction spins the sphere, so it
    rolls; ``choices.SphereBody``); ground_height: optional static ground plane z = ground_height [m] (None: no ground).

    A world built from them fixes them (:meth:`freeze`): its sub-steps, gravity and captured
    CUDA graph were made from the values it saw, so a later assignment is refused rather than
    ignored. For other values build a new model, e.g. with ``params.model_copy(update={...})``.
    """

    ground_height: Optional[float] = None
    _frozen: bool = PrivateAttr(default=False)

    def freeze(self) -> "PhysicsParams":
        """Refuse assignments from now on (called by the worlds built from these parameters)."""
        self._frozen = True
        return self

    def __setattr__(self, name, value):
        # a new user's dt / gravity / substeps set on a built world were ignored (and World.dt
        # reported the new dt while the step kept the old one)
        if not name.startswith("_") and self._frozen:
            raise ValueError(f"physics {name}: the parameters are fixed once a world is built from them (its "
                             f"sub-steps and captured step use them); build a new model with "
                             f"params.model_copy(update={{{name!r}: ...}})")
        super().__setattr__(name, value)

    def model_copy(self, *, update=None, deep: bool = False) -> "PhysicsParams":
        """A copy (``update``: fields to change) that is not frozen: the parameters of a new model."""
        copy = super().model_copy(update=update, deep=deep)
        copy._frozen = False
        return copy


#: reference values of the default scene, to name what drives a large sub-step count
_REFERENCE = {"radius": 0.05, "speed": 1.0, "dt": 1.0 / 240.0}


#: the loop's seam (the jump from the last frame back to the first) repeats the animation when its
#: largest vertex jump is at most this many times the largest between two frames within it
#: (measured: horse_gallop 0.79, the default scene's wave_bowl 0.76; pcow 2.8, chicken_crossing
#: 14.9, horse_collapse 28.9)
SEAM_REPEAT_RATIO = 1.5


def seam_jumps(seq) -> tuple[float, float]:
    """``(seam, within)``: the largest vertex jump from the last frame of the fixed-topology
    ``seq`` back to its first, and the largest between two consecutive frames within it [m]."""
    if seq.num_frames < 2:
        return 0.0, 0.0
    return (float(np.linalg.norm(seq.V[0] - seq.V[-1], axis=-1).max()),
            float(np.linalg.norm(np.diff(seq.V, axis=0), axis=-1).max()))


def resolve_playback(seq, playback) -> str:
    """The playback mode's name with ``auto`` resolved on ``seq`` (``choices.Playback.AUTO``):
    ``loop`` where the animation repeats (its seam no larger than ``SEAM_REPEAT_RATIO`` x the
    largest jump between two frames within it: :func:`seam_jumps`), else ``clamp``. A varying
    topology's frames have no vertex correspondence to measure a seam by: ``loop``. Other modes
    are returned as given (parsed)."""
    return _resolved(seq, playback)[0]


def _resolved(seq, playback) -> tuple[str, float, float]:
    """``(mode, seam, within)``: :func:`resolve_playback`'s mode and, where ``auto`` measured it
    (:func:`seam_jumps`, one pass over the frames), the two jumps; 0, 0 elsewhere."""
    mode = parse(Playback, playback, "playback")
    if mode != Playback.AUTO:
        return mode.value, 0.0, 0.0
    if not isinstance(seq, FixedTopologySequence):
        return Playback.LOOP.value, 0.0, 0.0
    seam, within = seam_jumps(seq)
    return (Playback.LOOP if seam <= SEAM_REPEAT_RATIO * within else Playback.CLAMP).value, seam, within


def playback_note(seq, playback) -> str:
    """Words for the user where ``auto`` holds the last frame (``""`` otherwise): the seam's jump
    against the motion within the animation, and how to loop it anyway."""
    if parse(Playback, playback, "playback") != Playback.AUTO:
        return ""
    mode, seam, within = _resolved(seq, playback)
    if mode != Playback.CLAMP:
        return ""
    return (f"surface.playback auto: clamp (the animation does not repeat: its last frame lies up to {seam:.3g} m "
            f"from its first, against {within:.3g} m between two frames within it), so its last frame is held "
            "after it ends; surface.playback: loop to repeat it anyway, pingpong to play it back and forth")


def seam_note(surface) -> str:
    """Where the loop's seam (the jump from the last frame back to the first) is what sets the
    surface's speed, words saying so: most captured animations do not repeat, and under the
    then default ``playback: loop`` a new user's sheet moving at 0.5 m/s was reported at 24 m/s and
    ran 4 sub-steps a step (``auto``, the default now, holds such an animation's last frame; this
    is said where a scene names ``loop``)."""
    seam, motion = float(surface.seam_speed), float(surface.motion_speed)
    if seam <= 0 or seam < float(surface.max_speed) or seam <= SEAM_REPEAT_RATIO * motion:
        return ""
    return (f" (the jump from the last frame back to the first under surface.playback: loop; within the "
            f"animation {motion:.3g} m/s: for an animation that does not repeat, set "
            "surface.playback: auto, clamp or pingpong)")


def required_substeps(max_speed: float, dt: float, r_min: float) -> int:
    """Sub-steps per step so a surface moving at ``max_speed`` [m/s] moves less than half the
    smallest body's radius (or half thickness) ``r_min`` [m] per sub-step: the sub-step rule of the
    world, the batch and the Newton adapter."""
    if max_speed <= 0 or not math.isfinite(r_min):
        return 1
    return max(1, math.ceil(max_speed * dt / (0.5 * r_min)))


def check_substep_budget(need: int, speed: float, r_min: float, p, note: str = "") -> None:
    """Raise :class:`WorkBudgetError` when the sub-step rule needs more than ``p.max_substeps``
    sub-steps per step: name the surface speed, the radius and dt, what drives it (the one
    farthest from the default scene's values) and the value of each that would fit."""
    cap = p.max_substeps
    if cap is None or need <= cap:
        return
    drivers = {"the sphere radius": _REFERENCE["radius"] / r_min, "the surface speed": speed / _REFERENCE["speed"],
               "physics.dt": p.dt / _REFERENCE["dt"]}
    driver = max(drivers, key=drivers.get)
    raise WorkBudgetError(
        f"work budget: the surface moves up to {speed:.3g} m/s{note} and the smallest sphere radius is {r_min:.3g} m, so "
        f"at physics.dt {p.dt:.3g} s a step needs {need:,} sub-steps (surface < r/2 per sub-step), over "
        f"physics.max_substeps {cap}; driven by {driver}. Fits with: radius >= {2 * speed * p.dt / cap:.3g} m, "
        f"or physics.dt <= {cap * 0.5 * r_min / speed:.3g} s, or a surface speed <= {cap * 0.5 * r_min / p.dt:.3g} m/s "
        "(surface.scale for data in other units); or raise physics.max_substeps (--no-work-limit lifts the bounds)")


class WorkBudgetError(ValueError):
    """The sub-steps a scene needs exceed the work budget (``physics.max_substeps`` /
    ``run.max_total_substeps``); the message names what drives them and the value that fits."""


class SurfaceModel:
    """Static data of a fixed-topology deforming surface.

    Attributes:
        frames: wp.array2d(vec3), (T, N) vertex positions per reconstruction frame [m].
        indices: wp.array(int32), (3M,) triangle vertex indices, shared by all frames.
        fps: reconstruction frame rate [1/s]; frame k = floor(t * fps) (``frame_pair_host``).
        playback: int code of "loop" | "clamp" | "pingpong" (times past the last frame; "auto"
            resolved on the sequence first: :func:`resolve_playback`).
        interpolate: blend frames k and k+1 linearly (else hold frame k).
        max_speed: largest vertex speed over the sequence [m/s] (host float): the larger of
        motion_speed (within the animation) and seam_speed (loop: the jump from the last frame
        back to the first; 0 otherwise).
        average_edge_length: (T,) float32 each frame's mean edge length [m] (host).
        max_abs_coordinate: the largest |coordinate| over the frames [m] (host float).
    """

    def __init__(self, seq: FixedTopologySequence, device=None, playback: str = DEFAULT_PLAYBACK, interpolate: bool = True):
        playback = resolve_playback(seq, playback)
        self.sequence = seq
        self.device = wp.get_device(device)
        self.frames = wp.array(seq.V, dtype=wp.vec3, device=self.device)
        self.indices = wp.array(seq.F.reshape(-1), dtype=wp.int32, device=self.device)
        self.fps = float(seq.fps)
        self.num_frames = seq.num_frames
        self.num_vertices = seq.num_vertices
        self.num_faces = seq.num_faces
        self.playback_name = playback
        self.playback = PLAYBACK_MODES[playback]
        self.interpolate = bool(interpolate)
        speed = seq.max_vertex_speed()
        self.motion_speed = speed  # the largest vertex speed within the animation [m/s]
        self.seam_speed = 0.0  # the loop's jump from the last frame back to the first [m/s] (loop only)
        if playback == "loop" and seq.num_frames > 1:
            wrap = float(np.linalg.norm(seq.V[0] - seq.V[-1], axis=-1).max() * seq.fps)
            self.seam_speed = wrap
            speed = max(speed, wrap)
        self.max_speed = speed
        self.max_frame_step = speed / self.fps  # largest vertex displacement per frame [m]
        F = seq.F
        edges = np.linalg.norm(seq.V[:, F[:, [1, 2, 0]]] - seq.V[:, F], axis=-1)  # (T, M, 3)
        self.average_edge_length = edges.mean(axis=(1, 2)).astype(np.float32)  # (T,) [m], host
        self.max_abs_coordinate = float(np.abs(seq.V).max())  # [m], host

    # What the rest of the package asks of a surface, answered by each surface class (no type
    # checks elsewhere): the colliders it supports, its state buffers, the indices of a frame,
    # the host mesh at a time, the faces every frame shares, the frame (k0, k1, alpha) it plays.
    #: colliders this surface supports
    colliders = tuple(values(Collider))
    #: the topology, for reports (summary, checkpoint fingerprint)
    topology = "fixed"

    @classmethod
    def colliders_for(cls, seq) -> tuple:
        """The colliders a surface of ``seq`` supports (known before any upload)."""
        return cls.colliders

    def resolve_collider(self, asked: str, choose) -> str:
        """``fixed`` (automatic): ``choose((swept, refit))`` (the measured faster one) when
        interpolating; else ``refit`` (swept boxes span the interpolated motion between frames)."""
        if asked != Collider.FIXED:
            return asked
        if not self.interpolate:
            return Collider.REFIT.value
        return choose((Collider.SWEPT.value, Collider.REFIT.value))

    def faces(self) -> np.ndarray:
        """(M, 3) int32 faces shared by every frame (host)."""
        return self.sequence.F

    def indices_at(self, frame: int):
        """Device (3M,) indices of ``frame``: the same array for every frame."""
        return self.indices

    def segment_at(self, frame: int) -> int:
        """One segment: the topology never changes."""
        return 0

    def allocate_state(self, state: "State") -> None:
        """State-owned buffers of the current surface: points, velocities, face normals."""
        d = self.device
        state.points = wp.zeros(self.num_vertices, dtype=wp.vec3, device=d)
        state.velocities = wp.zeros(self.num_vertices, dtype=wp.vec3, device=d)
        state.face_normals = wp.zeros(self.num_faces, dtype=wp.vec3, device=d)

    def host_mesh_at(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """(V (N, 3) float64, F) of the surface at ``time`` [s] as the step plays it (frames k,
        k+1 blended when interpolating): the host twin of ``update_frame_vertices``."""
        k0, k1, a = frame_pair_host(time, self.fps, self.num_frames, self.playback)
        V = self.sequence.V[k0].astype(np.float64)
        if self.interpolate:
            V = V * (1.0 - a) + self.sequence.V[k1].astype(np.float64) * a
        return V, self.sequence.F

    def update_state(self, state: "State", time: float, launch) -> int:
        """Stage 1 (on the device clock ``state.sim_time``): the vertex buffer and velocities at
        the current time, one launch of ``update_frame_vertices``; returns the frame k0 at the
        host twin ``time`` [s]. ``launch(kernel, dim, inputs, outputs)`` is the world's."""
        launch(update_frame_vertices, self.num_vertices,
               [self.frames, state.sim_time, self.fps, self.playback, int(self.interpolate)],
               [state.points, state.velocities])
        return 0

    def geometry_digest_inputs(self) -> tuple[list[np.ndarray], int, int]:
        """Arrays that fix the geometry (for a checkpoint's fingerprint), vertex and face counts."""
        return [self.sequence.V, self.sequence.F], int(self.num_vertices), int(self.num_faces)


class VaryingSurfaceModel:
    """Static data of a varying-topology surface, held as segments: maximal runs of frames that
    share their faces (``VaryingTopologySequence.segments()``: one per frame for a truly varying
    sequence, a few for a piecewise-fixed one such as ``convert`` writes where one template could
    not follow the input).

    Attributes:
        segment_frames: list of wp.array2d(vec3) (T_s, N_s) [m], the vertices of each segment's
            frames; segment_indices: list of wp.array(int32) (3M_s,), each segment's faces.
        segment_of: (T,) int host array, the segment of each frame; segment_start: (S,) its first frame.
        fps, playback, num_frames: as in :class:`SurfaceModel`.
        interpolate: blend frames k and k+1 when both lie in one segment (there the vertices
            correspond); across a segment boundary, and between the frames of a truly varying
            sequence, frame k is held and the surface velocity is zero.
        max_speed: largest vertex speed within a segment [m/s]; max_frame_step: the same per frame [m].
    """

    def __init__(self, seq: VaryingTopologySequence, device=None, playback: str = DEFAULT_PLAYBACK,
                 interpolate: bool = True):
        playback = resolve_playback(seq, playback)
        self.sequence = seq
        self.device = wp.get_device(device)
        runs = seq.segments()
        self.segment_of = np.repeat(np.arange(len(runs)), [b - a for a, b in runs])
        self.segment_start = np.array([a for a, _ in runs], np.int64)
        stacks = [np.stack([seq.frames[t][0] for t in range(a, b)]) for a, b in runs]
        self.segment_frames = [wp.array(V, dtype=wp.vec3, device=self.device) for V in stacks]
        self.segment_indices = [wp.array(seq.frames[a][1].reshape(-1), dtype=wp.int32, device=self.device)
                                for a, _ in runs]
        self.fps = float(seq.fps)
        self.num_frames = seq.num_frames
        self.playback_name = playback
        self.playback = PLAYBACK_MODES[playback]
        self.interpolate = bool(interpolate) and any(b - a > 1 for a, b in runs)
        self.colliders = self.colliders_for(seq, runs)
        step = max((float(np.linalg.norm(np.diff(V, axis=0), axis=-1).max()) for V in stacks if len(V) > 1),
                   default=0.0)
        self.max_frame_step = step  # largest vertex displacement between frames of one segment [m]
        self.max_speed = step * self.fps
        self.motion_speed, self.seam_speed = self.max_speed, 0.0  # as SurfaceModel's (no seam counted here)

    #: without vertex correspondence only a BVH built per segment, frame or step can follow it
    colliders = (Collider.REBUILD.value,)
    topology = "varying"

    @classmethod
    def colliders_for(cls, seq, runs: list | None = None) -> tuple:
        """``rebuild``; also ``fixed`` (the automatic choice, which takes ``rebuild``) for a
        piecewise-fixed sequence (``seq.is_piecewise_fixed()``; ``runs``: its segments when
        known): a truly varying one is refused unless asked for by name, so that its user
        hears that converting it gives interpolation and the faster colliders."""
        return cls.colliders + ((Collider.FIXED.value,) if seq.is_piecewise_fixed(runs) else ())

    def resolve_collider(self, asked: str, choose) -> str:
        return Collider.REBUILD.value  # the automatic choice too: only "rebuild" follows it

    def faces(self) -> np.ndarray:
        raise ValueError(f"{self.sequence.name}: a varying-topology surface has no faces shared by every frame "
                         "(convert it to fixed topology first: python -m dynmesh_warp.convert)")

    def indices_at(self, frame: int):
        return self.segment_indices[self.segment_of[frame]]

    def segment_at(self, frame: int) -> int:
        """The segment of ``frame`` (a rebuild collider's ``rebuild_every: segment`` key)."""
        return int(self.segment_of[frame])

    def allocate_state(self, state: "State") -> None:
        """Per-step buffers sized to the largest segment; the current segment's vertices go in
        their first N_s entries (State never aliases the Model's frames)."""
        d = self.device
        n = max(int(p.shape[1]) for p in self.segment_frames)
        m = max(int(i.shape[0]) // 3 for i in self.segment_indices)
        state.points_buffer = wp.zeros(n, dtype=wp.vec3, device=d)
        state.velocities_buffer = wp.zeros(n, dtype=wp.vec3, device=d)
        state.normals_buffer = wp.zeros(m, dtype=wp.vec3, device=d)
        state.segment_views = {}  # segment -> views of the buffers, made once (launch caches key on them)
        state.frame_shown = None
        self.update_state(state, 0.0, None)

    def _pair(self, time: float) -> tuple[int, int, int, float]:
        """(segment, k0, k1, alpha) at ``time``: k1 = k0 and alpha = 0 (frame k0 held) unless
        interpolating within one segment; k0, k1 are indices within the segment."""
        k0, k1, a = frame_pair_host(time, self.fps, self.num_frames, self.playback)
        s = int(self.segment_of[k0])
        start = int(self.segment_start[s])
        if k1 == k0 or self.segment_of[k1] != s:
            return s, k0 - start, k0 - start, 0.0
        return s, k0 - start, k1 - start, (a if self.interpolate else 0.0)

    def update_state(self, state: "State", time: float, launch) -> int:
        """Stage 1 on the host clock ``time`` [s]: the segment's frames k0, k1 blended (or frame
        k0 held) into the state's buffers with the velocity (V[k1] - V[k0]) * fps, as the fixed
        surface does; returns the frame k0. Not capturable (a segment's size changes the launches)."""
        s, k0, k1, a = self._pair(time)
        views = state.segment_views
        if s not in views:
            n = int(self.segment_frames[s].shape[1])
            m = int(self.segment_indices[s].shape[0]) // 3
            views[s] = (state.points_buffer[:n], state.velocities_buffer[:n], state.normals_buffer[:m])
        state.points, state.velocities, state.face_normals = views[s]
        key = (s, k0, k1, a)
        if state.frame_shown != key:
            wp.launch(blend_segment_vertices, state.points.shape[0],
                      inputs=[self.segment_frames[s], k0, k1, float(a), float(self.fps)],
                      outputs=[state.points, state.velocities], device=self.device)
            state.frame_shown = key
        return k0 + int(self.segment_start[s])

    def host_mesh_at(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """(V float64, F) at ``time`` as the step plays it: frames k, k+1 of one segment
        blended when interpolating, else frame k held."""
        s, k0, k1, a = self._pair(time)
        start = int(self.segment_start[s])
        v0 = np.asarray(self.sequence.frames[start + k0][0], np.float64)
        v1 = np.asarray(self.sequence.frames[start + k1][0], np.float64)
        return v0 * (1.0 - a) + v1 * a, np.asarray(self.sequence.frames[start + k0][1])

    def geometry_digest_inputs(self) -> tuple[list[np.ndarray], int, int]:
        seq = self.sequence
        return ([a for v, f in seq.frames for a in (v, f)], sum(len(v) for v, _ in seq.frames),
                sum(len(f) for _, f in seq.frames))


def surface_model_class(seq) -> type:
    """The surface class of a sequence (its ``colliders`` can be checked before any upload):
    :class:`SurfaceModel` for fixed topology, :class:`VaryingSurfaceModel` for varying."""
    if isinstance(seq, FixedTopologySequence):
        return SurfaceModel
    if isinstance(seq, VaryingTopologySequence):
        return VaryingSurfaceModel
    raise TypeError(f"expected a FixedTopologySequence or VaryingTopologySequence, got {type(seq).__name__}")


def surface_model(seq, device=None, playback: str = DEFAULT_PLAYBACK, interpolate: bool = True):
    """The surface model of a sequence (frames uploaded to ``device``); varying topology holds
    each frame, so ``interpolate`` applies to fixed topology only."""
    return surface_model_class(seq)(seq, device, playback=playback, interpolate=interpolate)


def _sphere_rows(name: str, values, count: int, first: int = 0) -> np.ndarray:
    """``values`` as (count, 3) float32 rows of spheres ``first``.., refusing another shape (a
    (3, S) stack of x, y and z rows was read as scrambled rows: a new user's) or a non-finite row
    (ValueError naming ``name``, "position" or "velocity", and the sphere). A flat (3 count,)
    array is taken row by row."""
    names = {"position": "positions", "velocity": "velocities", "spin": "spins"}[name]
    try:
        a = np.asarray(values, np.float32)
    except (TypeError, ValueError) as e:
        raise ValueError(f"sphere {names}: expected numbers, ({count}, 3) [x, y, z] rows ({e})") from None
    if a.shape != (count, 3) and not (a.ndim == 1 and a.size == 3 * count):
        raise ValueError(f"sphere {names}: expected ({count}, 3) [x, y, z] rows, one per sphere"
                         + (f" from sphere {first}" if first else "") + f", got shape {a.shape}")
    a = a.reshape(count, 3)
    bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
    if bad.size:
        raise ValueError(f"sphere {first + int(bad[0])}: {name} {a[bad[0]].tolist()} is not finite")
    return a


class SphereModel:
    """Static sphere data. radius (S,) [m]; inv_mass (S,) [1/kg], 0 for kinematic spheres;
    host twins radius_np (S,) float32 [m] and mass_np (S,) float64 [kg] (0 or inf: kinematic)."""

    def __init__(self, radius, mass, device=None):
        radius = np.asarray(radius, dtype=np.float32)
        if radius.ndim > 1:
            raise ValueError(f"sphere radius: expected one value per sphere, shape (S,), got shape {radius.shape}")
        radius = radius.reshape(-1)
        try:
            mass = np.broadcast_to(np.asarray(mass, dtype=np.float64), radius.shape)
        except ValueError:
            raise ValueError(f"sphere mass: expected one value or one per sphere ({radius.size}), got shape "
                             f"{np.shape(mass)}") from None
        if (radius <= 0).any() or not np.isfinite(radius).all():
            raise ValueError("sphere radius must be positive and finite")
        if (mass < 0).any() or np.isnan(mass).any():
            raise ValueError("sphere mass must be >= 0 (0 or inf = kinematic)")
        inv = np.where((mass > 0) & np.isfinite(mass), 1.0 / np.where(mass > 0, mass, 1.0), 0.0)
        self.count = int(radius.size)
        self.radius = wp.array(radius, dtype=float, device=device)
        self.inv_mass = wp.array(inv.astype(np.float32), dtype=float, device=device)
        self.radius_np = radius
        self.mass_np = np.array(mass, dtype=np.float64)


class Model:
    """Everything static: the surface, the spheres and the physics parameters."""

    def __init__(self, surface, spheres: SphereModel, params: PhysicsParams):
        self.surface = surface
        self.spheres = spheres
        self.params = params
        self.device = surface.device


class State:
    """Per-step data.

    Attributes:
        sim_time: (1,) float64 simulation time [s] (device clock, advanced by the step).
        frame_key: (1,) int32 the clock's frame pair k0 * num_frames + k1 at sim_time;
        frame_changed: (1,) int32 1 when the last clock advance (or time change) moved to another
        frame pair, else 0 (written by the step's integrate stage; a collider that rebuilds per
        frame pair, the swept one, reads it).
        points: (N,) vec3 current surface vertices [m]; velocities: (N,) vec3 [m/s].
        face_normals: (M,) vec3 unit normals of the current surface.
        sphere_pos: (S,) vec3 centres [m]; sphere_vel: (S,) vec3 [m/s]; sphere_spin: (S,) vec3
        angular velocities [rad/s] (stay as given where ``PhysicsParams.sphere_body`` is ``point``).
    """

    def __init__(self, model: Model, positions, velocities=None, t0: float = 0.0, spins=None):
        d = model.device
        surf = model.surface
        self.sim_time = wp.array([t0], dtype=wp.float64, device=d)
        self.frame_key = wp.full(1, -1, dtype=wp.int32, device=d)
        self.frame_changed = wp.zeros(1, dtype=wp.int32, device=d)
        self.update_frame_key(model)
        surf.allocate_state(self)  # points, velocities, face_normals: owned by the state
        S = model.spheres.count
        pos = _sphere_rows("position", positions, S)
        vel = np.zeros((S, 3), np.float32) if velocities is None else _sphere_rows("velocity", velocities, S)
        self.sphere_pos = wp.array(pos, dtype=wp.vec3, device=d)
        self.sphere_vel = wp.array(vel, dtype=wp.vec3, device=d)
        spin = np.zeros((S, 3), np.float32) if spins is None else _sphere_rows("spin", spins, S)
        warn_spins_kept(spin, model.params.sphere_body, "State")
        self.sphere_spin = wp.array(spin, dtype=wp.vec3, device=d)


    def update_frame_key(self, model: Model):
        """frame_key at sim_time; frame_changed = 1 if that differs from the stored key (eager
        or captured launch; after the clock was moved between steps)."""
        surf = model.surface
        wp.launch(detect_frame_change, dim=1, inputs=[self.sim_time, surf.fps, surf.num_frames, surf.playback],
                  outputs=[self.frame_key, self.frame_changed], device=model.device)


class Contacts:
    """Contact of each sphere with the surface at the last (sub)step.

    face (S,) int32, -1 when none; point (S,) vec3 closest surface point [m]; normal (S,) vec3
    unit, towards the sphere's free side; depth (S,) float radius - signed centre distance [m]
    (> 0 penetrating); velocity (S,) vec3 surface velocity at the point [m/s].
    memory (S,) ``kernels.integrate.pinch_memory`` (16 floats): the integrator's pinch memory,
    kept from one sub-step to the next: each sphere's contact of its last sub-step and the other
    side of its last pinch (normals, velocities, plane offsets, the other side's age). A contact
    facing one of these planes, both touched and closing on each other, is a pinch
    (``kernels.integrate.advance_sphere``).
    """

    def __init__(self, count: int, device=None):
        self.face = wp.full(count, -1, dtype=wp.int32, device=device)
        self.point = wp.zeros(count, dtype=wp.vec3, device=device)
        self.normal = wp.zeros(count, dtype=wp.vec3, device=device)
        self.depth = wp.zeros(count, dtype=float, device=device)
        self.velocity = wp.zeros(count, dtype=wp.vec3, device=device)
        self.memory = wp.zeros(count, dtype=pinch_memory, device=device)

    def numpy(self) -> dict:
        """The contact fields as NumPy copies (on the CPU ``wp.array.numpy()`` is a view that the next
        step overwrites: a new user's log of five steps' contacts read back five times the last)."""
        return {k: getattr(self, k).numpy().copy() for k in ("face", "point", "normal", "depth", "velocity")}


# ---------------------------------------------------------------------------------------------
# The step's stages: functions of (Model, State, Contacts, StepContext).
# ---------------------------------------------------------------------------------------------


class StepContext:
    """What the step's stages take besides ``(Model, State, Contacts)``: the sub-step length and
    contact reach, the launch function, and the host's bookkeeping of the clock. A ``World``
    owns one and keeps it current; the stages and the colliders read it (they never see the
    world).

    Attributes:
        device: the Warp device.
        launch: ``launch(kernel, dim, inputs, outputs)`` (the world's, with its CPU replay cache).
        sub_dt: sub-step length [s]; extra_speed: speed gained from gravity in one sub-step [m/s]
            (part of the contact query reach); gravity: wp.vec3 [m/s^2].
        time: host twin of ``State.sim_time`` [s] (the same float64 additions as the device).
        frame: the frame whose indices the last surface update used (0 for fixed topology, the
            held frame k for varying topology).
    """

    def __init__(self, device, launch, gravity, sub_dt: float = 0.0, extra_speed: float = 0.0, time: float = 0.0):
        self.device = device
        self.launch = launch
        self.gravity = gravity
        self.sub_dt = float(sub_dt)
        self.extra_speed = float(extra_speed)
        self.time = float(time)
        self.frame = 0

    def indices(self, model: Model):
        """The current triangle indices (3M,) of the surface."""
        return model.surface.indices_at(self.frame)

    def frame_key(self, model: Model):
        """Host-side frame key at ``time``: (k0, k1, alpha) with interpolation, else k0."""
        surf = model.surface
        k0, k1, a = frame_pair_host(self.time, surf.fps, surf.num_frames, surf.playback)
        return (k0, k1, a) if surf.interpolate else k0


def update_surface(model: Model, state: State, ctx: StepContext):
    """Stage 1: the vertex buffer (``state.points``, ``state.velocities``) at ``ctx.time``."""
    ctx.frame = model.surface.update_state(state, ctx.time, ctx.launch)


def compute_normals(model: Model, state: State, ctx: StepContext):
    """Stage 2: per-face normals of the current vertex buffer (``state.face_normals``)."""
    idx = ctx.indices(model)
    ctx.launch(compute_face_normals, idx.shape[0] // 3, [state.points, idx], [state.face_normals])


def collide_mesh(model: Model, state: State, contacts: "Contacts", ctx: StepContext, mesh_id, seed: bool = False,
                 tie_distance: float = 0.0):
    """Stage 3 on a ``wp.Mesh`` over the current vertex buffer (refit / rebuild colliders).
    ``seed``: each query reaches no farther than the previous contact face's distance +
    ``tie_distance`` [m] (``collide_sphere_mesh``; the same contacts)."""
    m, s, c = model, state, contacts
    ctx.launch(collide_sphere_mesh, m.spheres.count,
               [ctx.indices(m), m.spheres.radius, s.points, s.velocities, s.sphere_pos, s.sphere_vel,
                mesh_id, ctx.sub_dt, ctx.extra_speed, m.params.margin, int(seed), float(tie_distance)],
               [c.face, c.point, c.normal, c.depth, c.velocity])


def integrate(model: Model, state: State, contacts: "Contacts", ctx: StepContext):
    """Stage 4: sphere dynamics with the contacts of this sub-step; advances the device clock
    and its frame pair (``State.frame_key`` / ``frame_changed``)."""
    m, s, c = model, state, contacts
    surf = m.surface
    ctx.launch(integrate_spheres, max(m.spheres.count, 1),
               [m.spheres.inv_mass, m.spheres.radius, ctx.gravity,
                ctx.sub_dt, m.params.restitution, m.params.friction, m.params.rest_speed,
                int(m.params.ground_height is not None),
                float(m.params.ground_height if m.params.ground_height is not None else 0.0),
                ctx.sub_dt, surf.fps, surf.num_frames, surf.playback, SPHERE_INERTIA[m.params.sphere_body],
                c.face, c.normal, c.depth, c.velocity],
               [s.sphere_pos, s.sphere_vel, s.sphere_spin, s.sim_time, s.frame_key, s.frame_changed, c.memory])


def substep(model: Model, state: State, contacts: "Contacts", collider: "ColliderBase", ctx: StepContext):
    """One sub-step: surface (if the collider needs the vertex buffer), acceleration structure,
    contacts, dynamics. Device work only (capturable when the collider is); the caller advances
    ``ctx.time``."""
    if collider.needs_points:
        update_surface(model, state, ctx)
    collider.update(model, state, ctx)
    if model.spheres.count:
        collider.collide(model, state, contacts, ctx)
    integrate(model, state, contacts, ctx)


# ---------------------------------------------------------------------------------------------
# Colliders: how the acceleration structure follows the surface.
# ---------------------------------------------------------------------------------------------


class ColliderBase:
    """The collider protocol: how a step finds the surface. Every hook is defined here (a no-op
    where a collider has nothing to do), so the world calls them without ``getattr`` probes.

    Hooks take ``(model, state, ctx)`` (a :class:`StepContext`), never the world:

    - ``update(model, state, ctx)``: the acceleration structure for the current time (in the step).
    - ``collide(model, state, contacts, ctx)``: sphere contacts into ``contacts`` (in the step).
    - ``refresh(model, state, ctx)``: after the clock was moved between steps (default: ``update``).
    - ``resize(model, state, ctx)``: after the number of spheres changed.
    - ``spheres_moved(model, state, ctx)``: after sphere positions/velocities were set between steps.
    - ``checkpoint_state()`` / ``restore_checkpoint_state(st)``: per-run state a step reads.
    """

    name = "base"
    capturable = False
    needs_points = True

    def update(self, model: Model, state: State, ctx: StepContext):
        raise NotImplementedError

    def collide(self, model: Model, state: State, contacts: "Contacts", ctx: StepContext):
        raise NotImplementedError

    def refresh(self, model: Model, state: State, ctx: StepContext):
        self.update(model, state, ctx)

    def resize(self, model: Model, state: State, ctx: StepContext):
        pass

    def spheres_moved(self, model: Model, state: State, ctx: StepContext):
        pass

    def checkpoint_state(self) -> dict:
        return {}

    def restore_checkpoint_state(self, st: dict):
        pass


class RefitCollider(ColliderBase):
    """Fixed topology: one ``wp.Mesh`` BVH built at start, refit to the current vertices each
    sub-step (the reference path: per-step vertex copy/interpolation + refit)."""

    name = "refit"
    capturable = True
    needs_points = True

    def __init__(self, model: Model, state: State, ctx: StepContext):
        ctor, leaf = REFIT_BVH[device_kind(state.points.device)]
        self.mesh = wp.Mesh(points=state.points, indices=model.surface.indices, velocities=state.velocities,
                            bvh_constructor=ctor, bvh_leaf_size=leaf)
        self.seed = bool(SEED_REFIT_QUERY[device_kind(state.points.device)])
        # twice Warp's tie epsilon (1e-3 x the mesh's average edge) at the frame of the longest
        # edges (a blended triangle's edges are no longer than its frames': triangle inequality),
        # plus float32 rounding at the surface's coordinates (~1e-7 relative, kept 10x)
        surf = model.surface
        self.tie_distance = 2.0e-3 * float(np.max(surf.average_edge_length)) + 1.0e-6 * surf.max_abs_coordinate

    def update(self, model: Model, state: State, ctx: StepContext):
        self.mesh.refit()

    def collide(self, model: Model, state: State, contacts: "Contacts", ctx: StepContext):
        collide_mesh(model, state, contacts, ctx, self.mesh.id, self.seed, self.tie_distance)


class RebuildCollider(ColliderBase):
    """The varying-topology collider: a ``wp.Mesh`` built when the topology changes and refit
    in between (``every="segment"``, the default: once per segment of a piecewise-fixed
    sequence, once per frame of a truly varying one); or built from scratch every sub-step (the
    baseline, ``"step"``) or when the reconstruction frame changes (``"frame"``)."""

    name = "rebuild"
    capturable = False
    needs_points = True

    def __init__(self, model: Model, state: State, ctx: StepContext, every: str = DEFAULT_REBUILD_EVERY):
        every = parse(RebuildEvery, every, "rebuild_every").value
        if every == "frame" and model.surface.interpolate:
            raise ValueError("rebuild_every 'frame' needs a surface that changes only per frame: "
                             "set surface.interpolate: false (with interpolation it changes every step), or use "
                             "rebuild_every: segment (the default: a new BVH when the faces change, refit between)")
        self.every = every
        self.mesh = None
        self._key = self._shown = None

    def update(self, model: Model, state: State, ctx: StepContext):
        key = model.surface.segment_at(ctx.frame) if self.every == "segment" else ctx.frame_key(model)
        shown = getattr(state, "frame_shown", None)  # a varying surface's last blend (a fixed one moves every step)
        if self.mesh is None or self.every == "step" or key != self._key:
            self.mesh = wp.Mesh(points=state.points, indices=ctx.indices(model), velocities=state.velocities)
            self._key, self._shown = key, shown
        elif self.every == "segment" and (shown is None or shown != self._shown):
            self.mesh.refit()  # the segment's faces, its vertices moved in the buffer the mesh was built over
            self._shown = shown

    def collide(self, model: Model, state: State, contacts: "Contacts", ctx: StepContext):
        collide_mesh(model, state, contacts, ctx, self.mesh.id)


class SphereGrid:
    """The swept collider's ``sphere_grid`` search (kernels/sphere_grid.py): the spheres binned
    every step into a hashed two-level grid by their search radius, then one thread per face.

    Attributes (allocated for ``n`` spheres):
        cell_size: wp.vec2 the cell edge of levels 0 and 1 [m]: level 0 SPHERE_GRID_CELL_SCALE x
            the median sphere's radius + margin (no smaller than the mean edge), level 1
            SPHERE_GRID_LEVEL_SCALE x that and no smaller than the largest sphere's radius + margin.
        num_buckets: the hash table's size (SPHERE_GRID_BUCKETS_PER_SPHERE a sphere, a power of 2).
        surface_lower / surface_upper: wp.vec3 the box of every frame of the surface [m].
        sphere_reach, sphere_bound: (n,) float [m]; sphere_level: (n,) int32 (-1 none, 0, 1, 2).
        bucket_count, bucket_start: (num_buckets + 1,) int32 (the counts are zero between steps).
        cell_spheres: (27 n,) int32 and cell_sphere_balls: (27 n,) vec4 (centre [m], bound [m]).
        level_count: (3,) int32; every_face_spheres: (n,) int32.
    """

    def __init__(self, model: Model, n: int, device):
        d = device
        surf = model.surface
        V = np.asarray(surf.sequence.V).reshape(-1, 3)  # host: every frame
        self.surface_lower, self.surface_upper = wp.vec3(*V.min(axis=0)), wp.vec3(*V.max(axis=0))
        r = model.spheres.radius.numpy() if model.spheres.count else np.zeros(1, np.float32)
        # level-0 cells: SPHERE_GRID_CELL_SCALE x the median sphere's radius + margin (its search
        # radius at rest), no smaller than the mean edge (H100 sweep of 1-8x: docs/benchmarks.md)
        h = float(max(SPHERE_GRID_CELL_SCALE * (np.median(r) + model.params.margin),
                      float(surf.average_edge_length.mean()), 1e-9))
        # level 1 holds the largest sphere at rest too (a ball fits a level up to 1.5 cells wide):
        # with mixed sizes the large spheres go there, not to the list every face tests
        h1 = max(SPHERE_GRID_LEVEL_SCALE * h, 1.0 * (float(r.max()) + model.params.margin))
        self.cell_size = wp.vec2(h, h1)
        self.num_buckets = int(max(1024, 1 << int(np.ceil(np.log2(max(n, 1) * SPHERE_GRID_BUCKETS_PER_SPHERE)))))
        self.sphere_reach = wp.zeros(n, dtype=float, device=d)
        self.sphere_bound = wp.zeros(n, dtype=float, device=d)
        self.sphere_level = wp.zeros(n, dtype=wp.int32, device=d)
        self.bucket_count = wp.zeros(self.num_buckets + 1, dtype=wp.int32, device=d)
        self.bucket_start = wp.zeros(self.num_buckets + 1, dtype=wp.int32, device=d)
        # a sphere of level 0 or 1 spans at most CELL_RANGE^3 = 27 cells
        self.cell_spheres = wp.zeros(n * 27, dtype=wp.int32, device=d)
        self.cell_sphere_balls = wp.zeros(n * 27, dtype=wp.vec4, device=d)
        self.level_count = wp.zeros(3, dtype=wp.int32, device=d)
        self.every_face_spheres = wp.zeros(n, dtype=wp.int32, device=d)

    def bin_spheres(self, model: Model, state: State, contacts: "Contacts", ctx: StepContext, epsilon: float):
        """Each sphere's reach, bound and level, counted into the buckets, the scan, the scatter."""
        m, s = model, state
        surf = m.surface
        S = m.spheres.count
        self.level_count.zero_()
        ctx.launch(compute_sphere_bounds, S,
                   [surf.frames, surf.indices, m.spheres.radius, s.sim_time, s.sphere_pos, s.sphere_vel, contacts.face,
                    self.surface_lower, self.surface_upper, surf.fps, surf.playback, int(surf.interpolate),
                    epsilon, ctx.sub_dt, ctx.extra_speed, m.params.margin, self.cell_size],
                   [self.sphere_reach, self.sphere_bound, self.sphere_level, self.level_count,
                    self.every_face_spheres])
        grid_in = [s.sphere_pos, self.sphere_bound, self.sphere_level, epsilon, self.cell_size, self.num_buckets]
        ctx.launch(count_sphere_cells, (S, 27), grid_in, [self.bucket_count])
        wp.utils.array_scan(self.bucket_count, self.bucket_start, inclusive=False)
        ctx.launch(scatter_sphere_cells, (S, 27), [*grid_in, self.bucket_start],
                   [self.bucket_count, self.cell_spheres, self.cell_sphere_balls])

    def collide(self, model: Model, state: State, contacts: "Contacts", ctx: StepContext, epsilon: float,
                vertex_face_offsets, vertex_faces, best_key):
        """Bin the spheres, one pass over the faces into ``best_key`` (NO_KEY before), then each
        sphere's contact from its key (``resolve_closest_per_sphere``: a block a sphere, or one
        thread a sphere from SPHERE_GRID_SERIAL_RESOLVE spheres on)."""
        m, s, c = model, state, contacts
        surf = m.surface
        S = m.spheres.count
        if not S:
            return
        self.bin_spheres(m, s, c, ctx, epsilon)
        clock = [surf.fps, surf.playback, int(surf.interpolate), epsilon]
        ctx.launch(find_closest_in_sphere_cells, surf.num_faces,
                   [surf.frames, surf.indices, s.sim_time, s.sphere_pos, *clock, self.cell_size, self.num_buckets,
                    self.sphere_reach, self.sphere_bound, self.bucket_start, self.cell_spheres, self.cell_sphere_balls,
                    self.level_count, self.every_face_spheres], [best_key])
        resolve_in = [surf.frames, surf.indices, m.spheres.radius, vertex_face_offsets, vertex_faces,
                      s.sim_time, s.sphere_pos, s.sphere_vel, *clock, ctx.sub_dt, ctx.extra_speed, m.params.margin]
        resolve_out = [best_key, c.face, c.point, c.normal, c.depth, c.velocity]
        if S >= SPHERE_GRID_SERIAL_RESOLVE:
            ctx.launch(resolve_closest_per_sphere_serial, S, resolve_in, resolve_out)
        else:
            wp.launch_tiled(resolve_closest_per_sphere, dim=S, inputs=resolve_in, outputs=resolve_out,
                            block_dim=SWEPT_RESOLVE_THREADS, device=ctx.device)


class SweptCollider(ColliderBase):
    """Fixed topology with interpolation, at per-frame cost: a ``wp.Bvh`` over each face's box
    across the frame interval [k, k+1], refit only when the frame pair changes (a device-side
    test and a conditional graph node), and a contact kernel that evaluates the interpolated
    triangles itself. No per-step vertex copy or BVH refit.

    ``search`` (:class:`~dynmesh_warp.choices.SweptSearch`; default per device kind,
    ``DEFAULT_SWEPT_SEARCH``): how each step finds a sphere's closest feature among the faces
    its box query returns. ``serial``: one thread per sphere walks them (the CPU's path).
    ``tiled`` (CUDA default): one block of ``tile_threads`` threads per sphere walks the query
    together and reduces (``wp.tile_bvh_query_aabb``), so a sphere with thousands of faces in
    reach costs tens of dependent loads, not thousands (issue 14). Both give the serial rule's
    contacts (the tiled one picks the lowest face index among exactly equal distances).
    ``faces``: no BVH walk; one thread per face tests every sphere and the closest candidate per
    sphere is an atomic minimum (``find_closest_per_face``), then each sphere's contact with the
    ties looked for around the winning face's vertices (``resolve_closest_per_sphere``); its
    work is one pass over the faces' boxes per step times the sphere count, for few spheres on
    large meshes, where a sphere's box holds hundreds of faces; the BVH is not refit then.
    ``sphere_grid``: the face-parallel search for many spheres: each step the spheres are binned
    in a hashed grid by their search radius (the reach, or the distance to the previous contact
    face when less) and one thread per face tests the spheres of the cells its triangle at the
    step's time overlaps (kernels/sphere_grid.py); no BVH walk and no refit either.
    Measured per search, and the searches tried and dropped: docs/benchmarks.md.
    """

    name = "swept"
    capturable = True
    needs_points = False

    def __init__(self, model: Model, state: State, ctx: StepContext, search: str | None = None,
                 tile_threads: int | None = None):
        surf = model.surface
        d = ctx.device
        search = model.params.swept_search if search is None else search
        self.search = (DEFAULT_SWEPT_SEARCH[device_kind(d)] if search is None
                       else parse(SweptSearch, search, "swept_search"))
        if self.search in (SweptSearch.HYBRID, SweptSearch.GRID):
            raise ValueError(f"swept_search '{self.search}' is a batched world's search (envs); a single world's swept "
                             "collider searches 'serial', 'tiled', 'faces' or 'sphere_grid'")
        self.tile_threads = int(tile_threads or SWEPT_TILE_THREADS)
        self.resize(model, state, ctx)
        self.vertex_face_offsets = self.vertex_faces = None
        if self.search in (SweptSearch.FACES, SweptSearch.SPHERE_GRID):  # the faces around each vertex (CSR): ties
            F = surf.faces().ravel()
            counts = np.bincount(F, minlength=surf.num_vertices)
            self.vertex_face_offsets = wp.array(np.concatenate([[0], np.cumsum(counts)]).astype(np.int32), device=d)
            self.vertex_faces = wp.array((np.argsort(F, kind="stable") // 3).astype(np.int32), device=d)
        self.lowers = wp.zeros(surf.num_faces, dtype=wp.vec3, device=d)
        self.uppers = wp.zeros(surf.num_faces, dtype=wp.vec3, device=d)
        self.compute_bounds(model, state, ctx)
        self.bvh = wp.Bvh(self.lowers, self.uppers, leaf_size=4)  # cheaper per-frame refit on CPU
        # tie tolerance of the closest-feature search, as wp.Mesh: 1e-3 x average edge length
        self.epsilon = 1.0e-3 * float(surf.average_edge_length.mean())

    def compute_bounds(self, model: Model, state: State, ctx: StepContext):
        surf = model.surface
        ctx.launch(compute_swept_bounds, surf.num_faces,
                      [surf.frames, surf.indices, state.sim_time, surf.fps, surf.playback],
                      [self.lowers, self.uppers])

    def refit_frame(self, model: Model, state: State, ctx: StepContext):
        if self.search == SweptSearch.SPHERE_GRID:  # it reads neither the swept boxes nor the tree
            return
        self.compute_bounds(model, state, ctx)
        if self.search != SweptSearch.FACES:  # the face-parallel search reads the boxes only
            self.bvh.refit()

    def resize(self, model: Model, state: State, ctx: StepContext):
        """The face-parallel searches' per-sphere scratch: the closest key (NO_KEY between
        steps); the sphere grid (``sphere_grid``)."""
        d = ctx.device
        S = model.spheres.count
        n = max(S, 1) if self.search in (SweptSearch.FACES, SweptSearch.SPHERE_GRID) else 0
        self.best_key = wp.full(n, NO_KEY, dtype=wp.int64, device=d)
        self.grid = SphereGrid(model, n, d) if self.search == SweptSearch.SPHERE_GRID else None

    def update(self, model: Model, state: State, ctx: StepContext):
        """Refit if the clock's frame pair changed (``State.frame_changed``: set by the previous
        sub-step's integrate stage, or by the world when the clock was moved)."""
        wp.capture_if(state.frame_changed, on_true=self.refit_frame, model=model, state=state, ctx=ctx)

    #: per-frame state a step reads before writing it again: the swept bounds (the BVH is refit
    #: from them). (The frame pair and the pending-refit flag are the clock's:
    #: State.frame_key / frame_changed.)
    CHECKPOINT_ARRAYS = ("lowers", "uppers")

    def checkpoint_state(self) -> dict:
        return {k: getattr(self, k).numpy().copy() for k in self.CHECKPOINT_ARRAYS}

    def restore_checkpoint_state(self, st: dict):
        for k in self.CHECKPOINT_ARRAYS:
            getattr(self, k).assign(st[k])
        self.bvh.refit()  # the tree's topology comes from the build at the initial time, as in the run

    def collide(self, model: Model, state: State, contacts: "Contacts", ctx: StepContext):
        m, s, c = model, state, contacts
        surf = m.surface
        # kernel argument groups (kernels/swept.py): Model, State in, In, Out
        model_in = [surf.frames, surf.indices, m.spheres.radius]
        state_in = [s.sim_time, s.sphere_pos, s.sphere_vel]
        step_in = [surf.fps, surf.playback, int(surf.interpolate), self.epsilon, ctx.sub_dt, ctx.extra_speed,
                   m.params.margin]
        inputs = [*model_in, *state_in, self.bvh.id, self.lowers, self.uppers, *step_in]
        outputs = [c.face, c.point, c.normal, c.depth, c.velocity]
        if self.search == SweptSearch.SPHERE_GRID:
            self.grid.collide(model, state, contacts, ctx, self.epsilon, self.vertex_face_offsets, self.vertex_faces,
                              self.best_key)
        elif self.search == SweptSearch.FACES:
            ctx.launch(find_closest_per_face, surf.num_faces, [*model_in, *state_in, self.lowers, self.uppers, *step_in],
                       [self.best_key])
            if m.spheres.count:
                wp.launch_tiled(resolve_closest_per_sphere, dim=m.spheres.count,
                                inputs=[*model_in, self.vertex_face_offsets, self.vertex_faces, *state_in, *step_in],
                                outputs=[self.best_key, *outputs], block_dim=SWEPT_RESOLVE_THREADS, device=ctx.device)
        elif self.search == SweptSearch.TILED:
            if m.spheres.count:
                wp.launch_tiled(collide_sphere_swept_tiled, dim=m.spheres.count, inputs=inputs, outputs=outputs,
                                block_dim=self.tile_threads, device=ctx.device)
        else:
            seed = int(SEED_PREVIOUS_FACE[device_kind(ctx.device)])
            ctx.launch(collide_sphere_swept, m.spheres.count, [*inputs, seed], outputs)


COLLIDERS = {"refit": RefitCollider, "swept": SweptCollider, "rebuild": RebuildCollider}
COLLIDER_CHOICES = tuple(values(Collider))
#: the measured choice of ``fixed`` (docs/physics.md#the-automatic-collider): each candidate runs
#: the scene's own start on a copy of its state for CHOICE_HORIZON simulated seconds (or until
#: CHOICE_SECONDS of wall time), timed after CHOICE_WARMUP untimed steps; the median round counts
CHOICE_HORIZON = 2.0
CHOICE_SECONDS = 0.5
CHOICE_WARMUP = 4
CHOICE_UNTIMED = 2  # of the warm-up steps: the eager step and the capture (compile, module load)
CHOICE_ROUND_MAX = 120  # steps per timed round


def measure_colliders(model: Model, state: State, candidates, horizon: float | None = None,
                      budget_s: float | None = None) -> dict:
    """Seconds per step of each candidate collider (dict name -> s) on the run this state
    starts: each candidate steps a trial copy of ``state`` (spheres fall, land, bounce or roll
    off as they will in the run) for ``horizon`` simulated seconds, or until ``budget_s`` of
    wall time, after CHOICE_WARMUP untimed steps (eager, CUDA graph capture, two replays: the
    first replay uploads the graph). Timed in rounds of about two reconstruction frames (at
    most CHOICE_ROUND_MAX steps) with a device sync after each; the cost is the median round's
    time per step. Steps so costly that the warm-up alone outlasts ``budget_s`` end the trial
    there (their mean counts), so a scene with a huge sub-step count is not run for long. ``state`` is not touched."""
    horizon = CHOICE_HORIZON if horizon is None else float(horizon)
    budget_s = CHOICE_SECONDS if budget_s is None else float(budget_s)
    p, surf = model.params, model.surface
    per_round = int(min(max(4, math.ceil(2.0 / max(surf.fps * p.dt, 1e-12))), CHOICE_ROUND_MAX))
    total = max(per_round, math.ceil(horizon / p.dt)) if p.dt > 0 else per_round
    t0 = float(state.sim_time.numpy()[0])
    pos, vel = state.sphere_pos.numpy().copy(), state.sphere_vel.numpy().copy()
    cost = {}
    for name in candidates:
        with warnings.catch_warnings():  # the scene's own notes come from the real world
            warnings.simplefilter("ignore")
            base, _, search = name.partition("/")  # "swept/serial": the swept collider with that search
            w = World(model, State(model, pos, vel, t0=t0), collider=base, render_state=False,
                      swept_search=search or None)
        # the warm-up steps' times; the first CHOICE_UNTIMED (eager: compiles; capture: may load
        # modules on a cold kernel cache) never count. Replays that alone outlast the budget end
        # the trial there
        warm = []
        for _ in range(CHOICE_WARMUP):
            start = time.perf_counter()
            w.step()
            wp.synchronize_device(w.device)
            warm.append(time.perf_counter() - start)
            if sum(warm[CHOICE_UNTIMED:]) > budget_s:
                break
        if sum(warm[CHOICE_UNTIMED:]) > budget_s:
            cost[name] = sum(warm[CHOICE_UNTIMED:]) / len(warm[CHOICE_UNTIMED:])
            continue
        n, spent, rounds = 0, 0.0, []
        while n < total and spent < budget_s:
            start = time.perf_counter()
            for _ in range(per_round):
                w.step()
            wp.synchronize_device(w.device)
            rounds.append(time.perf_counter() - start)
            spent += rounds[-1]
            n += per_round
        # the median round: a one-off stall of the host (a page fault, a collection, another
        # process) costs a fast candidate's whole measurement if averaged in (the default scene's
        # swept collider, ~20 ms timed in all on the CPU, measured 4x slower now and then)
        cost[name] = float(np.median(rounds)) / per_round
    return cost


def warn_spins_kept(spins, body, who: str) -> None:
    """Warn where spins are given to spheres that do not rotate (``body`` point): they are kept as
    given and change nothing (``State``, ``BatchState`` and ``BatchedWorld.reset``; ``who`` names
    the caller). Warned at the caller's caller."""
    if np.any(spins) and SPHERE_INERTIA[body] == 0:
        warnings.warn(f"{who}: spins given to spheres that do not rotate (physics.sphere_body point): they are kept as "
                      "given and change nothing; sphere_body solid or shell makes them roll", stacklevel=3)


def physics_summary(params) -> dict:
    """The physics a run's ``summary.json`` records (a point-mass run and a rolling one could not
    be told apart afterwards: a new user's): the sphere body, friction, restitution, rest speed,
    gravity, the ground plane and the step."""
    return {"sphere_body": str(params.sphere_body), "friction": float(params.friction),
            "restitution": float(params.restitution), "rest_speed": float(params.rest_speed),
            "gravity": [float(g) for g in params.gravity], "dt": float(params.dt),
            "ground": None if params.ground_height is None else float(params.ground_height)}


def fallen_past_note(sequence, params, positions, hint: str = "") -> str:
    """The run line's note when spheres ended far below the surface's lowest point (along the
    scene's up, against ``params.gravity``) with no ground plane to stop them: ``"; n of S spheres
    fell past the surface (...)"``, else ``""`` (a new user's y-up horse played as z-up: "0/5 in
    contact", the spheres at z = -15 m, unsaid; another's sphere pinched through a closing slab).
    ``positions`` (S, 3) [m]; ``hint``: a cause of the caller's own, said first."""
    P = np.asarray(positions, np.float64).reshape(-1, 3)
    if params.ground_height is not None or not len(P):
        return ""
    lo, hi = sequence.bounds()
    up = up_from_gravity(params.gravity)
    # along the scene's up (a new user's y-up floor under gravity along -y lost its spheres
    # without this note, which looked along z): the bounding box's lowest corner along it
    low = float(np.where(up > 0, lo, hi) @ up)
    below = P @ up < low - 0.5 * float(np.linalg.norm(hi - lo))
    fell = int(np.count_nonzero(below))
    if not fell:
        return ""
    # those beside the surface's footprint (across the up axis) went off its edge, not through it
    # (a new user's spheres carried off an open sheet by its wave were blamed on the up axis)
    across = frame_across(up)[:2]
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    c_lo, c_hi = (corners @ across.T).min(axis=0), (corners @ across.T).max(axis=0)
    q = P[below] @ across.T
    off = int(np.count_nonzero(((q < c_lo) | (q > c_hi)).any(axis=1)))
    if off:
        hint = (f"{'all' if off == fell else off} of them beside the surface's footprint: they went off its edge "
                f"(rolled or thrown off); " + hint)
    return (f"; {fell} of {len(P)} spheres fell past the surface (below its lowest point, no ground plane: "
            f"{hint}--set physics.ground=auto would put one at the surface's lowest point; the data's up axis "
            "not the one it was read with? --set "
            "surface.up_axis=y or z; or pinched "
            "between two parts of the surface closing on them, which one contact per sphere cannot hold: raise "
            "physics.substeps, docs/physics.md)")


class World:
    """Spheres on a deforming mesh.

    ``step()`` advances by ``params.dt`` in ``params.substeps`` sub-steps. Each sub-step:
    surface vertices for the current time (refit/rebuild colliders) -> acceleration structure
    (refit / rebuild / swept bounds on frame change) -> sphere contacts -> integrate spheres and
    advance the device clock. After the sub-steps the face normals (render state) are updated
    and the post-step hooks run.

    Colliders: ``fixed`` runs ``swept`` (on CUDA once per search: tiled, serial) and ``refit``
    on trial copies of the state when interpolation is on and keeps the fastest
    (:func:`measure_colliders`; ``collider_costs``, ``swept_search``), else ``refit``;
    ``refit`` (BVH refit every sub-step, the reference), ``swept`` (refit once per frame),
    ``rebuild`` (varying-topology baseline, new BVH every sub-step or frame).

    Tunnelling guarantee: the sphere's own motion is handled continuously (time of impact
    within the step), and the number of sub-steps is raised if needed so that the surface moves
    less than half the smallest sphere radius per sub-step; a centre can then never be carried
    through the surface in one sub-step, and one found behind it is pushed back to the front.
    """

    def __init__(self, model: Model, state: State, collider: str = DEFAULT_COLLIDER,
                 rebuild_every: str = DEFAULT_REBUILD_EVERY,
                 use_graph: bool | None = None, render_state: bool = False, swept_search: str | None = None):
        self.model = model
        self.state = state
        self.device = model.device
        p = model.params.freeze()
        surf = model.surface
        collider = parse(Collider, collider, "collider").value
        rebuild_every = parse(RebuildEvery, rebuild_every, "rebuild_every").value
        if collider not in surf.colliders:
            raise ValueError(
                f"collider {collider!r}: a {surf.topology}-topology surface can only use collider "
                f"{' or '.join(map(repr, surf.colliders))} (or convert it to fixed topology first)"
            )
        self.collider_costs = None  # seconds per step of each candidate when ``fixed`` measured them
        self.swept_search = swept_search  # the swept collider's search (None: physics.swept_search or the default)
        collider = surf.resolve_collider(collider, lambda cands: self._choose_measured(model, state, cands))
        self.substeps = max(1, int(p.substeps))
        self.t0 = float(state.sim_time.numpy()[0])
        # the stages' context: sub-step, reach, launch, host clock (twin of sim_time: the same
        # float64 additions as the device)
        self.ctx = StepContext(self.device, self._launch, wp.vec3(*[float(g) for g in p.gravity]), time=self.t0)
        self._apply_substep_rule(stacklevel=3)
        self.contacts = Contacts(model.spheres.count, device=self.device)
        self.substep_count = 0
        self._launch_cache = None
        self.update_surface()
        m, st, ctx = self.model, self.state, self.ctx
        self.collider = (RebuildCollider(m, st, ctx, rebuild_every) if collider == "rebuild"
                         else SweptCollider(m, st, ctx, search=self.swept_search) if collider == "swept"
                         else COLLIDERS[collider](m, st, ctx))
        self._catch_up_collider()
        self.compute_normals()
        # keep the vertex buffer and normals current after each step only when asked (viewer,
        # Gaussians: render_state=True or a hook that needs it); else surface_points() brings them
        # up to date when read. (A collider's own buffer is at the last sub-step's start, one
        # sub-step behind the clock: a new user's renders lagged by it.)
        self.render_state = bool(render_state)
        if use_graph is None:
            use_graph = self.device.is_cuda and self.collider.capturable
        self.use_graph = bool(use_graph) and self.device.is_cuda and self.collider.capturable
        self._graph = None
        if self.device.is_cpu and self.collider.capturable:
            self._launch_cache = {}
        self._initial = (state.sphere_pos.numpy().copy(), state.sphere_vel.numpy().copy(),  # .numpy() is a view on the CPU
                         state.sphere_spin.numpy().copy())
        self._initial_spheres = model.spheres  # the scene's own spheres: reset() goes back to them
        self.post_step_hooks = []  # callables hook(world) launched after each step (inside the graph)
        self.surface_hooks = []  # those of them also run where the surface moves between steps

    def _choose_measured(self, model: Model, state: State, candidates) -> str:
        """The candidate with the least measured time per step (:func:`measure_colliders`);
        the first candidate on a tie. On CUDA the swept collider is measured once per search of
        ``SWEPT_MEASURED_SEARCHES`` (``swept/tiled``, ``swept/serial`` and ``swept/faces`` or
        ``swept/sphere_grid`` by the sphere count) unless
        ``physics.swept_search`` names one; the chosen search is kept (``swept_search``).
        Records the costs in ``collider_costs``."""
        searches = () if model.params.swept_search is not None else \
            SWEPT_MEASURED_SEARCHES[device_kind(self.device)]
        # the face-parallel searches split by the sphere count: faces (work faces x spheres) up to
        # SWEPT_FACES_MAX_SPHERES, the sphere grid above it (slower than faces on every few-sphere row)
        drop = SweptSearch.FACES if model.spheres.count > SWEPT_FACES_MAX_SPHERES else SweptSearch.SPHERE_GRID
        searches = tuple(x for x in searches if x != drop)
        trials = []
        for c in candidates:
            trials += [f"{c}/{s}" for s in searches] if c == Collider.SWEPT and searches else [c]
        self.collider_costs = measure_colliders(model, state, trials)
        best = min(trials, key=lambda c: self.collider_costs[c])
        name, _, search = best.partition("/")
        self.swept_search = search or None
        return name

    def add_post_step_hook(self, hook, needs_surface: bool = True, follows_surface: bool = False):
        """Run ``hook(world)`` after every step; it must only launch kernels (no allocation, no
        host reads) so it is captured in the same CUDA graph. With ``needs_surface`` the
        vertex buffer and normals are brought to the current time before it. With
        ``follows_surface`` it also runs where the surface moves between steps (:meth:`reset`,
        :meth:`set_time`, a restored checkpoint): attached Gaussians had stayed where the last step
        left them. Drops the graph."""
        self.post_step_hooks.append(hook)
        if follows_surface:
            self.surface_hooks.append(hook)
        if needs_surface:
            self.render_state = True
        self._graph = None

    # -- host-side bookkeeping (no device reads) ---------------------------------------------
    @property
    def time(self) -> float:
        """Simulation time [s], tracked on the host in step with the device clock."""
        return self.ctx.time

    @property
    def sub_dt(self) -> float:
        """Sub-step length [s] (``ctx.sub_dt``)."""
        return self.ctx.sub_dt

    @property
    def extra_speed(self) -> float:
        """Speed gained from gravity in one sub-step [m/s] (``ctx.extra_speed``)."""
        return self.ctx.extra_speed

    @property
    def gravity(self):
        return self.ctx.gravity

    def current_frame_key(self):
        return self.ctx.frame_key(self.model)

    # -- the Simulation protocol (runtime.Simulation): what runners and the viewer read ----------
    editable = True  # reset / set_time / add_spheres

    @property
    def surface(self):
        return self.model.surface

    @property
    def dt(self) -> float:
        """Physics step [s] (``params.dt``)."""
        return self.model.params.dt

    def surface_points(self):
        """The vertex buffer (N,) at the current time; synchronised first when the step does not
        keep it (``render_state`` false, the default)."""
        if not self.render_state:
            self.sync_surface()
        return self.state.points

    def surface_indices(self):
        return self.current_indices()

    def rigid_shapes(self) -> list:
        """Rigid shapes other than the built-in spheres, for rendering: none here."""
        return []

    def sphere_radii(self) -> np.ndarray:
        return self.model.spheres.radius_np

    @property
    def frame(self) -> int:
        """The frame whose indices the last surface update used (0 for fixed topology, whose
        indices every frame shares; the held frame k for varying topology)."""
        return self.ctx.frame

    def current_indices(self):
        return self.ctx.indices(self.model)

    def _launch(self, kernel, dim, inputs, outputs):
        """Launch a kernel. On the CPU with a static pipeline, each distinct launch is recorded
        once (``record_cmd``) and replayed: this removes most of Python's per-launch argument
        packing, which otherwise dominates a small CPU step. The cache holds the arguments, so
        the arrays stay alive and their ids stay unique."""
        if dim == 0 or (isinstance(dim, tuple) and 0 in dim):
            return
        if self._launch_cache is None:
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=self.device)
            return
        key = (kernel, dim) + tuple(a if isinstance(a, (int, float)) else id(a) for a in inputs + outputs)
        cmd = self._launch_cache.get(key)
        if cmd is None:
            cmd = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=self.device, record_cmd=True)
            self._launch_cache[key] = (cmd, inputs, outputs)
        else:
            cmd = cmd[0]
        cmd.launch()

    # -- pipeline stages (the module's stage functions on this world's model, state, context) ---
    def update_surface(self):
        """Stage 1: vertex buffer (points, velocities) at the current time."""
        update_surface(self.model, self.state, self.ctx)

    def compute_normals(self):
        """Stage 2: per-face normals of the current vertex buffer."""
        compute_normals(self.model, self.state, self.ctx)

    def collide_mesh(self, mesh_id):
        """Stage 3 on a wp.Mesh (refit / rebuild colliders)."""
        collide_mesh(self.model, self.state, self.contacts, self.ctx, mesh_id)

    def integrate(self):
        """Stage 4: sphere dynamics; advances the device clock and its frame pair."""
        integrate(self.model, self.state, self.contacts, self.ctx)

    def substep(self):
        substep(self.model, self.state, self.contacts, self.collider, self.ctx)

    def finish_step(self):
        if self.render_state:
            self.update_surface()  # at the clock's time: the sub-steps' buffer is one sub-step behind it
            self.compute_normals()
        for hook in self.post_step_hooks:
            hook(self)

    def _step_body(self):
        for _ in range(self.substeps):
            self.substep()
        self.finish_step()

    @property
    def graph_captured(self) -> bool:
        """Whether a captured CUDA graph is held (steps replay it)."""
        return self._graph is not None

    def capture(self):
        """Capture one step (all sub-steps) as a CUDA graph, which later ``step()`` calls replay;
        nothing where the world steps eagerly (``use_graph`` false: the CPU, a rebuild collider).
        Captures nothing, advances nothing. ``step()`` captures by itself after one eager step;
        the runner calls this after its warm-up step, so capture stays out of the timed loop."""
        if not self.use_graph:
            return
        # Load only our own kernel modules before capturing: ``force_module_load=True`` would load
        # (and on a cold cache compile) every Warp module imported in the process (all of
        # Newton's, for one), which took minutes on a fresh GPU machine. Kernels of other
        # modules launched by post-step hooks load during capture (CUDA driver >= 12.3).
        for module in _step_modules(bool(self.post_step_hooks)):
            wp.load_module(module, device=self.device)
        with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
            self._step_body()
        self._graph = cap.graph

    def step(self):
        """Advance by one physics step (params.dt). With ``use_graph`` the first step runs
        eagerly (it loads the step's modules) and the next captures the step as a CUDA graph
        (the same policy as ``NewtonWorld``); from then on steps replay it. Editing the world
        drops the graph; the next step captures it again."""
        if self.use_graph and (self._graph is not None or self.substep_count > 0):
            if self._graph is None:
                self.capture()
            wp.capture_launch(self._graph)
            for _ in range(self.substeps):
                self.ctx.time += self.sub_dt
            self.substep_count += self.substeps
            return
        for _ in range(self.substeps):
            self.substep()
            self.substep_count += 1
            self.ctx.time += self.sub_dt
        self.finish_step()

    def set_time(self, t: float):
        """Move the clock (host and device) to ``t`` [s] and the surface with it; spheres keep
        their state. Between steps only."""
        t = float(t)
        if not math.isfinite(t):  # a new user's NaN made the surface NaN and the spheres fall through it
            raise ValueError(f"set_time: the time must be a finite number of seconds, got {t}")
        if abs(t) > MAX_TIME_OFFSET:  # (1e30 froze the clock: t + dt == t; the batch's bound too)
            raise ValueError(f"set_time: the time must be within +-{MAX_TIME_OFFSET:g} s (far beyond it float64 "
                             f"rounding stops the clock), got {t:g}")
        self.ctx.time = t
        self.state.sim_time.assign(np.array([self.ctx.time], np.float64))
        self._refresh_surface()

    def sync_surface(self):
        """Bring the vertex buffer and normals to the current time (for a viewer); eager."""
        self.update_surface()
        self.compute_normals()

    # -- editing between steps (host side; invalidates the captured graph) ---------------------
    def _catch_up_collider(self):
        """The collider's structure at the current time (its ``refresh`` hook); the frame change
        it consumed is cleared, so the next step does not redo it."""
        self.collider.refresh(self.model, self.state, self.ctx)
        self.state.frame_changed.zero_()

    def _refresh_surface(self):
        self.update_surface()
        self.state.update_frame_key(self.model)  # the clock moved: its frame pair, and whether it changed
        self._catch_up_collider()
        self.compute_normals()
        for hook in self.surface_hooks:
            hook(self)

    def reset(self):
        """Back to the initial time and the scene's initial spheres: spheres added since
        (:meth:`add_spheres`, the viewer's "Drop sphere") are removed."""
        if self.model.spheres is not self._initial_spheres:
            with warnings.catch_warnings():  # the scene's own sub-step note was given when it was built
                warnings.simplefilter("ignore")
                self._set_spheres(self._initial_spheres, *(a[: self._initial_spheres.count] for a in self._initial),
                                  rederive_substeps=True)
            self._initial = tuple(a[: self.model.spheres.count] for a in self._initial)
        s = self.state
        s.sim_time.assign(np.array([self.t0], dtype=np.float64))
        s.sphere_pos.assign(self._initial[0])
        s.sphere_vel.assign(self._initial[1])
        s.sphere_spin.assign(self._initial[2])
        self.contacts.memory.zero_()  # (a pinch before the reset would squeeze the first sub-step after it)
        self.substep_count = 0
        self.ctx.time = self.t0
        self._refresh_surface()
        self.collider.resize(self.model, self.state, self.ctx)

    # -- checkpoints (run --checkpoint-every / --resume; dynmesh_warp.checkpoint) -------------
    def checkpoint_state(self) -> dict:
        """Everything a step reads that changes while the world runs, as NumPy copies: the clock
        (the host's float64 and the device's), the sub-step count, the spheres' positions,
        velocities and spins, the clock's frame pair and pending-change flag, and the collider's frame state
        (swept: :attr:`SweptCollider.CHECKPOINT_ARRAYS`;
        refit and rebuild derive theirs from the clock), and each sphere's last contact face: the
        seeded searches (``SEED_PREVIOUS_FACE``, ``SEED_REFIT_QUERY``) read it before they write
        it (without it a run resumed at step 3,665 of the default scene differed from the
        uninterrupted one by one float32 ulp of one velocity, a step later; CI caught it), and the
        integrator's pinch memory (``Contacts.memory``, read before it is written). The rest
        is static (surface, radii, masses, parameters: compared with the scene on resume), the
        other contact fields are written before they are read, and no step draws random numbers.
        Between steps only."""
        st = {"time": np.array(self.ctx.time, np.float64), "sim_time": self.state.sim_time.numpy().copy(),
              "substep_count": np.array(self.substep_count, np.int64),
              "sphere_pos": self.sphere_positions(), "sphere_vel": self.sphere_velocities(),
              "sphere_spin": self.sphere_spins(),
              "frame_key": self.state.frame_key.numpy().copy(), "frame_changed": self.state.frame_changed.numpy().copy(),
              "contact_face": self.contacts.face.numpy().copy(),
              "contact_memory": self.contacts.memory.numpy().copy()}
        st.update({f"collider_{k}": v for k, v in self.collider.checkpoint_state().items()})
        return st

    def restore_checkpoint_state(self, st: dict):
        """Continue from :meth:`checkpoint_state` of a world built the same way (same scene,
        collider and device kind; :mod:`dynmesh_warp.checkpoint` checks that). On the CPU the
        following steps are bit-identical to those of the world that wrote it."""
        S = self.model.spheres.count
        have = np.asarray(st["sphere_pos"]).reshape(-1, 3).shape[0]
        if have != S:  # before anything changes (Warp's copy error named neither)
            raise ValueError(f"checkpoint state: it holds {have} spheres, this world has {S}: it was written by "
                             "another scene or after add_spheres")
        self.set_time(float(st["time"]))  # surface and collider at that time, then the exact values
        self.state.sim_time.assign(np.asarray(st["sim_time"], np.float64).reshape(1))
        self.state.sphere_pos.assign(np.asarray(st["sphere_pos"], np.float32).reshape(-1, 3))
        self.state.sphere_vel.assign(np.asarray(st["sphere_vel"], np.float32).reshape(-1, 3))
        self.state.sphere_spin.assign(np.asarray(st["sphere_spin"], np.float32).reshape(-1, 3))  # (0 in an old file)
        self.state.frame_key.assign(np.asarray(st["frame_key"], np.int32).reshape(1))
        self.state.frame_changed.assign(np.asarray(st["frame_changed"], np.int32).reshape(1))
        self.contacts.face.assign(np.asarray(st["contact_face"], np.int32).reshape(-1))
        self.contacts.memory.assign(np.asarray(st["contact_memory"], np.float32).reshape(S, 16))
        self.substep_count = int(st["substep_count"])
        self.collider.restore_checkpoint_state({k[len("collider_"):]: v for k, v in st.items()
                                                if k.startswith("collider_")})
        self.collider.spheres_moved(self.model, self.state, self.ctx)  # per-sphere caches from the restored state
        self._graph = None

    def _apply_substep_rule(self, stacklevel: int):
        """Raise ``substeps`` (auto_substeps, interpolation on) so the surface moves less than half
        the smallest sphere radius per sub-step; warn when the rule is off and a sub-step exceeds
        that, or when interpolation is off and a frame jump does. Sets ``sub_dt`` and ``extra_speed``."""
        model, p = self.model, self.model.params
        surf = model.surface
        r_min = float(model.spheres.radius_np.min()) if model.spheres.count else math.inf
        if surf.max_speed > 0 and math.isfinite(r_min):
            need = required_substeps(surf.max_speed, p.dt, r_min)
            if p.auto_substeps and surf.interpolate and need > self.substeps:
                note = seam_note(surf)
                check_substep_budget(need, surf.max_speed, r_min, p, note)
                warnings.warn(
                    f"surface moves up to {surf.max_speed:.3g} m/s{note}: raising substeps from "
                    f"{self.substeps} to {need} so it moves < r/2 per sub-step", stacklevel=stacklevel)
                self.substeps = need
            elif not p.auto_substeps and surf.interpolate and need > self.substeps:
                # the rule turned off: said, as the jumps without interpolation are (a new user's
                # sheet at 20 m/s passed through a sphere without a word)
                warnings.warn(
                    f"auto_substeps is off and the surface moves up to {surf.max_speed:.3g} m/s: "
                    f"{surf.max_speed * p.dt / self.substeps:.3g} m per sub-step, over r/2 = {0.5 * r_min:.3g} m "
                    f"for the smallest sphere radius: spheres may tunnel; turn physics.auto_substeps on or set "
                    f"physics.substeps to {need}", stacklevel=stacklevel)
            if not surf.interpolate and surf.max_frame_step > 0.5 * r_min:
                warnings.warn(
                    f"interpolation is off and the surface jumps up to {surf.max_frame_step:.3g} m "
                    f"between frames (> half the smallest sphere radius {r_min:.3g} m): spheres may "
                    "tunnel at frame changes; turn interpolation on", stacklevel=stacklevel)
        self.ctx.sub_dt = p.dt / self.substeps
        # contact query reach: r + margin + (|v| + extra_speed) * dt, extra_speed = speed gained from
        # gravity in one sub-step. The surface's own approach is not added: the sub-step rule keeps
        # it under r/2 per sub-step, so a surface reaching into a sphere is caught as a (shallow)
        # penetration and pushed out; adding the global max surface speed would only enlarge every
        # query (x8 box volume on horse-gallop) for the same result.
        self.ctx.extra_speed = float(np.linalg.norm(p.gravity)) * self.ctx.sub_dt

    def add_spheres(self, positions, radius, mass=1.0, velocities=None):
        """Add spheres (between steps). Reallocates the sphere arrays and drops the graph."""
        first = self.model.spheres.count
        positions = np.asarray(positions, np.float32)
        n = positions.shape[0] if positions.ndim == 2 else positions.size // 3
        positions = _sphere_rows("position", positions, n, first)
        try:
            radius = np.broadcast_to(np.asarray(radius, np.float32), (n,))
        except ValueError:
            raise ValueError(f"sphere radius: expected one value or one per new sphere ({n}), got shape "
                             f"{np.shape(radius)}") from None
        self._refuse_inside(positions, first)
        surf, p = self.model.surface, self.model.params
        if n and surf.max_speed > 0 and surf.interpolate and p.auto_substeps and np.all(radius > 0):
            r_min = float(min(radius.min(), self.model.spheres.radius_np.min(initial=np.inf)))
            check_substep_budget(math.ceil(surf.max_speed * p.dt / (0.5 * r_min)), surf.max_speed, r_min, p,
                                 seam_note(surf))
        old = self.model.spheres
        old_mass = np.where(old.inv_mass.numpy() > 0, 1.0 / np.maximum(old.inv_mass.numpy(), 1e-30), np.inf)
        new_r = np.concatenate([old.radius_np, radius])
        new_m = np.concatenate([old_mass, np.broadcast_to(np.asarray(mass, np.float64), (n,))])
        vel = np.zeros((n, 3), np.float32) if velocities is None else _sphere_rows("velocity", velocities, n, first)
        spin = np.zeros((n, 3), np.float32)
        pos_all = np.concatenate([self.state.sphere_pos.numpy(), positions])
        vel_all = np.concatenate([self.state.sphere_vel.numpy(), vel])
        spin_all = np.concatenate([self.state.sphere_spin.numpy(), spin])
        spheres = SphereModel(new_r, new_m, self.device)  # checks radius and mass before anything changes
        self._set_spheres(spheres, pos_all, vel_all, spin_all, stacklevel=4)
        # what reset() restores: only once the spheres are in (a refused call changed it, and the
        # next reset() failed on arrays of different sizes; found by a new user)
        self._initial = tuple(np.concatenate([a, b]) for a, b in zip(self._initial, (positions, vel, spin)))

    def _refuse_inside(self, positions: np.ndarray, first: int) -> None:
        """ValueError when a new sphere's centre lies inside the surface, where it is closed, as
        it stands now: contacts are one-sided, so the sphere would fall out through it (the rule
        ``build_world`` applies to a scene's listed spheres). Skipped above WINDING_CHECK_BUDGET
        sphere-face pairs (the host's winding numbers are O(spheres x faces))."""
        F = self.current_indices().numpy().reshape(-1, 3)
        if not len(positions) or len(positions) * len(F) > WINDING_CHECK_BUDGET:
            return
        inside = points_inside(self.surface_points().numpy(), F, positions)
        if inside.size:
            i = int(inside[0])
            raise ValueError(f"sphere {first + i}: position {[round(float(x), 6) for x in positions[i]]} lies inside the "
                             f"closed surface at t = {self.time:.6g} s; contacts are one-sided, so it would fall out "
                             f"through it. Add it outside the surface"
                             + (f" ({inside.size} of the {len(positions)} new spheres are inside)" if inside.size > 1
                                else ""))

    def _set_spheres(self, spheres: SphereModel, pos, vel, spin, stacklevel: int = 3, rederive_substeps: bool = False):
        """Replace the sphere set (model and state arrays, contacts, sub-step rule, collider lists);
        drops the graph. ``rederive_substeps``: from the configured count again (after removing
        spheres), else only ever raised."""
        self.model.spheres = spheres
        self.state.sphere_pos = wp.array(np.asarray(pos, np.float32), dtype=wp.vec3, device=self.device)
        self.state.sphere_vel = wp.array(np.asarray(vel, np.float32), dtype=wp.vec3, device=self.device)
        self.state.sphere_spin = wp.array(np.asarray(spin, np.float32), dtype=wp.vec3, device=self.device)
        memory = self.contacts.memory.numpy()
        self.contacts = Contacts(self.model.spheres.count, device=self.device)
        kept = min(len(memory), self.model.spheres.count)  # the spheres kept keep their pinch memory
        if kept:
            wp.copy(self.contacts.memory, wp.array(memory[:kept], dtype=pinch_memory, device=self.device), count=kept)
        if rederive_substeps:
            self.substeps = max(1, int(self.model.params.substeps))
        self._apply_substep_rule(stacklevel=stacklevel)  # smaller spheres may need more sub-steps
        self._graph = None
        if self._launch_cache is not None:
            self._launch_cache = {}
        self.collider.resize(self.model, self.state, self.ctx)

    def initial_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """The spheres' positions (S, 3) [m] and velocities (S, 3) [m/s] at the initial time:
        the scene's, and those of spheres added since (what :meth:`reset` goes back to)."""
        return self._initial[0].copy(), self._initial[1].copy()

    def set_sphere(self, i: int, position, velocity=(0.0, 0.0, 0.0), spin=(0.0, 0.0, 0.0)):
        """Place sphere ``i`` at ``position`` [m] with ``velocity`` [m/s] and ``spin`` [rad/s] between
        steps, without a host read-back and keeping the captured graph (the arrays stay the same);
        the collider is told (``spheres_moved``)."""
        i = int(i)
        if not 0 <= i < self.model.spheres.count:
            raise IndexError(f"sphere {i}: the world has {self.model.spheres.count} spheres")
        rows = [_sphere_rows(name, v, 1, i) for name, v in (("position", position), ("velocity", velocity),
                                                             ("spin", spin))]
        for dst, row in zip((self.state.sphere_pos, self.state.sphere_vel, self.state.sphere_spin), rows):
            wp.copy(dst, wp.array(row, dtype=wp.vec3, device=self.device), dest_offset=i, count=1)
        self.contacts.memory[i:i + 1].zero_()  # a sphere placed anew remembers no contact
        self.collider.spheres_moved(self.model, self.state, self.ctx)

    # -- what the runner reads (runtime.Simulation; runner.run_simulation) ---------------------
    checkpointable = True  # checkpoint_state / checkpoint.Checkpoint.restore
    body_noun = "sphere"
    num_envs = 1

    def sample(self) -> dict:
        """The arrays of one ``trajectories.npz`` sample: ``position`` and ``velocity`` (S, 3)
        [m], [m/s] (host copies). (Spins are not sampled: :meth:`sphere_spins`.)"""
        return {"position": self.sphere_positions(), "velocity": self.sphere_velocities()}

    def trajectory_constants(self) -> dict:
        """Arrays stored once in ``trajectories.npz``: ``radius`` (S,) [m]."""
        return {"radius": self.model.spheres.radius.numpy()}

    def contact_count(self) -> int:
        """Spheres in contact with the surface after the last step."""
        return int((self.contacts.face.numpy() >= 0).sum())

    def _surface_gaps(self) -> np.ndarray:
        """(S,) signed gap of each sphere to the surface [m] from the last step's contacts; inf
        where a sphere has no contact candidate."""
        c = self.contacts.numpy()
        d = -c["depth"]
        d[c["face"] < 0] = np.inf
        return d

    def run_summary(self) -> dict:
        """The built-in world's fields of a run's ``summary.json``."""
        surf = self.model.surface
        pos, vel = self.sphere_positions(), self.sphere_velocities()
        gap = self._surface_gaps()
        return {
            "collider": self.collider.name + (f"/{self.collider.every}" if self.collider.name == "rebuild" else ""),
            "swept_search": str(self.collider.search) if self.collider.name == "swept" else None,
            "collider_choice": (None if self.collider_costs is None else
                                {"measured_steps_per_s": {k: 1.0 / max(v, 1e-12) for k, v in self.collider_costs.items()}}),
            "surface": {"frames": surf.num_frames, "fps": surf.fps,
                        "interpolate": bool(surf.interpolate), "max_speed_m_s": float(surf.max_speed)},
            "spheres": self.model.spheres.count,
            "physics": physics_summary(self.model.params),
            "final": {
                "finite": bool(np.isfinite(pos).all() and np.isfinite(vel).all()),
                "position": pos,
                "velocity": vel,
                "surface_gap": np.where(np.isfinite(gap), gap, None).tolist(),
                "max_penetration": float(max(0.0, -np.min(gap))) if self.model.spheres.count else 0.0,
                "on_ground": self.ground_count(),  # spheres on the ground plane (None: no ground)
            },
        }

    def ground_count(self) -> int | None:
        """Spheres touching the ground plane now (centre within its radius + 1 % of it above the
        ground); None without a ground. The contact counts are the surface's only (a new user's
        spheres resting on the ground read "0/5 in contact" as flown off)."""
        g = self.model.params.ground_height
        if g is None or not self.model.spheres.count:
            return None if g is None else 0
        z = self.state.sphere_pos.numpy()[:, 2]
        return int(np.count_nonzero(z <= g + 1.01 * self.model.spheres.radius_np))

    def run_line(self) -> tuple[str, str]:
        """(engine label, result) of the run's log line."""
        s = self.run_summary()
        ground = s["final"]["on_ground"]
        return (s["collider"], f"{self.contact_count()}/{s['spheres']} spheres in contact with the surface"
                + ("" if ground is None else f", {ground} on the ground plane")
                + f", max penetration {s['final']['max_penetration']:.2e} m" + self._fallen_text())

    def _fallen_text(self) -> str:
        """The run line's note on spheres that fell past the surface (:func:`fallen_past_note`)."""
        return fallen_past_note(self.model.surface.sequence, self.model.params, self.state.sphere_pos.numpy())

    # -- convenience ---------------------------------------------------------------------------
    def sphere_positions(self) -> np.ndarray:
        return self.state.sphere_pos.numpy().copy()  # a snapshot: .numpy() is a view on the CPU

    def sphere_velocities(self) -> np.ndarray:
        return self.state.sphere_vel.numpy().copy()

    def sphere_spins(self) -> np.ndarray:
        """(S, 3) angular velocities [rad/s] (zero where ``physics.sphere_body`` is ``point``)."""
        return self.state.sphere_spin.numpy().copy()
