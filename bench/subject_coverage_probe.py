"""How well the conversion keeps a subject that shares its capture with static surroundings
(docs/conversion.md, "A static floor in the capture"): a GT npz whose first ``--subject``
vertices are the subject (``bench/unseen_variants.py --floor`` writes the floor last) goes
through issue 12's protocol input (``conversion_eval.varying_input``: remeshed, 1 % error) and
the default ``convert`` (graph, template segments), once per option set; per frame, the
coverage the conversion loses on the subject's GT vertices alone (distance to the output minus
distance to the input, / the subject's own bbox diagonal), so a floor's many vertices do not
hide it.

    python bench/subject_coverage_probe.py --sequence out/figure_floor.npz --subject 2312 \\
        --runs '{"adaptive": {}, "fixed spacing": {"adaptive_spacing": false}}'
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, checked_output, describe_device, write_json  # noqa: E402
from conversion_eval import add_input_args, probe_input  # noqa: E402

from dynmesh_warp.convert import nearest_surface, to_piecewise_fixed  # noqa: E402


def main(argv=None):
    import warp as wp

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_input_args(ap, None, 0.01)
    ap.add_argument("--subject", type=int, required=True, help="the subject's GT vertices are the first SUBJECT")
    ap.add_argument("--runs", default='{"defaults": {}}', help="JSON {label: {option: value}}")
    a = ap.parse_args(argv)
    out = Path(a.out) if a.out else RESULTS / f"subject_coverage_probe_{Path(a.sequence).stem}.json"
    checked_output(out, "file", "--out", [a.sequence if Path(a.sequence).exists() else None, a.cache])
    gt, var = probe_input(a)
    n = int(a.subject)
    T = gt.num_frames
    d_in = np.stack([nearest_surface(var.frames[t], gt.V[t], device=a.device).dist for t in range(T)])
    diag = np.array([np.linalg.norm(np.ptp(gt.V[t][:n], 0)) for t in range(T)])
    res = {"machine": describe_device(wp.get_device(a.device)), "sequence": a.sequence, "subject_vertices": n,
           "gt_vertices": gt.num_vertices, "frames": T, "error": a.error, "resolution": a.resolution, "runs": {}}
    for label, opts in json.loads(a.runs).items():
        t0 = time.perf_counter()
        fx = to_piecewise_fixed(var, strategy="graph", device=a.device, **opts)
        s = time.perf_counter() - t0
        frames = fx.frames if hasattr(fx, "frames") else [(fx.V[t], fx.F) for t in range(T)]
        lost = np.stack([nearest_surface(frames[t], gt.V[t], device=a.device).dist for t in range(T)]) - d_in
        lost /= diag[:, None]
        sub, rest = lost[:, :n].max(1), lost[:, n:].max(1) if gt.num_vertices > n else np.zeros(T)
        info = fx.conversion
        res["runs"][label] = {"options": opts, "seconds": s, "subject_lost_max": float(sub.max()),
                              "subject_lost_worst_frame": int(sub.argmax()),
                              "subject_frames_lost_over_3pct": np.nonzero(sub > 0.03)[0].tolist(),
                              "subject_lost_mean_over_frames": float(sub.mean()),
                              "rest_lost_max": float(rest.max()), "subject_lost_per_frame": sub.tolist(),
                              "key_frame": info.key_frame, "moving_part": getattr(info, "moving_part", None),
                              "segments": info.segments, "key_trials": info.key_trials,
                              "recovered_frames": info.recovered_frames}
        print(f"{label}: the subject's worst lost GT vertex {100 * sub.max():.1f} % of its diagonal (frame "
              f"{sub.argmax()}), frames over 3 %: {np.nonzero(sub > 0.03)[0].tolist()}, mean of the per-frame "
              f"worst {100 * sub.mean():.2f} %; the rest {100 * rest.max():.1f} %; moving part "
              f"{getattr(info, 'moving_part', None)}; {s:.1f} s")
    write_json(out, res)


if __name__ == "__main__":
    main()
