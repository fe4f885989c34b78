"""The one runner (issue 13, runner.run_simulation): it drives anything that implements
runtime.Simulation, writes the run's own fields once for every engine, checks samples for
non-finite values naming the row, and refuses checkpoints where the engine has none."""

from __future__ import annotations

import json

import numpy as np
import pytest
import warp as wp

from dynmesh_warp.checkpoint import CheckpointError
from dynmesh_warp.config import load_scene_config
from dynmesh_warp.runner import run_simulation
from dynmesh_warp.runtime import NonFiniteStateError, Simulation

#: the fields every run's summary.json has, whatever the engine
RUN_FIELDS = {"scene", "device", "device_name", "cuda_graph", "dt", "substeps", "steps", "step_reached",
              "interrupted", "interrupted_by", "resumed_from", "checkpoint", "sim_time_s", "setup_and_compile_s",
              "timed_steps", "timed_wall_s", "steps_per_second", "contacts", "surface", "final"}


class Ballistic:
    """A minimal engine: B points under gravity, integrated on the host (no Warp world)."""

    editable = False
    checkpointable = False
    body_noun = "point"
    num_envs = 1
    use_graph = False

    def __init__(self, B=3, dt=0.01, blow_up_at=None):
        self.device = wp.get_device("cpu")
        self.surface = None
        self.t0, self.dt, self.substeps, self.substep_count = 0.0, dt, 1, 0
        self.x = np.zeros((B, 3))
        self.v = np.tile([1.0, 0.0, 2.0], (B, 1))
        self.blow_up_at = blow_up_at
        self.captured = 0

    @property
    def time(self):
        return self.t0 + self.substep_count * self.dt

    def step(self):
        self.v[:, 2] -= 9.81 * self.dt
        self.x += self.dt * self.v
        self.substep_count += 1
        if self.blow_up_at is not None and self.substep_count >= self.blow_up_at:
            self.x[1, 0] = np.nan

    def capture(self):
        self.captured += 1

    def surface_points(self):
        return None

    def surface_indices(self):
        return None

    def sphere_positions(self):
        return np.zeros((0, 3))

    def rigid_shapes(self):
        return []

    def sphere_radii(self):
        return np.zeros(0)

    def sample(self):
        return {"x": self.x.copy()}

    def trajectory_constants(self):
        return {"mass": np.ones(len(self.x))}

    def contact_count(self):
        return int((self.x[:, 2] < 0).sum())

    def run_summary(self):
        return {"engine": "ballistic", "final": {"finite": bool(np.isfinite(self.x).all()), "x": self.x}}

    def run_line(self):
        return "ballistic", f"{len(self.x)} points"


def _cfg(record_every=1):
    return load_scene_config(data={"name": "b", "device": "cpu", "run": {"record_every": record_every}})


def test_runner_drives_any_simulation(tmp_path):
    sim = Ballistic()
    assert isinstance(sim, Simulation)
    lines = []
    s = run_simulation(sim, _cfg(5), steps=41, out=tmp_path / "o", t_build=0.0, progress=False, log=lines.append)
    assert sim.captured == 1  # once, after the eager warm-up step
    assert RUN_FIELDS <= set(s) and s["engine"] == "ballistic" and s["step_reached"] == 41
    tr = np.load(tmp_path / "o" / "trajectories.npz")
    # samples at steps 0 (the initial state), 5, ..., 40 and the last, 41: the closed form of a
    # ballistic point at those times (the samples were 1, 6, ..., 41, with no initial state)
    steps_sampled = np.r_[np.arange(0, 41, 5), 41]
    t = tr["time"]
    np.testing.assert_allclose(t, 0.01 * steps_sampled)
    assert tr["x"].shape == (10, 3, 3) and tr["mass"].shape == (3,)
    k = steps_sampled[:, None]  # semi-implicit Euler: z_k = dt (v0 k - g dt k (k + 1) / 2)
    z = 0.01 * (2.0 * k - 9.81 * 0.01 * k * (k + 1) / 2)
    np.testing.assert_allclose(tr["x"][:, :, 2], np.repeat(z, 3, axis=1), rtol=1e-12)
    assert s["contacts"]["samples"] == 9 and s["contacts"]["contact_samples"] == 6  # below z = 0 at steps 40 and 41
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["timed_steps"] == 40
    assert lines and lines[0].startswith("b: 41 steps on cpu (ballistic)") and "3 points" in lines[0]


def test_runner_names_the_non_finite_row_and_keeps_the_old_outputs(tmp_path):
    out = tmp_path / "o"
    run_simulation(Ballistic(), _cfg(), steps=5, out=out, t_build=0.0, progress=False, log=lambda *a: None)
    before = (out / "trajectories.npz").read_bytes()
    with pytest.raises(NonFiniteStateError, match=r"point 1 has a non-finite state at step 7 .*x \[nan"):
        run_simulation(Ballistic(blow_up_at=7), _cfg(), steps=20, out=out, t_build=0.0, progress=False,
                       log=lambda *a: None)
    assert (out / "trajectories.npz").read_bytes() == before


def test_runner_refuses_checkpoints_without_engine_support(tmp_path):
    with pytest.raises(CheckpointError, match="not available"):
        run_simulation(Ballistic(), _cfg(), steps=5, out=tmp_path / "o", t_build=0.0, progress=False,
                       checkpoint_every=2)
    assert not (tmp_path / "o").exists()


def test_both_engines_write_the_same_run_fields(tmp_path, device):
    """The built-in and the Newton world go through the same runner: the same run fields, the
    same warm-up (the first sample is step 1), the engine's own fields on top."""
    pytest.importorskip("newton")
    from dynmesh_warp.run import run_scene

    data = {"name": "e", "device": device,
            "surface": {"source": "builtin:wave_bowl", "params": {"n": 8, "frames": 4}},
            "spheres": [{"position": [0.0, 0.0, 0.9], "radius": 0.06}], "run": {"steps": 30, "record_every": 10}}
    a = run_scene(load_scene_config(data=data), output=tmp_path / "a", progress=False, log=lambda *a: None)
    data["newton"] = {"solver": "xpbd", "bodies": []}
    b = run_scene(load_scene_config(data=data), output=tmp_path / "b", progress=False, log=lambda *a: None)
    assert RUN_FIELDS <= set(a) and RUN_FIELDS <= set(b)
    assert b["engine"] == "newton" and "collider" in a and "solver" in b
    ta, tb = np.load(tmp_path / "a" / "trajectories.npz"), np.load(tmp_path / "b" / "trajectories.npz")
    np.testing.assert_allclose(ta["time"], tb["time"])  # same samples: steps 1, 11, 21, 30
    assert len(ta["time"]) == 4 and ta["position"].shape == (4, 1, 3) and tb["body_q"].shape == (4, 1, 7)
    assert a["timed_steps"] == b["timed_steps"] == 29
