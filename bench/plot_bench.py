"""Plot steps/s against vertex count (fixed-topology colliders vs the rebuild baseline, CPU and
GPU) from bench/results/step_{cpu,cuda}.json -> docs/benchmark_scaling.png."""

from __future__ import annotations

import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(out: str | None = None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out) if out else ROOT / "docs" / "benchmark_scaling.png"
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, dev in zip(axes, ("cuda", "cpu")):
        f = ROOT / "bench" / "results" / f"step_{dev}.json"
        if not f.is_file():
            ax.set_title(f"{dev}: no results")
            continue
        d = json.loads(f.read_text())
        rows = d.get("scaling", [])
        spheres = sorted({r["spheres"] for r in rows})
        styles = {"swept": "-o", "refit": "-s", "rebuild": "--^"}
        for col in ("swept", "refit", "rebuild"):
            for i, s in enumerate(spheres):
                pts = sorted((r["vertices"], r["steps_per_s"]) for r in rows if r["collider"] == col and r["spheres"] == s)
                if pts:
                    ax.plot(*zip(*pts), styles[col], color=f"C{i}", alpha=0.9 if col != "rebuild" else 0.6,
                            label=f"{col}, {s} spheres", markersize=4)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("surface vertices")
        ax.grid(True, which="both", alpha=0.3)
        ax.set_title(f"{d['machine']['device_name']} ({d['machine']['device']})", fontsize=10)
        # each panel its own legend: the colours stand for each file's own sphere counts (the CPU
        # table's third is 10,000, the GPU's 100,000; one legend named both 100,000, a new user's)
        ax.legend(fontsize=7, ncol=3, loc="lower left")
    axes[0].set_ylabel("steps / s")
    fig.suptitle("dynmesh_warp step rate vs mesh size: fixed topology (swept, refit) vs rebuild baseline", fontsize=11)
    fig.tight_layout()
    from dynmesh_warp.outputs import atomic_path

    with atomic_path(out, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=120)
    print(f"wrote {out}")


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default=None, help="PNG to write (default docs/benchmark_scaling.png)")
    main(ap.parse_args().out)
