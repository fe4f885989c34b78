"""The conversion probes under bench/ check their outputs before any work (``common.checked_output``):
an output naming the probe's input, or a store folder holding a user's file of a name the probe
writes, is refused with one line naming it, and every input stays byte-identical."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _probe(name: str):
    sys.path.insert(0, str(ROOT / "bench"))
    spec = importlib.util.spec_from_file_location(name, ROOT / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture
def files(tmp_path):
    seq = tmp_path / "capture.npz"
    np.savez(seq, V=np.zeros((2, 3, 3), np.float32), F=np.array([[0, 1, 2]], np.int32), fps=24.0)
    store = tmp_path / "store"
    store.mkdir()
    (store / "k3.npz").write_bytes(b"a user's file")
    (tmp_path / "store.json").write_text(json.dumps({"keys": [3]}))
    return tmp_path, seq, store


def _snapshot(folder: Path) -> dict:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("case", ["score_out_is_input", "score_store_has_user_file", "subject_out_is_input",
                                  "rank_out_is_store_json"])
def test_probe_outputs_refused_before_any_work(files, case):
    tmp, seq, store = files
    before = _snapshot(tmp)
    common = ["--sequence", str(seq), "--subject", "1", "--cache", str(tmp / "cache")]
    if case == "score_out_is_input":
        run, argv, want = "key_score_probe", [*common, "--store", str(tmp / "new"), "--out", str(seq)], "is the input"
    elif case == "score_store_has_user_file":
        run, argv, want = "key_score_probe", [*common, "--store", str(store), "--out", str(tmp / "r.json")], "k3.npz"
    elif case == "subject_out_is_input":
        run, argv, want = "subject_coverage_probe", [*common, "--out", str(seq)], "is the input"
    else:
        run, argv, want = "key_score_rank", [str(store), "--out", str(tmp / "store.json")], "is the input"
    with pytest.raises(SystemExit, match=want):
        _probe(run).main(argv)
    assert _snapshot(tmp) == before
    assert not (tmp / "new").exists() and not (tmp / "cache").exists()  # nothing made: refused first
