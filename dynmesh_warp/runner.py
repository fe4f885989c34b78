"""The one runner of both engines (issue 13): warm-up and capture, the timed loop, samples,
checkpoints, stops and the atomic outputs of ``python -m dynmesh_warp.run``.

It drives any :class:`~dynmesh_warp.runtime.Simulation` — the built-in ``World`` or Newton's
``NewtonWorld`` — through what the protocol offers: ``step``, ``capture``, ``sample`` (the
arrays of ``trajectories.npz``), ``contact_count``, ``run_summary`` and ``run_line`` (what the
engine adds to ``summary.json`` and the log line), and, where ``checkpointable``,
``checkpoint_state``. The run's own fields (steps, timing, interruption, checkpoint, contacts
per sample) are written here once for both.

Warm-up, the same for both engines: one eager step (it loads, on a cold cache compiles, exactly
the Warp modules the step uses), then ``capture()`` (a CUDA graph of one step where the engine
uses one; nothing on the CPU). The first sample is the state after that step (step 1); the
timed loop starts there.
"""

from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np
import warp as wp

from .checkpoint import CHECKPOINT_NAME, CheckpointError, save_checkpoint
from .runtime import NonFiniteStateError, rate_text, steps_per_second, timed_loop

__all__ = ["run_simulation"]


def _link_or_copy(src: Path, dst: Path) -> None:
    """``dst`` as a hard link of ``src`` (same folder tree), else a copy."""
    import os
    import shutil

    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _check_finite(sample: dict, sim, step: int, every: int, out) -> None:
    """The first non-finite row of any sampled array, as a NonFiniteStateError naming it."""
    for name, a in sample.items():
        a = np.asarray(a)
        if a.ndim == 0 or a.dtype.kind != "f" or a.size == 0:  # no bodies (spheres.count 0): nothing to check
            continue
        rows = a.reshape(a.shape[0], -1)
        bad = np.flatnonzero(~np.isfinite(rows).all(axis=1))
        if bad.size:
            i = int(bad[0])
            raise NonFiniteStateError(
                f"{sim.body_noun} {i} has a non-finite state at step {step} (t = {sim.time:.4g} s; checked every "
                f"run.record_every = {every} steps): {name} {rows[i].tolist()}"
                f"{f' ({bad.size} {sim.body_noun}s)' if bad.size > 1 else ''}; stopped, {out} keeps its previous "
                "contents")


