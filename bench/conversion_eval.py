"""Conversion accuracy on reconstruction-like input (docs/evaluation.md, issue 12 protocol).

For each sequence: the ground truth (GT, fixed topology) is re-meshed per frame by marching
cubes and given smooth reconstruction-like error along the normals (RMS ``--error`` x the bbox
diagonal; 0 = noise-free), then converted back to one fixed topology by each strategy. Per frame:

* CD (DG-Mesh convention: vertices, squared L2, mean per direction, directions averaged) of the
  varying input and of the converted output against the GT vertices; the increase in percent;
* coverage: the distance of every GT vertex to the converted surface; its maximum over the GT
  vertices (the worst uncovered GT vertex) as a fraction of the GT's bbox diagonal;
* the converted vertices' distance to the GT surface (the other side), 99th percentile;
* the surface that is not there: the fraction of the converted surface's area whose faces'
  centroids lie farther than 2 % / 5 % of the diagonal from the GT surface (``spurious_area_2``,
  ``_5``; a web of faces stretched across a gap between parts shows here, not in vertex figures);
* triangle quality: the 1st percentile and the minimum of the faces' smallest angles [degrees];
* the coverage the conversion lost: per GT vertex, its distance to the converted surface minus
  its distance to that frame's input surface; the maximum over the GT vertices (a part the input
  has and the output dropped shows here even where the input itself misses other parts).
* the surface velocity against the GT's (``evaluate.surface_velocity_error``): per frame pair
  within a template segment, each converted vertex's displacement against the GT's at its
  nearest GT point; 99th percentile and maximum over the vertices (fractions of the diagonal per
  frame): a template sliding along the surface, which no per-frame figure sees;
* the drift (``evaluate.surface_drift``): each converted vertex's distance, per frame, to the GT
  point it stood on at its segment's key frame, carried by the GT; median and 99th percentile
  over the vertices: a slow slide that adds up over frames shows here.

A strategy named ``S/piecewise`` (e.g. ``graph/piecewise``) runs ``to_piecewise_fixed`` (new
template segments where one template cannot follow). Summaries report the mean and the worst
frame. Writes bench/results/conversion_eval_<device>.json and, next to it, a Markdown table
(.md) and a per-frame plot (.png: the worst uncovered GT vertex per frame, input and each
strategy, one panel per sequence). ``--plot-only JSON``
redraws both from an earlier result.

    python bench/conversion_eval.py --device cuda --sequences all --error 0.01
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"
if not DATA.exists():
    DATA = ROOT / ".gpu" / "data"

from dynmesh_warp.convert import nearest_surface, slide_ratio, to_fixed_topology, to_piecewise_fixed  # noqa: E402
from dynmesh_warp.evaluate import surface_drift, surface_velocity_error  # noqa: E402
from dynmesh_warp.metrics import chamfer_distance  # noqa: E402
from dynmesh_warp.sequence import FixedTopologySequence  # noqa: E402

SHARED = ("horse_gallop", "horse_collapse", "pcow", "chicken_crossing")
SOURCES = {
    "horse_gallop": "Sumner & Popovic 2004 (deformation transfer), horse-gallop",
    "horse_collapse": "Sumner & Popovic 2004, horse-collapse",
    "pcow": "Briceno et al. 2003 (geometry videos), elastic cow",
    "chicken_crossing": "James & Twigg 2005 (skinning mesh animations), chicken crossing",
    "articulated_figure": "built-in: dynmesh_warp.scenes.articulated_figure (jumping jacks)",
}


#: a converted face whose centroid lies farther than these fractions of the GT diagonal from the
#: GT surface counts in ``spurious_area_2`` / ``_5``: 2 % is twice the protocol's 1 % RMS error
#: (its peaks reach 2.9-3.9 %, error_peak_cpu.json, so at 1 % error the input itself has area
#: there); 5 % is above those peaks
SPURIOUS_GAPS = (0.02, 0.05)


def _diag(V):
    return float(np.linalg.norm(np.ptp(np.asarray(V, np.float64), axis=0)))


def ground_truth(name: str, frames: int | None) -> FixedTopologySequence | None:
    from dynmesh_warp.remesh import resample_time

    if name == "articulated_figure":
        from dynmesh_warp.scenes import articulated_figure

        return articulated_figure(frames=frames or 60, resolution=72)
    from dynmesh_warp.io import load_sequence

    path = Path(name) if name.endswith(".npz") else DATA / f"{name}.npz"  # a path: any fixed-topology npz
    if not path.exists():
        return None
    gt = load_sequence(path)
    if frames and frames != gt.num_frames:
        gt = FixedTopologySequence(resample_time(gt, frames), gt.F, fps=gt.fps, name=gt.name)
    return gt


def varying_input(gt, resolution: int, error: float, device, cache: Path | None):
    from dynmesh_warp.io import load_sequence, save_sequence
    from dynmesh_warp.remesh import remesh_sequence

    cf = cache / f"{gt.name}_T{gt.num_frames}_r{resolution}_e{error:g}.npz" if cache else None
    if cf is not None and cf.exists():
        return load_sequence(cf, kind="varying")
    var = remesh_sequence(gt, resolution=resolution, error=error, device=device)
    if cf is not None:
        cf.parent.mkdir(parents=True, exist_ok=True)
        save_sequence(var, cf)
    return var


def add_input_args(ap, sequence: str | None, error: float) -> None:
    """The arguments of a probe that takes one sequence through this protocol's input:
    --sequence (a name or a GT npz; required when ``sequence`` is None), --error, --resolution,
    --device, --cache, --out."""
    if sequence is None:
        ap.add_argument("--sequence", required=True, help="a sequence name or a GT npz (V, F, fps)")
    else:
        ap.add_argument("--sequence", default=sequence)
    ap.add_argument("--error", type=float, default=error)
    ap.add_argument("--resolution", type=int, default=96)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cache", default=str(Path(__file__).resolve().parents[1] / "out" / "cache"))
    ap.add_argument("--out", default=None)


def probe_input(a) -> tuple:
    """(GT, varying input) of the parsed :func:`add_input_args` arguments ``a`` (Warp initialised)."""
    import warp as wp

    wp.init()
    gt = ground_truth(a.sequence, None)
    if gt is None:
        raise SystemExit(f"{a.sequence}: not found")
    return gt, varying_input(gt, a.resolution, a.error, a.device, Path(a.cache))


def frame_metrics(gt_V, gt_F, V, F, device, cov_input=None) -> dict:
    """One frame's figures (fractions of the GT's diagonal); ``cov_input``: each GT vertex's
    distance to the input surface of the frame, for the coverage the conversion lost."""
    diag = _diag(gt_V)
    cd = chamfer_distance(V, gt_V, squared=True, device=device)
    cov = nearest_surface((V, F), gt_V, device=device).dist  # GT vertex -> output surface
    acc = nearest_surface((gt_V, gt_F), V, device=device).dist  # output vertex -> GT surface
    tri = np.asarray(V, np.float64)[np.asarray(F)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    d_gt = nearest_surface((gt_V, gt_F), tri.mean(axis=1), device=device).dist / diag
    m = {"cd": cd.value, "uncovered_max": float(cov.max()) / diag,
         "uncovered_p99": float(np.percentile(cov, 99)) / diag,
         "off_surface_p99": float(np.percentile(acc, 99)) / diag,
         **{f"spurious_area_{int(100 * g)}": float(area[d_gt > g].sum() / max(area.sum(), 1e-30))
            for g in SPURIOUS_GAPS}}
    if cov_input is not None:  # per GT vertex: how much farther the output is than the input
        m["coverage_loss_max"] = float((cov - cov_input).max()) / diag
    ang = _min_angles(V, F)  # triangle quality [degrees]: each face's smallest angle
    m["min_angle_p1"] = float(np.percentile(ang, 1))
    m["min_angle_min"] = float(ang.min())
    return m, cov


def _min_angles(V, F) -> np.ndarray:
    """Each triangle's smallest interior angle [degrees] (0 for a degenerate one)."""
    P = np.asarray(V, np.float64)[np.asarray(F)]
    out = np.full(len(P), 180.0)
    for i in range(3):
        u = P[:, (i + 1) % 3] - P[:, i]
        w = P[:, (i + 2) % 3] - P[:, i]
        nu, nw = np.linalg.norm(u, axis=1), np.linalg.norm(w, axis=1)
        c = np.einsum("ij,ij->i", u, w) / np.maximum(nu * nw, 1e-30)
        a = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
        out = np.minimum(out, np.where((nu > 0) & (nw > 0), a, 0.0))
    return out


