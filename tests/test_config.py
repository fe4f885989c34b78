"""Scene YAML validation (load_scene_config) and the headless CLI (dynmesh_warp.run.main).

Every bad input must give a SceneError whose message names the offending key path or file;
the CLI must turn it into exit code 2 with the message on stderr.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from reference import grid_height, surface_at

from dynmesh_warp.config import SceneConfig, SceneError, load_scene_config
from dynmesh_warp.run import main


def write_yaml(folder: Path, data, name="scene.yaml") -> Path:
    p = folder / name
    p.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return p


def test_default_scene_validates():
    cfg = load_scene_config()
    assert isinstance(cfg, SceneConfig)
    assert cfg.name == "default"
    assert cfg.surface.source == "builtin:wave_bowl"
    assert cfg.physics.dt > 0


def test_minimal_file_gets_defaults_and_its_name(tmp_path):
    cfg = load_scene_config(write_yaml(tmp_path, {"physics": {"dt": 0.002}}, "my_scene.yaml"))
    assert cfg.name == "my_scene"
    assert cfg.physics.dt == 0.002
    assert cfg.physics.restitution == SceneConfig().physics.restitution


def test_empty_file_is_the_defaults(tmp_path):
    """... and says so (a new user's empty file ran the built-in scene silently); a splats file
    that is not a .ply is refused with the scene (run took an npz, render refused it later)."""
    with pytest.warns(UserWarning, match="empty.yaml: the scene file is empty: the built-in default scene"):
        cfg = load_scene_config(write_yaml(tmp_path, "", "empty.yaml"))
    assert cfg.surface.source == "builtin:wave_bowl"
    (tmp_path / "g.npz").write_bytes(b"x")
    with pytest.raises(SceneError, match=r"gaussians.splats: a 3D Gaussian splatting .ply is expected, got 'g.npz'"):
        load_scene_config(write_yaml(tmp_path, {"gaussians": {"splats": "g.npz"}}, "s.yaml"))


@pytest.mark.parametrize("data, must_contain", [
    ({"physics": {"dtt": 0.01}}, ["physics.dtt: unknown key"]),
    ({"physiks": {"dt": 0.01}}, ["physiks: unknown key"]),
    ({"surface": {"source": "builtin:wave_bowl", "fpss": 3}}, ["surface.fpss: unknown key"]),
    ({"physics": {"dt": "fast"}}, ["physics.dt", "number"]),
    ({"physics": {"dt": -0.01}}, ["physics.dt", "greater than 0"]),
    ({"physics": {"dt": 0}}, ["physics.dt", "greater than 0"]),
    ({"physics": {"restitution": 1.5}}, ["physics.restitution"]),
    ({"physics": {"substeps": 0}}, ["physics.substeps"]),
    ({"physics": {"collider": "octree"}}, ["physics.collider"]),
    ({"physics": {"gravity": [0, -9.8]}}, ["physics.gravity"]),
    ({"surface": {"playback": "bounce"}}, ["surface.playback"]),
    ({"run": {"steps": 0}}, ["run.steps"]),
    ({"name": "a/b"}, ["name"]),
    ({"name": ".."}, ["name", "not '.' or '..'"]),  # run.output "out/{name}" would be the folder above
    ({"name": "."}, ["name"]),
    ({"name": "a\tb"}, ["name", "control characters"]),
    ({"gaussians": {"splats": "."}}, ["gaussians.splats", "a folder, not a file"]),
    ({"gaussians": {"splats": "none.ply"}}, ["gaussians.splats", "file not found"]),
])
def test_bad_values_name_the_key_path(tmp_path, data, must_contain):
    path = write_yaml(tmp_path, data)
    with pytest.raises(SceneError) as ei:
        load_scene_config(path)
    msg = str(ei.value)
    assert str(path) in msg  # names the file
    for s in must_contain:
        assert s in msg, f"{s!r} not in message:\n{msg}"


def test_bad_sphere_in_list_names_the_field(tmp_path):
    path = write_yaml(tmp_path, {"spheres": [{"position": [0, 0, 1]}, {"position": [0, 0, 1], "radius": -1}]})
    with pytest.raises(SceneError) as ei:
        load_scene_config(path)
    assert "spheres" in str(ei.value) and "radius" in str(ei.value)


def test_missing_surface_file_names_the_path(tmp_path):
    path = write_yaml(tmp_path, {"surface": {"source": "data/missing_sequence.npz"}})
    with pytest.raises(SceneError) as ei:
        load_scene_config(path)
    msg = str(ei.value)
    assert "surface.source" in msg
    assert str(tmp_path / "data" / "missing_sequence.npz") in msg  # resolved against the YAML folder
    assert msg.startswith(f"{path}: surface.source: file or folder not found")  # not "(top level): surface.source"
    # an empty source resolved to the scene's own folder, which exists
    with pytest.raises(SceneError, match=r"surface\.source: String should have at least 1 character"):
        load_scene_config(write_yaml(tmp_path, {"surface": {"source": ""}}))


def test_missing_scene_file(tmp_path):
    with pytest.raises(SceneError, match="not found") as ei:
        load_scene_config(tmp_path / "nope.yaml")
    assert "nope.yaml" in str(ei.value)


@pytest.mark.parametrize("text", ["physics: {dt: 0.01\n", "physics:\n  dt: 0.1\n dt2: [\n", "a: b: c\n"])
def test_yaml_syntax_error(tmp_path, text):
    path = write_yaml(tmp_path, text, "broken.yaml")
    with pytest.raises(SceneError) as ei:
        load_scene_config(path)
    assert "broken.yaml" in str(ei.value)
    assert "YAML" in str(ei.value)


def test_top_level_must_be_a_mapping(tmp_path):
    with pytest.raises(SceneError, match="mapping"):
        load_scene_config(write_yaml(tmp_path, "- 1\n- 2\n", "list.yaml"))


def test_relative_paths_resolve_against_the_yaml_folder(tmp_path, monkeypatch):
    from dynmesh_warp import scenes
    from dynmesh_warp.io import load_sequence

    data = tmp_path / "scene_dir" / "data"
    data.mkdir(parents=True)
    seq = scenes.pulsing_blob(subdivisions=1, frames=3)
    np.savez(data / "blob.npz", V=seq.V, F=seq.F, fps=np.float32(seq.fps), name="blob")
    path = write_yaml(tmp_path / "scene_dir", {"surface": {"source": "data/blob.npz"}})
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # the working directory must not matter
    cfg = load_scene_config(path)
    assert cfg.resolve(cfg.surface.source) == (data / "blob.npz").resolve()
    assert cfg.resolve(cfg.run.output.format(name=cfg.name)).parent.resolve() == (tmp_path / "scene_dir" / "out").resolve()
    loaded = load_sequence(cfg.resolve(cfg.surface.source))
    np.testing.assert_array_equal(loaded.V, seq.V)
    # the same relative path from the wrong folder is reported missing
    with pytest.raises(SceneError, match="blob.npz"):
        load_scene_config(write_yaml(elsewhere, {"surface": {"source": "data/blob.npz"}}))


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------

TINY_SCENE = {
    "name": "tiny",
    "surface": {"source": "builtin:wave_bowl", "params": {"n": 24, "frames": 12}},
    "spheres": [{"position": [0.1, 0.0, 0.9], "radius": 0.08},
                {"position": [-0.3, 0.2, 1.1], "radius": 0.06, "velocity": [0.5, 0.0, 0.0]}],
    "physics": {"dt": 1.0 / 240.0},
}


def test_cli_runs_tiny_scene_and_writes_outputs(tmp_path, capsys):
    from dynmesh_warp import scenes

    scene = write_yaml(tmp_path, TINY_SCENE, "tiny.yaml")
    out = tmp_path / "out"
    steps = 200
    rc = main([str(scene), "--steps", str(steps), "--device", "cpu", "--no-progress", "--output", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    summary = json.loads((out / "summary.json").read_text())
    traj = np.load(out / "trajectories.npz")
    assert summary["steps"] == steps
    assert summary["steps_per_second"] > 0
    assert summary["spheres"] == 2
    assert summary["final"]["finite"] is True
    pos = np.asarray(summary["final"]["position"], float)
    assert pos.shape == (2, 3) and np.isfinite(pos).all()
    assert summary["final"]["max_penetration"] < 0.02
    assert summary["sim_time_s"] == pytest.approx(steps / 240.0)
    # trajectories: time increases; the record starts at the initial state (t = 0) and ends at
    # the final state
    t, P = traj["time"], traj["position"]
    assert P.shape == (len(t), 2, 3) and np.all(np.diff(t) > 0) and t[0] == 0.0
    np.testing.assert_allclose(traj["radius"], [0.08, 0.06])
    np.testing.assert_allclose(P[-1], pos, atol=1e-6)
    # the record is a trajectory, not the final state repeated: sphere 0 starts near where it was put
    np.testing.assert_allclose(P[0, 0], TINY_SCENE["spheres"][0]["position"], atol=1e-6)
    assert P[0, 0, 2] - P[-1, 0, 2] > 0.1  # it fell onto the bowl
    # both spheres end above the surface (independent check: NumPy height field at that time)
    seq = scenes.wave_bowl(n=24, frames=12)
    h = grid_height(surface_at(seq, summary["sim_time_s"]), 24, 2.0, pos[:, :2].astype(np.float64))
    assert np.isfinite(h).all()
    assert (pos[:, 2] - h > 0.5 * traj["radius"]).all()


def test_cli_bad_scene_exit_code_2(tmp_path, capsys):
    scene = write_yaml(tmp_path, {"physics": {"dtt": 0.01}}, "bad.yaml")
    rc = main([str(scene), "--steps", "5", "--device", "cpu", "--no-progress", "--output", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "physics.dtt: unknown key" in err
    assert not (tmp_path / "o" / "summary.json").exists()


def test_cli_missing_scene_and_bad_builtin_params(tmp_path, capsys):
    rc = main([str(tmp_path / "absent.yaml"), "--steps", "5", "--device", "cpu", "--no-progress"])
    assert rc == 2
    assert "absent.yaml" in capsys.readouterr().err
    scene = write_yaml(tmp_path, {"surface": {"source": "builtin:wave_bowl", "params": {"wobble": 3}}}, "p.yaml")
    rc = main([str(scene), "--steps", "5", "--device", "cpu", "--no-progress", "--output", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "wave_bowl" in err and "wobble" in err
    scene = write_yaml(tmp_path, {"surface": {"source": "builtin:no_such_scene"}}, "q.yaml")
    rc = main([str(scene), "--steps", "5", "--device", "cpu", "--no-progress", "--output", str(tmp_path / "o")])
    assert rc == 2
    assert "no_such_scene" in capsys.readouterr().err


def test_set_overrides_apply_before_validation(tmp_path, capsys):
    from dynmesh_warp.config import apply_overrides

    cfg = load_scene_config(overrides=["physics.dt=0.002", "spheres.count=3", "surface.playback=pingpong",
                                       "physics.gravity=[0, 0, -3]", "physics.ground=null", "newton.solver=vbd"])
    assert cfg.physics.dt == 0.002 and cfg.spheres.count == 3 and cfg.surface.playback == "pingpong"
    assert cfg.physics.gravity == (0.0, 0.0, -3.0) and cfg.physics.ground is None and cfg.newton.solver == "vbd"
    assert cfg.spheres.radius == 0.08  # the rest of the default scene is kept
    raw = {"physics": {"dt": 0.01}}
    assert apply_overrides(raw, ["physics.substeps=2"]) == {"physics": {"dt": 0.01, "substeps": 2}}
    assert raw == {"physics": {"dt": 0.01}}  # the caller's mapping is untouched
    for bad, msg in [("physics.dtt=1", r"physics\.dtt: unknown key"),
                     ("physics.dt=-1", r"physics\.dt: Input should be greater than 0"),
                     ("surface.source.x=1", r"surface\.source is a str, not a section"),
                     ("physics.dt", r"expected KEY\.PATH=VALUE"), ("physics.dt=[1", r"not valid YAML"),
                     # a list item (read as "newton: unknown key" before)
                     ("newton.bodies[0].type=cone", r"'bodies\[0\]' addresses a list item, which --set cannot set")]:
        with pytest.raises(SceneError, match=msg):
            load_scene_config(overrides=[bad])
    out = tmp_path / "o"
    assert main(["--viewer", "none", "--no-progress", "--steps", "20", "--output", str(out),
                 "--set", "spheres.count=2", "--set", "physics.dt=0.002"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert len(s["final"]["position"]) == 2 and s["steps"] == 20
    assert main(["--viewer", "none", "--steps", "5", "--output", str(tmp_path / "p"), "--set", "physics.dt=0"]) == 2
    assert "physics.dt" in capsys.readouterr().err and not (tmp_path / "p").exists()


def test_scene_swept_search_reaches_the_world_and_the_batch(tmp_path, capsys):
    """physics.swept_search is the search the run uses (single world and --envs); a batch-only
    search in a single world is refused naming the field, exit 2, before any step."""
    data = {**TINY_SCENE, "physics": {**TINY_SCENE.get("physics", {}), "collider": "swept", "swept_search": "faces"}}
    scene = write_yaml(tmp_path, data, "faces.yaml")
    rc = main([str(scene), "--steps", "20", "--device", "cpu", "--no-progress", "--output", str(tmp_path / "f")])
    assert rc == 0, capsys.readouterr().err
    assert json.loads((tmp_path / "f" / "summary.json").read_text())["swept_search"] == "faces"
    data["physics"]["swept_search"] = "hybrid"
    scene = write_yaml(tmp_path, data, "hybrid.yaml")
    rc = main([str(scene), "--steps", "20", "--device", "cpu", "--no-progress", "--envs", "2",
               "--output", str(tmp_path / "h")])
    assert rc == 0, capsys.readouterr().err
    assert json.loads((tmp_path / "h" / "summary.json").read_text())["swept_search"] == "hybrid"
    rc = main([str(scene), "--steps", "20", "--device", "cpu", "--no-progress", "--output", str(tmp_path / "s")])
    assert rc == 2
    assert "swept_search" in capsys.readouterr().err
    assert not (tmp_path / "s" / "summary.json").exists()


def test_a_scene_file_that_is_not_a_mapping_says_what_a_scene_is(tmp_path):
    """A .txt (or any YAML whose top level is a string or a list) is named as not a scene, with
    what a scene is and how a mesh sequence is given instead."""
    from dynmesh_warp import load_scene_config
    from dynmesh_warp.config import SceneError

    p = tmp_path / "notes.txt"
    p.write_text("just some words\n")
    with pytest.raises(SceneError, match=r"notes\.txt: a scene file is a YAML mapping of sections") as e:
        load_scene_config(p)
    assert "top level is a str" in str(e.value) and "folder of frames" in str(e.value)


@pytest.mark.parametrize("doc,field", [({"spheres": {"count": True}}, "spheres.count"),
                                       ({"physics": {"gravity": [0, 0, True]}}, "physics.gravity"),
                                       ({"physics": {"dt": False}}, "physics.dt"),
                                       ({"envs": {"count": True}}, "envs.count")])
def test_a_boolean_where_a_number_goes_is_refused(doc, field):
    """``spheres.count: true`` ran one sphere (a new user's): booleans for numbers are refused,
    naming the field; a quoted number stays a number (YAML reads 1e-3 as a string)."""
    with pytest.raises(SceneError, match=rf"{field}: a number is expected, not the boolean"):
        load_scene_config(None, overrides=[f"{k}.{kk}={str(v).lower() if not isinstance(v, list) else v}"
                                          for k, d in doc.items() for kk, v in d.items()])
    assert load_scene_config(None, overrides=["physics.dt=1e-3"]).physics.dt == pytest.approx(1e-3)


def test_a_ground_plane_needs_gravity_along_minus_z():
    """The ground is the plane z = height. Under gravity along -y it stood parallel to the fall
    and stopped nothing (a new user's sphere fell 19 m past it, with no word): refused, naming
    the angle and what to do; gravity off, or within 45 degrees of -z, keeps it."""
    with pytest.raises(SceneError, match=r"physics: ground: the ground is the plane z = height.*90 degrees from -z"):
        load_scene_config(data={"physics": {"gravity": [0, -9.81, 0], "ground": "auto"}})
    with pytest.raises(SceneError, match="ground"):
        load_scene_config(overrides=["physics.gravity=[0,0,9.81]", "physics.ground=0"])  # upside down
    assert load_scene_config(data={"physics": {"gravity": [0, 0, 0], "ground": 0.0}}).physics.ground == 0.0
    assert load_scene_config(data={"physics": {"gravity": [3, 0, -9.81], "ground": "auto"}}).physics.ground == "auto"
    assert load_scene_config(data={"physics": {"gravity": [0, -9.81, 0]}}).physics.ground is None


def test_newton_body_fields_of_the_other_kind_are_refused_not_dropped(tmp_path):
    """A new user's `floating: false` box fell, `options` on a box, `velocity` and `density` on
    an mjcf model were taken and dropped unsaid: each is refused naming the body and the field."""
    from dynmesh_warp.config import SceneError, load_scene_config

    def scene(body):
        return {"surface": {"source": "builtin:wave_bowl"}, "spheres": [], "newton": {"bodies": [body]}}

    box = {"type": "box", "position": [0, 0, 1], "half_extents": [0.1, 0.1, 0.1]}
    (tmp_path / "ant.xml").write_text("<mujoco/>")
    mjcf = {"type": "mjcf", "file": str(tmp_path / "ant.xml")}
    for body, what in [({**box, "floating": False}, "floating: false fixes a model file's base"),
                       ({**box, "options": {"ignore_names": ["floor"]}}, "options are keyword arguments of add_mjcf"),
                       ({**mjcf, "velocity": [3, 0, 0]}, "velocity is a box / sphere / capsule's initial velocity"),
                       ({**mjcf, "density": 500}, "density applies to a box / sphere / capsule")]:
        with pytest.raises(SceneError, match=r"newton\.bodies\.0.*" + what):
            load_scene_config(data=scene(body))
    load_scene_config(data=scene({**box, "floating": True, "velocity": [1, 0, 0], "density": 500}))
    load_scene_config(data=scene({**mjcf, "floating": False, "options": {"ignore_names": ["floor"]}}))
