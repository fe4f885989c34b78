"""Issue 20: outputs never touch inputs, everything is checked before the work, the work is bounded.

``test_bad_path_or_value_refused_before_the_work`` runs each command line (as a user would): it
must exit 2 with one line naming the offending path or value, no traceback, without launching a
Warp kernel or building a Warp mesh (the work), and leave every file in the work folder (inputs and
pre-existing outputs) exactly as it was, with no temporary file left behind. One case per command
runs in a subprocess (``python -m``: the exit status and everything the process prints, its
start-up included); the others call the command's ``main`` in this process with the same checks
(its return value is the exit status: ``sys.exit(main())``), which saves a Python and Warp start-up
(~2 CPU-s) per case.
"""

from __future__ import annotations

import hashlib
import importlib
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from dynmesh_warp.io import write_mesh
from dynmesh_warp.outputs import MANIFEST, OutputError, OutputFolder, check_output
from dynmesh_warp.scenes import icosphere

RUN, CONVERT, EVALUATE = (["-m", f"dynmesh_warp.{m}"] for m in ("run", "convert", "evaluate"))


def _ico(T=4):
    V, F = icosphere(1)
    return [(V * (0.3 + 0.02 * t), F) for t in range(T)]


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A user's folder: per-frame meshes, a folder of their own scans, a ground-truth npz,
    scenes, an unrelated file, an earlier recording, a symlink to the frames."""
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.sequence import FixedTopologySequence

    w = tmp_path_factory.mktemp("user")
    (w / "frames").mkdir()
    for t, (V, F) in enumerate(_ico()):
        write_mesh(w / "frames" / f"{t:03d}.obj", V, F)
    (w / "scans").mkdir()
    write_mesh(w / "scans" / "my_scan.obj", *_ico(1)[0])
    V, F = icosphere(1)
    save_sequence(FixedTopologySequence(np.stack([V, V * 1.1, V * 1.2]), F, fps=10), w / "gt.npz")
    (w / "notes.txt").write_text("my notes\n")
    (w / "old.viser").write_bytes(b"an earlier recording")
    (w / "dir.viser").mkdir()
    (w / "dir.viser" / "keep").write_text("x")
    (w / "frames_link").symlink_to(w / "frames")
    (w / "dangling.npz").symlink_to(w / "nowhere" / "x.npz")
    (w / "frames_broken").mkdir()  # a frame that is a link to nowhere (it was dropped unremarked)
    for t, (V, F) in enumerate(_ico(3)):
        write_mesh(w / "frames_broken" / f"{t:03d}.obj", V, F)
    (w / "frames_broken" / "003.obj").symlink_to(w / "nowhere" / "003.obj")
    scenes = {
        "ok.yaml": "surface: {source: frames}\nrun: {steps: 2}\n",
        "dt_inf.yaml": "physics: {dt: .inf}\n",
        "dur_inf.yaml": "run: {duration: .inf}\n",
        "ground_nan.yaml": "physics: {ground: .nan}\n",
        "sphere_nan.yaml": "spheres: [{position: [.nan, 0, 1]}]\n",
        "placeholder.yaml": "run: {output: 'out/{nmae}'}\n",
        "dup.yaml": "run: {steps: 2}\nrun: {steps: 3}\n",
        "substeps.yaml": "physics: {substeps: 100000000}\n",
        "into_input.yaml": "surface: {source: frames}\nrun: {output: frames/out}\n",
        "dt_tiny.yaml": "physics: {dt: 1.0e-12}\n",
        "restitution.yaml": "physics: {restitution: 5}\n",
        "gravity.yaml": "physics: {gravity: [0, 0, -3.0e+38]}\n",
    }
    for name, text in scenes.items():
        (w / name).write_text(text)
    return w


def _snapshot(root: Path) -> dict:
    """Every entry under ``root`` (links as links) -> a checksum of its content."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for n in dirnames + filenames:
            p = Path(dirpath) / n
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "link:" + os.readlink(p)
            elif p.is_dir():
                out[rel] = "dir"
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


# (command, text the one error line must contain)
BAD = [
    # run: output paths
    (RUN + ["--output", "notes.txt"], "notes.txt"),
    (RUN + ["--output", "notes.txt/sub"], "notes.txt"),
    (RUN + ["--output", "/proc/dynmesh_out"], "/proc"),
    (RUN + ["--output", "scans"], "--overwrite"),
    (RUN + ["ok.yaml", "--output", "frames"], "input"),
    (RUN + ["ok.yaml", "--output", "frames_link"], "input"),
    (RUN + ["ok.yaml", "--output", "."], "input"),
    (RUN + ["into_input.yaml"], "frames"),
    # run: --record
    (RUN + ["--record", "rec.txt"], ".txt"),
    (RUN + ["--record", "old.viser"], "old.viser"),
    (RUN + ["--record", "dir.viser"], "dir.viser"),
    (RUN + ["--record", "new.viser", "--output", "o"], "--output"),
    # run: options
    (RUN + ["--steps", "0"], "--steps"),
    (RUN + ["--duration", "inf"], "--duration"),
    (RUN + ["--duration", "nan"], "--duration"),
    (RUN + ["--port", "70000"], "--port"),
    (RUN + ["--steps", "x"], "--steps"),
    (RUN + ["--device", "nodevice"], "nodevice"),
    (RUN + ["missing.yaml"], "missing.yaml"),
    # run: scene values
    (RUN + ["dt_inf.yaml"], "physics.dt"),
    (RUN + ["dur_inf.yaml"], "run.duration"),
    (RUN + ["ground_nan.yaml"], "physics.ground"),
    (RUN + ["sphere_nan.yaml"], "spheres.0.position"),
    (RUN + ["placeholder.yaml"], "{nmae}"),
    (RUN + ["dup.yaml"], "duplicate key 'run'"),
    (RUN + ["substeps.yaml"], "max_substeps"),
    (RUN + ["restitution.yaml"], "physics.restitution"),
    (RUN + ["dt_tiny.yaml"], "work budget"),
    (RUN + ["--set", "surface.fps=1e300"], "surface.fps"),  # an OverflowError traceback (a new user's)
    (RUN + ["gravity.yaml"], "physics.gravity: |gravity| 3e+38 m/s^2 is over"),  # ran to positions of 1e37 m
    # convert
    (CONVERT + ["frames", "frames", "--fmt", "obj"], "input"),
    (CONVERT + ["frames", "frames_link"], "input"),
    (CONVERT + ["frames", "scans", "--fmt", "obj"], "--overwrite"),
    (CONVERT + ["frames", "frames/out.npz"], "inside the input"),
    (CONVERT + ["frames", "dangling.npz"], "a symbolic link to"),  # refused only after the work
    (CONVERT + ["frames", "somedir.npz/"], "names a folder (trailing"),  # written as a file
    (CONVERT + ["frames", "o.npz", "--fps", "1e300"], "--fps must be a frame rate of 0.0001 to 1e+07"),  # fps=inf written
    (CONVERT + ["frames", "gt.npz"], "--overwrite"),
    (CONVERT + ["frames", "out.obj"], ".obj"),
    (CONVERT + ["frames", "scans/my_scan.pc2"], "my_scan.obj"),  # the cache's faces would replace a scan
    (CONVERT + ["frames", "x.pc2", "--fmt", "obj"], "--fmt"),
    (CONVERT + ["frames", "x.npz", "--tracked-weight", "nan"], "--tracked-weight"),
    (CONVERT + ["frames", "x.npz", "--fps", "inf"], "--fps"),
    (CONVERT + ["nothere", "x.npz"], "nothere"),
    (CONVERT + ["frames", "x.npz", "--template", "nope.obj"], "nope.obj"),
    (CONVERT + ["frames", "x.npz", "--template", "scans"], "--template scans: a folder, not a file"),  # "not found"
    (CONVERT + ["frames_broken", "x.npz"], "003.obj: a symbolic link to"),  # converted 3 frames unremarked
    (CONVERT + ["frames", "x.npz", "--option", "iterations=2", "--option", "iterations=3"], "given twice"),  # last won
    # evaluate
    (EVALUATE + ["gt.npz", "--out", "."], "input"),
    (EVALUATE + ["gt.npz", "--out", "notes.txt"], "notes.txt"),
    (EVALUATE + ["gt.npz", "--out", "scans"], "--overwrite"),
    (EVALUATE + ["gt.npz", "--noise", "inf"], "--noise"),
    (EVALUATE + ["gt.npz", "--frame-stride", "0"], "--frame-stride"),
    (EVALUATE + ["gt.npz", "--strategies", "nope"], "nope"),
    (EVALUATE + ["absent.npz"], "absent.npz"),
    (EVALUATE + ["--compare", "frames", "scans", "--out", "frames/x"], "inside the input"),
]


