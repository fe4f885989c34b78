"""Build a :class:`~dynmesh_warp.world.World` from a validated scene description."""

from __future__ import annotations

import re
import shlex
from pathlib import Path
import warnings

import numpy as np

from .choices import Collider, UpAxis, parse
from .config import PhysicsCore, SceneConfig, SceneError, scene_config, spawn_positions
from .runtime import free_bytes, scene_device
from .geometry import has_area, orient_faces, points_inside, up_from_gravity
from .sequence import (FixedTopologySequence, MeshDataError, TopologyMismatchError, VaryingTopologySequence,
                       surface_vertices, upsampled_frames)
from .world import (Model, PhysicsParams, SphereModel, State, World, playback_note, resolve_playback, surface_model,
                    surface_model_class)

__all__ = ["load_surface", "prepare_surface", "scene_spheres", "scene_ground", "build_model", "build_world"]

# y-up data to z-up: rotate +90 degrees about x, (x, y, z) -> (x, -z, y)
_Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def up_axis_of(cfg, seq) -> str:
    """``surface.up_axis`` resolved for the loaded sequence ``seq``: ``auto`` is the axis its
    coordinates are up along (:func:`~dynmesh_warp.io.sequence_up_axis`: what it says, else what its
    source file says: ``y`` for glTF, whose specification fixes +Y up, and for what this project
    wrote from it), else ``z``."""
    from .io import sequence_up_axis

    if cfg.up_axis != UpAxis.AUTO:
        return str(cfg.up_axis)
    return sequence_up_axis(seq)


def _transform(V: np.ndarray, cfg, up_axis: str) -> np.ndarray:
    V = V.astype(np.float64)
    if up_axis == "y":
        V = V @ _Y_TO_Z.T
    return (V * cfg.scale + np.asarray(cfg.translate)).astype(np.float32)


def _orient(V: np.ndarray, F: np.ndarray, cfg, up) -> tuple:
    """``(faces, report)`` as ``surface.orientation`` asks: contacts are one-sided (the side the
    triangle normals point to), so ``auto`` winds every manifold piece consistently, turns a
    closed one outward and an open one (a sheet, a terrain) up, against gravity
    (:func:`~dynmesh_warp.geometry.orient_faces`); report None for ``keep`` and ``flip``."""
    if cfg.orientation == "flip":
        return F[:, ::-1].copy(), None
    if cfg.orientation == "keep":
        return F, None
    return orient_faces(V, F, up)


def _say_orientation(reports: list, where: str) -> None:
    """One warning per kind of change :func:`_orient` made, over a sequence's frames
    (``reports``: ``(frame or None, report)``)."""
    def frames(key):
        hit = [t for t, r in reports if r and r.get(key)]
        if not hit or hit == [None]:
            return ""
        return f" (frame{'s' if len(hit) > 1 else ''} {', '.join(map(str, hit[:8]))}{' ...' if len(hit) > 8 else ''})"

    tail = " (surface.orientation: keep to leave them)"
    total = {k: sum(r.get(k, 0) for _, r in reports if r)
             for k in ("rewound", "inward", "container", "down", "non_orientable")}
    if total["rewound"]:
        warnings.warn(f"{where}{frames('rewound')}: inconsistent winding (neighbouring triangles faced opposite "
                      f"ways): flipped {total['rewound']} triangle(s) to agree with their neighbours" + tail,
                      stacklevel=3)
    if total["inward"]:
        warnings.warn(f"{where}{frames('inward')}: closed mesh whose triangles face inward (negative volume): "
                      "flipped them to face outward" + tail, stacklevel=3)
    if total["container"]:
        warnings.warn(f"{where}{frames('container')}: open container (a large hole opening upward: a cup, a "
                      "bucket, a box without its lid) whose triangles face out of it: flipped them to face into it, "
                      "where dropped bodies land (contacts are one-sided)" + tail, stacklevel=3)
    if total["down"]:
        # said against gravity, not in world axes (with gravity along +z, "face up" read as +z, the
        # reverse of the flip done, a new user found)
        warnings.warn(f"{where}{frames('down')}: open surface whose triangles face along gravity, away from where "
                      "falling bodies come from (contacts are one-sided): flipped them to face against gravity" + tail,
                      stacklevel=3)
    if total["non_orientable"]:
        warnings.warn(f"{where}{frames('non_orientable')}: a part with no consistent winding (a Moebius-like "
                      "strip); contacts are one-sided, so some of its faces may let spheres through", stacklevel=3)


