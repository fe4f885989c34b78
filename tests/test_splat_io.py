"""3D Gaussian Splatting .ply read/write: bit-exact round trip, activations, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from dynmesh_warp.splat_io import (
    SH_C0,
    SplatCloud,
    SplatPlyError,
    read_splat_ply,
    splat_ply_bytes,
    write_splat_ply,
)

STD_ORDER = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _cloud(rng, G=257):
    q = rng.normal(size=(G, 4))
    return SplatCloud.from_activated(rng.normal(size=(G, 3)), np.exp(rng.normal(-4, 1, (G, 3))), q,
                                     rng.random((G, 3)), rng.uniform(0.01, 0.99, G),
                                     f_rest=rng.normal(0, 0.1, (G, 45)), normals=rng.normal(size=(G, 3)))


def _plyfile_style_bytes(rng, G=100) -> tuple[bytes, np.ndarray]:
    """A file laid out exactly as the reference 3DGS code writes it (plyfile, float32 columns)."""
    dt = np.dtype([(n, "<f4") for n in STD_ORDER])
    data = np.zeros(G, dt)
    for n in STD_ORDER:
        data[n] = rng.normal(size=G).astype(np.float32)
    hdr = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % G
    hdr += "".join(f"property float {n}\n" for n in STD_ORDER) + "end_header\n"
    return hdr.encode() + data.tobytes(), data


def test_round_trip_bit_exact(tmp_path, rng):
    c = _cloud(rng)
    p = tmp_path / "a.ply"
    write_splat_ply(p, c)
    c2 = read_splat_ply(p)
    assert c2.data.dtype.names == tuple(STD_ORDER)
    assert c2.data.tobytes() == c.data.tobytes()
    for n in STD_ORDER:
        assert np.array_equal(c2.data[n], c.data[n])
    p2 = tmp_path / "b.ply"
    write_splat_ply(p2, c2)
    assert p2.read_bytes() == p.read_bytes()
    assert c2.sh_degree == 3


def test_reference_layout_round_trip_and_activations(tmp_path, rng):
    raw, data = _plyfile_style_bytes(rng)
    p = tmp_path / "ref.ply"
    p.write_bytes(raw)
    c = read_splat_ply(p)
    assert splat_ply_bytes(c) == raw
    assert np.array_equal(c.positions, np.stack([data["x"], data["y"], data["z"]], 1))
    np.testing.assert_allclose(c.scales(), np.exp(np.stack([data[f"scale_{i}"] for i in range(3)], 1)), rtol=1e-6)
    np.testing.assert_allclose(c.opacities(), 1 / (1 + np.exp(-data["opacity"].astype(np.float64))), rtol=1e-12)
    q = np.stack([data[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    np.testing.assert_allclose(c.rotations_wxyz(), q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-12)
    dc = np.stack([data[f"f_dc_{i}"] for i in range(3)], 1).astype(np.float64)
    np.testing.assert_allclose(c.rgb(), np.maximum(0.5 + SH_C0 * dc, 0), atol=1e-12)  # 3DGS: clamped at 0 only
    assert c.f_rest.shape == (len(data), 45)
    assert np.array_equal(c.f_rest[:, 7], data["f_rest_7"])


def test_from_activated_inverts_activations(rng):
    G = 50
    s = np.exp(rng.normal(-3, 1, (G, 3)))
    op = rng.uniform(0.05, 0.95, G)
    rgb = rng.uniform(0.05, 0.95, (G, 3))
    q = rng.normal(size=(G, 4))
    c = SplatCloud.from_activated(rng.normal(size=(G, 3)), s, q, rgb, op)
    np.testing.assert_allclose(c.scales(), s, rtol=1e-6)
    np.testing.assert_allclose(c.opacities(), op, rtol=1e-5)
    np.testing.assert_allclose(c.rgb(), rgb, atol=1e-6)
    np.testing.assert_allclose(c.rotations_wxyz(), q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-6)


def test_keeps_comments_and_other_types(tmp_path, rng):
    raw, _ = _plyfile_style_bytes(rng, 3)
    raw = raw.replace(b"format binary_little_endian 1.0\n", b"format binary_little_endian 1.0\ncomment made by x\n")
    raw = raw.replace(b"end_header\n", b"property uchar flag\nend_header\n")
    G, itemsize = 3, 4 * len(STD_ORDER)
    body = raw[raw.index(b"end_header\n") + 11:]
    body = b"".join(body[i * itemsize:(i + 1) * itemsize] + bytes([i]) for i in range(G))
    raw = raw[:raw.index(b"end_header\n") + 11] + body
    p = tmp_path / "c.ply"
    p.write_bytes(raw)
    c = read_splat_ply(p)
    assert c.comments == ["comment made by x"]
    assert list(c.data["flag"]) == [0, 1, 2]
    assert splat_ply_bytes(c) == raw


@pytest.mark.parametrize("mutate, match", [
    (lambda b: b.replace(b"binary_little_endian", b"ascii"), "only binary_little_endian"),
    (lambda b: b.replace(b"binary_little_endian", b"binary_big_endian"), "only binary_little_endian"),
    (lambda b: b[:-7], "data has"),
    (lambda b: b.replace(b"property float opacity\n", b""), "data has|missing"),
    (lambda b: b.replace(b"end_header\n", b"element face 1\nproperty list uchar int vertex_indices\nend_header\n"),
     "second element"),
    (lambda b: b"plx" + b[3:], "not a PLY"),
])
def test_bad_files_raise_clear_errors(tmp_path, rng, mutate, match):
    raw, _ = _plyfile_style_bytes(rng, 4)
    p = tmp_path / "bad.ply"
    p.write_bytes(mutate(raw))
    with pytest.raises(SplatPlyError, match=match) as e:
        read_splat_ply(p)
    assert str(p) in str(e.value)


def test_missing_property_named(tmp_path):
    dt = np.dtype([(n, "<f4") for n in ["x", "y", "z", "opacity"]])
    with pytest.raises(SplatPlyError, match="missing properties"):
        SplatCloud(np.zeros(2, dt))
    with pytest.raises(FileNotFoundError, match="file not found"):
        read_splat_ply(tmp_path / "nope.ply")
    with pytest.raises(FileNotFoundError, match="a folder, not a file"):  # said "file not found" before
        read_splat_ply(tmp_path)


def test_a_header_with_windows_line_endings_reads(tmp_path, rng):
    """A valid binary 3DGS file whose header lines end in CRLF was refused as "not a PLY file (no
    'ply' magic or no 'end_header')" (a new user's); it reads as the LF file does."""
    raw, data = _plyfile_style_bytes(rng)
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    (tmp_path / "lf.ply").write_bytes(raw)
    (tmp_path / "crlf.ply").write_bytes(raw[:end].replace(b"\n", b"\r\n") + raw[end:])
    a, b = read_splat_ply(tmp_path / "lf.ply"), read_splat_ply(tmp_path / "crlf.ply")
    assert b.data.tobytes() == a.data.tobytes() == data.tobytes()


