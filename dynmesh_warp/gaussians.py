"""3D Gaussians bound to the faces of the physics mesh: binding, per-step update, generation.

:class:`GaussianBinding` holds the static data (face, barycentrics, normal offset, local
rotation and scale, colour, opacity), :class:`GaussianState` the per-step world outputs, both
as ``wp.array``s on one device (like the World's Model/State). :class:`Gaussians` owns one of
each; :meth:`Gaussians.attach` registers the ``update_gaussians`` kernel as a post-step hook of
a :class:`~dynmesh_warp.world.World`, so it runs inside the same CUDA graph as the physics step.

See ``kernels/gaussians.py`` and ``docs/rendering.md`` for the binding math.
"""

from __future__ import annotations

import warnings

import numpy as np
import warp as wp

from .choices import DEFAULT_COLOR_SOURCE, ColorSource
from .geometry import face_areas, flat_faces
from .kernels.gaussians import bind_gaussians_to_faces, pack_splat_covariances, update_gaussians
from .kernels.geometry import project_points_to_mesh
from .sequence import validate_mesh
from .splat_io import SplatCloud, rotate_sh, sh_dc_to_rgb

__all__ = [
    "GaussianBinding",
    "GaussianState",
    "Gaussians",
    "bind_splats",
    "rebind",
    "SegmentedGaussians",
    "generate_gaussians",
    "gaussians_for_surface",
    "can_bind",
    "gaussians_for_world",
    "quat_wxyz_to_xyzw",
    "quat_xyzw_to_wxyz",
    "DEFAULT_COLOR",
    "shaded_rgb",
]

DEFAULT_COLOR = (0.75, 0.72, 0.68)


def quat_wxyz_to_xyzw(q):
    q = np.asarray(q)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def quat_xyzw_to_wxyz(q):
    q = np.asarray(q)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def quat_xyzw_matrices(q) -> np.ndarray:
    """(G, 3, 3) rotation matrices of quaternions (G, 4) (x, y, z, w), normalised first."""
    q = np.asarray(q, np.float64).reshape(-1, 4)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-300)
    x, y, z, w = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                     2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                     2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1).reshape(-1, 3, 3)


class GaussianBinding:
    """Static per-Gaussian data (G Gaussians on a mesh of M faces).

    Attributes (wp.array on ``device``):
        face (G,) int32 face index in [0, M); bary (G,) vec3 weights of the face's vertices
        (i0, i1, i2); offset (G,) float along the face normal [face scales = sqrt(face area)];
        local_rotation (G,) quat (x, y, z, w) in the face frame; local_scale (G,) vec3 std devs
        [face scales].
    Host attributes: rgb (G, 3) float64, the linear colour 0.5 + C0 f_dc, not clipped (above 1
        for a bright splat, below 0 for a dark one: the renderer clamps it at 0 as 3DGS does, the
        images and the viewer's u8 colours are clipped to [0, 1]; kept unclipped so that an export
        writes f_dc back); opacity (G,) float32 in [0, 1]; opacity_logit (G,) float32, the stored
        logits of splats read from a file (exported as they are), or None; f_rest (G, K) float32
        higher SH (exported turned with each Gaussian, not rendered); f_rest_rotation (G, 4) quat
        (x, y, z, w) or None: the world rotation each Gaussian had when its f_rest were written (the
        splat file's: an export turns f_rest by the rotation since, ``splat_io.rotate_sh``; None:
        exported as they are).
    """

    def __init__(self, face, bary, offset, local_rotation_xyzw, local_scale, rgb, opacity, num_faces: int,
                 f_rest=None, device=None, opacity_logit=None, f_rest_rotation_xyzw=None):
        self.device = wp.get_device(device)
        face = np.asarray(face, np.int32).reshape(-1)
        G = face.size
        if G and (face.min() < 0 or face.max() >= num_faces):
            raise ValueError(f"gaussian face index out of range [0, {num_faces})")
        self.count = G
        self.num_faces = int(num_faces)
        self.face = wp.array(face, dtype=wp.int32, device=self.device)
        self.bary = wp.array(np.asarray(bary, np.float32).reshape(G, 3), dtype=wp.vec3, device=self.device)
        self.offset = wp.array(np.asarray(offset, np.float32).reshape(G), dtype=float, device=self.device)
        self.local_rotation = wp.array(np.asarray(local_rotation_xyzw, np.float32).reshape(G, 4), dtype=wp.quat,
                                       device=self.device)
        self.local_scale = wp.array(np.asarray(local_scale, np.float32).reshape(G, 3), dtype=wp.vec3,
                                    device=self.device)
        self.rgb = np.asarray(rgb, np.float64).reshape(G, 3).copy()
        self.opacity = np.clip(np.asarray(opacity, np.float32).reshape(G), 0.0, 1.0)
        self.opacity_logit = None if opacity_logit is None else np.asarray(opacity_logit, np.float32).reshape(G)
        self.f_rest = np.zeros((G, 0), np.float32) if f_rest is None else np.asarray(f_rest, np.float32)
        self.f_rest_rotation = (None if f_rest_rotation_xyzw is None or self.f_rest.shape[1] == 0
                                else np.asarray(f_rest_rotation_xyzw, np.float64).reshape(G, 4).copy())