def scene_up(cfg) -> np.ndarray:
    """The scene's up: against ``physics.gravity`` (+z without gravity), a unit vector
    (:func:`~dynmesh_warp.geometry.up_from_gravity`)."""
    return up_from_gravity(cfg.physics.gravity)


def _say_interrupted(seq, where: str) -> None:
    """Warn of the segments of a piecewise-fixed sequence played as it is whose frames either side
    share one topology (:meth:`~dynmesh_warp.sequence.VaryingTopologySequence.interrupted_segments`):
    a frame that lost faces, which the physics would play as a segment of its own."""
    runs = seq.segments()
    if len(runs) < 3 or not seq.is_piecewise_fixed(runs):
        return
    for a, b in seq.interrupted_segments(runs)[:4]:
        name = f" ({Path(seq.frame_sources[a]).name})" if seq.frame_sources else ""
        frames_ = f"frame {a}" if b == a + 1 else f"frames {a}..{b - 1}"
        warnings.warn(
            f"{where}: {frames_}{name} {'has' if b == a + 1 else 'have'} other faces than the frames either side, which "
            f"share theirs ({len(seq.frames[a][1])} against {len(seq.frames[a - 1][1])} faces): a frame cut short or "
            "damaged? It is played as it is, as a segment of its own", stacklevel=4)


def _check_size(V0: np.ndarray, cfg, up_axis: str) -> None:
    """Warn when the surface is implausibly large or small for metres (wrong units?). ``up_axis``:
    the axis the data were read up along; the hint to read y-up data so only when it was z (a new
    user's glTF, read y-up already, was told to set surface.up_axis: y)."""
    diag = float(np.linalg.norm(V0.max(axis=0) - V0.min(axis=0)))
    if diag > 100.0 or diag < 0.01:
        warnings.warn(
            f"surface {cfg.source}: the first frame is {diag:.3g} m across (bounding-box diagonal) in the "
            "scene frame, which is in metres; for data in other units set surface.scale (e.g. 0.001 for "
            "millimetres)" + (", and surface.up_axis: y for y-up data" if up_axis == "z" else ""), stacklevel=3)


#: a spawn's column of spheres (count x 2.5 radii high) over this many times the surface's
#: diagonal is warned of: the spheres rain for a long time before the last lands
SPAWN_COLUMN_WARN = 10.0

#: the host memory a spawned sphere takes while the spawn is made and checked [bytes], at least
#: (its float64 draws and float32 copies, radius, mass; the world's arrays come on top)
SPAWN_BYTES = 128

#: float32 resolution limits at the scene's farthest coordinate, as fractions of the smallest
#: sphere radius: above PRECISION_ERROR the scene is refused (positions cannot resolve 1 % of a
#: radius: at r = 5 cm, coordinates beyond ~4 km), above PRECISION_WARN a warning (~0.5 km)
PRECISION_ERROR = 1e-2
PRECISION_WARN = 1e-3


#: a sphere whose radius is over this many times the surface's bbox diagonal is refused: the
#: surface is a speck to it (a new user's radius 1e30 m ran with the spheres frozen where float32
#: put them, and the summary said "finite")
SPHERE_SIZE_MAX = 1e3


def refuse_outsized_spheres(lo, hi, radius, where: str) -> None:
    """Refuse (:class:`SceneError`) spheres over SPHERE_SIZE_MAX times the surface's size (bounds
    ``lo``, ``hi`` over all frames)."""
    radius = np.asarray(radius, np.float64)
    diag = float(np.linalg.norm(np.asarray(hi, np.float64) - np.asarray(lo, np.float64)))
    if radius.size and diag > 0 and float(radius.max()) > SPHERE_SIZE_MAX * diag:
        r = float(radius.max())
        raise SceneError(f"{where}: a sphere radius of {r:.4g} m is {r / diag:.3g} x the surface's size ({diag:.4g} m "
                         "across its bounding box's diagonal): the surface is a speck to it; give the radius in the "
                         "surface's units (spheres.radius, or each listed sphere's radius)")