#: ``python -c NO_WORK <module> <args>`` runs ``python -m <module> <args>`` with every Warp kernel
#: launch (``wp.launch``, and ``wp.launch_tiled`` through it) and every ``wp.Mesh`` (a BVH build)
#: noted in the file $DYNMESH_WORK_NOTES: the work of run, convert and evaluate is Warp kernels, so
#: a command refused before the work notes nothing (a deterministic check, not a wall-clock limit)
NO_WORK = """
import os, runpy, sys
import warp
import warp._src.context as context
import warp._src.types as types

def noting(what, real):
    def call(*args, **kwargs):
        with open(os.environ["DYNMESH_WORK_NOTES"], "a") as f:
            f.write(f"{what} {getattr(args[0], 'key', '') if args else ''}\\n")
        return real(*args, **kwargs)
    return call

assert warp.launch is context.launch
warp.launch = context.launch = noting("launch", context.launch)
types.Mesh.__init__ = noting("Mesh", types.Mesh.__init__)
module, sys.argv = sys.argv[1], sys.argv[:1] + sys.argv[2:]
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""


def run_noting_work(argv: list[str], cwd: Path, notes: Path) -> subprocess.CompletedProcess:
    """``python -m ...`` (``argv`` = ["-m", module, *args]) in a subprocess, its Warp work noted in ``notes``."""
    assert argv[0] == "-m"
    return subprocess.run([sys.executable, "-c", NO_WORK, *argv[1:]], cwd=cwd, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "DYNMESH_WORK_NOTES": str(notes)})


#: the cases of BAD run as a real process (one per command, each refused at a different stage:
#: the scene's work budget, a broken frame of the input, an unknown strategy); the rest in-process
IN_A_PROCESS = {("dynmesh_warp.run", "dt_tiny.yaml"), ("dynmesh_warp.convert", "frames_broken"),
                ("dynmesh_warp.evaluate", "--strategies")}


def _in_a_process(argv) -> bool:
    return any(argv[1] == module and arg in argv for module, arg in IN_A_PROCESS)


def run_in_process_noting_work(argv: list[str], cwd: Path, monkeypatch, capfd) -> tuple[int, str, str, list[str]]:
    """``python -m ...`` (``argv`` = ["-m", module, *args]) as ``sys.exit(<module>.main(args))`` in
    this process, in ``cwd``: (exit status, stdout, stderr, the Warp work noted as NO_WORK notes it).
    A warning the command leaves uncaught is a line of stderr, as in a fresh interpreter (shown
    once per place; deprecation, import and resource warnings ignored)."""
    import warp
    import warp._src.context as context
    import warp._src.types as types

    assert argv[0] == "-m"
    module = importlib.import_module(argv[1])
    work = []

    def noting(what, real):
        def call(*args, **kwargs):
            work.append(f"{what} {getattr(args[0], 'key', '') if args else ''}".strip())
            return real(*args, **kwargs)
        return call

    capfd.readouterr()
    with monkeypatch.context() as m, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
            warnings.filterwarnings("ignore", category=category)
        m.chdir(cwd)
        launch = noting("launch", context.launch)
        m.setattr(warp, "launch", launch)
        m.setattr(context, "launch", launch)
        m.setattr(types.Mesh, "__init__", noting("Mesh", types.Mesh.__init__))
        try:
            rc = module.main(argv[2:])
        except SystemExit as e:  # argparse's usage errors
            rc = e.code
    out, err = capfd.readouterr()
    err += "".join(f"warning ({w.category.__name__}): {w.message}\n" for w in caught)
    return (0 if rc is None else rc), out, err, work


@pytest.mark.parametrize("argv,needle", BAD, ids=[" ".join(a[2:]) for a, _ in BAD])
def test_bad_path_or_value_refused_before_the_work(work, tmp_path, argv, needle, monkeypatch, capfd):
    before = _snapshot(work)
    argv = argv + ["--no-progress"] if argv[1] != "dynmesh_warp.convert" else argv
    if _in_a_process(argv):
        notes = tmp_path / "work_notes.txt"  # outside the user's folder, which must stay as it was
        r = run_noting_work(argv, work, notes)
        rc, out, err = r.returncode, r.stdout, r.stderr
        noted = notes.read_text().split() if notes.exists() else []
    else:
        rc, out, err, noted = run_in_process_noting_work(argv, work, monkeypatch, capfd)
    lines = [ln for ln in (out + err).splitlines() if ln.strip()]
    assert rc == 2, (rc, lines)
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    assert needle in lines[0]
    assert "Traceback" not in err
    assert not noted, "refused after the work began: " + " ".join(noted[:12])
    assert _snapshot(work) == before  # nothing written, changed, or left behind


def test_each_command_has_a_case_in_a_process():
    assert sorted(a[1] for a, _ in BAD if _in_a_process(a)) == ["dynmesh_warp.convert", "dynmesh_warp.evaluate",
                                                                 "dynmesh_warp.run"]


def test_the_work_check_sees_a_kernel_launch_and_a_mesh(tmp_path):
    """The check above notes the work: a run of one step launches kernels and builds the surface's mesh."""
    notes = tmp_path / "work_notes.txt"
    r = run_noting_work(RUN + ["--steps", "1", "--viewer", "none", "--device", "cpu", "--no-progress",
                               "--output", str(tmp_path / "o")], tmp_path, notes)
    assert r.returncode == 0, r.stderr[-2000:]
    noted = notes.read_text().splitlines()
    assert any(n.startswith("launch ") for n in noted) and any(n.startswith("Mesh") for n in noted), noted[:5]


