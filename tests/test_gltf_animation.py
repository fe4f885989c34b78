"""Animated glTF (docs/data.md, "Animated glTF"): GLB files built here byte by byte from the
glTF 2.0 specification, with motions whose poses are known in closed form (a bone bent about
its joint, a morph target, STEP and CUBICSPLINE channels, a node hierarchy), read back by
``load_sequence``; static poses also against trimesh's own glTF loader; bad files named."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from dynmesh_warp.io import load_sequence
from dynmesh_warp.sequence import MeshDataError


class Builder:
    """A minimal glTF 2.0 writer: arrays appended to one binary buffer, one accessor each."""

    def __init__(self):
        self.blob = b""
        self.doc = {"asset": {"version": "2.0"}, "buffers": [], "bufferViews": [], "accessors": [],
                    "nodes": [], "meshes": [], "scenes": [{"nodes": []}], "scene": 0}

    def add(self, arr, kind: str, ctype: int = 5126) -> int:
        dt = {5126: "<f4", 5125: "<u4", 5123: "<u2", 5121: "<u1"}[ctype]
        a = np.ascontiguousarray(arr, dtype=dt)
        data = a.tobytes()
        self.blob += b"\0" * (-len(self.blob) % 4)
        self.doc["bufferViews"].append({"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)})
        self.blob += data
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[kind]
        acc = {"bufferView": len(self.doc["bufferViews"]) - 1, "componentType": ctype,
               "count": a.size // width, "type": kind}
        if kind == "SCALAR" and ctype == 5126:
            acc["min"], acc["max"] = [float(a.min())], [float(a.max())]
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def glb(self) -> bytes:
        self.blob += b"\0" * (-len(self.blob) % 4)
        self.doc["buffers"] = [{"byteLength": len(self.blob)}]
        js = json.dumps(self.doc).encode()
        js += b" " * (-len(js) % 4)
        body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(self.blob), 0x004E4942) + self.blob
        return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def _rz(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def _quat_z(deg):
    a = np.radians(deg) / 2
    return [0.0, 0.0, np.sin(a), np.cos(a)]


def _bar():
    """A strip of quads along x from 0 to 2 (y = +-0.1): vertices 0..5 at x = 0, 1, 2."""
    P = np.array([[0, -0.1, 0], [0, 0.1, 0], [1, -0.1, 0], [1, 0.1, 0], [2, -0.1, 0], [2, 0.1, 0]], np.float64)
    F = np.array([[0, 2, 1], [1, 2, 3], [2, 4, 3], [3, 4, 5]])
    return P, F


def test_skinned_bone_bends_about_its_joint_as_in_closed_form(tmp_path):
    P, F = _bar()
    b = Builder()
    J = np.array([[0, 0, 0, 0]] * 2 + [[0, 1, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2)
    Wt = np.array([[1, 0, 0, 0]] * 2 + [[0.5, 0.5, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2)
    prim = {"attributes": {"POSITION": b.add(P, "VEC3"), "JOINTS_0": b.add(J, "VEC4", 5123),
                           "WEIGHTS_0": b.add(Wt, "VEC4")}, "indices": b.add(F.ravel(), "SCALAR", 5125)}
    b.doc["meshes"] = [{"primitives": [prim]}]
    ibm = np.stack([np.eye(4), np.eye(4)])
    ibm[1, 0, 3] = -1.0  # joint 1 sits at x = 1 in the bind pose
    b.doc["skins"] = [{"joints": [1, 2], "inverseBindMatrices": b.add(ibm.transpose(0, 2, 1), "MAT4")}]
    b.doc["nodes"] = [{"mesh": 0, "skin": 0, "translation": [5, 0, 0]},  # ignored for a skinned mesh
                      {"children": [2]}, {"translation": [1, 0, 0]}]
    b.doc["scenes"][0]["nodes"] = [0, 1]
    times = b.add([0.0, 1.0], "SCALAR")
    rot = b.add([_quat_z(0), _quat_z(90)], "VEC4")
    b.doc["animations"] = [{"channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}],
                            "samplers": [{"input": times, "output": rot, "interpolation": "LINEAR"}]}]
    (tmp_path / "bone.glb").write_bytes(b.glb())
    seq = load_sequence(tmp_path / "bone.glb", fps=4)
    assert seq.V.shape == (5, 6, 3) and seq.fps == 4
    np.testing.assert_array_equal(seq.F, F)
    for f in range(5):
        R = _rz(90 * f / 4)  # slerp between 0 and 90 degrees about one axis: the angle is linear
        bent = (P - [1, 0, 0]) @ R.T + [1, 0, 0]
        want = np.r_[P[:2], 0.5 * (P[2:4] + bent[2:4]), bent[4:]]
        np.testing.assert_allclose(seq.V[f], want, atol=1e-6)


def test_morph_target_and_step_translation(tmp_path):
    b = Builder()
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    D = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 1.0]])
    b.doc["meshes"] = [{"primitives": [{"attributes": {"POSITION": b.add(P, "VEC3")},
                                         "targets": [{"POSITION": b.add(D, "VEC3")}]}], "weights": [0.0]}]
    b.doc["nodes"] = [{"mesh": 0}]
    b.doc["scenes"][0]["nodes"] = [0]
    tw = b.add([0.0, 1.0], "SCALAR")
    ts = b.add([0.0, 0.5], "SCALAR")
    b.doc["animations"] = [{"name": "go", "channels": [
        {"sampler": 0, "target": {"node": 0, "path": "weights"}},
        {"sampler": 1, "target": {"node": 0, "path": "translation"}}], "samplers": [
        {"input": tw, "output": b.add([0.0, 1.0], "SCALAR")},
        {"input": ts, "output": b.add([[0, 0, 0], [0, 2, 0]], "VEC3"), "interpolation": "STEP"}]}]
    (tmp_path / "m.glb").write_bytes(b.glb())
    seq = load_sequence(tmp_path / "m.glb")
    assert seq.fps == 2.0 and seq.num_frames == 3  # keyframes 0.5 s apart: 2 frames/s
    for f, t in enumerate([0.0, 0.5, 1.0]):
        want = P + t * D + (np.array([0, 2, 0]) if t >= 0.5 else 0)
        np.testing.assert_allclose(seq.V[f], want, atol=1e-6)


def test_cubicspline_translation_follows_the_hermite_curve(tmp_path):
    b = Builder()
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    b.doc["meshes"] = [{"primitives": [{"attributes": {"POSITION": b.add(P, "VEC3")}, "mode": 4}]}]
    b.doc["nodes"] = [{"mesh": 0}]
    b.doc["scenes"][0]["nodes"] = [0]
    p0, p1 = np.array([0.0, 0, 0]), np.array([2.0, 1, 0])
    a0, b0 = np.array([9.0, 9, 9]), np.array([1.0, 0, 3])  # in-tangent (unused at the start), out-tangent
    a1, b1 = np.array([0.0, -2, 1]), np.array([7.0, 7, 7])
    out = b.add([a0, p0, b0, a1, p1, b1], "VEC3")
    b.doc["animations"] = [{"channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
                            "samplers": [{"input": b.add([0.0, 2.0], "SCALAR"), "output": out,
                                          "interpolation": "CUBICSPLINE"}]}]
    (tmp_path / "c.glb").write_bytes(b.glb())
    seq = load_sequence(tmp_path / "c.glb", fps=10)
    assert seq.num_frames == 21
    for f in range(21):
        u, td = f / 20, 2.0
        h = ((2 * u**3 - 3 * u**2 + 1) * p0 + (u**3 - 2 * u**2 + u) * td * b0 + (-2 * u**3 + 3 * u**2) * p1
             + (u**3 - u**2) * td * a1)
        np.testing.assert_allclose(seq.V[f], P + h, atol=1e-5)


def test_node_hierarchy_matches_trimesh_at_rest(tmp_path):
    """Nested nodes with matrix and TRS transforms and an animation that holds still: every frame
    equals trimesh's static reading of the scene."""
    trimesh = pytest.importorskip("trimesh")
    P, F = _bar()
    b = Builder()
    b.doc["meshes"] = [{"primitives": [{"attributes": {"POSITION": b.add(P, "VEC3")},
                                         "indices": b.add(F.ravel(), "SCALAR", 5125)}]}]
    M = np.eye(4)
    M[:3, :3] = _rz(30) * 2.0
    M[:3, 3] = [0.5, -1, 2]
    b.doc["nodes"] = [{"matrix": M.T.ravel().tolist(), "children": [1]},
                      {"translation": [0, 0, 1], "rotation": _quat_z(-45), "scale": [1, 3, 1], "children": [2]},
                      {"mesh": 0, "translation": [1, 1, 1]}]
    b.doc["scenes"][0]["nodes"] = [0]
    b.doc["animations"] = [{"channels": [{"sampler": 0, "target": {"node": 2, "path": "translation"}}],
                            "samplers": [{"input": b.add([0.0, 1.0], "SCALAR"),
                                          "output": b.add([[1, 1, 1], [1, 1, 1]], "VEC3")}]}]
    data = b.glb()
    (tmp_path / "h.glb").write_bytes(data)
    seq = load_sequence(tmp_path / "h.glb")
    scene = trimesh.load(tmp_path / "h.glb", force="scene", process=False)
    ref = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)  # trimesh < 4.6
    order = np.lexsort(np.asarray(ref.vertices).T)  # trimesh may reorder; compare as sets
    for f in range(seq.num_frames):
        got = seq.V[f][np.lexsort(seq.V[f].T)]
        np.testing.assert_allclose(got, np.asarray(ref.vertices)[order], atol=1e-5)