def check_precision(lo, hi, positions, radius, where: str, translate=(0.0, 0.0, 0.0), scale: float = 1.0) -> None:
    """Refuse (:class:`SceneError`) or warn about a scene so far from the origin that float32,
    the simulation's precision, cannot resolve its contacts: the spacing of float32 numbers at
    the largest coordinate of the surface (bounds ``lo``, ``hi`` over all frames) or of a
    sphere (``positions``) against the smallest sphere ``radius``. The message gives the
    ``surface.translate`` that brings the surface's centre to the origin (``translate``: the
    one already applied). Only what moving to the origin fixes is reported: spheres tiny for the
    surface itself are the work budget's to refuse."""
    radius = np.asarray(radius, np.float64)
    if radius.size == 0:
        return
    far = max(float(np.abs(lo).max()), float(np.abs(hi).max()),
              float(np.abs(positions).max()) if np.size(positions) else 0.0)
    ulp = float(np.spacing(np.float32(far)))
    r = float(radius.min())
    if ulp <= PRECISION_WARN * r:
        # moved to the origin by surface.translate: the vertices were read as float32 where they
        # lay, before the move, and keep that rounding (a new user's float64 data 6 km out kept
        # 0.24 mm, 100 km out 3.9 mm, with no word once the suggested translate was set)
        held = float(np.spacing(np.float32(np.abs(np.asarray(translate, np.float64)).max() / scale))) * scale
        if held > PRECISION_WARN * r:
            warnings.warn(f"{where}: surface.translate moves the data {np.linalg.norm(translate):.4g} m, but its "
                          f"vertices were read as float32 where they lay, so they keep a rounding of "
                          f"{held * 1e3:.2g} mm ({100 * held / r:.2g} % of the smallest sphere radius, {r:g} m); "
                          "for full precision, centre the data in the file itself", stacklevel=3)
        return
    surf_far = max(float(np.abs(lo).max()), float(np.abs(hi).max()))
    if float(np.spacing(np.float32(surf_far))) <= PRECISION_WARN * r:
        # the surface is near the origin and the spheres are not (a new user's 100,000 spawned
        # spheres, stacked 12.5 km high, were told to move the 1 m surface to the origin)
        msg = (f"{where}: spheres reach {far:.4g} m from the origin, where float32 (the simulation's precision) "
               f"resolves only {ulp * 1e3:.2g} mm, {100 * ulp / r:.2g} % of the smallest sphere radius ({r:g} m), "
               f"while the surface lies within {surf_far:.4g} m of it: place the spheres nearer the surface (a spawn "
               f"stacks its spheres 2.5 radii apart: fewer of them, or a list of positions)")
        if ulp > PRECISION_ERROR * r:
            raise SceneError(msg + "; contacts and motion would be wrong")
        warnings.warn(msg, stacklevel=3)
        return
    mid = 0.5 * (np.asarray(lo, np.float64) + np.asarray(hi, np.float64))
    half = 0.5 * float((np.asarray(hi, np.float64) - np.asarray(lo, np.float64)).max())
    if float(np.spacing(np.float32(half))) > PRECISION_WARN * r:
        # not the origin's fault: the surface is that large. What matters then is where the
        # spheres are (a new user's 5 cm sphere 8 km out on a 12 km terrain, 0.98 % of its radius,
        # was told nothing): warned, with the remedy that helps
        at = float(np.abs(positions).max()) if np.size(positions) else 0.0
        sulp = float(np.spacing(np.float32(at)))
        if sulp > PRECISION_WARN * r:
            warnings.warn(f"{where}: spheres reach {at:.4g} m from the origin on a surface {2 * half:.4g} m across, "
                          f"where float32 (the simulation's precision) resolves only {sulp * 1e3:.2g} mm, "
                          f"{100 * sulp / r:.2g} % of the smallest sphere radius ({r:g} m); moving the surface does "
                          "not help: crop it to the region the spheres use (and centre that), or use larger spheres",
                          stacklevel=3)
        return
    centre = [float(f"{c:.4g}") for c in np.asarray(translate, np.float64) - mid]
    msg = (f"{where}: coordinates reach {far:.4g} m from the origin, where float32 (the simulation's "
           f"precision) resolves only {ulp * 1e3:.2g} mm, {100 * ulp / r:.2g} % of the smallest sphere radius "
           f"({r:g} m). Move the scene to the origin: surface.translate: {centre} (and listed spheres "
           "by as much)")
    if ulp > PRECISION_ERROR * r:
        raise SceneError(msg + "; contacts and motion would be wrong")
    warnings.warn(msg, stacklevel=3)


