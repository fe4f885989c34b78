"""What the conversion journal (``convert --resume``) costs and saves.

One input converted four ways with the default strategy and ``to_piecewise_fixed`` (what
``convert`` runs for an .npz or folder output): without a journal; with one (the overhead of
writing every frame fit); stopped after about half of its frame fits, then resumed from that
journal; and resumed from the complete journal (every fit taken from it: the floor of a resume,
the work between the fits). Records the seconds of each, the journal's size, the frames taken
from the journal, and whether each result equals the uninterrupted one bit for bit.

    python bench/bench_convert_journal.py --device cpu --input out/cache/horse-gallop_T24_r96_e0.01.npz \
        --out bench/results/convert_journal_cpu.json
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import describe_device  # noqa: E402
from dynmesh_warp.convert import to_piecewise_fixed  # noqa: E402
from dynmesh_warp.convert_journal import ConversionJournal  # noqa: E402
from dynmesh_warp.io import load_sequence  # noqa: E402
from dynmesh_warp.outputs import atomic_write_json  # noqa: E402
from dynmesh_warp.scenes import torus_to_sphere  # noqa: E402
from dynmesh_warp.sequence import VaryingTopologySequence  # noqa: E402


def _frames(res) -> list:
    return [(res.V[t], res.F) for t in range(res.num_frames)] if hasattr(res, "V") else list(res.frames)


def _equal(a, b) -> bool:
    fa, fb = _frames(a), _frames(b)
    return len(fa) == len(fb) and all(np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1]) for x, y in zip(fa, fb))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default=None)
    p.add_argument("--input", default=None, help="a sequence file (default: the built-in torus closing into a sphere)")
    p.add_argument("--frames", type=int, default=60, help="the built-in input's frames (200: bench_convert's input)")
    p.add_argument("--resolution", type=int, default=32, help="its marching-cubes grid (76: ~10k vertices a frame)")
    p.add_argument("--deterministic", action="store_true",
                   help="the conversion option deterministic=True (a GPU run then repeats bit for bit)")
    p.add_argument("--repeats", type=int, default=1, help="timed conversions without and with a journal (medians)")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    wp.config.quiet = True
    device = wp.get_device(a.device)
    seq = load_sequence(a.input) if a.input else torus_to_sphere(frames=a.frames, resolution=a.resolution)
    work = Path(tempfile.mkdtemp(prefix="journal_bench_"))
    try:
        def timed(**kw):
            t0 = time.perf_counter()
            r = to_piecewise_fixed(seq, device=device, **kw, **({"deterministic": True} if a.deterministic else {}))
            return r, time.perf_counter() - t0

        warm = VaryingTopologySequence(list(seq.frames[:3]), fps=seq.fps)  # Warp's kernels compiled, not timed
        to_piecewise_fixed(warm, device=device, **({"deterministic": True} if a.deterministic else {}))
        plains, journals = [], []
        for r in range(a.repeats):  # alternately, so that the machine's drift falls on both
            plain, t = timed()
            plains.append(t)
            shutil.rmtree(work / "full", ignore_errors=True)
            full_j = ConversionJournal(work / "full", {})
            journaled, t = timed(journal=full_j)
            journals.append(t)
        t_plain, t_journal = float(np.median(plains)), float(np.median(journals))
        size = sum(q.stat().st_size for q in full_j.folder.iterdir())
        half = max(full_j.written // 2, 1)
        stop_j = ConversionJournal(work / "stop", {})
        _, t_stopped = timed(journal=stop_j, should_stop=lambda: stop_j.written >= half)
        resume_j = ConversionJournal(work / "stop", {}, resume=True)
        resumed, t_resumed = timed(journal=resume_j)
        replay_j = ConversionJournal(work / "full", {}, resume=True)
        replayed, t_replayed = timed(journal=replay_j)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    res = {
        "input": a.input or f"torus_to_sphere(frames={a.frames}, resolution={a.resolution})",
        "frames": seq.num_frames,
        "input_vertices_mean": float(np.mean([len(v) for v, _ in seq.frames])),
        "segments": [list(s) for s in plain.conversion.segments],
        "device": describe_device(device),
        "deterministic": a.deterministic,
        "seconds_without_journal": t_plain,
        "seconds_with_journal": t_journal,
        "journal_overhead": t_journal / t_plain - 1.0,
        "repeats": {"without_journal": plains, "with_journal": journals},
        "frame_fits": full_j.written,
        "journal_bytes": size,
        "journal_bytes_per_fit": size / max(full_j.written, 1),
        "stopped_after_fits": stop_j.written,
        "seconds_to_the_stop": t_stopped,
        "seconds_resumed": t_resumed,
        "resumed_fits_taken_from_journal": resume_j.replayed,
        "resumed_fits_done": resume_j.written,
        "seconds_all_from_journal": t_replayed,
        "equal_to_uninterrupted": {"with_journal": _equal(journaled, plain), "resumed": _equal(resumed, plain),
                                   "all_from_journal": _equal(replayed, plain)},
    }
    atomic_write_json(a.out, res)
    print(res)


if __name__ == "__main__":
    main()