def run_simulation(sim, cfg, *, steps: int, out: Path, t_build: float, progress: bool = True, log=print,
                   overwrite: bool | str = "ours", stop=None, checkpoint_every: int = 0, ckpt=None) -> dict:
    """Warm up, run ``sim`` to ``steps`` steps, write ``trajectories.npz`` and ``summary.json``
    atomically into ``out`` (checked by the caller before the work) and return the summary.

    ``t_build``: ``time.perf_counter()`` when building began (the summary's
    ``setup_and_compile_s`` runs from there to the end of the warm-up). ``checkpoint_every`` /
    ``ckpt`` (a restored :class:`~dynmesh_warp.checkpoint.Checkpoint`) need a checkpointable
    simulation; ``stop``: a callable checked between steps, see
    :func:`dynmesh_warp.run.run_scene`."""
    from .cli import checking_stops
    from .outputs import MANIFEST, OutputFolder, OutputKind, add_to_manifest, atomic_write_json, atomic_write_npz, entries

    every = int(checkpoint_every or 0)
    # the output folder as the caller checked it: what appears in it during the run is not replaced
    # (OutputFolder's checked); this run's own checkpoint (and the manifest listing it) excepted
    checked = entries(out) | ({CHECKPOINT_NAME, MANIFEST} if (every or ckpt is not None) else set())
    if (every or ckpt is not None) and not sim.checkpointable:
        raise CheckpointError(f"checkpoints: not available for this simulation ({type(sim).__name__})")
    rec = cfg.run.record_every
    times: list[float] = []
    samples: dict[str, list] = {}
    contact_samples, start = 0, 0
    if ckpt is not None:
        ckpt.check_record_every(rec)
        ckpt.restore(sim)  # checked against the scene first (CheckpointError naming the field)
        times = list(ckpt.times)
        samples = {"position": list(ckpt.positions), "velocity": list(ckpt.velocities)}
        contact_samples, start = ckpt.contact_samples, ckpt.step
    marks = {"record": None, "checkpoint": None}  # the last step recorded / checkpointed

    def step_now() -> int:
        return sim.substep_count // sim.substeps  # steps since the run's start (restored on resume)

    def record(count_contacts: bool = True):
        nonlocal contact_samples
        sample = sim.sample()
        marks["record"] = step_now()
        _check_finite(sample, sim, marks["record"], rec, out)
        times.append(sim.time)
        for k, v in sample.items():
            samples.setdefault(k, []).append(v)
        if count_contacts:
            contact_samples += sim.contact_count()

    def checkpoint(step: int):
        st = sim.checkpoint_state()
        if not (np.isfinite(st["sphere_pos"]).all() and np.isfinite(st["sphere_vel"]).all()):
            raise NonFiniteStateError(f"non-finite sphere state at step {step}: no checkpoint written there; "
                                      f"{out / CHECKPOINT_NAME} keeps the last good one")
        out.mkdir(parents=True, exist_ok=True)
        # a checkpointable simulation samples "position" and "velocity" (the checkpoint's layout)
        save_checkpoint(out / CHECKPOINT_NAME, sim, scene=cfg.name, step=step, steps=steps,
                        checkpoint_every=every, contact_samples=contact_samples, times=times,
                        positions=samples["position"], velocities=samples["velocity"], record_every=rec)
        add_to_manifest(out, CHECKPOINT_NAME, holds=OutputKind.RUN)
        marks["checkpoint"] = step

    # the samples are the states at steps 0, rec, 2 rec, ... and the last step: a new run's first
    # is the scene's initial state (it had none, and the samples ran 1, 1 + rec, ...; a new user)
    if ckpt is None:
        record(count_contacts=False)
    # warm-up: one eager step (loads the step's modules), then the graph capture, outside the
    # timed loop
    sim.step()
    sim.capture()
    wp.synchronize_device(sim.device)
    build_s = time.perf_counter() - t_build
    first = start + 1
    with checking_stops():  # a signal from here on stops at a step boundary (cli.py)
        if first % rec == 0:
            record()
        if every and first % every == 0:
            checkpoint(first)
        sim_s, reached = timed_loop(sim, steps, rec, record, progress, start=first, origin=0,
                                    stop=stop, checkpoint_every=every, checkpoint=checkpoint)
        if first == steps and marks["record"] != steps:
            record()  # a one-step run (or a resume one step short of the end): its final sample
        reason = stop() if (stop is not None and reached < steps) else None
        if reason:  # stopped early: a checkpoint there (when checkpointing), then the final sample
            if every and marks["checkpoint"] != reached:
                checkpoint(reached)
            if marks["record"] != reached:
                record()
        timed_steps = reached - first  # the first step (compile, graph capture) is not timed
        sps = steps_per_second(timed_steps, sim_s)
        summary = {
            "scene": cfg.name,
            "device": str(sim.device),
            "device_name": sim.device.name if sim.device.is_cuda else (platform.processor() or platform.machine()),
            "cuda_graph": bool(sim.use_graph),
            "dt": sim.dt,
            "substeps": sim.substeps,
            "steps": steps,
            "step_reached": reached,
            "interrupted": bool(reason),
            "interrupted_by": (reason if isinstance(reason, str) else "stop()") if reason else None,
            "resumed_from": {"checkpoint": str(ckpt.path), "step": start} if ckpt is not None else None,
            "checkpoint": ({"file": CHECKPOINT_NAME, "step": marks["checkpoint"], "every": every}
                           if marks["checkpoint"] is not None else None),
            "sim_time_s": sim.time,
            "setup_and_compile_s": build_s,
            "timed_steps": timed_steps,
            "timed_wall_s": sim_s,
            "steps_per_second": sps,
            "env_steps_per_second": None if sps is None else sps * sim.num_envs,
            "contacts": {
                "in_contact_final": sim.contact_count(),
                "contact_samples": contact_samples,
                "samples": len(times) - 1,
            },
            **sim.run_summary(),  # the engine's fields: collider or solver, surface, bodies, final state
        }
        summary["surface"] = {"source": cfg.surface.source, **summary.get("surface", {})}
        arrays = {k: np.asarray(v) for k, v in samples.items()}
        arrays.update(sim.trajectory_constants())
        # an interrupted run without checkpoints never replaces an earlier output (it goes beside
        # it, <out>.partial); with them, it stays where its checkpoint is (to resume from there)
        folder = OutputFolder(out, overwrite=bool(overwrite), checked=checked, holds=OutputKind.RUN,
                              interrupted=bool(reason) and marks["checkpoint"] is None and ckpt is None)
        with folder as tmp:
            atomic_write_npz(tmp / "trajectories.npz", time=np.asarray(times), **arrays)
            atomic_write_json(tmp / "summary.json", summary)
            if marks["checkpoint"] is not None:  # the latest checkpoint stays with the outputs
                _link_or_copy(out / CHECKPOINT_NAME, tmp / CHECKPOINT_NAME)
    if folder.written != folder.path:
        import sys

        why = ("holds an earlier output, which an interrupted run does not replace" if folder.beside == "partial" else
               "gained files during the run (another run's output, or files of the names this run writes)")
        print(f"warning: {out} {why}: kept as it is; this run's outputs are in {folder.written}", file=sys.stderr)
        out = folder.written
    summary["output"] = str(out)
    if reason:
        return summary  # the CLI says what was written (one line on stderr)
    label, tail = sim.run_line()
    envs = f"{sps * sim.num_envs:,.0f} env-steps/s; " if (sps is not None and sim.num_envs > 1) else ""
    log(f"{cfg.name}: {steps} steps on {summary['device']} ({label}{', CUDA graph' if sim.use_graph else ''}): "
        + rate_text(sps) + envs + f"{tail}; outputs in {out}")
    if not summary["final"]["finite"]:
        log(f"WARNING: non-finite {sim.body_noun} state at the end of the run")
    bound = getattr(getattr(cfg, "physics", None), "max_substeps", None)
    fast = fast_sphere_note(arrays, sim.dt, int(sim.substeps), bound) if sim.body_noun == "sphere" else ""
    if fast:
        log(fast)
    return summary


