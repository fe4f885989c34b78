"""Write a GT sequence moved the way a new user's capture moves, as a GT npz for
``bench/conversion_eval.py --sequences PATH.npz``: the conversion's defaults were chosen on
sequences that stay in place, at metre scale; a performance capture walks across the room, turns
round, and may be in millimetres (docs/evaluation.md, "Unseen placements").

    python bench/unseen_variants.py --sequence articulated_figure --walk 2 --turn 3.14 --out out/figure_walk.npz
    python bench/unseen_variants.py --sequence ../shared/data/horse_gallop.npz --scale 1000 --out out/gallop_mm.npz

``--walk W``: the body's centre travels W x its rest bbox diagonal along x over the sequence;
``--turn A``: it turns by A radians about the vertical through its centre (linear in time);
``--scale S``, ``--offset D``: every coordinate times S, then D x the diagonal added to each axis;
``--floor S``: a static slab S x the diagonal wide under the lowest point of the sequence, centred
under frame 0 (``scenes.with_floor``), as a reconstruction of a real capture keeps the floor the
subject stands on (its feet touch it); the walk and the turn move the subject, not the floor;
``--hold``: the vertices below frame 0's centroid along the first horizontal axis keep
frame 0's position (a person who stands still and moves one arm: the moving part is small, with
no floor); ``--scene-args JSON``: keyword arguments of a built-in scene, e.g.
``'{"arm_swing": 1.2, "leg_swing": 0, "sway": 0}'`` for ``articulated_figure``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def load(name: str, scene_args: dict | None = None):
    from dynmesh_warp.scenes import BUILTIN_SCENES, builtin_sequence
    if name in BUILTIN_SCENES:
        s = builtin_sequence(name, **(scene_args or {}))
        return np.asarray(s.V, np.float64), np.asarray(s.F), float(s.fps)
    z = np.load(name)
    return np.asarray(z["V"], np.float64), np.asarray(z["F"]), float(z["fps"]) if "fps" in z else 24.0


def horizontal(up: int) -> list:
    """The two horizontal axes (indices) when ``up`` is the vertical one."""
    return [a for a in range(3) if a != up]


def place(V: np.ndarray, walk: float = 0.0, turn: float = 0.0, scale: float = 1.0, offset: float = 0.0,
          up: int = 2) -> np.ndarray:
    """The moved copy of V (T, N, 3): turn about the vertical through each frame's centroid,
    then walk along the first horizontal axis, then scale and offset (see the module doc)."""
    T = len(V)
    diag = float(np.linalg.norm(V[0].max(0) - V[0].min(0)))
    h = horizontal(up)
    out = np.empty_like(V)
    for t in range(T):
        u = t / max(T - 1, 1)
        c = V[t].mean(0)
        a = turn * u
        R = np.eye(3)
        R[np.ix_(h, h)] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        P = (V[t] - c) @ R.T + c
        P[:, h[0]] += walk * diag * u
        out[t] = P
    return out * scale + offset * diag * scale


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", required=True, help="a built-in scene name or a GT npz (V, F, fps)")
    ap.add_argument("--walk", type=float, default=0.0)
    ap.add_argument("--turn", type=float, default=0.0)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--offset", type=float, default=0.0)
    ap.add_argument("--floor", type=float, default=0.0)
    ap.add_argument("--hold", action="store_true", help="the negative half keeps frame 0's position")
    ap.add_argument("--scene-args", default=None, help="JSON keyword arguments of a built-in scene")
    ap.add_argument("--up", type=int, default=2, help="vertical axis index (default 2: z)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    if Path(a.sequence).exists() and Path(a.out).resolve() == Path(a.sequence).resolve():
        raise SystemExit(f"--out {a.out} is the input sequence; name another file")
    scene_args = None
    if a.scene_args:
        from dynmesh_warp.scenes import BUILTIN_SCENES
        if a.sequence not in BUILTIN_SCENES:
            raise SystemExit(f"--scene-args: {a.sequence} is not a built-in scene ({sorted(BUILTIN_SCENES)})")
        try:
            scene_args = json.loads(a.scene_args)
        except json.JSONDecodeError as e:
            raise SystemExit(f"--scene-args: not JSON ({e})") from None
        if not isinstance(scene_args, dict):
            raise SystemExit(f"--scene-args: expected a JSON object of keyword arguments, got {a.scene_args}")
    try:
        V, F, fps = load(a.sequence, scene_args)
    except TypeError as e:  # an argument the scene does not take
        raise SystemExit(f"--scene-args: {e}") from None
    if a.hold:
        h = horizontal(a.up)[0]
        V = np.where((V[0][:, h] < V[0][:, h].mean())[None, :, None], V[:1], V)
    W = place(V, a.walk, a.turn, 1.0, 0.0, a.up)  # the subject moves; a floor stays where frame 0 stands
    if a.floor > 0:
        from dynmesh_warp.scenes import with_floor
        W, F = with_floor(W, F, a.floor, a.up)
    W = place(W, scale=a.scale, offset=a.offset, up=a.up).astype(np.float32)
    from dynmesh_warp.outputs import atomic_write_npz

    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_npz(a.out, V=W, F=F.astype(np.int32), fps=np.float32(fps), name=Path(a.out).stem)
    print(f"wrote {a.out}: {W.shape[0]} frames x {W.shape[1]} vertices; extent {np.ptp(W.reshape(-1, 3), 0)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
