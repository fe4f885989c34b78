"""What the hand-written mesh codecs buy next to trimesh and meshio (docs/dependencies.md).

For one mesh of about N vertices (an icosphere, subdivided), writes it as OBJ, OFF and binary
PLY and times reading it back with ``dynmesh_warp.io.read_mesh`` (own OBJ/OFF readers; PLY
through trimesh), ``trimesh.load(process=False, maintain_order=True)`` and ``meshio.read``;
and writing with our writers vs trimesh's export. Best of ``--repeats``. Also records which
readers keep the vertex order and which accept a malformed file (a face index 0 in an OBJ,
past the vertex count in an OFF) silently, crash, or report it.

    python bench/bench_io.py --subdivisions 7 --out bench/results/io_cpu.json
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import RESULTS, describe_device, write_json  # noqa: E402
from dynmesh_warp.io import read_mesh, write_mesh  # noqa: E402


def best(fn, repeats):
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return min(ts), out


def main(argv=None):
    import meshio
    import trimesh

    ap = argparse.ArgumentParser()
    ap.add_argument("--subdivisions", type=int, default=7)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(RESULTS / "io_cpu.json"))
    a = ap.parse_args(argv)
    m = trimesh.creation.icosphere(subdivisions=a.subdivisions)
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(m.vertices))  # a vertex order no reader would produce by itself
    V = np.asarray(m.vertices, np.float32)[perm]
    F = np.argsort(perm)[m.faces].astype(np.int32)
    res = {"machine": describe_device("cpu"), "vertices": len(V), "faces": len(F), "read_s": {}, "write_s": {},
           "keeps_vertex_order": {}, "malformed": {}}
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        for ext in ("obj", "off", "ply"):
            p = d / f"m.{ext}"
            t, _ = best(lambda p=p: write_mesh(p, V, F), a.repeats)
            res["write_s"][f"ours_{ext}"] = t
            q = d / f"t.{ext}"
            if ext != "off":
                t, _ = best(lambda q=q: trimesh.Trimesh(V, F, process=False).export(str(q)), a.repeats)
                res["write_s"][f"trimesh_{ext}"] = t
            readers = {"ours": lambda p=p: read_mesh(p),
                       "trimesh": lambda p=p: (lambda t: (t.vertices, t.faces))(
                           trimesh.load(str(p), process=False, maintain_order=True)),
                       "meshio": lambda p=p: (lambda mm: (mm.points, mm.cells_dict.get("triangle")))(meshio.read(str(p)))}
            for name, fn in readers.items():
                try:
                    t, (Vr, Fr) = best(fn, a.repeats)
                except Exception as e:  # noqa: BLE001 - recorded
                    res["read_s"][f"{name}_{ext}"] = f"failed: {type(e).__name__}"
                    continue
                res["read_s"][f"{name}_{ext}"] = t
                Vr = np.asarray(Vr)
                res["keeps_vertex_order"][f"{name}_{ext}"] = bool(
                    Vr.shape == V.shape and np.allclose(Vr, V, atol=1e-6))
        # malformed files
        (d / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n")
        (d / "bad.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
        for f in ("bad.obj", "bad.off"):
            for name, fn in (("ours", lambda f=f: read_mesh(d / f)),
                             ("trimesh", lambda f=f: trimesh.load(str(d / f), process=False)),
                             ("meshio", lambda f=f: meshio.read(str(d / f)))):
                try:
                    fn()
                    res["malformed"][f"{name}_{f}"] = "accepted silently"
                except Exception as e:  # noqa: BLE001 - recorded
                    res["malformed"][f"{name}_{f}"] = f"{type(e).__name__}: {str(e)[:120]}"
    write_json(Path(a.out), res)
    print(res["read_s"], res["write_s"], res["keeps_vertex_order"], res["malformed"], sep="\n")


if __name__ == "__main__":
    main()
