"""Graph conversion speed probe: the first N frames of the 200-frame torus_to_sphere input
(~10k vertices, the bench_convert.py workload) with the default ``graph`` strategy, printing as it
goes and dumping the Python stacks every 60 s if stuck. Writes a JSON naming machine and device.

    python bench/gpu_probe.py --device cuda:0 --frames 20 --out bench/results/graph_probe_cuda.json
"""
import argparse
import json
import faulthandler
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import describe_device, write_json  # noqa: E402

from dynmesh_warp.convert import to_fixed_topology  # noqa: E402
from dynmesh_warp.scenes import torus_to_sphere  # noqa: E402
from dynmesh_warp.sequence import VaryingTopologySequence  # noqa: E402


def _instrument() -> dict:
    """Wrap the conversion's parts with synchronised timers; returns the dict they add to [s]."""
    import dynmesh_warp.deform_graph as dg

    parts = {}
    calls = parts.setdefault("calls", {})

    def wrap(owner, name, label):
        f = getattr(owner, name)

        def timed(*args, **kw):
            wp.synchronize()
            t = time.perf_counter()
            out = f(*args, **kw)
            wp.synchronize()
            parts[label] = parts.get(label, 0.0) + time.perf_counter() - t
            calls[label] = calls.get(label, 0) + 1
            return out
        setattr(owner, name, timed)

    # public stages of the graph fit only (the rest of a frame: total minus "graph fit")
    wrap(dg.GraphFitter, "fit", "graph fit")
    wrap(dg.GraphFitter, "solve", "graph fit: CG solves")
    wrap(dg.GraphFitter, "assemble", "graph fit: assembly")
    wrap(dg.GraphFitter, "correspondences", "graph fit: correspondences")
    wrap(dg.GraphFitter, "update_rotations", "graph fit: rotations")
    wrap(dg.GraphFitter, "rebuild", "graph fit: template BVH build")
    return parts


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--out", default=None)
    ap.add_argument("--options", default=None, help='graph options as JSON, e.g. \'{"restart_fits": 2}\'')
    ap.add_argument("--breakdown", action="store_true",
                    help="time the conversion's parts (synchronising around each: adds a little)")
    a = ap.parse_args()
    faulthandler.dump_traceback_later(60, repeat=True, file=sys.stdout)
    wp.config.quiet = True
    wp.init()
    t0 = time.perf_counter()
    seq = torus_to_sphere(frames=200, resolution=76)
    print(f"gen {time.perf_counter() - t0:.1f} s, {len(seq.frames[0][0])} vertices", flush=True)
    t = time.perf_counter()
    to_fixed_topology(VaryingTopologySequence(seq.frames[:2]), strategy="graph", device=a.device)
    wp.synchronize()
    compile_s = time.perf_counter() - t
    parts = _instrument() if a.breakdown else None
    t = time.perf_counter()
    opts = json.loads(a.options) if a.options else {}
    r = to_fixed_topology(VaryingTopologySequence(seq.frames[:a.frames]), strategy="graph", device=a.device, **opts)
    wp.synchronize()
    s = time.perf_counter() - t
    fs = np.array(r.conversion.frame_seconds)
    faulthandler.cancel_dump_traceback_later()
    res = {"benchmark": "graph_probe", **describe_device(a.device), "input": "torus_to_sphere(frames=200, resolution=76)",
           "template_vertices": int(r.num_vertices), "frames": a.frames, "warmup_s": compile_s, "total_s": s,
           "ms_per_frame": 1e3 * s / a.frames, "frame_ms_median": 1e3 * float(np.median(fs)),
           "frame_ms_max": 1e3 * float(fs.max()), "recovered_frames": len(r.conversion.recovered_frames),
           "unrecovered_frames": len(r.conversion.unrecovered_frames),
           "coverage_mean": float(np.mean(r.conversion.coverage)), "coverage_max": float(np.max(r.conversion.coverage)),
           "key_frame": r.conversion.key_frame, "key_trials": [list(x) for x in r.conversion.key_trials],
           "options": opts}
    if parts is None:  # per frame, after the printed summary (long)
        res["coverage"] = [round(float(c), 6) for c in r.conversion.coverage]
    else:
        calls = parts.pop("calls")
        res["breakdown_s"] = {k: round(v, 4) for k, v in parts.items()}
        res["breakdown_calls"] = calls
    print({k: v for k, v in res.items() if k != "coverage"}, flush=True)
    if a.out:
        write_json(a.out, res)


if __name__ == "__main__":
    main()
