"""Kernel signatures follow one convention (issue 13; docs/architecture.md#kernel-conventions),
checked on the source like MuJoCo Warp's kernel linter: every ``@wp.kernel`` in ``kernels/``

* has a verb-first name (``VERBS``) and a docstring;
* groups its parameters under comment headers from one vocabulary, in this order, each at most
  once: ``# Model:`` (static data, never written), ``# State in:`` (per-step state it reads),
  ``# In:`` (other inputs), ``# State out:`` (per-step state it writes, in place included),
  ``# Out:`` (other results); a header may carry a note, ``# Out (accumulated):``;
* names parameters under ``# State in:`` with the suffix ``_in`` and under ``# State out:``
  with ``_out`` (the rest of the name is the host field the array carries);
* writes array types with the bracket syntax, ``wp.array[wp.vec3]``, ``wp.array2d[float]``
  (not ``wp.array(dtype=...)``).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GROUPS = ["Model", "State in", "In", "State out", "Out"]
HEADER = re.compile(r"^#\s*(Model|State in|In|State out|Out)(\s*\([^)]*\))?:\s*$")
VERBS = {
    "accumulate", "add", "advance", "apply", "begin", "bind", "blend", "cast", "collide", "combine", "compute", "count",
    "detect", "emit", "evaluate",
    "find", "gather", "integrate", "mark", "measure", "multiply", "pack", "project", "rasterize", "reject", "relax", "reset",
    "resolve", "sample", "scatter", "skin", "smooth", "solve", "sum", "transform", "update",
}


def _kernels():
    for path in sorted((ROOT / "kernels").glob("*.py")):
        src = path.read_text()
        lines = src.splitlines()
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, ast.FunctionDef) and any(
                    ast.unparse(d) in ("wp.kernel", "warp.kernel") or ast.unparse(d).startswith("wp.kernel(")
                    for d in node.decorator_list):
                yield path, node, lines


def _groups(node: ast.FunctionDef, lines: list[str]) -> tuple[list[tuple[str, str]], list[str]]:
    """[(group, parameter)] from the comment lines between the parameters, and problems found."""
    problems = []
    out = []
    args = node.args.args
    group = None
    seen = []
    prev_end = node.lineno  # the "def" line
    for a in args:
        for ln in lines[prev_end:a.lineno - 1]:  # comment lines before this parameter
            s = ln.strip()
            if not s.startswith("#"):
                continue
            m = HEADER.match(s)
            if not m:
                problems.append(f"unknown header {s!r}")
                continue
            g = m.group(1)
            if g in seen:
                problems.append(f"header {g!r} twice")
            elif seen and GROUPS.index(g) < GROUPS.index(seen[-1]):
                problems.append(f"header {g!r} after {seen[-1]!r} (order: {GROUPS})")
            seen.append(g)
            group = g
        if group is None:
            problems.append(f"parameter {a.arg!r} under no header")
        out.append((group, a.arg))
        prev_end = a.end_lineno
    return out, problems


def _array_syntax(node: ast.FunctionDef) -> list[str]:
    """Parameters typed with the call form ``wp.array(dtype=...)`` instead of ``wp.array[...]``."""
    return [f"parameter {a.arg!r}: write {ast.unparse(a.annotation)} as wp.array[...]"
            for a in node.args.args
            if isinstance(a.annotation, ast.Call) and ast.unparse(a.annotation.func).startswith("wp.array")]


KERNELS = list(_kernels())


def test_kernels_found():
    assert len(KERNELS) >= 40


@pytest.mark.parametrize("path,node,lines", KERNELS, ids=[f"{p.stem}.{n.name}" for p, n, _ in KERNELS])
def test_kernel_convention(path, node, lines):
    where = f"{path.name}:{node.lineno} {node.name}"
    assert node.name.split("_")[0] in VERBS, f"{where}: name must start with a verb from VERBS"
    assert ast.get_docstring(node), f"{where}: no docstring"
    groups, problems = _groups(node, lines)
    problems += _array_syntax(node)
    assert not problems, f"{where}: " + "; ".join(problems)
    for g, name in groups:
        if g == "State in":
            assert name.endswith("_in"), f"{where}: state input {name!r} must end with _in"
        if g == "State out":
            assert name.endswith("_out"), f"{where}: state output {name!r} must end with _out"


def test_checker_rejects_violations(tmp_path):
    """The checker itself can fail: a kernel with an unknown header, a bad order, a missing
    suffix and a non-verb name is reported."""
    src = '''
import warp as wp

@wp.kernel
def spheres_integrate(
    # inputs
    a: wp.array(dtype=float),
    # Out:
    b: wp.array(dtype=float),
    # Model:
    c: wp.array(dtype=float),
    # State out:
    d: wp.array(dtype=float),
):
    pass
'''
    tree = ast.parse(src)
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef))
    groups, problems = _groups(node, src.splitlines())
    assert any("unknown header" in p for p in problems)
    assert any("after 'Out'" in p for p in problems)
    assert node.name.split("_")[0] not in VERBS
    assert ("State out", "d") in groups and not "d".endswith("_out")
    assert ast.get_docstring(node) is None
    assert len(_array_syntax(node)) == 4  # the call form, four times


def test_ruff_passes_with_the_project_configuration():
    """``ruff check`` (configured in pyproject.toml: pycodestyle errors/warnings and pyflakes) is
    clean on the package, the kernels, the tests and the benchmarks."""
    import shutil
    import subprocess

    exe = shutil.which("ruff")
    if exe is None:
        pytest.skip("ruff is not installed (it is in the test extra)")
    r = subprocess.run([exe, "check", "dynmesh_warp", "kernels", "tests", "bench"], cwd=ROOT, capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stdout[-3000:]
