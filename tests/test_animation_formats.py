"""Single-file animations (.anime, .pc2, .mdd; docs/data.md): files written here with ``struct``
from each format's spec, independently of the package's writers, read back exactly; the writers
round-trip; every bad file is an error naming it."""

from __future__ import annotations

import struct
import textwrap

import numpy as np
import pytest

from dynmesh_warp.io import load_sequence, read_mesh, save_sequence, write_mesh
from dynmesh_warp.outputs import OutputExistsError
from dynmesh_warp.sequence import FixedTopologySequence, MeshDataError

# a tetrahedron whose vertices move differently each frame
F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int64)
V0 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
T = 5
V = np.stack([V0 + 0.1 * t * np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, -1]]) + [0.5 * t, 0, 0]
              for t in range(T)]).astype(np.float32)


def _anime_bytes(V, F) -> bytes:  # DeformingThings4D: little-endian int32 nf, nv, nt; v0; faces; offsets
    nf, nv = V.shape[:2]
    out = struct.pack("<3i", nf, nv, len(F))
    out += struct.pack(f"<{3 * nv}f", *V[0].ravel())
    out += struct.pack(f"<{3 * len(F)}i", *F.ravel())
    for t in range(1, nf):
        out += struct.pack(f"<{3 * nv}f", *(V[t] - V[0]).ravel())
    return out


def _pc2_bytes(V) -> bytes:  # header <12siiffi, then little-endian float32 samples
    nf, nv = V.shape[:2]
    out = struct.pack("<12siiffi", b"POINTCACHE2\0", 1, nv, 1.0, 1.0, nf)
    return out + struct.pack(f"<{V.size}f", *V.ravel())


def _mdd_bytes(V, fps, rest=None) -> bytes:  # big-endian int32 frames, points; times [s]; frames
    nf, nv = V.shape[:2]
    out = struct.pack(">2i", nf, nv) + struct.pack(f">{nf}f", *[t / fps for t in range(nf)])
    if rest is not None:  # old Blender exporters: an uncounted rest pose first
        out += struct.pack(f">{rest.size}f", *rest.ravel())
    return out + struct.pack(f">{V.size}f", *V.ravel())


def test_anime_written_from_the_spec_reads_exactly(tmp_path):
    p = tmp_path / "bear_run.anime"
    p.write_bytes(_anime_bytes(V, F))
    seq = load_sequence(p)
    assert isinstance(seq, FixedTopologySequence) and seq.name == "bear_run" and seq.fps == 24.0
    np.testing.assert_array_equal(seq.F, F)
    # frame t = frame 0 + offset in float32, as the dataset's own loaders compute it
    np.testing.assert_allclose(seq.V, V, atol=1e-6)
    assert load_sequence(p, fps=30).fps == 30


@pytest.mark.parametrize("ext", [".pc2", ".mdd"])
def test_point_cache_takes_its_faces_from_the_mesh_next_to_it(tmp_path, ext):
    p = tmp_path / f"walk{ext}"
    p.write_bytes(_pc2_bytes(V) if ext == ".pc2" else _mdd_bytes(V, fps=30.0))
    write_mesh(tmp_path / "walk.ply", V0 * 7, F)  # the rest mesh: its positions are not used
    seq = load_sequence(p)
    np.testing.assert_array_equal(seq.V, V)
    np.testing.assert_array_equal(seq.F, F)
    assert seq.fps == (24.0 if ext == ".pc2" else 30.0)  # MDD: from its frame times


def test_mdd_with_an_uncounted_rest_pose_skips_it(tmp_path):
    p = tmp_path / "old.mdd"
    p.write_bytes(_mdd_bytes(V, fps=25.0, rest=V0.astype(np.float32) * 3))
    write_mesh(tmp_path / "old.obj", V0, F)
    seq = load_sequence(p)
    np.testing.assert_array_equal(seq.V, V)
    assert seq.fps == 25.0


