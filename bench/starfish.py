"""An animated mesh none of the conversion work was tuned on: a starfish whose five thin arms
curl up and down out of phase (analytic bending, fixed topology), for
``bench/conversion_eval.py --sequences out/starfish.npz``.

The arms are 6 % of the diagonal thick and curl to a half circle and back in one second (their
tips move ~2 m/s against a 1.9 m span): thin parts moving fast, bending rather than rotating
rigidly, with tips that come close to the body (the motion class where a closest-point fit loses
limbs, issue 12).

    python bench/starfish.py --out out/starfish.npz --frames 48
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def starfish(frames: int = 48, fps: float = 24.0, arms: int = 5, resolution: int = 96, arm_length: float = 0.8,
             arm_radius: float = 0.06, body_radius: float = 0.22, curl: float = 1.0):
    """(V (T, N, 3) float32, F (M, 3) int32): the rest mesh by marching cubes of a body ball and
    ``arms`` capsules, each arm bent per frame about the axis across it at the body's edge, its
    centreline a circular arc of curvature ``curl * pi / arm_length * sin(2 pi t / T + phase)``."""
    from skimage.measure import marching_cubes

    from dynmesh_warp.geometry import orient_outward

    half = 1.2
    g = np.linspace(-half, half, resolution)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    P = np.stack([X, Y, Z], -1)
    sdf = np.linalg.norm(P * [1.0, 1.0, 1.6], axis=-1) - body_radius
    dirs = [np.array([np.cos(a), np.sin(a), 0.0]) for a in 2 * np.pi * np.arange(arms) / arms]
    for d in dirs:
        s = np.clip(P @ d, 0.0, body_radius + arm_length)
        r = arm_radius * (1.0 - 0.5 * s / (body_radius + arm_length))  # tapered
        sdf = np.minimum(sdf, np.linalg.norm(P - s[..., None] * d, axis=-1) - r)
    v, f, _, _ = marching_cubes(sdf, 0.0, spacing=(g[1] - g[0],) * 3)
    V0 = v - half
    F = orient_outward(V0, f.astype(np.int32))
    out = np.empty((frames, len(V0), 3), np.float32)
    for t in range(frames):
        Vt = V0.copy()
        for k, d in enumerate(dirs):
            e = np.cross([0.0, 0.0, 1.0], d)
            s = V0 @ d
            arm = (s > body_radius) & (np.abs(V0 @ e) < 2 * arm_radius)
            kappa = curl * np.pi / arm_length * np.sin(2 * np.pi * t / frames + 2 * np.pi * k / arms)
            u, w = V0[arm] @ e, V0[arm, 2]
            ls = s[arm] - body_radius
            if abs(kappa) < 1e-9:
                continue
            th = kappa * ls
            c = body_radius * d + (np.sin(th) / kappa)[:, None] * d + ((1 - np.cos(th)) / kappa)[:, None] * [0, 0, 1.0]
            n = -np.sin(th)[:, None] * d + np.cos(th)[:, None] * [0, 0, 1.0]
            Vt[arm] = c + u[:, None] * e + w[:, None] * n
        out[t] = Vt
    return out, F


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/starfish.npz")
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--resolution", type=int, default=96)
    a = ap.parse_args()
    V, F = starfish(frames=a.frames, resolution=a.resolution)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    np.savez(a.out, V=V, F=F, fps=np.float32(24.0), name="starfish")
    print(f"wrote {a.out}: {V.shape[0]} frames x {V.shape[1]} vertices, {len(F)} faces")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
