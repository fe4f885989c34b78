"""Closed-form checks of the physics on low-rate data, with and without ``surface.upsample``
(docs/physics.md, "The data's frame rate"): the same smooth motions sampled at 24 fps, played
as they are (straight lines between frames: the velocity jumps at each frame boundary), played
on the C1 curve of ``surface.upsample`` 4 and 10, and sampled at 240 fps for reference.

- turntable: a 1.2 m disc turning at 2 rad/s, a sphere (r = 0.05 m, mu = 0.5) riding it at
  0.5 m with the disc's speed; omega^2 R = 2 m/s^2 < mu g, so it should stay at 0.5 m. Reports
  its distance from the axis after 2.9 s.
- shaker: a plate at -A cos(2 pi 2 t); a resting sphere stays on while A omega^2 < g (A = 0.04 m)
  and leaves when the plate's downward acceleration passes g (A = 0.10 m: at 0.1783 s, flight
  peak 70.3 mm). Reports the highest gap over the surface, and when it first passes 1 mm.

    python bench/low_rate_motion.py --device cpu     # -> bench/results/low_rate_motion_cpu.json
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, describe_device, write_json  # noqa: E402

OMEGA, R, RADIUS = 2.0, 0.5, 0.05


def turntable(fps: float, seconds: float = 3.0):
    from dynmesh_warp.sequence import FixedTopologySequence

    n = 48
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    P = np.vstack([np.zeros((1, 3))] + [np.c_[r * np.cos(ang), r * np.sin(ang), np.zeros(n)] for r in (0.3, 0.6, 0.9, 1.2)])
    F = [[0, 1 + i, 1 + (i + 1) % n] for i in range(n)]
    for k in range(3):
        a, b = 1 + k * n, 1 + (k + 1) * n
        for i in range(n):
            j = (i + 1) % n
            F += [[a + i, b + i, b + j], [a + i, b + j, a + j]]
    t = np.arange(int(seconds * fps) + 1) / fps
    c, s = np.cos(OMEGA * t), np.sin(OMEGA * t)
    rot = np.stack([np.stack([c, s, 0 * c], -1), np.stack([-s, c, 0 * c], -1), np.stack([0 * c, 0 * c, 1 + 0 * c], -1)], 1)
    return FixedTopologySequence(np.einsum("nj,tjk->tnk", P, rot).astype(np.float32), np.array(F, np.int32), fps, "turntable")


def shaker(fps: float, amplitude: float, seconds: float = 3.0):
    from dynmesh_warp.sequence import FixedTopologySequence

    g = np.linspace(-1.0, 1.0, 9)
    X, Y = np.meshgrid(g, g, indexing="ij")
    P = np.c_[X.ravel(), Y.ravel(), np.zeros(81)]
    F = [f for i in range(8) for j in range(8)
         for f in ([i * 9 + j, i * 9 + j + 9, i * 9 + j + 10], [i * 9 + j, i * 9 + j + 10, i * 9 + j + 1])]
    t = np.arange(int(seconds * fps) + 1) / fps
    V = np.stack([P + [0.0, 0.0, -amplitude * np.cos(4 * np.pi * tk)] for tk in t])
    return FixedTopologySequence(V.astype(np.float32), np.array(F, np.int32), fps, "shaker")


def world_for(seq, upsample: int, sphere: dict, device, collider: str):
    from dynmesh_warp.config import SceneConfig
    from dynmesh_warp.scene import build_world

    cfg = SceneConfig.model_validate({"surface": {"playback": "clamp", "upsample": upsample, "up_axis": "z"},
                                      "spheres": [{"radius": RADIUS, **sphere}]})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return build_world(cfg, device=device, sequence=seq, collider=collider)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--collider", default="refit")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    device = wp.get_device(a.device)
    cases = [(24.0, 1), (24.0, 4), (24.0, 10), (240.0, 1)]
    rows = []
    for fps, up in cases:
        w = world_for(turntable(fps), up, {"position": [R, 0.0, RADIUS], "velocity": [0.0, OMEGA * R, 0.0]},
                      a.device, a.collider)
        for _ in range(int(2.9 * 240)):
            w.step()
        p = w.sphere_positions()[0]
        row = {"data_fps": fps, "upsample": up, "turntable_radius_m": float(np.hypot(p[0], p[1])),
               "turntable_expected_m": R}
        for amp in (0.04, 0.10):
            w = world_for(shaker(fps, amp), up, {"position": [0.05, 0.03, RADIUS - amp]}, a.device, a.collider)
            gaps, times = [], []
            for _ in range(int(1.0 * 240)):
                w.step()
                gaps.append(float(w.sphere_positions()[0][2]) - RADIUS - float(w.surface_points().numpy()[0][2]))
                times.append(w.time)
            gaps = np.asarray(gaps)
            first = float(times[int(np.argmax(gaps > 1e-3))]) if (gaps > 1e-3).any() else None
            row[f"shaker_{amp:g}_highest_gap_mm"] = float(gaps.max() * 1e3)
            row[f"shaker_{amp:g}_first_gap_over_1mm_s"] = first
        rows.append(row)
        print(row, flush=True)
    out = Path(a.out) if a.out else RESULTS / f"low_rate_motion_{'cuda' if device.is_cuda else 'cpu'}.json"
    write_json(out, {"machine": describe_device(device), "collider": a.collider, "dt": 1 / 240,
                     "closed_form": {"turntable_radius_m": R, "shaker_0.04_highest_gap_mm": 0.0,
                                     "shaker_0.1_lift_off_s": 0.1783, "shaker_0.1_flight_peak_mm": 70.3},
                     "rows": rows})


if __name__ == "__main__":
    main()