class GaussianState:
    """Per-step outputs: centers (G,) vec3 [m]; rotations (G,) quat (x, y, z, w), world;
    scales (G,) vec3 std devs [m]; covariances (G,) mat33 R diag(s^2) R^T [m^2]."""

    def __init__(self, count: int, device=None):
        self.centers = wp.zeros(count, dtype=wp.vec3, device=device)
        self.rotations = wp.zeros(count, dtype=wp.quat, device=device)
        self.scales = wp.zeros(count, dtype=wp.vec3, device=device)
        self.covariances = wp.zeros(count, dtype=wp.mat33, device=device)


class Gaussians:
    """Gaussians bound to a mesh: a :class:`GaussianBinding` + a :class:`GaussianState`."""

    def __init__(self, binding: GaussianBinding):
        self.binding = binding
        self.device = binding.device
        self.count = binding.count
        self.state = GaussianState(binding.count, self.device)
        self._cov16 = wp.zeros((binding.count, 6), dtype=wp.float16, device=self.device)

    def update(self, points: wp.array, indices: wp.array):
        """Recompute the world Gaussians from vertices ``points`` (N,) vec3 and ``indices`` (3M,)."""
        if indices.shape[0] // 3 != self.binding.num_faces:
            raise ValueError(f"mesh has {indices.shape[0] // 3} faces, the Gaussians were bound to "
                             f"{self.binding.num_faces}")
        if self.count == 0:
            return
        b, s = self.binding, self.state
        wp.launch(update_gaussians, dim=self.count,
                  inputs=[points, indices, b.face, b.bary, b.offset, b.local_rotation, b.local_scale],
                  outputs=[s.centers, s.rotations, s.scales, s.covariances], device=self.device)

    def attach(self, world) -> "Gaussians":
        """Update after every step of ``world`` (a post-step hook, captured in its CUDA graph), and
        where its surface moves between steps (``reset``, ``set_time``, a restored checkpoint)."""
        try:
            world.model.surface.faces()  # Gaussians are bound to faces every frame shares
        except ValueError:
            raise ValueError("Gaussians need a fixed-topology surface (convert the sequence first; a piecewise-fixed "
                             "one, with template segments, with one template: --option max_segments=1)") from None
        if world.device != self.device:
            raise ValueError(f"Gaussians are on {self.device}, the world on {world.device}")
        self.update(world.state.points, world.current_indices())
        b, s = self.binding, self.state

        def hook(w):
            w._launch(update_gaussians, self.count,
                      [w.state.points, w.current_indices(), b.face, b.bary, b.offset, b.local_rotation,
                       b.local_scale], [s.centers, s.rotations, s.scales, s.covariances])

        world.add_post_step_hook(hook, follows_surface=True)
        return self

    def splat_covariances_f16(self, min_scale: float, min_ratio: float = 0.05) -> np.ndarray:
        """(G, 6) float16 upper-triangle covariances for the viewer, std devs clamped to
        >= max(min_scale [m], min_ratio * largest std dev) (see docs/rendering.md)."""
        if self.count:
            wp.launch(pack_splat_covariances, dim=self.count,
                      inputs=[self.state.rotations, self.state.scales, float(min_scale), float(min_ratio)],
                      outputs=[self._cov16], device=self.device)
        return self._cov16.numpy().copy()

    def numpy(self) -> dict:
        s = self.state
        # copies: on the CPU ``wp.array.numpy()`` is a view that the next update overwrites
        return {"centers": s.centers.numpy().copy(), "rotations_xyzw": s.rotations.numpy().copy(),
                "scales": s.scales.numpy().copy(), "covariances": s.covariances.numpy().copy()}

    def current_f_rest(self) -> np.ndarray:
        """The binding's ``f_rest`` turned with each Gaussian from the rotation it had when they were
        written (``binding.f_rest_rotation``) to its current one: (G, K) float32."""
        b = self.binding
        if b.f_rest_rotation is None or b.f_rest.shape[1] == 0:
            return b.f_rest
        R = quat_xyzw_matrices(self.state.rotations.numpy()) @ quat_xyzw_matrices(b.f_rest_rotation).transpose(0, 2, 1)
        return rotate_sh(b.f_rest, R)

    def to_splat_cloud(self) -> SplatCloud:
        """The current world Gaussians as a 3DGS cloud (for ``write_splat_ply``); ``f_rest`` turned
        with each Gaussian (:meth:`current_f_rest`)."""
        d = self.numpy()
        return SplatCloud.from_activated(d["centers"], np.maximum(d["scales"], 1e-12),
                                         quat_xyzw_to_wxyz(d["rotations_xyzw"]), self.binding.rgb,
                                         self.binding.opacity, f_rest=self.current_f_rest(),
                                         opacity_logits=self.binding.opacity_logit)