def test_static_glb_still_reads_as_one_mesh(tmp_path):
    b = Builder()
    P, F = _bar()
    b.doc["meshes"] = [{"primitives": [{"attributes": {"POSITION": b.add(P, "VEC3")},
                                         "indices": b.add(F.ravel(), "SCALAR", 5125)}]}]
    b.doc["nodes"] = [{"mesh": 0}]
    b.doc["scenes"][0]["nodes"] = [0]
    (tmp_path / "s.glb").write_bytes(b.glb())
    seq = load_sequence(tmp_path / "s.glb")
    assert seq.num_frames == 1
    np.testing.assert_allclose(seq.V[0], P, atol=1e-6)


def test_a_static_skinned_glb_reads_as_its_animated_frame_0_and_node_transforms_apply(tmp_path):
    """A file without animations is read by the glTF reader's own rules (the scene as its nodes
    and skins stand), not through trimesh: a skinned mesh's own node transform is not applied
    (the specification; a new user's static skinned file sat 5 m off the same file's animated
    frame 0 through trimesh), and an unskinned node's transform is (closed form)."""
    P, F = _bar()

    def bone(animated: bool) -> bytes:
        b = Builder()
        J = np.array([[0, 0, 0, 0]] * 6)
        Wt = np.array([[1, 0, 0, 0]] * 6)
        prim = {"attributes": {"POSITION": b.add(P, "VEC3"), "JOINTS_0": b.add(J, "VEC4", 5123),
                               "WEIGHTS_0": b.add(Wt, "VEC4")}, "indices": b.add(F.ravel(), "SCALAR", 5125)}
        b.doc["meshes"] = [{"primitives": [prim]}, {"primitives": [{"attributes": {"POSITION": b.add(P, "VEC3")},
                                                                     "indices": b.add(F.ravel(), "SCALAR", 5125)}]}]
        b.doc["skins"] = [{"joints": [1]}]
        b.doc["nodes"] = [{"mesh": 0, "skin": 0, "translation": [5, 5, 5]},  # ignored: a skinned mesh
                          {"translation": [0, 0, 1]},  # the joint lifts the skinned bar by 1
                          {"mesh": 1, "translation": [0, 3, 0], "rotation": _quat_z(90)}]
        b.doc["scenes"][0]["nodes"] = [0, 1, 2]
        if animated:
            b.doc["animations"] = [{"channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}],
                                    "samplers": [{"input": b.add([0.0, 1.0], "SCALAR"),
                                                  "output": b.add([[0, 0, 1], [0, 0, 2]], "VEC3")}]}]
        return b.glb()

    (tmp_path / "static.glb").write_bytes(bone(False))
    (tmp_path / "anim.glb").write_bytes(bone(True))
    static, anim = load_sequence(tmp_path / "static.glb"), load_sequence(tmp_path / "anim.glb")
    want = np.r_[P + [0, 0, 1], P @ _rz(90).T + [0, 3, 0]]
    assert static.num_frames == 1
    np.testing.assert_allclose(static.V[0], want, atol=1e-6)
    np.testing.assert_allclose(anim.V[0], want, atol=1e-6)
    np.testing.assert_array_equal(static.F, anim.F)


