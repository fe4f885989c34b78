"""Across GPUs and machines with Ray (issue 15): one actor per GPU, each holding a batched env.

``run_rollouts(tasks, num_actors=..., envs_per_actor=...)`` starts one
:class:`RolloutActor` per device (``ray.init()`` locally, or ``address=`` a cluster's), fans the
tasks out (a rollout of a controller with given gains and seed: a parameter sweep, or many seeds
of one policy) and gathers their results in order. Each actor builds its
:class:`~dynmesh_warp.envs.RideSurfaceEnv` once and reuses it for every task it gets; on a GPU
node each actor asks Ray for one GPU (``num_gpus=1``) and runs on the device Ray gives it.
No process pool or RPC of our own: Ray does the scheduling, placement and transport.

    python -m dynmesh_warp.distributed --actors 2 --envs 64 --steps 300 --sweep kp=1,2,4
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time

import numpy as np

__all__ = ["rollout", "RolloutActor", "run_rollouts", "main"]


def pd_actions(obs: np.ndarray, kp: float, kd: float) -> np.ndarray:
    """A proportional-derivative controller of the ball (observation layout of envs.py): push
    towards the target against the velocity, clipped to the action range."""
    return np.clip(-kp * obs[:, 0:2] - kd * obs[:, 3:5], -1.0, 1.0).astype(np.float32)


def rollout(env, steps: int, seed: int, kp: float = 0.0, kd: float = 0.0) -> dict:
    """Run ``env`` (numpy backend) for ``steps`` vector steps under the PD controller (kp = kd =
    0: no action) from ``reset(seed)``; returns the finished episodes' mean return and length,
    the mean return of each env's first episode (None until every env's first has ended: at
    least ``max_steps`` steps; the episodes that finish inside the window are biased short, so
    their mean reads low: a new user's 376 against 395 for the first episodes, no action), the
    reward per env-step and the env-steps/s."""
    obs, _ = env.reset(seed=seed)
    E = env.num_envs
    ret, length = np.zeros(E), np.zeros(E)
    first = np.full(E, np.nan)
    returns, lengths, total = [], [], 0.0
    t0 = time.perf_counter()
    for _ in range(steps):
        obs, r, term, trunc, _ = env.step(pd_actions(obs, kp, kd))
        ret += r
        length += 1
        total += float(r.sum())
        done = term | trunc
        first[done & np.isnan(first)] = ret[done & np.isnan(first)]
        returns += ret[done].tolist()
        lengths += length[done].tolist()
        ret[done], length[done] = 0.0, 0.0
    wall = time.perf_counter() - t0
    return {"kp": kp, "kd": kd, "seed": seed, "episodes": len(returns),
            "mean_return": float(np.mean(returns)) if returns else None,
            "mean_length": float(np.mean(lengths)) if lengths else None,
            "first_episode_mean_return": None if np.isnan(first).any() else float(first.mean()),
            "reward_per_env_step": total / (steps * E), "env_steps_per_s": steps * E / wall}


class RolloutActor:
    """Holds one batched env on its device; ``run(task)`` returns :func:`rollout`'s result plus
    the actor's device. Used as a Ray actor (``ray.remote(RolloutActor)``)."""

    def __init__(self, num_envs: int, scene=None, env_kwargs: dict | None = None, device: str | None = None):
        import warp as wp

        from .envs import RideSurfaceEnv

        wp.config.quiet = True
        if device is None:
            device = "cuda:0" if wp.is_cuda_available() else "cpu"  # Ray sets CUDA_VISIBLE_DEVICES per actor
        self.device = device
        self.env = RideSurfaceEnv(num_envs=num_envs, scene=scene, device=device, **(env_kwargs or {}))

    def run(self, task: dict) -> dict:
        out = rollout(self.env, int(task["steps"]), int(task.get("seed", 0)), float(task.get("kp", 0.0)),
                      float(task.get("kd", 0.0)))
        return {**out, "device": str(self.device)}