def test_bright_and_dark_colours_and_extreme_opacities_survive_bind_and_export(tmp_path, rng):
    """3DGS clamps the DC colour at 0 only (``clamp_min(sh_dc * C0 + 0.5, 0)``): f_dc 3.0 is
    rgb 0.5 + 3 C0 = 1.346, not 1. The binding clipped colours to [0, 1] (f_dc 3.0 came back
    from ``to_splat_cloud`` as 1.7725) and the export clipped opacities to [1e-6, 1 - 1e-6]
    (logits +-20 came back as +-13.8: sigmoid(20) is 1.0 in float32). Now a read -> bind ->
    export round trip keeps f_dc (3.0, -3.0 too) and the opacity logits."""
    import warp as wp

    from dynmesh_warp.gaussians import bind_splats
    from dynmesh_warp.splat_io import OPACITY_EPS

    raw, data = _plyfile_style_bytes(rng, 6)
    data["f_dc_0"] = [3.0, -3.0, 0.25, 1.9, 3.0, 0.0]
    data["opacity"] = [20.0, -20.0, 0.5, 13.9, 30.0, -2.0]
    for i in range(4):
        data[f"rot_{i}"] = [1.0, 0.0, 0.0, 0.0][i]
    data["x"], data["y"], data["z"] = rng.uniform(-0.4, 0.4, 6), rng.uniform(-0.4, 0.4, 6), 0.01
    p = tmp_path / "bright.ply"
    p.write_bytes(raw[:raw.index(b"end_header\n") + 11] + data.tobytes())
    cloud = read_splat_ply(p)
    np.testing.assert_allclose(cloud.rgb()[:, 0], np.maximum(0.5 + SH_C0 * data["f_dc_0"].astype(np.float64), 0))
    assert cloud.rgb()[0, 0] > 1.34 and cloud.rgb()[1, 0] == 0.0
    V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    out = bind_splats(cloud, V, F, device="cpu")
    out.update(wp.array(V, dtype=wp.vec3, device="cpu"), wp.array(F.reshape(-1), dtype=wp.int32, device="cpu"))
    back = out.to_splat_cloud()
    for i in range(3):
        assert np.array_equal(back.data[f"f_dc_{i}"], data[f"f_dc_{i}"]), i
    assert np.array_equal(back.opacity_logits, data["opacity"])
    # activated values alone (no logits kept): 0 and 1 are the nearest float32 opacities that are not
    c = SplatCloud.from_activated(np.zeros((2, 3)), np.full((2, 3), 0.1), np.tile([1.0, 0, 0, 0], (2, 1)),
                                  np.full((2, 3), 1.346), [1.0, 0.0])
    np.testing.assert_allclose(c.opacity_logits, [np.log((1 - OPACITY_EPS) / OPACITY_EPS),
                                                  -np.log((1 - OPACITY_EPS) / OPACITY_EPS)], rtol=1e-6)
    np.testing.assert_allclose(c.rgb(), 1.346, rtol=1e-6)


