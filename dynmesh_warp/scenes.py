"""Built-in scenes generated in code (no download): the default scene and the test data.

- ``wave_bowl``  fixed topology: a square sheet shaped as a shallow bowl with travelling
  waves on it (a height field, normals up, +z), periodic in time so it loops seamlessly.
- ``pulsing_blob`` fixed topology, closed: an icosphere with a breathing, wobbling, drifting
  radial deformation (outward normals).
- ``torus_to_sphere`` varying topology: marching cubes of an implicit shape morphing from a
  torus into a sphere (genus 1 -> 0), a new mesh every frame.
- ``rigid_motion`` fixed topology: a mesh under a rotation + translation (for conversion tests).
- ``articulated_figure`` fixed topology: a capsule person doing jumping jacks, arms starting
  3 cm from the torso (the conversion's articulated-motion test).
- ``starfish`` fixed topology: five thin arms bending into arcs and back, out of phase (an
  unseen-motion check of the conversion; ``curl`` > 1.5 makes loops).
"""

from __future__ import annotations

import numpy as np

from .geometry import orient_outward
from .sequence import FixedTopologySequence, VaryingTopologySequence

__all__ = ["wave_bowl", "pulsing_blob", "torus_to_sphere", "rigid_motion", "articulated_figure", "starfish", "FIGURE_BONES",
           "grid_sheet", "icosphere",
           "BUILTIN_SCENES", "builtin_sequence"]


def grid_sheet(n: int = 64, size: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """(n*n, 3) vertices on z = 0 over [-size/2, size/2]^2 and (2(n-1)^2, 3) faces, normals +z."""
    xs = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(xs, xs, indexing="xy")
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], axis=1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="xy")
    v00 = (j * n + i).ravel()
    v10 = v00 + 1
    v01 = v00 + n
    v11 = v01 + 1
    F = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    return V.astype(np.float32), F.astype(np.int32)


def wave_bowl(n: int = 64, frames: int = 48, fps: float = 24.0, amplitude: float = 0.06) -> FixedTopologySequence:
    """A 2 m x 2 m bowl-shaped sheet (z up) with travelling waves, periodic over ``frames``."""
    V0, F = grid_sheet(n, 2.0)
    x, y = V0[:, 0].astype(np.float64), V0[:, 1].astype(np.float64)
    r2 = x * x + y * y
    period = frames / fps
    w = 2 * np.pi / period
    V = np.repeat(V0[None], frames, axis=0).astype(np.float64)
    for t in range(frames):
        s = t / fps
        z = 0.3 * r2
        z += amplitude * np.sin(3.0 * x - w * s) * np.cos(2.0 * y)
        z += 0.5 * amplitude * np.sin(4.0 * (x + y) + 2 * w * s)
        z += 0.8 * amplitude * np.sin(w * s) * np.exp(-4.0 * r2)  # a central bump rising and falling
        V[t, :, 2] = z
    return FixedTopologySequence(V.astype(np.float32), F, fps=fps, name="wave_bowl", source="builtin:wave_bowl")


def icosphere(subdivisions: int = 4, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32)


def pulsing_blob(subdivisions: int = 4, frames: int = 48, fps: float = 24.0, radius: float = 0.5,
                 center=(0.0, 0.0, 0.6)) -> FixedTopologySequence:
    """A closed, outward-oriented blob breathing and wobbling in place, periodic over ``frames``."""
    V0, F = icosphere(subdivisions, 1.0)
    d = V0.astype(np.float64)
    w = 2 * np.pi * fps / frames
    V = np.empty((frames,) + V0.shape)
    for t in range(frames):
        s = t / fps
        rr = 1.0 + 0.12 * np.sin(w * s) + 0.08 * np.sin(3 * d[:, 0] + w * s) * np.cos(2 * d[:, 1])
        V[t] = radius * d * rr[:, None] + np.asarray(center)
    return FixedTopologySequence(V.astype(np.float32), F, fps=fps, name="pulsing_blob", source="builtin:pulsing_blob")