def _check_splats(cloud: SplatCloud) -> None:
    """Refuse splats that cannot be rendered: NaN/inf in a required property (centre, colour,
    opacity, log-scale, rotation) or a zero rotation quaternion; warn on an empty cloud."""
    from .splat_io import _REQUIRED, SplatPlyError

    if len(cloud) == 0:
        warnings.warn(f"{cloud.source}: the splat file holds no Gaussians", stacklevel=3)
        return
    for name in _REQUIRED:
        with np.errstate(over="ignore", invalid="ignore"):  # the kernels get float32
            col = np.asarray(cloud.data[name], np.float64).astype(np.float32)
        bad = ~np.isfinite(col)
        if bad.any():
            what = "NaN/inf" if not np.isfinite(np.asarray(cloud.data[name], np.float64)).all() else \
                "beyond float32's range (|x| > 3.4e38)"
            raise SplatPlyError(f"{cloud.source}: property {name!r} is {what} in {int(bad.sum())} splats "
                                f"(first: splat {int(np.flatnonzero(bad)[0])})")
    with np.errstate(over="ignore"):
        # the covariance holds the squares: a log-scale of 45 (std dev 3.5e19 m) passed and gave inf
        big = ~np.isfinite((cloud.scales().astype(np.float64) ** 2).astype(np.float32)).all(axis=1)
    if big.any():
        raise SplatPlyError(f"{cloud.source}: {int(big.sum())} splats have a log-scale (scale_*) whose exp "
                            f"squared (the covariance) overflows float32 (first: splat {int(np.flatnonzero(big)[0])})")
    q = np.linalg.norm(np.asarray(cloud.rotations_raw, np.float64), axis=1)
    if (q == 0).any():
        raise SplatPlyError(f"{cloud.source}: {int((q == 0).sum())} splats have a zero rotation quaternion "
                            f"(first: splat {int(np.flatnonzero(q == 0)[0])})")


#: splats whose median distance to the mesh they are bound to exceeds this fraction of the mesh's
#: bounding-box diagonal are warned of (another frame or units?)
SPLAT_FAR = 0.1

