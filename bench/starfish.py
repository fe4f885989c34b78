"""Write the built-in starfish (``dynmesh_warp.scenes.starfish``: five thin arms bending into
arcs and back, out of phase; a motion none of the conversion's defaults was tuned on) as a GT npz
for ``bench/conversion_eval.py --sequences out/starfish.npz`` (docs/evaluation.md).

    python bench/starfish.py --out out/starfish.npz                                 # half-circle curl, 48 frames
    python bench/starfish.py --out out/starfish_fast.npz --frames 24 --curl 1.6     # loops, twice as fast
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from dynmesh_warp.scenes import starfish  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/starfish.npz")
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--curl", type=float, default=1.0)
    ap.add_argument("--resolution", type=int, default=96)
    a = ap.parse_args()
    seq = starfish(frames=a.frames, curl=a.curl, resolution=a.resolution)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    name = Path(a.out).stem
    np.savez(a.out, V=seq.V, F=seq.F, fps=np.float32(seq.fps), name=name)
    print(f"wrote {a.out}: {seq.num_frames} frames x {seq.V.shape[1]} vertices, {len(seq.F)} faces")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