def _sliding_bar() -> "Builder":
    """The bar as one node translated by 1 along x over a second (a LINEAR channel)."""
    b = Builder()
    P, F = _bar()
    b.doc["meshes"] = [{"primitives": [{"attributes": {"POSITION": b.add(P, "VEC3")}}]}]
    b.doc["nodes"] = [{"mesh": 0}]
    b.doc["scenes"][0]["nodes"] = [0]
    b.doc["animations"] = [{"channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
                            "samplers": [{"input": b.add([0.0, 1.0], "SCALAR"),
                                          "output": b.add([[0, 0, 0], [1, 0, 0]], "VEC3")}]}]
    return b


def test_bad_gltf_files_name_the_file_and_the_problem(tmp_path):
    b = _sliding_bar()
    good = b.glb()
    (tmp_path / "cut.glb").write_bytes(good[:-40])
    with pytest.raises(MeshDataError, match=r"cut\.glb: GLB header says .* bytes, but the file has .* \(truncated\)"):
        load_sequence(tmp_path / "cut.glb")
    b.doc["accessors"][0]["count"] = 1000  # reaches past its buffer view
    (tmp_path / "acc.glb").write_bytes(b.glb())
    with pytest.raises(MeshDataError, match=r"acc\.glb: accessor 0 \(1000 x VEC3\) reaches byte"):
        load_sequence(tmp_path / "acc.glb")
    b.doc["accessors"][0]["count"] = 6
    b.doc["extensionsRequired"] = ["KHR_draco_mesh_compression"]
    (tmp_path / "draco.glb").write_bytes(b.glb())
    with pytest.raises(MeshDataError, match=r"draco\.glb: requires KHR_draco_mesh_compression"):
        load_sequence(tmp_path / "draco.glb")
    del b.doc["extensionsRequired"]
    b.doc["accessors"][0]["sparse"] = {"count": 1}
    (tmp_path / "sparse.glb").write_bytes(b.glb())
    with pytest.raises(MeshDataError, match=r"sparse\.glb: accessor 0 is sparse"):
        load_sequence(tmp_path / "sparse.glb")
    del b.doc["accessors"][0]["sparse"]
    b.doc["meshes"][0]["primitives"][0]["mode"] = 1  # lines only
    (tmp_path / "lines.glb").write_bytes(b.glb())
    with pytest.raises(MeshDataError, match=r"lines\.glb: its scene has no triangle mesh"):
        load_sequence(tmp_path / "lines.glb")


