"""The long fuzzing profile of every reader (tests/test_fuzz.py with DYNMESH_FUZZ=long).

Random (not derandomized) Hypothesis runs with many more examples than CI's bounded profile;
failing inputs are shrunk, printed and kept in ``.hypothesis/`` so the next run replays them
first. The outcome goes to ``bench/results/fuzz_long.json``.

    python bench/fuzz_long.py                    # 3000 examples per unit (about 5 min on 2 cores)
    python bench/fuzz_long.py --examples 20000 -k yaml
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=3000,
                    help="examples per unit (tests scale it: read_mesh and YAML x3, npz and splat x2)")
    ap.add_argument("-k", default="test_fuzz_", help="pytest -k expression (default: every fuzz test)")
    ap.add_argument("--out", type=Path, default=RESULTS / "fuzz_long.json")
    args = ap.parse_args(argv)
    if args.examples < 1:
        ap.error("--examples must be >= 1")
    env = dict(os.environ, DYNMESH_FUZZ="long", DYNMESH_FUZZ_EXAMPLES=str(args.examples))
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/test_fuzz.py",
           "-k", args.k, "--hypothesis-show-statistics"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    out = proc.stdout + proc.stderr
    print(out[-6000:])
    stats = {m.group(1): int(m.group(2)) for m in re.finditer(
        r"tests/test_fuzz\.py::(\w+):\n(?:.*\n)*?\s+- (\d+) passing examples", out)}
    result = {"command": " ".join(cmd), "examples_per_unit": args.examples, "k": args.k,
              "returncode": proc.returncode, "passed": proc.returncode == 0, "wall_s": round(wall, 1),
              "passing_examples": stats, "python": platform.python_version(),
              "machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "date": time.strftime("%Y-%m-%d")}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"{'passed' if proc.returncode == 0 else 'FAILED'} in {wall:.0f} s -> {args.out}")
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