def test_the_in_process_work_check_sees_a_kernel_launch_and_a_mesh(tmp_path, monkeypatch, capfd):
    """... and so does its in-process form, for each command: a run of one step, a conversion
    of two frames, an evaluation of two frames launch kernels and build meshes."""
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.sequence import FixedTopologySequence

    V, F = icosphere(1)
    save_sequence(FixedTopologySequence(np.stack([V, V * 1.1]), F, fps=10), tmp_path / "gt.npz")
    for argv in (RUN + ["--steps", "1", "--viewer", "none", "--device", "cpu", "--no-progress", "--output", "o"],
                 CONVERT + ["gt.npz", "c.npz", "--strategy", "projection", "--device", "cpu", "--no-progress"],
                 EVALUATE + ["gt.npz", "--strategies", "projection", "--no-emd", "--resolution", "16", "--device", "cpu",
                             "--no-progress", "--out", "e"]):
        rc, out, err, noted = run_in_process_noting_work(argv, tmp_path, monkeypatch, capfd)
        assert rc == 0, err[-2000:]
        assert any(n.startswith("launch ") for n in noted) and any(n.startswith("Mesh") for n in noted), (argv, noted[:5])


def test_a_viewer_host_it_cannot_listen_on_is_refused(work):
    """``--host`` an address of no interface here: viser's server thread died and the viewer
    waited for it forever, with no word (a new user's); now one line naming it, exit 2."""
    import socket

    try:
        with socket.socket() as s:
            s.bind(("192.0.2.55", 0))  # TEST-NET-1: no interface has it, unless non-local binds are allowed
        pytest.skip("this machine may bind 192.0.2.55")
    except OSError:
        pass
    r = subprocess.run([sys.executable, *RUN, "ok.yaml", "--viewer", "viser", "--host", "192.0.2.55", "--no-progress"],
                       cwd=work, capture_output=True, text=True, timeout=60)
    lines = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.startswith("error: ")]
    assert r.returncode == 2 and len(lines) == 1 and "--host 192.0.2.55: cannot listen there" in lines[0], r.stderr


def test_there_are_at_least_30_cases():
    assert len(BAD) >= 30 and {a[1] for a, _ in BAD} == {"dynmesh_warp.run", "dynmesh_warp.convert",
                                                          "dynmesh_warp.evaluate"}


# --------------------------------------------------------------------------- --overwrite


def test_convert_overwrite_keeps_the_users_files(work, tmp_path, capsys):
    from dynmesh_warp import convert

    out = tmp_path / "scans"
    out.mkdir()
    (out / "my_scan.obj").write_bytes((work / "scans" / "my_scan.obj").read_bytes())
    mine = hashlib.sha256((out / "my_scan.obj").read_bytes()).hexdigest()
    assert convert.main([str(work / "frames"), str(out), "--fmt", "obj"]) == 2  # refused without it
    assert sorted(p.name for p in out.iterdir()) == ["my_scan.obj"]
    for _ in range(2):  # a second time replaces the first conversion, not the scan
        assert convert.main([str(work / "frames"), str(out), "--fmt", "obj", "--overwrite"]) == 0
        names = sorted(p.name for p in out.iterdir())
        assert names == [MANIFEST] + [f"frame_{t:04d}.obj" for t in range(4)] + ["my_scan.obj"]
        assert hashlib.sha256((out / "my_scan.obj").read_bytes()).hexdigest() == mine
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scans"]  # no temp folders left
    assert (out.stat().st_mode & 0o777) == 0o777 & ~_umask()  # the user's umask, not 0700
    # a file of a name it writes, not written by it, is never replaced
    (out / "frame_0009.obj").write_text("mine")
    assert convert.main([str(work / "frames"), str(out), "--fmt", "obj", "--overwrite"]) == 2
    assert "frame_0009.obj" in capsys.readouterr().err


