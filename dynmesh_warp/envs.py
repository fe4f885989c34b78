"""A Gymnasium vector env on the batched world (issue 15): keep a pushed ball on a deforming
reconstruction, near a target (by default the top of the surface: the galloping horse's back).

``RideSurfaceEnv(num_envs, scene=...)`` is a ``gymnasium.vector.VectorEnv`` (gymnasium >= 1.0)
whose envs share one :class:`~dynmesh_warp.batch.BatchedWorld`, each at its own phase of the
sequence. Everything per step runs on the simulation device (kernels/envs.py): the actions
enter as velocity changes, the world takes ``decimation`` physics steps (one CUDA graph each),
observations, rewards and flags are computed there, and finished envs are reset there (same-step
autoreset: the returned observation of a finished env is its new episode's first; the last one
is in ``info["final_obs"]``). With ``backend="torch"`` step returns torch tensors on the
simulation device that share memory with the Warp arrays (``wp.to_torch``: no host round trip);
with ``backend="numpy"`` (default, Gymnasium's convention) host copies.

Observation (18 per env): ball position relative to the target (3) [m], ball velocity (3)
[m/s], heights of the surface at a 3 x 3 grid around the ball relative to it (9) [m], in contact
(1), sin/cos of the env's phase in its playback of the sequence (2). A probe that meets no
surface below reads the floor: the ground, or where the scene has none 2 ball radii under the
sequence's lowest point (``FLOOR_DROP``). Action (2 per env): in [-1, 1] x ``accel`` [m/s^2], a
horizontal velocity change of action x accel x decimation x dt at the start of the env step (an
impulse). Reward per step: 1 - (horizontal distance / max_distance)^2 - 0.01 |action|^2, less 1
on the step that terminates (the ball fell to the floor or left ``max_distance``): that step
earns -(distance / max_distance)^2 - 0.01 |action|^2; episodes are truncated after ``max_steps``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .batch import BatchedWorld, BatchModel, BatchState
from .metrics import kernel_seed
from .kernels.envs import (
    OBS_DIM,
    apply_env_actions,
    combine_env_flags,
    count_env_steps,
    evaluate_ball_task,
    reset_ball_envs,
    reset_env_streams,
)

try:  # gymnasium is an optional dependency (the "rl" and "all" extras)
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode, VectorEnv
except ImportError:  # pragma: no cover - reported when an env is made
    gym = None
    VectorEnv = object
    AutoresetMode = None

__all__ = ["ENV_ID", "RideSurfaceEnv", "RideSurfaceSingleEnv", "ride_surface_scene", "surface_target"]

#: the Gymnasium id registered when this module is imported: ``gym.make(ENV_ID)`` makes a
#: :class:`RideSurfaceSingleEnv`, ``gym.make_vec(ENV_ID, num_envs=E)`` a :class:`RideSurfaceEnv`
#: (its ``vector_entry_point``: one batched world, not E copies); without importing this module
#: first, ``gym.make("dynmesh_warp.envs:" + ENV_ID)``
ENV_ID = "dynmesh_warp/RideSurface-v0"
#: the episode length [env steps] when none is given: ``max_steps`` of :class:`RideSurfaceEnv`, and
#: the registered ``max_episode_steps`` of ``ENV_ID`` (Gymnasium's TimeLimit ends ``gym.make``'s
#: episodes, ``gym.make_vec`` passes it to the batch)
MAX_STEPS = 500


def surface_target(V0: np.ndarray, top_fraction: float = 0.1) -> np.ndarray:
    """Default target [m]: the centroid of the highest ``top_fraction`` of frame 0's vertices (a
    horse's back and head; a bowl's rim would be a ring, so pass your own target there)."""
    z = V0[:, 2]
    top = V0[z >= np.quantile(z, 1.0 - top_fraction)]
    return top.mean(axis=0).astype(np.float32)


#: with no ground, the floor lies this many ball radii under the sequence's lowest point: a ball
#: resting anywhere on the surface is above it, one that left the surface passes it soon
FLOOR_DROP = 2.0


def ride_surface_scene(scene=None) -> tuple:
    """``(cfg, sequence)`` of the RideSurface task for ``scene`` (a path, a mapping, a
    ``SceneConfig`` or None: a ball on the built-in pulsing blob), its spheres left out, checked
    before any env is built: gravity along -z, a fixed-topology surface (``SceneError``,
    ``MeshDataError`` or ``ValueError`` naming the file and field). ``python -m
    dynmesh_warp.distributed`` asks it before it starts Ray (a new user's bad scene file was a
    40-line actor traceback)."""
    from .config import scene_config
    from .scene import load_surface, require_fixed_topology

    cfg = scene_config(scene, default={"surface": {"source": "builtin:pulsing_blob"}})
    cfg = cfg.model_copy(update={"spheres": []})
    g = np.asarray(cfg.physics.gravity, np.float64)
    if not (g[2] <= 0 and np.allclose(g[:2], 0.0)):  # (no gravity: up is +z, as a scene takes it)
        # the task is laid out along z (probes cast down -z, pushes in x and y, the target on
        # top along z): a y-up scene's ball was pushed into its floor, unsaid (a new user's)
        raise ValueError(f"the RideSurface envs need gravity along -z (probes cast down, pushes across); the "
                         f"scene's physics.gravity is {list(cfg.physics.gravity)}: for y-up data set "
                         "surface.up_axis: y (it is turned z-up) and keep gravity [0, 0, -9.81]")
    # a varying-topology scene raised AttributeError ('no attribute V') here (a new user's)
    return cfg, require_fixed_topology(cfg, load_surface(cfg), "the RideSurface envs need")


class RideSurfaceEnv(VectorEnv):
    """Keep a pushed ball on a deforming surface near a target; ``num_envs`` envs in one batch.

    Args:
        num_envs: E.
        scene: a scene (``config.SceneConfig``, a YAML path, or None: ``builtin:pulsing_blob``, a ball
            on top of a breathing blob); its
            surface and physics are used, its spheres are not (one ball per env).
        device: Warp device (default: the scene's, else Warp's).
        backend: "numpy" (host arrays) or "torch" (device tensors, zero copy).
        radius: ball radius [m]; max_steps: episode length (default ``MAX_STEPS``; Gymnasium's
            ``max_episode_steps`` is the same setting); decimation: physics steps per env
            step; accel: action scale [m/s^2]; push: largest initial push [m/s]; max_distance:
            horizontal reach around the target [m] (default 0.25 x the surface's bbox diagonal);
            target: (3,) [m] (default :func:`surface_target`); seed: the episodes' random stream
            (default None: fresh entropy, as Gymnasium's first ``reset()`` without a seed;
            ``reset(seed=s)`` sets it too).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP if AutoresetMode is not None else "same-step",
                "render_modes": ["rgb_array"]}

    def __init__(self, num_envs: int = 64, scene=None, device=None, backend: str = "numpy", radius: float = 0.05,
                 max_steps: int | None = None, decimation: int = 4, accel: float = 4.0, push: float = 0.6,
                 max_distance: float | None = None, target=None, seed: int | None = None, render_mode: str | None = None,
                 render_size: tuple[int, int] = (128, 128), max_episode_steps: int | None = None):
        if gym is None:
            raise ImportError("RideSurfaceEnv needs gymnasium >= 1.0: pip install 'dynmesh_warp[rl]'")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        size = tuple(render_size) if np.ndim(render_size) == 1 else ()
        if len(size) != 2 or any(isinstance(v, bool) or int(v) != v or v < 1 for v in size):
            raise ValueError(f"render_size must be (width, height) in pixels, got {render_size!r}")
        self.render_mode, self.render_size = render_mode, (int(size[0]), int(size[1]))
        if max_episode_steps is not None:  # Gymnasium's name (gym.make_vec passes it) for max_steps
            if max_steps is not None and max_steps != max_episode_steps:
                raise ValueError(f"max_steps ({max_steps!r}) and max_episode_steps ({max_episode_steps!r}) are one "
                                 "setting, the episode length: give one (gym.make_vec passes the registered "
                                 f"max_episode_steps, {MAX_STEPS}, unless you give max_episode_steps=N)")
            max_steps = max_episode_steps
        max_steps = MAX_STEPS if max_steps is None else max_steps
        if backend not in ("numpy", "torch"):
            raise ValueError(f"backend must be 'numpy' or 'torch', got {backend!r}")
        if backend == "torch":
            try:
                import torch  # noqa: F401
            except ImportError:
                raise ImportError("RideSurfaceEnv(backend='torch') needs PyTorch (pip install torch); or use "
                                  "backend='numpy'") from None
        for name, value, low in (("num_envs", num_envs, 1), ("max_steps", max_steps, 1), ("decimation", decimation, 1)):
            if isinstance(value, bool) or int(value) != value or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        opt = () if max_distance is None else (("max_distance", max_distance),)
        for name, value in (("radius", radius), ("accel", accel), ("push", push), *opt):
            if not (np.isfinite(value) and value >= (0.0 if name == "push" else 1e-12)):
                raise ValueError(f"{name} must be a finite {'non-negative' if name == 'push' else 'positive'} number, "
                                 f"got {value!r}")
        from .scene import build_model

        cfg, seq = ride_surface_scene(scene)
        self._cfg, self._seq = cfg, seq
        self._camera_state = None  # (key, Gaussians, Renderer, camera) of render_images
        model, _ = build_model(cfg, seq, device)
        self.device = model.device
        self.backend = backend
        V0 = seq.V[0]
        diag = float(np.linalg.norm(V0.max(axis=0) - V0.min(axis=0)))
        if target is not None:  # a new user's bad target failed later, without its name
            t = np.asarray(target, dtype=np.float64) if np.ndim(target) else None
            if t is None or t.shape != (3,) or not np.isfinite(t).all():
                raise ValueError(f"target must be a finite point [x, y, z] [m], got {target!r}")
        self.target = np.asarray(surface_target(V0) if target is None else target, np.float32).reshape(3)
        self.max_distance = float(0.25 * diag if max_distance is None else max_distance)
        self.radius, self.max_steps, self.decimation = float(radius), int(max_steps), int(decimation)
        self.accel, self.push = float(accel), float(push)
        self.top = float(seq.V[..., 2].max()) + 1.0
        gh = model.params.ground_height
        # where a probe finds no surface below, and below which the ball has fallen: the ground,
        # or with none FLOOR_DROP ball radii under the sequence's lowest point (a probe read -1e6
        # there before; at the lowest point itself a ball resting on a flat sheet had "fallen"
        # at its spawn and every step after)
        self.floor = float(seq.V[..., 2].min() - FLOOR_DROP * self.radius if gh is None else gh)
        bm = BatchModel(model.surface, int(num_envs), [self.radius], 1.0, model.params)
        far = np.tile(self.target + np.array([0.0, 0.0, 10.0], np.float32), (1, 1))
        self.world = BatchedWorld(bm, BatchState(bm, far))
        self.num_envs = bm.num_envs
        E, d = self.num_envs, self.device
        self.env_steps = wp.zeros(E, dtype=wp.int32, device=d)
        self.env_episode = wp.zeros(E, dtype=wp.int32, device=d)
        self.obs = wp.zeros((E, OBS_DIM), dtype=float, device=d)
        self.final_obs = wp.zeros((E, OBS_DIM), dtype=float, device=d)
        self.reward = wp.zeros(E, dtype=float, device=d)
        self.terminated = wp.zeros(E, dtype=wp.int32, device=d)
        self.truncated = wp.zeros(E, dtype=wp.int32, device=d)
        self.done = wp.zeros(E, dtype=wp.int32, device=d)
        self.actions = wp.zeros((E, 2), dtype=float, device=d)
        self._all = wp.ones(E, dtype=wp.int32, device=d)
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))):
            raise ValueError(f"seed: one integer for the batch, or None (fresh entropy), got {seed!r}")
        # no seed: fresh entropy, as Gymnasium's reset() without one (every env made without a seed
        # played seed 0's episodes: a new user's unseeded workers collected the same data)
        # each env's seed, set where a seeded reset starts it (a masked one left the others' seed and
        # episode count alone: they had been rewound to replay their first episode; a new user's)
        self.env_seed = wp.full(E, kernel_seed(np.random.SeedSequence().entropy if seed is None else seed),
                                dtype=wp.int32, device=d)
        # bounded where the value is: the contact flag (obs 15) in {0, 1}, the phase's sin and cos
        # (16, 17) in [-1, 1]; positions and velocities unbounded (check_env warned twice of it)
        low, high = np.full(int(OBS_DIM), -np.inf, np.float32), np.full(int(OBS_DIM), np.inf, np.float32)
        low[15:], high[15:] = (0.0, -1.0, -1.0), 1.0
        box = gym.spaces.Box(low, high, (int(OBS_DIM),), np.float32)
        act = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.single_observation_space, self.single_action_space = box, act
        self.observation_space = gym.vector.utils.batch_space(box, E)
        self.action_space = gym.vector.utils.batch_space(act, E)

    # -- device stages ------------------------------------------------------------------------------
    def _reset_envs(self, mask: wp.array):
        m, s = self.world.model, self.world.state
        surf = m.surface
        wp.launch(reset_ball_envs, self.num_envs,
                  inputs=[surf.frames, surf.indices, m.pair_bvh, surf.fps, int(surf.interpolate), m.time_slices,
                          m.spheres_per_env, mask, self.env_seed, wp.vec3(*self.target.tolist()), 0.3 * self.max_distance,
                          self.push, self.top, self.radius],
                  outputs=[s.env_time, s.env_playback, s.sphere_pos, s.sphere_vel, s.sphere_spin, self.env_steps,
                           self.env_episode, self.world.contacts.memory],
                  device=self.device)

    def _evaluate(self, mask: wp.array | None = None):
        """Observation, reward and flags of every env; with ``mask`` the observation of the masked
        envs alone (their first after a reset; the finished step's rewards and flags stay)."""
        m, s = self.world.model, self.world.state
        surf = m.surface
        wp.launch(evaluate_ball_task, self.num_envs,
                  inputs=[surf.frames, surf.indices, m.pair_bvh, surf.fps, int(surf.interpolate), m.time_slices,
                          m.spheres_per_env, self.floor,
                          s.env_time, s.env_playback, s.sphere_pos, s.sphere_vel,
                          self.world.contacts.face, self.actions, self.env_steps,
                          self._all if mask is None else mask, int(mask is not None), wp.vec3(*self.target.tolist()),
                          self.max_distance, 0.5 * self.max_distance / 3.0, self.top, self.radius, self.max_steps],
                  outputs=[self.obs, self.reward, self.terminated, self.truncated], device=self.device)

    def render_images(self, width: int = 64, height: int = 64, gaussians: int = 5000):
        """Camera observations, when asked (issue 16): one RGB image per env, (E, height, width, 3)
        in [0, 1] (torch on the simulation device with ``backend="torch"``, else NumPy), each env's
        Gaussians posed at its own time with its own ball (:func:`render.render_envs`), seen by
        one fixed camera looking at the target from the side and above (the scene's size away).
        The ``gaussians`` Gaussians are generated once on the surface (or bound from the scene's
        ``gaussians.splats``). Call it after ``step``/``reset``; it is not part of the captured step."""
        from .gaussians import gaussians_for_surface
        from .render import Renderer, look_at, render_envs

        key = (int(width), int(height), int(gaussians))
        if self._camera_state is None or self._camera_state[0] != key:
            cfg = self._cfg.model_copy(update={"gaussians": self._cfg.gaussians.model_copy(update={"count": key[2]})})
            g = gaussians_for_surface(self._seq, cfg, self.device)
            V0 = self._seq.V[0]
            diag = float(np.linalg.norm(V0.max(axis=0) - V0.min(axis=0)))
            eye = self.target + diag * np.array([0.9, -0.9, 0.6], np.float32)
            self._camera_state = (key, g, Renderer(self.device), look_at(eye, self.target, width=key[0], height=key[1]))
        _, g, r, cam = self._camera_state
        return self._out(render_envs(self.world, g, cam, renderer=r).rgb)

    def render(self):
        """With ``render_mode="rgb_array"``: every env's camera image (:meth:`render_images` at
        ``render_size``, default 128 x 128) as (E, height, width, 3) uint8 NumPy; else None."""
        if self.render_mode != "rgb_array":
            return None
        rgb = self.render_images(*self.render_size)
        rgb = rgb.detach().cpu().numpy() if hasattr(rgb, "detach") else rgb
        return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)

    def _out(self, a: wp.array):
        if self.backend == "torch":
            return wp.to_torch(a)
        return a.numpy().copy()

    # -- the Gymnasium API ---------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start a new episode in every env, or with ``options={"reset_mask": m}`` ((E,) booleans,
        Gymnasium's vector API) in the envs where ``m`` is true (the others go on). ``seed``
        makes the phases, spawn points and pushes reproducible. Returns (obs (E, 18), info {})."""
        self._check_open()
        mask = self._all
        unknown = set(options or {}) - {"reset_mask"}
        if unknown:  # a typo was ignored and every env reset
            raise ValueError(f"reset options: unknown {sorted(unknown)}; the one option is 'reset_mask'")
        if options and options.get("reset_mask") is not None:
            m = options["reset_mask"]
            m = m.detach().cpu().numpy() if hasattr(m, "detach") else np.asarray(m)
            if m.dtype != bool or m.shape != (self.num_envs,):
                raise ValueError(f"reset_mask: expected ({self.num_envs},) booleans, one per env, got "
                                 f"{m.dtype} {m.shape}")
            if not getattr(self, "_was_reset", False) and not m.all():
                raise RuntimeError("RideSurfaceEnv: the first reset() starts every env (reset_mask all true)")
            mask = wp.array(m.astype(np.int32), dtype=wp.int32, device=self.device)
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
                raise ValueError(f"seed: one integer for the batch (each env draws its own stream from it and its "
                                 f"index), got {seed!r}")
            # the envs it starts take the seed (Gymnasium's vector API seeds the masked envs only)
            wp.launch(reset_env_streams, self.num_envs, inputs=[mask, kernel_seed(seed)],
                      outputs=[self.env_seed, self.env_episode], device=self.device)
        # the vector env's own np_random, as Gymnasium's VectorEnv.reset seeds it (a negative seed, which
        # Gymnasium refuses and the envs take, seeds it with its mixed form)
        super().reset(seed=None if seed is None else int(seed) if seed >= 0 else kernel_seed(seed))
        self.actions.zero_()
        self._reset_envs(mask)
        self._evaluate(mask)  # the episodes' first observations (in contact: 0)
        self._was_reset = True
        return self._out(self.obs), {}

    def step(self, actions):
        """Apply the actions (E, 2), take ``decimation`` physics steps, and return (obs, reward,
        terminated, truncated, info); finished envs are reset in the same step."""
        self._check_open()
        if not getattr(self, "_was_reset", False):  # Gymnasium's contract; the envs held their far-away start
            raise RuntimeError("RideSurfaceEnv: call reset() before the first step()")
        E = self.num_envs
        shape = tuple(actions.shape) if hasattr(actions, "shape") else np.shape(actions)
        if shape != (E, 2):
            raise ValueError(f"actions must have shape ({E}, 2) (one (x, y) per env), got {shape}")
        if np.iscomplexobj(actions) if not hasattr(actions, "detach") else actions.is_complex():
            raise ValueError(f"actions must be real numbers, got complex {getattr(actions, 'dtype', '')}".rstrip())
        if self.backend == "torch" and hasattr(actions, "detach"):  # a tensor (a list or array: the NumPy path)
            # no host check here (it would wait for the device every step): a non-finite action
            # counts as 0 (kernels/envs.py: applied_action)
            wp.copy(self.actions, wp.from_torch(actions.detach().to(dtype=__import__("torch").float32).contiguous()))
        else:
            a = np.asarray(actions, np.float64)  # checked before the cast: 1e40 is finite, not inf
            if not np.isfinite(a).all():
                bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
                # one env (gymnasium's single env, a batch of one): no env index it never made
                raise ValueError("the action is NaN or infinite" if E == 1 else
                                 f"actions of env(s) {bad[:8].tolist()} are NaN or infinite")
            self.actions.assign(np.clip(a, -1.0, 1.0).astype(np.float32))  # as applied_action takes them
        w = self.world
        wp.launch(apply_env_actions, self.num_envs,
                  inputs=[w.model.spheres_per_env, self.actions, self.accel, self.decimation * w.dt],
                  outputs=[w.state.sphere_vel], device=self.device)
        for _ in range(self.decimation):
            w.step()
        wp.launch(count_env_steps, self.num_envs, outputs=[self.env_steps], device=self.device)
        self._evaluate()
        wp.copy(self.final_obs, self.obs)
        wp.launch(combine_env_flags, self.num_envs, inputs=[self.terminated, self.truncated], outputs=[self.done],
                  device=self.device)
        self._reset_envs(self.done)
        self._evaluate(self.done)
        done = self._out(self.done)
        ended = done.astype(bool) if self.backend == "numpy" else done.bool()
        # Gymnasium's same-step keys, as its SyncVectorEnv gives them: the finished envs' last
        # observations and their last step's info (this env's step info is empty, so an empty dict)
        info = {"final_obs": self._out(self.final_obs), "_final_obs": ended,
                "final_info": {}, "_final_info": ended.clone() if self.backend == "torch" else ended.copy()}
        term, trunc = self._out(self.terminated), self._out(self.truncated)
        if self.backend == "numpy":
            return self._out(self.obs), self._out(self.reward), term.astype(bool), trunc.astype(bool), info
        return wp.to_torch(self.obs), wp.to_torch(self.reward), term.bool(), trunc.bool(), info

    def close(self, **kwargs):
        """Release the env; ``reset`` and ``step`` refuse afterwards, and ``closed`` is True
        (Gymnasium's ``VectorEnv.closed``)."""
        self.closed = True
        self._camera_state = None

    def _check_open(self):
        if getattr(self, "closed", False):
            raise RuntimeError("RideSurfaceEnv: the env is closed")


class RideSurfaceSingleEnv(gym.Env if gym is not None else object):
    """The same task as one ``gymnasium.Env`` (what Stable-Baselines3's ``check_env``, Gymnasium's
    wrappers and most single-env code expect): a :class:`RideSurfaceEnv` of one env underneath,
    so the physics, observation, reward and flags are the batch's, step for step.

    Unlike the vector env there is no autoreset: a step that ends the episode returns its last
    observation, and ``reset()`` starts the next (a ``step`` before it is refused).
    ``render_mode="rgb_array"``: ``render()`` returns the env's camera image
    (:meth:`RideSurfaceEnv.render_images`) as (``render_size``) uint8 RGB. Every other keyword
    argument is :class:`RideSurfaceEnv`'s (``scene``, ``device``, ``radius``, ``max_steps``, ...).
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, render_mode: str | None = None, render_size: tuple[int, int] = (128, 128), **kwargs):
        if gym is None:
            raise ImportError("RideSurfaceSingleEnv needs gymnasium >= 1.0: pip install 'dynmesh_warp[rl]'")
        taken = sorted({"num_envs", "backend"} & set(kwargs))
        if taken:
            raise ValueError(f"RideSurfaceSingleEnv: {taken[0]} is fixed for one env (use RideSurfaceEnv for a batch)")
        self.vector_env = RideSurfaceEnv(num_envs=1, backend="numpy", render_mode=render_mode, render_size=render_size,
                                         **kwargs)
        self.observation_space = self.vector_env.single_observation_space
        self.action_space = self.vector_env.single_action_space
        self.render_mode, self.render_size = self.vector_env.render_mode, self.vector_env.render_size
        v = self.vector_env
        self.metadata = {**self.metadata, "render_fps": 1.0 / (v.decimation * v.world.dt)}
        self._ended = True  # reset() first

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode; ``seed`` makes it reproducible (as the vector env's). Returns (obs (18,), {})."""
        super().reset(seed=seed)
        if options:
            raise ValueError(f"reset options: RideSurfaceSingleEnv takes none, got {sorted(options)}")
        obs, _ = self.vector_env.reset(seed=seed)
        self._ended = False
        return obs[0], {}

    def step(self, action):
        """Apply the action (2,) and take ``decimation`` physics steps: (obs, reward, terminated,
        truncated, info)."""
        if self._ended:
            raise RuntimeError("RideSurfaceSingleEnv: the episode has ended (or not begun); call reset()")
        shape = np.shape(action)
        if shape != (2,):
            raise ValueError(f"action must have shape (2,) (a horizontal (x, y) push), got {shape}")
        obs, reward, term, trunc, info = self.vector_env.step(np.asarray(action, np.float64)[None])
        self._ended = bool(term[0] or trunc[0])
        if self._ended:  # the vector env has already started the next episode; its last observation:
            obs = info["final_obs"]
        return obs[0], float(reward[0]), bool(term[0]), bool(trunc[0]), {}

    def render(self):
        """The env's camera image, (height, width, 3) uint8, with ``render_mode="rgb_array"``; else None."""
        rgb = self.vector_env.render()
        return None if rgb is None else rgb[0]

    def close(self):
        self.vector_env.close()


def make_single_env(**kwargs) -> RideSurfaceSingleEnv:
    """``gym.make(ENV_ID, ...)``'s entry point: a :class:`RideSurfaceSingleEnv` whose episodes end
    where Gymnasium's TimeLimit ends them (``max_episode_steps``: ``MAX_STEPS`` as registered, or
    the one given to ``gym.make``; -1 none). Its own limit is off: at 500 it cut
    ``gym.make(..., max_episode_steps=700)``'s episodes at 500 (a new user's)."""
    if "max_steps" in kwargs:
        raise ValueError(f"gym.make({ENV_ID!r}): give the episode length as max_episode_steps="
                         f"{kwargs['max_steps']!r} (Gymnasium's TimeLimit ends gym.make's episodes), not max_steps")
    return RideSurfaceSingleEnv(max_steps=NO_STEP_LIMIT, **kwargs)


make_single_env.metadata = RideSurfaceSingleEnv.metadata
#: the episode length of an env whose episodes a wrapper ends (``make_single_env``) [env steps]
NO_STEP_LIMIT = 2**31 - 1

if gym is not None and ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=f"{__name__}:make_single_env", vector_entry_point=f"{__name__}:RideSurfaceEnv",
                 max_episode_steps=MAX_STEPS)

