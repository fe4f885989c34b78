"""What a per-step refit costs at 10^6 vertices (issue 14: the refit path's step at 10^6 x 10^5 is
~0.57 ms on an H100, most of it ``wp.Mesh.refit``).

Times, replayed from a CUDA graph (device time): ``wp.Mesh.refit`` (edge lengths, a scan, the
triangle boxes, the tree) for each BVH constructor and leaf size; ``wp.Bvh.refit`` over the same
triangle boxes (the tree only); and the triangle-box pass itself.

    python bench/refit_probe.py --device cuda --vertices 1000000 --out bench/results/refit_probe_cuda.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import describe_device, write_json  # noqa: E402


@wp.kernel
def compute_face_boxes(points: wp.array[wp.vec3], indices: wp.array[wp.int32],
                       lowers: wp.array[wp.vec3], uppers: wp.array[wp.vec3]):
    f = wp.tid()
    a = points[indices[3 * f]]
    b = points[indices[3 * f + 1]]
    c = points[indices[3 * f + 2]]
    lowers[f] = wp.min(wp.min(a, b), c)
    uppers[f] = wp.max(wp.max(a, b), c)


def grid(n):
    s = int(round(np.sqrt(n)))
    x, y = np.meshgrid(np.linspace(0, 1, s), np.linspace(0, 1, s), indexing="ij")
    V = np.stack([x.ravel(), y.ravel(), 0.01 * np.sin(7 * x.ravel()) * np.cos(5 * y.ravel())], 1).astype(np.float32)
    i = np.arange(s * s).reshape(s, s)
    a, b, c, d = i[:-1, :-1].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel(), i[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return V, F


def replay_ms(fn, device, launches, repeats):
    fn()
    wp.synchronize_device(device)
    if device.is_cuda:
        with wp.ScopedCapture(device) as cap:
            for _ in range(launches):
                fn()
        run = lambda: wp.capture_launch(cap.graph)  # noqa: E731
        per = launches
    else:
        run, per = fn, 1
    run()
    ts = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        run()
        wp.synchronize_device(device)
        ts.append((time.perf_counter() - t0) / per)
    return float(np.median(ts)) * 1e3


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--vertices", type=int, default=1_000_000)
    ap.add_argument("--launches", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.init()
    d = wp.get_device(a.device)
    V, F = grid(a.vertices)
    pts = wp.array(V, dtype=wp.vec3, device=d)
    idx = wp.array(F.reshape(-1), dtype=wp.int32, device=d)
    nf = len(F)
    lo = wp.zeros(nf, dtype=wp.vec3, device=d)
    hi = wp.zeros(nf, dtype=wp.vec3, device=d)
    rows = {}

    def boxes():
        wp.launch(compute_face_boxes, nf, inputs=[pts, idx], outputs=[lo, hi], device=d)

    rows["face_boxes"] = replay_ms(boxes, d, a.launches, a.repeats)
    boxes()
    ctors = ["lbvh", "sah"] if d.is_cuda else ["sah"]
    for ctor in ctors:
        for leaf in (1, 2, 4, 8):
            try:
                m = wp.Mesh(points=pts, indices=idx, bvh_constructor=ctor, bvh_leaf_size=leaf)
                rows[f"mesh_refit_{ctor}_leaf{leaf}"] = replay_ms(m.refit, d, a.launches, a.repeats)
            except Exception as e:  # noqa: BLE001 - a probe: record what failed
                rows[f"mesh_refit_{ctor}_leaf{leaf}"] = f"failed: {e}"
            try:
                bvh = wp.Bvh(lo, hi, constructor=ctor, leaf_size=leaf)
                rows[f"bvh_refit_{ctor}_leaf{leaf}"] = replay_ms(bvh.refit, d, a.launches, a.repeats)
            except Exception as e:  # noqa: BLE001
                rows[f"bvh_refit_{ctor}_leaf{leaf}"] = f"failed: {e}"
            print(ctor, leaf, rows[f"mesh_refit_{ctor}_leaf{leaf}"], rows[f"bvh_refit_{ctor}_leaf{leaf}"], flush=True)
    print("face boxes", rows["face_boxes"])
    res = {"machine": describe_device(d), "vertices": len(V), "faces": nf, "ms": rows}
    if a.out:
        write_json(a.out, res)


if __name__ == "__main__":
    main()