def bind_splats(cloud: SplatCloud, V, F, device=None, max_dist: float = 1.0e30) -> Gaussians:
    """Bind a world-space splat cloud to the mesh (V (N,3) rest vertices [m], F (M,3)).

    Each Gaussian goes to its nearest face (``project_points_to_mesh`` on a ``wp.Mesh``); its
    world rotation and scale are expressed in that face's frame (``bind_gaussians_to_faces``),
    so the binding reproduces the cloud at the rest pose.
    """
    V, F = validate_mesh(V, F, source="bind_splats mesh")
    device = wp.get_device(device)
    _check_splats(cloud)
    rotations = quat_wxyz_to_xyzw(cloud.rotations_wxyz())
    bound = _bind_world(cloud.positions, rotations, cloud.scales(), V, F, device, cloud.source, max_dist)
    binding = GaussianBinding(*bound, sh_dc_to_rgb(cloud.f_dc, clamp=False), cloud.opacities(), num_faces=F.shape[0],
                              f_rest=cloud.f_rest, device=device, opacity_logit=cloud.opacity_logits,
                              f_rest_rotation_xyzw=rotations)
    return Gaussians(binding)


def _bind_world(centers, rotations_xyzw, scales, V, F, device, source: str, max_dist: float = 1.0e30) -> tuple:
    """World Gaussians (centres (G, 3) [m], rotations (G, 4) quat x, y, z, w, std devs (G, 3) [m])
    bound to the mesh (V, F): each to its nearest face, in that face's frame. Returns the
    binding's (face, bary, offset, local rotation, local scale) as NumPy arrays."""
    G = len(centers)
    pts = wp.array(np.asarray(V, np.float32), dtype=wp.vec3, device=device)
    idx = wp.array(np.asarray(F, np.int32).reshape(-1), dtype=wp.int32, device=device)
    c = wp.array(np.asarray(centers, np.float32), dtype=wp.vec3, device=device)
    face = wp.zeros(G, dtype=wp.int32, device=device)
    bary = wp.zeros(G, dtype=wp.vec3, device=device)
    if G:
        # only faces with an area at the rest pose: a splat bound to one without (its corners at one
        # point, a reconstruction's face that opens later) kept no size (std dev 0: invisible) and
        # moved onto a corner (a new user's)
        Fn = np.asarray(F, np.int64).reshape(-1, 3)
        live = np.flatnonzero(~flat_faces(V, Fn))
        if not len(live):
            raise ValueError(f"{source}: every face of the mesh has zero area at the rest pose: nothing to bind to")
        sub = idx if len(live) == len(Fn) else wp.array(Fn[live].astype(np.int32).reshape(-1), dtype=wp.int32,
                                                         device=device)
        mesh = wp.Mesh(points=pts, indices=sub)
        closest = wp.zeros(G, dtype=wp.vec3, device=device)
        dist = wp.zeros(G, dtype=float, device=device)
        wp.launch(project_points_to_mesh, dim=G, inputs=[mesh.id, c, float(max_dist)],
                  outputs=[closest, face, bary, dist], device=device)
        f = face.numpy()
        if (f < 0).any():
            raise ValueError(f"{source}: {(f < 0).sum()} splats are farther than {max_dist} from the mesh")
        if len(live) < len(Fn):  # back to the mesh's own face numbers
            face = wp.array(live[f].astype(np.int32), dtype=wp.int32, device=device)
        d = dist.numpy()
        Vn = np.asarray(V, np.float64)
        diag = float(np.linalg.norm(Vn.max(axis=0) - Vn.min(axis=0))) if len(Vn) else 0.0
        if diag > 0 and float(np.median(d)) > SPLAT_FAR * diag:
            # a new user's y-up splats, the mesh turned z-up by surface.up_axis and they not:
            # bound 2 m off a 2 m mesh, rendered floating, unsaid
            warnings.warn(f"{source}: the splats lie far from the mesh they are bound to (median {np.median(d):.4g}, "
                          f"max {d.max():.4g}; the mesh is {diag:.4g} across): are they in another frame? They "
                          "must be in the scene frame: surface.up_axis, scale and translate turn the mesh, not the "
                          "splats", UserWarning, stacklevel=4)
    rot = wp.array(np.asarray(rotations_xyzw, np.float32), dtype=wp.quat, device=device)
    scl = wp.array(np.asarray(scales, np.float32), dtype=wp.vec3, device=device)
    offset = wp.zeros(G, dtype=float, device=device)
    lrot = wp.zeros(G, dtype=wp.quat, device=device)
    lscl = wp.zeros(G, dtype=wp.vec3, device=device)
    if G:
        wp.launch(bind_gaussians_to_faces, dim=G, inputs=[pts, idx, face, c, rot, scl],
                  outputs=[bary, offset, lrot, lscl], device=device)
    return face.numpy(), bary.numpy(), offset.numpy(), lrot.numpy(), lscl.numpy()