def test_point_cache_topology_named_explicitly_and_from_a_scene(tmp_path):
    (tmp_path / "cache").mkdir()
    p = tmp_path / "cache" / "take1.pc2"
    p.write_bytes(_pc2_bytes(V))
    write_mesh(tmp_path / "body.obj", V0, F)
    with pytest.raises(MeshDataError, match=r"take1\.pc2: .*point cache holds vertex positions only.*topology"):
        load_sequence(p)
    seq = load_sequence(p, topology=tmp_path / "body.obj")
    np.testing.assert_array_equal(seq.V, V)

    from dynmesh_warp.config import load_scene_config as load_config
    from dynmesh_warp.scene import load_surface

    scene = tmp_path / "s.yaml"
    scene.write_text(textwrap.dedent("""
        surface: {source: cache/take1.pc2, topology: body.obj, up_axis: z}
        spheres: [{position: [0, 0, 2]}]
    """))
    cfg = load_config(scene)
    assert cfg.resolve(cfg.surface.topology) in cfg.inputs()
    surf = load_surface(cfg)
    np.testing.assert_allclose(surf.V, V, atol=1e-6)
    scene.write_text("surface: {source: cache/take1.pc2, topology: nobody.obj}\n")
    with pytest.raises(ValueError, match=r"surface.topology: file not found: .*nobody\.obj"):
        load_config(scene)
    scene.write_text("surface: {source: 'builtin:wave_bowl', topology: body.obj}\n")
    with pytest.raises(ValueError, match=r"surface.topology: only for a vertex-only source"):
        load_config(scene)
    scene.write_text("surface: {source: cache/take1.pc2, topology: cache}\n")  # a folder: it said "file not found"
    with pytest.raises(ValueError, match=r"surface.topology: a folder, not a file"):
        load_config(scene)

    # convert's --topology (its error told a command-line user of options only the library and scenes have)
    from dynmesh_warp import convert

    out = tmp_path / "fixed.npz"
    assert convert.main([str(p), str(out), "--device", "cpu", "--no-progress"]) == 2
    assert convert.main([str(p), str(out), "--topology", str(tmp_path / "body.obj"), "--device", "cpu",
                         "--no-progress", "--option", "key_candidates=0"]) == 0
    res = load_sequence(out)
    assert res.num_frames == len(V) and res.num_vertices == V.shape[1]
    assert convert.main([str(tmp_path / "body.obj"), str(tmp_path / "x.npz"), "--topology", str(tmp_path / "body.obj")]) == 2
    # the --topology mesh is an input: a point-cache output whose faces file it is, is refused even with --overwrite
    body = (tmp_path / "body.obj").read_bytes()
    assert convert.main([str(p), str(tmp_path / "body.pc2"), "--topology", str(tmp_path / "body.obj"), "--overwrite",
                         "--device", "cpu", "--no-progress"]) == 2
    assert (tmp_path / "body.obj").read_bytes() == body and not (tmp_path / "body.pc2").exists()


@pytest.mark.parametrize("ext", [".anime", ".pc2", ".mdd"])
def test_writers_round_trip_and_match_the_spec(tmp_path, ext):
    seq = FixedTopologySequence(V, F, fps=30.0, name="tet")
    p = tmp_path / f"tet{ext}"
    save_sequence(seq, p)
    back = load_sequence(p)
    np.testing.assert_allclose(back.V, V, atol=1e-6)
    np.testing.assert_array_equal(back.F, F)
    if ext == ".pc2":
        assert p.read_bytes() == struct.pack("<12siiffi", b"POINTCACHE2\0", 1, 4, 0.0, 1.0, T) + V.astype("<f4").tobytes()
    elif ext == ".mdd":
        assert p.read_bytes() == _mdd_bytes(V, fps=30.0) and back.fps == 30.0
    else:
        assert p.read_bytes() == _anime_bytes(V, F)
    if ext != ".anime":  # the faces went next to the cache
        Vm, Fm = read_mesh(tmp_path / "tet.obj")
        np.testing.assert_array_equal(Fm, F)
        np.testing.assert_allclose(Vm, V[0], atol=1e-6)


