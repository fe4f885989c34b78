"""Markdown tables from bench/results/step_{cuda,cpu}.json (for docs/benchmarks.md)."""

from __future__ import annotations

import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def paper_table(d):
    p = d["paper"]
    lines = ["| collider | steps/s | µs/step | vs rebuild every step | CUDA graph | first step (compile+capture) s |",
             "|---|---|---|---|---|---|"]
    base = p["rebuild_every_step"]["steps_per_s"]
    for k in ("swept", "refit", "rebuild_every_step", "rebuild_every_frame"):
        r = p[k]
        note = "" if r.get("interpolate", True) else " (interpolation off)"
        lines.append(f"| {k}{note} | {r['steps_per_s']:,.0f} | {r['us_per_step']:.1f} | {r['steps_per_s'] / base:.1f}× | "
                     f"{'yes' if r['cuda_graph'] else 'no'} | {r['first_step_s (compile+capture)']:.2f} |")
    return "\n".join(lines)


def stages_table(d):
    lines = ["| path | stage | µs |", "|---|---|---|"]
    for path, st in d["stages_us"].items():
        for k, v in st.items():
            lines.append(f"| {path} | {k} | {v:.1f} |")
    for k, v in d["floor_us"].items():
        if k != "note":
            lines.append(f"| floor | {k} | {v:.1f} |")
    return "\n".join(lines)


def scaling_table(d):
    rows = d.get("scaling", [])
    lines = ["| vertices | spheres | swept steps/s | refit steps/s | rebuild steps/s | device memory (refit), MiB |",
             "|---|---|---|---|---|---|"]
    keys = sorted({(r["vertices"], r["spheres"]) for r in rows})
    for v, s in keys:
        get = {r["collider"]: r for r in rows if r["vertices"] == v and r["spheres"] == s}
        def f(c):
            return f"{get[c]['steps_per_s']:,.0f}" if c in get else "–"
        mem = get.get("refit", {}).get("device_mem_bytes")
        lines.append(f"| {v:,} | {s:,} | {f('swept')} | {f('refit')} | {f('rebuild')} | "
                     f"{'–' if mem is None else f'{mem / 2**20:.1f}'} |")
    return "\n".join(lines)


if __name__ == "__main__":
    for dev in ("cuda", "cpu"):
        f = ROOT / "bench" / "results" / f"step_{dev}.json"
        if not f.is_file():
            continue
        d = json.loads(f.read_text())
        print(f"## {dev}: {d['machine']['device_name']}\n")
        print(paper_table(d), "\n")
        print(stages_table(d), "\n")
        print(scaling_table(d), "\n")
