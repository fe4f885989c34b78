"""Tests for dynmesh_warp.io: loading/saving sequences and meshes, ordering, bad input.

All data is generated here (small icospheres); nothing is read from the shared data folder
except by the optional test at the end, which skips when it is absent.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh

from dynmesh_warp.io import (
    frame_index_from_name,
    load_sequence,
    read_mesh,
    save_sequence,
    write_mesh,
)
from dynmesh_warp.sequence import (
    FixedTopologySequence,
    MeshDataError,
    VaryingTopologySequence,
)

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


# --------------------------------------------------------------------------- helpers


def icosphere(subdiv: int = 1):
    m = trimesh.creation.icosphere(subdivisions=subdiv)
    return m.vertices.astype(np.float32), m.faces.astype(np.int32)


def fixed_seq(T: int = 4, subdiv: int = 1, name: str = "ico") -> FixedTopologySequence:
    """A fixed-topology sequence whose frame t is shifted by t along x (identifiable)."""
    V, F = icosphere(subdiv)
    rng = np.random.default_rng(0)
    frames = [V * (1 + 0.05 * rng.standard_normal(V.shape)) + [t, 0, 0] for t in range(T)]
    return FixedTopologySequence(np.stack(frames).astype(np.float32), F, fps=30.0, name=name)


def varying_seq(T: int = 3) -> VaryingTopologySequence:
    frames = []
    for t in range(T):
        V, F = icosphere(t % 3)  # 12 / 42 / 162 vertices: different topology per frame
        frames.append((V + np.float32(t), F))
    return VaryingTopologySequence(frames, fps=12.5, name="vary")


def write_obj_text(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def frame_of(V: np.ndarray) -> int:
    """Recover the frame marker t from vertices written as ``base + [t, 0, 0]``."""
    return int(round(float(V[:, 0].mean())))


TRI_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


# --------------------------------------------------------------------------- round trips


def assert_same_fixed(a: FixedTopologySequence, b: FixedTopologySequence):
    assert isinstance(b, FixedTopologySequence)
    assert b.V.dtype == np.float32 and b.F.dtype == np.int32
    np.testing.assert_allclose(b.V, a.V, rtol=0, atol=1e-6)  # vertex order preserved
    np.testing.assert_array_equal(b.F, a.F)


def test_roundtrip_fixed_npz(tmp_path):
    seq = fixed_seq()
    save_sequence(seq, tmp_path / "s.npz")
    with np.load(tmp_path / "s.npz") as d:  # the shared-data layout, exactly
        assert set(d.files) == {"V", "F", "fps", "name"}
        assert d["V"].dtype == np.float32 and d["F"].dtype == np.int32
        assert d["fps"].shape == () and str(d["name"]) == "ico"
    out = load_sequence(tmp_path / "s.npz")
    assert_same_fixed(seq, out)
    assert out.fps == 30.0 and out.name == "ico"
    assert load_sequence(tmp_path / "s.npz", fps=10).fps == 10.0  # argument wins


@pytest.mark.parametrize("fmt", ["ply", "obj"])
def test_roundtrip_fixed_folder(tmp_path, fmt):
    seq = fixed_seq()
    save_sequence(seq, tmp_path / "out", fmt=fmt)
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == [".dynmesh_outputs.json"] + [f"frame_{i:04d}.{fmt}" for i in range(seq.num_frames)]
    out = load_sequence(tmp_path / "out")
    assert_same_fixed(seq, out)
    # the frame rate comes back from the manifest (a new user's 30 fps conversion read back at 24)
    assert seq.fps == 30.0 and out.fps == 30.0
    assert load_sequence(tmp_path / "out", fps=12).fps == 12.0  # the argument wins
    (tmp_path / "out" / ".dynmesh_outputs.json").unlink()
    assert load_sequence(tmp_path / "out").fps == 24.0  # a folder that says no rate: the default
    seq.fps = 29.97
    save_sequence(seq, tmp_path / "s.npz")
    assert load_sequence(tmp_path / "s.npz").fps == 29.97  # float64 in the npz (float32: 29.9699993)


@pytest.mark.parametrize("target", ["npz", "ply", "obj"])
def test_roundtrip_varying(tmp_path, target):
    seq = varying_seq()
    dest = tmp_path / ("v.npz" if target == "npz" else "v")
    save_sequence(seq, dest, fmt=None if target == "npz" else target)
    out = load_sequence(dest)
    assert isinstance(out, VaryingTopologySequence)
    assert out.num_frames == seq.num_frames
    for (va, fa), (vb, fb) in zip(seq.frames, out.frames):
        np.testing.assert_allclose(vb, va, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(fb, fa)
    if target == "npz":
        assert out.fps == 12.5 and out.name == "vary"
        with np.load(dest) as d:
            assert {"V_packed", "F_packed", "V_offsets", "F_offsets"} <= set(d.files)
    else:
        assert out.frame_sources[1].endswith(f"frame_0001.{target}")


def test_kind_conversions(tmp_path):
    save_sequence(fixed_seq(), tmp_path / "f.npz")
    assert isinstance(load_sequence(tmp_path / "f.npz", kind="varying"), VaryingTopologySequence)
    # a varying-layout npz whose frames happen to share topology loads as fixed in auto mode
    save_sequence(fixed_seq().to_varying(), tmp_path / "fv.npz")
    assert isinstance(load_sequence(tmp_path / "fv.npz"), FixedTopologySequence)
    with pytest.raises(ValueError, match="kind"):
        load_sequence(tmp_path / "f.npz", kind="bogus")


def test_a_bad_fps_is_named_for_both_sequence_kinds():
    """A string, None, a bool, NaN, 0, a negative fps or one outside choices.FPS_RANGE is a
    MeshDataError naming the sequence (a new user's "abc" got float()'s message, naming neither
    the field nor the sequence; --fps 1e300 wrote fps=inf, 1e-300 a .glb of non-finite times)."""
    seq = fixed_seq()
    for bad in ("abc", None, True, float("nan"), 0.0, -24.0, 1e300, 1e-300):  # 1e300: fps=inf written
        with pytest.raises(MeshDataError, match=r"cap: fps must be a positive number, 0.0001 to 1e\+07 frames/s, got "):
            FixedTopologySequence(seq.V, seq.F, fps=bad, name="cap")
        with pytest.raises(MeshDataError, match=r"cap: fps must be a positive number, 0.0001 to 1e\+07 frames/s, got "):
            VaryingTopologySequence(seq.to_varying().frames, fps=bad, name="cap")
    assert FixedTopologySequence(seq.V, seq.F, fps="30", name="cap").fps == 30.0  # a numeric string as before


def test_varying_frames_given_as_two_lists_are_named():
    """VaryingTopologySequence takes one list of (V, F) pairs; a list of vertex arrays and a list
    of face arrays given separately (the shape of FixedTopologySequence's arguments) failed with
    Python's "too many values to unpack", naming nothing."""
    seq = fixed_seq()
    with pytest.raises(MeshDataError, match=r"cap: frame 0: frames must be a list of \(V, F\) pairs.*ndarray of length"):
        VaryingTopologySequence(list(seq.V), name="cap")
    with pytest.raises(MeshDataError, match=r"frames must be a list of \(V, F\) pairs.*tuple of length 3"):
        VaryingTopologySequence([(seq.V[0], seq.F, None)], name="cap")
    assert VaryingTopologySequence(seq.to_varying().frames, name="cap").num_frames == seq.num_frames


def test_single_mesh_file(tmp_path):
    V, F = icosphere()
    write_mesh(tmp_path / "one.ply", V, F)
    seq = load_sequence(tmp_path / "one.ply")
    assert isinstance(seq, FixedTopologySequence) and seq.num_frames == 1
    np.testing.assert_allclose(seq.V[0], V, atol=1e-6)
    np.testing.assert_array_equal(seq.F, F)


def test_write_mesh_formats_preserve_order(tmp_path):
    V, F = icosphere()
    V = V[::-1].copy()  # an order trimesh processing would not keep
    F = (len(V) - 1 - F).astype(np.int32)
    for ext in ("ply", "obj", "off"):
        write_mesh(tmp_path / f"m.{ext}", V, F)
        V2, F2 = read_mesh(tmp_path / f"m.{ext}")
        np.testing.assert_allclose(V2, V, atol=1e-6)
        np.testing.assert_array_equal(F2, F)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp leftovers


def test_save_refuses_an_existing_file_without_overwrite(tmp_path):
    """overwrite=False held for folders only: a new user's own .npz (and an .anime / .glb) was
    replaced. Now refused before anything is written; overwrite=True replaces it."""
    from dynmesh_warp.outputs import OutputExistsError

    seq = fixed_seq()
    for name in ("mine.npz", "mine.anime", "mine.glb", "mine.pc2"):
        p = tmp_path / name
        p.write_bytes(b"the user's file")
        with pytest.raises(OutputExistsError, match=rf"{name}: exists; pass overwrite=True to replace it"):
            save_sequence(seq, p)
        assert p.read_bytes() == b"the user's file"
        save_sequence(seq, p, overwrite=True)
        assert load_sequence(p).num_frames == seq.num_frames


def test_save_replaces_existing_folder_and_refuses_foreign_content(tmp_path):
    save_sequence(fixed_seq(T=5), tmp_path / "out", fmt="ply")
    save_sequence(fixed_seq(T=2), tmp_path / "out", fmt="ply")
    assert load_sequence(tmp_path / "out").num_frames == 2  # old frames gone
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temp folders left
    (tmp_path / "out" / "notes.json").write_text("{}")
    with pytest.raises(FileExistsError, match="notes.json"):
        save_sequence(fixed_seq(T=2), tmp_path / "out", fmt="obj")
    with pytest.raises(ValueError, match="fmt"):
        save_sequence(fixed_seq(), tmp_path / "other")


def test_interrupted_save_leaves_no_partial_output(tmp_path, monkeypatch):
    import dynmesh_warp.mesh_formats as mf

    save_sequence(fixed_seq(T=3), tmp_path / "out", fmt="ply")
    save_sequence(fixed_seq(T=3), tmp_path / "s.npz")
    before = sorted(p.name for p in tmp_path.iterdir())
    real = dict(mf.WRITERS)

    def failing(ext):
        def write(fh, V, F):
            real[ext](fh, V, F)  # the file is (partly) there, then the save is interrupted
            if Path(fh.name).name.startswith(("frame_0001", ".one.")):
                raise KeyboardInterrupt
        return write

    for ext in (".ply", ".obj"):  # the registries of mesh_formats (a format's writer)
        monkeypatch.setitem(mf.WRITERS, ext, failing(ext))
    with pytest.raises(KeyboardInterrupt):
        save_sequence(fixed_seq(T=5), tmp_path / "out", fmt="ply")
    with pytest.raises(KeyboardInterrupt):
        save_sequence(fixed_seq(T=5), tmp_path / "new", fmt="obj")
    with pytest.raises(KeyboardInterrupt):
        write_mesh(tmp_path / "one.ply", *icosphere())
    monkeypatch.setattr(np, "savez", lambda *a, **k: (_ for _ in ()).throw(OSError("disk full")))
    with pytest.raises(OSError, match="disk full"):
        save_sequence(fixed_seq(T=5), tmp_path / "s.npz", overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no temp files or folders
    assert load_sequence(tmp_path / "out").num_frames == 3  # old output intact
    assert load_sequence(tmp_path / "s.npz").num_frames == 3


# --------------------------------------------------------------------------- ordering


def test_frame_index_from_name():
    assert frame_index_from_name("frame_0010.ply") == 10
    assert frame_index_from_name("horse9.obj") == 9
    assert frame_index_from_name("mesh_gt/bird3.obj") == 3
    assert frame_index_from_name("/data/run2/scan_v2_017.obj") == 17
    with pytest.raises(MeshDataError, match="mesh.obj"):
        frame_index_from_name("mesh.obj")


def write_marked_frames(folder: Path, names: list[str], marks: list[int]):
    V, F = icosphere(0)
    for name, t in zip(names, marks):
        write_mesh(folder / name, V + np.float32([t, 0, 0]), F)


def test_folder_numeric_order(tmp_path):
    write_marked_frames(tmp_path, ["frame_2.ply", "frame_10.ply", "frame_1.ply"], [2, 10, 1])
    (tmp_path / "cameras.json").write_text("{}")  # non-mesh and hidden files are ignored
    (tmp_path / "readme.txt").write_text("x")
    (tmp_path / ".hidden.ply").write_text("junk")
    with pytest.warns(UserWarning, match="gaps"):  # 3..9 are missing
        seq = load_sequence(tmp_path)
    assert isinstance(seq, FixedTopologySequence)
    assert [frame_of(v) for v in seq.V] == [1, 2, 10]


def test_folder_numeric_order_obj_names(tmp_path):
    write_marked_frames(tmp_path, ["horse10.obj", "horse9.obj", "horse11.obj"], [10, 9, 11])
    (tmp_path / "horse.mtl").write_text("newmtl a\n")
    seq = load_sequence(tmp_path)
    assert [frame_of(v) for v in seq.V] == [9, 10, 11]


@pytest.mark.parametrize("names, times", [
    ([f"mesh_t{round(k * 0.05, 2)}.ply" for k in range(10)], None),  # as f"{t}" writes them: 0.05 before 0.1
    ([f"mesh_t{k / 30:.3f}.ply" for k in range(40)], None),  # 0.000 .. 1.300: the last integer repeats
    ([f"frame_{k:03d}_iter30000.ply" for k in range(6)], list(range(6))),  # a suffix all share
    ([f"frame_{k:04d}_v2.ply" for k in range(6)], list(range(6))),
    ([f"scan_v2_{k:03d}.obj" for k in range(4)], list(range(4))),
    ([f"shot1.{k}.obj" for k in (8, 9, 10, 11)], [8, 9, 10, 11]),  # name.frame: 1.10 is no decimal
    (["frame_000_iter30000.obj", "frame_001_iter29500.obj", "frame_002_iter31000.obj"], [0, 1, 2]),
    (["t-1.0.obj", "t-0.5.obj", "t0.0.obj", "t0.5.obj"], None),  # negative time stamps
    (["2024-05-01_frame_098.obj", "2024-05-01_frame_099.obj", "2024-05-02_frame_100.obj"], [98, 99, 100])])
def test_folder_order_by_the_number_that_counts_the_frames(tmp_path, names, times):
    """The frame's number is the last one that differs between the names (a decimal time stamp
    by its value): time stamps read 0, 2, 4, 6, 8, 1, 3, ... and names with a shared suffix were
    refused as "two files have frame index 30000" (a new user's). Written shuffled; frame k is
    marked at x = k. A folder output keeps integer numbers, a time stamp's frames are numbered
    from 0 (``input_frame_numbers``)."""
    from dynmesh_warp.convert_cli import input_frame_numbers

    import warnings

    order = np.random.default_rng(1).permutation(len(names))
    write_marked_frames(tmp_path, [names[i] for i in order], [int(i) for i in order])
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        seq = load_sequence(tmp_path)
    assert not any("different ways" in str(w.message) for w in seen)  # one series (a date that changes too)
    assert [frame_of(v) for v in seq.V] == list(range(len(names)))
    assert input_frame_numbers(tmp_path, len(names)) == times


def test_folder_of_one_subfolder_a_frame(tmp_path):
    """``0000/mesh.ply``, ``0001/mesh.ply``, ...: the frames in the subfolders' order (it was
    refused with "pass subdir=...", which reads one subfolder); a subfolder with two meshes is not
    this layout."""
    for k in (2, 0, 10, 1):
        write_marked_frames(tmp_path / f"{k:04d}", ["mesh.ply"], [k])
    assert [frame_of(v) for v in load_sequence(tmp_path).V] == [0, 1, 2, 10]
    write_marked_frames(tmp_path / "0003", ["mesh.ply", "points.ply"], [3, 3])
    with pytest.raises(MeshDataError, match="read as one mesh a subfolder .* but 0003 holds 2 mesh files"):
        load_sequence(tmp_path)
    for k in (0, 1, 2):  # subfolders named by time stamp (t0.05: no extension)
        write_marked_frames(tmp_path / "ts" / f"t{round(0.05 * k, 2)}", ["mesh.obj"], [k])
    assert [frame_of(v) for v in load_sequence(tmp_path / "ts").V] == [0, 1, 2]


def test_gaps_are_said_once_by_convert(tmp_path, capsys):
    """The numbering's warning comes from the loader alone: ``convert`` looked at the folder
    three times and said a new user's gaps three times."""
    from dynmesh_warp.convert import main

    import warnings

    write_marked_frames(tmp_path / "g", [f"frame_{n:04d}.ply" for n in (0, 1, 2, 5, 6, 9)], list(range(6)))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert main([str(tmp_path / "g"), str(tmp_path / "o.npz"), "--as-is", "--device", "cpu"]) == 0
    said = [str(w.message) for w in seen] + capsys.readouterr().err.splitlines()
    assert sum("frame numbering has gaps" in m for m in said) == 1


def test_npz_of_object_arrays_names_the_packed_layout(tmp_path):
    """Per-frame lists saved with np.savez (object arrays, which need pickle) are refused naming the
    packed layout to save instead (it was NumPy's "Object arrays cannot be loaded ...")."""
    V = np.empty(2, object)
    V[:] = [np.zeros((3, 3)), np.zeros((4, 3))]
    np.savez(tmp_path / "lists.npz", V=V, F=V)
    with pytest.raises(MeshDataError, match=r"lists\.npz: it holds object arrays .* V_packed"):
        load_sequence(tmp_path / "lists.npz")


def test_dgmesh_layouts(tmp_path):
    scene = tmp_path / "bird"
    write_marked_frames(scene / "dynamic_mesh", [f"frame_{i}.ply" for i in range(3)], [0, 1, 2])
    V, F = icosphere(1)  # the ground truth differs (more vertices)
    for i in range(4):
        write_mesh(scene / "mesh_gt" / f"bird{i}.obj", V + np.float32([i, 0, 0]), F)
    (scene / "input.ply").write_text("not a frame")  # e.g. 3DGS output next to them

    rec = load_sequence(scene)  # dynamic_mesh preferred
    assert rec.num_frames == 3 and rec.num_vertices == 12
    gt = load_sequence(scene, subdir="mesh_gt")
    assert gt.num_frames == 4 and gt.num_vertices == 42
    assert [frame_of(v) for v in gt.V] == [0, 1, 2, 3]

    only_gt = tmp_path / "only_gt"
    only_gt.mkdir()
    (scene / "mesh_gt").rename(only_gt / "mesh_gt")
    assert load_sequence(only_gt).num_frames == 4  # the single DG-Mesh subfolder is found
    with pytest.raises(FileNotFoundError, match="nope"):
        load_sequence(scene, subdir="nope")


# --------------------------------------------------------------------------- topology


def test_quads_are_triangulated(tmp_path):
    quads = (
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\n"
        "f 1 2 3 4\nf 2 5 6 3\n"
    )
    V, F = read_mesh(write_obj_text(tmp_path / "q.obj", quads))
    assert V.shape == (6, 3) and F.shape == (4, 3)  # 2 triangles per quad
    np.testing.assert_array_equal(F, [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    pent = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0.5 2 0\nv 0 1 0\nf 1 2 3 4 5\n"
    _, F = read_mesh(write_obj_text(tmp_path / "p.obj", pent))
    assert F.shape == (3, 3)  # fan: n-2 triangles
    off = "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    _, F = read_mesh(write_obj_text(tmp_path / "q.off", off))
    assert F.shape == (2, 3)


def test_obj_index_forms(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\nf -3/1/1 -2/1/1 -1/1/1\nl 1 2\n"
    V, F = read_mesh(write_obj_text(tmp_path / "a.obj", text))
    np.testing.assert_array_equal(F, [[0, 1, 2]])
    text = "v 9 9 9\n" + TRI_OBJ.replace("f 1 2 3", "f 2 3 4")  # unreferenced vertex kept
    V, F = read_mesh(write_obj_text(tmp_path / "b.obj", text))
    assert V.shape == (4, 3) and V[0, 0] == 9


def test_obj_comments_and_line_continuation(tmp_path):
    """A ``#`` comment after a record and a backslash continuing a record on the next line (both
    in the OBJ format) read as the plain file does; the error for a bad record names its line."""
    plain = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n"
    ref = read_mesh(write_obj_text(tmp_path / "plain.obj", plain))
    for name, text in [("comment.obj", "v 0 0 0 # origin\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4  # a quad\n"),
                       ("continued.obj", "v 0 0 0\nv 1 0 0\nv 1 1 \\\n 0\nv 0 1 0\nf 1 2 \\\n  3 4\n")]:
        V, F = read_mesh(write_obj_text(tmp_path / name, text))
        np.testing.assert_array_equal(V, ref[0])
        np.testing.assert_array_equal(F, ref[1])
    with pytest.raises(MeshDataError, match="line 5: bad face index 'x'"):
        read_mesh(write_obj_text(tmp_path / "bad.obj", "v 0 0 0\nv 1 0 0\nv 1 1 \\\n 0\nf 1 2 \\\n 3 x\n"))


def test_folder_fixed_vs_varying(tmp_path):
    varying_seq_ = varying_seq()
    save_sequence(varying_seq_, tmp_path / "vary", fmt="ply")
    seq = load_sequence(tmp_path / "vary")
    assert isinstance(seq, VaryingTopologySequence)
    assert seq.frame_sources and seq.frame_sources[0].endswith("frame_0000.ply")
    save_sequence(fixed_seq(), tmp_path / "fix", fmt="obj")
    assert isinstance(load_sequence(tmp_path / "fix"), FixedTopologySequence)
    assert isinstance(load_sequence(tmp_path / "fix", kind="varying"), VaryingTopologySequence)


def test_kind_fixed_on_differing_vertex_counts(tmp_path):
    V0, F0 = icosphere(1)
    V1, F1 = icosphere(0)
    for i in range(8):
        V, F = (V1, F1) if i == 7 else (V0, F0)
        write_mesh(tmp_path / f"frame_{i}.ply", V, F)
    assert isinstance(load_sequence(tmp_path), VaryingTopologySequence)
    with pytest.raises(MeshDataError) as e:
        load_sequence(tmp_path, kind="fixed")
    msg = str(e.value)
    assert "frame_7.ply" in msg and "frame 7" in msg and "frame_0.ply" in msg
    assert "12 vertices" in msg and "42" in msg


def test_kind_fixed_on_differing_faces(tmp_path):
    V, F = icosphere(0)
    write_mesh(tmp_path / "m0.obj", V, F)
    write_mesh(tmp_path / "m1.obj", V, F[:, [0, 2, 1]])
    with pytest.raises(MeshDataError, match=r"m1\.obj.*frame 1.*faces differ") as e:
        load_sequence(tmp_path, kind="fixed")
    # the same count: the message says so (it read "(20 vs 20 faces)", a seeming contradiction)
    assert f"the same number ({len(F)}), other vertex indices (first at face 0)" in str(e.value)


# --------------------------------------------------------------------------- bad input


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.npz"):
        load_sequence(tmp_path / "nothere.npz")
    with pytest.raises(FileNotFoundError, match="nodir"):
        load_sequence(tmp_path / "nodir")
    with pytest.raises(FileNotFoundError, match="gone.obj"):
        read_mesh(tmp_path / "gone.obj")


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no meshes here")
    with pytest.raises(MeshDataError, match="empty.*no mesh files"):
        load_sequence(tmp_path / "empty")


@pytest.mark.parametrize(
    "name,content",
    [
        ("bad.obj", "v 0 0 zzz\nf 1 2 3\n"),
        ("bad.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n"
                    b"property float x\nend_header\n\x00\x01"),
        ("bad2.ply", b"\x00\x01 definitely not a mesh"),
        ("bad.off", "OFF\n3 1 0\n0 0 0\n"),
        ("bad.npz", b"PK\x03\x04 truncated zip"),
    ],
)
def test_corrupt_file(tmp_path, name, content):
    p = tmp_path / name
    p.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(MeshDataError, match=name.replace(".", r"\.")):
        load_sequence(p)


_TETRA_PLY = ("ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 4\nproperty float x\nproperty float y\n"
              "property float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n"
              "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")


@pytest.mark.parametrize("keep_lines", [0, 2, 4, 5, 7])
def test_truncated_ascii_ply_is_an_error(tmp_path, keep_lines):
    """An ASCII PLY cut short (in the vertex or the face list) names the file and what is
    missing; trimesh alone read the faces that were there without a word (found by a new user)."""
    head, body = _TETRA_PLY.split("end_header\n")
    full = tmp_path / "full.ply"
    full.write_text(_TETRA_PLY)
    V, F = read_mesh(full)
    assert V.shape == (4, 3) and F.shape == (4, 3)
    p = tmp_path / "cut.ply"
    p.write_text(head + "end_header\n" + "".join(body.splitlines(keepends=True)[:keep_lines]))
    with pytest.raises(MeshDataError, match=r"cut\.ply: truncated: the header declares 4 vertices and 4 faces "
                                            rf"but the file has {keep_lines} data lines"):
        read_mesh(p)


def _binary_ply(path, V, polys, endian: str, index: str, face_flags: bool = False) -> None:
    """A binary PLY written with struct from the PLY specification: x y z, normals and colours
    per vertex; per face a vertex_indices list with a uchar count and ``index`` ("i" int, "I"
    uint) items, and optionally a per-corner texcoord list (float) and a uchar property after it."""
    order = "little" if endian == "<" else "big"
    head = (f"ply\nformat binary_{order}_endian 1.0\ncomment written by the test\nelement vertex {len(V)}\n"
            "property float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\n"
            "property float nz\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
            f"element face {len(polys)}\nproperty list uchar {'int' if index == 'i' else 'uint'} vertex_indices\n"
            + ("property list uchar float texcoord\nproperty uchar flags\n" if face_flags else "") + "end_header\n")
    body = b"".join(struct.pack(endian + "6f3B", *v, 0.0, 0.0, 1.0, 200, 100, 50) for v in V)
    body += b"".join(struct.pack(f"{endian}B{len(p)}{index}", len(p), *p)
                     + (struct.pack(f"{endian}B{2 * len(p)}fB", 2 * len(p), *np.linspace(0, 1, 2 * len(p)), 7)
                        if face_flags else b"") for p in polys)
    path.write_bytes(head.encode("ascii") + body)


@pytest.mark.parametrize("endian", ["<", ">"])
@pytest.mark.parametrize("index", ["i", "I"])
@pytest.mark.parametrize("sizes", [(4, 3, 4, 3, 3), (4, 5, 4, 6, 4), (3, 4, 3, 4), (4, 3, 5)])
def test_binary_ply_with_mixed_face_sizes(tmp_path, endian, index, sizes):
    """Quads among triangles or n-gons in a binary PLY (Blender's export) load, fanned (v0, vi,
    vi+1) in face order as OBJ/OFF are; trimesh's binary reader takes every face list as long as
    the first and refused them ("PLY is unexpected length!") or read garbage (found by a new
    user). (4, 3, 5) takes as many bytes as three quads: trimesh read it as quads, garbage."""
    rng = np.random.default_rng(len(sizes))
    V = rng.random((12, 3)).astype(np.float32)
    polys = [[int(i) for i in rng.choice(12, size=k, replace=False)] for k in sizes]
    want = [(p[0], p[i], p[i + 1]) for p in polys for i in range(1, len(p) - 1)]
    for flags in (False, True):
        p = tmp_path / f"frame_1_{flags}.ply"
        _binary_ply(p, V, polys, endian, index, flags)
        V2, F2 = read_mesh(p)
        np.testing.assert_array_equal(V2, V)
        np.testing.assert_array_equal(F2, want)


@pytest.mark.parametrize("endian", ["<", ">"])
def test_binary_ply_with_mixed_face_sizes_cut_short_is_an_error(tmp_path, endian):
    p = tmp_path / "cut.ply"
    _binary_ply(p, np.eye(5, 3, dtype=np.float32), [[0, 1, 2, 3], [1, 2, 4], [0, 1, 2, 3, 4]], endian, "i")
    data = p.read_bytes()
    for cut in (1, 4, 21):
        p.write_bytes(data[:-cut])
        with pytest.raises(MeshDataError, match=r"cut\.ply: truncated: element face \(3 rows"):
            read_mesh(p)


def test_corrupt_frame_in_folder_names_file_and_frame(tmp_path):
    write_marked_frames(tmp_path, ["f0.obj", "f1.obj", "f2.obj"], [0, 1, 2])
    (tmp_path / "f1.obj").write_text("v 0 0 zzz\n")
    with pytest.raises(MeshDataError, match=r"f1\.obj, frame 1: line 1"):
        load_sequence(tmp_path)


@pytest.mark.parametrize(
    "name,content",
    [
        ("empty.obj", "# nothing\n"),
        ("empty.ply", "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                      "property float y\nproperty float z\nend_header\n"),
    ],
)
def test_empty_mesh(tmp_path, name, content):
    p = write_obj_text(tmp_path / name, content)
    with pytest.raises(MeshDataError, match=name.replace(".", r"\.")):
        read_mesh(p)


@pytest.mark.parametrize(
    "name,content",
    [
        ("pts.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
        ("lines.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 3\n"),
        ("pts.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                    "property float y\nproperty float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n"),
    ],
)
def test_points_without_faces(tmp_path, name, content):
    p = write_obj_text(tmp_path / name, content)
    with pytest.raises(MeshDataError, match=name.replace(".", r"\.") + ".*no triangle faces"):
        read_mesh(p)


PLY_HEAD = (
    "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
)


@pytest.mark.parametrize(
    "name,content",
    [
        ("oor.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 5\n"),
        ("zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n"),
        ("oor.ply", PLY_HEAD + "0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n"),
        ("oor.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n"),
    ],
)
def test_face_index_out_of_range_file(tmp_path, name, content):
    p = write_obj_text(tmp_path / name, content)
    with pytest.raises(MeshDataError, match=name.replace(".", r"\.") + ".*(out of range|index 0)"):
        read_mesh(p)


def test_face_index_out_of_range_npz(tmp_path):
    seq = fixed_seq()
    F = seq.F.copy()
    F[5, 1] = seq.num_vertices + 3
    np.savez(tmp_path / "oor.npz", V=seq.V, F=F, fps=np.float32(24), name="x")
    with pytest.raises(MeshDataError, match=r"oor\.npz.*out of range"):
        load_sequence(tmp_path / "oor.npz")


@pytest.mark.parametrize("ext", ["obj", "ply"])
def test_nan_vertex_in_file(tmp_path, ext):
    if ext == "obj":
        p = write_obj_text(tmp_path / "nan.obj", TRI_OBJ.replace("v 1 0 0", "v nan 0 0"))
    else:
        p = write_obj_text(tmp_path / "nan.ply", PLY_HEAD + "0 0 0\nnan 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(MeshDataError, match=rf"nan\.{ext}.*NaN"):
        read_mesh(p)


def test_nan_vertex_in_folder_frame(tmp_path):
    write_marked_frames(tmp_path, [f"frame_{i}.obj" for i in range(3)], [0, 1, 2])
    (tmp_path / "frame_2.obj").write_text(TRI_OBJ.replace("v 1 0 0", "v 1 inf 0"))
    with pytest.raises(MeshDataError, match=r"frame_2\.obj, frame 2.*NaN/inf"):
        load_sequence(tmp_path, kind="varying")


def test_nan_vertex_in_npz_later_frame(tmp_path):
    seq = fixed_seq()
    V = seq.V.copy()
    V[2, 7, 1] = np.nan
    np.savez(tmp_path / "nan.npz", V=V, F=seq.F, fps=np.float32(24), name="x")
    with pytest.raises(MeshDataError, match=r"nan\.npz, frame 2.*NaN"):
        load_sequence(tmp_path / "nan.npz")
    # the same in the varying layout
    vs = varying_seq()
    v1 = vs.frames[1][0].copy()
    v1[3] = np.inf
    bad = VaryingTopologySequence.__new__(VaryingTopologySequence)  # skip validation
    bad.frames, bad.fps, bad.name = [vs.frames[0], (v1, vs.frames[1][1])], 24.0, "bad"
    bad.source = bad.frame_sources = None
    save_sequence(bad, tmp_path / "vnan.npz")
    with pytest.raises(MeshDataError, match=r"vnan\.npz, frame 1.*NaN"):
        load_sequence(tmp_path / "vnan.npz")


def test_unknown_npz_layout(tmp_path):
    np.savez(tmp_path / "none.npz", colors=np.zeros((3, 3)))
    with pytest.raises(MeshDataError, match=r"none\.npz.*layout"):
        load_sequence(tmp_path / "none.npz")
    np.savez(tmp_path / "odd.npz", points=np.zeros((3, 3)))
    # vertices without faces: a vertex-only file, whose faces come from a mesh (topology=)
    with pytest.raises(MeshDataError, match=r"odd\.npz: this file holds vertex positions only \(no faces.*topology="):
        load_sequence(tmp_path / "odd.npz")


def test_folder_name_without_integer(tmp_path):
    write_marked_frames(tmp_path, ["frame_0.ply", "frame_1.ply", "final.ply"], [0, 1, 2])
    with pytest.raises(MeshDataError, match=r"final\.ply.*no integer"):
        load_sequence(tmp_path)


def test_folder_duplicate_index(tmp_path):
    write_marked_frames(tmp_path, ["a_3.ply", "b_03.ply"], [0, 1])
    with pytest.raises(MeshDataError, match=r"a_3\.ply.*b_03\.ply"):
        load_sequence(tmp_path)


def test_folder_mixed_extensions(tmp_path):
    write_marked_frames(tmp_path, ["frame_0.ply", "frame_1.obj"], [0, 1])
    with pytest.raises(MeshDataError, match=r"\.obj.*\.ply"):
        load_sequence(tmp_path)


def test_folder_gap_warns(tmp_path):
    write_marked_frames(tmp_path, ["f1.ply", "f2.ply", "f5.ply"], [1, 2, 5])
    with pytest.warns(UserWarning, match="missing 3, 4"):
        seq = load_sequence(tmp_path)
    assert [frame_of(v) for v in seq.V] == [1, 2, 5]


def test_folder_numbered_at_a_stride_is_said_as_a_stride(tmp_path):
    """frame_000, frame_010, frame_020: an export of every 10th frame, which a new user was told
    had gaps (missing 1, 2, 3 ...) with no word on the frame rate."""
    write_marked_frames(tmp_path, ["frame_000.ply", "frame_010.ply", "frame_020.ply", "frame_030.ply"], [0, 1, 2, 3])
    with pytest.warns(UserWarning, match=r"numbered every 10 \(0, 10, 20, \.\.\.\).*fps / 10") as rec:
        seq = load_sequence(tmp_path)
    assert not any("missing" in str(r.message) for r in rec)
    assert [frame_of(v) for v in seq.V] == [0, 1, 2, 3]


# --------------------------------------------------------------------------- shared data


def test_shared_pcow_npz():
    path = SHARED_DATA / "pcow.npz"
    if not path.exists():
        pytest.skip(f"{path} not available")
    seq = load_sequence(path)
    assert isinstance(seq, FixedTopologySequence)
    assert seq.V.shape == (204, 2904, 3) and seq.F.shape == (5804, 3)  # README figures
    assert seq.fps == 24.0 and seq.name == "pcow"


def test_text_sorted_frames_are_detected_and_restored(tmp_path):
    """A sequence stored in text order (1, 10, 11, ..., 2, 20, ...) warns and is restored on request."""
    import warnings

    from dynmesh_warp.sequence import detect_text_sorted_frames, text_sorted_permutation

    T = 23
    t = np.arange(T, dtype=np.float32)
    base = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    V = base[None] + 0.05 * t[:, None, None] * np.array([1.0, 0.2, 0.0], np.float32)  # smooth drift
    F = np.array([[0, 1, 2], [2, 3, 4]], np.int32)
    labels = sorted(str(i) for i in range(1, T + 1))  # what a text sort of frame_1..frame_23 gives
    stored = V[[int(x) - 1 for x in labels]]
    assert [int(x) for x in labels[:4]] == [1, 10, 11, 12]
    np.testing.assert_array_equal(stored[text_sorted_permutation(T, 1)], V)
    assert detect_text_sorted_frames(stored) == 1
    assert detect_text_sorted_frames(V) is None
    path = tmp_path / "seq.npz"
    np.savez(path, V=stored, F=F, fps=np.float32(24))
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        seq = load_sequence(path)
    assert any("sorted as text" in str(x.message) and "seq.npz" in str(x.message) for x in w)
    np.testing.assert_array_equal(seq.V, stored)
    fixed = load_sequence(path, frame_order="text_sorted")
    np.testing.assert_array_equal(fixed.V, V)
    np.testing.assert_array_equal(load_sequence(path, frame_order="auto").V, V)
    path2 = tmp_path / "ordered.npz"
    np.savez(path2, V=V, F=F, fps=np.float32(24))
    np.testing.assert_array_equal(load_sequence(path2, frame_order="auto").V, V)  # nothing to undo
    with pytest.raises(ValueError, match="frame_order"):
        load_sequence(path, frame_order="alphabetical")
    # a varying-topology npz: reordered when asked (it was left as stored, unsaid; a new user's)
    from dynmesh_warp.sequence import VaryingTopologySequence

    frames = [(V[k] * (1.0 if k % 2 else 1.01), F if k % 2 else F[::-1]) for k in range(T)]
    vpath = tmp_path / "varying.npz"
    save_sequence(VaryingTopologySequence([frames[int(x) - 1] for x in labels], fps=24.0), vpath)
    back = load_sequence(vpath, frame_order="text_sorted")
    assert isinstance(back, VaryingTopologySequence)
    for k in range(T):
        np.testing.assert_array_equal(back.frames[k][0], frames[k][0])


def test_a_registered_format_is_read_written_and_found_in_folders(tmp_path):
    """mesh_formats' registries: a format added with register_format is used by write_mesh,
    read_mesh and folder loading (the one place a new format goes; docs/architecture.md)."""
    import dynmesh_warp.mesh_formats as mf

    def write_tri(fh, V, F):  # a toy text format: "N M", N vertex lines, M face lines
        fh.write(f"{len(V)} {len(F)}\n".encode())
        np.savetxt(fh, V, fmt="%.9g")
        np.savetxt(fh, F, fmt="%d")

    def read_tri(path):
        n, m = map(int, Path(path).read_text().split("\n", 1)[0].split())
        rows = np.loadtxt(path, skiprows=1, ndmin=2)
        return rows[:n], rows[n:n + m].astype(np.int64)

    V, F = icosphere()
    try:
        mf.register_format("TRI", reader=read_tri, writer=write_tri)
        for t in range(3):
            write_mesh(tmp_path / "seq" / f"f_{t}.tri", V * (1 + t), F)
        V1, F1 = read_mesh(tmp_path / "seq" / "f_1.tri")
        np.testing.assert_array_equal(F1, F)
        np.testing.assert_allclose(V1, (V * 2).astype(np.float32))
        seq = load_sequence(tmp_path / "seq")
        assert isinstance(seq, FixedTopologySequence) and seq.num_frames == 3
        np.testing.assert_allclose(seq.V[2], (V * 3).astype(np.float32))
    finally:
        mf.READERS.pop(".tri", None)
        mf.WRITERS.pop(".tri", None)
        mf.MESH_EXTENSIONS.discard(".tri")
    assert ".tri" not in mf.MESH_EXTENSIONS


@pytest.mark.parametrize("faces", [False, True])
def test_npz_with_a_corrupt_member_header_names_the_file(tmp_path, faces):
    """A zip whose central directory is sound but whose member's local header is not (the fuzz
    test's find: b"PK\\x03\\x04nan..."): reading the vertices raised zipfile.BadZipFile out of
    load_sequence for a vertex-only npz; now a MeshDataError naming the file, as for the layouts
    with faces."""
    import io as _io
    import zipfile

    buf = _io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for key, a in (("V", np.zeros((2, 3, 3), np.float32)),) + ((("F", np.array([[0, 1, 2]], np.int32)),)
                                                                     if faces else ()):
            b = _io.BytesIO()
            np.lib.format.write_array(b, a, allow_pickle=False)
            z.writestr(key + ".npy", b.getvalue())
    data = buf.getvalue()
    data = data[:4] + b"nan" + data[4:]  # three bytes inserted after the first local signature
    p = tmp_path / "broken.npz"
    p.write_bytes(data)
    with pytest.raises(MeshDataError, match=r"broken\.npz"):
        load_sequence(p)


def test_npz_with_a_corrupt_status_member_still_loads(tmp_path):
    """The stopped-run check reads an npz's ``status`` before the loader: a corrupt status member
    (its local header shifted, the central directory sound) raised zipfile.BadZipFile out of
    load_sequence; the check now leaves a file it cannot read to the loader, which reads V and F."""
    import io as _io
    import zipfile

    buf = _io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for key, a in (("status", np.asarray('{"complete": false}')), ("V", np.zeros((2, 3, 3), np.float32)),
                       ("F", np.array([[0, 1, 2]], np.int32))):
            b = _io.BytesIO()
            np.lib.format.write_array(b, a, allow_pickle=False)
            z.writestr(key + ".npy", b.getvalue())
    data = buf.getvalue()
    p = tmp_path / "status.npz"
    p.write_bytes(data[:4] + b"nan" + data[4:])  # the first member (status): header shifted
    seq = load_sequence(p)
    assert seq.num_frames == 2


def test_obj_and_off_with_a_byte_order_mark(tmp_path):
    """A file saved as UTF-8 with a byte-order mark (Windows tools, some exporters) reads as the
    plain file does: the mark is not part of the first record (it dropped vertex 1 and shifted
    every index, silently where the last vertex was unused; a new user's)."""
    plain = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 5 5 5\nf 1 2 3 4\n"
    ref = read_mesh(write_obj_text(tmp_path / "plain.obj", plain))
    (tmp_path / "bom.obj").write_text(plain, encoding="utf-8-sig")
    V, F = read_mesh(tmp_path / "bom.obj")
    np.testing.assert_array_equal(V, ref[0])
    np.testing.assert_array_equal(F, ref[1])
    off = "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    (tmp_path / "bom.off").write_text(off, encoding="utf-8-sig")
    V, F = read_mesh(tmp_path / "bom.off")
    np.testing.assert_array_equal(V, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(F, [[0, 1, 2]])


def _quadratic_motion(t: np.ndarray) -> np.ndarray:
    """A triangle whose vertices move on parabolas: (len(t), 3, 3) float64."""
    x = np.stack([0.3 + 2.0 * t - 4.0 * t ** 2, 1.0 + 0.5 * t, 3.0 * t ** 2], -1)
    return np.stack([x, x + [1.0, 0.0, 0.0], x + [0.0, 1.0, 0.0]], 1)


def test_upsampled_is_a_c1_curve_through_the_frames():
    """``FixedTopologySequence.upsampled``: every input frame kept, a motion quadratic in time
    reproduced exactly between the frames (Catmull-Rom's tangents are exact for it), the frame
    counts and rate of each playback, and the ends as each playback plays them."""
    fps, T, n = 24.0, 7, 10
    seq = FixedTopologySequence(_quadratic_motion(np.arange(T) / fps).astype(np.float32),
                                np.array([[0, 1, 2]], np.int32), fps)
    assert seq.upsampled(1) is seq
    for playback, frames in (("loop", T * n), ("clamp", (T - 1) * n + 1), ("pingpong", (T - 1) * n + 1)):
        up = seq.upsampled(n, playback)
        assert (up.num_frames, up.fps) == (frames, fps * n)
        np.testing.assert_array_equal(up.V[::n][:T], seq.V)  # the input's frames, unchanged
        np.testing.assert_array_equal(up.F, seq.F)
        # the intervals whose four neighbours are input frames (1 -> 2 ... T-3 -> T-2): exact
        inner = slice(n, (T - 2) * n + 1)
        exact = _quadratic_motion(np.arange(frames)[inner] / (fps * n))
        np.testing.assert_allclose(up.V[inner], exact, atol=2e-6)
    # pingpong reflects its ends: the motion turns with velocity 0 there (C1 through the turn)
    fine = 100  # the velocity over the first 1 % of the interval, against the one at frame 1
    up = seq.upsampled(fine, "pingpong")
    v_end = np.abs(up.V[1] - up.V[0]).max() * fps * fine
    v_next = np.abs(up.V[fine + 1] - up.V[fine]).max() * fps * fine
    assert v_end < 0.05 * v_next
    up = seq.upsampled(fine, "clamp")  # clamp takes the end frame as its own neighbour: half the chord
    assert np.abs(up.V[1] - up.V[0]).max() * fps * fine > 0.3 * v_next
    # loop: a point turning once around a circle over the loop; every interval, the seam's too,
    # is the first one turned (the wrap's neighbours come from across it)
    ang = 2 * np.pi * np.arange(T) / T
    ring = np.stack([np.stack([np.cos(ang + a), np.sin(ang + a), np.zeros(T)], -1) for a in (0.0, 2.0, 4.0)], 1)
    up = FixedTopologySequence(ring.astype(np.float32), np.array([[0, 1, 2]], np.int32), fps).upsampled(n, "loop")
    first = up.V[:n].astype(np.float64)
    for k in range(T):
        c, s = np.cos(ang[k]), np.sin(ang[k])
        turned = first @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        np.testing.assert_allclose(up.V[k * n:(k + 1) * n], turned, atol=2e-6)
    with pytest.raises(ValueError, match="factor"):
        seq.upsampled(0)
    with pytest.raises(ValueError, match="playback"):
        seq.upsampled(2, "bounce")


def test_a_gltf_input_saved_as_npz_or_glb_reads_back_the_same_way_up(tmp_path):
    """glTF is +Y up, so ``surface.up_axis: auto`` turns it; a sequence loaded from one keeps
    those coordinates, and its npz or .glb used to be read back unturned (a new user's converted
    glTF lay on its side: frame 0's extent (0.92, 0.59, 0.10) became (0.92, 0.10, 0.59)). The npz
    now says ``up_axis: y`` and the .glb is written as +Y up, so the scene is the same from each;
    data made in memory (z-up) reads back unturned as before; a frames folder warns."""
    from test_gltf_animation import _sliding_bar

    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.io import stored_up_axis
    from dynmesh_warp.scene import load_surface

    b = _sliding_bar()
    b.doc["asset"]["generator"] = "SomeExporter 1.0"
    src = tmp_path / "bar.glb"
    src.write_bytes(b.glb())
    seq = load_sequence(src)
    save_sequence(seq, tmp_path / "bar.npz")
    save_sequence(seq, tmp_path / "back.glb")
    with pytest.warns(UserWarning, match=r"its coordinates are \+Y up, .* surface.up_axis: y"):
        save_sequence(seq, tmp_path / "frames", fmt="obj")

    def scene_V(path, **surface):
        return load_surface(load_scene_config(data={"surface": {"source": str(path), "orientation": "keep",
                                                                **surface}})).V

    ref = scene_V(src)
    assert np.ptp(ref[0][:, 2]) > np.ptp(ref[0][:, 1])  # the bar's +Y extent is now up (z)
    for out in ("bar.npz", "back.glb"):
        assert stored_up_axis(tmp_path / out) == "y"
        np.testing.assert_allclose(scene_V(tmp_path / out), ref, atol=1e-6)
    np.testing.assert_allclose(scene_V(tmp_path / "frames", up_axis="y"), ref, atol=1e-6)
    zup = fixed_seq()  # made in memory: this project's z-up world, read back unturned
    save_sequence(zup, tmp_path / "z.npz")
    save_sequence(zup, tmp_path / "z.glb")
    assert stored_up_axis(tmp_path / "z.npz") == "z" and stored_up_axis(tmp_path / "z.glb") == "z"
    np.testing.assert_allclose(scene_V(tmp_path / "z.glb"), scene_V(tmp_path / "z.npz"), atol=1e-6)
    # a scene's surface (turned to z-up) says so: saved, it reads back unturned, and it is not
    # turned twice when given to a scene again
    from dynmesh_warp.scene import prepare_surface

    cfg = load_scene_config(data={"surface": {"source": str(src), "orientation": "keep"}})
    surf = load_surface(cfg)
    assert surf.up_axis == "z" and seq.up_axis is None
    np.testing.assert_allclose(prepare_surface(surf, cfg).V, ref, atol=1e-6)
    save_sequence(surf, tmp_path / "scene.npz")
    np.testing.assert_allclose(scene_V(tmp_path / "scene.npz"), ref, atol=1e-6)
    with pytest.raises(MeshDataError, match="up_axis must be 'y', 'z' or None"):
        FixedTopologySequence(seq.V, seq.F, up_axis="Y")