def test_convert_to_a_point_cache_reads_back_as_the_npz_output(work, tmp_path):
    from dynmesh_warp import convert
    from dynmesh_warp.io import load_sequence

    # on the CPU: two GPU conversions differ in the last bits (docs/conversion.md, "deterministic"),
    # and an H200 run of this test compared two of them
    assert convert.main([str(work / "frames"), str(tmp_path / "c.npz"), "--device", "cpu"]) == 0
    assert convert.main([str(work / "frames"), str(tmp_path / "c.pc2"), "--device", "cpu"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.npz", "c.obj", "c.pc2"]  # the cache's faces
    a, b = load_sequence(tmp_path / "c.npz"), load_sequence(tmp_path / "c.pc2")
    np.testing.assert_array_equal(a.V, b.V)
    np.testing.assert_array_equal(a.F, b.F)
    assert convert.main([str(work / "frames"), str(tmp_path / "c.pc2")]) == 2  # exists: --overwrite
    # an animated glTF, converted on the CPU too (GPU conversions are not repeatable bit for bit)
    assert convert.main([str(work / "frames"), str(tmp_path / "c.glb"), "--device", "cpu"]) == 0
    np.testing.assert_allclose(load_sequence(tmp_path / "c.glb").V, a.V, atol=1e-6)


def test_convert_never_writes_over_the_faces_of_its_point_cache_input(tmp_path, capsys):
    """A cache output writes <stem>.obj: when that is the input cache's own mesh, refused even
    with --overwrite, and every input stays byte-identical."""
    from dynmesh_warp import convert
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.sequence import FixedTopologySequence

    V, F = icosphere(1)
    save_sequence(FixedTopologySequence(np.stack([V, V * 1.1, V * 1.2]).astype(np.float32), F, fps=10),
                  tmp_path / "walk.pc2")
    before = _snapshot(tmp_path)
    assert convert.main([str(tmp_path / "walk.pc2"), str(tmp_path / "walk.mdd"), "--overwrite"]) == 2
    assert "this is the input" in capsys.readouterr().err
    assert _snapshot(tmp_path) == before


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def test_run_overwrite_keeps_the_users_files_and_nan_keeps_previous_outputs(tmp_path, capsys):
    from dynmesh_warp.run import main

    out = tmp_path / "o"
    args = ["--viewer", "none", "--device", "cpu", "--no-progress", "--steps", "2", "--output", str(out)]
    assert main(args) == 0
    assert main(args) == 2 and "--overwrite" in capsys.readouterr().err
    (out / "mine.txt").write_text("keep me")
    assert main(args + ["--overwrite"]) == 0
    assert (out / "mine.txt").read_text() == "keep me"
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "mine.txt", "summary.json", "trajectories.npz"]
    assert (out / "summary.json").stat().st_mode & 0o777 == 0o666 & ~_umask()


def test_overwrite_replaces_only_an_output_of_the_same_kind(work, tmp_path, capsys):
    """``render --out`` into a run's output folder with ``--overwrite`` deleted the run's
    trajectories and summary (both this tool's files) and exited 0. The manifest now says what
    a folder holds; another command's output is refused before the work, naming it, and stays
    byte for byte; the same kind is replaced as before, and a manifest written before it said
    what it holds is replaced as before too."""
    from dynmesh_warp.outputs import OutputKind, read_manifest_kind
    from dynmesh_warp.render import main as render
    from dynmesh_warp.run import main as run

    out, frames = tmp_path / "run", tmp_path / "frames"
    run_args = ["--viewer", "none", "--device", "cpu", "--no-progress", "--steps", "2"]
    render_args = ["--device", "cpu", "--no-progress", "--frames", "1", "--width", "32", "--height", "24"]
    assert run(run_args + ["--output", str(out)]) == 0
    assert read_manifest_kind(out) == OutputKind.RUN
    before = _snapshot(out)
    capsys.readouterr()
    assert render(render_args + ["--out", str(out), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "holds a run's outputs (summary.json, trajectories.npz)" in err and "rendered frames" in err
    assert _snapshot(out) == before
    # nor a file of it: convert OUT.npz over the run's trajectories.npz replaced it with exit 0
    from dynmesh_warp.convert import main as convert

    assert convert([str(work / "frames"), str(out / "trajectories.npz"), "--device", "cpu", "--overwrite",
                    "--no-progress"]) == 2
    assert "is one of a run's outputs" in capsys.readouterr().err and _snapshot(out) == before
    assert render(render_args + ["--out", str(frames)]) == 0 and read_manifest_kind(frames) == OutputKind.RENDER
    assert render(render_args + ["--out", str(frames), "--overwrite"]) == 0  # the same kind: replaced
    assert run(run_args + ["--output", str(frames), "--overwrite"]) == 2
    assert "holds rendered frames (frame_0000.png)" in capsys.readouterr().err
    assert sorted(p.name for p in frames.iterdir()) == [MANIFEST, "frame_0000.png"]
    # the commit itself: another kind that appeared during the work is not replaced (".new")
    with OutputFolder(out, overwrite=True, holds=OutputKind.RENDER) as tmp:
        (tmp / "frame_0000.png").write_bytes(b"x")
    assert _snapshot(out) == before and (tmp_path / "run.new" / "frame_0000.png").is_file()
    # a manifest without "holds" (written before it was stored) is replaced as before
    (out / MANIFEST).write_text('{"tool": "dynmesh_warp", "files": ["summary.json", "trajectories.npz"]}')
    assert render(render_args + ["--out", str(out), "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "frame_0000.png"]


def test_record_onto_an_existing_file_needs_overwrite(tmp_path, capsys):
    pytest.importorskip("viser")  # --record writes through viser (the GPU machine has none)
    from dynmesh_warp.run import main

    rec = tmp_path / "r.viser"
    rec.write_bytes(b"earlier")
    args = ["--viewer", "none", "--device", "cpu", "--no-progress", "--steps", "2", "--record", str(rec)]
    assert main(args) == 2 and "--overwrite" in capsys.readouterr().err
    assert rec.read_bytes() == b"earlier"
    assert main(args + ["--overwrite"]) == 0
    assert rec.read_bytes() != b"earlier" and rec.with_suffix(".html").is_file()


# --------------------------------------------------------------------------- outputs.py


def test_output_folder_is_untouched_on_error_and_refuses_foreign_files(tmp_path):
    out = tmp_path / "o"
    with OutputFolder(out) as tmp:
        (tmp / "a.txt").write_text("1")
    assert (out / "a.txt").read_text() == "1"
    with pytest.raises(RuntimeError):
        with OutputFolder(out) as tmp:
            (tmp / "a.txt").write_text("2")
            raise RuntimeError("NaN")
    assert (out / "a.txt").read_text() == "1" and sorted(p.name for p in tmp_path.iterdir()) == ["o"]
    (out / "user.txt").write_text("u")
    with pytest.raises(FileExistsError, match="user.txt"):  # the API default: only what it wrote
        with OutputFolder(out) as tmp:
            (tmp / "a.txt").write_text("3")
    with OutputFolder(out, overwrite=True) as tmp:
        (tmp / "b.txt").write_text("3")
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "b.txt", "user.txt"]  # a.txt was ours
    with pytest.raises(OutputError, match="inside the input"):
        check_output(out / "x", kind="folder", what="--out", inputs=[out])


def test_overwrite_never_moves_the_users_files_and_keeps_the_folder(tmp_path, monkeypatch):
    """A new user's second Ctrl-C, 0.6 s into an --overwrite commit that was moving 300k of the
    user's files into the new folder, deleted 140k of them. The user's entries now stay where they
    are (same inodes), the tool's old entries move out and the new ones in; an interruption in the
    middle puts every entry back; the folder keeps its mode bits (setgid) and is not replaced
    where the process stands (run --output . left the shell in a deleted folder)."""
    import dynmesh_warp.outputs as outputs

    out = tmp_path / "o"
    with OutputFolder(out) as tmp:
        (tmp / "frame_0.txt").write_text("old")
    (out / "user.txt").write_text("u")
    (out / "data").mkdir()
    ino = {e: os.stat(out / e).st_ino for e in ("user.txt", "data")}
    folder_ino = os.stat(out).st_ino
    real = os.replace
    calls = []

    def interrupted(a, b):  # the third rename of the commit is interrupted
        calls.append(a)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(a, b)

    monkeypatch.setattr(outputs.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        with OutputFolder(out, overwrite=True) as tmp:
            (tmp / "frame_0.txt").write_text("new")
            (tmp / "frame_1.txt").write_text("new")
    monkeypatch.setattr(outputs.os, "replace", real)
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "data", "frame_0.txt", "user.txt"]
    assert (out / "frame_0.txt").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"]  # no temporaries left
    with OutputFolder(out, overwrite=True) as tmp:
        (tmp / "frame_1.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "data", "frame_1.txt", "user.txt"]
    assert {e: os.stat(out / e).st_ino for e in ino} == ino and os.stat(out).st_ino == folder_ino
    # only the tool's files: the folders are swapped, the new one with the old one's mode bits
    mine = tmp_path / "m"
    with OutputFolder(mine) as tmp:
        (tmp / "a.txt").write_text("1")
    os.chmod(mine, 0o2750)
    with OutputFolder(mine) as tmp:
        (tmp / "a.txt").write_text("2")
    assert (mine / "a.txt").read_text() == "2" and os.stat(mine).st_mode & 0o7777 == 0o2750
    # where the process stands, the folder is not replaced (entry by entry, as with the user's files)
    monkeypatch.chdir(mine)
    with OutputFolder(mine) as tmp:
        (tmp / "a.txt").write_text("3")
    assert os.getcwd() == str(mine) and (Path(os.getcwd()) / "a.txt").read_text() == "3"


def test_a_hard_exit_leaves_a_folder_being_committed(tmp_path):
    """The second signal's clean-up (abandon_temporaries) waits for a commit in progress; when
    it is still going on after the timeout, the folder it moves entries through is left, not
    removed; temporaries of writes not being committed are removed."""
    import threading

    from dynmesh_warp import outputs

    busy, idle = tmp_path / ".o.tmp-1", tmp_path / ".p.tmp-2"
    busy.mkdir()
    idle.mkdir()
    (busy / "user.txt").write_text("u")
    held, release = threading.Event(), threading.Event()

    def commit():
        with outputs._COMMIT:
            held.set()
            release.wait(10)

    t = threading.Thread(target=commit)
    t.start()
    held.wait(10)
    try:
        with outputs.temporary(busy, folder=True):
            assert outputs.abandon_temporaries(timeout=0.1) == [str(busy)]  # named to the user
        assert (busy / "user.txt").read_text() == "u"
    finally:
        release.set()
        t.join()
    with outputs.temporary(idle, folder=True):
        assert outputs.abandon_temporaries(timeout=0.1) == []
    assert not idle.exists()


# --------------------------------------------------------------------------- the work budget


@pytest.mark.parametrize("yaml_text", ["spheres: {count: 2, radius: 1.0e-9}\n",
                                       "physics: {dt: 1.0e-12}\n",
                                       "surface: {source: builtin:wave_bowl, scale: 1.0e7}\n"],
                         ids=["radius_1e-9", "dt_1e-12", "scale_1e7"])
def test_work_budget_refuses_quickly_and_the_flag_lifts_it(tmp_path, capsys, monkeypatch, yaml_text):
    import warp
    import warp._src.context as context

    from dynmesh_warp.run import main
    from dynmesh_warp.world import World

    scene = tmp_path / "s.yaml"
    scene.write_text(yaml_text)
    base = [str(scene), "--viewer", "none", "--device", "cpu", "--no-progress", "--output", str(tmp_path / "o")]
    work = []  # refused before the work: no sub-step (World.substep, whose last kernel is integrate_spheres) ran

    def noting(what, real):
        def call(*args, **kwargs):
            work.append(f"{what} {getattr(args[0], 'key', '') if args else ''}".strip())
            return real(*args, **kwargs)
        return call

    def run_noting(argv) -> tuple[int, list[str]]:
        work.clear()
        with monkeypatch.context() as m:
            launch = noting("launch", context.launch)
            m.setattr(warp, "launch", launch)
            m.setattr(context, "launch", launch)
            m.setattr(World, "substep", noting("substep", World.substep))
            rc = main(argv)
        return rc, [w for w in work if w.startswith("substep") or w == "launch integrate_spheres"]

    rc, stepped = run_noting(base)
    assert rc == 2 and stepped == [], f"refused after the work began: {stepped[:6]}"
    err = capsys.readouterr().err
    assert "work budget" in err and "Fits with" in err and "--no-work-limit" in err
    if "radius" in yaml_text:
        assert "driven by the sphere radius" in err
    elif "scale" in yaml_text:
        assert "driven by the surface speed" in err
    else:
        assert "physics.dt" in err
    # lifted: a run of one step (dt 1e-12: 1 sub-step; the others: one step of many sub-steps)
    if "dt" in yaml_text:
        steps = ["--steps", "3"]
    else:
        scene.write_text(yaml_text + "physics: {dt: 1.0e-6}\n")  # fewer sub-steps per step, same rule
        steps = ["--steps", "1"]
    rc, stepped = run_noting(base + steps + ["--no-work-limit"])
    assert rc in (0, 1) and "substep" in stepped and "launch integrate_spheres" in stepped  # the check sees the work
    assert (tmp_path / "o" / "summary.json").is_file()


# --------------------------------------------------------------------------- values


def test_physics_params_validate_like_the_scene_schema():
    from dynmesh_warp import PhysicsParams
    from dynmesh_warp.config import PhysicsConfig

    with pytest.raises(ValueError) as e:
        PhysicsParams(dt=-0.01, restitution=5, friction=-1)
    assert all(f in str(e.value) for f in ("dt", "restitution", "friction"))
    p = PhysicsParams()
    with pytest.raises(ValueError, match="finite"):
        p.dt = float("nan")
    with pytest.raises(ValueError, match="finite"):
        PhysicsParams(gravity=(0.0, 0.0, float("-inf")))
    assert PhysicsParams().dt == PhysicsConfig().dt  # one place for the defaults


def test_nan_during_a_run_stops_naming_sphere_and_step_and_keeps_previous_outputs(tmp_path, capsys):
    from dynmesh_warp.run import main

    out = tmp_path / "o"
    scene = tmp_path / "s.yaml"
    # (a gravity of -3e38 did this before gravity was bounded: a sphere shot up at 3e38 m/s now)
    scene.write_text("spheres: [{position: [0, 0, 2], velocity: [0, 0, 3.0e+38]}]\n")
    base = [str(scene), "--viewer", "none", "--device", "cpu", "--no-progress", "--output", str(out)]
    assert main(base + ["--steps", "2"]) == 0
    before = _snapshot(out)
    assert main(base + ["--steps", "400", "--overwrite"]) == 1  # float32 overflows after ~270 steps
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "sphere 0" in err and "non-finite" in err and "step 2" in err
    assert _snapshot(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["o", "s.yaml"]


def test_sphere_starting_inside_a_closed_surface_is_refused():
    from dynmesh_warp.config import SceneError, load_scene_config
    from dynmesh_warp.scene import build_world

    inside = load_scene_config(data={"surface": {"source": "builtin:pulsing_blob"},
                                     "spheres": [{"position": [0, 0, 2]}, {"position": [0, 0, 0.6]}]})
    with pytest.raises(SceneError, match=r"spheres\.1: position \[0\.0, 0\.0, 0\.6\] starts inside the closed surface"):
        build_world(inside, device="cpu")  # plain numbers (it printed np.float64(0.0) ...)
    outside = load_scene_config(data={"surface": {"source": "builtin:pulsing_blob"},
                                      "spheres": [{"position": [0, 0, 2]}]})
    assert build_world(outside, device="cpu").model.spheres.count == 1


def test_convert_prints_an_estimate_after_the_second_frame_naming_faster_options(capsys):
    from dynmesh_warp.convert_cli import FrameEstimate

    est = FrameEstimate("cpu", "regularized", limit_s=0.0)  # any length is "long"
    est(5.0, 1, 4)  # the first frame (compilation): no estimate yet
    assert "estimate" not in capsys.readouterr().err
    est(2.0, 2, 4)
    err = capsys.readouterr().err
    assert err.count("estimate:") == 1 and "2.0 s per frame" in err and "--device cuda" in err \
        and "--strategy projection" in err
    assert "about 4 s for 4 frames" in err  # what has passed (~0 s here) + 2 frames left x 2 s
    est(2.0, 3, 4)
    assert "estimate" not in capsys.readouterr().err  # once
    quiet = FrameEstimate("cpu", "tracking", limit_s=1e9)
    quiet(1.0, 1, 3), quiet(1.0, 2, 3)
    assert "estimate" not in capsys.readouterr().err


def test_the_frame_loop_times_each_frame_it_fits():
    """The estimate's input: the frame loop calls ``FRAME_TIMER`` once per fitted frame, with the
    frames done so far (it counted reads of the frame list before, and the input's checks read
    three frames in a millisecond: a new user's 400k-vertex frames got no estimate)."""
    from dynmesh_warp.convert import to_fixed_topology
    from dynmesh_warp.convert_fit import FRAME_TIMER
    from dynmesh_warp.scenes import pulsing_blob

    calls = []
    token = FRAME_TIMER.set(lambda seconds, done, frames: calls.append((seconds, done, frames)))
    try:
        to_fixed_topology(pulsing_blob(subdivisions=2, frames=4).to_varying(), device="cpu", iterations=1,
                          refine_rounds=0, key_frame=1)
    finally:
        FRAME_TIMER.reset(token)
    assert [(d, n) for _, d, n in calls][:4] == [(1, 4), (2, 4), (3, 4), (4, 4)]
    assert all(s > 0 for s, _, _ in calls)


def test_evaluate_estimates_emd_on_the_cpu_up_front(work, capsys):
    from dynmesh_warp.evaluate import main

    assert main([str(work / "gt.npz"), "--out", str(work / "notes.txt" / "x")]) == 2  # checked first, no estimate
    assert "estimate" not in capsys.readouterr().err
    from dynmesh_warp import evaluate

    class A:
        no_emd, compare, scenes, num_frames, frame_stride, emd_stride = False, None, ["s"], 200, 1, 0
        strategies, protocol = ["projection"], ["paper"]

    line = evaluate._emd_estimate(A, "cpu")
    assert "estimate" in line and "--no-emd" in line and "--emd-stride" in line and "--device cuda" in line
    assert evaluate._emd_estimate(A, "cuda:0") is None


def test_convert_refuses_a_bad_key_frame_before_writing(work, tmp_path, capsys):
    from dynmesh_warp import convert

    out = tmp_path / "out.npz"
    with pytest.raises(SystemExit) as e:
        convert.main([str(work / "frames"), str(out), "--key-frame", "middle"])
    assert e.value.code == 2 and "--key-frame" in capsys.readouterr().err
    assert convert.main([str(work / "frames"), str(out), "--key-frame", "9"]) == 2
    err = capsys.readouterr().err
    assert "key_frame" in err and "4 frames" in err, err
    assert list(tmp_path.iterdir()) == []  # nothing written
    assert convert.main([str(work / "frames"), str(out), "--key-frame", "-1", "--strategy", "tracking"]) == 0
    assert "template from frame 3" in capsys.readouterr().out


def test_command_lines_print_their_warnings_as_one_line():
    """While a command line runs (``cli.user_warnings``), a ``UserWarning`` prints as
    ``warning: <message>`` without Python's file, line and source line; other categories keep
    Python's format; the format is restored afterwards."""
    import warnings

    from dynmesh_warp.cli import user_warnings

    before = warnings.formatwarning
    with user_warnings():
        assert warnings.formatwarning("the data is odd", UserWarning, "/x/scene.py", 7, "src()") == \
            "warning: the data is odd\n"
        other = warnings.formatwarning("overflow", RuntimeWarning, "/x/k.py", 3, "a * b")
        assert "RuntimeWarning" in other and "/x/k.py:3" in other
    assert warnings.formatwarning is before


def test_the_helpers_module_run_as_a_command_names_the_commands():
    """A new user's ``python -m dynmesh_warp.cli convert IN OUT`` printed nothing, wrote nothing
    and exited 0; it now exits 2 naming the real commands, each of which is a module with a
    --help (so the list cannot name a command that does not exist)."""
    import importlib

    from dynmesh_warp.cli import COMMANDS

    r = subprocess.run([sys.executable, "-m", "dynmesh_warp.cli", "convert", "a", "b"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "it is not a command" in r.stderr
    for name in COMMANDS:
        assert f"python -m dynmesh_warp.{name} " in r.stderr
        assert hasattr(importlib.import_module(f"dynmesh_warp.{name}"), "main")
    # so did ``python -m dynmesh_warp.viewer scene.yaml`` (another's): it says that run starts it
    r = subprocess.run([sys.executable, "-m", "dynmesh_warp.viewer", "scene.yaml"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "dynmesh_warp.run scene.yaml --viewer viser" in r.stderr


def test_an_output_that_appears_during_convert_is_kept(work, tmp_path, monkeypatch, capsys):
    """Without --overwrite, an output another run wrote while this one worked (the check before
    the work passed) is kept unchanged: this run's frames go beside it, ``<stem>.new.npz``, and
    the user is told. With --overwrite it is replaced, as asked."""
    from dynmesh_warp import convert
    from dynmesh_warp.io import load_sequence

    out = tmp_path / "out.npz"
    real = convert.to_piecewise_fixed

    def other_run_writes_first(*args, **kwargs):
        out.write_bytes(b"the other run's output")
        return real(*args, **kwargs)

    monkeypatch.setattr(convert, "to_piecewise_fixed", other_run_writes_first)
    assert convert.main([str(work / "frames"), str(out), "--device", "cpu", "--no-progress"]) == 0
    cap = capsys.readouterr()
    new = tmp_path / "out.new.npz"
    assert out.read_bytes() == b"the other run's output"
    assert f"{out} appeared during the work" in cap.err and f"wrote {new}: " in cap.out
    assert load_sequence(new).num_frames == 4
    out.unlink()
    assert convert.main([str(work / "frames"), str(out), "--device", "cpu", "--no-progress", "--overwrite"]) == 0
    assert load_sequence(out).num_frames == 4 and not (tmp_path / "out.new-2.npz").exists()


def test_convert_says_when_its_output_does_not_keep_the_frame_rate(work, tmp_path, capsys):
    """A new user's --fps 30 to a folder (or a .pc2 / .anime) read back at 24 fps without a word:
    convert says so for a .pc2 / .anime; a .npz keeps the rate and says nothing, and so does a folder,
    whose manifest keeps it since (the note said it was lost: a later user's)."""
    from dynmesh_warp import convert
    from dynmesh_warp.io import load_sequence

    assert convert.main([str(work / "frames"), str(tmp_path / "f"), "--fps", "30", "--device", "cpu", "--no-progress"]) == 0
    assert "frame rate" not in capsys.readouterr().err and load_sequence(tmp_path / "f").fps == 30.0
    assert convert.main([str(work / "frames"), str(tmp_path / "f.pc2"), "--fps", "30", "--device", "cpu",
                         "--no-progress"]) == 0
    assert "does not store the frame rate (30 fps): it reads back at 24" in capsys.readouterr().err
    assert convert.main([str(work / "frames"), str(tmp_path / "f.npz"), "--fps", "30", "--device", "cpu",
                         "--no-progress"]) == 0
    assert "frame rate" not in capsys.readouterr().err and load_sequence(tmp_path / "f.npz").fps == 30.0


def test_a_stop_before_the_first_frame_is_acted_on_at_once(tmp_path, monkeypatch, capsys):
    """A signal during the input's checks or the converter's set-up (minutes on large frames: a new
    user's SIGINT was acted on 159 s later) stops there: ``ConversionStopped``, nothing fitted; the
    CLI exits 128 + the signal with nothing written. After the first frame the run stops between
    frames and keeps them, as before."""
    from dynmesh_warp import convert as cv
    from dynmesh_warp.convert_fit import FRAME_TIMER
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.scenes import pulsing_blob

    seq = pulsing_blob(subdivisions=2, frames=4).to_varying()
    asked, fitted = [], []
    one = cv.to_fixed_topology(seq, device="cpu", iterations=1, refine_rounds=0, should_stop=lambda: "SIGINT")
    assert one.num_frames == 1  # the Python API, unasked: at least the first frame, as documented
    token = FRAME_TIMER.set(lambda *a: fitted.append(a))
    try:
        with cv.stopping_early():
            with pytest.raises(cv.ConversionStopped, match="SIGINT"):  # stops inside the input's per-frame checks
                cv.to_fixed_topology(seq, device="cpu", iterations=1, refine_rounds=0,
                                     should_stop=lambda: asked.append(1) or ("SIGINT" if len(asked) >= 2 else None))
            assert len(asked) == 2 and not fitted
            later = cv.to_fixed_topology(seq, device="cpu", iterations=1, refine_rounds=0, key_frame=0,
                                         should_stop=lambda: "SIGINT" if fitted else None)
            assert later.num_frames == 1  # the key frame fitted, then the stop between frames
    finally:
        FRAME_TIMER.reset(token)
    save_sequence(seq, tmp_path / "in.npz")
    import dynmesh_warp.cli

    monkeypatch.setattr(dynmesh_warp.cli, "stop_reason", lambda: "SIGTERM")  # as if a SIGTERM came before the work
    assert cv.main([str(tmp_path / "in.npz"), str(tmp_path / "out.npz"), "--device", "cpu", "--no-progress"]) == 143
    assert "interrupted by SIGTERM before any frame was fitted: nothing written" in capsys.readouterr().err
    assert not (tmp_path / "out.npz").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.npz"]  # no journal left either


def test_a_killed_writes_temporary_is_the_tools_own(tmp_path):
    """A run killed (SIGKILL) while it wrote its checkpoint left .checkpoint.XXXXXXXX.tmp.npz in its
    output folder: --resume was then refused ("holds .checkpoint....tmp.npz, which this tool did not
    write") and --overwrite kept it for ever as the user's (a new user's). The tool's own temporaries
    (atomic_path's and OutputFolder's names, made the same way here) are not foreign, and a
    replacement of the folder removes them; a user's look-alike names stay the user's."""
    import tempfile

    from dynmesh_warp.outputs import foreign_entries

    out = tmp_path / "ck"
    with OutputFolder(out) as tmp:
        (tmp / "checkpoint.npz").write_text("1")
    fd, stale = tempfile.mkstemp(prefix=".checkpoint.", suffix=".tmp.npz", dir=out)  # as atomic_path names it
    os.close(fd)
    stale_dir = tempfile.mkdtemp(prefix=".frames.tmp-", dir=out)
    (out / ".notes.tmp").write_text("mine")
    (out / "my.tmp.npz").write_text("mine")
    assert foreign_entries(out) == [".notes.tmp", "my.tmp.npz"]
    with OutputFolder(out, overwrite=True) as tmp:
        (tmp / "checkpoint.npz").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, ".notes.tmp", "checkpoint.npz", "my.tmp.npz"]
    assert not os.path.exists(stale) and not os.path.exists(stale_dir)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")
def test_a_pipe_or_a_device_is_refused_not_read(tmp_path):
    """A pipe given as input waited for a writer for ever; /dev/zero behind an .npz link was read
    until memory ran out; a pipe named as a frame was left out of the folder's numbering unsaid (a
    new user's). Each is now an error naming it, before anything is read."""
    from dynmesh_warp.config import SceneError, load_scene_config
    from dynmesh_warp.io import load_sequence, read_mesh
    from dynmesh_warp.sequence import MeshDataError

    os.mkfifo(tmp_path / "a.ply")
    with pytest.raises(MeshDataError, match=r"a\.ply: not a regular file"):
        load_sequence(tmp_path / "a.ply")
    with pytest.raises(MeshDataError, match=r"a\.ply: not a regular file"):
        read_mesh(tmp_path / "a.ply")
    if os.path.exists("/dev/zero"):
        (tmp_path / "z.npz").symlink_to("/dev/zero")
        with pytest.raises(MeshDataError, match=r"z\.npz: not a regular file"):
            load_sequence(tmp_path / "z.npz")
    frames = tmp_path / "frames"
    frames.mkdir()
    V, F = icosphere(1, 0.5)
    for t in range(2):
        write_mesh(frames / f"frame_{t}.ply", V, F)
    os.mkfifo(frames / "frame_2.ply")
    with pytest.raises(MeshDataError, match=r"frame_2\.ply: not a regular file"):
        load_sequence(frames)
    os.mkfifo(tmp_path / "s.yaml")
    with pytest.raises(SceneError, match=r"s\.yaml: not a regular file, not a scene file"):
        load_scene_config(tmp_path / "s.yaml")


def test_a_full_disk_is_one_line_naming_the_output(tmp_path, monkeypatch, capsys):
    """A full file system (or a file-size limit, a quota, a read-only mount) during the work ended
    in chained tracebacks, exit 1, naming no output (a new user's). The write error is re-raised
    naming the output it was for (numpy's savez names none), the tool's temporary is gone, and the
    CLI says it in one line (convert: with the --resume note, as python -m, where the hint was lost)."""
    import errno

    import dynmesh_warp.io as dio
    from dynmesh_warp.convert import main
    from dynmesh_warp.outputs import atomic_path

    target = tmp_path / "x.npz"
    with pytest.raises(OSError) as info:
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(OSError, match="Permission denied"):  # other errors stay as they are
        with atomic_path(target):
            raise PermissionError(errno.EACCES, "Permission denied")
    src = tmp_path / "in"
    src.mkdir()
    for k, sub in enumerate((1, 2)):
        Vk, Fk = icosphere(sub, 0.5)
        write_mesh(src / f"f_{k}.ply", Vk, Fk)

    def full(seq, path, *a, **k):
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"x")
            raise OSError(errno.EFBIG, "File too large")

    monkeypatch.setattr(dio, "save_sequence", full)  # convert's main imports it from io when it runs
    rc = main([str(src), str(tmp_path / "out.npz"), "--device", "cpu", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and "Traceback" not in err
    line = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    assert len(line) == 1 and line[0].startswith(f"error: {tmp_path / 'out.npz'}: File too large while writing"), err
    assert "--resume to go on from them" in err  # the frame fits are kept in the journal
    assert not (tmp_path / "out.npz").exists()


def test_an_output_name_too_long_for_what_is_written_beside_it_is_refused_first(tmp_path, capsys):
    """A 240-byte output name is legal, but its journal and temporaries beside it are not: convert
    and run failed after the work with an ENAMETOOLONG traceback (a new user's). Refused before the
    work now, naming the limit; a name that fits is taken."""
    from dynmesh_warp.io import load_sequence, save_sequence
    from dynmesh_warp.outputs import SIBLING_NAME_BYTES

    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    with pytest.raises(OutputError, match=rf"its name is {limit - 20} bytes.*at most {limit - SIBLING_NAME_BYTES}"):
        check_output(tmp_path / ("b" * (limit - 24) + ".npz"), kind="file", what="output")
    check_output(tmp_path / ("b" * (limit - SIBLING_NAME_BYTES - 4) + ".npz"), kind="file", what="output")
    src = tmp_path / "in"
    src.mkdir()
    for k, sub in enumerate((1, 2)):
        write_mesh(src / f"f_{k}.ply", *icosphere(sub, 0.5))
    from dynmesh_warp.convert import main

    assert main([str(src), str(tmp_path / ("c" * (limit - 10) + ".npz")), "--device", "cpu", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error: output" in err and "bytes" in err
    with pytest.raises(OutputError, match="its name is"):
        save_sequence(load_sequence(src / "f_0.ply"), tmp_path / ("q" * (limit - 4) + ".npz"))


def test_a_folder_made_meanwhile_by_another_save_is_not_a_traceback(tmp_path, monkeypatch):
    """Two saves to one new folder at once: the second's rename met the folder the first had just
    made, "[Errno 39] Directory not empty: '.out.tmp-...' -> 'out'" (a new user's, 1 try in 10), and
    its result was thrown away. The commit now goes again by the rules of an existing folder (here:
    the other's output, this tool's, is replaced); a white-space name is refused first."""
    import errno

    import dynmesh_warp.outputs as outputs

    out = tmp_path / "out"
    real_replace = os.replace
    calls = []

    def racing(src, dst):
        if Path(dst) == out and not calls:
            calls.append(1)
            with OutputFolder(tmp_path / "other") as tmp:  # the other process's whole save
                (tmp / "frame_0000.ply").write_text("theirs")
            real_replace(tmp_path / "other", out)
            raise OSError(errno.ENOTEMPTY, "Directory not empty", str(src), None, str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(outputs.os, "replace", racing)
    with OutputFolder(out) as tmp:
        (tmp / "frame_0000.ply").write_text("mine")
    assert calls and (out / "frame_0000.ply").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporary left
    monkeypatch.undo()
    with pytest.raises(OutputError, match="white space"):
        check_output(tmp_path / "trail.npz ", kind="file", what="output")


def test_a_users_file_where_the_journal_goes_is_named_as_a_file(tmp_path, capsys):
    """A user's file named OUT.convert-journal was called an unreadable journal folder, "remove the
    folder to start over" (a new user's); it is named as a file, to be moved, and kept."""
    from dynmesh_warp.convert import main

    src = tmp_path / "in"
    src.mkdir()
    for k, sub in enumerate((1, 2)):
        write_mesh(src / f"f_{k}.ply", *icosphere(sub, 0.5))
    mine = tmp_path / "o.npz.convert-journal"
    mine.write_text("my notes")
    rc = main([str(src), str(tmp_path / "o.npz"), "--device", "cpu", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "a file where convert keeps its journal" in err and "Traceback" not in err, err
    assert mine.read_text() == "my notes"


@pytest.mark.skipif(sys.platform != "linux", reason="a file name that is not UTF-8 needs a byte-named file system")
def test_a_sequence_whose_name_is_not_utf8_is_named(tmp_path):
    """run / render on a sequence whose file name is not valid UTF-8 said "<scene dict>:
    surface.source: Input should be a valid string", naming no file (a new user's)."""
    from dynmesh_warp.config import SceneError, scene_source

    V, F = icosphere(1, 0.5)
    name = os.fsdecode(b"bad\xff.npz")
    write_mesh(tmp_path / "ok.ply", V, F)
    os.rename(tmp_path / "ok.ply", tmp_path / name)
    with pytest.raises(SceneError, match=r"bad\\udcff\.npz'?: the file's name is not valid UTF-8"):
        scene_source(str(tmp_path / name))
