"""The example scenes in examples/ validate and run a few steps (the ones whose data is here)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from dynmesh_warp.config import DEFAULT_SCENE_FILE, load_scene_config
from dynmesh_warp.run import run_scene

# the examples, and the packaged built-in default scene (dynmesh_warp/default_scene.yaml)
EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.yaml")) + [DEFAULT_SCENE_FILE]


def test_there_are_examples():
    assert {p.stem for p in EXAMPLES} >= {"default_scene", "horse_gallop", "newton_bodies"}


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_example_scene_runs(path, tmp_path):
    text = path.read_text()
    if "shared/data" in text and not (path.resolve().parents[2] / "shared" / "data").is_dir():
        pytest.skip("shared data not present")
    if "newton:" in text and importlib.util.find_spec("newton") is None:
        pytest.skip("newton not installed")
    cfg = load_scene_config(path)
    summary = run_scene(cfg, device="cpu", steps=40, output=tmp_path / "out", progress=False, log=lambda *_: None)
    assert (tmp_path / "out" / "summary.json").is_file()
    if "final" in summary and "position" in summary["final"]:
        assert np.isfinite(np.asarray(summary["final"]["position"], float)).all()