def load_surface(cfg: SceneConfig):
    """Load (or generate) the scene's surface sequence, transformed to the scene frame.

    A varying-topology input is converted to fixed topology when ``surface.conversion`` is
    set; otherwise it is returned as is (only the ``rebuild`` collider can run it).
    """
    s = cfg.surface
    if s.source.startswith("builtin:"):
        from .scenes import builtin_sequence

        try:
            seq = builtin_sequence(s.source.split(":", 1)[1], **s.params)
        except (TypeError, ValueError) as e:
            raise SceneError(f"surface.source {s.source!r}: {e}") from e
    else:
        from .io import load_sequence

        seq = load_sequence(cfg.resolve(s.source), fps=s.fps, frame_order=s.frame_order,
                            **({"subdir": s.subdir} if s.subdir else {}),
                            **({"topology": cfg.resolve(s.topology)} if s.topology else {}),
                            **({"animation": s.animation} if s.animation is not None else {}))
    return prepare_surface(seq, cfg)


def _require_area(V: np.ndarray, F: np.ndarray, where: str, frame: int) -> None:
    """Refuse a surface frame whose faces all are flat (:func:`~dynmesh_warp.geometry.has_area`):
    nothing to collide with or render (``validate_mesh`` lets it through: ``evaluate`` still
    measures a collapsed prediction)."""
    if not has_area(V, F):
        raise MeshDataError(f"{where}, frame {frame}: every face has zero area ({len(F)} faces; the first "
                            f"{np.asarray(F)[0].tolist()}): no surface to collide with or render (faces that repeat a "
                            "vertex, or corners on a line); wrong face indices?")


