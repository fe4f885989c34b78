"""What every runner needs, below the CLIs and the engines: the device a scene runs on, the
number of steps of a run and its work budget, the run's output folder checked before the work,
and the timed stepping loop with its rate (shared by the built-in world and the Newton path).

Layer: above the schema (config), outputs and the world; below the engines' runners
(``run``, ``newton_adapter``, ``viewer``). Imports nothing above it (docs/architecture.md).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import warp as wp

from .config import SceneConfig, SceneError

__all__ = ["Simulation", "free_bytes", "resolve_device", "scene_device", "run_steps", "check_total_work", "lift_work_limits",
           "NonFiniteStateError", "RUN_OUTPUTS", "check_run_output", "check_record_output", "timed_loop",
           "steps_per_second", "rate_text"]


@runtime_checkable
class Simulation(Protocol):
    """What runners and the viewer read of a simulation, built-in (``world.World``) or Newton
    (``newton_adapter.NewtonWorld``): one protocol, so neither needs a stand-in for the other.

    Attributes:
        device: the Warp device; surface: the deforming surface (``world.SurfaceModel``);
        t0: start time [s]; time: simulation time [s] (host twin of the device clock);
        dt: physics step [s]; substeps: sub-steps per step; substep_count: sub-steps taken;
        use_graph: whether steps replay a captured CUDA graph; editable: whether ``reset``,
        ``set_time`` and ``add_spheres`` exist (the built-in world; a Newton world's bodies are
        Newton's); checkpointable: whether ``checkpoint_state`` exists (the built-in world);
        body_noun: what a row of the sampled arrays is ("sphere", "body"), for messages;
        num_envs: environments stepped together (1 but for ``batch.BatchedWorld``).

    The runner (``runner.run_simulation``) reads only this protocol: ``step``, ``capture``,
    ``sample``, ``trajectory_constants``, ``contact_count``, ``run_summary``, ``run_line``.
    """

    device: object
    surface: object
    t0: float
    substeps: int
    substep_count: int
    use_graph: bool
    editable: bool
    checkpointable: bool
    body_noun: str
    num_envs: int

    @property
    def time(self) -> float: ...

    @property
    def dt(self) -> float: ...

    def step(self) -> None:
        """Advance by one physics step (eager the first time; then a captured graph where
        ``use_graph``)."""

    def capture(self) -> None:
        """Capture one step as a CUDA graph (nothing without ``use_graph``); advances nothing.
        Called after one eager step, which loaded the step's modules."""

    def sample(self) -> dict:
        """The arrays of one trajectory sample (host copies; rows = bodies)."""

    def trajectory_constants(self) -> dict:
        """Arrays stored once next to the samples (e.g. sphere radii)."""

    def contact_count(self) -> int:
        """Contacts now (spheres in contact; Newton's rigid contacts)."""

    def run_summary(self) -> dict:
        """The engine's fields of a run's summary (collider or solver, surface, bodies, and
        ``final`` with a ``finite`` flag)."""

    def run_line(self) -> tuple[str, str]:
        """(engine label, result) for the run's log line."""

    def surface_points(self):
        """The surface's vertex buffer (N,) wp.vec3 [m] at ``time`` (brought up to date)."""

    def surface_indices(self):
        """The surface's triangle indices (3M,) wp.int32."""

    def sphere_positions(self) -> np.ndarray:
        """(S, 3) built-in sphere centres [m] (S = 0 for a Newton world)."""

    def rigid_shapes(self) -> list:
        """Rigid shapes other than the built-in spheres, for rendering (``render.RigidShapes``):
        one dict per shape with ``type`` (``sphere`` | ``box`` | ``capsule`` | ``cylinder`` |
        ``ellipsoid`` | ``mesh`` | ...), ``scale`` (3,) [m], ``pose`` (7,) world position [m] and
        quaternion (x, y, z, w), mesh shapes also ``vertices`` (N, 3) and ``indices`` (M, 3);
        empty for the built-in world (its bodies are the spheres)."""

    def sphere_radii(self) -> np.ndarray:
        """(S,) built-in sphere radii [m]."""


def scene_device(cfg: SceneConfig, device=None, given_as: str = "--device"):
    """The device a scene runs on: ``device`` (the CLI's --device, or a library call's argument:
    ``given_as`` names it) if given, else the scene's ``device`` field, else Warp's default; a
    :class:`SceneError` names whichever is unavailable."""
    return resolve_device(device, given_as) if device else resolve_device(cfg.device, "device")


def resolve_device(name, field: str = "device"):
    """``wp.get_device(name)``, with a :class:`SceneError` naming ``field`` when the device
    does not exist here (e.g. ``cuda`` on a machine without a GPU)."""
    try:
        if isinstance(name, str) and name.startswith("cuda") and not wp.is_cuda_available():
            raise RuntimeError("no CUDA device or driver on this machine")  # before Warp's native errors
        return wp.get_device(name)
    except (RuntimeError, ValueError) as e:
        have = ", ".join(str(d) for d in wp.get_devices())
        raise SceneError(f"{field} {name!r}: not available here ({e}); devices here: {have}") from None


def run_steps(cfg, duration: float | None = None) -> int:
    """Physics steps of a run: ``duration`` (the CLI's --duration) / physics.dt, else run.steps,
    else run.duration / physics.dt."""
    if duration is None and cfg.run.steps:
        return int(cfg.run.steps)
    d = cfg.run.duration if duration is None else duration
    return max(1, int(round(d / cfg.physics.dt)))


def check_total_work(cfg, steps: int, substeps: int) -> None:
    """Refuse a run of more than ``run.max_total_substeps`` sub-steps (steps x sub-steps), naming
    the step count, what it comes from and the values that would fit."""
    from .world import WorkBudgetError

    cap = cfg.run.max_total_substeps
    total = int(steps) * int(substeps)
    if cap is None or total <= cap:
        return
    dt = cfg.physics.dt
    fit_steps = max(1, cap // max(int(substeps), 1))
    raise WorkBudgetError(
        f"work budget: {steps:,} steps x {substeps:,} sub-steps = {total:.3g} sub-steps, over "
        f"run.max_total_substeps {cap:.3g}; {steps * dt:.3g} s of simulated time at physics.dt {dt:.3g} s. "
        f"Fits with: at most {fit_steps:,} steps (--steps, run.steps, or a duration <= {fit_steps * dt:.3g} s), "
        f"or physics.dt >= {steps * dt / fit_steps:.3g} s; or raise run.max_total_substeps "
        "(--no-work-limit lifts the bounds)")


def lift_work_limits(cfg) -> None:
    """``--no-work-limit``: no bound on sub-steps per step or per run."""
    cfg.physics.max_substeps = None
    cfg.run.max_total_substeps = None


class NonFiniteStateError(RuntimeError):
    """The simulation produced NaN/inf; the message names the sphere and the step."""


#: what a run writes into its output folder
RUN_OUTPUTS = ("summary.json", "trajectories.npz", "checkpoint.npz")


def check_run_output(cfg, output=None, overwrite: bool | str = "ours", what: str | None = None,
                     resume=None) -> Path:
    """The run's output folder (``output``, else ``run.output``), checked before the work: not an
    input of the scene, a folder, creatable and writable, existing only with ``overwrite``.
    Resuming from the checkpoint inside it continues that run: the folder may then be replaced
    without ``overwrite`` when everything in it was written by this tool."""
    from .outputs import OutputExistsError, OutputKind, _real, check_output, foreign_entries

    path = cfg.output_path(output)
    what = what or ("--output" if output else "run.output")
    if resume is not None and not overwrite and _real(resume).parent == _real(path) and Path(path).is_dir():
        foreign = foreign_entries(_real(path))
        if foreign:
            raise OutputExistsError(f"{what} {path}: holds {foreign[0]}, which this tool did not write; add "
                                    "--overwrite to resume into it (files this tool did not write are kept)")
        overwrite = "ours"
    check_output(path, kind="folder", what=what, inputs=cfg.inputs(), overwrite=overwrite, writes=RUN_OUTPUTS,
                 holds=OutputKind.RUN)
    return path


def check_record_output(cfg, record, overwrite: bool) -> None:
    """``--record OUT.viser`` and the ``OUT.html`` next to it, checked before the work."""
    from .outputs import OutputKind, check_output

    check_output(record, kind="file", what="--record", inputs=cfg.inputs(), overwrite=overwrite,
                 suffixes={".viser"}, holds=OutputKind.RUN)
    check_output(Path(record).with_suffix(".html"), kind="file", what="--record (its .html page)",
                 inputs=cfg.inputs(), overwrite=overwrite, holds=OutputKind.RUN)


def timed_loop(world, steps: int, every: int, record, progress: bool, *, start: int = 0, origin: int | None = None,
               stop=None, checkpoint_every: int = 0, checkpoint=None, chunk_s: float = 0.05) -> tuple[float, int]:
    """Step ``world`` from step ``start`` to step ``steps`` (steps counted from the start of the
    run) with a progress bar. ``record()`` runs after every step ``s`` with ``(s - origin) %
    every == 0`` (``origin`` defaults to ``start``) and after the last; ``checkpoint(s)`` after
    every multiple of ``checkpoint_every`` (after that step's sample, before a last-step-only
    one). ``stop()`` is checked between chunks of about ``chunk_s`` wall seconds of steps and at
    those boundaries: once true the loop ends there. Returns (wall seconds of the steps alone,
    device synchronised, recording excluded; the step reached). The loop of
    ``runner.run_simulation``, for both engines."""
    import warp as wp

    origin = start if origin is None else origin
    try:
        from tqdm import tqdm

        bar = tqdm(total=steps - start, unit="step", disable=not progress, file=sys.stderr, dynamic_ncols=True)
    except ImportError:  # pragma: no cover
        bar = None
    sim_s, s, chunk = 0.0, start, 1
    stopped = False
    while s < steps and not stopped:
        nxt = min(s + every - (s - origin) % every, steps)  # the next sample
        if checkpoint_every:
            nxt = min(nxt, (s // checkpoint_every + 1) * checkpoint_every)
        while s < nxt:
            n = min(chunk, nxt - s)
            t0 = time.perf_counter()
            for _ in range(n):
                world.step()
            wp.synchronize_device(world.device)
            dt = time.perf_counter() - t0
            sim_s += dt
            s += n
            if bar is not None:
                bar.update(n)
            # chunks of about chunk_s: a stop is seen within that (at most doubling per chunk)
            chunk = max(1, min(2 * n, int(n * chunk_s / dt) if dt > 0 else 2 * n))
            if s < nxt and stop is not None and stop():
                stopped = True
                break
        if stopped:
            break
        regular = (s - origin) % every == 0
        if regular:
            record()
        if checkpoint_every and checkpoint is not None and s % checkpoint_every == 0:
            checkpoint(s)
        if s == steps and not regular:
            record()
        if s < steps and stop is not None and stop():
            break
    if bar is not None:
        bar.close()
    return sim_s, s


def steps_per_second(timed_steps: int, wall_s: float) -> float | None:
    """Rate of the timed steps; None (null in summary.json) when nothing was timed."""
    return timed_steps / wall_s if timed_steps > 0 and wall_s > 0 else None


def rate_text(sps: float | None) -> str:
    return f"{sps:,.0f} steps/s; " if sps is not None else "too few steps to time; "


def free_bytes(device=None) -> int:
    """Free memory [bytes] of ``device`` (a Warp device; None: the host): the GPU's, or the host's
    available physical memory; 0 where it cannot be told (no check then)."""
    import os

    try:
        if device is not None and device.is_cuda:
            return int(device.free_memory)
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return 0

