"""Per-kernel profile of the swept step in the paper scene's steady state (spheres landed).

    python bench/profile_swept.py --device cuda:0 [--out file.json]

Each part is captured alone as a CUDA graph (eager on the CPU) and replayed; also reports how
many spheres took the serial fallback (left their gathered ball or overflowed their list).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_step import graph_or_eager, make_world  # noqa: E402
from common import describe_device, load_paper_sequence, time_loop, write_json  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default=None)
    ap.add_argument("--settle", type=int, default=600)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    wp.config.quiet = True
    device = wp.get_device(args.device)
    seq, shared = load_paper_sequence()
    w = make_world(seq, device, "swept")
    for _ in range(args.settle):
        w.step()
    wp.synchronize_device(device)
    c = w.collider
    parts = {
        "full_step": w.step,
        "conditional refit node (not taken)": lambda: c.update(w),
        "collide (evaluate+resolve or serial)": lambda: c.collide(w),
        "integrate + clock + frame test": w.integrate,
        "per_frame: bounds+bvh_refit+gather": lambda: c.refit_frame(w),
        "per_frame: bounds only": lambda: c.compute_bounds(w),
        "per_frame: bvh_refit only": lambda: c.bvh.refit(),
    }
    if c.parallel:
        parts["per_frame: gather only"] = lambda: c.gather(w)
    res = {}
    for k, f in parts.items():
        fn = f if k == "full_step" else graph_or_eager(f, device)
        res[k] = time_loop(fn, device, 500, 5)["us_per_step"]
        print(f"{k:<40} {res[k]:8.2f} us", flush=True)
    # which spheres take the serial path now
    info = {}
    if c.parallel:
        p = w.state.sphere_pos.numpy()
        v = np.linalg.norm(w.state.sphere_vel.numpy(), axis=1)
        r = w.model.spheres.radius.numpy()
        reach = r + w.model.params.margin + (v + w.extra_speed) * w.sub_dt
        cnt = c.cand_count.numpy()
        out_of_ball = np.linalg.norm(p - c.cand_center.numpy(), axis=1) + reach + c.epsilon > c.cand_radius.numpy()
        info = {"candidates": cnt.tolist(), "overflow": (c.cand_start.numpy() < 0).tolist(),
                "left_ball": out_of_ball.tolist(), "in_contact": (w.contacts.face.numpy() >= 0).tolist()}
        print(info)
    result = {"machine": describe_device(device), "sequence": seq.name, "from_shared_data": shared,
              "parallel": c.parallel, "us": res, "state": info}
    if args.out:
        write_json(Path(args.out), result)


if __name__ == "__main__":
    main()