def evaluate(name, strategies, args, device) -> dict | None:
    gt = ground_truth(name, args.frames)
    if gt is None:
        print(f"skip {name}: not found")
        return None
    t0 = time.perf_counter()
    var = varying_input(gt, args.resolution, args.error, device, Path(args.cache) if args.cache else None)
    prep = time.perf_counter() - t0
    T = gt.num_frames
    inp, cov_in = zip(*[frame_metrics(gt.V[t], gt.F, *var.frames[t], device) for t in range(T)])
    inp = list(inp)
    out = {"scene": name, "source": SOURCES.get(name, name), "frames": T, "gt_vertices": int(gt.num_vertices),
           "input_vertices": [int(min(len(v) for v, _ in var.frames)), int(max(len(v) for v, _ in var.frames))],
           "resolution": args.resolution, "error": args.error, "prepare_s": prep,
           "input": _summ(inp), "input_per_frame": inp, "strategies": {}}
    for label in strategies:
        s, _, mode = label.partition("/")
        run = to_piecewise_fixed if mode == "piecewise" else to_fixed_topology
        given = json.loads(args.options) if args.options else {}
        opts = given.get(label, given.get(s, {}))  # keyed by the label (graph/piecewise) or the strategy (graph)
        # warm-up (kernel compilation) on 2 frames (a chosen key frame is the run's, not the warm-up's)
        to_fixed_topology(type(var)(var.frames[:2], fps=var.fps, name=var.name), strategy=s, device=device,
                          **{k: v for k, v in opts.items() if k != "key_frame"})
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        fx = run(var, strategy=s, device=device, **opts)
        wp.synchronize_device(device)
        sec = time.perf_counter() - t0
        per = [frame_metrics(gt.V[t], gt.F, *fx.frame(t), device, cov_in[t])[0] for t in range(T)]
        info = fx.conversion
        summ = _summ(per)
        summ["cd_increase_pct"] = 100.0 * (summ["cd_mean"] / out["input"]["cd_mean"] - 1.0)
        summ["worst_frame_cd_ratio"] = max(p["cd"] / max(q["cd"], 1e-30) for p, q in zip(per, inp))
        vel = surface_velocity_error(gt, fx, device)  # the surface velocity against the GT's
        summ.update({f"velocity_error_{k}": v for k, v in vel.items() if k != "pairs"})
        drift = surface_drift(gt, fx, device)  # how far the vertices slid from their GT points since the key frame
        slide = slide_ratio(info)[0]
        summ.update({f"drift_{k}": v for k, v in drift.items() if k != "frames"})
        out["strategies"][label] = {"summary": summ, "seconds": sec, "per_frame": per, "velocity_per_pair": vel["pairs"],
                                "drift_per_frame": drift["frames"],
                                "slide_ratio": slide, "frame_motion": list(info.frame_motion),
                                "input_motion": list(info.input_motion),
                                "key_frame": info.key_frame, "coverage": info.coverage,
                                "web": info.web, "buried": info.buried,
                                "segments": [list(x) for x in info.segments],
                                "recovered_frames": [list(r) for r in info.recovered_frames],
                                "key_trials": [list(x) for x in info.key_trials],
                                "options": {k: v for k, v in info.options.items()}}
        print(f"{name:18s} {label:16s} CD in {out['input']['cd_mean'] * 1e3:.4f} out {summ['cd_mean'] * 1e3:.4f} "
              f"({summ['cd_increase_pct']:+.0f}%), worst frame ratio {summ['worst_frame_cd_ratio']:.2f}, "
              f"uncovered max {100 * summ['uncovered_max_max']:.2f}% (mean {100 * summ['uncovered_max_mean']:.2f}%), "
              f"coverage lost max {100 * summ['coverage_loss_max_max']:.2f}%, "
              f"spurious area >2%/5% max {100 * summ['spurious_area_2_max']:.2f}/{100 * summ['spurious_area_5_max']:.2f}% "
              f"(input {100 * out['input']['spurious_area_2_max']:.2f}/{100 * out['input']['spurious_area_5_max']:.2f}%), "
              f"surface velocity error p99 mean {100 * (summ['velocity_error_p99_mean'] or np.nan):.2f}% / worst pair "
              f"{100 * (summ['velocity_error_p99_max'] or np.nan):.2f}% (the GT's own p99 "
              f"{100 * (summ['velocity_error_gt_p99_mean'] or np.nan):.2f}%), "
              f"drift median {100 * (summ['drift_p50_mean'] or np.nan):.2f}% / "
              f"p99 {100 * (summ['drift_p99_mean'] or np.nan):.2f}% "
              f"(worst frame p99 {100 * (summ['drift_p99_max'] or np.nan):.2f}%), "
              f"slide {slide or np.nan:.2f}x, "
              f"{len(info.segments)} segment(s), {sec:.1f} s", flush=True)
    return out


