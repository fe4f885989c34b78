"""Where the 200-frame conversion's time goes (bench_convert's input, ``to_piecewise_fixed``,
strategy ``graph``): two views of one timed run after a warm-up run.

    python bench/profile_convert.py --device cuda:0 --mode sample   # wall clock of every thread
    python bench/profile_convert.py --device cuda:0 --mode gpu      # GPU activity per kernel

``sample``: a thread reads every other thread's stack about once a millisecond and counts the
innermost project frame (with the leaf function) and every project frame on the stack (so time
waiting on the device shows where the host waits). ``gpu``: Warp's timing API
(``wp.timing_begin(cuda_filter=wp.TIMING_ALL)``): elapsed GPU time per kernel, graph, memcpy and
memset. Text to stdout and ``--out``.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import threading
import time
from pathlib import Path

import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dynmesh_warp.convert import to_fixed_topology, to_piecewise_fixed  # noqa: E402
from dynmesh_warp.outputs import atomic_write_bytes  # noqa: E402
from dynmesh_warp.scenes import torus_to_sphere  # noqa: E402
from dynmesh_warp.sequence import VaryingTopologySequence  # noqa: E402


def _sampled(run) -> tuple:
    """(wall seconds, report lines) of run() sampled from another thread."""
    inner, cum = collections.Counter(), collections.Counter()
    stop = threading.Event()

    def sample():
        me = threading.get_ident()
        while not stop.is_set():
            for tid, fr in sys._current_frames().items():
                if tid == me:
                    continue
                names, first, f = set(), None, fr
                leaf = f"{os.path.basename(fr.f_code.co_filename)}:{fr.f_code.co_name}"
                while f is not None:
                    if "dynmesh_warp" in f.f_code.co_filename:
                        nm = f"{os.path.basename(f.f_code.co_filename)}:{f.f_code.co_name}"
                        names.add(nm)
                        first = first or nm
                    f = f.f_back
                if names:
                    th = threading._active.get(tid)
                    tn = th.name if th else "?"
                    inner[(tn, first, leaf)] += 1
                    for nm in names:
                        cum[(tn, nm)] += 1
            time.sleep(0.001)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    wall = run()
    stop.set()
    th.join()
    tot = max(sum(inner.values()), 1)
    lines = [f"wall {wall:.3f} s, {tot} samples", "== innermost project frame, leaf"]
    lines += [f"{v:6d} {100 * v / tot:5.1f}% {k}" for k, v in inner.most_common(60)]
    lines += ["== cumulative (on the stack)"] + [f"{v:6d} {100 * v / tot:5.1f}% {k}" for k, v in cum.most_common(80)]
    return wall, lines


def _gpu_timed(run) -> tuple:
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    wall = run()
    res = wp.timing_end()
    agg = collections.defaultdict(lambda: [0, 0.0])
    for r in res:
        k = (r.name.split("_cuda_kernel")[0][:70])
        agg[k][0] += 1
        agg[k][1] += r.elapsed
    tot = sum(v[1] for v in agg.values())
    lines = [f"wall {wall:.3f} s; GPU activity {tot / 1000:.3f} s over {len(res)} records",
             "     ms   count   us each  what"]
    lines += [f"{ms:9.1f} {n:7d} {1000 * ms / n:9.1f}  {k}" for k, (n, ms) in sorted(agg.items(), key=lambda kv: -kv[1][1])[:40]]
    return wall, lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default=None)
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--resolution", type=int, default=76)
    p.add_argument("--mode", choices=("sample", "gpu"), default="sample")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    dev = wp.get_device(a.device)
    seq = torus_to_sphere(frames=a.frames, resolution=a.resolution)
    to_fixed_topology(VaryingTopologySequence(seq.frames[:2]), strategy="graph", device=dev)  # compile

    def run():
        t0 = time.perf_counter()
        to_piecewise_fixed(seq, strategy="graph", device=dev)
        wp.synchronize_device(dev)
        return time.perf_counter() - t0

    print(f"warm-up run {run():.3f} s", flush=True)
    _, lines = (_sampled if a.mode == "sample" else _gpu_timed)(run)
    head = f"# profile_convert --mode {a.mode}: {dev.name} ({dev.alias}), warp {wp.__version__}, {a.frames} frames"
    txt = "\n".join([head] + lines)
    print(txt)
    if a.out:
        atomic_write_bytes(a.out, (txt + "\n").encode())


if __name__ == "__main__":
    main()
