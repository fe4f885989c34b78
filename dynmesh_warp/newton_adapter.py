"""Newton adapter: any Newton rigid body or robot against our deforming, fixed-topology mesh.

Newton (``newton`` package, optional) is imported only inside functions, so importing this module
or :mod:`dynmesh_warp` never imports it.

:class:`DeformingMeshShape` adds the surface to a ``newton.ModelBuilder`` as a static mesh shape
(body -1, identity transform, unit scale) backed by its OWN ``wp.Mesh``: the ``newton.Mesh`` is
created with ``enable_surface_velocity=True``, which makes ``ModelBuilder.finalize`` key its
geometry cache on object identity too, so it is never merged with an identical mesh (Newton
otherwise shares one ``wp.Mesh`` between meshes with equal content hashes). After
``finalize``, :meth:`DeformingMeshShape.bind` checks that ``Model.shape_source_ptr`` of the shape
is that mesh's id and that no other shape uses it. Every sub-step :meth:`DeformingMeshShape.update`

1. writes the vertices and per-vertex surface velocities at the device clock ``sim_time`` into
   the mesh's ``points`` / ``velocities`` (``kernels/frames.py::update_frame_vertices``),
2. refits the BVH,
3. recomputes the shape's local AABB and bounding radius (``Model.shape_collision_aabb_lower``,
   ``..._upper``, ``Model.shape_collision_radius``), which Newton's broad phase
   (``compute_shape_aabbs``) otherwise keeps at the first frame's values.

Newton solvers use only the tangential part of the mesh velocity (friction); the normal motion of
the surface reaches bodies through the moving geometry (penetration correction), see
``docs/newton.md``.

:class:`NewtonWorld` is the time-stepper: a finalized Newton model, a solver, a collision
pipeline and the deforming mesh, stepped like :class:`dynmesh_warp.world.World`.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .choices import DEFAULT_NEWTON_SOLVER, NewtonSolver, values
from .config import PhysicsCore
from .kernels.frames import update_frame_vertices
from .kernels.integrate import advance_time
from .kernels.newton_adapter import accumulate_shape_bounds, reset_shape_bounds
from .world import SurfaceModel

__all__ = ["newton_available", "DeformingMeshShape", "NewtonWorld", "SOLVERS", "make_solver"]

#: the physics defaults (one home: dynmesh_warp.config.PhysicsCore)
_PHYSICS = {k: f.default for k, f in PhysicsCore.model_fields.items()}

#: the Newton solvers make_solver creates (dynmesh_warp.choices.NewtonSolver)
SOLVERS = tuple(values(NewtonSolver))


def newton_available() -> bool:
    """True when the optional ``newton`` package can be imported."""
    try:
        import newton  # noqa: F401, PLC0415
    except Exception:  # noqa: BLE001 (any import failure means: not available)
        return False
    return True


def _import_newton():
    try:
        import newton  # noqa: PLC0415
    except ImportError as e:
        raise ImportError("the Newton adapter needs the optional 'newton' package (pip install newton)") from e
    return newton


class DeformingMeshShape:
    """Our deforming mesh as a static Newton mesh shape, updated on the device every sub-step.

    Args:
        surface: a :class:`SurfaceModel` (fixed topology; its ``frames`` buffer is read by the
            update kernel).
        update_bounds: recompute the shape's collision AABB / radius each update (default). Only
            tests switch it off, to show that Newton's broad phase then misses the moved surface.
        bounds_pad: extra padding of the bounds [m] (default 0: the bounds are recomputed before
            every collision pass, and Newton adds the shape's margin + gap on top).
        mu, restitution: Newton shape material of the surface (default: the scene's physics
            defaults, ``physics.friction`` and ``physics.restitution``).
    """

    def __init__(self, surface: SurfaceModel, *, update_bounds: bool = True, bounds_pad: float = 0.0,
                 mu: float = _PHYSICS["friction"], restitution: float = _PHYSICS["restitution"],
                 label: str = "dynmesh_surface"):
        if not isinstance(surface, SurfaceModel):
            raise TypeError("the Newton adapter needs a fixed-topology SurfaceModel "
                            "(convert a varying-topology input first)")
        self.surface = surface
        self.update_bounds = bool(update_bounds)
        self.bounds_pad = float(bounds_pad)
        self.mu = float(mu)
        self.restitution = float(restitution)
        self.label = label
        self.shape = None
        self.model = None
        self.newton_mesh = None
        self.mesh = None  # the wp.Mesh we write to, after bind()

    def add_to_builder(self, builder) -> int:
        """Add the surface (first frame) as a static mesh shape; returns the shape index."""
        newton = _import_newton()
        seq = self.surface.sequence
        V0 = np.ascontiguousarray(seq.V[0], dtype=np.float32)
        F = np.ascontiguousarray(seq.F, dtype=np.int32).reshape(-1)
        # enable_surface_velocity: per-vertex velocities reach the contacts (friction), and the
        # builder keeps a separate wp.Mesh for this object even if another mesh has equal content
        self.newton_mesh = newton.Mesh(V0, F, compute_inertia=False, is_solid=False, enable_surface_velocity=True)
        cfg = newton.ModelBuilder.ShapeConfig(density=0.0, mu=self.mu, restitution=self.restitution)
        self.shape = builder.add_shape_mesh(-1, mesh=self.newton_mesh, cfg=cfg, label=self.label)
        return self.shape

    def bind(self, model, sim_time: wp.array | None = None):
        """Attach to the finalized ``model``: find our ``wp.Mesh`` and check that it is ours alone.

        ``sim_time`` is the (1,) float64 device clock [s] read by :meth:`update` (default: a new
        one at t = 0). Writes the surface at that time and its bounds.
        """
        if self.shape is None:
            raise RuntimeError("call add_to_builder(builder) before finalize() and bind()")
        mesh = self.newton_mesh.mesh
        ptr = model.shape_source_ptr.numpy()
        if mesh is None or int(ptr[self.shape]) != int(mesh.id):
            raise RuntimeError("Newton did not give the deforming surface shape its own wp.Mesh")
        if int((ptr == ptr[self.shape]).sum()) != 1:
            raise RuntimeError("the deforming surface's wp.Mesh is shared with another Newton shape")
        if mesh.points.shape[0] != self.surface.num_vertices or mesh.velocities is None:
            raise RuntimeError("Newton's mesh for the surface has an unexpected layout")
        tr = model.shape_transform.numpy()[self.shape]
        if not np.allclose(tr, [0, 0, 0, 0, 0, 0, 1]) or not np.allclose(model.shape_scale.numpy()[self.shape], 1):
            raise RuntimeError("the deforming surface shape must have an identity transform and unit scale")
        if model.device != self.surface.device:
            raise ValueError(f"Newton model is on {model.device}, the surface on {self.surface.device}")
        self.model = model
        self.mesh = mesh
        self.sim_time = sim_time if sim_time is not None else wp.zeros(1, dtype=wp.float64, device=model.device)
        self.update()
        return self

    def update(self):
        """Write the surface at ``sim_time`` into the mesh, refit its BVH, update its bounds.

        Only kernel launches (no allocation, no host read): safe inside CUDA graph capture.
        """
        surf = self.surface
        m = self.mesh
        d = self.model.device
        wp.launch(update_frame_vertices, dim=surf.num_vertices,
                  inputs=[surf.frames, self.sim_time, surf.fps, surf.playback, int(surf.interpolate)],
                  outputs=[m.points, m.velocities], device=d)
        m.refit()
        if self.update_bounds:
            model = self.model
            outs = [model.shape_collision_aabb_lower, model.shape_collision_aabb_upper, model.shape_collision_radius]
            wp.launch(reset_shape_bounds, dim=1, inputs=[self.shape], outputs=outs, device=d)
            wp.launch(accumulate_shape_bounds, dim=surf.num_vertices, inputs=[m.points, self.shape, self.bounds_pad],
                      outputs=outs, device=d)


def make_solver(model, name: str = DEFAULT_NEWTON_SOLVER, **options):
    """Create a Newton solver by name (``SOLVERS``); ``options`` go to its constructor."""
    newton = _import_newton()
    name = str(name).lower()
    if name == "xpbd":
        options.setdefault("iterations", 5)
        return newton.solvers.SolverXPBD(model, **options)
    if name == "semi_implicit":
        return newton.solvers.SolverSemiImplicit(model, **options)
    if name == "featherstone":
        return newton.solvers.SolverFeatherstone(model, **options)
    if name == "vbd":
        return newton.solvers.SolverVBD(model, **options)
    if name == "mujoco":
        try:
            return newton.solvers.SolverMuJoCo(model, **options)
        except ImportError as e:
            raise ImportError(f"Newton solver 'mujoco' needs mujoco / mujoco_warp: {e}") from e
    raise ValueError(f"unknown Newton solver {name!r}; choose one of {list(SOLVERS)}")


_GEO_NAMES = None


def _geo_names():
    global _GEO_NAMES
    if _GEO_NAMES is None:
        newton = _import_newton()
        _GEO_NAMES = {int(v): v.name.lower() for v in newton.GeoType}
    return _GEO_NAMES


class NewtonWorld:
    """Newton bodies on our deforming mesh, stepped like :class:`dynmesh_warp.world.World`.

    Build a ``newton.ModelBuilder`` with the bodies (``add_body`` + shapes, ``add_mjcf`` ...),
    then ``NewtonWorld(surface, builder, ...)`` adds the surface, finalizes the model on the
    surface's device and creates the solver and collision pipeline.

    Each sub-step (of ``dt / substeps``): advance the device clock -> write the surface at the new
    time into the mesh, refit, update bounds -> ``CollisionPipeline.collide`` -> ``solver.step``.
    The surface is the one at the END of the sub-step, the position the solver's contact
    constraints should reach. On CUDA the first step runs eagerly (loading the modules it uses);
    the second is captured as a CUDA graph and replayed from then on.

    Args:
        surface: :class:`SurfaceModel`; builder: ``newton.ModelBuilder`` holding the bodies.
        solver: a name in ``SOLVERS``; solver_options: constructor keyword arguments.
        gravity: overrides the builder's gravity [m/s^2] (a 3-vector) when given.
        update_bounds / bounds_pad / mu / restitution: see :class:`DeformingMeshShape`.
    """

    def __init__(self, surface: SurfaceModel, builder, *, dt: float = _PHYSICS["dt"],
                 substeps: int = _PHYSICS["substeps"], solver: str = DEFAULT_NEWTON_SOLVER,
                 solver_options: dict | None = None, gravity=None, update_bounds: bool = True,
                 bounds_pad: float = 0.0, mu: float = _PHYSICS["friction"],
                 restitution: float = _PHYSICS["restitution"],
                 t0: float = 0.0, use_graph: bool | None = None):
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"dt must be a positive number, got {dt}")
        if int(substeps) < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        self.device = surface.device
        self.surface = surface
        self.dt = float(dt)
        self.substeps = int(substeps)
        self.sub_dt = self.dt / self.substeps
        self.adapter = DeformingMeshShape(surface, update_bounds=update_bounds, bounds_pad=bounds_pad,
                                          mu=mu, restitution=restitution)
        self.adapter.add_to_builder(builder)
        if gravity is not None:
            builder.gravity = tuple(float(g) for g in gravity)
        self.solver_name = solver
        if solver == "vbd":
            builder.color()
        self.model = builder.finalize(device=self.device)
        self.t0 = float(t0)
        self.sim_time = wp.array([self.t0], dtype=wp.float64, device=self.device)
        self.adapter.bind(self.model, self.sim_time)
        opts = dict(solver_options or {})
        if solver == "xpbd" and float(restitution) > 0 and "enable_restitution" not in opts:
            # Newton's XPBD leaves restitution off unless asked: a new user's restitution 1.0 gave
            # no bounce at all (0.05 m after a 0.5 m drop; 0.50 m with it on, 0.51 m built-in)
            opts["enable_restitution"] = True
        if solver == "xpbd" and opts.get("enable_restitution") and surface.motion_speed > 0:
            import warnings  # noqa: PLC0415

            warnings.warn(f"restitution {float(restitution):g} turns on Newton XPBD's restitution, which takes the "
                          "deforming surface as static along its normal: a body riding the moving surface follows it, "
                          "but its velocity reads as if the surface stood still (a new user's box on a floor rising at "
                          "1 m/s read 0.024 m/s, and was not thrown up when the floor stopped); for bodies that ride "
                          "the surface set physics.restitution: 0 (docs/newton.md)", UserWarning, stacklevel=3)
        self.solver = make_solver(self.model, solver, **opts)
        newton = _import_newton()
        self.state_0 = self.model.state()
        self.state_1 = self.model.state()
        self.control = self.model.control()
        if self.model.joint_count:
            newton.eval_fk(self.model, self.model.joint_q, self.model.joint_qd, self.state_0)
        self.pipeline = newton.CollisionPipeline(self.model)
        self.contacts = self.pipeline.contacts()
        self.substep_count = 0
        if use_graph is None:
            use_graph = self.device.is_cuda
        self.use_graph = bool(use_graph) and self.device.is_cuda
        self._graph = None

    # -- stepping ------------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Simulation time [s], tracked on the host in step with the device clock."""
        return self.t0 + self.substep_count * self.sub_dt

    def substep(self, last: bool):
        self.state_0.clear_forces()
        wp.launch(advance_time, dim=1, inputs=[self.sub_dt], outputs=[self.sim_time], device=self.device)
        self.adapter.update()
        self.pipeline.collide(self.state_0, self.contacts)
        self.solver.step(self.state_0, self.state_1, self.control, self.contacts, self.sub_dt)
        if last and self.substeps % 2 == 1:
            self.state_0.assign(self.state_1)  # keeps state_0 the same arrays (graph replay)
        else:
            self.state_0, self.state_1 = self.state_1, self.state_0

    def _step_body(self):
        for i in range(self.substeps):
            self.substep(i == self.substeps - 1)

    @property
    def graph_captured(self) -> bool:
        """Whether a captured CUDA graph is held (steps replay it)."""
        return self._graph is not None

    def capture(self):
        """Capture one step as a CUDA graph that later ``step()`` calls replay; nothing without
        ``use_graph``. Captures nothing, advances nothing. Call it after one eager step: that step
        loaded exactly the Warp modules Newton's pipeline and solver use (``force_module_load=True``
        would instead load, on a cold cache compile, every module Newton defines: minutes on a
        GPU). ``step()`` does the same by itself on its second call."""
        if not self.use_graph or self._graph is not None:
            return
        with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
            self._step_body()
        self._graph = cap.graph

    def step(self):
        """Advance by one physics step (dt): eager the first time, then a captured CUDA graph
        (``use_graph``; the same policy as the built-in ``World``)."""
        if self.use_graph and self._graph is None and self.substep_count > 0:
            self.capture()
        if self._graph is not None:
            wp.capture_launch(self._graph)
        else:
            self._step_body()
        self.substep_count += self.substeps

    # -- the Simulation protocol (runtime.Simulation) ------------------------------------------
    editable = False  # reset / set_time / add_spheres are the built-in world's

    def surface_points(self):
        """The surface's vertices (N,) at the current time: the adapter writes them into Newton's
        mesh every sub-step."""
        return self.adapter.mesh.points

    def surface_indices(self):
        return self.surface.indices

    def sphere_positions(self) -> np.ndarray:
        return np.zeros((0, 3), np.float32)  # the bodies are Newton's (body_transforms)

    def rigid_shapes(self) -> list:
        """The bodies' visible shapes (``shapes()`` with Newton's VISIBLE flag, sites left out)
        with their world poses now (``pose``), for rendering; the deforming surface and static
        planes left out."""
        newton = _import_newton()
        visible, site = int(newton.ShapeFlags.VISIBLE), int(newton.ShapeFlags.SITE)
        X = self.shape_transforms()
        out = []
        for sh in self.shapes():
            if sh["type"] == "plane" or not sh["flags"] & visible or sh["flags"] & site:
                continue
            out.append({**sh, "pose": X[sh["index"]]})
        return out

    def sphere_radii(self) -> np.ndarray:
        return np.zeros(0, np.float32)

    # -- what the runner reads (runtime.Simulation; runner.run_simulation) ---------------------
    checkpointable = False  # the Newton solver's state is not saved
    body_noun = "body"
    num_envs = 1

    def sample(self) -> dict:
        """The arrays of one ``trajectories.npz`` sample: ``body_q`` (B, 7) body poses."""
        return {"body_q": self.body_transforms()}

    def trajectory_constants(self) -> dict:
        return {}

    def contact_count(self) -> int:
        """Rigid contacts found by Newton's collision pipeline in the last sub-step."""
        return int(self.contacts.rigid_contact_count.numpy()[0])

    def run_summary(self) -> dict:
        """The Newton world's fields of a run's ``summary.json``."""
        final = self.body_transforms()
        return {
            "engine": "newton",
            "newton_version": _import_newton().__version__,
            "solver": self.solver_name,
            "surface": {"frames": self.surface.num_frames, "fps": self.surface.fps,
                        "vertices": self.surface.num_vertices, "faces": self.surface.num_faces},
            "bodies": self.model.body_count,
            "num_envs": self.num_envs,  # Newton worlds (ModelBuilder.replicate), one clock
            "entries": self.records,
            "final": {"finite": bool(np.isfinite(final).all()), "body_q": final, "body_labels": self.body_labels()},
        }

    def run_line(self) -> tuple[str, str]:
        """(engine label, result) of the run's log line."""
        return f"Newton {self.solver_name}", f"{self.model.body_count} bodies"

    # -- read-out (host copies; for the viewer and summaries) ----------------------------------
    def body_transforms(self) -> np.ndarray:
        """(B, 7) body poses: position [m] and quaternion (x, y, z, w)."""
        return self.state_0.body_q.numpy().copy()

    def body_velocities(self) -> np.ndarray:
        """(B, 6) body twists as Newton stores them (linear [m/s], angular [rad/s])."""
        return self.state_0.body_qd.numpy().copy()

    def body_labels(self) -> list[str]:
        return list(self.model.body_label) if getattr(self.model, "body_label", None) else []

    def shape_transforms(self) -> np.ndarray:
        """(S, 7) world poses of all shapes (body pose * shape's local transform; static shapes:
        the local transform)."""
        local = self.model.shape_transform.numpy()
        body = self.model.shape_body.numpy()
        bq = self.state_0.body_q.numpy()
        out = local.copy()
        for s in np.nonzero(body >= 0)[0]:
            out[s] = _transform_multiply(bq[body[s]], local[s])
        return out

    def shapes(self, include_surface: bool = False) -> list[dict]:
        """Descriptions of the collision shapes for display.

        Each dict: ``index``, ``body`` (-1 static), ``type`` (``box`` | ``sphere`` | ``capsule`` |
        ``cylinder`` | ``mesh`` | ...), ``scale`` (box: half extents; sphere: (r, 0, 0); capsule and
        cylinder: (radius, half_height, 0), axis local z) [m], ``local_transform`` (7,) in the body
        frame; mesh shapes also ``vertices`` (N, 3) and ``indices`` (M, 3) in the shape frame.
        The deforming surface itself is left out unless ``include_surface``.
        """
        m = self.model
        names = _geo_names()
        types = m.shape_type.numpy()
        scales = m.shape_scale.numpy()
        bodies = m.shape_body.numpy()
        local = m.shape_transform.numpy()
        flags = m.shape_flags.numpy()
        out = []
        for s in range(m.shape_count):
            if s == self.adapter.shape and not include_surface:
                continue
            d = {"index": s, "body": int(bodies[s]), "type": names.get(int(types[s]), str(int(types[s]))),
                 "scale": scales[s].tolist(), "local_transform": local[s].tolist(), "flags": int(flags[s])}
            src = m.shape_source[s] if getattr(m, "shape_source", None) is not None else None
            if src is not None and hasattr(src, "vertices") and hasattr(src, "indices"):
                d["vertices"] = np.asarray(src.vertices, np.float32)
                d["indices"] = np.asarray(src.indices, np.int32).reshape(-1, 3)
            out.append(d)
        return out



def _quat_rotate(q, v):
    x, y, z, w = q
    u = np.array([x, y, z])
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _transform_multiply(a, b):
    p = a[:3] + _quat_rotate(a[3:], b[:3])
    return np.concatenate([p, _quat_mul(a[3:], b[3:])])


# ---------------------------------------------------------------------------------------------
# Scenes: the ``newton:`` section of a scene YAML (see dynmesh_warp/config.py, docs/newton.md)
# ---------------------------------------------------------------------------------------------


def _set_free_velocity(builder, velocity):
    """Initial linear velocity [m/s] of the body just added by ``add_body`` (its free joint's
    qd is (v_com_world, omega_world))."""
    if velocity is None or not np.any(velocity):
        return
    j = builder.joint_count - 1
    q0 = builder.joint_qd_start[j]
    for k in range(3):
        builder.joint_qd[q0 + k] = float(velocity[k])


def add_scene_bodies(builder, cfg, sphere_positions=None) -> list[dict]:
    """Add the bodies of ``cfg.newton`` (and the scene's spheres when ``include_spheres``) to a
    ``newton.ModelBuilder``. Returns one record per entry: kind, label, first/last body index."""
    newton = _import_newton()
    ncfg = cfg.newton
    records = []
    # the bodies' own friction is physics.friction; newton.surface_mu is the deforming surface's
    # (Newton combines the two shapes'); it was given to every body too, so surface_mu 0 made a
    # box with friction 1 slide off a 20-degree slope (a new user's)
    mu = cfg.physics.friction
    for i, b in enumerate(ncfg.bodies):
        label = b.label or f"{b.type}_{i}"
        xf = wp.transform(wp.vec3(*b.position), wp.normalize(wp.quat(*b.rotation)))
        scfg = newton.ModelBuilder.ShapeConfig(density=b.density, mu=mu, restitution=cfg.physics.restitution)
        first = builder.body_count
        if b.type in ("box", "sphere", "capsule"):
            body = builder.add_body(xform=xf, label=label)
            if b.type == "box":
                hx, hy, hz = b.half_extents
                builder.add_shape_box(body, hx=hx, hy=hy, hz=hz, cfg=scfg)
            elif b.type == "sphere":
                builder.add_shape_sphere(body, radius=b.radius, cfg=scfg)
            else:
                builder.add_shape_capsule(body, radius=b.radius, half_height=b.half_height, cfg=scfg)
            _set_free_velocity(builder, b.velocity)
        else:
            path = str(cfg.resolve(b.file))
            loader = {"mjcf": builder.add_mjcf, "urdf": builder.add_urdf, "usd": builder.add_usd}[b.type]
            try:
                loader(path, xform=xf, floating=b.floating, **b.options)
            except Exception as e:  # noqa: BLE001 (report which file failed, with Newton's reason)
                raise ValueError(f"newton.bodies.{i}.file: Newton could not load {b.type} {path}: {e}") from e
        records.append({"kind": b.type, "label": label, "bodies": [first, builder.body_count]})
    if ncfg.include_spheres and sphere_positions is not None:
        radius, mass, pos, vel = sphere_positions
        for k in range(len(pos)):
            label = f"sphere_{k}"
            vol = 4.0 / 3.0 * math.pi * radius[k] ** 3
            scfg = newton.ModelBuilder.ShapeConfig(density=float(mass[k]) / vol, mu=mu,
                                                   restitution=cfg.physics.restitution)
            first = builder.body_count
            body = builder.add_body(xform=wp.transform(wp.vec3(*[float(x) for x in pos[k]]), wp.quat_identity()),
                                    label=label)
            builder.add_shape_sphere(body, radius=float(radius[k]), cfg=scfg)
            _set_free_velocity(builder, None if vel is None else vel[k])
            records.append({"kind": "scene_sphere", "label": label, "bodies": [first, builder.body_count]})
    return records


def _refuse_bodies_inside(cfg, seq) -> None:
    """The built-in world's rule for the Newton path too (docs/scene.md): a listed scene sphere
    (``include_spheres``) or a box / sphere / capsule body whose centre starts inside the closed
    surface (frame 0) is refused; contacts with the surface are one-sided, and a new user's
    sphere fell out through a blob (z 0.6 -> -7.7 in 1 s) where the built-in engine refused it."""
    from .scene import refuse_starts_inside, sphere_entries  # noqa: PLC0415

    def clearance(b):  # how far its surface reaches from its centre [m]
        return max(b.half_extents) if b.type == "box" else b.radius + (b.half_height or 0.0)

    bodies = [(f"newton.bodies.{i}", b.position, clearance(b)) for i, b in enumerate(cfg.newton.bodies)
              if b.type in ("box", "sphere", "capsule")]
    refuse_starts_inside(*seq.frame(0), (sphere_entries(cfg) if cfg.newton.include_spheres else []) + bodies)


def _inscribed(b) -> float:
    """How far a box / sphere / capsule body reaches from its centre in every direction [m]: its
    smallest half extent, or its radius."""
    return min(b.half_extents) if b.type == "box" else b.radius


def _refuse_bodies_below_ground(cfg, ground: float | None) -> None:
    """A box / sphere / capsule body whose centre starts under ``ground`` + its reach
    (:func:`_inscribed`, less GROUND_OVERLAP of it) is refused, as a sphere is
    (``scene.refuse_below_ground``): a new user's box 0.2 m under the ground plane was shot up at
    48 m/s where a sphere there was refused."""
    from .config import SceneError  # noqa: PLC0415
    from .scene import GROUND_OVERLAP  # noqa: PLC0415

    if ground is None:
        return
    for i, b in enumerate(cfg.newton.bodies):
        if b.type in ("box", "sphere", "capsule") and b.position[2] < ground + (1.0 - GROUND_OVERLAP) * _inscribed(b):
            raise SceneError(f"newton.bodies.{i}: centre z = {b.position[2]:.6g} starts below the ground plane "
                             f"(physics.ground = {cfg.physics.ground!r}, z = {ground:.6g}, plus its "
                             f"{'smallest half extent' if b.type == 'box' else 'radius'} {_inscribed(b):.4g}): Newton "
                             "would throw it up at the first step. Lower physics.ground (null: none) or raise the body")


def _warn_bodies_overlapping(cfg, seq) -> None:
    """Warn of a box / sphere / capsule body that starts overlapping the surface (frame 0): its
    centre nearer the surface than it reaches every way (:func:`_inscribed`). Newton pushes it
    out at once: a new user's box 4 cm into a sheet left at 6.4 m/s and rose 2 m (the built-in
    world pushes a sphere out by its depth, at rest)."""
    import warnings  # noqa: PLC0415

    from .convert_base import nearest_surface  # noqa: PLC0415

    bodies = [(i, b) for i, b in enumerate(cfg.newton.bodies) if b.type in ("box", "sphere", "capsule")]
    if not bodies:
        return
    reach = max(_inscribed(b) for _, b in bodies)  # (a centre farther than every body's reach: no overlap)
    near = nearest_surface(seq.frame(0), [b.position for _, b in bodies], device="cpu", max_dist=2.0 * reach,
                           source="surface (frame 0)")
    for (i, b), d in zip(bodies, near.dist):
        if d < _inscribed(b):
            warnings.warn(f"newton.bodies.{i} ({b.type}) starts {_inscribed(b) - d:.4g} m into the surface (its centre "
                          f"{d:.4g} m from it, reaching {_inscribed(b):.4g} m every way): Newton pushes it out at the "
                          "first steps, fast (a box 4 cm into a sheet left at 6.4 m/s); start it clear of the surface",
                          UserWarning, stacklevel=4)


def _newton_substeps(cfg, surface, radii) -> int:
    """``physics.substeps``, raised (``physics.auto_substeps``, with a warning; else only warned
    of) so the surface moves less than half the thinnest body per sub-step: the built-in world's
    rule (``World._apply_substep_rule``), the thickness a box's smallest half extent, a capsule's
    or a sphere's radius (mjcf / urdf / usd bodies: not known, not counted). A new user's box (5 cm
    half height) fell through a sheet moving at 8.5 m/s at one sub-step, unsaid."""
    import warnings  # noqa: PLC0415

    from .world import check_substep_budget, required_substeps, seam_note  # noqa: PLC0415

    p = cfg.physics
    thick = [_inscribed(b) for b in cfg.newton.bodies if b.type in ("box", "sphere", "capsule")]
    thick += list(radii) if cfg.newton.include_spheres else []
    if not thick or surface.max_speed <= 0 or not surface.interpolate:
        return int(p.substeps)
    r_min = float(min(thick))
    need = required_substeps(surface.max_speed, p.dt, r_min)
    if need <= p.substeps:
        return int(p.substeps)
    note = seam_note(surface)
    if not p.auto_substeps:
        warnings.warn(f"auto_substeps is off and the surface moves up to {surface.max_speed:.3g} m/s{note}: "
                      f"{surface.max_speed * p.dt / p.substeps:.3g} m per sub-step, over half the thinnest Newton "
                      f"body ({0.5 * r_min:.3g} m): bodies may pass through it; set physics.substeps to {need}",
                      stacklevel=3)
        return int(p.substeps)
    check_substep_budget(need, surface.max_speed, r_min, p, note)
    warnings.warn(f"surface moves up to {surface.max_speed:.3g} m/s{note}: raising substeps from {p.substeps} to "
                  f"{need} so it moves < half the thinnest Newton body ({r_min:.3g} m) per sub-step", stacklevel=3)
    return need


def build_newton_world(cfg, device=None, sequence=None, num_worlds: int = 1, **overrides) -> NewtonWorld:
    """Create a :class:`NewtonWorld` from a validated scene with a ``newton:`` section.

    ``num_worlds`` > 1: Newton's own batching (issue 15, for comparison with ``batch``): the
    scene's bodies are built once and replicated into that many Newton worlds
    (``ModelBuilder.replicate``: copies do not collide with each other); the deforming surface
    and the ground are global (world -1), shared by every world, so all worlds see the surface
    at one time (Newton has one clock; per-world clocks would need one mesh per world)."""
    from .config import SceneError  # noqa: PLC0415
    from .scene import build_model, load_surface, prepare_surface, require_fixed_topology  # noqa: PLC0415

    if cfg.newton is None:
        raise SceneError("the scene has no 'newton:' section")
    try:
        newton = _import_newton()
    except ImportError as e:
        raise SceneError(f"newton: {e}") from e
    seq = load_surface(cfg) if sequence is None else prepare_surface(sequence, cfg)
    require_fixed_topology(cfg, seq, "the Newton path needs")
    _refuse_bodies_inside(cfg, seq)
    _warn_bodies_overlapping(cfg, seq)
    # the one builder (scene.build_model): the surface on the device, the spheres, the ground
    model, state = build_model(cfg, seq, device)
    _refuse_bodies_below_ground(cfg, model.params.ground_height)
    surface, sp = model.surface, model.spheres
    vel = state.sphere_vel.numpy() if isinstance(cfg.spheres, list) else None
    sph = (sp.radius_np.tolist(), sp.mass_np.tolist(), state.sphere_pos.numpy().copy(), vel)
    if any(m <= 0 for m in sph[1]) and cfg.newton.include_spheres:
        raise SceneError("spheres: the Newton path needs mass > 0 for every sphere")
    if int(num_worlds) < 1:
        raise SceneError(f"num_worlds must be >= 1, got {num_worlds}")
    builder = newton.ModelBuilder()
    if int(num_worlds) == 1:
        records = add_scene_bodies(builder, cfg, sph)
    else:
        one = newton.ModelBuilder()
        records = add_scene_bodies(one, cfg, sph)
        builder.replicate(one, copy_count=int(num_worlds))
    p = cfg.physics
    mu = p.friction if cfg.newton.surface_mu is None else cfg.newton.surface_mu
    if model.params.ground_height is not None:  # the same static plane the built-in world has
        builder.add_ground_plane(height=float(model.params.ground_height), cfg=newton.ModelBuilder.ShapeConfig(mu=mu))
    kw = dict(dt=p.dt, substeps=_newton_substeps(cfg, surface, sph[0]), solver=cfg.newton.solver,
              solver_options=dict(cfg.newton.solver_options), gravity=p.gravity, mu=mu, restitution=p.restitution)
    kw.update(overrides)
    where = f"{cfg.source_file}: " if cfg.source_file else ""  # the scene file, as the schema's errors name it
    solver = getattr(cfg.newton.solver, "value", cfg.newton.solver)
    try:
        world = NewtonWorld(surface, builder, **kw)
    except ImportError as e:  # e.g. the mujoco solver without mujoco_warp installed
        raise SceneError(f"{where}newton.solver {solver!r}: {e}") from e
    except TypeError as e:  # a constructor argument the solver does not take
        raise SceneError(f"{where}newton.solver_options: {e}") from e
    world.records = records  # the bodies of world 0 (world w's are offset by w x its body count)
    world.num_envs = int(num_worlds)
    return world