def test_cache_writer_never_replaces_a_foreign_mesh(tmp_path):
    seq = FixedTopologySequence(V, F, fps=24.0, name="tet")
    write_mesh(tmp_path / "tet.obj", V0, F[:3])  # someone's mesh, other faces
    before = (tmp_path / "tet.obj").read_bytes()
    with pytest.raises(OutputExistsError, match=r"tet\.obj: exists and is not the topology"):
        save_sequence(seq, tmp_path / "tet.pc2")
    assert (tmp_path / "tet.obj").read_bytes() == before and not (tmp_path / "tet.pc2").exists()
    write_mesh(tmp_path / "tet.obj", V0 * 2, F)  # the same faces: kept as it is, the cache written
    before = (tmp_path / "tet.obj").read_bytes()
    save_sequence(seq, tmp_path / "tet.pc2")
    assert (tmp_path / "tet.obj").read_bytes() == before
    np.testing.assert_array_equal(load_sequence(tmp_path / "tet.pc2").V, V)


def test_a_cache_beside_another_animation_of_the_same_stem_reads(tmp_path):
    """save_sequence to walk.mdd (its faces in walk.obj) and then to walk.glb beside it: both
    meshes have the cache's vertex count; the cache takes its writer's walk.obj (it was refused
    as ambiguous), and the .glb reads as itself."""
    seq = FixedTopologySequence(V.astype(np.float32), F, fps=24.0)
    save_sequence(seq, tmp_path / "walk.mdd")
    save_sequence(seq, tmp_path / "walk.glb")
    for name in ("walk.mdd", "walk.glb"):
        got = load_sequence(tmp_path / name)
        np.testing.assert_allclose(got.V, V, atol=1e-6)
        np.testing.assert_array_equal(got.F, F)


def test_varying_sequence_cannot_be_saved_as_one_animation(tmp_path):
    var = FixedTopologySequence(V, F, fps=24.0).to_varying()
    var.frames[1] = (V[1][:3], F[:1])
    with pytest.raises(ValueError, match=r"topology varies \(convert it first"):
        save_sequence(var, tmp_path / "x.anime")


def test_bad_files_name_the_file_and_what_disagrees(tmp_path):
    good = _anime_bytes(V, F)
    cases = {
        "short.anime": (good[:-4], r"short\.anime: header: 5 frames x 4 vertices, 4 faces make .* \(truncated\)"),
        "long.anime": (good + b"\0" * 8, r"long\.anime: .*extra data after the last frame"),
        "huge.anime": (struct.pack("<3i", 10**9, 10**9, 4) + good[12:],
                       r"huge\.anime: header: 1000000000 frames x 1000000000 vertices.*truncated"),
        "neg.anime": (struct.pack("<3i", 5, -4, 4) + good[12:], r"neg\.anime: header: vertices = -4"),
        "tiny.anime": (b"\1\0", r"tiny\.anime: 2 bytes: too short"),
        "magic.pc2": (b"POINTCACHE3" + _pc2_bytes(V)[11:], r"magic\.pc2: not a PC2 point cache"),
        "cut.pc2": (_pc2_bytes(V)[:-1], r"cut\.pc2: header: 5 samples x 4 points make 272 bytes, but the file has 271"),
        "cut.mdd": (_mdd_bytes(V, 24.0)[:-12], r"cut\.mdd: header: 5 frames x 4 points .* \(truncated\)"),
    }
    write_mesh(tmp_path / "cut.obj", V0, F)
    write_mesh(tmp_path / "magic.obj", V0, F)
    for name, (data, msg) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(MeshDataError, match=msg):
            load_sequence(tmp_path / name)
    # a cache and a mesh of another vertex count
    (tmp_path / "other.pc2").write_bytes(_pc2_bytes(V))
    write_mesh(tmp_path / "other.obj", np.vstack([V0, V0 + 2]), np.vstack([F, F + 4]))
    with pytest.raises(MeshDataError, match=r"other\.pc2: 4 points a frame, but its topology .*other\.obj has 8"):
        load_sequence(tmp_path / "other.pc2")
    # several candidate meshes: the one with the cache's vertex count gives the faces; several
    # such (none the <stem>.obj a cache writer writes) are an error naming them
    write_mesh(tmp_path / "other.ply", V0, F[:, ::-1])
    np.testing.assert_array_equal(load_sequence(tmp_path / "other.pc2").F, F[:, ::-1])
    write_mesh(tmp_path / "other.off", V0, F)
    with pytest.raises(MeshDataError, match=r"several meshes could give its faces \(other\.off, other\.ply\)"):
        load_sequence(tmp_path / "other.pc2")
    # topology= where it does not apply
    (tmp_path / "ok.anime").write_bytes(good)
    with pytest.raises(MeshDataError, match=r"ok\.anime: an \.anime file holds its own faces"):
        load_sequence(tmp_path / "ok.anime", topology=tmp_path / "cut.obj")
    with pytest.raises(ValueError, match=r"topology= applies to vertex-only files"):
        load_sequence(tmp_path / "cut.obj", topology=tmp_path / "cut.obj")
    # out-of-range face indices in an .anime reach validate_mesh: named, not a crash
    bad_faces = F.copy()
    bad_faces[2, 1] = 9
    (tmp_path / "faces.anime").write_bytes(_anime_bytes(V, bad_faces))
    with pytest.raises(MeshDataError, match=r"faces\.anime.*out of range"):
        load_sequence(tmp_path / "faces.anime")


