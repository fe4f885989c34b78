"""Render Gaussians (and the rigid spheres) with our own Warp splatting rasteriser (issue 16).

``Renderer.render(means, covariances, sh, opacities, cameras, spheres=...)`` returns device
arrays (rgb (C, H, W) vec3, alpha, expected depth) for a batch of pinhole cameras in the
OpenCV/COLMAP convention; ``render_world(world, gaussians, cameras)`` draws a simulation's bound
Gaussians and its spheres. kernels/render.py has the maths (the reference 3DGS rasteriser's:
EWA projection, 16 x 16 tiles, radix sort by (camera, tile, depth), front-to-back alpha
compositing with early termination). Runs on the CPU and on CUDA.

    python -m dynmesh_warp.render scene.yaml --out frames/ --frames 48
    python -m dynmesh_warp.render scene.yaml --figure strip.png --moments 4
    python -m dynmesh_warp.render scene.yaml --video run.gif --frames 48
"""

from __future__ import annotations

import contextlib
import math
import signal
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from .choices import DEFAULT_RASTERISER, Rasteriser, device_kind, parse, values
from .gaussians import SHADE_AMBIENT
from .kernels.render import (
    EMPTY_KEY,
    EMPTY_KEY32,
    KEY_KERNELS,
    RASTERIZE_SHARED,
    SH_C0,
    SHAPE_BOX,
    SHAPE_CAPSULE,
    SHAPE_CYLINDER,
    SHAPE_ELLIPSOID,
    SHAPE_MESH,
    SHAPE_SPHERE,
    TILE,
    cast_rigid_shapes,
    emit_depth_keys,
    project_gaussians,
    rasterize_gaussians,
    scatter_depth_rank,
)

__all__ = ["Camera", "look_at", "orbit_cameras", "Renderer", "RenderResult", "RigidShapes", "rgb_to_sh", "render_world",
           "render_envs", "main"]

#: shape types drawn by :class:`RigidShapes` (Newton's ``GeoType`` names, lower case)
SHAPE_KINDS = {"sphere": int(SHAPE_SPHERE), "box": int(SHAPE_BOX), "capsule": int(SHAPE_CAPSULE),
               "cylinder": int(SHAPE_CYLINDER), "ellipsoid": int(SHAPE_ELLIPSOID), "mesh": int(SHAPE_MESH),
               "convex_mesh": int(SHAPE_MESH)}


#: how far a camera's ``R`` may be from a rotation: max |R R^T - I| and |det R - 1| (a float32
#: rotation is ~1e-7 off; a scaled or sheared R draws a distorted picture)
ROTATION_TOL = 1e-4
#: how close to parallel ``look_at``'s ``up`` and view direction may be: |up x view| / |up|
UP_PARALLEL_TOL = 1e-6


def _check_sizes(width, height, where: str) -> None:
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v <= 0:
            raise ValueError(f"{where}: {name} must be a positive integer [px], got {v!r}")


def _check_cameras(R, t, k, where) -> None:
    """The one check of camera values (a :class:`Camera` when made, a render's cameras when they
    change): R (C, 3, 3) a rotation (finite, orthonormal with det +1 within ``ROTATION_TOL``),
    t (C, 3) finite, k (C, 4) = fx, fy finite > 0 and cx, cy finite [px]. A ValueError names
    the field, its value and the camera (``where(c)``): NaN gave an all-background image, fx 0 or
    < 0 and a non-rotation R a wrong one, without a word."""
    R, t, k = (np.asarray(v, np.float64) for v in (R, t, k))
    with np.errstate(invalid="ignore"):  # vectorised over the cameras (a batch's check is one pass)
        off = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(np.where(np.isfinite(R), R, 0.0))
        bad = [~(np.isfinite(k[:, 0]) & (k[:, 0] > 0)), ~(np.isfinite(k[:, 1]) & (k[:, 1] > 0)), ~np.isfinite(k[:, 2]),
               ~np.isfinite(k[:, 3]), ~np.isfinite(t).all(axis=1), ~np.isfinite(R).all(axis=(1, 2)),
               (off > ROTATION_TOL) | (np.abs(det - 1.0) > ROTATION_TOL)]
    for which, b in enumerate(bad):
        if not b.any():
            continue
        c = int(np.flatnonzero(b)[0])
        if which < 2:
            raise ValueError(f"{where(c)}: {'fx' if which == 0 else 'fy'} must be a finite focal length > 0 [px], "
                             f"got {k[c, which]:g}")
        if which < 4:
            raise ValueError(f"{where(c)}: {'cx' if which == 2 else 'cy'} must be finite [px], got {k[c, which]:g}")
        if which == 4:
            raise ValueError(f"{where(c)}: t must be finite [m], got {t[c].tolist()}")
        if which == 5:
            raise ValueError(f"{where(c)}: R must be finite, got {R[c].tolist()}")
        raise ValueError(f"{where(c)}: R must be a rotation (orthonormal, det +1, to {ROTATION_TOL:g}), got "
                         f"{np.round(R[c], 6).tolist()} (max |R R^T - I| {off[c]:.3g}, det {det[c]:.6g})")


@dataclass
class Camera:
    """A pinhole camera, OpenCV/COLMAP convention (x right, y down, z forward): world-to-camera
    rotation ``R`` (3, 3) and translation ``t`` (3,) [m]; intrinsics fx, fy, cx, cy [px]; image
    width x height [px] (positive integers). Checked when made (``_check_cameras``: fx, fy > 0,
    every value finite, R a rotation) and again by a render whose cameras changed."""

    R: np.ndarray
    t: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        _check_sizes(self.width, self.height, "Camera")
        R, t = np.asarray(self.R), np.asarray(self.t)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"Camera: R must be (3, 3) and t (3,), got R {R.shape}, t {t.shape}")
        try:
            k = np.array([[self.fx, self.fy, self.cx, self.cy]], np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"Camera: fx, fy, cx, cy must be numbers [px], got {self.fx!r}, {self.fy!r}, "
                             f"{self.cx!r}, {self.cy!r}") from None
        _check_cameras(R[None], t[None], k, lambda c: "Camera")

    @property
    def center(self) -> np.ndarray:
        return -np.asarray(self.R, np.float64).T @ np.asarray(self.t, np.float64)


