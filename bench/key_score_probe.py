"""Which GT-free score ranks the key trials' runs like the ground truth does, on a capture whose
subject shares the frame with static surroundings (docs/conversion.md, "A static floor in the
capture")? Each key frame the trials would try (the automatic one and ``key_candidates``) is
converted alone (``to_fixed_topology``, graph, ``key_frame`` fixed) from issue 12's protocol
input; per run the GT figure (the subject's worst lost GT vertex per frame, as in
``subject_coverage_probe.py``) and the per-frame distances every GT-free score is made of (each
input vertex to the output surface, each output vertex to the input surface) are stored in
``--store`` so that scores can be compared without converting again.

    python bench/key_score_probe.py --sequence out/figure_floor_walk.npz --subject 2312 \\
        --store out/keyscore/walk
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, checked_output, describe_device, write_json  # noqa: E402
from conversion_eval import add_input_args, probe_input  # noqa: E402

from dynmesh_warp.conversion_options import option_defaults  # noqa: E402
from dynmesh_warp.outputs import add_to_manifest, atomic_write_npz  # noqa: E402
from dynmesh_warp.convert import _as_varying, nearest_surface, to_fixed_topology  # noqa: E402
from dynmesh_warp.convert_input import _candidate_keys, _chamfer_to_input, _key_frame  # noqa: E402


def main(argv=None):
    import warp as wp

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_input_args(ap, None, 0.01)
    ap.add_argument("--subject", type=int, required=True, help="the subject's GT vertices are the first SUBJECT")
    ap.add_argument("--keys", default=None, help="comma-separated key frames (default: the automatic one and "
                    "the key_candidates the trials try)")
    ap.add_argument("--store", required=True, help="folder for each run's per-frame distances (npz)")
    a = ap.parse_args(argv)
    out = Path(a.out) if a.out else RESULTS / f"key_score_probe_{Path(a.sequence).stem}.json"
    inputs = [a.sequence if Path(a.sequence).exists() else None, a.cache]
    store = checked_output(a.store, "folder", "--store", inputs, writes=["k*.npz"])
    checked_output(out, "file", "--out", [*inputs, store])
    gt, var = probe_input(a)
    vseq = _as_varying(var)
    n, T = int(a.subject), gt.num_frames
    if a.keys:
        keys = [int(k) for k in a.keys.split(",")]
    else:
        K = _key_frame(vseq, "auto", False)
        keys = [K] + _candidate_keys(T, int(option_defaults("graph")["key_candidates"]), K)
    store.mkdir(parents=True, exist_ok=True)
    d_in = np.stack([nearest_surface(var.frames[t], gt.V[t], device=a.device).dist for t in range(T)])
    diag = np.array([np.linalg.norm(np.ptp(gt.V[t][:n], 0)) for t in range(T)])
    res = {"machine": describe_device(wp.get_device(a.device)), "sequence": a.sequence, "subject_vertices": n,
           "frames": T, "error": a.error, "resolution": a.resolution, "keys": keys, "runs": {}}
    for k in keys:
        t0 = time.perf_counter()
        fx = to_fixed_topology(var, strategy="graph", device=a.device, key_frame=k)
        s = time.perf_counter() - t0
        lost = np.stack([nearest_surface((fx.V[t], fx.F), gt.V[t], device=a.device).dist for t in range(T)]) - d_in
        sub = (lost[:, :n] / diag[:, None]).max(1)
        d_io = [nearest_surface((fx.V[t], fx.F), var.frames[t][0], device=a.device).dist for t in range(T)]
        d_oi = [nearest_surface(var.frames[t], fx.V[t], device=a.device).dist for t in range(T)]
        atomic_write_npz(store / f"k{k}.npz", V=fx.V, F=fx.F, subject_lost=sub,
                         d_io=np.concatenate(d_io).astype(np.float32), n_io=[len(x) for x in d_io],
                         d_oi=np.stack(d_oi).astype(np.float32), coverage=fx.conversion.coverage, web=fx.conversion.web)
        add_to_manifest(store, f"k{k}.npz")  # written by this tool: a rerun may replace it
        info = fx.conversion
        res["runs"][str(k)] = {"seconds": s, "subject_lost_max": float(sub.max()),
                               "subject_lost_mean_over_frames": float(sub.mean()),
                               "subject_frames_lost_over_3pct": np.nonzero(sub > 0.03)[0].tolist(),
                               "chamfer_to_input": _chamfer_to_input(fx, vseq, a.device),
                               "coverage_mean": float(np.mean(info.coverage)),
                               "coverage_max": float(np.max(info.coverage)),
                               "moving_part": info.moving_part, "recovered_frames": info.recovered_frames}
        r = res["runs"][str(k)]
        print(f"key {k}: subject worst {100 * sub.max():.2f} %, mean {100 * sub.mean():.2f} %, "
              f"frames over 3 % {len(r['subject_frames_lost_over_3pct'])}; chamfer {r['chamfer_to_input']:.4e}, "
              f"coverage mean {100 * r['coverage_mean']:.3f} %; {s:.0f} s", flush=True)
    write_json(out, res)


if __name__ == "__main__":
    main()