def test_interleaved_strided_buffer_view_and_normalized_weights(tmp_path):
    """Exporters interleave attributes in one buffer view (byteStride) and store weights as
    normalized bytes: both read as the specification says."""
    P, F = _bar()
    b = Builder()
    inter = np.zeros((len(P), 5), np.float32)  # position (3 floats) + 2 floats of something else
    inter[:, :3] = P
    inter[:, 3:] = 7.0
    view = b.add(inter, "VEC3")  # a placeholder accessor, rewired below
    b.doc["bufferViews"][view]["byteStride"] = 20
    b.doc["accessors"][view].update(count=len(P), type="VEC3")
    J = np.zeros((len(P), 4), np.uint8)
    W = np.zeros((len(P), 4), np.uint8)
    W[:, 0] = 255  # 1.0 as a normalized unsigned byte
    b.doc["meshes"] = [{"primitives": [{"attributes": {"POSITION": view, "JOINTS_0": b.add(J, "VEC4", 5121),
                                                       "WEIGHTS_0": b.add(W, "VEC4", 5121)},
                                        "indices": b.add(F.ravel(), "SCALAR", 5125)}]}]
    b.doc["accessors"][-2]["normalized"] = True
    b.doc["skins"] = [{"joints": [1]}]
    b.doc["nodes"] = [{"mesh": 0, "skin": 0}, {}]
    b.doc["scenes"][0]["nodes"] = [0, 1]
    b.doc["animations"] = [{"channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}],
                            "samplers": [{"input": b.add([0.0, 1.0], "SCALAR"),
                                          "output": b.add([[0, 0, 0], [0, 0, 3]], "VEC3")}]}]
    (tmp_path / "i.glb").write_bytes(b.glb())
    seq = load_sequence(tmp_path / "i.glb", fps=2)
    for f, t in enumerate([0.0, 0.5, 1.0]):
        np.testing.assert_allclose(seq.V[f], P + [0, 0, 3 * t], atol=1e-6)