def prepare_surface(seq, cfg: SceneConfig):
    """Bring a loaded sequence into the scene frame as the ``surface`` section asks: fps,
    up_axis, scale, translate, orientation, then ``conversion`` of a varying-topology one, then
    ``upsample``.
    ``build_world(cfg, sequence=seq)`` calls it for a sequence you built or loaded yourself."""
    s = cfg.surface
    if not isinstance(seq, (FixedTopologySequence, VaryingTopologySequence)):
        raise TypeError(f"expected a FixedTopologySequence or VaryingTopologySequence, got {type(seq).__name__}")
    fps = float(s.fps) if s.fps is not None else seq.fps  # a new sequence: the caller's is untouched
    where = seq.source or seq.name
    axis, up = up_axis_of(s, seq), scene_up(cfg)  # a scene's surface says z: not turned again
    if isinstance(seq, FixedTopologySequence):
        V = _transform(seq.V, s, axis)
        F, report = _orient(V[0], seq.F, s, up)
        _say_orientation([(None, report)], where)
        seq = FixedTopologySequence(V, F, fps, seq.name, seq.source, colors=seq.colors)
        _require_area(seq.V[0], F, where, 0)  # faces all [a, b, b]: every sphere fell through, unsaid
        _check_size(surface_vertices(seq.V[0], F), s, axis)
    else:
        frames, reports = [], []
        prev = None  # (input faces, oriented faces) of the frame before
        for t, (v, f) in enumerate(seq.frames):
            v = _transform(v, s, axis)
            if prev is not None and prev[0].shape == f.shape and np.array_equal(prev[0], f):
                frames.append((v, prev[1]))  # a run of frames on one set of faces (a segment) stays one
                continue
            g, report = _orient(v, f, s, up)
            prev = (f, g)
            frames.append((v, g))
            reports.append((t, report))
        _say_orientation(reports, where)
        for t, (v, g) in enumerate(frames):
            _require_area(v, g, seq.frame_sources[t] if seq.frame_sources else where, t)
        _check_size(surface_vertices(*frames[0]), s, axis)
        seq = VaryingTopologySequence(frames, fps, seq.name, seq.source, seq.frame_sources, colors=seq.colors)
        if s.conversion is None:
            _say_interrupted(seq, where)
        if seq.is_fixed_topology():
            seq = seq.to_fixed()
        elif s.conversion is not None:
            from .convert import conversion_summary, to_fixed_topology  # noqa: PLC0415 (optional stage)

            template, template_turned = None, False
            if s.conversion.template:
                from .geometry import mesh_orientation
                from .io import read_mesh

                V, F = read_mesh(cfg.resolve(s.conversion.template))
                tv = _transform(V, s, axis)
                tf = _orient(tv, F, s, up)[0]  # wound as the frames are (keep / flip / auto), unsaid
                # convert fits frames facing outward (it turns closed inward ones) and its template
                # must agree; the winding asked for is given back on the output below (a new user's
                # inward template gave an inward output under auto and flip, all of it "flipped")
                template_turned = mesh_orientation(tv, tf, up) == "inward"
                template = (tv, np.ascontiguousarray(tf[:, ::-1]) if template_turned else tf)
            try:
                seq = to_fixed_topology(seq, strategy=s.conversion.strategy, template=template,
                                        **s.conversion.options)
            except MeshDataError as e:  # a data problem: its own message, the template's named as the scene's
                if template is not None and str(e).startswith("template"):
                    raise MeshDataError(f"surface.conversion.template ({s.conversion.template}): {e}") from None
                raise
            except (TypeError, ValueError) as e:  # unknown or bad strategy options
                raise SceneError(f"surface.conversion.options: {e}") from e
            info = seq.conversion
            if template_turned or (template is None and s.orientation in ("keep", "flip")
                                   and info.key_frame in set(info.turned_outward)):
                # convert fits frames facing outward (its fit compares normals) and turned the key
                # frame, whose faces the template keeps: the winding asked for is given back (a new
                # user's inward frames came out facing outward under orientation: keep)
                seq = FixedTopologySequence(seq.V, np.ascontiguousarray(seq.F[:, ::-1]), seq.fps, seq.name, seq.source,
                                            colors=seq.colors)
                seq.conversion = info
            for line in conversion_summary(seq.conversion):  # a poor fit or a web is said, as convert says it
                if line.startswith("warning: "):
                    warnings.warn(f"{where}: surface.conversion: {scene_keys(line[len('warning: '):])}", UserWarning,
                                  stacklevel=2)
    note = playback_note(seq, s.playback)
    if note:
        warnings.warn(f"{where}: {note}", stacklevel=2)
    seq = _upsampled(seq, s, where)
    seq.up_axis = "z"  # the scene's frame: saved, it is read back unturned (io.stored_up_axis aside)
    return seq


def _upsampled(seq, s, where: str):
    """``seq`` played at ``surface.upsample`` frames per input frame
    (:meth:`FixedTopologySequence.upsampled`, its ends as ``surface.playback`` plays them)."""
    factor = int(s.upsample)
    if factor == 1 or seq.num_frames < 2:
        return seq
    if not isinstance(seq, FixedTopologySequence):
        raise SceneError(f"surface.upsample {factor}: {where} has varying topology (or template segments), whose "
                         "frames cannot be blended across a change of faces; convert it to one template first "
                         "(surface.conversion, or python -m dynmesh_warp.convert to an .npz file) or leave "
                         "surface.upsample at 1")
    playback = resolve_playback(seq, s.playback)
    frames = upsampled_frames(seq.num_frames, factor, playback)
    need, free = frames * seq.num_vertices * 12, free_bytes()  # float32 frames, host (the device holds a copy)
    if free and need > free:
        raise SceneError(f"surface.upsample {factor}: {frames:,} frames of {seq.num_vertices:,} vertices need "
                         f"{need / 2**30:,.1f} GiB, {free / 2**30:,.1f} GiB free; a smaller factor")
    return seq.upsampled(factor, playback)


#: convert's command-line flags in its summary, and the scene keys that set the same in a scene's
#: surface.conversion section (a run's warning said "--key-frame N", which run refuses)
_CONVERT_FLAGS = ((re.compile(r"--key-frame( N)?"), lambda m: "surface.conversion.options.key_frame" + (
                      ": N" if m.group(1) else "")),
                  (re.compile(r"--option ([a-z_]+)=(\S+)"), lambda m: f"surface.conversion.options.{m.group(1)}: "
                                                                      f"{m.group(2)}"),
                  (re.compile(r"--strategy ([a-z]+)"), lambda m: f"surface.conversion.strategy: {m.group(1)}"))


