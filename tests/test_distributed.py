"""Ray across processes (issue 15; dynmesh_warp/distributed.py): a local Ray with 2 CPU actors,
a few envs each; the results come back in task order and equal the same rollouts run here."""

from __future__ import annotations

import pytest

ray = pytest.importorskip("ray")
pytest.importorskip("gymnasium")

from dynmesh_warp.distributed import RolloutActor, run_rollouts  # noqa: E402

SCENE = {"surface": {"source": "builtin:pulsing_blob", "params": {"subdivisions": 2, "frames": 12}}}


def test_rollouts_fan_out_over_ray_actors_and_match_local_runs():
    from dynmesh_warp.config import load_scene_config

    cfg = load_scene_config(data=SCENE)
    tasks = [{"steps": 25, "seed": s, "kp": kp, "kd": 0.8} for s, kp in ((0, 0.0), (1, 3.0), (2, 1.5))]
    remote = run_rollouts(tasks, num_actors=2, envs_per_actor=4, scene=cfg, env_kwargs={"max_steps": 10},
                          device="cpu")
    assert [r["seed"] for r in remote] == [0, 1, 2] and [r["kp"] for r in remote] == [0.0, 3.0, 1.5]
    local = RolloutActor(4, cfg, {"max_steps": 10}, device="cpu")
    for task, r in zip(tasks, remote):
        mine = local.run(task)
        assert r["episodes"] == mine["episodes"] > 0
        assert r["mean_return"] == pytest.approx(mine["mean_return"], rel=1e-6)
        assert r["reward_per_env_step"] == pytest.approx(mine["reward_per_env_step"], rel=1e-6)
    assert not ray.is_initialized()  # the local Ray it started is shut down again


def test_sweep_values_are_checked_by_name():
    """``--sweep kp=abc`` ended in float()'s traceback and ``--sweep seed=1.5`` ran seed 1 (a new
    user's): each is now refused naming the option; whole seeds and finite gains pass."""
    from dynmesh_warp.distributed import _sweep

    assert _sweep(["kp=1,2.5", "seed=3"]) == [{"kp": 1.0, "seed": 3}, {"kp": 2.5, "seed": 3}]
    for bad, what in (("kp=abc", "kp values must be finite numbers, got 'abc'"),
                      ("kd=1,inf", "kd values must be finite numbers, got 'inf'"),
                      ("seed=1.5", "seed values must be whole numbers, got '1.5'")):
        with pytest.raises(SystemExit, match=f"--sweep {bad}: {what}"):
            _sweep([bad])


def test_a_bad_scene_is_refused_before_ray_starts(tmp_path, monkeypatch, capsys):
    """A scene with an unknown key, a missing scene file and a y-up scene: one line naming the file
    and field, exit 2, Ray never started (it was a 40-line actor traceback and exit 1)."""
    import dynmesh_warp.distributed as D

    monkeypatch.setattr(D, "run_rollouts", lambda *a, **k: pytest.fail("Ray was started"))
    (tmp_path / "bad.yaml").write_text("surface:\n  source: builtin:pulsing_blob\nphysics:\n  dtt: 1\n")
    (tmp_path / "y.yaml").write_text("surface:\n  source: builtin:pulsing_blob\nphysics:\n  gravity: [0, -9.81, 0]\n")
    for name, said in (("bad.yaml", "physics.dtt: unknown key"), ("nope.yaml", "scene file not found"),
                       ("y.yaml", "need gravity along -z")):
        assert D.main([str(tmp_path / name), "--device", "cpu", "--envs", "2", "--steps", "5"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and said in err and len(err.splitlines()) == 1, err
