"""Accuracy and run time of the topology-conversion strategies (docs/conversion.md table).

For each sequence (built-in torus_to_sphere; the /work/shared/data sequences re-meshed into
varying topology with dynmesh_warp.remesh) and each strategy: convert, then per frame measure
  * vtx->surf: mean distance of the converted vertices to the input frame's surface,
  * chamfer:   0.5 * (vtx->surf + mean distance of the input vertices to the converted surface),
both relative to the frame-0 bounding-box diagonal; summarized as mean and max over frames.
For re-meshed data with a ground truth (GT), also the Chamfer to the GT of the input and of the
converted mesh, and its increase in percent (the measure of the literature's 65-80 %).

Writes bench/results/conversion_table_<device>.json and .md. Time excludes Warp kernel
compilation (a 2-frame warm-up conversion runs first) and the re-meshing.

    python bench/conversion_table.py --device cpu [--frames 200] [--resolution 96]
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"

from dynmesh_warp.convert import STRATEGIES, surface_deviation, to_fixed_topology  # noqa: E402
from dynmesh_warp.outputs import atomic_write_bytes, atomic_write_json  # noqa: E402
from dynmesh_warp.sequence import FixedTopologySequence, VaryingTopologySequence  # noqa: E402

SOURCES = {
    "horse_gallop": "Sumner & Popovic 2004 (deformation transfer), horse-gallop",
    "horse_collapse": "Sumner & Popovic 2004, horse-collapse",
    "pcow": "Briceno et al. 2003 (geometry videos), elastic cow",
}


def _diag(V):
    return float(np.linalg.norm(np.ptp(V, axis=0)))


def load_inputs(names, frames, resolution, device, cache: Path | None):
    """name -> (varying sequence, ground-truth fixed sequence resampled to `frames`, or None)."""
    from dynmesh_warp.io import load_sequence
    from dynmesh_warp.remesh import remesh_sequence, resample_time
    from dynmesh_warp.scenes import torus_to_sphere

    out = {}
    for name in names:
        t0 = time.perf_counter()
        if name == "torus_to_sphere":
            out[name] = (torus_to_sphere(frames=frames), None, {"resolution": 48, "remesh_s": None})
            continue
        path = DATA / f"{name}.npz"
        if not path.exists():
            print(f"skip {name}: {path} not found")
            continue
        gt = load_sequence(path, frame_order="auto")  # horse_collapse and pcow are stored text-sorted
        gtV = resample_time(gt, frames)
        gt_seq = FixedTopologySequence(gtV, gt.F, fps=gt.fps, name=name)
        cf = cache / f"{name}_f{frames}_r{resolution}_ordered.npz" if cache else None
        if cf is not None and cf.exists():
            var = load_sequence(cf, kind="varying")
            rs = None
        else:
            var = remesh_sequence(gt, resolution=resolution, num_frames=frames, device=device, progress=True)
            rs = time.perf_counter() - t0
            if cf is not None:
                from dynmesh_warp.io import save_sequence

                cf.parent.mkdir(parents=True, exist_ok=True)
                save_sequence(var, cf)
        out[name] = (var, gt_seq, {"resolution": resolution, "remesh_s": rs})
    return out


def evaluate(var: VaryingTopologySequence, res: FixedTopologySequence, gt, device, every: int):
    diag = _diag(var.frames[0][0])
    rows = []
    for t in range(0, var.num_frames, every):
        Vi, Fi = var.frames[t]
        d = surface_deviation(res.V[t], res.F, Vi, Fi, device=device)
        row = {"frame": t, "vtx_to_surf": d["to_ref"] / diag, "chamfer": d["chamfer"] / diag}
        if gt is not None:
            row["chamfer_gt_converted"] = surface_deviation(res.V[t], res.F, gt.V[t], gt.F, device=device)["chamfer"] / diag
            row["chamfer_gt_input"] = surface_deviation(Vi, Fi, gt.V[t], gt.F, device=device)["chamfer"] / diag
        rows.append(row)
    s = {}
    for k in rows[0]:
        if k == "frame":
            continue
        a = np.array([r[k] for r in rows])
        s[f"{k}_mean"], s[f"{k}_max"] = float(a.mean()), float(a.max())
    if gt is not None:
        s["chamfer_gt_increase_pct"] = 100.0 * (s["chamfer_gt_converted_mean"] / s["chamfer_gt_input_mean"] - 1.0)
    return s


def markdown(result) -> str:
    dev = result["device"]
    L = [f"Device: {dev} ({result['machine']}), Warp {result['warp']}; frames per sequence: "
         f"{result['frames']}; distances relative to the frame-0 bounding-box diagonal.", "",
         "| sequence (input verts/frame) | strategy | vtx->surf mean | vtx->surf max | chamfer mean | "
         "chamfer max | chamfer to GT: input -> converted (increase) | time (s) | frames/s |",
         "|---|---|---|---|---|---|---|---|---|"]
    for name, d in result["sequences"].items():
        for st, r in d["strategies"].items():
            gt = "n/a (no GT)"
            if "chamfer_gt_increase_pct" in r:
                gt = (f"{r['chamfer_gt_input_mean']:.2e} -> {r['chamfer_gt_converted_mean']:.2e} "
                      f"({r['chamfer_gt_increase_pct']:+.0f} %)")
            L.append(f"| {name} ({d['input_vertices_mean']:.0f}) | {st} | {r['vtx_to_surf_mean']:.2e} | "
                     f"{r['vtx_to_surf_max']:.2e} | {r['chamfer_mean']:.2e} | {r['chamfer_max']:.2e} | {gt} | "
                     f"{r['seconds']:.2f} | {r['frames_per_s']:.1f} |")
    return "\n".join(L) + "\n"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--resolution", type=int, default=96)
    p.add_argument("--sequences", default="torus_to_sphere,horse_gallop,horse_collapse,pcow")
    p.add_argument("--strategies", default=",".join(STRATEGIES))
    p.add_argument("--eval-every", type=int, default=1, help="evaluate every k-th frame")
    p.add_argument("--cache", default="/tmp/dynmesh_remesh_cache", help="cache of re-meshed inputs ('' = none)")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(a.device)
    inputs = load_inputs(a.sequences.split(","), a.frames, a.resolution, device, Path(a.cache) if a.cache else None)
    result = {"device": device.alias, "device_name": device.name, "machine": platform.node() or platform.machine(),
              "cpu": platform.processor() or platform.machine(), "warp": wp.__version__, "frames": a.frames,
              "sequences": {}}
    # compile once (excluded from the timings)
    var0 = next(iter(inputs.values()))[0]
    warm = VaryingTopologySequence(var0.frames[:2])
    t0 = time.perf_counter()
    for st in a.strategies.split(","):
        to_fixed_topology(warm, strategy=st, device=device)
    wp.synchronize_device(device)
    result["warmup_compile_s"] = time.perf_counter() - t0
    for name, (var, gt, meta) in inputs.items():
        d = {"input_vertices_mean": float(np.mean([len(v) for v, _ in var.frames])),
             "template_vertices": int(len(var.frames[0][0])), **meta, "strategies": {}}
        if name in SOURCES:
            d["source"] = SOURCES[name]
        for st in a.strategies.split(","):
            t0 = time.perf_counter()
            res = to_fixed_topology(var, strategy=st, device=device)
            wp.synchronize_device(device)
            sec = time.perf_counter() - t0
            s = evaluate(var, res, gt, device, a.eval_every)
            s.update(seconds=sec, frames_per_s=var.num_frames / sec, options=res.conversion.options,
                     reanchored_frames=res.conversion.reanchored_frames)
            d["strategies"][st] = s
            print(f"{name:16s} {st:12s} vtx->surf {s['vtx_to_surf_mean']:.2e} chamfer {s['chamfer_mean']:.2e} "
                  + (f"GT +{s['chamfer_gt_increase_pct']:.0f}% " if gt is not None else "") + f"{sec:.1f}s", flush=True)
        result["sequences"][name] = d
    out = Path(a.out) if a.out else ROOT / "bench" / "results" / f"conversion_table_{device.alias.replace(':', '')}.json"
    atomic_write_json(out, result)
    atomic_write_bytes(out.with_suffix(".md"), markdown(result).encode())
    print(f"wrote {out} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
