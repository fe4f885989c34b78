"""bench/soak.py's checks find what they look for (issue 17): the winding number and the
height-field test tell inside from outside, the surface they test is the one the world plays,
and a short soak of a built-in scene drops spheres, checks them and passes."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from reference import surface_at, winding_number as reference_winding

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def soak():
    spec = importlib.util.spec_from_file_location("soak", ROOT / "bench" / "soak.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_inside_tests_tell_inside_from_outside(soak):
    from dynmesh_warp.scenes import grid_sheet, icosphere

    V, F = icosphere(2, radius=1.0)
    P = np.array([[0, 0, 0], [0.5, 0.2, -0.3], [0, 0, 1.2], [2, 0, 0], [0.0, 0.0, 0.97]])
    wn = soak.winding_number(V, F, P, chunk=2)
    np.testing.assert_allclose(wn, reference_winding(V, F, P), atol=1e-9)
    assert (wn[:2] > 0.99).all() and (np.abs(wn[2:4]) < 0.01).all() and wn[4] > 0.5
    assert soak.boundary_edges(F) == 0
    G, H = grid_sheet(8, 2.0)
    G = G.astype(np.float64)
    G[:, 2] = 0.1 * G[:, 0] + 0.2 * G[:, 1] + 0.3  # a tilted plane
    xy = np.array([[0.3, -0.4], [-0.99, 0.99], [1.5, 0.0]])
    h = soak.sheet_height(G, H, xy)
    np.testing.assert_allclose(h[:2], 0.1 * xy[:2, 0] + 0.2 * xy[:2, 1] + 0.3, atol=1e-12)
    assert np.isnan(h[2]) and soak.boundary_edges(H) > 0


def test_surface_now_is_the_played_surface(soak):
    from dynmesh_warp.scene import build_world

    w = build_world(soak.scene_config("pulsing_blob"), device="cpu")
    for _ in range(37):
        w.step()
    V, F = soak.surface_now(w)
    np.testing.assert_allclose(V, surface_at(w.model.surface.sequence, w.time, "loop"), atol=1e-9)


def test_short_soak_passes_and_is_not_vacuous(soak):
    r = soak.soak_scene("pulsing_blob", "cpu", steps=2000, check_every=50, drop_every=100, max_spheres=8, seed=1,
                        stop_flag={}, log=lambda *_: None)
    assert r["passed"] and r["steps"] == 2000 and r["checks"] == 40 and not r["interrupted"]
    assert r["spheres_dropped"] == 19 and r["final_spheres"] == 8  # 3 added to the 5, then 16 dropped again
    assert r["spheres_that_touched_the_surface"] >= 3 and r["max_winding_number"] < 0.5


def test_soak_reports_a_centre_inside(soak, monkeypatch):
    """Negative control: checked against the surface grown 100x about its centre (every centre
    inside it), the soak counts every sphere check as tunnelled and fails."""
    played = soak.surface_now

    def grown(w):
        V, F = played(w)
        c = V.mean(axis=0)
        return c + 100.0 * (V - c), F

    monkeypatch.setattr(soak, "surface_now", grown)
    r = soak.soak_scene("pulsing_blob", "cpu", steps=300, check_every=100, drop_every=1000, max_spheres=8, seed=1,
                        stop_flag={}, log=lambda *_: None)
    assert not r["passed"] and r["tunnelled"] == r["sphere_checks"] == 15 and r["max_winding_number"] > 0.99
    assert r["events"][0]["kind"] == "inside" and r["events"][0]["step"] == 100


def test_sheet_rim_distance(soak):
    from dynmesh_warp.scenes import grid_sheet

    G, H = grid_sheet(5, 2.0)
    rim = soak.boundary_edge_list(H)
    assert len(rim) == 16
    d = soak.distance_to_boundary_xy(G.astype(np.float64), rim, np.array([[0.0, 0.0], [0.96, 0.2], [-0.9, -0.95]]))
    np.testing.assert_allclose(d, [1.0, 0.04, 0.05], atol=1e-12)


class _StopAfter(dict):
    """A stop flag that turns on after ``n`` looks (the soak looks once per loop turn)."""

    def __init__(self, n):
        super().__init__()
        self.n = n

    def get(self, key, default=None):
        self.n -= 1
        return "SIGTERM" if self.n < 0 else default


@pytest.mark.parametrize("recycle, collider", [("oldest", "swept"), ("lowest", "refit")])
def test_soak_stopped_and_resumed_equals_one_run(soak, tmp_path, recycle, collider):
    """A soak stopped early writes a checkpoint; resumed in a new call it ends with the same
    tallies as the run that was never stopped (CPU: bit-identical steps, the same drops). The
    resumed call, not told the collider, keeps the checkpoint's: the automatic choice is measured
    and can differ between calls (a resume once met a checkpoint of the other collider, KeyError)."""
    kw = dict(steps=1500, check_every=50, drop_every=40, max_spheres=8, seed=3, log=lambda *_: None,
              recycle=recycle)
    whole = soak.soak_scene("pulsing_blob", "cpu", stop_flag={}, collider=collider, **kw)
    ck = tmp_path / "ck.npz"
    first = soak.soak_scene("pulsing_blob", "cpu", stop_flag=_StopAfter(17), checkpoint=ck, collider=collider, **kw)
    assert first["interrupted"] and 1 < first["steps"] < 1500 and ck.is_file()
    rest = soak.soak_scene("pulsing_blob", "cpu", stop_flag={}, resume=ck, **kw)
    assert whole["collider"] == first["collider"] == rest["collider"] == collider
    assert rest["steps"] == 1500 and not rest["interrupted"] and len(rest["segments"]) == 2
    assert rest["segments"][0]["to_step"] == rest["segments"][1]["from_step"] == first["steps"]
    for k in ("checks", "sphere_checks", "sphere_checks_in_contact", "spheres_dropped", "max_winding_number",
              "max_contact_depth_m", "spheres_that_touched_the_surface", "tunnelled", "non_finite", "final_spheres"):
        assert rest[k] == whole[k], k
    assert whole["spheres_that_touched_the_surface"] > 0 and whole["sphere_checks_in_contact"] > 0
    with pytest.raises(SystemExit, match="written for scene"):
        soak.soak_scene("pulsing_blob", "cpu", stop_flag={}, resume=ck, **{**kw, "seed": 4})


def test_checkpoint_never_replaces_a_file_it_did_not_write(soak, tmp_path, capsys):
    """--checkpoint pointed at a user's file (here a scene YAML) is refused before any work, and
    the file is left byte-identical; a missing --resume file is refused too."""
    user = tmp_path / "scene.yaml"
    user.write_bytes(b"name: mine\n")
    with pytest.raises(SystemExit) as e:
        soak.main(["--scenes", "pulsing_blob", "--steps", "10", "--checkpoint", str(user),
                   "--out", str(tmp_path / "o.json")])
    assert e.value.code == 2 and "is not a soak checkpoint" in capsys.readouterr().err
    assert user.read_bytes() == b"name: mine\n" and not (tmp_path / "o.json").exists()
    with pytest.raises(SystemExit) as e:
        soak.main(["--scenes", "pulsing_blob", "--resume", str(tmp_path / "none.npz")])
    assert e.value.code == 2 and "no such file" in capsys.readouterr().err


def test_every_soak_scene_builds(soak):
    """Each scene the soak plays builds a world (torus_to_sphere asked for rebuild_every 'frame'
    with interpolation on, which the rebuild collider refuses: the whole soak stopped there)."""
    from dynmesh_warp.scene import build_world

    for name in soak.BUILTIN:
        w = build_world(soak.scene_config(name), device="cpu")
        w.step()
        assert np.isfinite(w.sphere_positions()).all(), name