def torus_to_sphere(frames: int = 200, fps: float = 24.0, resolution: int = 48,
                    center=(0.0, 0.0, 0.6)) -> VaryingTopologySequence:
    """Marching cubes of an implicit shape morphing from a torus into a sphere over ``frames``.

    f = (1 - s) * sdf_torus + s * sdf_sphere, s = smoothstep(t / (frames - 1)); the shape also
    turns slowly about z. Vertex count and faces change every frame (genus 1 -> 0).
    """
    from skimage.measure import marching_cubes

    lo, hi = -0.85, 0.85
    g = np.linspace(lo, hi, resolution)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    spacing = (g[1] - g[0],) * 3
    out = []
    for t in range(frames):
        u = t / max(frames - 1, 1)
        s = u * u * (3 - 2 * u)
        ang = 0.6 * np.pi * u
        ca, sa = np.cos(ang), np.sin(ang)
        xr, yr = ca * X + sa * Y, -sa * X + ca * Y
        q = np.sqrt(xr**2 + yr**2) - 0.45
        torus = np.sqrt(q**2 + Z**2) - 0.2
        sphere = np.sqrt(xr**2 + yr**2 + Z**2) - 0.5
        f = (1 - s) * torus + s * sphere
        verts, faces, _, _ = marching_cubes(f, level=0.0, spacing=spacing)
        verts = verts + lo + np.asarray(center)
        faces = orient_outward(verts, faces.astype(np.int32))
        out.append((verts.astype(np.float32), faces.astype(np.int32)))
    return VaryingTopologySequence(out, fps=fps, name="torus_to_sphere", source="builtin:torus_to_sphere")


def rigid_motion(base: tuple[np.ndarray, np.ndarray] | None = None, frames: int = 30, fps: float = 24.0,
                 angular_speed: float = 0.5, velocity=(0.1, 0.05, 0.0)) -> FixedTopologySequence:
    """A mesh (default: icosphere with bumps) rotating about z and translating at constant speed."""
    if base is None:
        V0, F = icosphere(3, 0.5)
        V0 = V0 * (1.0 + 0.15 * np.sin(4 * V0[:, :1]))  # break the symmetry
    else:
        V0, F = base
    V = np.empty((frames,) + V0.shape)
    for t in range(frames):
        s = t / fps
        a = angular_speed * s
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        V[t] = V0 @ R.T + np.asarray(velocity) * s
    return FixedTopologySequence(V.astype(np.float32), F, fps=fps, name="rigid_motion", source="builtin:rigid_motion")