def test_an_animation_is_picked_by_name_or_index_also_from_a_scene(tmp_path):
    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.scene import load_surface

    b = Builder()
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    b.doc["meshes"] = [{"primitives": [{"attributes": {"POSITION": b.add(P, "VEC3")}}]}]
    b.doc["nodes"] = [{"mesh": 0}]
    b.doc["scenes"][0]["nodes"] = [0]
    t = b.add([0.0, 1.0], "SCALAR")
    b.doc["animations"] = [
        {"name": name, "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
         "samplers": [{"input": t, "output": b.add([[0, 0, 0], [d, 0, 0]], "VEC3")}]}
        for name, d in (("Walk", 1.0), ("Run", 5.0))]
    (tmp_path / "fox.glb").write_bytes(b.glb())
    for pick, d in ((None, 1.0), ("Run", 5.0), (0, 1.0), (1, 5.0)):
        seq = load_sequence(tmp_path / "fox.glb", fps=1, animation=pick)
        np.testing.assert_allclose(seq.V[-1], P + [d, 0, 0], atol=1e-6)
    with pytest.raises(MeshDataError, match=r"fox\.glb: no animation named 'Fly'; it has \['Walk', 'Run'\]"):
        load_sequence(tmp_path / "fox.glb", animation="Fly")
    scene = tmp_path / "s.yaml"
    scene.write_text("surface: {source: fox.glb, animation: Run, fps: 1, up_axis: z}\n")
    np.testing.assert_allclose(load_surface(load_scene_config(scene)).V[-1], P + [5, 0, 0], atol=1e-6)
    # up_axis auto (the default): glTF is +Y up by its specification, so it is turned z-up,
    # (x, y, z) -> (x, -z, y); other formats stay as they are
    scene.write_text("surface: {source: fox.glb, animation: Run, fps: 1}\n")
    Q = P + [5, 0, 0]
    np.testing.assert_allclose(load_surface(load_scene_config(scene)).V[-1], np.c_[Q[:, 0], -Q[:, 2], Q[:, 1]],
                               atol=1e-6)
    np.savez(tmp_path / "fox_faces.npz", V=P[None], F=np.array([[0, 1, 2]]))
    scene.write_text("surface: {source: fox_faces.npz}\n")
    np.testing.assert_allclose(load_surface(load_scene_config(scene)).V[-1], P, atol=1e-6)
    # a .glb this project wrote (convert's output) holds its input's coordinates unturned: auto
    # reads it back as it was written, so `run in.npz` and `run out.glb` agree
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.sequence import FixedTopologySequence

    save_sequence(FixedTopologySequence(np.stack([P, P + [0, 0, 1]]).astype(np.float32), np.array([[0, 1, 2]]),
                                        fps=24.0), tmp_path / "ours.glb")
    scene.write_text("surface: {source: ours.glb}\n")
    np.testing.assert_allclose(load_surface(load_scene_config(scene)).V[-1], P + [0, 0, 1], atol=1e-6)
    scene.write_text("surface: {source: 'builtin:wave_bowl', animation: Run}\n")
    with pytest.raises(ValueError, match=r"surface\.animation: only for an animated \.glb / \.gltf source"):
        load_scene_config(scene)
    np.save(tmp_path / "x.npy", P[None])
    with pytest.raises(ValueError, match=r"animation= picks one animation of an animated \.glb"):
        load_sequence(tmp_path / "x.npy", animation="Run")


def test_sequence_written_as_an_animated_glb_reads_back_and_blends_like_the_physics(tmp_path):
    """save_sequence(seq, "x.glb"): frame 0 is the mesh, each later frame a morph target whose
    weight is 1 at its own time (LINEAR): read back at the frame rate it is the sequence; at
    twice the rate the frames in between are the midpoints, as the physics blends frames."""
    trimesh = pytest.importorskip("trimesh")
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.sequence import FixedTopologySequence

    P, F = _bar()
    T = 6
    rng = np.random.default_rng(0)
    V = (P[None] + rng.normal(size=(T, len(P), 3)) * 0.1).astype(np.float32)
    seq = FixedTopologySequence(V, F, fps=12.0, name="bar")
    save_sequence(seq, tmp_path / "bar.glb")
    back = load_sequence(tmp_path / "bar.glb")
    assert back.fps == 12.0 and back.num_frames == T
    np.testing.assert_array_equal(back.F, F)
    np.testing.assert_allclose(back.V, V, atol=1e-6)
    fine = load_sequence(tmp_path / "bar.glb", fps=24.0)
    assert fine.num_frames == 2 * T - 1
    np.testing.assert_allclose(fine.V[1::2], 0.5 * (V[:-1] + V[1:]), atol=1e-6)
    scene = trimesh.load(tmp_path / "bar.glb", force="scene", process=False)  # another reader: frame 0,
    ref = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)
    # +Y up as glTF says (the z-up data turned, (x, y, z) -> (x, z, -y)): upright in a glTF viewer
    np.testing.assert_allclose(np.asarray(ref.vertices), V[0][:, [0, 2, 1]] * [1, 1, -1], atol=1e-6)
    with pytest.raises(ValueError, match=r"topology varies \(convert it first"):
        var = seq.to_varying()
        var.frames[1] = (V[1][:3], F[:1])
        save_sequence(var, tmp_path / "v.glb")