def rebind(gaussians: Gaussians, V_from, F_from, V_to, F_to) -> Gaussians:
    """The same Gaussians on another mesh: posed on (V_from, F_from) (the mesh they are bound to,
    at some frame), then each bound to its nearest face of (V_to, F_to) with its world rotation
    and scale kept, and its distance from the surface too (its old offset along the face normal,
    in metres: not the gap between the two meshes, which a new user's splats kept as a float of up
    to 7 % of the diagonal for a whole segment); colours, opacities and SH carried over. So splats
    continue across a change of template (a new segment of a piecewise-fixed sequence): where both
    meshes show the surface at one moment, the rebound Gaussians are where the old ones were."""
    d = gaussians.device
    F_from = np.asarray(F_from, np.int32)
    gaussians.update(wp.array(np.asarray(V_from, np.float32), dtype=wp.vec3, device=d),
                     wp.array(F_from.reshape(-1), dtype=wp.int32, device=d))
    s, b = gaussians.state, gaussians.binding
    V_to, F_to = validate_mesh(V_to, F_to, source="rebind mesh")
    bound = list(_bind_world(s.centers.numpy(), s.rotations.numpy(), s.scales.numpy(), V_to, F_to, d, "rebind"))
    # the old offset in metres (offsets are in face scales, sqrt(area)), in the new face's scale
    old_scale = np.sqrt(face_areas(np.asarray(V_from, np.float64), F_from[b.face.numpy()]))
    new_scale = np.sqrt(face_areas(np.asarray(V_to, np.float64), np.asarray(F_to)[bound[0]]))
    live = new_scale > 0  # a degenerate face keeps offset 0 (bind_gaussians_to_faces)
    bound[2] = np.where(live, b.offset.numpy() * old_scale / np.where(live, new_scale, 1.0), 0.0).astype(np.float32)
    # f_rest as they stand now (turned since their file), and the rotation they stand at
    return Gaussians(GaussianBinding(*bound, b.rgb, b.opacity, num_faces=F_to.shape[0], f_rest=gaussians.current_f_rest(),
                                     device=d, opacity_logit=b.opacity_logit,
                                     f_rest_rotation_xyzw=None if b.f_rest_rotation is None else s.rotations.numpy()))