def _segment_distance(P: np.ndarray, a, b) -> tuple[np.ndarray, np.ndarray]:
    """Distance of points P (..., 3) to the segment a-b and the segment parameter in [0, 1]."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    u = np.clip(((P - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(P - (a + u[..., None] * ab), axis=-1), u


def _axis_rotation(axis, angle: float) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


#: bones of ``articulated_figure``: name -> (start joint, end joint, radius) in the rest pose [m]
#: (z up, the figure faces -y; the arms join the torso at the shoulders and hang ~3 cm from it).
FIGURE_BONES = {
    "torso": ((0.0, 0.0, 0.95), (0.0, 0.0, 1.45), 0.15),
    "head": ((0.0, 0.0, 1.62), (0.0, 0.0, 1.66), 0.11),
    "arm_l": ((0.17, 0.0, 1.40), (0.27, 0.0, 0.85), 0.05),
    "arm_r": ((-0.17, 0.0, 1.40), (-0.27, 0.0, 0.85), 0.05),
    "leg_l": ((0.09, 0.0, 0.92), (0.11, 0.0, 0.08), 0.07),
    "leg_r": ((-0.09, 0.0, 0.92), (-0.11, 0.0, 0.08), 0.07),
}


def articulated_figure(frames: int = 60, fps: float = 30.0, resolution: int = 56,
                       arm_swing: float = 2.6, leg_swing: float = 0.5, cycles: float = 1.0, sway: float = 1.0
                       ) -> FixedTopologySequence:
    """A stick-figure person doing jumping jacks (fixed topology; the conversion's articulated test).

    The rest mesh is marching cubes (``resolution`` cells on the height) of a smooth union of
    capsules (:data:`FIGURE_BONES`: torso, head, two arms joined at the shoulders and hanging
    ~3 cm from the torso, two legs). Frame k poses it by linear blend skinning: the arms swing up and out about the
    shoulders by up to ``arm_swing`` rad, the legs spread by ``leg_swing`` rad, the whole body
    hops and turns a little (``sway`` x the default hop and turn; 0: the body stays where it
    stands); ``cycles`` full cycles over the sequence. With the defaults the
    hands travel ~1.3 m (the bbox diagonal is ~2 m) and an arm moves ~0.1 m per frame.
    """
    from skimage.measure import marching_cubes

    lo, hi = np.array([-0.45, -0.3, -0.02]), np.array([0.45, 0.3, 1.82])
    h = (hi[2] - lo[2]) / int(resolution)
    axes = [np.arange(lo[i], hi[i] + h, h) for i in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    f = None
    k = 0.01  # smooth-min radius [m]
    for a, b, r in FIGURE_BONES.values():
        d = _segment_distance(G, a, b)[0] - r
        if f is None:
            f = d
        else:  # polynomial smooth minimum
            hh = np.clip(0.5 + 0.5 * (d - f) / k, 0.0, 1.0)
            f = d * (1 - hh) + f * hh - k * hh * (1 - hh)
    verts, faces, _, _ = marching_cubes(f, level=0.0, spacing=(h, h, h))
    V0 = verts + lo
    F = orient_outward(V0, faces.astype(np.int32))
    # skinning weights: softmax of the distance to each bone
    names = list(FIGURE_BONES)
    D = np.stack([_segment_distance(V0, *FIGURE_BONES[n][:2])[0] - FIGURE_BONES[n][2] for n in names], 1)
    W = np.exp(-(D - D.min(axis=1, keepdims=True)) / 0.012)
    W /= W.sum(axis=1, keepdims=True)
    out = np.empty((frames, len(V0), 3))
    for t in range(frames):
        u = t / max(frames - 1, 1)
        s = 0.5 - 0.5 * np.cos(2 * np.pi * cycles * u)  # 0 -> 1 -> 0 per cycle
        Vt = np.zeros_like(V0)
        for j, n in enumerate(names):
            a = np.asarray(FIGURE_BONES[n][0], float)
            if n.startswith("arm"):
                sign = 1.0 if n.endswith("l") else -1.0
                R = _axis_rotation((0, 1, 0), -sign * arm_swing * s)
            elif n.startswith("leg"):
                sign = 1.0 if n.endswith("l") else -1.0
                R = _axis_rotation((0, 1, 0), -sign * leg_swing * s)
            else:
                R = np.eye(3)
            Vt += W[:, j:j + 1] * ((V0 - a) @ R.T + a)
        turn = _axis_rotation((0, 0, 1), sway * 0.4 * np.sin(2 * np.pi * u))
        Vt = Vt @ turn.T + sway * np.array([0.15 * np.sin(np.pi * u), 0.0, 0.12 * s])
        out[t] = Vt
    return FixedTopologySequence(out.astype(np.float32), F, fps=fps, name="articulated_figure",
                                 source="builtin:articulated_figure")


def starfish(frames: int = 48, fps: float = 24.0, arms: int = 5, resolution: int = 96, arm_length: float = 0.8,
             arm_radius: float = 0.06, body_radius: float = 0.22, curl: float = 1.0) -> FixedTopologySequence:
    """A starfish whose ``arms`` thin, tapered arms bend (not rotate) into an arc and back, out of
    phase (fixed topology; a conversion test motion no default was tuned on, docs/evaluation.md).

    The rest mesh is marching cubes (``resolution`` cells over 2.4 m) of a flattened body ball
    and capsules tapering to half their radius. Frame t bends each arm about the axis across it
    at the body's edge: the arm's centreline becomes a circular arc of curvature
    ``curl * pi / arm_length * sin(2 pi t / frames + 2 pi k / arms)`` and each point keeps its
    offset from it (an exact bend: volume kept). ``curl`` 1: up to a half circle (tips ~2 m/s at
    48 frames); above ~1.5 the tips curl back onto their own arms (loops: genus changes)."""
    from skimage.measure import marching_cubes

    half = 1.2
    g = np.linspace(-half, half, int(resolution))
    P = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1)
    sdf = np.linalg.norm(P * [1.0, 1.0, 1.6], axis=-1) - body_radius
    dirs = [np.array([np.cos(a), np.sin(a), 0.0]) for a in 2 * np.pi * np.arange(arms) / arms]
    for d in dirs:
        s_ = np.clip(P @ d, 0.0, body_radius + arm_length)
        r = arm_radius * (1.0 - 0.5 * s_ / (body_radius + arm_length))
        sdf = np.minimum(sdf, np.linalg.norm(P - s_[..., None] * d, axis=-1) - r)
    v, f, _, _ = marching_cubes(sdf, 0.0, spacing=(g[1] - g[0],) * 3)
    V0 = v - half
    F = orient_outward(V0, f.astype(np.int32))
    up = np.array([0.0, 0.0, 1.0])
    out = np.empty((frames, len(V0), 3), np.float32)
    for t in range(frames):
        Vt = V0.copy()
        for k, d in enumerate(dirs):
            e = np.cross(up, d)
            along = V0 @ d
            arm = (along > body_radius) & (np.abs(V0 @ e) < 2 * arm_radius)
            kappa = curl * np.pi / arm_length * np.sin(2 * np.pi * t / frames + 2 * np.pi * k / arms)
            if abs(kappa) < 1e-9:
                continue
            th = kappa * (along[arm] - body_radius)
            c = body_radius * d + (np.sin(th) / kappa)[:, None] * d + ((1 - np.cos(th)) / kappa)[:, None] * up
            n = -np.sin(th)[:, None] * d + np.cos(th)[:, None] * up
            Vt[arm] = c + (V0[arm] @ e)[:, None] * e + V0[arm, 2:3] * n
        out[t] = Vt
    return FixedTopologySequence(out, F, fps=fps, name="starfish", source="builtin:starfish")


def with_floor(V: np.ndarray, F: np.ndarray, size: float = 1.5, up: int = 2, thickness: float = 0.03,
               gap: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A fixed-topology sequence (V (T, N, 3), F) with a static slab added, as the reconstruction
    of a real capture keeps the floor its subject stands on: ``size`` x frame 0's bbox diagonal
    wide, ``thickness`` x it thick, its top ``gap`` x it below the lowest point of the sequence
    (0: the feet touch it), centred under frame 0, and subdivided to about twice the sequence's
    mean edge (so vertex-based metrics count it). ``up``: the vertical axis index. Returns
    (V (T, N + N_floor, 3) float32, F int32), the slab's vertices and faces last."""
    import trimesh

    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    diag = float(np.linalg.norm(V[0].max(0) - V[0].min(0)))
    ext = np.full(3, float(size) * diag)
    ext[up] = float(thickness) * diag
    box = trimesh.creation.box(extents=ext)
    edge = float(np.linalg.norm(V[0][F[:, 0]] - V[0][F[:, 1]], axis=1).mean())
    bv, bf = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=2.0 * edge, max_iter=20)
    c = V[0].mean(0)
    c[up] = V[:, :, up].min() - (float(gap) + 0.5 * float(thickness)) * diag
    W = np.concatenate([V, np.broadcast_to(bv + c, (len(V),) + bv.shape)], axis=1)
    return W.astype(np.float32), np.concatenate([F, bf + V.shape[1]]).astype(np.int32)


BUILTIN_SCENES = {
    "wave_bowl": wave_bowl,
    "pulsing_blob": pulsing_blob,
    "torus_to_sphere": torus_to_sphere,
    "rigid_motion": rigid_motion,
    "starfish": starfish,
    "articulated_figure": articulated_figure,
}


def builtin_sequence(name: str, **kwargs):
    if name not in BUILTIN_SCENES:
        raise ValueError(f"unknown built-in sequence {name!r}; choose one of {sorted(BUILTIN_SCENES)}")
    return BUILTIN_SCENES[name](**kwargs)
