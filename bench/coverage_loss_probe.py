"""Where the conversion loses coverage the input has (issue 12; docs/evaluation.md): one
sequence through issue 12's protocol (bench/conversion_eval.py's input), converted by the
default strategy; per frame and GT vertex the distance to the converted surface minus the
distance to the input surface (fraction of the diagonal). Writes which GT vertices lose most,
how often, and how far they lie from the GT's centre (limbs' tips lie far out).

    python bench/coverage_loss_probe.py --sequence chicken_crossing --error 0
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, describe_device, write_json  # noqa: E402
from conversion_eval import _diag, add_input_args, probe_input  # noqa: E402

from dynmesh_warp.convert import nearest_surface, to_fixed_topology  # noqa: E402


def main(argv=None):
    import warp as wp

    ap = argparse.ArgumentParser()
    add_input_args(ap, "chicken_crossing", 0.0)
    a = ap.parse_args(argv)
    gt, var = probe_input(a)
    fx = to_fixed_topology(var, strategy="graph", device=a.device)
    T, N = gt.num_frames, gt.num_vertices
    K = fx.conversion.key_frame
    loss = np.zeros((T, N))
    cov_in, cov_out = np.zeros((T, N)), np.zeros((T, N))  # GT vertex -> input / output surface, / diagonal
    for t in range(T):
        d_in = nearest_surface(var.frames[t], gt.V[t], device=a.device).dist
        d_out = nearest_surface((fx.V[t], fx.F), gt.V[t], device=a.device).dist
        cov_in[t], cov_out[t] = d_in / _diag(gt.V[t]), d_out / _diag(gt.V[t])
        loss[t] = (d_out - d_in) / _diag(gt.V[t])
        if t == K:  # the template's own gap: each GT vertex's distance to the key frame's input
            # surface (the template) at the key frame; a vertex the template never had cannot be
            # kept by any fit of it
            key_gap = d_in / _diag(gt.V[K])
    radial = np.stack([np.linalg.norm(gt.V[t] - gt.V[t].mean(0), axis=1) / _diag(gt.V[t]) for t in range(T)])
    worst = loss.argmax(1)
    over = loss > 0.03
    lost_t, lost_v = np.nonzero(over)
    counts = over.sum(0)
    # how often the input itself shows each lost vertex (within 3 %): a part the input shows on
    # a few frames only (a thin tip thinned away by the remeshing on the others) is one a
    # temporally coherent template does not follow
    ever = np.nonzero(counts)[0]
    shown_in, shown_out = (cov_in[:, ever] <= 0.03).sum(0), (cov_out[:, ever] <= 0.03).sum(0)
    top = np.argsort(-counts)[:20]
    res = {"machine": describe_device(wp.get_device(a.device)), "sequence": a.sequence, "error": a.error,
           "frames": T, "gt_vertices": N, "key_frame": K,
           "loss_max_per_frame": loss.max(1).tolist(), "worst_vertex_per_frame": worst.tolist(),
           "vertices_over_3pct_per_frame": over.sum(1).tolist(),
           "vertices_ever_over_3pct": int((counts > 0).sum()),
           "most_often_over_3pct": [{"vertex": int(v), "frames": int(counts[v]),
                                    "radial_fraction_mean": float(radial[:, v].mean()),
                                    "radial_percentile": float((radial.mean(0) < radial[:, v].mean()).mean() * 100)}
                                   for v in top],
           "lost_vertices_input_shows_on_frames": {"median": float(np.median(shown_in)) if ever.size else None,
                                                    "min": int(shown_in.min()) if ever.size else None,
                                                    "max": int(shown_in.max()) if ever.size else None},
           "lost_vertices_output_shows_on_frames": {"median": float(np.median(shown_out)) if ever.size else None},
           "lost_vertices_median_distance_input_output": [float(np.median(np.median(cov_in[:, ever], 0))),
                                                          float(np.median(np.median(cov_out[:, ever], 0)))]
           if ever.size else None,
           "lost_vertices": [{"vertex": int(v), "lost_on": np.nonzero(over[:, v])[0].tolist(),
                              "input_shows_on": int(si), "output_shows_on": int(so),
                              "median_distance_input": float(np.median(cov_in[:, v])),
                              "median_distance_output": float(np.median(cov_out[:, v]))}
                             for v, si, so in zip(ever, shown_in, shown_out)],
           "frames_over_3pct": sorted(set(lost_t.tolist())),
           "key_gap_max": float(key_gap.max()),
           "lost_with_key_gap_over_1pct": float((key_gap[lost_v] > 0.01).mean()) if lost_v.size else None,
           "lost_with_key_gap_over_2pct": float((key_gap[lost_v] > 0.02).mean()) if lost_v.size else None,
           "all_with_key_gap_over_1pct": float((key_gap > 0.01).mean()),
           "lost_vertex_frames": [[int(t), int(v), float(loss[t, v]), float(key_gap[v])]
                                  for t, v in zip(lost_t, lost_v)][:400],
           "worst_vertex_radial_percentile_per_frame": [
               float((radial[t] < radial[t, worst[t]]).mean() * 100) for t in range(T)]}
    print(f"{a.sequence}: vertices ever > 3 %: {res['vertices_ever_over_3pct']} of {N}; per frame mean "
          f"{over.sum(1).mean():.1f}; the worst vertex's radial percentile (median over frames) "
          f"{np.median(res['worst_vertex_radial_percentile_per_frame']):.0f}; (frame, vertex) pairs over 3 % "
          f"whose GT vertex the template (key frame {K}) misses by > 1 % / 2 % of the diagonal: "
          f"{res['lost_with_key_gap_over_1pct']} / {res['lost_with_key_gap_over_2pct']} "
          f"(all vertices > 1 %: {res['all_with_key_gap_over_1pct']:.3f}); frames with a vertex over 3 %: "
          f"{res['frames_over_3pct']}; the lost vertices are within 3 % of the input on "
          f"{res['lost_vertices_input_shows_on_frames']} of {T} frames, of the output on "
          f"{res['lost_vertices_output_shows_on_frames']}")
    write_json(Path(a.out) if a.out else RESULTS / f"coverage_loss_probe_{a.sequence}_e{a.error:g}.json", res)


if __name__ == "__main__":
    main()
