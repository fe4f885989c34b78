"""Roofline-style reading of the step's scaling table (issue 14): for each row, a lower bound on
the bytes a step must move and the fraction of the device's memory bandwidth the measured rate
reaches.

The model counts only the traffic a step cannot avoid (every array read or written once, in
float32 / int32; nothing for caches, atomics or launch overhead), per collider:

- ``refit`` (every step): the vertex buffer blended from two frames (read 2 x 12 N, write
  12 N), the normals (read 12 N points + 12 M indices, write 12 N), ``wp.Mesh.refit`` (read 12 N
  points and 12 M indices, write and read back the 2M - 1 node boxes, 2 x 32 B each), the
  contact query of each sphere (a root-to-leaf BVH path, 32 B per level, plus its leaf
  triangles, ``LEAF_TRIANGLES`` x (12 B indices + 3 x 12 B vertices)) and the integration
  (64 B per sphere);
- ``swept`` (every step): the contact query on the pair BVH (the same path, the candidate
  triangles read from two frames) and the integration; once per reconstruction frame (every
  ``steps_per_frame`` steps, amortised): the swept boxes (read 2 x 12 N + 12 M, write 24 M) and
  the pair BVH's refit (as above);
- ``swept/faces`` (the face-parallel search): every step one read of the M swept boxes (24 B
  each) and the integration; once per frame the swept boxes as above, with no tree refit;
- ``fixed``: the collider (and swept search) it chose.

Bandwidth: the H100 SXM's nominal HBM3 bandwidth, 3.35 TB/s (``--peak-tb-s``); a plain
device-to-device copy reaches about 90 % of it, so a fraction near 0.9 is the floor.

    python bench/roofline.py bench/results/step_fixed_choice_cuda_h100.json
    python bench/roofline.py bench/results/step_cuda_h100_tiled.json --out bench/results/roofline_cuda_h100_tiled.json

(The tree searches, serial or tiled, move the same lower-bound bytes: they differ in how many
dependent loads one sphere's query waits on, not in the bytes that must move.)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

from common import RESULTS, write_json  # noqa: E402

LEAF_TRIANGLES = 4  # triangles a sphere's query evaluates at the least (one leaf)


def tree_bytes(M: int) -> float:
    """Refit of a BVH over M triangles: 2M - 1 node boxes written and read back (32 B each)."""
    return 2.0 * (2 * M - 1) * 32.0


def query_bytes(M: int, two_frames: bool) -> float:
    """One sphere's contact query: the root-to-leaf path and one leaf's triangles."""
    depth = max(1.0, math.ceil(math.log2(max(M, 2))))
    tri = 12.0 + (2 if two_frames else 1) * 3 * 12.0
    return depth * 32.0 + LEAF_TRIANGLES * tri


def step_bytes(collider: str, N: int, M: int, S: int, steps_per_frame: float) -> float:
    """Lower bound on the bytes one step moves (module docstring)."""
    integrate = 64.0 * S
    if collider == "refit":
        surface = 36.0 * N + (24.0 * N + 12.0 * M) + (12.0 * N + 12.0 * M + tree_bytes(M))
        return surface + S * query_bytes(M, False) + integrate
    if collider == "swept":
        per_frame = (24.0 * N + 12.0 * M + 24.0 * M) + (24.0 * M + tree_bytes(M))
        return per_frame / steps_per_frame + S * query_bytes(M, True) + integrate
    if collider == "swept/faces":
        per_frame = 24.0 * N + 12.0 * M + 24.0 * M
        return per_frame / steps_per_frame + 24.0 * M + integrate
    raise ValueError(collider)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("table", nargs="?", default=str(RESULTS / "step_fixed_choice_cuda_h100.json"))
    ap.add_argument("--peak-tb-s", type=float, default=3.35)
    ap.add_argument("--steps-per-frame", type=float, default=10.0,
                    help="physics steps per reconstruction frame (dt 1/240 s, 24 frames/s: 10)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    src = json.loads(Path(a.table).read_text())
    rows = src["scaling"] if "scaling" in src else src["rows"]
    peak = a.peak_tb_s * 1e12
    out = []
    for r in rows:
        col = r["collider"]
        if col.startswith("rebuild"):
            continue
        if col == "fixed":
            col_model = r.get("chosen", col) + (f"/{r['swept_search']}" if r.get("swept_search") else "")
        else:
            col_model = col
        # swept/serial, swept/tiled: the tree searches' bytes (swept); swept/faces its own
        model = col_model if col_model == "swept/faces" else col_model.partition("/")[0]
        b = step_bytes(model, int(r["vertices"]), int(r["faces"]), int(r["spheres"]), a.steps_per_frame)
        floor_us = 1e6 * b / peak
        out.append({"vertices": r["vertices"], "faces": r["faces"], "spheres": r["spheres"], "collider": col,
                    "model": model, "steps_per_s": r["steps_per_s"], "us_per_step": r["us_per_step"],
                    "bytes_per_step": b, "floor_us": floor_us,
                    "bandwidth_fraction": b * r["steps_per_s"] / peak})
    res = {"source": str(Path(a.table).name), "machine": src.get("machine"), "peak_bytes_per_s": peak,
           "steps_per_frame": a.steps_per_frame, "leaf_triangles": LEAF_TRIANGLES, "rows": out,
           "model": __doc__.split("\n\n")[1]}
    print("| vertices × spheres | collider | steps/s | µs/step | bytes moved per step (lower bound) "
          "| floor µs at peak | fraction of peak bandwidth |")
    print("|---|---|---|---|---|---|---|")
    for o in out:
        name = o["collider"] + (f" ({o['model']})" if o["collider"] == "fixed" else "")
        print(f"| {o['vertices']:,} × {o['spheres']:,} | {name} | {o['steps_per_s']:,.0f} | {o['us_per_step']:.1f} | "
              f"{o['bytes_per_step'] / 1e6:.3g} MB | {o['floor_us']:.2f} | {o['bandwidth_fraction']:.3f} |")
    dev = "cuda_h100" if "H100" in str((src.get("machine") or {}).get("device_name", "")) else "device"
    write_json(Path(a.out) if a.out else RESULTS / f"roofline_{dev}.json", res)


if __name__ == "__main__":
    main()
