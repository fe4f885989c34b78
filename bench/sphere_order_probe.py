"""Probe: what the refit collider's sphere order (world.SphereOrder) costs and buys in the step,
one variant at a time on the scaling scene (bench_step.py's wave grid, spheres spawned at random
over it): the order as shipped (sorted at the start and on every frame change), sorted once at
the start only, the spawn order through the same indirection (no sort); and checks that the
order is a permutation of the spheres after the timed steps. Writes a JSON naming the machine.

    python bench/sphere_order_probe.py --device cuda --verts 100000,1000000 --spheres 100000
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_step import make_world, wave_grid  # noqa: E402
from common import RESULTS, describe_device, time_loop, write_json  # noqa: E402

from dynmesh_warp import world as world_mod  # noqa: E402

VARIANTS = ("per_frame", "once", "spawn_order")


def main(argv=None):
    import numpy as np
    import warp as wp

    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--verts", default="10000")
    ap.add_argument("--spheres", default="1000")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp.init()
    dev = wp.get_device(a.device)
    res = {"machine": describe_device(dev), "rows": []}
    sort, update = world_mod.SphereOrder.sort, world_mod.SphereOrder.update
    for nv in [int(x) for x in a.verts.split(",")]:
        seq = wave_grid(int(round(np.sqrt(nv))))
        for ns in [int(x) for x in a.spheres.split(",")]:
            radius = float(min(0.05, 0.5 / np.sqrt(ns)))
            for variant in VARIANTS:
                world_mod.SphereOrder.sort = sort if variant != "spawn_order" else (lambda self, m, s, c: None)
                world_mod.SphereOrder.update = update if variant == "per_frame" else (lambda self, m, s, c: None)
                try:
                    w = make_world(seq, dev, "refit", spheres=ns, radius=radius, spread=0.9)
                    w.step()
                    w.capture()
                    t = time_loop(w.step, dev, a.steps, a.repeats, warmup=3)
                finally:
                    world_mod.SphereOrder.sort, world_mod.SphereOrder.update = sort, update
                perm = w.collider.sphere_order.order.numpy()[:ns]
                row = {"vertices": len(seq.V[0]), "spheres": ns, "variant": variant, **t,
                       "order_is_permutation": bool(np.array_equal(np.sort(perm), np.arange(ns)))}
                res["rows"].append(row)
                print(f"N={row['vertices']:>8} S={ns:>6} {variant:<12} {t['steps_per_s']:>9.0f} steps/s "
                      f"(permutation: {row['order_is_permutation']})", flush=True)
                del w
    write_json(Path(a.out) if a.out else RESULTS / f"sphere_order_probe_{'cuda' if dev.is_cuda else 'cpu'}.json", res)


if __name__ == "__main__":
    main()
