"""A mesh's own vertex colours: read from PLY / OBJ / glTF / npz, kept through the scene and a
save, carried by a conversion to its template, and the colour of the scene's generated Gaussians.
Oracles: PLY and OBJ bytes written here by hand, trimesh's reader, the sRGB formula's known
values, barycentric interpolation in NumPy."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import trimesh

from conftest import TEST_DEVICE
from dynmesh_warp.config import scene_config
from dynmesh_warp.convert import to_fixed_topology
from dynmesh_warp.gaussians import gaussians_for_surface
from dynmesh_warp.io import load_sequence, save_sequence
from dynmesh_warp.mesh_formats import read_vertex_colors
from dynmesh_warp.scene import prepare_surface
from dynmesh_warp.sequence import FixedTopologySequence, MeshDataError, VaryingTopologySequence


def _sphere(subdivisions=2, center=(0.0, 0.0, 0.0)):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    return (m.vertices + np.asarray(center)).astype(np.float32), m.faces.astype(np.int32)


def _rgb_of(P):
    """A colour that is a linear function of position (interpolation on a face is exact)."""
    return np.clip(np.asarray(P, np.float64) + 0.5, 0.0, 1.0)


def _ply_bytes(V, F, C8=None, ascii=False, float_colors=None):
    props = "property float x\nproperty float y\nproperty float z\n"
    if C8 is not None:
        props += "property uchar red\nproperty uchar green\nproperty uchar blue\n"
    if float_colors is not None:
        props += "property float r\nproperty float g\nproperty float b\n"
    fmt = "ascii" if ascii else "binary_little_endian"
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {len(V)}\n{props}"
            f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    rows = []
    for i, v in enumerate(V):
        extra = [] if C8 is None else list(C8[i])
        fextra = [] if float_colors is None else list(float_colors[i])
        if ascii:
            rows.append((" ".join(f"{x:.9g}" for x in v) + "".join(f" {c}" for c in extra)
                         + "".join(f" {c:.6g}" for c in fextra) + "\n").encode())
        else:
            rows.append(struct.pack("<3f", *v) + bytes(int(c) for c in extra) + struct.pack(f"<{len(fextra)}f", *fextra))
    for f in F:
        rows.append((f"3 {f[0]} {f[1]} {f[2]}\n").encode() if ascii else struct.pack("<B3i", 3, *f))
    return head + b"".join(rows)


@pytest.mark.parametrize("ascii", [False, True])
def test_ply_uchar_colours_read_as_their_bytes(tmp_path, ascii):
    V, F = _sphere(1)
    C8 = np.random.default_rng(0).integers(0, 256, (len(V), 3))
    p = tmp_path / "c.ply"
    p.write_bytes(_ply_bytes(V, F, C8, ascii=ascii))
    C = read_vertex_colors(p, len(V))
    np.testing.assert_allclose(C, C8 / 255.0, atol=1e-7)
    # trimesh, an independent reader, agrees
    np.testing.assert_array_equal(trimesh.load(p, process=False).visual.vertex_colors[:, :3], C8)


def test_ply_float_colours_and_none(tmp_path):
    V, F = _sphere(1)
    Cf = np.random.default_rng(1).random((len(V), 3)).astype(np.float32)
    p = tmp_path / "f.ply"
    p.write_bytes(_ply_bytes(V, F, float_colors=Cf))
    np.testing.assert_allclose(read_vertex_colors(p), Cf, atol=1e-7)
    p.write_bytes(_ply_bytes(V, F))
    assert read_vertex_colors(p) is None
    with pytest.raises(MeshDataError, match="f.ply: .*colours for"):
        p.write_bytes(_ply_bytes(V, F, float_colors=Cf))
        read_vertex_colors(p, len(V) + 1)


def test_obj_colours_every_vertex_or_none(tmp_path):
    V, F = _sphere(1)
    C = _rgb_of(V)
    p = tmp_path / "c.obj"
    lines = [f"v {x:.9g} {y:.9g} {z:.9g} {r:.6f} {g:.6f} {b:.6f}" for (x, y, z), (r, g, b) in zip(V, C)]
    p.write_text("\n".join(lines + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]) + "\n")
    np.testing.assert_allclose(read_vertex_colors(p), C, atol=1e-6)
    lines[3] = "v {:.9g} {:.9g} {:.9g}".format(*V[3])  # one vertex without: no colours
    p.write_text("\n".join(lines + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]) + "\n")
    assert read_vertex_colors(p) is None


@pytest.mark.parametrize("fmt", ["ply", "obj", "npz", "glb", "pc2"])
def test_colours_round_trip_through_save_and_load(tmp_path, fmt):
    V, F = _sphere(1)
    frames = np.stack([V, V + [0.1, 0.0, 0.0], V + [0.2, 0.0, 0.0]])
    C = (np.round(_rgb_of(V) * 255) / 255).astype(np.float32)  # byte-exact for PLY's uchar
    seq = FixedTopologySequence(frames, F, fps=10.0, colors=C)
    out = tmp_path / ("o" if fmt in ("ply", "obj") else f"o.{fmt}")
    save_sequence(seq, out, fmt=fmt if fmt in ("ply", "obj") else None)
    back = load_sequence(out)
    assert back.colors is not None
    np.testing.assert_allclose(back.colors, C, atol=2e-4 if fmt in ("obj", "pc2") else 1e-5)  # pc2: its .obj
    np.testing.assert_allclose(back.V, frames, atol=1e-6)


def test_glb_colour_is_linear_as_the_specification_says(tmp_path):
    import json

    V, F = _sphere(0)
    C = np.full((len(V), 3), 0.5, np.float32)
    save_sequence(FixedTopologySequence(np.stack([V, V]), F, colors=C), tmp_path / "a.glb")
    raw = (tmp_path / "a.glb").read_bytes()
    n = struct.unpack_from("<I", raw, 12)[0]
    doc = json.loads(raw[20:20 + n])
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"]]
    view = doc["bufferViews"][acc["bufferView"]]
    bin_start = 20 + n + 8
    vals = np.frombuffer(raw, "<f4", acc["count"] * 3, bin_start + view.get("byteOffset", 0))
    np.testing.assert_allclose(vals, 0.21404114, atol=1e-6)  # sRGB 0.5 in linear light


def test_folder_of_coloured_frames_takes_frame_0s_colours(tmp_path):
    V, F = _sphere(1)
    for t in range(3):
        C8 = np.round(_rgb_of(V + 0.1 * t) * 255).astype(int)
        (tmp_path / f"frame_{t:04d}.ply").write_bytes(_ply_bytes(V + [0.1 * t, 0, 0], F, C8))
    seq = load_sequence(tmp_path)
    np.testing.assert_allclose(seq.colors, np.round(_rgb_of(V) * 255) / 255, atol=1e-7)


def test_bad_colours_name_the_source():
    V, F = _sphere(0)
    with pytest.raises(MeshDataError, match="mine: colors must have shape"):
        FixedTopologySequence(V[None], F, source="mine", colors=np.zeros((3, 3)))
    with pytest.raises(MeshDataError, match="mine: colors hold NaN"):
        FixedTopologySequence(V[None], F, source="mine", colors=np.full((len(V), 3), np.nan))


@pytest.mark.parametrize("source", ["mesh", "uniform"])
def test_scene_gaussians_take_the_meshs_colours(source):
    V, F = _sphere(2)
    C = _rgb_of(V).astype(np.float32)
    cfg = scene_config({"gaussians": {"count": 500, "colors": source, "color": [0.2, 0.4, 0.6]}})
    seq = prepare_surface(FixedTopologySequence(np.stack([V, V]), F, colors=C), cfg)
    assert seq.colors is not None  # kept through the scene's transforms
    g = gaussians_for_surface(seq, cfg, TEST_DEVICE)
    b = g.binding
    face, bary = b.face.numpy(), b.bary.numpy().astype(np.float64)
    if source == "mesh":
        expect = np.einsum("gk,gkc->gc", bary, seq.colors[seq.F[face]])
    else:
        expect = np.tile([0.2, 0.4, 0.6], (len(b.rgb), 1))
    np.testing.assert_allclose(b.rgb, expect, atol=1e-5)


def test_conversion_carries_colours_to_the_template():
    """Frames of other tessellations: the output's colours are those of the input's frame 0 at the
    output's frame-0 vertices (the colour is linear in position, so it is known exactly there)."""
    frames = [_sphere(3, (0.02 * t, 0.0, 0.0)) for t in range(3)]
    frames[1] = _sphere(2, (0.02, 0.0, 0.0))
    seq = VaryingTopologySequence(frames, fps=10.0, colors=_rgb_of(frames[0][0]))
    res = to_fixed_topology(seq, device=TEST_DEVICE)
    X0 = res.V[0]
    assert res.colors is not None and res.colors.shape == X0.shape
    # the template's vertices lie on (or within a fraction of an edge of) frame 0's surface
    err = np.abs(res.colors - _rgb_of(X0)).max()
    assert err < 0.02, err


