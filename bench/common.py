"""Shared helpers of the benchmarks: device description, timing, JSON output."""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def describe_device(device) -> dict:
    import warp as wp

    d = wp.get_device(device)
    info = {"device": str(d), "warp": wp.__version__, "python": sys.version.split()[0],
            "host": platform.node(), "cpu": cpu_name(), "cpu_count": os.cpu_count()}
    if d.is_cuda:
        info["device_name"] = d.name
        info["gpu_memory_gib"] = round(d.total_memory / 2**30, 1)
        info["cuda_driver"] = wp.context.runtime.driver_version if hasattr(wp, "context") else None
    else:
        info["device_name"] = info["cpu"]
    return info


def time_loop(fn, device, steps: int, repeats: int = 5, warmup: int = 20) -> dict:
    """Median over ``repeats`` of the wall time of ``steps`` calls of fn, synchronized."""
    import warp as wp

    for _ in range(warmup):
        fn()
    wp.synchronize_device(device)
    per_step = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            fn()
        wp.synchronize_device(device)
        per_step.append((time.perf_counter() - t0) / steps)
    med = statistics.median(per_step)
    return {"us_per_step": med * 1e6, "steps_per_s": 1.0 / med, "repeats": repeats, "steps": steps,
            "min_us": min(per_step) * 1e6, "max_us": max(per_step) * 1e6}


def checked_output(path, kind: str, what: str, inputs=(), writes=()) -> Path:
    """``outputs.check_output`` for a probe's output, before any work: never the probe's input,
    inside it or holding it; a folder never has a file of a name in ``writes`` that this tool did
    not write. A result is replaced (``overwrite``), as benchmarks rerun. Refused: SystemExit
    with the check's one line."""
    from dynmesh_warp.outputs import OutputError, check_output

    try:
        return check_output(path, kind=kind, what=what, inputs=inputs, overwrite=True, writes=writes)
    except OutputError as e:
        raise SystemExit(str(e)) from None


def write_json(path: Path, obj: dict):
    from dynmesh_warp.outputs import atomic_write_json

    atomic_write_json(path, obj)
    print(f"wrote {path}")


def load_paper_sequence(prefer_shared: bool = True):
    """horse_gallop from ../shared/data when present, else a built-in surface of similar size."""
    from dynmesh_warp.sequence import FixedTopologySequence

    f = SHARED_DATA / "horse_gallop.npz"
    if prefer_shared and f.is_file():
        d = np.load(f)
        # y-up data: rotate to z-up like `up_axis: y` does in a scene
        V = d["V"].astype(np.float64) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float).T
        return FixedTopologySequence(V.astype(np.float32), d["F"], float(d["fps"]), "horse_gallop", str(f)), True
    from dynmesh_warp.scenes import wave_bowl

    return wave_bowl(n=92, frames=24), False