@pytest.mark.parametrize("k", [30, 3, 1, 46])
def test_an_f_rest_count_that_fits_no_sh_degree_is_refused(tmp_path, rng, k):
    """Degree d has 3 ((d + 1)^2 - 1) f_rest coefficients: 0, 9, 24, 45. A file with 30 was read
    and reported as sh_degree 2 (a new user's); now it is refused naming the file, the count and
    the valid counts. The valid counts read with their degrees."""
    from dynmesh_warp.splat_io import F_REST_COUNTS

    def ply(n):
        names = STD_ORDER[:9] + [f"f_rest_{i}" for i in range(n)] + STD_ORDER[54:]
        data = np.zeros(3, [(m, "<f4") for m in names])
        data["rot_0"] = 1.0
        hdr = "ply\nformat binary_little_endian 1.0\nelement vertex 3\n" + "".join(f"property float {m}\n" for m in names)
        p = tmp_path / f"rest{n}.ply"
        p.write_bytes((hdr + "end_header\n").encode() + data.tobytes())
        return p

    assert F_REST_COUNTS == (0, 9, 24, 45)
    for d, n in enumerate(F_REST_COUNTS):
        c = read_splat_ply(ply(n))
        assert c.sh_degree == d and c.f_rest.shape == (3, n)
    p = ply(k)
    with pytest.raises(SplatPlyError, match=rf"{k} f_rest properties fit no SH degree .*0, 9, 24, 45 for degrees 0..3"
                       ) as e:
        read_splat_ply(p)
    assert str(p) in str(e.value)
    with pytest.raises(SplatPlyError, match=f"{k} f_rest properties"):
        SplatCloud.from_activated(np.zeros((2, 3)), np.full((2, 3), 0.1), np.tile([1.0, 0, 0, 0], (2, 1)),
                                  np.full((2, 3), 0.5), [0.5, 0.5], f_rest=np.zeros((2, k)))


