"""Benchmark of the evaluation metrics: Chamfer distance on 10k points, approxmatch EMD on 8,192.

Inputs: two seeded area-weighted sample sets of the horse_gallop frames 0 and 12 from
/work/shared/data when present (else a deformed icosphere). Compile time (first launch of the
kernel module) is reported separately; then warm-up and the median of repeats.

    python bench/bench_metrics.py --device cpu   # -> bench/results/metrics_cpu.json
    python bench/bench_metrics.py --device cuda  # -> bench/results/metrics_cuda.json
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import warp as wp

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "horse_gallop.npz"


def _meshes():
    if DATA.exists():
        d = np.load(DATA)
        return (d["V"][0], d["F"]), (d["V"][12], d["F"]), "horse_gallop frames 0 and 12"
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=5)
    V = np.asarray(s.vertices, np.float32)
    return (V, s.faces), (V * 1.05, s.faces), "icosphere(5) and a 1.05 scaled copy"


def _time(fn, repeats, sync):
    """(wall seconds of each repeat, last return value)."""
    out, val = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        val = fn()
        sync()
        out.append(time.perf_counter() - t0)
    return out, val


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cd-points", type=int, default=10000)
    ap.add_argument("--emd-points", type=int, default=8192)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--emd-repeats", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    from dynmesh_warp import metrics as M
    from dynmesh_warp.kernels import metrics as K
    from dynmesh_warp.outputs import atomic_write_json

    dev = wp.get_device(a.device)

    def sync():
        wp.synchronize_device(dev)

    (Va, Fa), (Vb, Fb), what = _meshes()
    t0 = time.perf_counter()
    wp.load_module(K, device=dev)  # compile (or load from the kernel cache)
    compile_s = time.perf_counter() - t0
    pa = M.sample_surface(Va, Fa, a.cd_points, 0, dev)
    pb = M.sample_surface(Vb, Fb, a.cd_points, 1, dev)
    ea = M.sample_surface(Va, Fa, a.emd_points, 0, dev)
    eb = M.sample_surface(Vb, Fb, a.emd_points, 1, dev)

    res = {"machine": platform.node(), "platform": platform.platform(), "processor": platform.processor(),
           "device": str(dev), "device_name": getattr(dev, "name", str(dev)), "warp": wp.config.version,
           "inputs": what, "compile_or_cache_load_s": compile_s, "repeats": a.repeats}
    # sampling (10k points, one mesh)
    M.sample_surface(Va, Fa, a.cd_points, 0, dev)
    t, _ = _time(lambda: M.sample_surface(Va, Fa, a.cd_points, 0, dev), a.repeats, sync)
    res["sample_surface"] = {"points": a.cd_points, "median_s": statistics.median(t), "all_s": t}
    # Chamfer: both directions incl. hash-grid build and host<->device copies
    M.chamfer_distance(pa, pb, device=dev)
    t, v = _time(lambda: M.chamfer_distance(pa, pb, device=dev), a.repeats, sync)
    res["chamfer"] = {"points": a.cd_points, "median_s": statistics.median(t), "all_s": t,
                      "value": v.value}
    # approxmatch EMD
    M.approxmatch_emd(ea[:256], eb[:256], device=dev)  # warm-up
    t, v = _time(lambda: M.approxmatch_emd(ea, eb, device=dev), a.emd_repeats, sync)
    res["approxmatch_emd"] = {"points": a.emd_points, "levels": len(M.APPROXMATCH_LEVELS),
                              "median_s": statistics.median(t), "all_s": t, "value": v}
    out = Path(a.out) if a.out else Path(__file__).parent / "results" / f"metrics_{dev.alias.replace(':', '')}.json"
    atomic_write_json(out, res)
    print(out)
    for k in ("sample_surface", "chamfer", "approxmatch_emd"):
        print(f"{k:16s} {res[k]['points']:6d} pts  median {res[k]['median_s'] * 1e3:9.2f} ms")
    print(f"compile/load {compile_s:.2f} s")


if __name__ == "__main__":
    main()