class SegmentedGaussians:
    """Gaussians over a piecewise-fixed sequence (template segments, ``convert``'s output where
    one template could not follow): one :class:`Gaussians` per segment, each carried over from
    the previous segment onto its own first frame (:func:`rebind`): posed on the previous template
    carried on to that moment (its last frame plus its last frame's motion, constant velocity: the
    surface moves between the two frames, and splats posed at the last frame kept that motion as a
    gap). ``update(points,
    indices)`` takes the segment whose faces ``indices`` are (found once per index buffer) and
    poses it; every other attribute (``count``, ``state``, ``binding``, ...) is the current
    segment's. The count, colours and opacities are the same in every segment."""

    def __init__(self, seq, first: Gaussians):
        runs = seq.segments()
        self.parts = [first]
        for (a, b), (c, _) in zip(runs, runs[1:]):
            V, F = seq.frames[b - 1]
            if b - 1 > a:  # the previous template at frame c, its last motion carried on
                V = V + (c - b + 1) * (V - seq.frames[b - 2][0])
            self.parts.append(rebind(self.parts[-1], V, F, *seq.frames[c]))
        self.faces = [np.asarray(seq.frames[a][1]) for a, _ in runs]
        self.current = first
        self._by_ptr = {}

    def __getattr__(self, name):
        return getattr(self.__dict__["current"], name)

    def segment_of(self, indices: wp.array) -> int:
        """The segment whose faces the index buffer holds (compared once per buffer)."""
        key = (indices.ptr, indices.shape[0])
        if key not in self._by_ptr:
            F = indices.numpy().reshape(-1, 3)
            hits = [k for k, f in enumerate(self.faces) if f.shape == F.shape and np.array_equal(f, F)]
            if not hits:
                raise ValueError("SegmentedGaussians.update: these faces are no segment's of the sequence")
            # the buffer is kept alive with its answer, so that its address is not reused by another
            self._by_ptr[key] = (indices, hits[0])
        return self._by_ptr[key][1]

    def update(self, points: wp.array, indices: wp.array):
        self.current = self.parts[self.segment_of(indices)]
        self.current.update(points, indices)

    def attach(self, world) -> "SegmentedGaussians":
        """Update after every step of ``world`` (a post-step hook; a piecewise-fixed surface is
        stepped eagerly, its index buffer changing per segment)."""
        if world.device != self.device:
            raise ValueError(f"Gaussians are on {self.device}, the world on {world.device}")
        self.update(world.state.points, world.current_indices())
        world.add_post_step_hook(lambda w: self.update(w.state.points, w.current_indices()), follows_surface=True)
        return self


def generate_gaussians(V, F, count: int = 20000, seed: int = 0, vertex_colors=None, color=DEFAULT_COLOR,
                       opacity: float = 0.9, coverage: float = 0.6, thickness: float = 0.1,
                       device=None) -> Gaussians:
    """Seeded area-weighted Gaussians on the mesh surface (V (N,3) [m], F (M,3)).

    Faces are drawn in proportion to area by systematic sampling (``count`` evenly spaced
    quantiles of the cumulative area with one random phase: each face gets its share +-1, no
    clumps), points uniformly inside them. Each
    Gaussian is a flat disc in its face's plane: in-plane std dev = coverage * sqrt(A / count)
    (A = total area), normal std dev = thickness * that. Colour: ``vertex_colors`` (N,3) in
    [0,1] (or 0..255 uint8) interpolated at the sample, else ``color``.
    """
    V, F = validate_mesh(V, F, source="generate_gaussians mesh")
    if count < 0:
        raise ValueError(f"gaussians.count must be >= 0, got {count}")
    rng = np.random.default_rng(seed)
    V64 = V.astype(np.float64)
    area = face_areas(V64, F)
    total = float(area.sum())
    if total <= 0:
        raise ValueError("cannot generate Gaussians on a mesh of zero area")
    # systematic sampling by area: count evenly spaced quantiles of the cumulative area (one random
    # phase), so each face gets its share +-1 (independent draws clump and leave holes: the default
    # scene's silhouette was 98.4 % covered at 320 px, see docs/rendering.md)
    q = (np.arange(count) + rng.random()) * (total / max(count, 1))
    face = np.minimum(np.searchsorted(np.cumsum(area), q, side="right"), F.shape[0] - 1).astype(np.int32)
    r1, r2 = rng.random(count), rng.random(count)
    s1 = np.sqrt(r1)
    bary = np.stack([1.0 - s1, s1 * (1.0 - r2), s1 * r2], axis=1)
    sigma = coverage * np.sqrt(total / max(count, 1))
    sf = np.sqrt(area[face])
    local_scale = np.stack([sigma / sf, sigma / sf, thickness * sigma / sf], axis=1)
    local_rot = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (count, 1))
    if vertex_colors is not None:
        vc = np.asarray(vertex_colors)
        if vc.shape != V.shape:
            raise ValueError(f"vertex_colors must have shape {V.shape}, got {vc.shape}")
        vc = vc.astype(np.float64) / (255.0 if vc.dtype == np.uint8 else 1.0)
        rgb = np.einsum("gk,gkc->gc", bary, vc[F[face]])
    else:
        rgb = np.broadcast_to(np.asarray(color, np.float64), (count, 3))
    binding = GaussianBinding(face, bary, np.zeros(count), local_rot, local_scale, rgb,
                              np.full(count, opacity), num_faces=F.shape[0], device=device)
    return Gaussians(binding)