def look_at(eye, target, up=(0.0, 0.0, 1.0), width: int = 640, height: int = 480, fov_y_deg: float = 45.0) -> Camera:
    """A camera at ``eye`` looking at ``target`` with ``up`` roughly up in the image; fov_y_deg
    the vertical field of view in (0, 180) degrees. ``up`` must be finite, non-zero and not
    parallel to the view direction (the camera's roll would be undefined: a NaN camera)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    if not (np.isfinite(z).all() and np.linalg.norm(z) > 0):
        raise ValueError(f"look_at: eye {eye.tolist()} and target {target.tolist()} must be finite and apart")
    if not (isinstance(fov_y_deg, (int, float, np.integer, np.floating)) and 0.0 < fov_y_deg < 180.0):
        raise ValueError(f"look_at: fov_y_deg must be in (0, 180) degrees, got {fov_y_deg!r}")
    if up.shape != (3,) or not np.isfinite(up).all() or np.linalg.norm(up) == 0:
        raise ValueError(f"look_at: up must be a finite, non-zero 3-vector, got {up.tolist()}")
    z /= np.linalg.norm(z)
    x = np.cross(z, up / np.linalg.norm(up))
    if np.linalg.norm(x) < UP_PARALLEL_TOL:
        raise ValueError(f"look_at: up {up.tolist()} is parallel to the view direction {z.tolist()} (eye to target): "
                         "the camera's roll is undefined; give another up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world
    _check_sizes(width, height, "look_at")
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return Camera(R, -R @ eye, f, f, width / 2.0, height / 2.0, width, height)


def orbit_cameras(center, distance: float, count: int, elevation_deg: float = 20.0, width: int = 640,
                  height: int = 480, fov_y_deg: float = 45.0, start_deg: float = 0.0) -> list[Camera]:
    """``count`` cameras on a circle around ``center`` (z up) at ``elevation_deg``."""
    c = np.asarray(center, np.float64)
    el = math.radians(elevation_deg)
    out = []
    for i in range(count):
        az = math.radians(start_deg) + 2 * math.pi * i / max(count, 1)
        eye = c + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        out.append(look_at(eye, c, width=width, height=height, fov_y_deg=fov_y_deg))
    return out


def rgb_to_sh(rgb) -> np.ndarray:
    """Degree-0 SH coefficients (G, 1, 3) that render as ``rgb`` (G, 3), >= 0 (above 1 for a bright splat, as 3DGS)."""
    return ((np.asarray(rgb, np.float32) - 0.5) / SH_C0).reshape(-1, 1, 3).astype(np.float32)


@dataclass
class RenderResult:
    """rgb (C, H, W) vec3 in [0, 1]; alpha (C, H, W) float; depth (C, H, W) float, expected
    camera z [m] of what was drawn (0 where nothing). Device arrays (``.numpy()`` to read)."""

    rgb: wp.array
    alpha: wp.array
    depth: wp.array
    #: (1,) int32 on the device: (Gaussian, tile) entries dropped by a fixed-capacity render
    #: (``capacity=``); 0 when everything was drawn (always 0 without a capacity)
    overflow: wp.array | None = None


class RigidShapes:
    """Rigid shapes drawn into a render besides the spheres (e.g. a Newton world's bodies,
    ``Simulation.rigid_shapes()``): ray-cast per pixel in each shape's frame, opaque, shaded
    like the spheres, composited by depth with the splats.

    ``shapes``: dicts with ``type`` (a key of :data:`SHAPE_KINDS`), ``scale`` (3,) [m] (sphere
    (r, -, -); box half extents; capsule and cylinder (r, half height, -) along local z;
    ellipsoid semi-axes; mesh the scale of its vertices), ``pose`` (7,) world position and
    quaternion (x, y, z, w), and for meshes ``vertices`` (N, 3) / ``indices`` (M, 3) in the
    shape frame (or ``wp_mesh``: a ``wp.Mesh`` on the device, used as it is). Other types
    (cones, height fields, planes) are not drawn and are listed in
    ``skipped``. ``set_poses`` updates the poses (one upload); the geometry is uploaded once."""

    def __init__(self, shapes: list, device=None, color=(0.35, 0.5, 0.85)):
        self.device = wp.get_device(device)

        def drawable(s):
            return s["type"] in SHAPE_KINDS and (SHAPE_KINDS[s["type"]] != int(SHAPE_MESH) or "vertices" in s
                                                 or "wp_mesh" in s)

        #: indices into ``shapes`` of the shapes drawn (the order ``set_poses`` takes)
        self.kept = [i for i, s in enumerate(shapes) if drawable(s)]
        keep = [shapes[i] for i in self.kept]
        self.skipped = sorted({str(s["type"]) + ("" if s["type"] not in SHAPE_KINDS else " (no vertices)")
                               for s in shapes if not drawable(s)})
        self.count = len(keep)
        d = self.device
        self._meshes = []  # kept alive: the kernel holds their ids
        ids = np.zeros(self.count, np.uint64)
        for j, sh in enumerate(keep):
            if "wp_mesh" in sh:  # a device mesh kept up to date by the caller (the physics surface)
                self._meshes.append(sh["wp_mesh"])
                ids[j] = sh["wp_mesh"].id
            elif SHAPE_KINDS[sh["type"]] == int(SHAPE_MESH):
                V = np.asarray(sh["vertices"], np.float32).reshape(-1, 3)
                F = np.asarray(sh["indices"], np.int32).reshape(-1)
                m = wp.Mesh(points=wp.array(V, dtype=wp.vec3, device=d), indices=wp.array(F, dtype=wp.int32, device=d))
                self._meshes.append(m)
                ids[j] = m.id
        scale = np.array([np.asarray(sh["scale"], np.float64) for sh in keep], np.float32).reshape(-1, 3)
        bad = [j for j, sh in enumerate(keep) if not np.all(np.isfinite(scale[j])) or
               np.any(scale[j][:1] <= 0) or (sh["type"] in ("box", "ellipsoid", "mesh", "convex_mesh")
                                             and np.any(scale[j] <= 0))]
        if bad:
            j = bad[0]
            raise ValueError(f"RigidShapes: shape {j} ({keep[j]['type']}) has a non-positive or non-finite size "
                             f"{scale[j].tolist()}")
        cols = [np.asarray(sh.get("color", color), np.float32) for sh in keep]
        self.kind = wp.array(np.array([SHAPE_KINDS[sh["type"]] for sh in keep], np.int32), dtype=wp.int32, device=d)
        self.size = wp.array(scale, dtype=wp.vec3, device=d)
        self.mesh = wp.array(ids, dtype=wp.uint64, device=d)
        self.color = wp.array(np.array(cols, np.float32).reshape(-1, 3), dtype=wp.vec3, device=d)
        self.pose = wp.zeros(self.count, dtype=wp.transform, device=d)
        if self.count:
            self.set_poses([sh["pose"] for sh in keep])

    def set_poses(self, poses) -> None:
        """World poses (K, 7) [m, quaternion x y z w] of the kept shapes, in their order."""
        P = np.asarray(poses, np.float32).reshape(-1, 7)
        if P.shape[0] != self.count:
            raise ValueError(f"RigidShapes.set_poses: {P.shape[0]} poses for {self.count} shapes")
        q = np.linalg.norm(P[:, 3:], axis=1)
        if not np.all(np.isfinite(P)) or np.any(q < 1e-6):
            raise ValueError("RigidShapes.set_poses: non-finite pose or zero quaternion")
        P[:, 3:] /= q[:, None]
        self.pose.assign(wp.array(P, dtype=wp.transform, device=self.device))


class Renderer:
    """Reusable buffers for rendering G Gaussians from C cameras of one image size. The arrays of
    a :class:`RenderResult` are this renderer's own: valid until its next ``render`` (copy them
    to keep them). Each stage's launch is recorded and replayed while its arguments are the same
    arrays (``_launch``), so the renderer holds the last call's input arrays until a call with
    other ones."""

    def __init__(self, device=None, compact_keys: bool = True, rasteriser: Rasteriser | str | None = None):
        """``compact_keys``: sort 32-bit (tile, depth rank) keys where the camera tiles and the
        (camera, Gaussian) ranks fit in 32 bits (one more, small sort of the depths first); off,
        or where they do not fit, 64-bit (tile, depth) keys. The two give the same picture up
        to the order of splats whose depths differ by less than a micrometre. ``rasteriser``: a
        :class:`~dynmesh_warp.choices.Rasteriser` (None: the device kind's default,
        ``choices.DEFAULT_RASTERISER``); both give the same images bit for bit."""
        self.device = wp.get_device(device)
        self.compact_keys = bool(compact_keys)
        self.rasteriser = (DEFAULT_RASTERISER[device_kind(self.device)] if rasteriser is None
                           else parse(Rasteriser, rasteriser, "Renderer rasteriser"))
        self._cap = 0
        self._keys = self._keys32 = self._values = None
        self._bkey, self._b = None, {}
        self._overflow = wp.zeros(1, dtype=wp.int32, device=self.device)
        self._no_spheres = (wp.zeros(0, dtype=wp.vec3, device=self.device), wp.zeros(0, dtype=float, device=self.device))
        self._no_solid = wp.zeros((1, 1, 1), dtype=wp.vec4, device=self.device)
        self._no_splats = (wp.zeros(0, dtype=wp.vec3, device=self.device), wp.zeros(0, dtype=wp.mat33, device=self.device),
                           wp.zeros((0, 1, 3), dtype=float, device=self.device), wp.zeros(0, dtype=float, device=self.device))
        self._cams = (None, None)  # (the cameras' values, their device arrays): reused while unchanged
        self._cmds = {}  # recorded launches per stage, replayed while their arguments are the same

    def _launch(self, stage: str, kernel, dim, inputs, outputs, block_dim: int | None = None, volatile=()):
        """``wp.launch`` (``wp.launch_tiled`` with ``block_dim``) through a recorded launch
        (``record_cmd``) kept per stage and replayed while its arguments are the same arrays and
        values, so a render with the same inputs as the last does not pack every argument again
        on the host (an eager render's cost is mostly its launches). ``volatile``: indices of
        scalar inputs that may change per call (set on the recorded launch, as is ``dim``). The
        record keeps its arrays alive, so an array's address cannot pass to another meanwhile."""
        args = (*inputs, *outputs)
        key = (kernel, block_dim, tuple(None if i in volatile else (a.ptr, a.shape) if isinstance(a, wp.array) else a
                                        for i, a in enumerate(args)))
        rec = self._cmds.get(stage)
        if rec is None or rec[0] != key:
            if block_dim is None:
                cmd = wp.launch(kernel, dim, inputs=inputs, outputs=outputs, device=self.device, record_cmd=True)
            else:
                cmd = wp.launch_tiled(kernel, dim=dim, inputs=inputs, outputs=outputs, block_dim=block_dim,
                                      device=self.device, record_cmd=True)
            if cmd is None:  # an empty launch (no Gaussians): nothing to record or run
                self._cmds.pop(stage, None)
                return
            rec = self._cmds[stage] = (key, cmd, args, dim)
        else:
            cmd = rec[1]
            for i in volatile:
                cmd.set_param_at_index(i, args[i])
            if dim != rec[3]:
                cmd.set_dim(dim)
                self._cmds[stage] = (key, cmd, args, dim)
        cmd.launch()

    def _camera_arrays(self, cameras):
        """Device (R, t, intrinsics) of the cameras, uploaded only when their values change (so a
        render with the same cameras as the previous one does no host-to-device copy)."""
        R = np.stack([np.asarray(c.R, np.float32) for c in cameras])
        t = np.stack([np.asarray(c.t, np.float32) for c in cameras])
        k = np.array([[c.fx, c.fy, c.cx, c.cy] for c in cameras], np.float32)
        key = R.tobytes() + t.tobytes() + k.tobytes()
        if self._cams[0] != key:
            _check_cameras(R, t, k, lambda c: f"render: camera {c}")  # changed since made? (checked once per value)
            d = self.device
            self._cams = (key, (wp.array(R, dtype=wp.mat33, device=d), wp.array(t, dtype=wp.vec3, device=d),
                                wp.array(k, dtype=wp.vec4, device=d)))
        return self._cams[1]

    def _buffers(self, C: int, G: int, W: int, H: int) -> dict:
        """Per-(C, G, W, H) buffers, allocated once and reused; the kernels write every entry they
        read (tile ranges are cleared per render)."""
        key = (C, G, W, H)
        if self._bkey != key:
            d = self.device
            tiles = C * ((W + TILE - 1) // TILE) * ((H + TILE - 1) // TILE)
            self._b = {
                "mean2d": wp.zeros((C, G), dtype=wp.vec2, device=d), "conic": wp.zeros((C, G), dtype=wp.vec3, device=d),
                "depth": wp.zeros((C, G), dtype=float, device=d), "radius": wp.zeros((C, G), dtype=wp.int32, device=d),
                # one entry more than the (camera, Gaussian) pairs, 0 in touched: the exclusive scan's
                # last offset is the entry count (one host read)
                "touched": wp.zeros(C * G + 1, dtype=wp.int32, device=d), "color": wp.zeros((C, G), dtype=wp.vec3, device=d),
                "offsets": wp.zeros(C * G + 1, dtype=wp.int32, device=d),
                "start": wp.zeros(tiles, dtype=wp.int32, device=d), "end": wp.zeros(tiles, dtype=wp.int32, device=d),
                "rgb": wp.zeros((C, H, W), dtype=wp.vec3, device=d), "alpha": wp.zeros((C, H, W), dtype=float, device=d),
                "depth_image": wp.zeros((C, H, W), dtype=float, device=d)}
            self._bkey = key
        return self._b

    def _grow(self, n: int):
        if n > self._cap:
            self._cap = max(n, int(self._cap * 1.5), 1024)
            self._keys = self._keys32 = None  # the kind a render needs is made by _sort_keys
            self._values = wp.zeros(2 * self._cap, dtype=wp.int32, device=self.device)
            self._s_xyod = wp.zeros(self._cap, dtype=wp.vec4, device=self.device)  # splats in key order
            self._s_conic = wp.zeros(self._cap, dtype=wp.vec3, device=self.device)
            self._s_color = wp.zeros(self._cap, dtype=wp.vec3, device=self.device)

    @property
    def capacity(self) -> int:
        """(Gaussian, tile) entries the sort buffers hold now (grown by renders; 0 before the
        first): a ``capacity=`` that the last exactly sized render fits in."""
        return self._cap

    def _last_buffers(self, asked: str) -> dict:
        if self._bkey is None:
            raise ValueError(f"{asked}: nothing rendered yet")
        return self._b

    def last_tile_counts(self) -> np.ndarray:
        """Splats listed per (camera, tile) in the last render, (C * tiles,) int (a host copy;
        for diagnostics: a tile's compositing cost follows its count)."""
        b = self._last_buffers("last_tile_counts")
        return b["end"].numpy() - b["start"].numpy()

    def last_entry_count(self) -> int:
        """(Gaussian, tile) entries of the last render (one host read; for diagnostics)."""
        return int(self._last_buffers("last_entry_count")["offsets"].numpy()[-1])

    def key_layout(self, C: int, G: int, tiles: int) -> tuple[bool, int]:
        """(compact, shift) of the sort keys of C cameras x G Gaussians over ``tiles`` (camera,
        tile) bins: compact 32-bit keys where the bin and the depth rank among C x G fit in 32
        bits (decided from the sizes alone: nothing read back), the bin above ``shift`` bits."""
        rank_bits = max(C * G - 1, 1).bit_length()
        compact = self.compact_keys and max(tiles - 1, 1).bit_length() + rank_bits <= 32
        return compact, (rank_bits if compact else 32)

    def _sort_keys(self, compact: bool):
        """The (key, value) arrays of this render's kind (2 x capacity entries, for the radix
        sort), allocated on first use at the current capacity."""
        if compact:
            if self._keys32 is None:
                self._keys32 = wp.zeros(2 * self._cap, dtype=wp.uint32, device=self.device)
            return self._keys32
        if self._keys is None:
            self._keys = wp.zeros(2 * self._cap, dtype=wp.int64, device=self.device)
        return self._keys

    def _depth_rank(self, C: int, G: int, depth, radius):
        """Each (camera, Gaussian)'s position in the depth order of all C x G (culled ones
        last): the compact keys' low bits (``emit_depth_keys``, a float radix sort,
        ``scatter_depth_rank``)."""
        b, d = self._b, self.device
        if "depth_keys" not in b:
            b["depth_keys"] = wp.zeros(2 * C * G, dtype=float, device=d)
            b["depth_order"] = wp.zeros(2 * C * G, dtype=wp.int32, device=d)
            b["depth_rank"] = wp.zeros(C * G, dtype=wp.int32, device=d)
        self._launch("emit_depth_keys", emit_depth_keys, (C, G), [depth, radius], [b["depth_keys"], b["depth_order"]])
        wp.utils.radix_sort_pairs(b["depth_keys"], b["depth_order"], C * G)
        self._launch("scatter_depth_rank", scatter_depth_rank, C * G, [b["depth_order"]], [b["depth_rank"]])
        return b["depth_rank"]

    def render(self, means, covariances, sh, opacities, cameras: list[Camera], sh_degree: int | None = None,
               spheres=None, sphere_color=(0.85, 0.25, 0.2), background=(1.0, 1.0, 1.0),
               near: float = 0.01, per_camera: bool = False, capacity: int | None = None,
               shapes: RigidShapes | None = None, shade: float | None = None) -> RenderResult:
        """Render for every camera (all of one size). means (G,) vec3 / (G, 3) [m]; covariances
        (G,) mat33 / (G, 3, 3) [m^2]; sh (G, K, 3) SH coefficients (K = 1, 4, 9 or 16; degree
        from K unless given); opacities (G,) in [0, 1]; spheres: (centres (S, 3), radii (S,))
        or None. ``per_camera``: each camera has its own scene (one env each): means and
        covariances (C * G,) camera-major, spheres (C * S,) with camera c's at c * S; sh and
        opacities shared (the same Gaussians, posed differently). ``capacity``: a fixed number of
        (Gaussian, tile) entries to sort: no value is read back to the host, so the call can be
        captured in a CUDA graph (``wp.ScopedCapture``) with array inputs; entries beyond it are
        dropped and counted in ``result.overflow`` (check it, and raise the capacity, when the
        picture must be complete). None: the exact count is read back (one small host read).
        ``shapes``: :class:`RigidShapes` seen by every camera (opaque, composited by depth).
        ``shade``: an ambient level in [0, 1]: each Gaussian's colour shaded by a head light of
        its camera from its flat axis (``project_gaussians``); None: unlit."""
        d = self.device
        if not cameras:
            raise ValueError("render: no cameras")
        for i, c in enumerate(cameras):
            _check_sizes(c.width, c.height, f"render: camera {i}")
        W, H = cameras[0].width, cameras[0].height
        if any((c.width, c.height) != (W, H) for c in cameras):
            raise ValueError("render: every camera of a batch must have the same image size")
        means = means if isinstance(means, wp.array) else wp.array(np.asarray(means, np.float32), dtype=wp.vec3, device=d)
        covs = covariances if isinstance(covariances, wp.array) else wp.array(
            np.asarray(covariances, np.float32), dtype=wp.mat33, device=d)
        sh = sh if isinstance(sh, wp.array) else wp.array(np.asarray(sh, np.float32), dtype=float, device=d)
        if sh.ndim != 3 or sh.shape[2] != 3 or sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"sh: expected (G, K, 3) with K in 1, 4, 9, 16, got {tuple(sh.shape)}")
        most = int(round(math.sqrt(sh.shape[1]))) - 1  # the degree the coefficients hold
        degree = most if sh_degree is None else int(sh_degree)
        if not 0 <= degree <= most:
            raise ValueError(f"sh_degree {sh_degree}: the sh array holds {sh.shape[1]} coefficient(s) a colour, enough "
                             f"for degrees 0..{most}")
        op = opacities if isinstance(opacities, wp.array) else wp.array(np.asarray(opacities, np.float32), dtype=float,
                                                                        device=d)
        C = len(cameras)
        G = sh.shape[0]
        scenes = C if per_camera else 1
        if means.shape[0] != scenes * G or covs.shape[0] != scenes * G or op.shape[0] != G:
            raise ValueError(f"render: means and covariances need {scenes} x G entries"
                             f"{' (per_camera: one scene per camera)' if per_camera else ''}, sh and opacities G "
                             f"(G = {G}); got means {means.shape[0]}, covariances {covs.shape[0]}, opacities {op.shape[0]}")
        Rs, ts, ks = self._camera_arrays(cameras)
        b = self._buffers(C, G, W, H)
        mean2d, conic, depth, radius, touched, color, offsets = (b[k] for k in (
            "mean2d", "conic", "depth", "radius", "touched", "color", "offsets"))
        self._launch("project_gaussians", project_gaussians, (C, G),
                     [means, covs, sh, degree, Rs, ts, ks, W, H, near, G if per_camera else 0,
                      -1.0 if shade is None else float(shade)], [mean2d, conic, depth, radius, touched, color])
        wp.utils.array_scan(touched, offsets, inclusive=False)
        start, end = b["start"], b["end"]
        start.zero_()
        end.zero_()
        tiles = start.shape[0]
        compact, shift = self.key_layout(C, G, tiles)
        self._overflow.zero_()
        # the depth rank needs no entry count: queued before the count is read, the GPU works on
        # it while the host waits (an eager render's one sync)
        rank = self._depth_rank(C, G, depth, radius) if compact else b.setdefault(
            "no_rank", wp.zeros(0, dtype=wp.int32, device=d))
        if capacity is not None:  # fixed capacity: nothing read back (capturable); the unused tail sorts last
            n = int(capacity)
            if n < 1:
                raise ValueError(f"render: capacity must be >= 1, got {capacity}")
            self._grow(n)
        else:
            n = int(offsets[C * G:].numpy()[0])  # one host read: the list size
            self._grow(max(n, 1))
        keys = self._sort_keys(compact)
        if capacity is not None:
            keys.fill_(EMPTY_KEY32 if compact else EMPTY_KEY)
        if n:
            emit_tile_keys, gather_sorted_splats = KEY_KERNELS[keys.dtype]
            self._launch("emit_tile_keys", emit_tile_keys, (C, G), [mean2d, depth, radius, offsets, rank, shift, W, H, n],
                         [keys, self._values, self._overflow], volatile=(8,))
            wp.utils.radix_sort_pairs(keys, self._values, n)
            self._launch("gather_sorted_splats", gather_sorted_splats, n,
                         [keys, self._values, shift, n, tiles // C, mean2d, conic, depth, color, op],
                         [start, end, self._s_xyod, self._s_conic, self._s_color], volatile=(3,))
        if spheres is None:
            sc, sr = self._no_spheres
        else:
            sc = spheres[0] if isinstance(spheres[0], wp.array) else wp.array(
                np.asarray(spheres[0], np.float32).reshape(-1, 3), dtype=wp.vec3, device=d)
            sr = spheres[1] if isinstance(spheres[1], wp.array) else wp.array(
                np.asarray(spheres[1], np.float32).reshape(-1), dtype=float, device=d)
        if per_camera and sc.shape[0] % C:
            raise ValueError(f"render: per_camera spheres must be C x S = {C} x S, got {sc.shape[0]}")
        s_per = sc.shape[0] // C if per_camera else 0
        rgb, alpha, zbuf = b["rgb"], b["alpha"], b["depth_image"]  # every pixel is written
        has_solid = shapes is not None and shapes.count > 0
        if has_solid:
            if shapes.device != d:
                raise ValueError(f"render: the shapes are on {shapes.device}, the renderer on {d}")
            solid = b.get("solid")
            if solid is None:
                solid = b["solid"] = wp.empty((C, H, W), dtype=wp.vec4, device=d)
            wp.launch(cast_rigid_shapes, (C, H, W), inputs=[shapes.kind, shapes.size, shapes.mesh, shapes.color,
                                                            shapes.pose, Rs, ts, ks], outputs=[solid], device=d)
        else:
            solid = self._no_solid
        raster_in = [self._s_xyod, self._s_conic, self._s_color, start, end, Rs, ts, ks, sc, sr, s_per,
                     wp.vec3(*sphere_color), solid, int(has_solid), wp.vec3(*background), W, H]
        if self.rasteriser == Rasteriser.SHARED:  # a block per tile, a thread per pixel
            self._launch("rasterize", RASTERIZE_SHARED[device_kind(d)], (tiles,), raster_in,
                         [rgb, alpha, zbuf], block_dim=TILE * TILE)
        else:  # a thread per pixel of each tile
            self._launch("rasterize", rasterize_gaussians, (C, (tiles // C) * TILE * TILE), raster_in,
                         [rgb, alpha, zbuf])
        return RenderResult(rgb, alpha, zbuf, self._overflow)


def render_world(sim, gaussians, cameras: list[Camera], renderer: Renderer | None = None, shade: bool = True,
                 splats: bool = True, mesh: bool = False, mesh_color=(0.78, 0.74, 0.66), **kw) -> RenderResult:
    """The simulation's bound Gaussians (``gaussians.Gaussians``, updated to its current
    surface), its spheres and its other rigid shapes (``sim.rigid_shapes()``: a Newton world's
    boxes, capsules, meshes ...), from ``cameras``. ``shade``: each Gaussian's colour times
    a + (1 - a) |n . l| (a = ``gaussians.SHADE_AMBIENT``), n its flat axis (the surface normal
    for Gaussians bound to faces), l a head light of each camera tilted down, so the shape reads
    (the binding's colours are unlit; computed in ``project_gaussians``, nothing on the host per
    frame). ``mesh``: the physics mesh itself drawn too, opaque and shaded like the bodies (for
    debugging: where the splats and the collision surface differ); ``splats=False`` leaves the
    Gaussians out (``gaussians`` may then be None)."""
    renderer = renderer or Renderer(sim.device)
    rigid = list(sim.rigid_shapes())
    if mesh:
        rigid.append({"type": "mesh", "scale": [1.0, 1.0, 1.0], "pose": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                      "wp_mesh": _surface_mesh(renderer, sim), "color": mesh_color})
    shapes = None
    if rigid:  # a Newton world's bodies, the physics mesh: geometry uploaded once, poses every call
        key = (id(sim), len(rigid), id(rigid[-1].get("wp_mesh")))
        if getattr(renderer, "_shapes_key", None) != key:
            renderer._shapes = RigidShapes(rigid, sim.device)
            renderer._shapes_key = key
        shapes = renderer._shapes
        shapes.set_poses([rigid[i]["pose"] for i in shapes.kept])
    pos, rad = sim.sphere_positions(), sim.sphere_radii()
    spheres = (pos, rad) if len(rad) else None
    if not splats:
        return renderer.render(*renderer._no_splats, cameras, spheres=spheres, shapes=shapes, **kw)
    sh, op = _binding_colours(renderer, gaussians.binding, sim.device)
    return renderer.render(gaussians.state.centers, gaussians.state.covariances, sh, op, cameras,
                           spheres=spheres, shapes=shapes, shade=SHADE_AMBIENT if shade else None, **kw)


def _binding_colours(renderer: Renderer, binding, device):
    """The binding's colours as SH DC coefficients and its opacities on the device, uploaded once
    per binding and kept on the renderer."""
    if getattr(renderer, "_colour_binding", None) is not binding:
        renderer._colours = (wp.array(rgb_to_sh(binding.rgb), dtype=float, device=device),
                             wp.array(binding.opacity, dtype=float, device=device))
        renderer._colour_binding = binding
    return renderer._colours


def _surface_mesh(renderer: Renderer, sim) -> wp.Mesh:
    """A ``wp.Mesh`` of the simulation's current surface, kept on the renderer: its points
    copied in and the tree refit on each call; rebuilt when the index buffer changes (varying
    topology)."""
    pts, idx = sim.surface_points(), sim.surface_indices()
    m, key = getattr(renderer, "_surface", (None, None))
    if m is None or key != (id(sim), id(idx), pts.shape[0], idx.shape[0]):
        m = wp.Mesh(points=wp.clone(pts), indices=wp.clone(idx))
        renderer._surface = (m, (id(sim), id(idx), pts.shape[0], idx.shape[0]))
    else:
        wp.copy(m.points, pts)
        m.refit()
    return m


def render_envs(batch, gaussians, cameras, renderer: Renderer | None = None, shade: bool = True,
                **kw) -> RenderResult:
    """Camera observations of a batch: one image per env, env e seen by ``cameras[e]`` (a list of
    E cameras of one size, or one camera for every env) with the Gaussians bound to the shared
    surface posed at **env e's own time** (its clock, rate and playback mode:
    ``kernels.gaussians.update_env_gaussians``) and env e's own spheres only. Returns the
    renderer's device arrays, rgb (E, H, W) vec3 etc. (``wp.to_torch`` for zero-copy torch).

    ``batch``: a ``batch.BatchedWorld``; ``gaussians``: the ``gaussians.Gaussians`` bound to its
    surface (their binding is used, not their state). ``shade``: the binding's colours shaded by
    each camera's head light from each Gaussian's flat axis at its env's pose (as
    :func:`render_world`); False: unlit. ``capacity=`` (passed
    on to :meth:`Renderer.render`): no host read, for a CUDA graph; with the same cameras and
    Gaussians as the call before, nothing is uploaded either."""
    from .kernels.gaussians import update_env_gaussians

    d = batch.device
    renderer = renderer or Renderer(d)
    E, G = batch.num_envs, gaussians.count
    cams = list(cameras) if isinstance(cameras, (list, tuple)) else [cameras] * E
    if len(cams) != E:
        raise ValueError(f"render_envs: {len(cams)} cameras for {E} envs (give one per env, or one for all)")
    surf, b, st = batch.model.surface, gaussians.binding, batch.state
    if b.num_faces != surf.num_faces:
        raise ValueError(f"render_envs: the Gaussians were bound to {b.num_faces} faces, the surface has {surf.num_faces}")
    key = (E, G)
    if getattr(renderer, "_env_key", None) != key:
        renderer._env_means = wp.zeros(E * G, dtype=wp.vec3, device=d)
        renderer._env_covs = wp.zeros(E * G, dtype=wp.mat33, device=d)
        renderer._env_key = key
    means, covs = renderer._env_means, renderer._env_covs
    if G:
        wp.launch(update_env_gaussians, (E, G),
                  inputs=[surf.frames, surf.indices, surf.fps, int(surf.interpolate), st.env_time, st.env_playback,
                          b.face, b.bary, b.offset, b.local_rotation, b.local_scale],
                  outputs=[means, covs], device=d)
    sh, op = _binding_colours(renderer, b, d)  # uploaded once per binding
    spheres = (st.sphere_pos, batch.model.spheres.radius) if batch.model.spheres_per_env else None
    return renderer.render(means, covs, sh, op, cams, spheres=spheres, per_camera=True,
                           shade=SHADE_AMBIENT if shade else None, **kw)


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _write_png(path: Path, img: np.ndarray) -> None:
    from .outputs import atomic_path

    from PIL import Image

    with atomic_path(path, suffix=".png") as tmp:
        Image.fromarray(img).save(tmp, format="PNG")


def frame_steps(frames: int, fps: float, dt: float) -> np.ndarray:
    """The world's steps before each of ``frames`` frames shown ``fps`` times a simulated second
    (int64 (frames,), the first 0): frame k shows time k / fps to within dt / 2. Each frame took
    round(1 / (fps dt)) steps before, so --fps 100 at dt = 1/240 showed frames 1/120 s apart and
    --fps 25 ran 4 % fast (a new user's)."""
    return np.diff(np.round(np.arange(-1, frames) / (fps * dt)).clip(0)).astype(np.int64)


#: the shortest GIF frame delay browsers play as written [1/100 s]: a 1/100 s delay is played
#: as 1/10 s (so a GIF plays at most 50 frames a second)
GIF_MIN_DELAY_CS = 2


def gif_timing(frames: int, fps: float) -> tuple[int, list]:
    """(every how many frames a GIF keeps, each kept frame's delay in ms): GIF delays are whole
    1/100 s, so each is rounded where the frames' times fall (24 fps: 40, 40, 50, 40, 40, 50 ... ms,
    the rate kept on average; a single 40 ms delay played 24 fps at 25), and above 50 fps frames
    are left out (every n-th kept) rather than written with 1/100 s delays that browsers slow to
    1/10 s."""
    every = max(1, int(np.ceil(fps * GIF_MIN_DELAY_CS / 100.0 - 1e-9)))
    kept = len(range(0, frames, every))
    ends = np.round(np.arange(kept + 1) * every * 100.0 / fps).astype(np.int64)
    return every, (10 * np.diff(ends)).tolist()


def _write_video(path: Path, frames: list, fps: float) -> None:
    """Frames (H, W, 3) uint8 as a .gif (imageio + Pillow; :func:`gif_timing`) or .mp4
    (imageio-ffmpeg), atomically."""
    import imageio.v2 as imageio

    from .outputs import atomic_path

    with atomic_path(path, suffix=path.suffix) as tmp:
        if path.suffix.lower() == ".gif":
            every, delays = gif_timing(len(frames), fps)
            if every > 1:
                print(f"note: {path.name}: a GIF plays at most {100 // GIF_MIN_DELAY_CS} frames a second (its delays are "
                      f"whole 1/100 s, and browsers slow 1/100 s to 1/10 s): every {every}th frame written, "
                      f"{fps / every:.4g} a second; an .mp4 keeps them all", file=sys.stderr)
            imageio.mimsave(tmp, frames[::every], format="GIF", duration=delays, loop=0)
        else:
            imageio.mimsave(tmp, frames, fps=fps, format="FFMPEG")


#: the largest image side --width / --height take [pixels] (a new user's 100000 x 100000 ended in
#: a RuntimeError traceback after the scene had loaded)
MAX_IMAGE_SIDE = 16384


def main(argv=None) -> int:
    """The render CLI: its own warnings as one ``warning:`` line each, and Ctrl-C / SIGTERM
    (between frames: the frames done are written, marked, beside an earlier --out), as the other
    CLIs (it had no stop handling: a traceback, and an --overwrite folder of mixed frames)."""
    from .cli import interruptible_main

    return interruptible_main(_main)(argv)


def _main(argv=None) -> int:
    from .cli import Interrupted, Parser, checking_stops, quiet_warp, stop_reason

    p = Parser(prog="python -m dynmesh_warp.render", description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", help="scene YAML (default: the built-in default scene); or a mesh sequence "
                   "(.npz, .glb, a folder of frames, ...), played with spheres dropped on it as `run` plays it")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE", dest="overrides",
                   help="override a scene field (YAML value), as for run, e.g. --set surface.scale=0.001; repeatable")
    p.add_argument("--out", help="folder for frame_NNNN.png (written atomically, one per frame)")
    p.add_argument("--figure", help="a PNG strip of --moments moments side by side")
    p.add_argument("--video", help="a video of the frames: .gif (imageio with Pillow) or .mp4 (needs imageio-ffmpeg); "
                                   "written atomically")
    p.add_argument("--frames", type=int, default=48, help="frames rendered (--out, --video); also the span of time the "
                   "--figure moments are taken from")
    p.add_argument("--moments", type=int, default=4)
    p.add_argument("--fps", type=float, default=24.0, help="frames per simulated second")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--device", default=None)
    p.add_argument("--rasteriser", choices=values(Rasteriser), default=None,
                   help=f"the splat rasteriser (default: by device, {DEFAULT_RASTERISER['cpu']} on the CPU, "
                        f"{DEFAULT_RASTERISER['cuda']} on CUDA)")
    p.add_argument("--mesh", action="store_true", help="draw the physics mesh too (opaque, shaded): for debugging")
    p.add_argument("--no-splats", action="store_true", help="leave the Gaussians out (with --mesh: the mesh alone)")
    p.add_argument("--unlit", action="store_true",
                   help="the Gaussians' own colours, not shaded by the head light (a 3DGS capture's colours already "
                        "hold its lighting; generated splats are flat grey and read better shaded, the default)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --figure / --video file, or frames in a non-empty --out folder")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    quiet_warp(a.device)
    if not a.out and not a.figure and not a.video:
        p.error("give --out FOLDER, --video RUN.gif|RUN.mp4 and/or --figure STRIP.png")
    if a.video:
        ext = Path(a.video).suffix.lower()
        if ext not in (".gif", ".mp4"):
            p.error(f"--video {a.video}: give a .gif or .mp4 path")
        if ext == ".mp4":
            import importlib.util

            if importlib.util.find_spec("imageio_ffmpeg") is None:
                p.error(f"--video {a.video}: .mp4 needs the imageio-ffmpeg package (pip install imageio-ffmpeg); "
                        "or write a .gif, or PNG frames with --out")
    for name, ok, need in (("frames", a.frames >= 1, "at least 1"), ("moments", a.moments >= 1, "at least 1"),
                           ("width", 16 <= a.width <= MAX_IMAGE_SIDE, f"16..{MAX_IMAGE_SIDE} pixels"),
                           ("height", 16 <= a.height <= MAX_IMAGE_SIDE, f"16..{MAX_IMAGE_SIDE} pixels"),
                           ("fps", 0 < a.fps < float("inf"), "a positive, finite frame rate")):
        if not ok:  # one line naming the option and its value (it listed all five for any of them)
            p.error(f"--{name} must be {need}, got {getattr(a, name)}")
    from .config import SceneError, load_scene_config, say_sequence_scene, scene_source
    from .gaussians import can_bind, gaussians_for_surface
    from .scene import build_world

    from .outputs import OutputFolder, OutputKind, check_output, entries

    try:
        cfg = load_scene_config(**scene_source(a.scene), overrides=a.overrides)
        say_sequence_scene(a.scene, cfg)
        # the outputs, before any work: never one of the scene's inputs, nothing replaced unasked
        ins = cfg.inputs()
        if a.figure:
            check_output(a.figure, kind="file", what="--figure", inputs=ins, overwrite=a.overwrite, suffixes={".png"},
                         holds=OutputKind.RENDER)
        if a.video:
            check_output(a.video, kind="file", what="--video", inputs=ins, overwrite=a.overwrite,
                         holds=OutputKind.RENDER)
        if a.out:
            check_output(a.out, kind="folder", what="--out", inputs=ins, overwrite=a.overwrite,
                         writes=("frame_*.png",), holds=OutputKind.RENDER)
        out_checked = entries(a.out) if a.out else None  # what appears there meanwhile is not replaced
        if cfg.newton is not None:  # a newton: scene renders the Newton world, its bodies drawn in
            from .newton_adapter import build_newton_world

            world = build_newton_world(cfg, device=a.device)
        else:
            world = build_world(cfg, device=a.device)
            world.render_state = True
        seq = world.surface.sequence
        gs = None
        if not a.no_splats:
            if not can_bind(seq):
                raise ValueError(f"surface {cfg.surface.source}: its topology changes from frame to frame, and "
                                 "Gaussians are bound to one mesh (or to a piecewise-fixed one, as convert writes): "
                                 "convert it first (python -m dynmesh_warp.convert SOURCE OUT.npz) and render OUT.npz, "
                                 "or draw the mesh alone with --mesh --no-splats")
            gs = gaussians_for_surface(seq, cfg, world.device)  # updated once per frame below
    except (SceneError, ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    lo, hi = (np.asarray(b, np.float64) for b in seq.bounds())
    centre, diag = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    renderer = Renderer(world.device, rasteriser=a.rasteriser)
    steps = frame_steps(max(a.frames, a.moments) + 1, a.fps, world.dt)
    if a.fps * world.dt > 1.0:
        print(f"note: --fps {a.fps:g} is above the physics rate (1 / dt = {1.0 / world.dt:.4g} steps a second): "
              "some frames repeat the one before", file=sys.stderr)
    total = a.frames if (a.out or a.video) else 0
    video = []
    moments = sorted(set(np.linspace(0, max(a.frames, a.moments) - 1, a.moments).astype(int).tolist()))
    last = max(total - 1, moments[-1] if a.figure else 0)
    strip = []
    try:
        from tqdm import tqdm

        it = tqdm(range(last + 1), unit="frame", disable=a.no_progress, file=sys.stderr)
    except ImportError:  # pragma: no cover
        it = range(last + 1)
    # the frames go into a temporary folder renamed into place at the end (they went one by one
    # into --out, so a stopped --overwrite left old and new frames mixed: a new user's)
    folder = OutputFolder(a.out, overwrite=a.overwrite, checked=out_checked, holds=OutputKind.RENDER) if a.out else None
    done, reason = 0, None
    with checking_stops(), (folder if folder is not None else contextlib.nullcontext()) as tmp:
        for f in it:
            reason = stop_reason()
            if reason:
                break
            if not a.no_splats:
                gs.update(world.surface_points(), world.surface_indices())
            cam = orbit_cameras(centre, 1.05 * diag, 1, 20.0, a.width, a.height,
                                start_deg=30.0 + 90.0 * f / max(last, 1))
            res = render_world(world, gs, cam, renderer, shade=not a.unlit, splats=not a.no_splats, mesh=a.mesh)
            img = _to_uint8(res.rgb.numpy()[0])
            if a.out and f < total:
                _write_png(tmp / f"frame_{f:04d}.png", img)
            if a.video and f < total:
                video.append(img)
            if a.figure and f in moments:
                strip.append(img)
            done = f + 1
            for _ in range(int(steps[f + 1])):  # to the next frame's time, (f + 1) / fps
                world.step()
        if folder is not None:
            folder.interrupted = bool(reason)  # a stopped render never replaces an earlier --out
            folder.status = {"complete": not reason, "frames": min(done, total), "frames_asked": total,
                             "interrupted_by": reason}
            if reason and not done:
                raise Interrupted(getattr(signal, reason))
    shown = folder.written if folder is not None else None
    if reason:
        print(f"interrupted by {reason} after {done} of {last + 1} frames: "
              + (f"wrote {shown} with frames 0..{min(done, total) - 1} (manifest status: complete false)"
                 if a.out else "nothing written")
              + (f"; {a.out}, which was there before, is unchanged" if a.out and shown != folder.path else "")
              + ("; the --figure and --video need every frame: not written" if a.figure or a.video else ""),
              file=sys.stderr)
        return 128 + int(getattr(signal, reason))
    if a.figure:
        _write_png(Path(a.figure), np.concatenate(strip, axis=1))
    if a.video:
        _write_video(Path(a.video), video, a.fps)
    if folder is not None and shown != folder.path:
        print(f"warning: {a.out} gained files during the render (another run's output, or files of the names it "
              f"writes): kept as it is; the frames are in {shown}", file=sys.stderr)
    print(f"rendered {last + 1} frames of {cfg.name} ({a.width}x{a.height})"
          + (f"; frames in {shown}" if a.out else "") + (f"; figure {a.figure}" if a.figure else "")
          + (f"; video {a.video}" if a.video else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