@pytest.mark.parametrize("name, what", [("take.abc", "Alembic"), ("rig.fbx", "FBX"), ("shot.usdc", "USD")])
def test_unread_animation_formats_say_what_to_export_instead(tmp_path, name, what):
    (tmp_path / name).write_bytes(b"\0" * 64)
    with pytest.raises(MeshDataError, match=rf"{name}: {what} files are not read .* \.pc2 or \.mdd point cache"):
        load_sequence(tmp_path / name)


@pytest.mark.parametrize("name, what", [("walk.abc", "Alembic"), ("rig.fbx", "FBX"), ("m.bvh", "BVH")])
def test_run_and_render_refuse_unread_animation_formats_too(tmp_path, capsys, monkeypatch, name, what):
    """``run`` / ``render`` given an Alembic, FBX, ... file say what ``convert`` says (exit 2):
    they read it as a scene YAML, and an empty ``.abc`` played the built-in default scene with
    exit 0 (a new user's)."""
    from dynmesh_warp.render import main as render_main
    from dynmesh_warp.run import main as run_main

    monkeypatch.chdir(tmp_path)
    (tmp_path / name).write_bytes(b"" if name.endswith(".abc") else b"\xff\0HIERARCHY")
    for argv in ([name, "--device", "cpu", "--viewer", "none", "--steps", "2"],
                 [name, "--device", "cpu", "--figure", "f.png"]):
        main = run_main if "--viewer" in argv else render_main
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"{name}: {what}" in err and "files are not read" in err and "is a mesh sequence" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # nothing written


def test_vertex_only_npz_and_npy_take_faces_from_a_mesh(tmp_path):
    """SMPL / AMASS-style exports: vertices (T, N, 3) in an npz without faces, or a bare .npy."""
    np.savez(tmp_path / "smpl_walk.npz", vertices=V.astype(np.float64), fps=np.float32(30))
    np.save(tmp_path / "cache.npy", V)
    write_mesh(tmp_path / "body.obj", V0, F)
    for name, fps in (("smpl_walk.npz", 30.0), ("cache.npy", 24.0)):
        with pytest.raises(MeshDataError, match=rf"{name}: this file holds vertex positions only.*topology"):
            load_sequence(tmp_path / name)
        seq = load_sequence(tmp_path / name, topology=tmp_path / "body.obj")
        np.testing.assert_allclose(seq.V, V, atol=1e-6)
        np.testing.assert_array_equal(seq.F, F)
        assert seq.fps == fps
    write_mesh(tmp_path / "cache.ply", V0, F)  # the mesh next to it with the same stem
    np.testing.assert_allclose(load_sequence(tmp_path / "cache.npy").V, V, atol=1e-6)
    np.save(tmp_path / "flat.npy", V.reshape(T, -1))  # (T, 3N): not vertices
    with pytest.raises(MeshDataError, match=r"flat\.npy: vertex array of shape \(5, 12\)"):
        load_sequence(tmp_path / "flat.npy", topology=tmp_path / "body.obj")
    # an npz with faces ignores nothing and takes no topology
    np.savez(tmp_path / "full.npz", V=V, F=F)
    with pytest.raises(ValueError, match=r"full\.npz: topology= applies to vertex-only files"):
        load_sequence(tmp_path / "full.npz", topology=tmp_path / "body.obj")
    np.testing.assert_array_equal(load_sequence(tmp_path / "full.npz").V, V)