def test_the_up_axis_and_animation_checks_read_only_the_json_chunk(tmp_path, monkeypatch):
    """``up_axis: auto`` (asset.generator) and the animated-or-static choice read a .glb's JSON
    chunk, not its whole file: a large capture is read once, by the loader. A file cut inside its
    binary buffer still answers them, and the loader names the truncation; a .gltf answers too."""
    from dynmesh_warp import gltf_animation as ga

    b = _sliding_bar()
    b.doc["asset"]["generator"] = "SomeExporter 1.0"
    cut = tmp_path / "cut.glb"
    cut.write_bytes(b.glb()[:-40])
    monkeypatch.setattr(ga._File, "__init__", lambda *a, **k: pytest.fail("read the whole file"))
    assert ga.gltf_generator(cut) == "SomeExporter 1.0"
    assert ga.gltf_has_animation(cut)
    monkeypatch.undo()
    with pytest.raises(MeshDataError, match=r"cut\.glb: GLB header says .* bytes, but the file has .* \(truncated\)"):
        load_sequence(cut)
    static = tmp_path / "static.gltf"
    static.write_text(json.dumps({"asset": {"version": "2.0"}}))
    assert not ga.gltf_has_animation(static) and ga.gltf_generator(static) == ""
    (tmp_path / "bad.glb").write_bytes(b"glTF\x02\x00\x00\x00" + b"\x00" * 4)  # a header and nothing else
    with pytest.raises(MeshDataError, match=r"bad\.glb"):
        ga.gltf_has_animation(tmp_path / "bad.glb")


def _keyed_triangle(times, path: str = "translation", interpolation: str = "STEP") -> bytes:
    """A triangle whose node moves to x = k at keyframe k (times as given, stored float32)."""
    b = Builder()
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    b.doc["meshes"] = [{"primitives": [{"attributes": {"POSITION": b.add(P, "VEC3")}}]}]
    b.doc["nodes"] = [{"mesh": 0}]
    b.doc["scenes"][0]["nodes"] = [0]
    K = len(times)
    out = np.c_[np.arange(K), np.zeros(K), np.zeros(K)]
    if interpolation == "CUBICSPLINE":  # in-tangent, value, out-tangent per key
        out = np.stack([np.zeros_like(out), out, np.zeros_like(out)], axis=1).reshape(-1, 3)
    b.doc["animations"] = [{"channels": [{"sampler": 0, "target": {"node": 0, "path": path}}],
                            "samplers": [{"input": b.add(np.asarray(times, np.float32), "SCALAR"),
                                          "output": b.add(out, "VEC3"), "interpolation": interpolation}]}]
    return b.glb()


@pytest.mark.parametrize("fps", [24, 25, 30, 60])
def test_the_last_key_is_a_frame_though_its_float32_time_rounds_down(tmp_path, fps):
    """40 keys baked at k / fps (float32, as exporters store them) are 40 frames at fps: the
    count was taken from the last key's float32 time, and where it rounded down (25, 30, 60 fps)
    the last frame was lost (found by a new user)."""
    (tmp_path / "k.glb").write_bytes(_keyed_triangle(np.arange(40) / fps))
    for rate in (None, fps):
        seq = load_sequence(tmp_path / "k.glb", fps=rate)
        assert seq.fps == fps and seq.num_frames == 40


@pytest.mark.parametrize("fps", [24, 25, 30, 60, 120])
def test_the_writer_round_trip_keeps_every_frame_count(tmp_path, fps):
    """save_sequence's .glb read back has its T frames for every T up to 60 (lost one for 4 to 8
    of the 59 lengths at each rate: 60 frames at 24 fps read back as 59)."""
    from dynmesh_warp.gltf_animation import read_gltf_animation, write_gltf_animation

    P, F = _bar()
    for T in range(2, 61):
        V = (P[None] + np.arange(T)[:, None, None] * np.array([0.0, 0.0, 0.01])).astype(np.float32)
        write_gltf_animation(tmp_path / "w.glb", V, F, fps)
        V2, F2, fps2 = read_gltf_animation(tmp_path / "w.glb")
        assert fps2 == fps and V2.shape == V.shape, T
        np.testing.assert_allclose(V2, V, atol=1e-6)