def _summ(per):
    keys = per[0].keys()
    s = {}
    for k in keys:
        a = np.array([p[k] for p in per])
        s[f"{k}_mean"] = float(a.mean())
        s[f"{k}_max"] = float(a.max())
        s[f"{k}_worst_frame"] = int(a.argmax())
    return s


def report(path: Path):
    """Write PATH.md (table: mean and worst) and PATH.png (per-frame worst uncovered GT vertex)."""
    doc = json.loads(Path(path).read_text())
    rows = ["| sequence (frames, GT vertices) | input CD | input worst uncovered | strategy | CD | vs input | "
            "worst-frame CD ratio | worst uncovered (mean over frames) | coverage lost, worst | key frame | "
            "recovered frames | s |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for sc in doc["scenes"]:
        i = sc["input"]
        for k, v in sc["strategies"].items():
            m = v["summary"]
            lost = f"{100 * m['coverage_loss_max_max']:.1f}%" if "coverage_loss_max_max" in m else "–"
            rows.append(f"| {sc['scene']} ({sc['frames']}, {sc['gt_vertices']}) | {1e3 * i['cd_mean']:.3f} | "
                        f"{100 * i['uncovered_max_max']:.1f}% | {k} | {1e3 * m['cd_mean']:.3f} | "
                        f"{m['cd_increase_pct']:+.0f}% | {m['worst_frame_cd_ratio']:.2f} | "
                        f"{100 * m['uncovered_max_max']:.1f}% ({100 * m['uncovered_max_mean']:.1f}%) | "
                        f"{lost} | {v.get('key_frame', 0)} | {len(v['recovered_frames'])} | {v['seconds']:.1f} |")
    md = Path(path).with_suffix(".md")
    md.write_text(f"Conversion evaluation on {doc['device_name']} ({doc['device']}), error {doc['args']['error']}, "
                  f"resolution {doc['args']['resolution']}; CD x1e-3 (vertices, squared)\n\n" + "\n".join(rows) + "\n")
    print("wrote", md)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plot")
        return
    n = len(doc["scenes"])
    fig, axes = plt.subplots(n, 1, figsize=(8, 2.4 * n), squeeze=False)
    for ax, sc in zip(axes[:, 0], doc["scenes"]):
        ax.plot([100 * p["uncovered_max"] for p in sc["input_per_frame"]], "k--", label="varying input")
        for k, v in sc["strategies"].items():
            ax.plot([100 * p["uncovered_max"] for p in v["per_frame"]], label=k)
        ax.set_title(sc["scene"], fontsize=9)
        ax.set_ylabel("worst uncovered\nGT vertex [% diag]", fontsize=8)
        ax.set_yscale("log")
    axes[-1, 0].set_xlabel("frame")
    axes[0, 0].legend(fontsize=7, ncol=5)
    fig.tight_layout()
    png = Path(path).with_suffix(".png")
    fig.savefig(png, dpi=90)
    print("wrote", png)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--sequences", default="all")
    ap.add_argument("--strategies", default="graph,regularized")
    ap.add_argument("--frames", type=int, default=None, help="resample time to this many frames")
    ap.add_argument("--resolution", type=int, default=96)
    ap.add_argument("--error", type=float, default=0.01)
    ap.add_argument("--options", default=None,
                    help='JSON {strategy or label: {option: value}}, e.g. {"graph": {"iterations": 4}}')
    ap.add_argument("--cache", default=str(ROOT / "out" / "cache"))
    ap.add_argument("--out", default=None)
    ap.add_argument("--plot-only", default=None, help="redraw the table and plot of this result JSON")
    args = ap.parse_args()
    if args.plot_only:
        report(Path(args.plot_only))
        return
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    names = list(SHARED) + ["articulated_figure"] if args.sequences == "all" else args.sequences.split(",")
    res = []
    for n in names:
        r = evaluate(n, args.strategies.split(","), args, device)
        if r is not None:
            res.append(r)
    doc = {"machine": platform.node(), "processor": platform.processor() or platform.machine(),
           "device": str(device), "device_name": getattr(device, "name", str(device)),
           "warp": wp.__version__, "args": vars(args), "scenes": res}
    out = Path(args.out) if args.out else ROOT / "bench" / "results" / f"conversion_eval_{device.alias.split(':')[0]}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    from dynmesh_warp.outputs import atomic_write_json

    atomic_write_json(out, doc)
    print("wrote", out)
    report(out)


if __name__ == "__main__":
    main()