def gaussians_for_world(world, cfg=None) -> Gaussians:
    """Gaussians for a world built from a scene: bind ``cfg.gaussians.splats`` (a 3DGS .ply in
    the scene frame) if set, else generate ``cfg.gaussians.count`` on the first frame. Attached
    (updated after every step), so ``world`` is a :class:`~dynmesh_warp.world.World`; for another
    simulation (a ``NewtonWorld``) a ``TypeError`` says what to call instead."""
    if not hasattr(world, "add_post_step_hook") or not hasattr(getattr(world, "model", None), "surface"):
        raise TypeError(f"gaussians_for_world: a {type(world).__name__} takes no step hooks; use "
                        "gaussians_for_surface(world.surface.sequence, cfg, world.device) and update the Gaussians "
                        "yourself (update(points, indices) with the surface at the time you render)")
    return gaussians_for_surface(world.model.surface.sequence, cfg, world.device).attach(world)


def can_bind(seq) -> bool:
    """Whether Gaussians can be bound to the sequence: fixed topology, or piecewise-fixed
    (template segments, :class:`SegmentedGaussians`); not a truly varying one (a new mesh every
    frame)."""
    return hasattr(seq, "V") or seq.is_piecewise_fixed()


def gaussians_for_surface(seq, cfg=None, device=None) -> Gaussians:
    """Gaussians for a fixed-topology sequence as a scene asks (``cfg.gaussians``): bound to, or
    generated on, its first frame. Not attached: call ``update(points, indices)`` yourself. A
    piecewise-fixed sequence (template segments) gets :class:`SegmentedGaussians`: the same
    Gaussians carried from segment to segment."""
    from .splat_io import read_splat_ply

    if not can_bind(seq):
        raise ValueError("Gaussians need a fixed-topology surface (convert the sequence first)")
    segmented = not hasattr(seq, "V")
    V0, F0 = seq.frame(0)
    gcfg = getattr(cfg, "gaussians", None) if cfg is not None else None
    if gcfg is not None and gcfg.splats:
        g = bind_splats(read_splat_ply(cfg.resolve(gcfg.splats)), V0, F0, device=device)
    else:
        kw = {} if gcfg is None else {"count": gcfg.count, "seed": gcfg.seed, "color": gcfg.color,
                                      "opacity": gcfg.opacity}
        source = DEFAULT_COLOR_SOURCE if gcfg is None else gcfg.colors
        colors = getattr(seq, "colors", None) if source == ColorSource.MESH else None
        g = generate_gaussians(V0, F0, device=device, vertex_colors=colors, **kw)
    return SegmentedGaussians(seq, g) if segmented else g


#: ambient level of the splats' shading (the viewer's key light, the renderer's head light)
SHADE_AMBIENT = 0.35


def shaded_rgb(gaussians: "Gaussians", light_dir, ambient: float = SHADE_AMBIENT) -> np.ndarray:
    """(G, 3) colours of ``gaussians`` shaded by ambient + (1 - ambient) |n . l|: n each
    Gaussian's flat axis (its smallest scale: the face normal for Gaussians bound to faces, at
    the current state), l the unit ``light_dir`` towards the scene. The binding's colours are
    unlit; shading baked per frame lets the shape read (the viewer, ``render_world``)."""
    q = gaussians.state.rotations.numpy()
    s = gaussians.state.scales.numpy()
    axis = np.eye(3)[np.argmin(s, axis=1)]
    u, w = q[:, :3], q[:, 3:4]
    uv = (u * axis).sum(axis=1, keepdims=True)
    n = 2.0 * uv * u + (w * w - (u * u).sum(axis=1, keepdims=True)) * axis + 2.0 * w * np.cross(u, axis)
    light = np.asarray(light_dir, np.float64)
    light = light / np.linalg.norm(light)
    return (gaussians.binding.rgb * (ambient + (1.0 - ambient) * np.abs(n @ light))[:, None]).astype(np.float32)