def run_rollouts(tasks: list[dict], num_actors: int = 2, envs_per_actor: int = 64, scene=None,
                 env_kwargs: dict | None = None, address: str | None = None, gpus_per_actor: float | None = None,
                 device: str | None = None) -> list[dict]:
    """Fan ``tasks`` (dicts with ``steps`` and optionally ``seed``, ``kp``, ``kd``) out over
    ``num_actors`` Ray actors and return their results in the order of ``tasks``.

    ``address``: a Ray cluster (``"auto"`` or ``"ray://host:10001"``); None starts a local Ray.
    ``gpus_per_actor``: default 1 where Ray sees GPUs, else 0 (CPU actors)."""
    import ray

    started = False
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, log_to_driver=False,
                 **({} if address else {"num_cpus": max(num_actors, 1)}))
        started = True
    try:
        if gpus_per_actor is None:
            gpus_per_actor = 1.0 if ray.cluster_resources().get("GPU", 0) >= 1 else 0.0
        Actor = ray.remote(num_gpus=gpus_per_actor, num_cpus=1)(RolloutActor)
        actors = [Actor.remote(envs_per_actor, scene, env_kwargs, device) for _ in range(num_actors)]
        futures = [actors[i % num_actors].run.remote(t) for i, t in enumerate(tasks)]
        return ray.get(futures)
    finally:
        if started:
            ray.shutdown()


def _sweep(spec: list[str]) -> list[dict]:
    """["kp=1,2", "kd=0.5"] -> the grid of dicts."""
    keys, values = [], []
    for s in spec:
        k, _, v = s.partition("=")
        if k not in ("kp", "kd", "seed") or not v:
            raise SystemExit(f"--sweep {s}: expected kp=..., kd=... or seed=... with comma-separated values")
        keys.append(k)
        values.append([_sweep_value(s, k, x) for x in v.split(",")])
    return [dict(zip(keys, combo)) for combo in itertools.product(*values)] or [{}]


def _sweep_value(spec: str, key: str, text: str):
    """One value of ``--sweep KEY=...``: a finite number for kp / kd, a whole number for seed
    (``kp=abc`` ended in float()'s traceback and ``seed=1.5`` ran seed 1: a new user's)."""
    try:
        x = float(text)
    except ValueError:
        x = float("nan")
    if key == "seed":
        if not (math.isfinite(x) and x == int(x)):
            raise SystemExit(f"--sweep {spec}: seed values must be whole numbers, got {text!r}")
        return int(x)
    if not math.isfinite(x):
        raise SystemExit(f"--sweep {spec}: {key} values must be finite numbers, got {text!r}")
    return x


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m dynmesh_warp.distributed", description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", help="scene YAML (default: a ball on the built-in pulsing blob)")
    p.add_argument("--actors", type=int, default=2)
    p.add_argument("--envs", type=int, default=64, help="envs per actor")
    p.add_argument("--steps", type=int, default=300, help="vector steps per task")
    p.add_argument("--sweep", action="append", default=[], metavar="KEY=V1,V2",
                   help="controller gains / seeds to fan out, e.g. --sweep kp=1,2,4 --sweep kd=0.5,1")
    p.add_argument("--address", default=None, help="Ray cluster address (default: a local Ray)")
    p.add_argument("--device", default=None, help="Warp device of every actor (default: its GPU, else cpu)")
    a = p.parse_args(argv)
    if a.actors < 1 or a.envs < 1 or a.steps < 1:
        print("error: --actors, --envs and --steps must be >= 1", file=sys.stderr)
        return 2
    tasks = [{"steps": a.steps, "seed": 0, "kp": 0.0, "kd": 0.0, **t} for t in _sweep(a.sweep)]
    from .config import SceneError  # noqa: PLC0415
    from .envs import ride_surface_scene  # noqa: PLC0415
    from .sequence import MeshDataError  # noqa: PLC0415

    try:  # the scene's errors here, as run gives them, not from inside the actors after Ray starts
        ride_surface_scene(a.scene)
    except (SceneError, MeshDataError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    res = run_rollouts(tasks, a.actors, a.envs, scene=a.scene, address=a.address, device=a.device)
    wall = time.perf_counter() - t0
    for r in res:
        ret = ("no episode ended (raise --steps)" if r["mean_return"] is None
               else f"mean return {r['mean_return']:.4g}")
        print(f"kp={r['kp']:g} kd={r['kd']:g} seed={r['seed']}: {ret}, "
              f"{r['episodes']} episodes, {r['env_steps_per_s']:,.0f} env-steps/s on {r['device']}")
    total = sum(a.steps * a.envs for _ in res)
    print(f"{len(res)} tasks on {a.actors} actors: {total / wall:,.0f} env-steps/s overall ({wall:.1f} s with start-up)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
