"""Run a scene headless (or with a viewer): ``python -m dynmesh_warp.run [scene.yaml]``.

With no scene file the built-in default scene runs (a deforming bowl with five spheres).
Writes ``trajectories.npz`` and ``summary.json`` (atomically) to the output folder and prints
steps/s. ``--checkpoint-every N`` also keeps ``checkpoint.npz`` there (every N steps), which
``--resume`` continues from. Ctrl-C or SIGTERM stops at the next step and writes what was done
(``"interrupted": true``; docs/scene.md#interrupted-runs).
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
import warnings
from pathlib import Path


from .cli import interruptible_main
from .config import NEWTON_IGNORES, say_sequence_scene, scene_source
from .runtime import (
    NonFiniteStateError,
    check_record_output,
    check_run_output,
    check_total_work,
    lift_work_limits,
    run_steps,
)

__all__ = ["main", "run_scene"]


def _parser() -> argparse.ArgumentParser:
    from .choices import DEFAULT_COLLIDER, DEFAULT_REBUILD_EVERY, Collider, RebuildEvery, values
    from .cli import Parser
    from .viewer import SPLAT_GROUPS

    p = Parser(prog="python -m dynmesh_warp.run", description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", help="scene YAML file (default: the built-in default scene); or a mesh "
                   "sequence (.npz, .anime, .pc2, .mdd, an animated .glb/.gltf, one mesh file, "
                   "a folder of frames), played with spheres dropped on it")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE", dest="overrides",
                   help="override a scene field (YAML value), e.g. --set physics.dt=0.002 --set spheres.count=20; "
                        "repeatable, applied before validation")
    p.add_argument("--device", help="Warp device: cpu, cuda, cuda:0 (default: scene's, else Warp's default)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--duration", type=float, help="simulated seconds (overrides run.duration)")
    g.add_argument("--steps", type=int, help="number of physics steps (overrides run.duration/steps)")
    p.add_argument("--collider", choices=values(Collider),
                   help=f"{DEFAULT_COLLIDER} (default): the faster of swept and refit, timed on the scene's first 2 s "
                        "(interpolation on; else refit); refit: refit one BVH every step; "
                        "swept: refit swept bounds once per frame; rebuild: new BVH (varying-topology baseline)")
    p.add_argument("--rebuild-every", choices=values(RebuildEvery),
                   help=f"for --collider rebuild (default {DEFAULT_REBUILD_EVERY})")
    p.add_argument("--viewer", choices=["viser", "none"], default=None,
                   help="viser: live viewer (default when stdin and stdout are a terminal); none: headless")
    p.add_argument("--port", type=int, default=8080, help="viewer port (0: any free port)")
    p.add_argument("--host", default="127.0.0.1", help="viewer address to listen on (0.0.0.0: all)")
    p.add_argument("--record", metavar="OUT.viser",
                   help="save a replayable viser recording and a self-contained OUT.html next to it")
    p.add_argument("--splat-groups", type=int, metavar="K", default=None,
                   help="viewer/--record: send the splats once and then only the poses of K rigidly moving "
                        f"groups per frame (default {SPLAT_GROUPS}; more: closer to the surface, more bytes); 0: the "
                        "whole splat buffer every frame (docs/rendering.md)")
    p.add_argument("--view-envs", metavar="LIST",
                   help="batched envs in the viewer/--record: the envs shown, e.g. 3 (that env) or 0,1,2,3 or 0-8 "
                        "(side by side in a grid); default: env 0")
    p.add_argument("--envs", type=int, metavar="N",
                   help="run N batched environments on the shared surface, each at its own clock "
                        "(overrides envs.count; prints env-steps/s; docs/envs.md)")
    p.add_argument("--output", help="output folder (overrides run.output)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing outputs (only files this tool wrote; other files are kept)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("--no-work-limit", action="store_true",
                   help="lift the work budget (physics.max_substeps, run.max_total_substeps)")
    p.add_argument("--checkpoint-every", type=int, metavar="N",
                   help="write OUTPUT/checkpoint.npz every N steps and where an interrupted run stops "
                        "(0: none; with --resume: the checkpoint's interval)")
    p.add_argument("--resume", metavar="CHECKPOINT",
                   help="continue the run from a checkpoint.npz (same scene and options); the trajectory "
                        "is the uninterrupted run's (bit for bit on the CPU)")
    return p


def run_scene(cfg, device=None, steps: int | None = None, collider: str | None = None,
              rebuild_every: str | None = None, output: str | Path | None = None,
              progress: bool = True, log=print, overwrite: bool | str = "ours",
              checkpoint_every: int | None = None, resume: str | Path | None = None, stop=None) -> dict:
    """Build and run a scene; write outputs; return the summary dict.

    The output folder is checked before the work (:func:`dynmesh_warp.outputs.check_output`)
    and written atomically at the end; ``overwrite="ours"`` (default) replaces an existing
    folder only when everything in it was written by this tool, ``True`` replaces what this
    tool wrote and keeps the rest.

    checkpoint_every: write ``<output>/checkpoint.npz`` (:mod:`dynmesh_warp.checkpoint`) every
    that many steps, and at the step where a stopped run ends (0 / None: none). resume: a
    checkpoint to continue from (checked against the scene); the run goes on to ``steps`` in all
    and writes the whole trajectory, equal to the uninterrupted run's (bit for bit on the CPU);
    its checkpoint interval is kept unless ``checkpoint_every`` is given. stop: a callable
    checked between steps (at least every ~0.05 s of stepping): once it returns a true value
    (e.g. ``"SIGINT"``) the run ends at that step and writes what it has, with
    ``"interrupted": true`` and ``"step_reached"`` in the summary."""
    newton = getattr(cfg, "newton", None) is not None  # bodies simulated by Newton (docs/newton.md)
    from .checkpoint import Checkpoint, CheckpointError, load_checkpoint
    from .config import SceneError
    from .runner import run_simulation

    if newton:
        if collider is not None or rebuild_every is not None:
            warnings.warn("--collider / --rebuild-every choose the built-in world's collider; a scene "
                          "with a newton: section uses Newton's collision pipeline, so they are ignored",
                          stacklevel=2)
        builtin_only = sorted(set(cfg.physics.model_fields_set) & NEWTON_IGNORES)
        if builtin_only:  # (a new user's collider, margin, rest_speed and sphere_body ran unsaid)
            warnings.warn(f"physics.{', physics.'.join(builtin_only)}: the built-in world's setting(s); a scene with a "
                          "newton: section uses Newton's solver and collision pipeline, so they are ignored",
                          stacklevel=2)
        if checkpoint_every or resume is not None:
            raise CheckpointError("--checkpoint-every / --resume: not available for a scene with a newton: section "
                                  "(the Newton solver's state is not saved)")
    ckpt = resume
    if resume is not None and not isinstance(resume, Checkpoint):
        ckpt = load_checkpoint(resume)  # the file on its own, before any work
    resume = None if ckpt is None else ckpt.path
    out = check_run_output(cfg, output, overwrite, resume=resume)
    t_build = time.perf_counter()
    if steps is None:
        steps = int(ckpt.meta["steps"]) if ckpt is not None else run_steps(cfg)
    if ckpt is not None and ckpt.step >= steps:
        raise CheckpointError(f"--resume {resume}: the checkpoint is at step {ckpt.step:,}, and this run has "
                              f"{steps:,} steps; give more (--steps, --duration, run.steps) to continue it")
    every = int(ckpt.checkpoint_every if (ckpt is not None and checkpoint_every is None) else (checkpoint_every or 0))
    check_total_work(cfg, steps, cfg.physics.substeps)  # before loading: the configured sub-steps
    if newton:
        from .newton_adapter import build_newton_world

        E = cfg.envs.count
        if E > 1 and (("time_offset" in cfg.envs.model_fields_set and cfg.envs.time_offset != 0)
                      or tuple(cfg.envs.rate) != (1.0, 1.0)):
            raise SceneError("envs.time_offset / envs.rate with a newton: section: Newton's own batching "
                             "(ModelBuilder.replicate) has one clock for every world; leave envs.time_offset "
                             "unset or 0 and envs.rate [1, 1], or drop the newton: section for the built-in "
                             "world's per-env clocks (docs/envs.md)")
        sim = build_newton_world(cfg, device=device, num_worlds=E)
    elif cfg.envs.count > 1:  # batched environments (docs/envs.md)
        from .batch import build_batched_world

        if collider not in (None, "swept", "fixed") or rebuild_every is not None:
            raise SceneError(f"--collider {collider}: batched envs use the swept pair BVHs (docs/envs.md)")
        chosen = cfg.physics.model_fields_set & {"collider", "rebuild_every"}
        if ("collider" in chosen and cfg.physics.collider not in ("swept", "fixed")) or "rebuild_every" in chosen:
            # (the scene's own choice was dropped unsaid where the flag was refused; a new user's)
            raise SceneError(f"physics.collider {getattr(cfg.physics.collider, 'value', cfg.physics.collider)!r} / "
                             "physics.rebuild_every: batched envs (envs.count > 1) use the swept pair BVHs; leave "
                             "them unset, fixed or swept (docs/envs.md)")
        sim = build_batched_world(cfg, device=device)
    else:
        from .choices import Collider
        from .scene import build_world

        if ckpt is not None and (collider or cfg.physics.collider) == Collider.FIXED:
            # the automatic choice is measured (it can differ between machines): a resumed run
            # keeps the collider its checkpoint was written with
            kept = str(ckpt.meta.get("fingerprint", {}).get("physics.collider", ""))
            if kept in (Collider.SWEPT, Collider.REFIT):
                collider = kept
        sim = build_world(cfg, device=device, collider=collider, rebuild_every=rebuild_every)
        check_total_work(cfg, steps, sim.substeps)  # with the sub-step rule's count
    return run_simulation(sim, cfg, steps=steps, out=out, t_build=t_build, progress=progress, log=log,
                          overwrite=overwrite, stop=stop, checkpoint_every=every, ckpt=ckpt)


def parse_env_list(text: str) -> list:
    """``--view-envs``: "3", "0,1,2,3" or "0-8" (ranges inclusive; at most 16 envs shown)."""
    from .config import SceneError

    out = []
    try:
        for part in str(text).split(","):
            a, _, b = part.strip().partition("-")
            lo, hi = int(a), int(b) if b else int(a)
            if lo < 0 or hi < lo:
                raise ValueError
            out.extend(range(lo, hi + 1))
    except ValueError:
        raise SceneError(f"--view-envs {text!r}: expected env indices like 3, 0,1,2,3 or 0-8") from None
    if len(out) > 16:
        raise SceneError(f"--view-envs {text!r}: {len(out)} envs; show at most 16 side by side")
    return out


def check_listen_host(host: str) -> None:
    """A viewer's ``--host`` this machine can listen on (one line, exit 2): viser's server
    thread dies on an address it cannot bind, and the viewer then waits for it forever."""
    import socket

    from .config import SceneError

    try:
        addrs = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        raise SceneError(f"--host {host}: not an address or a name this machine resolves ({e})") from None
    err = None
    for family, kind, proto, _, addr in addrs:
        try:
            with socket.socket(family, kind, proto) as s:
                s.bind(addr)  # port 0: any free port; only the address is tried
            return
        except OSError as e:
            err = e
    raise SceneError(f"--host {host}: cannot listen there ({err.strerror or err}); 127.0.0.1 is this machine only, "
                     "0.0.0.0 every interface") from None


def check_cli_options(args) -> None:
    """Every option of ``run`` checked before the scene is loaded (one line, exit 2)."""
    from .config import SceneError

    if args.steps is not None and args.steps < 1:
        raise SceneError(f"--steps must be at least 1, got {args.steps}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise SceneError(f"--duration must be a positive, finite number of seconds, got {args.duration}")
    if not 0 <= args.port <= 65535:
        raise SceneError(f"--port must be in 0..65535, got {args.port}")
    if not args.host.strip():
        raise SceneError("--host: empty address")
    if args.output is not None and args.record:
        raise SceneError(f"--output {args.output}: a --record run writes only the recording (OUT.viser and "
                         "OUT.html; it keeps no trajectories); run once more without --record for "
                         "summary.json and trajectories.npz")
    if args.view_envs is not None:
        args.view_envs = parse_env_list(args.view_envs)
        if args.viewer == "none" and not args.record:  # accepted and ignored before (a new user's)
            raise SceneError("--view-envs: chooses the envs the viewer or a --record recording shows; this run has "
                             "neither (--viewer none, no --record)")
    if args.splat_groups is not None and args.splat_groups < 0:
        raise SceneError(f"--splat-groups must be >= 0 (0: the whole splat buffer every frame), got {args.splat_groups}")
    if args.rebuild_every is not None and args.collider not in (None, "rebuild"):
        raise SceneError(f"--rebuild-every applies to --collider rebuild, not --collider {args.collider}")
    if args.checkpoint_every is not None and args.checkpoint_every < 0:
        raise SceneError(f"--checkpoint-every must be a number of steps >= 0 (0: no checkpoints), got "
                         f"{args.checkpoint_every}")
    if (args.checkpoint_every or args.resume is not None) and (args.record or args.viewer == "viser"):
        raise SceneError("--checkpoint-every / --resume apply to a headless run (--viewer none, no --record)")


def _interrupted_line(summary: dict) -> str:
    """The one line an interrupted run prints on stderr."""
    out = summary["output"]
    line = (f"interrupted by {summary['interrupted_by']} at step {summary['step_reached']:,} of {summary['steps']:,}: "
            f"wrote {out}/summary.json (\"interrupted\": true) and trajectories.npz up to that step")
    ck = summary.get("checkpoint")
    if ck:
        from .outputs import foreign_entries

        # a folder holding the user's files takes --overwrite to resume into (a new user's hint lacked it)
        more = " --overwrite" if foreign_entries(Path(out)) else ""
        line += f" and {ck['file']}; continue with --resume {Path(out) / ck['file']}{more} (same scene and options)"
    return line


@interruptible_main
def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from .cli import quiet_warp, stop_reason

    quiet_warp(args.device)
    from .config import SceneError, load_scene_config
    from .sequence import MeshDataError

    try:
        check_cli_options(args)
        ckpt = None
        if args.resume is not None:
            from .checkpoint import load_checkpoint

            ckpt = load_checkpoint(args.resume)  # the file on its own, before the scene's data is loaded
        if args.envs is not None and args.envs < 1:
            raise SceneError(f"--envs must be at least 1, got {args.envs}")
        overrides = list(args.overrides) + ([f"envs.count={args.envs}"] if args.envs is not None else [])
        cfg = load_scene_config(**scene_source(args.scene), overrides=overrides)
        say_sequence_scene(args.scene, cfg)
        if args.view_envs is not None and cfg.newton is not None:
            raise SceneError("--view-envs: a newton: scene's worlds share one clock and one place; "
                             "the viewer shows world 0")
        if args.view_envs is not None and max(args.view_envs) >= cfg.envs.count:
            raise SceneError(f"--view-envs: env {max(args.view_envs)} does not exist (the scene has "
                             f"{cfg.envs.count} env{'s' if cfg.envs.count != 1 else ''}; --envs N to batch)")
        if args.no_work_limit:
            lift_work_limits(cfg)
        steps = args.steps
        if args.duration is not None:
            steps = run_steps(cfg, args.duration)
        if steps is None and ckpt is not None:
            steps = int(ckpt.meta["steps"])  # resuming: the interrupted run's length
        check_total_work(cfg, steps or run_steps(cfg), cfg.physics.substeps)  # before any data is loaded
        viewer = args.viewer
        if viewer is None:
            import importlib.util

            tty = sys.stdin.isatty() and sys.stdout.isatty()
            viewer = "viser" if tty and importlib.util.find_spec("viser") is not None else "none"
        from .runtime import scene_device

        scene_device(cfg, args.device)  # a missing device is reported before any data is loaded
        if viewer == "viser" or args.record:
            check_listen_host(args.host)
            from .splat_io import SplatPlyError
            from .viewer import run_viewer

            if args.record:
                check_record_output(cfg, args.record, args.overwrite)
                print(f"note: --record writes {args.record} and its .html page only; summary.json and "
                      "trajectories.npz come from a run without --record", file=sys.stderr)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("always")
                    res = run_viewer(cfg, device=args.device, viewer=viewer, port=args.port, host=args.host,
                                     record=args.record, steps=steps if (args.steps or args.duration) else None,
                                     collider=args.collider, rebuild_every=args.rebuild_every, stop=stop_reason,
                                     splat_groups=args.splat_groups, view_envs=args.view_envs)
            except (SplatPlyError, RuntimeError, OSError) as e:
                print(f"error: {e}", file=sys.stderr)
                return 2
            if res.get("interrupted_by"):
                what = f"wrote the recording {res['record']} up to there" if args.record else "viewer closed"
                if args.record and res["record"] != str(Path(args.record)):
                    what += f"; {args.record}, which was there before, is unchanged"
                print(f"interrupted by {res['interrupted_by']} after {res['frames']:,} frames "
                      f"(t = {res['sim_time_s']:.3f} s): {what}", file=sys.stderr)
                return 128 + int(getattr(signal, res["interrupted_by"], signal.SIGINT))
            return 0
        check_run_output(cfg, args.output, args.overwrite, resume=args.resume)
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            summary = run_scene(cfg, device=args.device, steps=steps, collider=args.collider,
                                rebuild_every=args.rebuild_every, output=args.output,
                                progress=not args.no_progress, overwrite=args.overwrite,
                                checkpoint_every=args.checkpoint_every, resume=ckpt, stop=stop_reason)
    except (SceneError, MeshDataError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except NonFiniteStateError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if summary.get("interrupted"):
        print(_interrupted_line(summary), file=sys.stderr)
        return 128 + int(getattr(signal, summary["interrupted_by"], signal.SIGINT))
    return 0 if summary["final"]["finite"] else 1


if __name__ == "__main__":
    sys.exit(main())
