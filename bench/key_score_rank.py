"""Rank the runs stored by ``key_score_probe.py`` by the key trials' GT-free scores (the mean
Chamfer distance to the input, ``convert._chamfer_to_input``; the moving points' score,
``convert._moving_score``: the mean of the largest ``MOVING_SCORE_TAIL`` of their distances to
the output, pooled over the frames; beside it the same tail at other fractions and the previous
score, the mean over frames of their mean squared distance) and set each score's pick against
the ground truth (the subject's worst lost GT vertex, frames over 3 %, the mean of the per-frame
worst; docs/conversion.md, "Ranking the key trials on the moving points"). Per score and scene
also ``margin``: the best score of a run that lost a part on 3 or more frames over the best
score of a run that lost one on at most 1 (how far apart the score keeps them; > 1: apart).

    python bench/key_score_rank.py out/keyscore/figure_floor_walk out/keyscore/figure_floor25 \\
        --out bench/results/key_score_rank_cpu.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import checked_output, describe_device, write_json  # noqa: E402
from conversion_eval import ground_truth, varying_input  # noqa: E402

from dynmesh_warp.convert import ConversionInfo, _as_varying  # noqa: E402
from dynmesh_warp.convert_input import _moving_distances, _moving_points, _moving_score_of, _tail_mean  # noqa: E402
from dynmesh_warp.convert_report import MOVING_SCORE_TAIL  # noqa: E402
from dynmesh_warp.sequence import FixedTopologySequence  # noqa: E402


#: the tail fractions reported beside the default (MOVING_SCORE_TAIL)
TAILS = (0.001, 0.002, 0.003, 0.005, 0.01, 0.02, 0.05)


def main(argv=None):
    import warp as wp

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stores", nargs="+", help="key_score_probe.py --store folders (their .json beside them)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cache", default=str(Path(__file__).resolve().parents[1] / "out" / "cache"))
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.out:
        checked_output(a.out, "file", "--out", [*a.stores, *(f"{f}.json" for f in a.stores), a.cache])
    wp.init()
    res = {"machine": describe_device(wp.get_device(a.device)), "scenes": {}}
    for folder in map(Path, a.stores):
        meta = json.loads(Path(f"{folder}.json").read_text())
        gt = ground_truth(meta["sequence"], None)
        var = _as_varying(varying_input(gt, meta["resolution"], meta["error"], a.device, Path(a.cache)))
        t0 = time.perf_counter()
        moving = _moving_points(var, a.device)
        seconds_points = time.perf_counter() - t0
        runs = {}
        for k in meta["keys"]:
            z = np.load(folder / f"k{k}.npz")
            out = FixedTopologySequence(z["V"], z["F"])
            out.conversion = ConversionInfo("graph", {}, len(z["V"]), z["V"].shape[1])
            r = meta["runs"][str(k)]
            d = _moving_distances(out, var, moving, a.device)
            pooled = np.concatenate(d)
            runs[k] = {"moving_score": _moving_score_of(d), "chamfer": r["chamfer_to_input"],
                       "mean_squared": float(np.mean([np.mean(x ** 2) if len(x) else 0.0 for x in d])),
                       **{f"tail_{q:g}": _tail_mean(pooled, q) for q in TAILS},
                       "gt_worst": r["subject_lost_max"], "gt_frames_over_3pct": len(r["subject_frames_lost_over_3pct"]),
                       "gt_mean": r["subject_lost_mean_over_frames"]}
        auto = meta["keys"][0]
        scores = ("moving_score", "chamfer", "mean_squared", *(f"tail_{q:g}" for q in TAILS))
        picks = {s: min(runs, key=lambda k: runs[k][s]) for s in scores}
        good = [k for k in runs if runs[k]["gt_frames_over_3pct"] <= 1]
        bad = [k for k in runs if runs[k]["gt_frames_over_3pct"] >= 3]
        margin = ({s: min(runs[k][s] for k in bad) / max(min(runs[k][s] for k in good), 1e-30) for s in scores}
                  if good and bad else None)
        res["scenes"][folder.name] = {"sequence": meta["sequence"], "automatic_key": auto, "runs": runs,
                                      "kept_by": picks, "margin": margin,
                                      "moving_points_per_frame": float(np.mean([len(m) for m in moving])),
                                      "seconds_moving_points": seconds_points}
        print(f"{folder.name} ({np.mean([len(m) for m in moving]):.0f} moving points a frame): GT worst / frames "
              "over 3 % / mean of the per-frame worst")
        for k, r in runs.items():
            tags = [s for s, p in picks.items() if p == k] + (["automatic"] if k == auto else [])
            print(f"  key {k:3d}: moving {r['moving_score']:.3e}, chamfer {r['chamfer']:.3e} | {100 * r['gt_worst']:.1f} % / "
                  f"{r['gt_frames_over_3pct']} / {100 * r['gt_mean']:.2f} %  {' '.join(tags)}")
    res["moving_score_tail"] = MOVING_SCORE_TAIL
    res["summary"] = {}
    print("per score: the kept runs' GT worst / frames over 3 % / mean of the per-frame worst, summed over the "
          "scenes; the least margin")
    for s in next(iter(res["scenes"].values()))["kept_by"]:
        kept = [sc["runs"][sc["kept_by"][s]] for sc in res["scenes"].values()]
        margins = [sc["margin"][s] for sc in res["scenes"].values() if sc["margin"]]
        res["summary"][s] = {"gt_worst_sum": sum(r["gt_worst"] for r in kept),
                             "gt_frames_over_3pct_sum": sum(r["gt_frames_over_3pct"] for r in kept),
                             "gt_mean_sum": sum(r["gt_mean"] for r in kept), "least_margin": min(margins, default=None)}
        x = res["summary"][s]
        print(f"  {s:14s} {100 * x['gt_worst_sum']:.2f} / {x['gt_frames_over_3pct_sum']} / {100 * x['gt_mean_sum']:.2f}"
              f", least margin {x['least_margin'] or 0:.2f}")
    if a.out:
        write_json(Path(a.out), res)


if __name__ == "__main__":
    main()