def fast_sphere_note(arrays: dict, dt: float, substeps: int, max_substeps: int | None = None) -> str:
    """A note when a sampled sphere moved farther than its radius in one sub-step (``arrays``: the
    run's ``trajectories.npz`` arrays, ``velocity`` (samples, S, 3) [m/s] and ``radius`` (S,) [m];
    ``dt`` [s] the step of ``substeps`` sub-steps): a contact is the sphere's nearest surface, so
    where another surface lies within a sub-step's travel (a floor and a wall, two close walls)
    the sphere can pass through that one (docs/physics.md, "Why spheres do not tunnel"; a new
    user's sphere sliding on a floor at 30 m/s went through a wall, r = 0.05 m at dt 1/240).
    ``max_substeps``: the scene's work bound, named too where the sub-steps said exceed it (the
    note's 84 was refused by the default 64). "" when none did."""
    v, r = arrays.get("velocity"), arrays.get("radius")
    if v is None or r is None or not np.size(v) or dt <= 0:
        return ""
    speed = np.linalg.norm(np.asarray(v, np.float64), axis=-1).reshape(len(v), -1).max(axis=0)  # per sphere
    r = np.asarray(r, np.float64).reshape(-1)
    if r.size not in (1, speed.size):
        return ""
    reach = speed * (dt / max(1, substeps)) / np.maximum(r, 1e-12)
    i = int(np.argmax(reach))
    if reach[i] <= 1.0:
        return ""
    need = max(1, substeps) * int(np.ceil(reach[i]))
    over = (f" --set physics.max_substeps={need} (its bound, {max_substeps}, is lower)"
            if max_substeps is not None and need > max_substeps else "")
    return (f"note: {int(np.count_nonzero(reach > 1.0))} sphere(s) moved farther than their radius in one sub-step "
            f"(sphere {i}: {speed[i]:.3g} m/s, {reach[i]:.1f} radii a sub-step): a sphere's contact is its nearest "
            "surface, so where another surface lies within that travel (a floor and a wall, two close walls) it can "
            f"pass through it; --set physics.substeps={need}{over} keeps it within one radius "
            "(docs/physics.md#why-spheres-do-not-tunnel)")