def scene_keys(line: str) -> str:
    """A line of ``convert``'s summary with its command-line flags as the scene keys that set the
    same (for warnings of a scene's own conversion)."""
    for pattern, repl in _CONVERT_FLAGS:
        line = pattern.sub(repl, line)
    return line


def refuse_starts_inside(V0, F0, entries, frame: int = 0, closed: bool | None = None) -> None:
    """Refuse (:class:`SceneError`) a body whose centre starts inside a closed surface, behind its
    faces (frame ``frame``, whose vertices are ``V0``; a surface facing inward has its inside in
    front of its faces, which hold the body): contacts with the surface are one-sided, so it would
    fall out through the faces (docs/scene.md). ``entries``: ``(label, position, clearance)`` per
    body, the label naming its scene field (``spheres.3``, ``newton.bodies.0``) and the clearance
    [m] (its radius: how far above the surface the message suggests). ``closed``: whether the
    surface is closed, when already known. The one rule of the built-in world, the batched envs
    (at each env's start frame) and the Newton path."""
    if not len(entries):
        return
    inside = points_inside(V0, F0, [pos for _, pos, _ in entries], closed)
    if inside.size:
        label, pos, clearance = entries[int(inside[0])]
        top = float(surface_vertices(V0, F0)[:, 2].max())  # not a stray vertex's height
        raise SceneError(
            f"{label}: position {[round(float(x), 6) for x in np.asarray(pos, float)]} starts inside the closed "
            f"surface (frame {frame}), behind its faces; contacts are one-sided, so it would fall out through it. "
            f"Move it outside, e.g. z >= {top + float(clearance):.4g} above the surface; or, for a body meant to be "
            "inside (a room, a tunnel, a container), wind the surface to face inward: surface.orientation: keep "
            "(faces as in the file) or flip"
            + (f" ({inside.size} {'spheres' if all(e[0].startswith('spheres.') for e in entries) else 'bodies'} "
               "are inside)" if inside.size > 1 else ""))


def sphere_entries(cfg: SceneConfig) -> list:
    """:func:`refuse_starts_inside`'s entries of a scene's listed spheres (none when spawned)."""
    if not isinstance(cfg.spheres, list):
        return []
    return [(f"spheres.{i}", sp.position, sp.radius) for i, sp in enumerate(cfg.spheres)]


def scene_spheres(cfg: SceneConfig, V0: np.ndarray):
    """The scene's spheres: ``(radius (S,) float32 [m], mass (S,) float64 [kg], position (S, 3)
    float32 [m], velocity (S, 3) float32 [m/s] or None)``, from a list of spheres or a spawn
    section (dropped against gravity over frame 0's surface points ``V0``, those a face uses:
    :func:`~dynmesh_warp.sequence.surface_vertices`). Both engines take their spheres from here."""
    if isinstance(cfg.spheres, list):
        radius = [sp.radius for sp in cfg.spheres]
        mass = [sp.mass for sp in cfg.spheres]
        pos = [sp.position for sp in cfg.spheres]
        vel = np.asarray([sp.velocity for sp in cfg.spheres], np.float32).reshape(-1, 3)
    else:
        n = cfg.spheres.count
        need, free = n * SPAWN_BYTES, free_bytes()
        if free and need > free:  # a new user's count 1e9 took the machine's 24 GB and was killed, unsaid
            raise SceneError(f"spheres.count {n:,}: spawning them needs about {need / 2**30:,.1f} GiB of memory, "
                             f"{free / 2**30:,.1f} GiB free; fewer spheres (envs.count runs batched copies)")
        radius, mass = np.full(n, cfg.spheres.radius, np.float32), np.full(n, cfg.spheres.mass, np.float64)
        pos, vel = spawn_positions(cfg.spheres, V0, scene_up(cfg)), None
        if n and cfg.spheres.mass == 0:
            warnings.warn("spheres.mass: 0 makes the spawned spheres kinematic: gravity and contacts do not move "
                          "them, so they hang where they are dropped (give a mass in kg to drop them)", stacklevel=2)
        extent = float(np.linalg.norm(np.ptp(V0, axis=0))) if len(V0) else 0.0
        column = 2.5 * cfg.spheres.radius * max(n - 1, 0)
        if column > SPAWN_COLUMN_WARN * max(extent, cfg.spheres.radius):
            g, top = float(np.linalg.norm(cfg.physics.gravity)), column + cfg.spheres.height
            fall = f"falls about {np.sqrt(2 * top / g):.3g} s before it lands" if g > 0 else "never lands (no gravity)"
            warnings.warn(f"spheres: the {n} spawned spheres are dropped one above another, 2.5 radii apart: the "
                          f"top one starts {top:.4g} m above the surface ({extent:.3g} m across) and {fall}; give "
                          "fewer spheres, or a list of positions (envs.count runs batched copies)", stacklevel=2)
    return (np.asarray(radius, np.float32).reshape(-1), np.asarray(mass, np.float64).reshape(-1),
            np.asarray(pos, np.float32).reshape(-1, 3), vel)