def test_a_cache_in_the_other_byte_order_reads_with_a_warning(tmp_path):
    """PC2 is little-endian and MDD big-endian by their specs; a cache written in the other byte
    order (its header read so fits the file exactly) reads with a warning saying so. A new user's
    big-endian PC2 was "201326592 samples x 2013265920 points ... (truncated)", without a hint.
    Where the data do not read as numbers either, the error says what the header suggests."""
    be_pc2 = struct.pack(">12siiffi", b"POINTCACHE2\0", 1, 4, 1.0, 1.0, T) + struct.pack(f">{V.size}f", *V.ravel())
    le_mdd = (struct.pack("<2i", T, 4) + struct.pack(f"<{T}f", *[t / 25 for t in range(T)])
              + struct.pack(f"<{V.size}f", *V.ravel()))
    for name, data, fmt, order, spec in [("be.pc2", be_pc2, "PC2", "big", "little"),
                                         ("le.mdd", le_mdd, "MDD", "little", "big")]:
        (tmp_path / name).write_bytes(data)
        write_mesh(tmp_path / name.replace(name[-4:], ".obj"), V0, F)
        with pytest.warns(UserWarning, match=rf"{name[:2]}\.{name[3:]}: read {order}-endian, its header fits the "
                                             rf"file: a {order}-endian {fmt}\? {fmt} is {spec}-endian by its spec"):
            seq = load_sequence(tmp_path / name)
        np.testing.assert_array_equal(seq.V, V)
        np.testing.assert_array_equal(seq.F, F)
        assert seq.fps == (25.0 if fmt == "MDD" else 24.0)
    nan = be_pc2[:32] + b"\xff" * (len(be_pc2) - 32)
    (tmp_path / "nan.pc2").write_bytes(nan)
    write_mesh(tmp_path / "nan.obj", V0, F)
    with pytest.raises(MeshDataError, match=r"nan\.pc2: header: 83886080 samples x 67108864 points make .* "
                                            r"\(truncated\); read big-endian, its header fits the file: a big-endian "
                                            r"PC2\? .* but its data do not read as numbers so"):
        load_sequence(tmp_path / "nan.pc2")
    # one NaN among the numbers is the data's own: read in the other order, the load names its frame
    # and vertex (a new user's was told of a corrupt header instead)
    one = bytearray(be_pc2)
    one[32 + 12 * (4 * 2 + 1) + 4:32 + 12 * (4 * 2 + 1) + 8] = struct.pack(">f", float("nan"))  # frame 2, vertex 1, y
    (tmp_path / "one.pc2").write_bytes(bytes(one))
    write_mesh(tmp_path / "one.obj", V0, F)
    with pytest.warns(UserWarning, match="read big-endian"), \
            pytest.raises(MeshDataError, match=r"one\.pc2, frame 2: 1 vertices have NaN.*first: vertex 1"):
        load_sequence(tmp_path / "one.pc2")


def test_writing_an_animation_says_what_it_cannot_hold(tmp_path):
    """A .pc2 / .anime stores no frame rate (30 fps read back at 24) and an .anime no colours: said
    when written (a new user's were lost unsaid); a .mdd keeps the rate (its frame times)."""
    import warnings

    from dynmesh_warp.io import load_sequence, save_sequence
    from dynmesh_warp.scenes import icosphere
    from dynmesh_warp.sequence import FixedTopologySequence

    V, F = icosphere(1, 0.5)
    seq = FixedTopologySequence(np.stack([V, V + 0.1]), F, fps=30.0, colors=np.full((len(V), 3), 0.5))
    for name, said in (("a.pc2", ["frame rate (30 fps"]), ("b.anime", ["frame rate (30 fps", "vertex colours"]),
                       ("c.mdd", [])):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            save_sequence(seq, tmp_path / name)
        text = " ".join(str(w.message) for w in caught)
        assert all(s in text for s in said) and (bool(said) == ("does not store" in text)), (name, text)
    assert load_sequence(tmp_path / "a.pc2").fps == 24.0 and load_sequence(tmp_path / "c.mdd").fps == 30.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        save_sequence(FixedTopologySequence(seq.V, F, fps=24.0), tmp_path / "d.pc2")  # nothing lost
    assert not any("does not store" in str(w.message) for w in caught)
