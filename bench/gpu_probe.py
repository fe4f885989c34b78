"""Diagnostic for the GPU machine: times the graph conversion stage by stage (prints as it goes;
dumps the Python stacks every 60 s if it is stuck)."""
import faulthandler
import sys
import time

import numpy as np
import warp as wp

faulthandler.dump_traceback_later(60, repeat=True, file=sys.stdout)
t0 = time.perf_counter()
wp.init()
dev = sys.argv[1] if len(sys.argv) > 1 else "cuda:0"
frames = int(sys.argv[2]) if len(sys.argv) > 2 else 20
from dynmesh_warp.convert import to_fixed_topology  # noqa: E402
from dynmesh_warp.scenes import torus_to_sphere  # noqa: E402
from dynmesh_warp.sequence import VaryingTopologySequence  # noqa: E402

seq = torus_to_sphere(frames=200, resolution=76)
print(f"gen {time.perf_counter() - t0:.1f} s, {len(seq.frames[0][0])} vertices", flush=True)
for st in ("graph",):
    t = time.perf_counter()
    to_fixed_topology(VaryingTopologySequence(seq.frames[:2]), strategy=st, device=dev)
    wp.synchronize()
    print(f"{st} warm-up (compile) {time.perf_counter() - t:.1f} s", flush=True)
    t = time.perf_counter()
    r = to_fixed_topology(VaryingTopologySequence(seq.frames[:frames]), strategy=st, device=dev)
    wp.synchronize()
    s = time.perf_counter() - t
    fs = np.array(r.conversion.frame_seconds)
    print(f"{st} {frames} frames {s:.2f} s ({1e3 * s / frames:.1f} ms/frame; median frame {1e3 * np.median(fs):.1f} ms, "
          f"max {1e3 * fs.max():.1f} ms; recovered {len(r.conversion.recovered_frames)})", flush=True)
faulthandler.cancel_dump_traceback_later()
