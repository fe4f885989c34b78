"""Benchmark: topology conversion of 200 frames of a ~10k-vertex varying-topology sequence.

Input: the built-in torus_to_sphere morph, marching cubes at a resolution chosen to give about
``--vertices`` vertices per frame (generation excluded from the timings). Per strategy: a
2-frame warm-up conversion (Warp kernel compilation; its time is reported separately as
compile_s), then ``--repeats`` timed conversions of all frames; the median is reported.

    python bench/bench_convert.py --device cpu            # -> bench/results/convert_cpu.json
    python bench/bench_convert.py --device cuda:0         # -> bench/results/convert_cuda0.json
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

from dynmesh_warp.convert import STRATEGIES, to_fixed_topology, to_piecewise_fixed  # noqa: E402
from dynmesh_warp.outputs import atomic_write_json  # noqa: E402
from dynmesh_warp.scenes import torus_to_sphere  # noqa: E402
from dynmesh_warp.sequence import VaryingTopologySequence  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--resolution", type=int, default=76, help="marching-cubes grid of the input (76 -> ~9-10k vertices)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--strategies", default=",".join(STRATEGIES))
    p.add_argument("--out", default=None)
    p.add_argument("--piecewise", action="store_true",
                   help="time to_piecewise_fixed (what the convert CLI runs: new templates where one cannot follow)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="a strategy option (YAML value), repeatable, e.g. --option restart_on_web=false")
    a = p.parse_args(argv)
    import yaml

    opts = {k: yaml.safe_load(v) for k, v in (o.split("=", 1) for o in a.option)}
    run = to_piecewise_fixed if a.piecewise else to_fixed_topology
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(a.device)
    t0 = time.perf_counter()
    seq = torus_to_sphere(frames=a.frames, resolution=a.resolution)
    gen_s = time.perf_counter() - t0
    nverts = [len(v) for v, _ in seq.frames]
    res = {
        "benchmark": "convert", "device": device.alias, "device_name": device.name,
        "machine": platform.node() or "unknown", "cpu": platform.processor() or platform.machine(),
        "python": platform.python_version(), "warp": wp.__version__,
        "input": {"scene": "torus_to_sphere", "frames": a.frames, "resolution": a.resolution,
                  "vertices_per_frame_mean": float(np.mean(nverts)), "vertices_per_frame_min": int(min(nverts)),
                  "vertices_per_frame_max": int(max(nverts)), "template_vertices": nverts[0],
                  "template_faces": int(len(seq.frames[0][1])), "generation_s": gen_s},
        "repeats": a.repeats, "function": run.__name__, "given_options": opts, "strategies": {},
    }
    warm = VaryingTopologySequence(seq.frames[:2])
    for st in a.strategies.split(","):
        t0 = time.perf_counter()
        to_fixed_topology(warm, strategy=st, device=device)  # compiles kernels on first use
        wp.synchronize_device(device)
        compile_s = time.perf_counter() - t0
        times = []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            out = run(seq, strategy=st, device=device, **opts)
            wp.synchronize_device(device)
            times.append(time.perf_counter() - t0)
        med = float(np.median(times))
        res["strategies"][st] = {"seconds_median": med, "seconds_all": times, "frames_per_s": a.frames / med,
                                 "ms_per_frame": 1000 * med / a.frames,
                                 "template_vertices": [n for *_, n in out.conversion.segments],
                                 "segments": [list(x) for x in out.conversion.segments],
                                 "web_max": float(max(out.conversion.web)),
                                 "compile_and_warmup_s": compile_s, "key_frame": out.conversion.key_frame,
                                 "key_trials": [list(x) for x in out.conversion.key_trials],
                                 "recovered_frames": len(out.conversion.recovered_frames),
                                 "options": out.conversion.options}
        print(f"{st:12s} {med:7.2f} s  {a.frames / med:7.1f} frames/s  ({len(out.conversion.segments)} segment(s), "
              f"web max {100 * max(out.conversion.web):.2f}%; "
              f"key frame {out.conversion.key_frame}, {len(out.conversion.key_trials)} key trials; "
              f"compile+warm-up {compile_s:.2f} s)", flush=True)
    out_path = Path(a.out) if a.out else ROOT / "bench" / "results" / f"convert_{device.alias.replace(':', '')}.json"
    atomic_write_json(out_path, res)
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()
