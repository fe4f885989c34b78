"""Modules are layered without cycles (issue 13; docs/architecture.md): every import inside the
package — at module level or inside a function — goes from a higher layer to a lower one."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = "dynmesh_warp"

#: the layers, bottom first (docs/architecture.md); a module imports only from layers below its own
LAYERS = [
    # data and vocabulary: import nothing from the package
    {"choices", "sequence", "outputs", "geometry"},
    # kernels (the top-level kernels/ folder, installed as dynmesh_warp.kernels)
    {"kernels"},
    # the conversion strategies' typed options (the schema and the converter take them from here);
    # mesh file formats (reader and writer registries)
    {"conversion_options", "mesh_formats"},
    # sequence layouts on disk (npz layouts, folders of frames, DG-Mesh folders); single-file
    # animations (.anime, .pc2, .mdd)
    {"sequence_layouts", "animation_formats", "gltf_animation"},
    # schema, readers/writers, signals and CLI plumbing, built-in surfaces
    {"config", "io", "splat_io", "scenes", "cli"},
    # the simulation core and the geometry stages
    {"world", "remesh", "metrics", "deform_graph"},
    # what runners share: devices, run length, output checks, the timed loop; checkpoints; Gaussians;
    # the cells collider measured for issue 14 and not kept (a world's collider put in from outside)
    # a conversion's journal (convert --resume)
    {"runtime", "checkpoint", "convert_journal", "gaussians", "face_cells"},
    # the one runner of both engines (it is handed a built simulation)
    {"runner"},
    # conversion (docs/architecture.md): what its stages share (closest points, ConversionInfo) and its
    # command line's plumbing (parser, output checks, journal); the
    # thresholds and the report; the input's analyses and the segments; the fit; then the public
    # API and its CLI (convert), then building a scene (which may convert)
    {"convert_base", "convert_cli"},
    {"convert_report"},
    {"convert_input", "convert_segments"},
    {"convert_fit"},
    {"convert"},
    {"scene"},
    # engines and tools over a scene
    {"newton_adapter", "evaluate", "batch"},
    # the renderer over either engine (its CLI builds a Newton world for a newton: scene)
    {"render"},
    {"viewer", "envs"},
    # Ray actors over the envs
    {"distributed"},
    # the run CLI on top
    {"run"},
]
LAYER = {m: i for i, layer in enumerate(LAYERS) for m in layer}


def _modules() -> dict[str, Path]:
    mods = {p.stem: p for p in (ROOT / PKG).glob("*.py") if p.stem != "__init__"}
    mods.update({f"kernels.{p.stem}": p for p in (ROOT / "kernels").glob("*.py") if p.stem != "__init__"})
    return mods


def _layer(mod: str) -> int:
    return LAYER["kernels"] if mod.startswith("kernels.") else LAYER[mod]


def _imports(mod: str, path: Path) -> set[str]:
    """Package modules ``mod`` imports (absolute or relative, anywhere in the file)."""
    pkg = mod.split(".")[:-1]  # [] for dynmesh_warp.x, ["kernels"] for dynmesh_warp.kernels.x
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg[: len(pkg) - (node.level - 1)] if node.level > 1 else pkg
                target = base + (node.module.split(".") if node.module else [])
            elif node.module and node.module.split(".")[0] == PKG:
                target = node.module.split(".")[1:]
            else:
                continue
            names = [a.name for a in node.names]
            if not target:  # from . import x
                out |= {n for n in names}
            elif target == ["kernels"]:
                out |= {f"kernels.{n}" for n in names} if node.module == "kernels" or node.level else {"kernels"}
            else:
                out.add(".".join(target[:2]) if target[0] == "kernels" else target[0])
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == PKG and len(parts) > 1:
                    out.add(".".join(parts[1:3]) if parts[1] == "kernels" else parts[1])
    mods = _modules()
    return {m for m in out if (m in mods or m == "kernels") and m != mod}


def _graph() -> dict[str, set[str]]:
    return {m: _imports(m, p) for m, p in _modules().items()}


def test_every_module_has_a_layer():
    missing = sorted(m for m in _modules() if not m.startswith("kernels.") and m not in LAYER)
    assert not missing, f"modules without a layer in tests/test_layers.py (and docs/architecture.md): {missing}"


def test_imports_go_down_the_layers():
    wrong = sorted(f"{a} (layer {_layer(a)}) imports {b} (layer {_layer(b)})"
                   for a, deps in _graph().items() for b in deps
                   if not (a.startswith("kernels.") and b.startswith("kernels.")) and _layer(b) >= _layer(a))
    assert not wrong, "\n".join(wrong)


def test_no_import_cycles():
    g = _graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(g.get(m, ())):
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            visit(m)


def test_the_checker_sees_function_level_and_relative_imports(tmp_path):
    """The checker itself: a lazy relative import inside a function is an edge."""
    f = tmp_path / "x.py"
    f.write_text("def f():\n    from .run import main\n    from .kernels.frames import wrap_frame\n")
    assert _imports("world", f) == {"run", "kernels.frames"}


def test_public_face_is_the_root_all():
    """Every name in ``dynmesh_warp.__all__`` resolves from the root (the conversion, I/O,
    Gaussians and viewer on first use), and importing the package loads neither viser nor newton."""
    import subprocess
    import sys

    code = ("import sys, dynmesh_warp as dw; assert 'viser' not in sys.modules and 'newton' not in sys.modules; "
            "missing = [n for n in dw.__all__ if getattr(dw, n, None) is None]; assert not missing, missing; "
            "from dynmesh_warp.io import load_sequence; assert dw.load_sequence is load_sequence; "
            "from dynmesh_warp.convert import to_fixed_topology; assert dw.to_fixed_topology is to_fixed_topology; "
            "assert {'load_sequence', 'save_sequence', 'to_fixed_topology', 'Gaussians', 'Viewer'} <= set(dw.__all__)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