def scene_ground(cfg: SceneConfig, seq) -> float | None:
    """The ground plane's height [m]: ``physics.ground``, where ``"auto"`` is the lowest vertex of
    any frame; None: no ground."""
    g = cfg.physics.ground
    return float(seq.bounds()[0][2]) if g == "auto" else (None if g is None else float(g))


#: a sphere may start overlapping the ground plane by this fraction of its radius (one placed
#: resting on it, up to rounding); deeper is refused
GROUND_OVERLAP = 0.01


def refuse_below_ground(cfg: SceneConfig, seq, ground: float | None, pos: np.ndarray, radius: np.ndarray) -> None:
    """Refuse (:class:`SceneError`) a sphere whose centre starts below ``ground`` + its radius
    (by more than GROUND_OVERLAP of it): the ground plane would move it up at the first step,
    without a word, and the run would report no penetration (a new user's physics.ground 0.5
    lifted a sphere from z 0.2 to 0.55; ground 5, a units slip, lifted every spawned sphere).
    Warns when the ground lies above the whole surface (every sphere would rest on it)."""
    if ground is None:
        return
    top = float(seq.bounds()[1][2])
    if ground > top:
        warnings.warn(f"physics.ground: {ground:.6g} lies above the whole surface (its highest point, any frame: "
                      f"z = {top:.6g}): the spheres rest on the ground plane and never meet the surface "
                      "(auto: the surface's lowest point)", UserWarning, stacklevel=3)
    pos = np.asarray(pos, np.float64).reshape(-1, 3)
    r = np.asarray(radius, np.float64).reshape(-1)
    low = np.flatnonzero(pos[:, 2] < ground + (1.0 - GROUND_OVERLAP) * r)
    if not low.size:
        return
    i = int(low[0])
    label = f"spheres.{i}" if isinstance(cfg.spheres, list) else "spheres (spawned)"
    raise SceneError(f"{label}: centre z = {pos[i, 2]:.6g} starts below the ground plane (physics.ground = "
                     f"{cfg.physics.ground!r}, z = {ground:.6g}, plus its radius {r[i]:.4g}): the ground would "
                     f"push it up to z = {ground + r[i]:.6g} at the first step"
                     + (f" ({low.size} of {len(pos)} spheres are below it)" if low.size > 1 else "")
                     + ". Lower physics.ground (auto: the surface's lowest point; null: none) or raise the spheres")


def require_fixed_topology(cfg, seq, who: str):
    """``seq`` when it has fixed topology; else a :class:`SceneError` saying that ``who`` (e.g.
    "batched envs need", "the Newton path needs") with its verb needs one, and how to get it: one template
    (``max_segments=1``) for convert's piecewise-fixed output, ``surface.conversion`` otherwise."""
    if isinstance(seq, FixedTopologySequence):
        return seq
    src = cfg.surface.source
    if isinstance(seq, VaryingTopologySequence) and seq.is_piecewise_fixed():
        how = (f"it has {len(seq.segments())} segments of fixed topology (convert's piecewise-fixed output, "
               f"played by a single world with collider: fixed or rebuild); convert it to one template, "
               f"python -m dynmesh_warp.convert INPUT OUT.npz --option max_segments=1, or set surface.conversion")
    else:
        how = ("set surface.conversion to convert it (on the command line: "
               "--set surface.conversion.strategy=graph), or convert it once with python -m dynmesh_warp.convert")
    raise SceneError(f"surface {src}: {who} a fixed-topology surface; {how}")


