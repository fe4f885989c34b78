"""Build a :class:`~dynmesh_warp.world.World` from a validated scene description."""

from __future__ import annotations

import numpy as np
import warp as wp

from .config import SceneConfig, SceneError, spawn_positions
from .sequence import FixedTopologySequence, VaryingTopologySequence
from .world import Model, PhysicsParams, SphereModel, State, SurfaceModel, VaryingSurfaceModel, World

__all__ = ["load_surface", "build_world"]

# y-up data to z-up: rotate +90 degrees about x, (x, y, z) -> (x, -z, y)
_Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _transform(V: np.ndarray, cfg) -> np.ndarray:
    V = V.astype(np.float64)
    if cfg.up_axis == "y":
        V = V @ _Y_TO_Z.T
    return (V * cfg.scale + np.asarray(cfg.translate)).astype(np.float32)


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
                            **({"subdir": s.subdir} if s.subdir else {}))
    if s.fps is not None:
        seq.fps = float(s.fps)
    if isinstance(seq, FixedTopologySequence):
        seq = FixedTopologySequence(_transform(seq.V, s), seq.F, seq.fps, seq.name, seq.source)
    else:
        frames = [(_transform(v, s), f) for v, f in seq.frames]
        seq = VaryingTopologySequence(frames, seq.fps, seq.name, seq.source, seq.frame_sources)
        if seq.is_fixed_topology():
            seq = seq.to_fixed()
        elif s.conversion is not None:
            from .convert import to_fixed_topology  # noqa: PLC0415 (optional stage)

            template = None
            if s.conversion.template:
                from .io import read_mesh

                V, F = read_mesh(cfg.resolve(s.conversion.template))
                template = (_transform(V, s), F)
            seq = to_fixed_topology(seq, strategy=s.conversion.strategy, template=template,
                                    **s.conversion.options)
    return seq


def build_world(cfg: SceneConfig, device=None, collider: str | None = None,
                rebuild_every: str | None = None, sequence=None) -> World:
    """Create the model, state and world of a scene on ``device`` (default: cfg.device or Warp's)."""
    device = wp.get_device(device or cfg.device)
    seq = load_surface(cfg) if sequence is None else sequence
    p = cfg.physics
    collider = collider or p.collider
    if isinstance(seq, FixedTopologySequence):
        surface = SurfaceModel(seq, device, playback=cfg.surface.playback, interpolate=cfg.surface.interpolate)
        V0 = seq.V[0]
    else:
        if collider != "rebuild":
            raise SceneError(
                f"surface {cfg.surface.source}: frames have different topology; use "
                "physics.collider: rebuild, or set surface.conversion to convert it to fixed topology")
        surface = VaryingSurfaceModel(seq, device, playback=cfg.surface.playback)
        V0 = seq.frames[0][0]
    if isinstance(cfg.spheres, list):
        radius = [sp.radius for sp in cfg.spheres]
        mass = [sp.mass for sp in cfg.spheres]
        pos = [sp.position for sp in cfg.spheres]
        vel = [sp.velocity for sp in cfg.spheres]
    else:
        n = cfg.spheres.count
        radius, mass = [cfg.spheres.radius] * n, [cfg.spheres.mass] * n
        pos, vel = spawn_positions(cfg.spheres, V0), None
    ground = p.ground
    if ground == "auto":
        ground = float(seq.V[:, :, 2].min()) if isinstance(seq, FixedTopologySequence) else float(
            min(v[:, 2].min() for v, _ in seq.frames))
    params = PhysicsParams(dt=p.dt, substeps=p.substeps, gravity=p.gravity, restitution=p.restitution,
                           friction=p.friction, rest_speed=p.rest_speed, margin=p.margin,
                           auto_substeps=p.auto_substeps, ground_height=ground)
    model = Model(surface, SphereModel(np.asarray(radius, np.float32).reshape(-1), mass, device), params)
    state = State(model, np.asarray(pos, np.float32).reshape(-1, 3),
                  None if vel is None else np.asarray(vel, np.float32).reshape(-1, 3))
    return World(model, state, collider=collider, rebuild_every=rebuild_every or p.rebuild_every)