@pytest.mark.parametrize("fps", [24, 25, 30, 60])
@pytest.mark.parametrize("interpolation", ["STEP", "LINEAR", "CUBICSPLINE"])
def test_every_frame_shows_its_own_key_though_key_times_are_float32(tmp_path, fps, interpolation):
    """Keys at float32 k / fps: frame k is key k exactly, for every interpolation. A frame time
    (float64 k / fps) was compared with the float32 key times, and where a key's rounded up,
    STEP gave the key before (14 of 40 frames at 24 fps, 18 at 25, 25 at 30 and 60; found by a
    new user), LINEAR a blend 2e-6 off. At twice the rate a STEP frame between keys holds the
    key before it."""
    (tmp_path / "k.glb").write_bytes(_keyed_triangle(np.arange(40) / fps, interpolation=interpolation))
    seq = load_sequence(tmp_path / "k.glb")
    assert seq.num_frames == 40
    np.testing.assert_array_equal(seq.V[:, 0, 0], np.arange(40))
    if interpolation == "STEP":
        fine = load_sequence(tmp_path / "k.glb", fps=2 * fps)
        np.testing.assert_array_equal(fine.V[:, 0, 0], np.arange(79) // 2)


@pytest.mark.parametrize("fps", [23.976, 29.97, 30000 / 1001, 12.5, 0.5, 7.0])
def test_the_writer_round_trip_keeps_a_rate_that_is_not_whole(tmp_path, fps):
    """Uniformly spaced keys give 1 / their spacing, whole or not, so that each key is a frame:
    only whole rates were taken, else the file was resampled at 30 fps (a new user's 23.976 fps,
    12 frames -> 30 fps, 14 frames; 12.5 -> 27 frames; 0.5 -> 661; 29.97 -> 30). The rate read
    is the shortest decimal that puts every float32 key on its k / fps."""
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.sequence import FixedTopologySequence

    P, F = _bar()
    V = (P[None] + np.random.default_rng(1).normal(size=(12, len(P), 3)) * 0.1).astype(np.float32)
    save_sequence(FixedTopologySequence(V, F, fps=fps, name="bar"), tmp_path / "bar.glb")
    back = load_sequence(tmp_path / "bar.glb")
    assert back.num_frames == 12
    assert back.fps == (29.97003 if fps == 30000 / 1001 else fps)
    np.testing.assert_allclose(back.V, V, atol=1e-6)


def test_keys_not_uniformly_spaced_keep_the_median_rule(tmp_path):
    """Keys at uneven times: 1 / the median spacing when whole (10 fps), else 30 fps."""
    (tmp_path / "a.glb").write_bytes(_keyed_triangle([0.0, 0.1, 0.2, 0.4, 0.5]))
    seq = load_sequence(tmp_path / "a.glb")
    assert seq.fps == 10.0 and seq.num_frames == 6
    np.testing.assert_array_equal(seq.V[:, 0, 0], [0, 1, 2, 2, 3, 4])
    (tmp_path / "b.glb").write_bytes(_keyed_triangle([0.0, 0.37, 0.5, 0.9]))
    assert load_sequence(tmp_path / "b.glb").fps == 30.0


@pytest.mark.parametrize("edit,message", [
    (lambda d: d["nodes"][0].update(mesh=7), r"nodes\[0\]\.mesh: 7, but the file has 1 meshes"),
    (lambda d: d.update(scene=2), r"scene: 2, but the file has 1 scenes"),
    (lambda d: d["scenes"][0].update(nodes=[0, 9]), r"scenes\[0\]\.nodes\[1\]: 9, but the file has 1 nodes"),
    (lambda d: d["nodes"][0].update(children=[5]), r"nodes\[0\]\.children\[0\]: 5, but the file has 1 nodes"),
    (lambda d: d["nodes"][0].update(skin=2), r"nodes\[0\]\.skin: 2, but the file has 0 skins"),
    (lambda d: (d["nodes"][0].update(skin=0), d.update(skins=[{"joints": [0, 9]}])),
     r"skins\[0\]\.joints\[1\]: 9, but the file has 1 nodes"),
    (lambda d: d["animations"][0]["channels"].append({"sampler": 0, "target": {"node": 9, "path": "rotation"}}),
     r"animations\[0\]\.channels\[1\]\.target\.node: 9, but the file has 1 nodes"),
    (lambda d: d["animations"][0]["channels"][0].update(sampler=3),
     r"animations\[0\]\.channels\[0\]\.sampler: 3, but animations\[0\] has 1 samplers"),
])
def test_a_reference_out_of_range_names_the_file_and_its_json_path(tmp_path, edit, message):
    """An index into a missing mesh, scene, node, skin or sampler is an error naming the file and
    the JSON path, as a glTF validator says it: a new user got a raw IndexError (a node's mesh,
    the scene), KeyError: 9 (a skin's joint), and a channel to a missing node was ignored."""
    b = _sliding_bar()
    edit(b.doc)
    (tmp_path / "ref.glb").write_bytes(b.glb())
    with pytest.raises(MeshDataError, match=r"ref\.glb: " + message):
        load_sequence(tmp_path / "ref.glb")


def _edit_glb_json(src, dst, edit):
    """Write ``src`` (a .glb) to ``dst`` with its JSON chunk passed through ``edit(doc)``, as
    another tool saving the file again would (its own asset block)."""
    from pathlib import Path

    raw = Path(src).read_bytes()
    n = struct.unpack_from("<I", raw, 12)[0]
    doc = edit(json.loads(raw[20:20 + n]))
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    rest = raw[20 + n:]
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + rest
    Path(dst).write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)