def build_model(cfg: SceneConfig, seq, device=None) -> tuple[Model, State]:
    """The one builder of a scene's :class:`~dynmesh_warp.world.Model` (surface, spheres,
    physics) and its initial :class:`~dynmesh_warp.world.State`, from a sequence already in the
    scene frame (``load_surface`` / ``prepare_surface``). The built-in world runs them; the
    Newton world takes the surface and the spheres from them (``build_newton_world``)."""
    device = scene_device(cfg, device, "the device argument")  # the CLI checked its --device before
    surface = surface_model(seq, device, playback=cfg.surface.playback, interpolate=cfg.surface.interpolate)
    radius, mass, pos, vel = scene_spheres(cfg, surface_vertices(*seq.frame(0)))
    check_precision(*seq.bounds(), pos, radius, f"surface {seq.source or seq.name}", cfg.surface.translate,
                    cfg.surface.scale)
    refuse_outsized_spheres(*seq.bounds(), radius, f"surface {seq.source or seq.name}")
    p = cfg.physics
    # every field the scene's physics section shares with PhysicsParams (PhysicsCore), so a new
    # setting cannot be validated by the schema and then dropped here
    ground = scene_ground(cfg, seq)
    refuse_below_ground(cfg, seq, ground, pos, radius)
    params = PhysicsParams(**{k: getattr(p, k) for k in PhysicsCore.model_fields}, ground_height=ground)
    model = Model(surface, SphereModel(radius, mass, device), params)
    return model, State(model, pos, vel)


def build_world(cfg: SceneConfig, device=None, collider: str | None = None,
                rebuild_every: str | None = None, sequence=None) -> World:
    """Create the model, state and world of a scene on ``device`` (default: cfg.device or Warp's).

    ``sequence``: a sequence already in memory (e.g. from ``load_sequence``) to use instead of
    ``surface.source``; the rest of the ``surface`` section (fps, up_axis, scale, translate,
    orientation, conversion) is applied to it as to a loaded one. ``cfg`` may also be a scene
    YAML's path or a dict of its sections (:func:`~dynmesh_warp.config.scene_config`)."""
    cfg = scene_config(cfg)
    seq = load_surface(cfg) if sequence is None else prepare_surface(sequence, cfg)
    p = cfg.physics
    collider = parse(Collider, collider or p.collider, "collider").value  # an unknown name: the choices, named
    if rebuild_every is not None and collider != Collider.REBUILD.value:  # accepted and ignored before (a new user's)
        raise SceneError(f"--rebuild-every (rebuild_every) applies to the rebuild collider; this scene's is {collider!r} "
                         "(add --collider rebuild, or set physics.rebuild_every in a scene with physics.collider: rebuild)")
    if collider not in surface_model_class(seq).colliders_for(seq):  # before the frames go to the device
        try:
            seq.to_fixed()
            why = "frames have different topology"
        except TopologyMismatchError as e:  # names the first frame that differs from frame 0
            why = e.summary
        if isinstance(seq, VaryingTopologySequence) and seq.is_piecewise_fixed():
            raise SceneError(
                f"surface {cfg.surface.source}: {why}; its {len(seq.segments())} segments of fixed topology "
                f"(piecewise-fixed, as convert writes) need physics.collider: fixed (automatic) or "
                f"collider: rebuild (a BVH per segment), not {Collider(collider).value!r}")
        raise SceneError(
            f"surface {cfg.surface.source}: {why}. Varying topology needs "
            "physics.collider: rebuild, or surface.conversion to convert it to fixed topology (on the "
            "command line: --set physics.collider=rebuild (run: --collider rebuild), or --set "
            "surface.conversion.strategy=graph; or convert it once, python -m dynmesh_warp.convert "
            f"{shlex.quote(str(cfg.surface.source))} OUT.npz, and run OUT.npz)")  # quoted: a path with spaces
    refuse_starts_inside(*seq.frame(0), sphere_entries(cfg))  # listed spheres must start outside a closed surface
    model, state = build_model(cfg, seq, device)
    return World(model, state, collider=collider, rebuild_every=rebuild_every or p.rebuild_every)