def test_npz_colours_of_other_types_read_as_the_ply_readers_do(tmp_path):
    """An npz's vertex_colors as float 0..255 or uint16 read almost white (clipped, or over 255):
    one rule now for every reader (sequence.unit_colors), integer types over their maximum."""
    V, F = _sphere(1)
    C = _rgb_of(V)
    for name, stored in (("f255", (C * 255).astype(np.float32)), ("u16", np.round(C * 65535).astype(np.uint16)),
                         ("u8", np.round(C * 255).astype(np.uint8)), ("unit", C.astype(np.float32))):
        np.savez(tmp_path / f"{name}.npz", V=V[None], F=F, vertex_colors=stored)
        np.testing.assert_allclose(load_sequence(tmp_path / f"{name}.npz").colors, C, atol=2.5e-3, err_msg=name)


def test_a_glb_mesh_written_alone_reads_back_as_saved(tmp_path):
    """io.write_mesh(x.glb, V, F, colors) went through trimesh as it was: z-up coordinates in a +Y-up
    format (a scene turned them onto their side) and sRGB values in COLOR_0, which is linear (read
    back 0.29 too bright; a new user's). Now +Y up and marked, COLOR_0 linear, as save_sequence's;
    read back as saved by read_mesh, load_sequence and a folder of such frames."""
    import json

    from dynmesh_warp.io import read_mesh, write_mesh

    V, F = _sphere(1)
    V = (V * [1.0, 1.0, 2.0]).astype(np.float32)  # tall along z
    C = _rgb_of(V / 2)
    write_mesh(tmp_path / "m.glb", V, F, colors=C)
    raw = (tmp_path / "m.glb").read_bytes()
    n = struct.unpack_from("<I", raw, 12)[0]
    doc = json.loads(raw[20:20 + n])
    assert doc["asset"]["extras"] == {"dynmesh_warp": {"turned_from_up_axis": "z"}}
    pos = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    assert pos["max"][1] > 0.9 and pos["max"][2] < 0.6  # tall along +Y in the file
    back = read_mesh(tmp_path / "m.glb")[0]
    np.testing.assert_allclose(back, V, atol=1e-6)
    seq = load_sequence(tmp_path / "m.glb")
    np.testing.assert_allclose(seq.V[0], V, atol=1e-6)
    np.testing.assert_allclose(seq.colors, C, atol=0.02)  # 8-bit linear: coarse in the darks
    frames = tmp_path / "frames"
    frames.mkdir()
    for t in range(2):
        write_mesh(frames / f"f_{t}.glb", V + [0.0, 0.0, 0.1 * t], F, colors=C)
    fs = load_sequence(frames)
    np.testing.assert_allclose(fs.V[1] - fs.V[0], np.tile([0.0, 0.0, 0.1], (len(V), 1)), atol=1e-6)
    np.testing.assert_allclose(fs.colors, C, atol=0.02)


def test_colours_not_read_are_said(tmp_path):
    import warnings

    V, F = _sphere(0)
    p = tmp_path / "some.obj"
    lines = [f"v {x} {y} {z}" + (" 1 0 0" if i < 3 else "") for i, (x, y, z) in enumerate(V)]
    p.write_text("\n".join(lines + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]) + "\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert read_vertex_colors(p) is None
    assert any("3 of its 12 vertices have colours" in str(w.message) for w in caught)
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\n"
            f"element face {len(F)}\nproperty list uchar int vertex_indices\nproperty uchar red\nproperty uchar green\n"
            "property uchar blue\nend_header\n")
    body = "".join(f"{x} {y} {z}\n" for x, y, z in V) + "".join(f"3 {a} {b} {c} 255 0 0\n" for a, b, c in F)
    (tmp_path / "fc.ply").write_text(head + body)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert read_vertex_colors(tmp_path / "fc.ply") is None
    assert any("colours are on its faces" in str(w.message) for w in caught)