def _sh_rows(f_rest_row, K):
    """One Gaussian's f_rest (channel-major) as reference.sh_color's (K + 1, 3), DC 0."""
    sh = np.zeros((K + 1, 3))
    sh[1:] = np.asarray(f_rest_row, np.float64).reshape(3, K).T
    return sh


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotated_sh_shows_the_colour_of_the_turned_direction(rng, degree):
    """rotate_sh(f, R) seen from v is f seen from R^T v, for every direction: the reference
    3DGS colour (tests/reference.sh_color, the renderer's oracle) at 40 random directions."""
    from scipy.spatial.transform import Rotation

    from dynmesh_warp.splat_io import rotate_sh
    from reference import sh_color

    K = (degree + 1) ** 2 - 1
    G = 12
    f = rng.normal(0, 0.3, (G, 3 * K))
    R = Rotation.random(G, random_state=3).as_matrix()
    out = rotate_sh(f, R)
    assert out.shape == f.shape and out.dtype == np.float32
    worst = 0.0
    for g in range(G):
        a, b = _sh_rows(out[g], K), _sh_rows(f[g], K)
        a[0] = b[0] = 10.0  # away from the clamp at 0
        for d in rng.normal(size=(40, 3)):
            d /= np.linalg.norm(d)
            worst = max(worst, np.abs(sh_color(a, degree, d) - sh_color(b, degree, R[g].T @ d)).max())
    assert worst < 1e-5, worst
    np.testing.assert_allclose(rotate_sh(f, np.eye(3)), f, atol=1e-6)  # the identity keeps them
    # turning twice is turning by the product
    np.testing.assert_allclose(rotate_sh(rotate_sh(f, R), R[::-1]), rotate_sh(f, R[::-1] @ R), atol=1e-5)


def test_exported_f_rest_turns_with_the_surface(rng):
    """Splats with SH degree 3 bound to a sheet; the sheet turned rigidly by R: the exported f_rest
    show, from each direction v, what the file's showed from R^T v (before: the file's f_rest,
    unturned, up to 0.41 off in a new user's degree-1 colour)."""
    import warp as wp
    from scipy.spatial.transform import Rotation

    from dynmesh_warp.gaussians import bind_splats, rebind
    from reference import sh_color

    G = 20
    q = rng.normal(size=(G, 4))
    pos = np.c_[rng.uniform(-0.8, 0.8, (G, 2)), np.zeros(G)]
    cloud = SplatCloud.from_activated(pos, np.full((G, 3), 0.05), q, rng.random((G, 3)), np.full(G, 0.5),
                                      f_rest=rng.normal(0, 0.3, (G, 45)))
    V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    g = bind_splats(cloud, V, F, device="cpu")
    R = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    V1 = (V @ R.T + [0.2, 0.1, 0.3]).astype(np.float32)
    idx = wp.array(F.reshape(-1), dtype=wp.int32, device="cpu")
    g.update(wp.array(V1, dtype=wp.vec3, device="cpu"), idx)
    out = g.to_splat_cloud().f_rest
    turned = rebind(g, V1, F, V1, F)  # carried to another binding: as they stand now
    turned.update(wp.array(V1, dtype=wp.vec3, device="cpu"), idx)
    np.testing.assert_allclose(turned.to_splat_cloud().f_rest, out, atol=1e-5)
    worst = 0.0
    for i in range(G):
        a, b = _sh_rows(out[i], 15), _sh_rows(cloud.f_rest[i], 15)
        a[0] = b[0] = 10.0
        for d in rng.normal(size=(10, 3)):
            d /= np.linalg.norm(d)
            worst = max(worst, np.abs(sh_color(a, 3, d) - sh_color(b, 3, R.T @ d)).max())
    assert worst < 1e-4, worst
    g.update(wp.array(V, dtype=wp.vec3, device="cpu"), idx)  # back at rest: the file's own
    np.testing.assert_allclose(g.to_splat_cloud().f_rest, cloud.f_rest, atol=1e-5)
