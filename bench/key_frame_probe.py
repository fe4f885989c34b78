"""Issue 12 probe: does a second key frame help? Two trackings of a sequence (A: key frame
auto; B: key frame K2) under the issue-12 protocol (1 % smooth error, remeshed at 96, CPU),
B carried onto A's template by a barycentric transfer at a handover frame (the frame between
the keys where both fit the input best), and the better of A / transferred B kept per frame by
a GT-free score (99.5th percentile of input -> output distance). Reports CD vs the input for A,
transferred B, the per-frame choice and the oracle choice.

    python bench/key_frame_probe.py pcow 30          # -> bench/results/key_frame_probe_pcow_30_cpu.json
    python bench/key_frame_probe.py pcow 30 pose     # + ..._pose_cpu.json (or fine)

With a mode, a third run: A guided by transferred B on the frames on B's side of the handover:
"pose" fits A's graph to the transferred surface and A's fit of the real frame starts from that
pose; "fine" starts A's fine stage from the transferred vertices; the better coverage kept per
frame. That run is an experiment on the converter's internals (it wraps the private
``convert_fit._Converter.step_graph`` and calls its private helpers), not a use of the public API:
it may break with the converter, and both modes were measured worse (docs/conversion.md).
"""
import json
import sys
import time
from pathlib import Path

import numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parent))
import warp as wp  # noqa: E402

wp.config.quiet = True
from common import RESULTS, describe_device, write_json  # noqa: E402
from conversion_eval import ground_truth, varying_input  # noqa: E402
import dynmesh_warp.convert_fit as cv  # noqa: E402
from dynmesh_warp.convert import nearest_surface, to_fixed_topology  # noqa: E402
from dynmesh_warp.convert_base import _device_frame  # noqa: E402
from dynmesh_warp.metrics import chamfer_distance  # noqa: E402