def test_a_glb_of_z_up_data_is_y_up_as_gltf_says_and_stays_upright_when_saved_again(tmp_path):
    """z-up data written to .glb was stored as it was, z-up, its only mark the asset.generator: a
    glTF viewer showed it lying on its side, and a file saved again by another tool (its own
    generator) came back turned 90 degrees (a new user's). Now it is turned to +Y up and marked:
    load_sequence gives back what was saved, and the same file without the mark (another tool's
    save) reads as any glTF, which the scene turns the same way up. A file written before (z-up,
    generator "dynmesh_warp") still reads unturned."""
    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.gltf_animation import GENERATOR, write_gltf_animation
    from dynmesh_warp.io import save_sequence, stored_up_axis
    from dynmesh_warp.scene import load_surface
    from dynmesh_warp.sequence import FixedTopologySequence

    P, F = _bar()
    V = np.stack([P, P + [0.0, 0.0, 0.5]]).astype(np.float32)  # rises along +z
    save_sequence(FixedTopologySequence(V, F, fps=24.0), tmp_path / "ours.glb")
    np.testing.assert_array_equal(load_sequence(tmp_path / "ours.glb").V, V)  # exact: a permutation and signs
    assert stored_up_axis(tmp_path / "ours.glb") == "z"

    def resaved(doc):
        doc["asset"] = {"version": "2.0", "generator": "SomeTool 4.2"}
        return doc

    _edit_glb_json(tmp_path / "ours.glb", tmp_path / "resaved.glb", resaved)
    raw = load_sequence(tmp_path / "resaved.glb")
    np.testing.assert_allclose(raw.V[1] - raw.V[0], np.tile([0.0, 0.5, 0.0], (len(P), 1)), atol=1e-6)  # +Y up
    assert stored_up_axis(tmp_path / "resaved.glb") == "y"
    surfaces = []
    for name in ("ours.glb", "resaved.glb"):
        (tmp_path / "s.yaml").write_text(f"surface: {{source: {name}}}\n")
        surfaces.append(load_surface(load_scene_config(tmp_path / "s.yaml")).V)
    np.testing.assert_allclose(surfaces[1], surfaces[0], atol=1e-6)
    np.testing.assert_allclose(surfaces[0][1] - surfaces[0][0], np.tile([0.0, 0.0, 0.5], (len(P), 1)), atol=1e-6)
    # the earlier files: z-up as it was, generator "dynmesh_warp" -> read unturned
    write_gltf_animation(tmp_path / "old.glb", V[:, :, [0, 2, 1]] * [1, -1, 1], F, 24.0, y_up=True)  # raw z-up

    def old(doc):
        doc["asset"] = {"version": "2.0", "generator": GENERATOR}
        return doc

    _edit_glb_json(tmp_path / "old.glb", tmp_path / "old2.glb", old)
    assert stored_up_axis(tmp_path / "old2.glb") == "z"

    def kept_generator(doc):  # a re-save that keeps a generator starting with ours, drops the mark
        doc["asset"] = {"version": "2.0", "generator": "dynmesh_warp 0.1.0"}
        return doc

    _edit_glb_json(tmp_path / "ours.glb", tmp_path / "kept.glb", kept_generator)
    assert stored_up_axis(tmp_path / "kept.glb") == "y"
