"""Issue 17: Ctrl-C / SIGTERM stop the command lines at a step or frame boundary and keep what
was done; checkpoints resume a run bit for bit on the CPU; a second Ctrl-C exits at once.

The signal tests run the real command lines in subprocesses and send the signal only after the
work has visibly started (the progress bar or a line on stdout), so they do not depend on
timing; each then checks the exit code (130 / 143), that stderr ends in one line saying what
was written and holds no traceback, and the outputs against an uninterrupted run computed
here. The checkpoint tests compare trajectories with ``np.array_equal`` (bit for bit).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dynmesh_warp.outputs import MANIFEST

RUN = [sys.executable, "-m", "dynmesh_warp.run", "--viewer", "none", "--device", "cpu"]
CODE = {signal.SIGINT: 130, signal.SIGTERM: 143}


class Proc:
    """A command line in a subprocess whose stderr (progress bars, no newlines) is read as it comes."""

    def __init__(self, argv, cwd):
        self.p = subprocess.Popen(argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        os.set_blocking(self.p.stderr.fileno(), False)
        os.set_blocking(self.p.stdout.fileno(), False)
        self.err, self.out = b"", b""

    def _read(self):
        for name in ("err", "out"):
            f = getattr(self.p, "stderr" if name == "err" else "stdout")
            try:
                d = os.read(f.fileno(), 1 << 16)
            except BlockingIOError:
                continue
            setattr(self, name, getattr(self, name) + (d or b""))

    def wait_for(self, text: bytes, where: str = "err", timeout: float = 120.0):
        t0 = time.monotonic()
        while text not in getattr(self, where):
            assert self.p.poll() is None, f"exited ({self.p.returncode}) before {text!r}: {self.err.decode()[-2000:]}"
            assert time.monotonic() - t0 < timeout, f"no {text!r} after {timeout} s"
            self._read()
            time.sleep(0.02)

    def finish(self, timeout: float = 60.0) -> tuple[int, str, str]:
        t0 = time.monotonic()
        while self.p.poll() is None:
            assert time.monotonic() - t0 < timeout, "did not stop"
            self._read()
            time.sleep(0.01)
        self._read()
        self.p.stdout.close()
        self.p.stderr.close()
        return self.p.returncode, self.out.decode(), self.err.decode().replace("\r", "\n")


def _last_line(err: str) -> str:
    return [ln for ln in err.splitlines() if ln.strip()][-1]


def _leftovers(folder: Path) -> list[str]:
    """Temporary files or folders of the atomic writers left in ``folder``."""
    return sorted(p.name for p in folder.iterdir() if ".tmp" in p.name or ".old-" in p.name)


def _run_inprocess(args) -> int:
    from dynmesh_warp.run import main

    return main(["--viewer", "none", "--device", "cpu", "--no-progress", *args])


def _same_trajectories(a: Path, b: Path):
    ta, tb = np.load(a / "trajectories.npz"), np.load(b / "trajectories.npz")
    assert sorted(ta.files) == sorted(tb.files)
    for k in ta.files:
        assert ta[k].shape == tb[k].shape, k
        assert np.array_equal(ta[k], tb[k]), f"{k} differs"
    sa, sb = (json.loads((x / "summary.json").read_text()) for x in (a, b))
    assert sa["final"] == sb["final"]
    assert sa["sim_time_s"] == sb["sim_time_s"]
    assert sa["contacts"] == sb["contacts"]


# --------------------------------------------------------------------------- run


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_run_stops_at_a_step_and_writes_the_prefix_of_the_run(tmp_path, capsys, sig):
    """An interrupted run = a run of the steps it reached: same trajectories, final state, contacts."""
    out = tmp_path / "o"
    pr = Proc(RUN + ["--steps", "2000000", "--output", str(out)], tmp_path)
    pr.wait_for(b"step/s")  # the progress bar: the timed loop is running
    time.sleep(0.3)
    t0 = time.monotonic()
    pr.p.send_signal(sig)
    rc, _, err = pr.finish()
    assert time.monotonic() - t0 < 5.0
    assert rc == CODE[sig], err[-2000:]
    assert "Traceback" not in err
    line = _last_line(err)
    name = signal.Signals(sig).name
    assert line.startswith(f"interrupted by {name} at step ") and "summary.json" in line, line
    summary = json.loads((out / "summary.json").read_text())
    k = summary["step_reached"]
    assert summary["interrupted"] is True and summary["interrupted_by"] == name
    assert summary["steps"] == 2_000_000 and 1 < k < 2_000_000 and f"{k:,}" in line
    assert summary["checkpoint"] is None and not (out / "checkpoint.npz").exists()  # not asked for
    assert json.loads((out / MANIFEST).read_text())["files"] == ["summary.json", "trajectories.npz"]
    assert _leftovers(tmp_path) == []
    # the run of exactly k steps, uninterrupted, gives the same files' content (with the collider
    # the interrupted run chose: the automatic choice is timed, and a busy CI machine once chose
    # the other one, whose contacts differ in the last bits)
    ref = tmp_path / "ref"
    assert _run_inprocess(["--steps", str(k), "--collider", summary["collider"], "--output", str(ref)]) == 0
    _same_trajectories(out, ref)
    traj = np.load(out / "trajectories.npz")
    assert np.array_equal(traj["position"][-1], np.asarray(summary["final"]["position"], np.float32))
    capsys.readouterr()


def test_run_stop_callable_ends_the_loop_within_a_chunk(tmp_path):
    """run_scene(stop=...) (what the CLI's signal flag drives): stops within a chunk of steps,
    writes trajectories equal to a run of the reached length, and marks the summary."""
    from dynmesh_warp import load_scene_config
    from dynmesh_warp.run import run_scene

    cfg = load_scene_config(data={"name": "s", "spheres": {"count": 3, "radius": 0.08, "seed": 2},
                                  "run": {"record_every": 3}})
    calls = []

    def stop():
        calls.append(time.perf_counter())
        return "test-stop" if len(calls) > 12 else None

    s = run_scene(cfg, device="cpu", steps=100_000, output=tmp_path / "a", progress=False, log=lambda *_: None,
                  stop=stop)
    k = s["step_reached"]
    assert s["interrupted"] and s["interrupted_by"] == "test-stop" and 1 < k < 100_000
    assert s["timed_wall_s"] < 5.0  # chunks of ~0.05 s: thirteen checks are well under a second of steps
    ref = run_scene(cfg, device="cpu", steps=k, output=tmp_path / "b", progress=False, log=lambda *_: None)
    assert not ref["interrupted"] and ref["step_reached"] == k and ref["interrupted_by"] is None
    _same_trajectories(tmp_path / "a", tmp_path / "b")
    # steps 0, 3, 6, ... and the last
    assert len(np.load(tmp_path / "a" / "trajectories.npz")["time"]) == 1 + k // 3 + (k % 3 > 0)


def test_an_interrupted_run_never_replaces_an_earlier_output(tmp_path, capsys):
    """A new user's complete run became an interrupted one under --overwrite. An interrupted run
    (no checkpoints) writes beside an earlier output, ``<out>.partial``; a complete one replaces
    it as asked; files another run put in the folder during a run without --overwrite are kept
    and the run's outputs go to ``<out>.new`` (the whole run was thrown away)."""
    from dynmesh_warp import load_scene_config
    from dynmesh_warp.run import run_scene

    cfg = load_scene_config(data={"name": "s", "spheres": {"count": 2, "radius": 0.08, "seed": 2}})
    out = tmp_path / "o"
    quiet = {"device": "cpu", "progress": False, "log": lambda *_: None}
    run_scene(cfg, steps=20, output=out, **quiet)
    before = (out / "summary.json").read_bytes()
    calls = []
    s = run_scene(cfg, steps=100_000, output=out, overwrite=True, stop=lambda: calls.append(1) or
                  ("SIGINT" if len(calls) > 3 else None), **quiet)
    assert s["interrupted"] and s["output"] == str(tmp_path / "o.partial")
    assert (out / "summary.json").read_bytes() == before
    assert json.loads((tmp_path / "o.partial" / "summary.json").read_text())["interrupted"]
    assert "o holds an earlier output, which an interrupted run does not replace" in capsys.readouterr().err
    run_scene(cfg, steps=30, output=out, overwrite=True, **quiet)  # complete: replaces it
    assert json.loads((out / "summary.json").read_text())["step_reached"] == 30

    fresh = tmp_path / "f"

    def another_run_writes(sim, *a, **k):  # files appear in the output folder during the run
        fresh.mkdir()
        (fresh / "mine.txt").write_text("the other run's")
        return real(sim, *a, **k)

    import dynmesh_warp.runner as runner

    real = runner.timed_loop
    try:
        runner.timed_loop = another_run_writes
        s = run_scene(cfg, steps=10, output=fresh, overwrite=False, **quiet)  # the CLI without --overwrite
    finally:
        runner.timed_loop = real
    assert s["output"] == str(tmp_path / "f.new") and (tmp_path / "f.new" / "summary.json").is_file()
    assert sorted(p.name for p in fresh.iterdir()) == ["mine.txt"]
    assert "gained files during the run" in capsys.readouterr().err
    # another run's output that appeared meanwhile (this tool's files) is not replaced either: a new
    # user's long run silently replaced a short run's finished output
    other = tmp_path / "g"

    def another_run_finishes_first(sim, *a, **k):
        runner.timed_loop = real  # the other run steps as usual
        run_scene(cfg, steps=5, output=other, **quiet)
        return real(sim, *a, **k)

    try:
        runner.timed_loop = another_run_finishes_first
        s = run_scene(cfg, steps=10, output=other, overwrite=False, **quiet)
    finally:
        runner.timed_loop = real
    assert s["output"] == str(tmp_path / "g.new")
    assert json.loads((other / "summary.json").read_text())["step_reached"] == 5


def test_newton_run_stops_at_a_step_and_writes_the_prefix(tmp_path):
    """The Newton path of run_scene takes the same stop callable: an interrupted run writes the
    body trajectory of the steps reached, equal to an uninterrupted run of that length."""
    pytest.importorskip("newton")
    from dynmesh_warp import load_scene_config
    from dynmesh_warp.run import run_scene

    cfg = load_scene_config(data={
        "name": "nt", "surface": {"source": "builtin:wave_bowl", "params": {"n": 16, "frames": 12}},
        "spheres": [{"position": [0.3, 0.0, 0.6], "radius": 0.06}],
        "newton": {"solver": "xpbd", "bodies": [{"type": "box", "position": [-0.3, 0.0, 0.6],
                                                  "half_extents": [0.08, 0.06, 0.05]}]},
        "run": {"record_every": 4}})
    calls = []

    def stop():
        calls.append(1)
        return "SIGTERM" if len(calls) > 5 else None

    s = run_scene(cfg, device="cpu", steps=1_000_000, output=tmp_path / "a", progress=False,
                  log=lambda *_: None, stop=stop)
    k = s["step_reached"]
    assert s["engine"] == "newton" and s["interrupted"] and s["interrupted_by"] == "SIGTERM" and 2 < k < 1_000_000
    assert s["steps"] == 1_000_000 and json.loads((tmp_path / "a" / "summary.json").read_text())["interrupted"]
    ref = run_scene(cfg, device="cpu", steps=k, output=tmp_path / "b", progress=False, log=lambda *_: None)
    assert not ref["interrupted"] and ref["step_reached"] == k
    ta, tb = np.load(tmp_path / "a" / "trajectories.npz"), np.load(tmp_path / "b" / "trajectories.npz")
    assert np.array_equal(ta["time"], tb["time"]) and np.array_equal(ta["body_q"], tb["body_q"])
    assert np.array_equal(ta["body_q"][-1], np.asarray(s["final"]["body_q"], np.float32))


# --------------------------------------------------------------------------- checkpoints


@pytest.mark.parametrize("collider,steps,every,more", [("swept", 700, 200, 300), ("refit", 300, 100, 150),
                                                       ("rebuild", 60, 25, 40)])
def test_resume_from_a_checkpoint_is_bit_identical(tmp_path, collider, steps, every, more):
    """A run of ``steps`` with --checkpoint-every leaves the checkpoint of its last multiple;
    resuming from it to ``steps + more`` gives the uninterrupted run of ``steps + more``, bit
    for bit (trajectories, final state, contact counts)."""
    base = ["--collider", collider, "--output"]
    a = tmp_path / "a"
    assert _run_inprocess(["--steps", str(steps), "--checkpoint-every", str(every)] + base + [str(a)]) == 0
    meta = json.loads(str(np.load(a / "checkpoint.npz")["meta"]))
    assert meta["step"] == (steps // every) * every and meta["checkpoint_every"] == every
    assert "checkpoint.npz" in json.loads((a / MANIFEST).read_text())["files"]
    total = steps + more
    b = tmp_path / "b"  # resumed into another folder (the checkpoint is only read)
    assert _run_inprocess(["--steps", str(total), "--resume", str(a / "checkpoint.npz")] + base + [str(b)]) == 0
    ref = tmp_path / "ref"
    assert _run_inprocess(["--steps", str(total)] + base + [str(ref)]) == 0
    _same_trajectories(b, ref)
    sb = json.loads((b / "summary.json").read_text())
    assert sb["resumed_from"]["step"] == meta["step"] and sb["step_reached"] == total
    assert sb["checkpoint"]["every"] == every  # the interval is kept on resume


def test_resume_of_rolling_spheres_is_bit_identical_and_an_old_checkpoint_had_none(tmp_path, capsys):
    """Spheres that roll (physics.sphere_body: solid) resume with their spins, bit for bit; a
    checkpoint without spins (written before they were kept) resumes a point-mass scene as it
    was, and is refused for a rolling one (its fingerprint's body is point)."""
    roll = ["--set", "physics.sphere_body=solid", "--collider", "swept"]
    a, b, ref = tmp_path / "a", tmp_path / "b", tmp_path / "ref"
    assert _run_inprocess(["--steps", "300", "--checkpoint-every", "150", "--output", str(a)] + roll) == 0
    assert np.abs(np.load(a / "checkpoint.npz")["sphere_spin"]).max() > 0.1  # they did spin
    assert _run_inprocess(["--steps", "450", "--resume", str(a / "checkpoint.npz"), "--output", str(b)] + roll) == 0
    assert _run_inprocess(["--steps", "450", "--output", str(ref)] + roll) == 0
    _same_trajectories(b, ref)
    c = tmp_path / "c"  # a point-mass run's checkpoint with the spins and the body taken out
    assert _run_inprocess(["--steps", "60", "--checkpoint-every", "30", "--collider", "swept", "--output", str(c)]) == 0
    d = dict(np.load(c / "checkpoint.npz"))
    d.pop("sphere_spin")
    meta = json.loads(str(d["meta"]))
    del meta["fingerprint"]["physics.sphere_body"]
    d["meta"] = np.asarray(json.dumps(meta))
    np.savez(tmp_path / "old.npz", **d)
    capsys.readouterr()
    out, ref2 = tmp_path / "out", tmp_path / "ref2"
    assert _run_inprocess(["--steps", "90", "--resume", str(tmp_path / "old.npz"), "--collider", "swept",
                           "--output", str(out)]) == 0
    assert _run_inprocess(["--steps", "90", "--collider", "swept", "--output", str(ref2)]) == 0
    _same_trajectories(out, ref2)
    capsys.readouterr()
    assert _run_inprocess(["--steps", "90", "--resume", str(tmp_path / "old.npz"), "--output", str(tmp_path / "x")]
                          + roll) == 2
    assert "physics.sphere_body is 'point' in the checkpoint but 'solid' here" in capsys.readouterr().err


def test_a_stop_says_how_long_the_frame_in_progress_may_take(capsys, monkeypatch):
    """A stop's acknowledgement adds the hint ``convert`` sets (``cli.set_stop_hint``): the frame
    being fitted may take as long as the last (a new user's 390k-vertex frame went on for 6
    minutes after Ctrl-C, unsaid); nothing for short frames."""
    from dynmesh_warp import cli
    from dynmesh_warp.convert_cli import FrameEstimate

    est = FrameEstimate("cpu", "graph")
    est(2.0, 1, 10)
    assert est.stop_hint() == ""
    est(382.0, 2, 10)
    assert est.stop_hint() == "after the frame being fitted: about 6 min, as long as the last one took"
    monkeypatch.setattr(cli._state, "installed", True)
    monkeypatch.setattr(cli._state, "done", __import__("threading").Event())
    monkeypatch.setattr(cli._state, "seen", __import__("threading").Event())
    cli.set_stop_hint(est.stop_hint)
    try:
        cli._acknowledge(2)
    finally:
        cli.set_stop_hint(None)
    err = capsys.readouterr().err
    assert "SIGINT: stopping at the next step or frame and writing what is done (after the frame being fitted: " \
           "about 6 min, as long as the last one took); send it again" in err


def test_resume_keeps_the_collider_fixed_chose(tmp_path, monkeypatch):
    """``fixed`` is measured and may choose differently on another machine: a resumed run takes
    the collider its checkpoint was written with, whatever a new measurement says."""
    import dynmesh_warp.world as world_mod

    a, b = tmp_path / "a", tmp_path / "b"
    monkeypatch.setattr(world_mod, "measure_colliders", lambda m, s, c: {k: 2.0 if k == "refit" else 1.0 for k in c})
    assert _run_inprocess(["--steps", "60", "--checkpoint-every", "30", "--output", str(a)]) == 0
    assert json.loads(str(np.load(a / "checkpoint.npz")["meta"]))["fingerprint"]["physics.collider"] == "swept"
    monkeypatch.setattr(world_mod, "measure_colliders", lambda m, s, c: {k: 1.0 if k == "refit" else 2.0 for k in c})
    assert _run_inprocess(["--steps", "90", "--resume", str(a / "checkpoint.npz"), "--output", str(b)]) == 0
    assert json.loads((b / "summary.json").read_text())["collider"] == "swept"


def test_interrupted_run_checkpoints_where_it_stops_and_resumes_in_place(tmp_path, capsys):
    """Ctrl-C with checkpointing on: checkpoint.npz at the step reached; --resume into the same
    folder (no --overwrite needed: all of it is the tool's) finishes the run as if never stopped."""
    out = tmp_path / "o"
    pr = Proc(RUN + ["--steps", "2000000", "--checkpoint-every", "1000", "--output", str(out)], tmp_path)
    pr.wait_for(b"step/s")
    time.sleep(0.3)
    pr.p.send_signal(signal.SIGINT)
    rc, _, err = pr.finish()
    assert rc == 130 and "Traceback" not in err, err[-2000:]
    k = json.loads((out / "summary.json").read_text())["step_reached"]
    meta = json.loads(str(np.load(out / "checkpoint.npz")["meta"]))
    assert meta["step"] == k and f"--resume {out / 'checkpoint.npz'}" in _last_line(err)
    total = k + 700
    assert _run_inprocess(["--steps", str(total), "--resume", str(out / "checkpoint.npz"), "--output", str(out)]) == 0
    ref = tmp_path / "ref"
    assert _run_inprocess(["--steps", str(total), "--output", str(ref)]) == 0
    _same_trajectories(out, ref)
    assert json.loads((out / "summary.json").read_text())["interrupted"] is False
    assert _leftovers(tmp_path) == []
    capsys.readouterr()


def test_the_resume_hint_says_overwrite_where_the_folder_holds_the_users_files(tmp_path):
    """A folder holding the user's files takes --overwrite to resume into: the stop line's hint
    lacked it, and the command it gave was refused (a new user's)."""
    from dynmesh_warp.outputs import OutputFolder
    from dynmesh_warp.run import _interrupted_line

    out = tmp_path / "o"
    with OutputFolder(out) as tmp:
        (tmp / "checkpoint.npz").write_bytes(b"x")
    summary = {"output": str(out), "interrupted_by": "SIGINT", "step_reached": 5, "steps": 10,
               "checkpoint": {"file": "checkpoint.npz", "step": 5, "every": 5}}
    assert _interrupted_line(summary).endswith(f"--resume {out / 'checkpoint.npz'} (same scene and options)")
    (out / "notes.txt").write_text("mine")
    assert _interrupted_line(summary).endswith(f"--resume {out / 'checkpoint.npz'} --overwrite (same scene and options)")


def test_checkpoint_of_another_scene_or_a_broken_file_is_refused(tmp_path, capsys):
    a = tmp_path / "a"
    assert _run_inprocess(["--steps", "20", "--checkpoint-every", "10", "--output", str(a)]) == 0
    ck = a / "checkpoint.npz"
    capsys.readouterr()
    six = tmp_path / "six.yaml"
    six.write_text("spheres: {count: 6, radius: 0.08, height: 0.4, seed: 1}\n")
    # the collider the checkpoint did not use (fixed picks swept or refit by their measured cost: under
    # load a CI run's pick was refit, and "--collider refit" then resumed it, exit 0)
    import json

    used = json.loads(str(np.load(ck)["meta"]))["fingerprint"]["physics.collider"]
    other = "refit" if used != "refit" else "swept"
    cases = [
        ([str(six), "--steps", "40", "--resume", str(ck)], ["spheres.count", "5 in the checkpoint", "6 here", str(ck)]),
        (["--steps", "40", "--collider", other, "--resume", str(ck)], ["physics.collider", f"'{used}'", f"'{other}'"]),
        # the spheres' start (a resume with another start went on with the old trajectory, exit 0)
        (["--steps", "40", "--set", "spheres.seed=2", "--resume", str(ck)], ["spheres.start"]),
        (["--steps", "10", "--resume", str(ck)], ["step 20", "10 steps", "give more"]),
        # the trajectory's sampling (a resumed run at another record_every mixed two spacings)
        (["--steps", "40", "--set", "run.record_every=7", "--resume", str(ck)],
         ["sampled every 4 steps", "asks 7", "run.record_every=4"]),
        (["--resume", str(tmp_path / "none.npz")], ["none.npz", "not found"]),
    ]
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all")
    cases.append((["--resume", str(junk)], ["junk.npz", "not a checkpoint"]))
    d = dict(np.load(ck))
    d["format"] = np.asarray("dynmesh_warp.checkpoint/2")  # an earlier format (its samples on another grid)
    np.savez(tmp_path / "old.npz", **d)
    cases.append((["--resume", str(tmp_path / "old.npz")], ["old.npz", "'format'", "checkpoint/2", "checkpoint/4",
                                                          "checkpoint/3"]))
    d = dict(np.load(ck))
    d.pop("sphere_vel")
    np.savez(tmp_path / "novel.npz", **d)
    cases.append((["--resume", str(tmp_path / "novel.npz")], ["novel.npz", "'sphere_vel'"]))
    d = dict(np.load(ck))
    d["sphere_pos"] = d["sphere_pos"].copy()
    d["sphere_pos"][2, 1] = np.nan
    np.savez(tmp_path / "nan.npz", **d)
    cases.append((["--resume", str(tmp_path / "nan.npz")], ["nan.npz", "'sphere_pos'", "NaN"]))
    for args, needles in cases:
        out = tmp_path / "out"
        assert _run_inprocess(args + ["--output", str(out)]) == 2, args
        err = capsys.readouterr().err.strip()
        assert err.startswith("error: ") and len(err.splitlines()) == 1, err
        for n in needles:
            assert n in err, (n, err)
        assert not out.exists()


def test_a_checkpoint_of_the_previous_format_resumes_without_the_pinch_memory(tmp_path, capsys):
    """A checkpoint written before the pinch memory (format 3: no ``contact_memory``) resumes with
    an empty one, said in a warning; where no sphere was pinched the run goes on bit for bit as
    the uninterrupted one (the default scene). An interrupted run of the previous version keeps
    what it had done."""
    a = tmp_path / "a"
    assert _run_inprocess(["--steps", "40", "--checkpoint-every", "20", "--output", str(a)]) == 0
    d = dict(np.load(a / "checkpoint.npz"))
    d.pop("contact_memory")
    d["format"] = np.asarray("dynmesh_warp.checkpoint/3")
    np.savez(tmp_path / "v3.npz", **d)
    capsys.readouterr()
    out = tmp_path / "out"
    with pytest.warns(UserWarning, match=r"checkpoint/3\), written before the integrator kept a pinch memory"):
        assert _run_inprocess(["--steps", "120", "--resume", str(tmp_path / "v3.npz"), "--output", str(out)]) == 0
    ref = tmp_path / "ref"
    assert _run_inprocess(["--steps", "120", "--output", str(ref)]) == 0
    _same_trajectories(out, ref)


def test_newton_scene_refuses_checkpoints(tmp_path, capsys):
    scene = tmp_path / "n.yaml"
    scene.write_text("newton:\n  bodies: [{type: sphere, radius: 0.1, position: [0, 0, 1]}]\nrun: {steps: 2}\n")
    assert _run_inprocess([str(scene), "--checkpoint-every", "1", "--output", str(tmp_path / "o")]) == 2
    assert "newton" in capsys.readouterr().err


# --------------------------------------------------------------------------- convert, evaluate


@pytest.fixture(scope="module")
def varying_npz(tmp_path_factory) -> Path:
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.scenes import torus_to_sphere

    p = tmp_path_factory.mktemp("conv") / "ts.npz"
    # 120 frames: a stop sent once the progress bar shows comes long before the end (~35 ms a frame
    # at resolution 24, 1,008 vertices; 32 took twice that for what the tests here check)
    save_sequence(torus_to_sphere(frames=120, resolution=24), p)
    return p


@pytest.fixture(scope="module")
def varying_regularized(varying_npz):
    """The uninterrupted ``regularized`` conversion of ``varying_npz``: the oracle of the
    interrupted command lines' frames (both signals), computed once."""
    from dynmesh_warp.convert import to_fixed_topology
    from dynmesh_warp.io import load_sequence

    return to_fixed_topology(load_sequence(varying_npz), strategy="regularized", device="cpu")


def test_to_fixed_topology_should_stop_keeps_a_prefix(varying_npz):
    from dynmesh_warp.convert import to_fixed_topology
    from dynmesh_warp.io import load_sequence

    seq = load_sequence(varying_npz)
    full = to_fixed_topology(seq, strategy="tracking", device="cpu", key_frame=0)
    n = []
    part = to_fixed_topology(seq, strategy="tracking", device="cpu", key_frame=0,
                             should_stop=lambda: n.append(1) or len(n) > 7)
    assert part.num_frames == 8 and np.array_equal(part.V, full.V[:8]) and np.array_equal(part.F, full.F)
    one = to_fixed_topology(seq, strategy="tracking", device="cpu", should_stop=lambda: True, key_frame=0)
    assert one.num_frames == 1  # the first frame is always converted: a valid (shorter) sequence
    # from a key frame in the middle: forward to the end first, then backward; a stop keeps the
    # contiguous frames done (first_frame..) and they equal the uninterrupted conversion's
    full = to_fixed_topology(seq, strategy="tracking", device="cpu", key_frame=100)
    n = []
    part = to_fixed_topology(seq, strategy="tracking", device="cpu", key_frame=100,
                             should_stop=lambda: n.append(1) or len(n) > 29)
    assert part.conversion.first_frame == 90 and part.num_frames == 30
    assert np.array_equal(part.V, full.V[90:120])


@pytest.mark.parametrize("sig,folder", [(signal.SIGINT, False), (signal.SIGTERM, True)],
                         ids=["SIGINT-npz", "SIGTERM-folder"])
def test_convert_interrupted_writes_the_frames_done(tmp_path, varying_npz, varying_regularized, sig, folder, capsys):
    from dynmesh_warp.io import load_sequence

    out = tmp_path / ("frames" if folder else "out.npz")
    if folder:
        out.mkdir()
        (out / "mine.txt").write_text("kept")
    pr = Proc([sys.executable, "-m", "dynmesh_warp.convert", str(varying_npz), str(out), "--strategy",
               "regularized", "--device", "cpu"] + (["--overwrite"] if folder else []), tmp_path)
    pr.wait_for(b"frame/s")
    pr.p.send_signal(sig)
    rc, _, err = pr.finish()
    assert rc == CODE[sig] and "Traceback" not in err, err[-2000:]
    name = signal.Signals(sig).name
    line = _last_line(err)
    assert line.startswith(f"interrupted by {name}: wrote {out} with input frames "), line
    with pytest.warns(UserWarning, match=r"written by a run that was stopped \((SIGINT|SIGTERM)\): it holds input "
                                         r"frames \d+\.\.\d+ of 0\.\.119"):  # it played with no word (a new user's)
        got = load_sequence(out)  # a valid sequence
    assert 1 <= got.num_frames < 120
    if folder:
        status = json.loads((out / MANIFEST).read_text())["status"]
        assert (out / "mine.txt").read_text() == "kept"
        assert status.pop("fps") == got.fps == 24.0  # the frame rate, which a folder cannot say itself
    else:
        status = json.loads(str(np.load(out)["status"]))
    k = status["first_frame"]
    seg = status.pop("segments")
    assert status == {"complete": False, "frames": got.num_frames, "input_frames": 120, "interrupted_by": name,
                      "first_frame": k, "strategy": "regularized"}
    assert len(seg) == 1 and seg[0][:2] == [k, k + got.num_frames] and seg[0][3] == got.V.shape[1]
    if folder:  # the frames keep their input numbers (they were written from frame_0000)
        assert sorted(p.name for p in out.glob("frame_*")) == [f"frame_{t:04d}.ply" for t in range(k, k + got.num_frames)]
    assert f"frames {k}..{k + got.num_frames - 1} of 0..119" in line
    full = varying_regularized
    np.testing.assert_allclose(got.V, full.V[k:k + got.num_frames], atol=1e-6)  # .ply / .npz round trip of the same frames
    assert _leftovers(tmp_path) == []
    capsys.readouterr()


def test_convert_interrupted_keeps_an_existing_output(tmp_path, varying_npz, capsys):
    """An interrupted ``convert --overwrite`` does not replace the output that was there (an
    earlier run's, maybe complete): the frames done go beside it, ``<stem>.partial.npz``."""
    from dynmesh_warp.io import load_sequence

    out = tmp_path / "out.npz"
    out.write_bytes(b"an earlier run's output")
    (tmp_path / "out.partial.npz").write_bytes(b"another file")  # taken: the next free name is used
    pr = Proc([sys.executable, "-m", "dynmesh_warp.convert", str(varying_npz), str(out), "--strategy",
               "regularized", "--device", "cpu", "--overwrite"], tmp_path)
    pr.wait_for(b"frame/s")
    pr.p.send_signal(signal.SIGINT)
    rc, _, err = pr.finish()
    assert rc == 130 and "Traceback" not in err, err[-2000:]
    partial = tmp_path / "out.partial-2.npz"
    line = _last_line(err)
    assert line.startswith(f"interrupted by SIGINT: wrote {partial} with input frames "), line
    assert f"{out}, which was there before, is unchanged; the same command with --resume goes on from the " in line
    assert out.read_bytes() == b"an earlier run's output"
    assert (tmp_path / "out.partial.npz").read_bytes() == b"another file"
    got = load_sequence(partial)
    assert 1 <= got.num_frames < 120
    assert json.loads(str(np.load(partial)["status"]))["complete"] is False
    assert _leftovers(tmp_path) == []
    capsys.readouterr()


def test_convert_signal_sent_twice_at_once_is_one_stop(tmp_path, varying_npz, capsys):
    """coreutils ``timeout`` sends its signal to the command and again to its process group: two
    signals microseconds apart are one stop (frames kept, exit 130), not "again: exiting at once"
    (which wrote nothing; found by a new user)."""
    out = tmp_path / "out.npz"
    pr = Proc([sys.executable, "-m", "dynmesh_warp.convert", str(varying_npz), str(out), "--strategy",
               "regularized", "--device", "cpu"], tmp_path)
    pr.wait_for(b"frame/s")
    pr.p.send_signal(signal.SIGINT)
    time.sleep(0.05)  # handled apart (two bytes for the watcher), well within the same stop
    pr.p.send_signal(signal.SIGINT)
    rc, _, err = pr.finish()
    assert rc == 130 and "again" not in err and "Traceback" not in err, err[-2000:]
    assert _last_line(err).startswith(f"interrupted by SIGINT: wrote {out} with input frames ")
    assert json.loads(str(np.load(out)["status"]))["complete"] is False
    capsys.readouterr()


def test_convert_stopped_after_the_last_frame_is_not_complete(tmp_path, varying_npz, monkeypatch, capsys):
    """A stop during the passes after every frame was converted (key-frame trials, segments, the
    floater retry) is reported: the output is the run so far, marked interrupted, exit 130; it
    was written as complete with exit 0 (found by a new user)."""
    import dynmesh_warp.convert as conv
    from dynmesh_warp import cli

    real = conv.to_piecewise_fixed

    def stopped_after(seq, **kw):
        res = real(seq, **kw)
        cli._first(signal.SIGINT)  # as if Ctrl-C came once every frame was done
        return res

    monkeypatch.setattr(conv, "to_piecewise_fixed", stopped_after)
    out = tmp_path / "out.npz"
    rc = conv.main([str(varying_npz), str(out), "--strategy", "tracking", "--device", "cpu", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 130
    line = _last_line(err)
    assert line.startswith(f"interrupted by SIGINT: wrote {out} with input frames 0..119 of 0..119"), line
    assert "every frame was converted, but the later passes" in line
    status = json.loads(str(np.load(out)["status"]))
    assert status["complete"] is False and status["interrupted_by"] == "SIGINT" and status["frames"] == 120


# --------------------------------------------------------------------------- convert --resume


def _frames(res) -> list:
    """A conversion result's frames (V, F), one template or several."""
    return [(res.V[t], res.F) for t in range(res.num_frames)] if hasattr(res, "V") else list(res.frames)


def _same_frames(a, b) -> bool:
    fa, fb = _frames(a), _frames(b)
    return len(fa) == len(fb) and all(np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1]) for x, y in zip(fa, fb))


@pytest.fixture(scope="module")
def segmented():
    """A torus closing into a sphere (its conversion: two template segments) and its uninterrupted
    conversion (graph, the default)."""
    from dynmesh_warp.convert import to_piecewise_fixed
    from dynmesh_warp.scenes import torus_to_sphere

    seq = torus_to_sphere(frames=24, resolution=24)
    return seq, to_piecewise_fixed(seq, device="cpu")


@pytest.mark.parametrize("stop_at", [4, 30])
def test_resumed_conversion_equals_the_uninterrupted_one(tmp_path, segmented, stop_at):
    """Stopped in its first run or in a later one (the second segment's), a conversion resumed
    from its journal is the uninterrupted conversion bit for bit (CPU): the frames, the per-frame
    figures, the segments; only the frames the journal lacks are fitted."""
    from dynmesh_warp.convert import to_piecewise_fixed
    from dynmesh_warp.convert_journal import ConversionJournal

    seq, full = segmented
    assert len(full.conversion.segments) == 2  # the case covers a later run (the second template's)
    calls = []
    j = ConversionJournal(tmp_path / "j", {"input": "torus"})
    part = to_piecewise_fixed(seq, device="cpu", journal=j, should_stop=lambda: calls.append(1) or len(calls) > stop_at)
    assert j.written == j.frames() > 0
    assert len(_frames(part)) < 24
    again = ConversionJournal(tmp_path / "j", {"input": "torus"}, resume=True)
    res = to_piecewise_fixed(seq, device="cpu", journal=again)
    assert again.replayed == j.written and again.written > 0  # every frame fit kept is used, the rest fitted
    assert _same_frames(res, full)
    c, f = res.conversion, full.conversion
    assert (c.coverage, c.web, c.flipped, c.input_motion, c.segments) == (f.coverage, f.web, f.flipped, f.input_motion,
                                                                        f.segments)


@pytest.mark.parametrize("strategy", ["regularized", "tracking"])
def test_resume_other_strategies(tmp_path, strategy):
    from dynmesh_warp.convert import to_fixed_topology
    from dynmesh_warp.convert_journal import ConversionJournal
    from dynmesh_warp.scenes import torus_to_sphere

    seq = torus_to_sphere(frames=16, resolution=20)
    full = to_fixed_topology(seq, strategy=strategy, device="cpu", key_frame=8)
    calls = []
    j = ConversionJournal(tmp_path / "j", {})
    to_fixed_topology(seq, strategy=strategy, device="cpu", key_frame=8, journal=j,
                      should_stop=lambda: calls.append(1) or len(calls) > 10)  # forward to 15, back to 6
    res = to_fixed_topology(seq, strategy=strategy, device="cpu", key_frame=8,
                            journal=ConversionJournal(tmp_path / "j", {}, resume=True))
    assert np.array_equal(res.V, full.V) and res.conversion.coverage == full.conversion.coverage
    assert res.conversion.recovered_frames == full.conversion.recovered_frames


def test_resume_refits_from_a_changed_input_frame(tmp_path):
    """A record is used only for the same input frame: an input mended after the stop (frame 9
    moved) is fitted again from that frame on; the result is the conversion of the mended input."""
    from dynmesh_warp.convert import to_fixed_topology
    from dynmesh_warp.convert_journal import ConversionJournal
    from dynmesh_warp.scenes import torus_to_sphere
    from dynmesh_warp.sequence import VaryingTopologySequence

    seq = torus_to_sphere(frames=16, resolution=20)
    j = ConversionJournal(tmp_path / "j", {})
    to_fixed_topology(seq, strategy="tracking", device="cpu", key_frame=0, journal=j)
    assert j.frames() == 16
    frames = [(v.copy(), f) for v, f in seq.frames]
    frames[9] = (frames[9][0] + np.float32(0.01), frames[9][1])
    mended = VaryingTopologySequence(frames, fps=seq.fps, name=seq.name)
    again = ConversionJournal(tmp_path / "j", {}, resume=True)
    res = to_fixed_topology(mended, strategy="tracking", device="cpu", key_frame=0, journal=again)
    assert again.replayed == 9 and again.written == 7  # frames 0-8 kept, 9-15 fitted again
    assert np.array_equal(res.V, to_fixed_topology(mended, strategy="tracking", device="cpu", key_frame=0).V)


def test_a_journal_that_cannot_be_written_does_not_stop_the_conversion(tmp_path, monkeypatch):
    """A full disk while the journal writes: one warning, the conversion goes on and is the same."""
    import errno

    import dynmesh_warp.convert_journal as cj
    from dynmesh_warp.convert import to_fixed_topology
    from dynmesh_warp.scenes import torus_to_sphere

    seq = torus_to_sphere(frames=8, resolution=20)
    full = to_fixed_topology(seq, strategy="tracking", device="cpu", key_frame=0)
    real, n = np.savez, []

    def savez(f, **arrays):
        n.append(1)
        if len(n) > 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(f, **arrays)

    monkeypatch.setattr(cj.np, "savez", savez)
    j = cj.ConversionJournal(tmp_path / "j", {})
    with pytest.warns(UserWarning, match=r"conversion journal: could not write .*run_0000_000003\.npz: \[Errno 28\] No space"):
        res = to_fixed_topology(seq, strategy="tracking", device="cpu", key_frame=0, journal=j)
    assert np.array_equal(res.V, full.V) and j.frames() == 3
    assert not list((tmp_path / "j").glob("*.tmp*"))  # no half-written record left


def test_convert_resume_command_line(tmp_path, varying_npz, capsys):
    """``convert`` stopped by SIGINT keeps its journal beside the output and says how to go on; the
    same command refuses to start over it; ``--resume`` with other options is refused naming the
    option; ``--resume`` replaces the stopped run's partial output with the whole conversion, equal
    byte for byte to an uninterrupted run's, and removes the journal."""
    from dynmesh_warp.convert import main
    from dynmesh_warp.convert_journal import journal_path

    out = tmp_path / "out.npz"
    args = [str(varying_npz), str(out), "--strategy", "regularized", "--device", "cpu"]
    pr = Proc([sys.executable, "-m", "dynmesh_warp.convert", *args], tmp_path)
    pr.wait_for(b"frame/s")
    pr.p.send_signal(signal.SIGINT)
    rc, _, err = pr.finish()
    journal = journal_path(out)
    assert rc == 130 and journal.is_dir(), err[-2000:]
    n = len(list(journal.glob("run_*_*.npz")))
    line = _last_line(err)
    assert line.endswith(f"the same command with --resume goes on from the {n} frame fits done ({journal})"), line
    stopped = out.read_bytes()
    capsys.readouterr()
    assert main(args + ["--no-progress"]) == 2
    assert f"an interrupted conversion of it left {n} frame fits in {journal}; give --resume" in capsys.readouterr().err
    assert main(args + ["--no-progress", "--resume", "--option", "iterations=2"]) == 2
    assert "the interrupted conversion had options {}, this command {'iterations': 2}" in capsys.readouterr().err
    assert out.read_bytes() == stopped and len(list(journal.glob("run_*_*.npz"))) == n  # refusals touch nothing
    assert main(args + ["--no-progress", "--resume"]) == 0
    assert not journal.exists()
    ref = tmp_path / "ref.npz"
    assert main([str(varying_npz), str(ref)] + args[2:] + ["--no-progress"]) == 0
    assert out.read_bytes() == ref.read_bytes()
    assert main(args + ["--no-progress", "--resume"]) == 2  # nothing left to go on with
    assert f"no interrupted conversion of {out} to go on with" in capsys.readouterr().err


def test_a_journal_without_fits_is_started_over(tmp_path):
    """Killed before its first fit was written, a conversion leaves a journal with nothing to go
    on from: the same command starts over (no --resume asked for) and removes it at the end."""
    from dynmesh_warp.convert import main
    from dynmesh_warp.convert_journal import ConversionJournal, journal_path
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.scenes import torus_to_sphere

    src = tmp_path / "in.npz"
    save_sequence(torus_to_sphere(frames=4, resolution=16), src)
    out = tmp_path / "out.npz"
    ConversionJournal(journal_path(out), {}).run({"a": 1})  # journal.json and a run, no fit
    assert journal_path(out).is_dir()
    assert main([str(src), str(out), "--strategy", "tracking", "--device", "cpu", "--no-progress"]) == 0
    assert out.is_file() and not journal_path(out).exists()


def test_convert_leaves_a_foreign_journal_name_alone(tmp_path, varying_npz, capsys):
    from dynmesh_warp.convert import main

    out = tmp_path / "frames"
    mine = tmp_path / "frames.convert-journal"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    for extra in ([], ["--resume"]):
        assert main([str(varying_npz), str(out), "--device", "cpu", "--no-progress", *extra]) == 2
        assert "not a conversion journal (no journal.json); it was not written by convert" in capsys.readouterr().err
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"] and not out.exists()


@pytest.fixture(scope="module")
def small_gt(tmp_path_factory) -> Path:
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.scenes import pulsing_blob

    p = tmp_path_factory.mktemp("gt") / "blob.npz"
    save_sequence(pulsing_blob(subdivisions=2, frames=80), p)
    return p


def test_evaluate_interrupted_writes_the_frames_done(tmp_path, small_gt):
    """... beside an earlier output of --out, which an interrupted run under --overwrite does not
    replace (a new user's complete results.json became a partial one): ``<out>.partial``."""
    from dynmesh_warp.outputs import OutputFolder

    earlier = tmp_path / "e"
    with OutputFolder(earlier) as tmp:
        (tmp / "results.json").write_text('{"complete": true}')
    out = tmp_path / "e.partial"
    pr = Proc([sys.executable, "-m", "dynmesh_warp.evaluate", str(small_gt), "--strategies", "projection",
               "--no-emd", "--protocol", "paper", "--resolution", "32", "--device", "cpu", "--out", str(earlier),
               "--overwrite"], tmp_path)
    pr.wait_for(b"metrics")  # 160 (row, frame) pairs at ~75/s here: the signal comes in the middle
    time.sleep(0.2)
    pr.p.send_signal(signal.SIGINT)
    rc, _, err = pr.finish()
    assert rc == 130 and "Traceback" not in err, err[-2000:]
    assert _last_line(err).startswith(f"interrupted by SIGINT: wrote {out} ")
    assert _last_line(err).endswith(f"{earlier} holds an earlier output or files another run wrote meanwhile: "
                                    "kept as it is")
    assert (earlier / "results.json").read_text() == '{"complete": true}'
    doc = json.loads((out / "results.json").read_text())
    info = doc["interrupted"]
    assert info["signal"] == "SIGINT" and info["partial_scene"] == "pulsing_blob" and info["not_evaluated"] == []
    rows = doc["scenes"][0]["rows"]
    done = {k: r["paper"]["frames"] for k, r in rows.items()}
    n = min(len(f) for f in done.values())
    assert 1 <= n < 80 and all(f == list(range(len(f))) for f in done.values())  # every row: frames 0..k-1
    assert max(len(f) for f in done.values()) - n <= 1  # frame by frame across the rows
    assert len(rows["projection"]["paper"]["cd"]) == len(done["projection"])
    assert "INTERRUPTED by SIGINT" in (out / "table_paper.md").read_text()


def test_evaluate_signal_while_remeshing_writes_nothing(tmp_path, small_gt):
    """A stage without frame boundaries (re-meshing) stops at once; with nothing evaluated yet
    no output folder appears."""
    out = tmp_path / "e"
    pr = Proc([sys.executable, "-m", "dynmesh_warp.evaluate", str(small_gt), "--strategies", "projection",
               "--no-emd", "--resolution", "32", "--device", "cpu", "--out", str(out)], tmp_path)
    pr.wait_for(b"remesh")
    pr.p.send_signal(signal.SIGTERM)
    rc, _, err = pr.finish()
    assert rc == 143 and "Traceback" not in err
    assert _last_line(err) == "interrupted (SIGTERM) before any output was written; existing outputs are unchanged"
    assert not out.exists() and _leftovers(tmp_path) == []


def test_second_sigint_exits_at_once_during_a_long_native_call(tmp_path, small_gt):
    """EMD of one frame pair takes ~1.5 min on the CPU (one native call): the first Ctrl-C waits
    for it (and says so after a second), the second exits at once, leaving no temporaries."""
    out = tmp_path / "e"
    (tmp_path / "blob.npz").write_bytes(small_gt.read_bytes())
    pr = Proc([sys.executable, "-m", "dynmesh_warp.evaluate", "blob.npz", "--strategies", "projection",
               "--protocol", "dgmesh", "--num-frames", "2", "--device", "cpu", "--out", str(out)], tmp_path)
    pr.wait_for(b"metrics")
    time.sleep(0.3)
    pr.p.send_signal(signal.SIGINT)
    pr.wait_for(b"send it again to exit at once", timeout=10)
    t0 = time.monotonic()
    pr.p.send_signal(signal.SIGINT)
    rc, _, err = pr.finish(timeout=10)
    assert time.monotonic() - t0 < 3.0
    assert rc == 130 and "Traceback" not in err
    assert _last_line(err).startswith("SIGINT again: exiting at once")
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["blob.npz"]


# --------------------------------------------------------------------------- viewer, quiet start


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_viewer_server_shuts_down_cleanly(tmp_path, sig):
    pytest.importorskip("viser")
    pr = Proc(RUN[:3] + ["--viewer", "viser", "--port", "0", "--device", "cpu"], tmp_path)
    pr.wait_for(b"viewer: http://", where="out")
    time.sleep(0.3)
    pr.p.send_signal(sig)
    rc, out, err = pr.finish(timeout=30)
    assert rc == CODE[sig] and "Traceback" not in err + out, err
    assert "Server stopped" in out
    assert _last_line(err).startswith(f"interrupted by {signal.Signals(sig).name} after ")


def test_recording_interrupted_keeps_the_frames_so_far(tmp_path):
    """--viewer none --record: SIGTERM ends the frame loop, the recording of the frames so far is
    written whole and the (headless) server stopped; exit 143, one line naming the frames. An
    earlier recording under --overwrite is kept: the stopped one goes beside it (a new user's
    complete recording was replaced by the stopped one)."""
    pytest.importorskip("viser")
    (tmp_path / "r.viser").write_bytes(b"an earlier recording")
    (tmp_path / "r.html").write_text("its page")
    pr = Proc(RUN[:3] + ["--viewer", "none", "--device", "cpu", "--record", "r.viser", "--steps", "1000000",
                         "--overwrite"], tmp_path)
    pr.wait_for(b"recording ", where="out")  # the size estimate (stdout), printed just before the frame loop
    time.sleep(8.0)  # time for some frames (3 s after the stderr note before it stopped it before the first
    # frame twice, under two workers on two busy cores: the set-up in between took up to ~16 s there)
    pr.p.send_signal(signal.SIGTERM)
    rc, out, err = pr.finish(timeout=60)
    assert rc == 143 and "Traceback" not in err + out, err[-2000:]
    line = _last_line(err)
    assert line.startswith("interrupted by SIGTERM after ") and "wrote the recording r.partial.viser" in line, line
    assert line.endswith("r.viser, which was there before, is unchanged"), line
    frames = int(line.split(" after ")[1].split(" frames")[0].replace(",", ""))
    assert frames >= 1
    assert (tmp_path / "r.viser").read_bytes() == b"an earlier recording" and (tmp_path / "r.html").read_text() == "its page"
    assert (tmp_path / "r.partial.viser").stat().st_size > 0 and (tmp_path / "r.partial.html").is_file()
    assert _leftovers(tmp_path) == []


def test_cpu_run_prints_no_cuda_driver_note_unless_cuda_is_asked(tmp_path):
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("needs a machine without a CUDA device")
    plain = subprocess.run([sys.executable, "-c", "import warp; warp.config.quiet = True; warp.init()"],
                           capture_output=True, text=True, timeout=120)
    note = "Could not find or load the NVIDIA CUDA driver"
    r = subprocess.run(RUN + ["--steps", "3", "--no-progress", "--output", str(tmp_path / "o")], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0 and r.stderr == "", r.stderr
    r = subprocess.run(RUN[:3] + ["--viewer", "none", "--device", "cuda", "--steps", "3"], capture_output=True,
                       text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2 and "error: --device 'cuda'" in r.stderr
    # Warp's own note comes only where CUDA was asked for (and only if Warp prints one here)
    assert (note in r.stderr) == (note in plain.stderr)


def test_out_of_memory_is_one_line_not_a_traceback(capsys):
    """A new user's evaluate --resolution 1200 ended in a MemoryError traceback; every CLI's
    main (interruptible_main) turns it into one error line, exit 1."""
    from dynmesh_warp.cli import interruptible_main

    @interruptible_main
    def main(argv=None):
        raise MemoryError

    assert main([]) == 1
    assert capsys.readouterr().err.startswith("error: out of memory; nothing more was written")


def _stop_seen_in_a_checking_region(cli):
    """A SIGINT sent to this process and seen by a loop that checks for stops (no exception)."""
    with cli.checking_stops():
        os.kill(os.getpid(), signal.SIGINT)
        deadline = time.monotonic() + 2.0
        while not cli.stop_requested() and time.monotonic() < deadline:
            time.sleep(0.001)
        assert cli.stop_requested()


def test_the_same_stops_second_signal_during_the_write_does_not_raise():
    """The stop's second signal (``timeout``'s, to the group) arriving after the loop saw the stop
    but before the handlers' exit — while the output is written, outside a checking region — raised
    Interrupted there: a traceback and exit 1 instead of 130 (the fresh-clone CI caught it in
    test_convert_signal_sent_twice_at_once_is_one_stop). In-process, deterministic."""
    from dynmesh_warp import cli

    with cli.handle_stop_signals():
        _stop_seen_in_a_checking_region(cli)
        os.kill(os.getpid(), signal.SIGINT)  # "writing the output": the same stop, sent again
        time.sleep(0.05)  # the handler runs here; it raised Interrupted


def test_a_late_signal_of_the_same_stop_does_not_raise_while_the_handlers_wait():
    """A stop seen in a checking region (no exception raised: the loop wrote its output) leaves
    the handlers up for the rest of the same-stop window; the stop's second signal (``timeout``'s,
    to the group) arriving then raised Interrupted out of the handlers' exit: a traceback, exit 1
    instead of 130 (the fresh suite's load caught it in test_convert_signal_sent_twice_at_once_is_one_stop).
    In-process, deterministic: the second signal is sent while the exit waits."""
    import threading

    from dynmesh_warp import cli

    with cli.handle_stop_signals():
        _stop_seen_in_a_checking_region(cli)
        # the output is written; the exit waits out the window, and the second signal comes then
        threading.Timer(0.1, os.kill, args=(os.getpid(), signal.SIGINT)).start()
    time.sleep(0.3)  # past the timer: had it raised, the with-block's exit would have


def test_ctrl_c_while_a_command_starts_up_is_one_line_and_130():
    """A Ctrl-C while ``python -m dynmesh_warp.<command>`` still imports Warp (before the command's
    handlers are in) printed a 37-line traceback from ``import warp`` (a new user). The package
    sees the ``-m`` start (runpy's ``sys.argv[0]``) and ends it with one line and exit 130; a
    plain library import is left alone (the interrupt's usual traceback)."""
    raise_it = "import dynmesh_warp; raise KeyboardInterrupt"
    cli = subprocess.run([sys.executable, "-c", "import sys; sys.argv = ['-m']; " + raise_it],
                         capture_output=True, text=True, timeout=120)
    assert cli.returncode == 130
    assert cli.stderr.strip().splitlines()[-1] == "interrupted during start-up; nothing was done"
    assert "Traceback" not in cli.stderr
    lib = subprocess.run([sys.executable, "-c", raise_it], capture_output=True, text=True, timeout=120)
    assert lib.returncode != 130 and "Traceback" in lib.stderr and "KeyboardInterrupt" in lib.stderr