def main():
    if len(sys.argv) > 1 and sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        return
    name = sys.argv[1] if len(sys.argv) > 1 else "pcow"
    K2 = int(sys.argv[2]) if len(sys.argv) > 2 else 30
    MODE = sys.argv[3] if len(sys.argv) > 3 else None  # the guided third run (below), before any work
    if MODE not in (None, "pose", "fine"):
        raise SystemExit(f"mode {MODE!r}: pose or fine")
    gt = ground_truth(name, None)
    var = varying_input(gt, 96, 0.01, "cpu", Path("out/cache"))
    T = gt.num_frames
    t0 = time.time()
    A = to_fixed_topology(var, strategy="graph", device="cpu")
    B = to_fixed_topology(var, strategy="graph", device="cpu", key_frame=K2)
    print("converted", time.time() - t0, "keys", A.conversion.key_frame, B.conversion.key_frame, flush=True)
    def score(V, F, t):
        iv, iF = var.frames[t]
        d1 = nearest_surface((V, F), iv).dist
        return float(np.percentile(d1, 99.5))
    sA = np.array([score(A.V[t], A.F, t) for t in range(T)])
    sB = np.array([score(B.V[t], B.F, t) for t in range(T)])
    # handover: between the two keys, the frame where both fit best
    kA, kB = A.conversion.key_frame, B.conversion.key_frame
    lo, hi = sorted((kA, kB))
    rng = np.arange(lo, hi + 1)
    h = int(rng[np.argmin((sA + sB)[rng])])
    ns = nearest_surface((B.V[h], B.F), A.V[h])
    fB = B.F[ns.face]  # (N,3)
    VBA = np.einsum("nk,tnkd->tnd", ns.bary, B.V[:, fB])  # (T, N, 3) B's surface at A's vertices
    sBA = np.array([score(VBA[t], A.F, t) for t in range(T)])
    choose = sBA < sA
    V = np.where(choose[:, None, None], VBA, A.V)
    def cd(X):
        return np.array([chamfer_distance(X[t], gt.V[t], squared=True, device="cpu").value for t in range(T)])


    cin = np.array([chamfer_distance(var.frames[t][0], gt.V[t], squared=True, device="cpu").value for t in range(T)])
    cA, cBA, cV = cd(A.V), cd(VBA), cd(V)
    def pct(c):
        return round(100 * (c.mean() / cin.mean() - 1), 1)


    cB = cd(B.V)
    print("handover", h, "chosen B frames", int(choose.sum()))
    res = {"machine": describe_device("cpu"), "sequence": name, "key_frames": [int(kA), int(kB)], "handover": h,
           "frames_choosing_b": int(choose.sum()),
           "cd_vs_input_pct": {"A": pct(cA), "B (own template)": pct(cB), "B transferred to A": pct(cBA),
                               "per-frame choice by score": pct(cV), "oracle A or B transferred": pct(np.minimum(cA, cBA)),
                               "oracle A or B own template": pct(np.minimum(cA, cB))},
           "worst_frame_ratio_choice": float((cV / cin).max()),
           "per_frame": {"score_A": sA.tolist(), "score_B_transferred": sBA.tolist(), "cd_A": cA.tolist(),
                         "cd_B": cB.tolist(), "cd_B_transferred": cBA.tolist(), "cd_input": cin.tolist()}}
    print(json.dumps(res["cd_vs_input_pct"]), "handover", h, "frames choosing B", int(choose.sum()))
    write_json(RESULTS / f"key_frame_probe_{name}_{K2}_cpu.json", res)

    # --- A guided: A's own tracking run again, with the transferred B pose as one more start pose
    # on the frames on B's side of the handover (A fits the real frame from the guide's pose; the
    # better coverage kept), so A's own fine stage distributes its vertices

    if MODE is None:
        return
    side = range(0, h) if kB < h else range(h + 1, T)
    GUIDE = {t: VBA[t] for t in side}
    orig_step = cv._Converter.step_graph
    accepted = []
    trace = []  # (frame, A's coverage, the guide's, the guide's after the fine stage) [m], mode "fine"


    def guided_step(self, frame, t):
        r = orig_step(self, frame, t)
        if t not in GUIDE or not self.history:
            return r
        X_prev = wp.clone(self.X)
        if MODE == "pose":  # the graph pose of the guide surface, then A's fit of the real frame from it
            o, gf = self.opts, self.gf
            its, lam0, lam1, mu = (int(o["graph_iterations"]), float(o["stiffness"]), float(o["stiffness_end"]),
                                   float(o["damping"]))
            R0, P0 = self.history[-1]
            Rg, Pg = gf.fit(self._graph_frame(_device_frame(GUIDE[t], A.F, self.device)), R0, P0, its, lam0, lam1, mu)
            R2, P2 = gf.fit(self._graph_frame(frame), Rg, Pg, its, lam1, lam1, mu)
            sc = self._graph_finish(frame, R2, P2)
        else:  # "fine": the transferred vertices themselves, then A's fine stage (fit + relaxation)
            self.X.assign(GUIDE[t].astype(np.float32))
            sc0 = self.coverage(frame)
            for _ in range(2 * int(self.opts["iterations"])):
                self.fit_nonrigid(frame)
            for _ in range(3):
                self.relax_and_project(frame)
            sc = self.coverage(frame)
            trace.append((t, self.scores[-1], sc0, sc))
        if sc < self.scores[-1]:
            accepted.append(t)
            self.scores[-1] = sc
            self.frame_coverage = sc
            if MODE == "pose":
                self.history[-1] = (R2, P2)
                self.frame_states[t] = (R2, P2)
        else:
            wp.copy(self.X, X_prev)
        return r


    cv._Converter.step_graph = guided_step
    G = to_fixed_topology(var, strategy="graph", device="cpu")
    cv._Converter.step_graph = orig_step
    cG = cd(G.V)
    res["cd_vs_input_pct"][f"A guided by transferred B ({MODE})"] = pct(cG)
    res["guided_frames_accepted"] = len(accepted)
    res["worst_frame_ratio_guided"] = float((cG / cin).max())
    res["per_frame"]["cd_A_guided"] = cG.tolist()
    res["guided_mode"] = MODE
    res["fine_mode_coverage_trace"] = trace
    print("guided", pct(cG), "accepted", len(accepted), "worst", round(float((cG / cin).max()), 2))
    write_json(RESULTS / f"key_frame_probe_{name}_{K2}_{MODE}_cpu.json", res)


if __name__ == "__main__":
    main()
