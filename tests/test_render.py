"""The Warp splatting renderer (issue 16; dynmesh_warp/render.py) against a plain NumPy renderer
with the same maths (reference.render_splats): random Gaussians with SH up to degree 3, a batch
of cameras in one launch, spheres composited by depth; and the render CLI."""

from __future__ import annotations

import numpy as np
import pytest
from reference import render_splats

from dynmesh_warp.render import Renderer, look_at, orbit_cameras, rgb_to_sh


def _scene(G, seed, degree):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    means = rng.uniform(-1, 1, (G, 3)).astype(np.float32)
    Rm = Rotation.random(G, random_state=seed).as_matrix()
    S = rng.uniform(0.02, 0.2, (G, 3))
    covs = np.einsum("gij,gj,gkj->gik", Rm, S**2, Rm).astype(np.float32)
    sh = np.concatenate([rgb_to_sh(rng.uniform(0, 1, (G, 3))),
                         rng.normal(0, 0.3, (G, (degree + 1) ** 2 - 1, 3)).astype(np.float32)], axis=1)
    op = rng.uniform(0.1, 1.0, G).astype(np.float32)
    return means, covs, sh, op


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_render_equals_the_numpy_reference(device, degree):
    means, covs, sh, op = _scene(300, degree, degree)
    cams = [look_at([3.0, 2.0, 1.5], [0, 0, 0], width=40, height=32),
            look_at([-2.5, 1.0, 2.5], [0.1, 0, 0], width=40, height=32, fov_y_deg=60)]
    spheres = (np.array([[0.2, 0.1, 0.0], [5.0, 5.0, 5.0]]), np.array([0.35, 0.1]))
    out = Renderer(device).render(means, covs, sh, op, cams, spheres=spheres)
    rgb, alpha = out.rgb.numpy(), out.alpha.numpy()
    for c, cam in enumerate(cams):
        ref_rgb, ref_alpha = render_splats(means, covs, sh, degree, op, cam, spheres=spheres)
        err = np.abs(rgb[c] - ref_rgb).max(axis=-1)
        assert np.quantile(err, 0.99) < 1e-3 and err.max() < 2e-2, (c, err.max())
        np.testing.assert_allclose(alpha[c], ref_alpha, atol=2e-2)
        assert 0.05 < ref_alpha.mean() < 0.99  # something drawn, not all of it opaque
    # the sphere changes the picture (drawn where no splat hides it, and hides splats behind it)
    plain = Renderer(device).render(means, covs, sh, op, cams).rgb.numpy()
    assert np.abs(plain - rgb).max() > 0.1


def test_render_batch_of_cameras_equals_one_at_a_time(device):
    means, covs, sh, op = _scene(200, 7, 0)
    cams = orbit_cameras([0, 0, 0], 3.5, 3, width=48, height=40)
    r = Renderer(device)
    batch = r.render(means, covs, sh, op, cams).rgb.numpy()
    for c, cam in enumerate(cams):
        np.testing.assert_allclose(batch[c], r.render(means, covs, sh, op, [cam]).rgb.numpy()[0], atol=1e-6)
    with pytest.raises(ValueError, match="same image size"):
        r.render(means, covs, sh, op, [cams[0], look_at([3, 0, 0], [0, 0, 0], width=10, height=10)])
    with pytest.raises(ValueError, match="sh"):
        r.render(means, covs, np.zeros((200, 2, 3)), op, cams)


@pytest.mark.parametrize("playback", ["loop", "pingpong"])
def test_render_envs_equals_each_env_rendered_alone(device, playback):
    """Camera observations of a batch (issue 16): env e's image, rendered in one launch with the
    others, equals rendering env e alone: its surface at its own time (EnvView), its Gaussians
    updated from it (the tested single-scene path), only its spheres, its camera."""
    from dynmesh_warp.batch import BatchedWorld, BatchModel, BatchState, EnvView
    from dynmesh_warp.gaussians import generate_gaussians
    from dynmesh_warp.gaussians import SHADE_AMBIENT
    from dynmesh_warp.render import render_envs
    from dynmesh_warp.scenes import wave_bowl
    from dynmesh_warp.world import PhysicsParams, SurfaceModel

    seq = wave_bowl(n=16, frames=8)
    E, S = 3, 2
    rng = np.random.default_rng(2)
    pos = np.concatenate([rng.uniform(-0.4, 0.4, (E, S, 2)), np.full((E, S, 1), 0.25)], axis=2)
    bm = BatchModel(SurfaceModel(seq, device, playback=playback), E, np.full(S, 0.12, np.float32), 1.0,
                    PhysicsParams())
    bw = BatchedWorld(bm, BatchState(bm, pos, times=np.array([0.0, 0.21, 0.55]), rates=[1.0, 0.5, 2.0]))
    for _ in range(5):
        bw.step()
    g = generate_gaussians(seq.V[0], seq.F, count=600, seed=1, device=device)
    cams = [look_at([1.6, -1.4, 1.2], [0, 0, 0], width=40, height=32),
            look_at([-1.5, 1.2, 1.4], [0, 0, 0.1], width=40, height=32, fov_y_deg=55),
            look_at([0.2, -2.0, 0.9], [0, 0, 0], width=40, height=32)]
    r = Renderer(device)
    out = render_envs(bw, g, cams, renderer=r)
    rgb, alpha, depth = out.rgb.numpy().copy(), out.alpha.numpy().copy(), out.depth.numpy().copy()
    assert rgb.shape == (E, 32, 40, 3)
    sh, op = rgb_to_sh(g.binding.rgb), g.binding.opacity
    for e in range(E):
        view = EnvView(bw, e)
        g.update(view.surface_points(), view.surface_indices())
        one = Renderer(device).render(g.state.centers, g.state.covariances, sh, op, [cams[e]],
                                      spheres=(view.sphere_positions(), view.sphere_radii()), shade=SHADE_AMBIENT)
        np.testing.assert_allclose(rgb[e], one.rgb.numpy()[0], atol=1e-5)
        np.testing.assert_allclose(alpha[e], one.alpha.numpy()[0], atol=1e-5)
        np.testing.assert_allclose(depth[e], one.depth.numpy()[0], atol=1e-4)
        assert 0.05 < alpha[e].mean() < 1.0
    # the envs' surfaces differ (own clocks): the same camera sees different pictures
    same = render_envs(bw, g, cams[0], renderer=r).rgb.numpy()
    assert np.abs(same[0] - same[2]).max() > 0.05
    with pytest.raises(ValueError, match="2 cameras for 3 envs"):
        render_envs(bw, g, cams[:2])


def test_fixed_capacity_render_equals_the_exact_one_and_counts_what_it_drops(device):
    """``capacity=``: no host read (capturable); with room for every entry the picture equals
    the exactly sized render and nothing is counted as dropped; with too little room the dropped
    entries are counted and the picture differs."""
    means, covs, sh, op = _scene(300, 4, 1)
    cams = orbit_cameras([0, 0, 0], 3.5, 2, width=40, height=32)
    r = Renderer(device)
    exact = r.render(means, covs, sh, op, cams)
    ref = exact.rgb.numpy().copy()
    assert int(exact.overflow.numpy()[0]) == 0
    assert r.capacity >= 1  # the exact render sized the buffers; rendering at that capacity drops nothing
    fits = r.render(means, covs, sh, op, cams, capacity=r.capacity)
    assert int(fits.overflow.numpy()[0]) == 0
    np.testing.assert_array_equal(fits.rgb.numpy(), ref)
    roomy = r.render(means, covs, sh, op, cams, capacity=200_000)
    np.testing.assert_array_equal(roomy.rgb.numpy(), ref)
    assert int(roomy.overflow.numpy()[0]) == 0
    tight = r.render(means, covs, sh, op, cams, capacity=500)
    assert int(tight.overflow.numpy()[0]) > 0
    assert np.abs(tight.rgb.numpy() - ref).max() > 0.05
    with pytest.raises(ValueError, match="capacity"):
        r.render(means, covs, sh, op, cams, capacity=0)


def test_compact_sort_keys_give_the_wide_keys_picture(device):
    """The compact 32-bit (tile, depth rank) keys sort the splats like the 64-bit (tile, depth)
    ones: the same picture, exactly sized and with a fixed capacity; the layout falls back to
    64-bit keys where the bins and ranks do not fit in 32 bits."""
    means, covs, sh, op = _scene(300, 11, 1)
    cams = orbit_cameras([0, 0, 0], 3.5, 3, width=40, height=32)
    spheres = (np.array([[0.2, 0.1, 0.0]]), np.array([0.3]))
    compact, wide = Renderer(device), Renderer(device, compact_keys=False)
    for kw in ({}, {"capacity": 100_000}):
        a = compact.render(means, covs, sh, op, cams, spheres=spheres, **kw)
        a_rgb, a_alpha, a_depth = a.rgb.numpy().copy(), a.alpha.numpy().copy(), a.depth.numpy().copy()
        b = wide.render(means, covs, sh, op, cams, spheres=spheres, **kw)
        np.testing.assert_array_equal(a_rgb, b.rgb.numpy())
        np.testing.assert_array_equal(a_alpha, b.alpha.numpy())
        np.testing.assert_array_equal(a_depth, b.depth.numpy())
        assert 0.05 < a_alpha.mean() < 0.99
    assert compact._keys32 is not None and compact._keys is None  # each took its own path
    assert wide._keys is not None and wide._keys32 is None
    # 1080p, one camera, 100k Gaussians: 8,160 bins (13 bits) + ranks of 10^5 (17 bits)
    assert compact.key_layout(1, 100_000, 8160) == (True, 17)
    # 1,024 cameras of 128 x 128 (65,536 bins) x 5,000 Gaussians: 16 + 23 bits, 64-bit keys
    assert compact.key_layout(1024, 5000, 65536) == (False, 32)
    assert wide.key_layout(1, 100, 4) == (False, 32)


def test_shared_memory_rasteriser_equals_the_per_pixel_one(device):
    """The block-per-tile rasteriser (splats staged in shared memory in batches of 256, the
    CUDA default) gives the per-pixel rasteriser's images bit for bit: tiles with several
    batches of splats, saturated pixels, a sphere and a box composited by depth, partial tiles
    at the image's edges, two cameras, exactly sized and with a fixed capacity."""
    from dynmesh_warp.choices import DEFAULT_RASTERISER, Rasteriser
    from dynmesh_warp.render import RigidShapes

    means, covs, sh, op = _scene(2500, 5, 1)
    cams = orbit_cameras([0, 0, 0], 3.5, 2, width=40, height=36)  # 36 rows: a partial tile row
    spheres = (np.array([[0.2, 0.1, 0.0], [-0.4, 0.2, 0.3]]), np.array([0.3, 0.25]))
    box = RigidShapes([{"type": "box", "scale": [0.2, 0.3, 0.2], "pose": [0.5, -0.3, 0.1, 0, 0, 0, 1]}], device)
    shared, per_pixel = Renderer(device, rasteriser="shared"), Renderer(device, rasteriser=Rasteriser.PER_PIXEL)
    assert Renderer(device).rasteriser == DEFAULT_RASTERISER["cuda" if shared.device.is_cuda else "cpu"]
    for kw in ({}, {"capacity": 200_000}):
        a = shared.render(means, covs, sh, op, cams, spheres=spheres, shapes=box, **kw)
        a_rgb, a_alpha, a_depth = a.rgb.numpy().copy(), a.alpha.numpy().copy(), a.depth.numpy().copy()
        b = per_pixel.render(means, covs, sh, op, cams, spheres=spheres, shapes=box, **kw)
        np.testing.assert_array_equal(a_rgb, b.rgb.numpy())
        np.testing.assert_array_equal(a_alpha, b.alpha.numpy())
        np.testing.assert_array_equal(a_depth, b.depth.numpy())
    runs = shared.last_tile_counts()
    assert runs.max() > 3 * 256  # tiles of several shared-memory batches
    assert (a_alpha > 0.99).mean() > 0.3 and (a_alpha < 0.9).any()  # near-saturated pixels, and others
    with pytest.raises(ValueError, match="rasteriser must be one of"):
        Renderer(device, rasteriser="warp")


def test_recorded_launches_follow_changed_inputs(device):
    """The renderer replays its recorded launches while the arguments are the same arrays: a
    second scene written into the same arrays (another entry count), a new array, and other
    cameras each give exactly the picture a fresh renderer gives."""
    import warp as wp

    a, b = _scene(250, 21, 1), _scene(400, 22, 1)
    cams = orbit_cameras([0, 0, 0], 3.5, 2, width=40, height=32)
    G = 400
    pad = lambda x, n: np.concatenate([x, np.zeros((n - len(x),) + x.shape[1:], x.dtype)])  # noqa: E731
    # scene a padded to G Gaussians of zero opacity, so both fit the same arrays
    a = tuple(pad(x, G) for x in a)
    arrays = [wp.array(a[0], dtype=wp.vec3, device=device), wp.array(a[1], dtype=wp.mat33, device=device),
              wp.array(a[2], dtype=float, device=device), wp.array(a[3], dtype=float, device=device)]
    r = Renderer(device)
    with pytest.raises(ValueError, match="nothing rendered yet"):
        r.last_entry_count()
    first = r.render(*arrays, cams).rgb.numpy().copy()
    entries_a = r.last_entry_count()
    np.testing.assert_array_equal(first, Renderer(device).render(*a, cams).rgb.numpy())
    for arr, x in zip(arrays, b):  # the same arrays, new contents
        arr.assign(x)
    second = r.render(*arrays, cams).rgb.numpy().copy()
    assert r.last_entry_count() != entries_a
    np.testing.assert_array_equal(second, Renderer(device).render(*b, cams).rgb.numpy())
    assert np.abs(second - first).max() > 0.1
    again = r.render(wp.array(a[0], dtype=wp.vec3, device=device), *arrays[1:], cams)  # one new array
    np.testing.assert_array_equal(again.rgb.numpy(), Renderer(device).render(a[0], *b[1:], cams).rgb.numpy())
    other = orbit_cameras([0, 0, 0], 3.0, 2, width=40, height=32)
    np.testing.assert_array_equal(r.render(*arrays, other).rgb.numpy(), Renderer(device).render(*b, other).rgb.numpy())


def test_fixed_capacity_render_is_captured_in_a_cuda_graph(cuda_device):
    """Camera observations inside a CUDA graph: render_envs with a capacity, after one warm-up
    call (cameras and colours uploaded, modules loaded), captured and replayed after the envs
    moved, equals an eager render at the new times."""
    import warp as wp

    from dynmesh_warp.batch import BatchedWorld, BatchModel, BatchState
    from dynmesh_warp.gaussians import generate_gaussians
    from dynmesh_warp.render import render_envs
    from dynmesh_warp.scenes import wave_bowl
    from dynmesh_warp.world import PhysicsParams, SurfaceModel

    seq = wave_bowl(n=16, frames=8)
    bm = BatchModel(SurfaceModel(seq, cuda_device), 4, [0.1], 1.0, PhysicsParams())
    bw = BatchedWorld(bm, BatchState(bm, [[0.0, 0.0, 0.3]], times=[0.0, 0.1, 0.2, 0.3]))
    g = generate_gaussians(seq.V[0], seq.F, count=500, seed=0, device=cuda_device)
    cam = look_at([1.6, -1.4, 1.2], [0, 0, 0], width=32, height=32)
    r = Renderer(cuda_device)
    render_envs(bw, g, cam, renderer=r, capacity=100_000)
    with wp.ScopedCapture(device=cuda_device) as cap:
        out = render_envs(bw, g, cam, renderer=r, capacity=100_000)
    for _ in range(7):
        bw.step()
    wp.capture_launch(cap.graph)
    got = out.rgb.numpy().copy()
    want = render_envs(bw, g, cam, renderer=Renderer(cuda_device)).rgb.numpy()
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert int(out.overflow.numpy()[0]) == 0


def test_a_stopped_render_keeps_its_frames_beside_an_earlier_output(tmp_path, monkeypatch, capsys):
    """A new user's Ctrl-C gave a KeyboardInterrupt traceback, and a stopped --overwrite left the
    folder with new frames mixed into old ones of another size. The frames now go through a
    temporary folder: a stop writes the frames done beside an earlier output (``<out>.partial``,
    status complete false), exit 130; the earlier frames stay as they were. A side over
    MAX_IMAGE_SIDE is refused before the work (a RuntimeError traceback after loading)."""
    import json

    import dynmesh_warp.cli as cli
    from dynmesh_warp.outputs import MANIFEST
    from dynmesh_warp.render import MAX_IMAGE_SIDE, main

    out = tmp_path / "fr"
    small = ["--width", "32", "--height", "24", "--no-progress", "--device", "cpu"]
    assert main(["--out", str(out), "--frames", "2"] + small) == 0
    before = {p.name: p.read_bytes() for p in out.glob("frame_*.png")}
    asked = []
    # the loop asks once a frame: the 8th answer stops it, after 7 frames
    monkeypatch.setattr(cli, "stop_reason", lambda: "SIGINT" if len(asked) > 6 or asked.append(1) else None)
    rc = main(["--out", str(out), "--frames", "9", "--overwrite", "--width", "40", "--height", "30", "--no-progress",
               "--device", "cpu"])
    err = capsys.readouterr().err
    assert rc == 130 and "Traceback" not in err
    part = tmp_path / "fr.partial"
    assert f"interrupted by SIGINT after 7 of 9 frames: wrote {part} with frames 0..6" in err
    assert {p.name: p.read_bytes() for p in out.glob("frame_*.png")} == before
    assert sorted(p.name for p in part.glob("frame_*.png")) == [f"frame_{f:04d}.png" for f in range(7)]
    assert json.loads((part / MANIFEST).read_text())["status"]["complete"] is False
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "big"), "--width", str(MAX_IMAGE_SIDE + 1)] + small[2:])


def test_render_cli_writes_frames_and_a_figure(tmp_path):
    from dynmesh_warp.render import main

    rc = main(["--out", str(tmp_path / "frames"), "--figure", str(tmp_path / "strip.png"), "--frames", "3",
               "--video", str(tmp_path / "run.gif"),
               "--moments", "2", "--width", "64", "--height", "48", "--no-progress", "--device", "cpu"])
    assert rc == 0
    from PIL import Image

    files = sorted((tmp_path / "frames").glob("frame_*.png"))
    assert len(files) == 3
    img = np.asarray(Image.open(files[0]))
    assert img.shape == (48, 64, 3) and img.std() > 5  # not blank
    strip = np.asarray(Image.open(tmp_path / "strip.png"))
    assert strip.shape == (48, 128, 3)
    gif = Image.open(tmp_path / "run.gif")
    assert gif.n_frames == 3 and gif.size == (64, 48)
    with pytest.raises(SystemExit):
        main(["--video", str(tmp_path / "run.avi"), "--device", "cpu"])  # a format it cannot write
    # --mesh --no-splats: the physics mesh alone, in its colour (no splat colours)
    assert main(["--figure", str(tmp_path / "mesh.png"), "--moments", "1", "--mesh", "--no-splats", "--width", "64",
                 "--height", "48", "--no-progress", "--device", "cpu"]) == 0
    m = np.asarray(Image.open(tmp_path / "mesh.png")).astype(float)
    fg = np.abs(m - 255).max(axis=-1) > 10  # not background
    assert fg.mean() > 0.05 and not np.array_equal(m, img.astype(float))
    # --unlit: the splats' own colours (a capture's hold its lighting): never darker than shaded
    # (shading multiplies by 0.35-1), and darker somewhere on the curved surface
    for name, extra in (("lit.png", []), ("unlit.png", ["--unlit"])):
        assert main(["--figure", str(tmp_path / name), "--moments", "1", "--width", "64", "--height", "48",
                     "--no-progress", "--device", "cpu"] + extra) == 0
    lit, unlit = (np.asarray(Image.open(tmp_path / n)).astype(float) for n in ("lit.png", "unlit.png"))
    on = np.abs(unlit - 255).max(axis=-1) > 10
    assert on.mean() > 0.05 and (unlit[on] >= lit[on] - 2).all() and (unlit[on] - lit[on]).mean() > 5


def test_render_cli_takes_a_sequence_as_run_does(tmp_path, capsys):
    """`render SEQUENCE` (not only a scene YAML) plays it with spheres dropped on it, as `run`
    does, with --set; a segmented output of `convert` renders (its bounds came from `.V`,
    which it has not: an AttributeError before); a varying one asks for a conversion, or draws
    the mesh alone with --mesh --no-splats."""
    from PIL import Image

    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.render import main
    from dynmesh_warp.scenes import pulsing_blob
    from dynmesh_warp.sequence import VaryingTopologySequence

    blob = pulsing_blob(subdivisions=2, frames=4)
    V, F = blob.V, blob.F
    save_sequence(blob, tmp_path / "blob.npz")
    args = ["--moments", "1", "--width", "48", "--height", "32", "--no-progress", "--device", "cpu"]
    assert main([str(tmp_path / "blob.npz"), "--figure", str(tmp_path / "a.png"), "--set", "spheres.count=2"]
                + args) == 0
    assert "mesh sequence, not a scene file" in capsys.readouterr().err
    assert np.asarray(Image.open(tmp_path / "a.png")).std() > 5
    # two segments of fixed topology (faces reordered in the second), as convert writes them
    perm = np.random.default_rng(0).permutation(len(F))
    frames = [(V[t], F) for t in range(2)] + [(V[t], F[perm]) for t in range(2, 4)]
    save_sequence(VaryingTopologySequence(frames, fps=24.0, name="seg"), tmp_path / "seg.npz")
    assert main([str(tmp_path / "seg.npz"), "--figure", str(tmp_path / "b.png")] + args) == 0
    # truly varying: a clear error (exit 2), or the mesh alone
    varying = [(V[t], F) if t % 2 == 0 else (np.concatenate([V[t], V[t][:1]]), F) for t in range(4)]  # a stray vertex
    save_sequence(VaryingTopologySequence(varying, fps=24.0, name="var"), tmp_path / "var.npz")
    capsys.readouterr()
    assert main([str(tmp_path / "var.npz"), "--figure", str(tmp_path / "c.png"), "--set", "physics.collider=rebuild"]
                + args) == 2
    assert "convert it first" in capsys.readouterr().err
    assert main([str(tmp_path / "var.npz"), "--figure", str(tmp_path / "c.png"), "--set", "physics.collider=rebuild",
                 "--mesh", "--no-splats"] + args) == 0


def _shape_list():
    from scipy.spatial.transform import Rotation

    q = lambda *euler: Rotation.from_euler("xyz", euler, degrees=True).as_quat()  # noqa: E731
    return [
        {"type": "box", "scale": [0.3, 0.2, 0.15], "pose": [0.0, 0.0, 0.0, *q(20, 35, -10)]},
        {"type": "capsule", "scale": [0.12, 0.3, 0.0], "pose": [0.55, -0.3, 0.1, *q(70, 0, 30)]},
        {"type": "cylinder", "scale": [0.15, 0.2, 0.0], "pose": [-0.5, 0.35, -0.1, *q(-30, 50, 0)]},
        {"type": "sphere", "scale": [0.18, 0.0, 0.0], "pose": [0.1, 0.6, 0.25, 0, 0, 0, 1]},
        {"type": "cone", "scale": [0.1, 0.2, 0.0], "pose": [0.0, 0.0, 2.0, 0, 0, 0, 1]},  # not drawn
    ]


def test_rigid_shapes_equal_sphere_traced_sdfs(device):
    """Boxes, capsules, cylinders and spheres cast by the kernels (closed-form intersections in
    each shape's frame) against sphere tracing of the exact SDFs in NumPy: the same pixels hit
    (but at silhouettes), the same depth and the same shade (0.25 + 0.75 |n . d|); an
    unsupported type is listed, not drawn; bad sizes are refused naming the shape."""
    from reference import cast_shapes_sdf

    from dynmesh_warp.render import RigidShapes

    shapes = _shape_list()
    rs = RigidShapes(shapes, device, color=(0.4, 0.6, 0.8))
    assert rs.count == 4 and rs.skipped == ["cone"] and rs.kept == [0, 1, 2, 3]
    no_mesh = RigidShapes([{"type": "mesh", "scale": [1, 1, 1], "pose": [0, 0, 0, 0, 0, 0, 1]}], device)
    assert no_mesh.count == 0 and no_mesh.skipped == ["mesh (no vertices)"]
    cam = look_at([2.2, -1.6, 1.4], [0, 0.05, 0], width=64, height=48, fov_y_deg=30)
    empty = (np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 1, 3)), np.zeros(0))
    out = Renderer(device).render(*empty, [cam], shapes=rs, background=(0.0, 0.0, 0.0))
    alpha, depth, rgb = out.alpha.numpy()[0], out.depth.numpy()[0], out.rgb.numpy()[0]
    R, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
    ys, xs = np.mgrid[0:48, 0:64]
    dc = np.stack([(xs + 0.5 - cam.cx) / cam.fx, (ys + 0.5 - cam.cy) / cam.fy, np.ones_like(xs, float)], -1).reshape(-1, 3)
    dc /= np.linalg.norm(dc, axis=1, keepdims=True)
    s, which, n = cast_shapes_sdf(shapes[:4], -(R.T @ t), dc @ R)
    hit_ref = np.isfinite(s).reshape(48, 64)
    hit = alpha > 0.5
    assert 0.1 < hit_ref.mean() < 0.7
    assert (hit != hit_ref).mean() < 0.01, (hit != hit_ref).sum()  # silhouette pixels only
    both = (hit & hit_ref).reshape(-1)
    z_ref = (s * dc[:, 2])
    np.testing.assert_allclose(depth.reshape(-1)[both], z_ref[both], atol=1e-4)
    shade = 0.25 + 0.75 * np.abs((n * (dc @ R)).sum(1))
    err = np.abs(rgb.reshape(-1, 3)[both] - shade[both, None] * np.array([0.4, 0.6, 0.8]))
    assert np.quantile(err, 0.98) < 1e-3 and err.max() < 0.05  # edges and box corners: gradients differ
    # each kind is visible (the reference sees all four)
    assert set(which[both].tolist()) == {0, 1, 2, 3}
    with pytest.raises(ValueError, match="shape 0 .box."):
        RigidShapes([{"type": "box", "scale": [0.1, 0.0, 0.1], "pose": [0, 0, 0, 0, 0, 0, 1]}], device)
    with pytest.raises(ValueError, match="2 poses for 4"):
        rs.set_poses(np.zeros((2, 7)))


def test_rigid_sphere_shape_composites_like_a_ray_cast_sphere(device):
    """Depth compositing with the splats: a sphere given as a rigid shape gives the same picture
    as the same sphere given to the tested sphere path (in front of some splats, behind others)."""
    from dynmesh_warp.render import RigidShapes

    means, covs, sh, op = _scene(300, 3, 1)
    cams = [look_at([3.0, 2.0, 1.5], [0, 0, 0], width=40, height=32)]
    col = (0.85, 0.25, 0.2)
    a = Renderer(device).render(means, covs, sh, op, cams, spheres=(np.array([[0.2, 0.1, 0.0]]), np.array([0.45])),
                                sphere_color=col)
    rs = RigidShapes([{"type": "sphere", "scale": [0.45, 0, 0], "pose": [0.2, 0.1, 0.0, 0, 0, 0, 1]}], device, color=col)
    b = Renderer(device).render(means, covs, sh, op, cams, shapes=rs)
    err = np.abs(a.rgb.numpy() - b.rgb.numpy()).max(axis=-1)
    assert np.quantile(err, 0.99) < 1e-4 and err.max() < 2e-2
    np.testing.assert_allclose(a.depth.numpy(), b.depth.numpy(), atol=1e-4)
    plain = Renderer(device).render(means, covs, sh, op, cams).rgb.numpy()
    assert np.abs(plain - b.rgb.numpy()).max() > 0.1  # the sphere is there


def test_rigid_mesh_shape_equals_brute_force_ray_casting(device):
    """A mesh shape (scaled, rotated, moved) against a brute-force NumPy ray caster on the same
    mesh in world coordinates: the same pixels hit and the same depth."""
    import trimesh
    from reference import ray_cast_triangles
    from scipy.spatial.transform import Rotation

    from dynmesh_warp.render import RigidShapes

    m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    m.vertices[:, 0] *= 1.5
    scale = np.array([0.3, 0.2, 0.25])
    q = Rotation.from_euler("xyz", [10, 40, 70], degrees=True)
    pose = [0.1, -0.1, 0.05, *q.as_quat()]
    rs = RigidShapes([{"type": "mesh", "scale": scale, "pose": pose, "vertices": m.vertices, "indices": m.faces}],
                     device)
    cam = look_at([1.8, 1.2, 1.0], [0.1, -0.1, 0.05], width=40, height=30, fov_y_deg=25)
    empty = (np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 1, 3)), np.zeros(0))
    out = Renderer(device).render(*empty, [cam], shapes=rs)
    alpha, depth = out.alpha.numpy()[0], out.depth.numpy()[0]
    world = trimesh.Trimesh(q.apply(m.vertices * scale) + pose[:3], m.faces, process=False)
    R, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
    ys, xs = np.mgrid[0:30, 0:40]
    dc = np.stack([(xs + 0.5 - cam.cx) / cam.fx, (ys + 0.5 - cam.cy) / cam.fy, np.ones_like(xs, float)], -1).reshape(-1, 3)
    dc /= np.linalg.norm(dc, axis=1, keepdims=True)
    s = ray_cast_triangles(-(R.T @ t), dc @ R, world.vertices, world.faces)
    hit_ref = np.isfinite(s).reshape(30, 40)
    assert 0.1 < hit_ref.mean() < 0.8
    assert (hit_ref != (alpha > 0.5)).mean() < 0.01
    both = (hit_ref & (alpha > 0.5)).reshape(-1)
    np.testing.assert_allclose(depth.reshape(-1)[both], (s * dc[:, 2])[both], atol=1e-4)


def test_render_world_draws_the_physics_mesh_where_a_ray_meets_it(device):
    """``render_world(mesh=True, splats=False)``: the physics mesh at the world's current time,
    opaque; the depth of every pixel equals a brute-force ray cast of the surface's current
    triangles, also after the surface has moved (the mesh is refit, not stale)."""
    from reference import ray_cast_triangles

    from dynmesh_warp import build_world, load_scene_config
    from dynmesh_warp.render import Renderer, look_at, render_world

    cfg = load_scene_config(data={"name": "m", "device": device, "spheres": [],
                                  "surface": {"source": "builtin:pulsing_blob", "params": {"subdivisions": 2}}})
    world = build_world(cfg)
    r = Renderer(world.device)
    cam = look_at([2.0, -1.5, 1.2], [0, 0, 0], width=24, height=18, fov_y_deg=40)
    R, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
    ys, xs = np.mgrid[0:18, 0:24]
    dc = np.stack([(xs + 0.5 - cam.cx) / cam.fx, (ys + 0.5 - cam.cy) / cam.fy, np.ones_like(xs, float)], -1).reshape(-1, 3)
    dc /= np.linalg.norm(dc, axis=1, keepdims=True)
    depths = []
    for _ in range(2):
        out = render_world(world, None, [cam], r, splats=False, mesh=True)
        P = world.surface_points().numpy()
        F = world.surface_indices().numpy().reshape(-1, 3)
        s = ray_cast_triangles(-(R.T @ t), dc @ R, P, F)
        hit = np.isfinite(s)
        alpha, depth = out.alpha.numpy()[0].reshape(-1), out.depth.numpy()[0].reshape(-1)
        assert 0.1 < hit.mean() < 0.9 and ((alpha > 0.5) != hit).mean() < 0.02
        both = hit & (alpha > 0.5)
        np.testing.assert_allclose(depth[both], (s * dc[:, 2])[both], atol=1e-4)
        depths.append(depth.copy())
        for _ in range(60):  # the blob pulses: a quarter second later the picture differs
            world.step()
    assert np.abs(depths[0] - depths[1]).max() > 1e-3


def test_kernel_shading_equals_the_host_shading_of_the_flat_axis(device):
    """The head-light shading computed in ``project_gaussians`` (flat axis = eigenvector of the
    smallest covariance eigenvalue) gives the picture of the host reference
    ``gaussians.shaded_rgb`` (flat axis from each Gaussian's rotation and scales) baked into the
    colours of an unlit render, for the same light; and it changes the picture."""
    from dynmesh_warp.gaussians import SHADE_AMBIENT, generate_gaussians, shaded_rgb
    from dynmesh_warp.scenes import wave_bowl

    seq = wave_bowl(n=16, frames=4)
    g = generate_gaussians(seq.V[2], seq.F, count=800, seed=3, device=device)
    g.update(_warp_points(seq.V[2], device), _warp_indices(seq.F, device))
    cam = look_at([1.5, -1.3, 1.1], [0, 0, 0], width=48, height=36)
    R = np.asarray(cam.R, np.float64)
    light = R[2] + np.array([0.0, 0.0, -0.5])
    op = g.binding.opacity
    host = Renderer(device).render(g.state.centers, g.state.covariances, rgb_to_sh(shaded_rgb(g, light, SHADE_AMBIENT)),
                                   op, [cam]).rgb.numpy()[0]
    kern = Renderer(device).render(g.state.centers, g.state.covariances, rgb_to_sh(g.binding.rgb), op, [cam],
                                   shade=SHADE_AMBIENT).rgb.numpy()[0]
    unlit = Renderer(device).render(g.state.centers, g.state.covariances, rgb_to_sh(g.binding.rgb), op,
                                    [cam]).rgb.numpy()[0]
    err = np.abs(host - kern).max(axis=-1)
    assert np.quantile(err, 0.99) < 2e-3 and err.max() < 2e-2, err.max()
    assert np.abs(unlit - kern).max() > 0.05


def _warp_points(V, device):
    import warp as wp

    return wp.array(np.asarray(V, np.float32), dtype=wp.vec3, device=device)


def _warp_indices(F, device):
    import warp as wp

    return wp.array(np.asarray(F, np.int32).reshape(-1), dtype=wp.int32, device=device)


def test_render_cli_never_writes_over_its_inputs_or_users_files(tmp_path, capsys):
    """Outputs checked before any work: --figure at the scene file, --video into an existing file,
    --out into a folder with a user's frame_0000.png are refused (exit 2, the field named) and
    leave every file byte-identical; --overwrite replaces only what the tool wrote."""
    import yaml

    from dynmesh_warp.render import main

    scene = tmp_path / "s.yaml"
    scene.write_text(yaml.safe_dump({"name": "s", "surface": {"source": "builtin:pulsing_blob",
                                                                "params": {"subdivisions": 1}},
                                     "spheres": [], "gaussians": {"count": 200}}))
    before = scene.read_bytes()
    small = ["--width", "32", "--height", "24", "--frames", "1", "--moments", "1", "--no-progress", "--device", "cpu"]
    assert main([str(scene), "--figure", str(scene)] + small) == 2
    assert "--figure" in capsys.readouterr().err and scene.read_bytes() == before
    gif = tmp_path / "old.gif"
    gif.write_bytes(b"not mine")
    assert main([str(scene), "--video", str(gif)] + small) == 2
    assert "--video" in capsys.readouterr().err and gif.read_bytes() == b"not mine"
    user = tmp_path / "photos"
    user.mkdir()
    (user / "frame_0000.png").write_bytes(b"a user's picture")
    for extra in ([], ["--overwrite"]):
        assert main([str(scene), "--out", str(user)] + small + extra) == 2
        assert "--out" in capsys.readouterr().err
    assert (user / "frame_0000.png").read_bytes() == b"a user's picture"
    # the tool's own frames: a second run replaces them with --overwrite only
    out = tmp_path / "frames"
    assert main([str(scene), "--out", str(out)] + small) == 0
    assert main([str(scene), "--out", str(out)] + small) == 2
    assert main([str(scene), "--out", str(out), "--overwrite"] + small) == 0
    assert (out / "frame_0000.png").read_bytes()[:4] == b"\x89PNG"


def test_an_sh_degree_beyond_the_coefficients_and_a_camera_at_its_target_are_refused():
    """sh_degree above what the (G, K, 3) coefficients hold read past each Gaussian's own
    (colours of 1e36 on the CPU); a look_at camera whose eye is its target has no direction
    (a NaN camera, a blank image). Both are ValueErrors naming the values; degrees up to the
    coefficients' render."""
    import re

    from dynmesh_warp.render import Renderer, look_at, rgb_to_sh

    rng = np.random.default_rng(0)
    G = 20
    means = rng.uniform(-0.5, 0.5, (G, 3)).astype(np.float32)
    covs = np.tile(np.eye(3, dtype=np.float32) * 0.02 ** 2, (G, 1, 1))
    sh, op = rgb_to_sh(rng.uniform(0, 1, (G, 3))), np.full(G, 0.9, np.float32)
    cam = look_at([2, 0, 0.5], [0, 0, 0], width=16, height=16)
    r = Renderer("cpu")
    with pytest.raises(ValueError, match=re.escape("sh_degree 3: the sh array holds 1 coefficient(s)")):
        r.render(means, covs, sh, op, [cam], sh_degree=3)
    assert np.isfinite(r.render(means, covs, sh, op, [cam], sh_degree=0).rgb.numpy()).all()
    with pytest.raises(ValueError, match=r"look_at: eye \[1.0, 0.0, 0.0\] and target \[1.0, 0.0, 0.0\]"):
        look_at([1, 0, 0], [1, 0, 0])


def test_render_cli_speaks_like_the_other_clis(tmp_path, capsys):
    """A bad argument is one ``error:`` line (no usage block), as run / convert / evaluate; a
    truly varying mesh sequence renders as a mesh with the rebuild collider set by --set, and
    the refusal without it names that --set (render has no --collider flag)."""
    import subprocess
    import sys

    from dynmesh_warp.render import main
    from dynmesh_warp.scenes import torus_to_sphere

    with pytest.raises(SystemExit) as e:
        main(["--bogus"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: unrecognized arguments: --bogus") and "usage:" not in err
    from dynmesh_warp.io import save_sequence

    folder = tmp_path / "frames"
    save_sequence(torus_to_sphere(frames=6, resolution=16), folder, fmt="ply")
    cmd = [sys.executable, "-m", "dynmesh_warp.render", str(folder), "--mesh", "--no-splats", "--figure",
           str(tmp_path / "f.png"), "--moments", "1", "--width", "32", "--height", "24", "--no-progress",
           "--device", "cpu"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode != 0 and "--set physics.collider=rebuild" in r.stderr and "Module " not in r.stderr
    r = subprocess.run(cmd + ["--set", "physics.collider=rebuild"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "f.png").exists() and "Module " not in r.stdout + r.stderr and "Warp " not in r.stdout


@pytest.mark.parametrize("opt,value,need", [("--width", "0", "--width must be 16..16384 pixels, got 0"),
                                            ("--fps", "0", "--fps must be a positive, finite frame rate, got 0.0"),
                                            ("--frames", "0", "--frames must be at least 1, got 0"),
                                            ("--moments", "0", "--moments must be at least 1, got 0")])
def test_a_bad_render_value_is_named_with_its_value(opt, value, need, capsys):
    """One line for any of five bad values listed all five (a new user's); now the one given."""
    from dynmesh_warp.render import main

    with pytest.raises(SystemExit) as e:
        main(["--out", "unused_dir", opt, value])
    assert e.value.code == 2 and need in capsys.readouterr().err


def _ewa_alpha_3dgs(mean_cam, cov_cam, opacity, fx, fy, W, H, clamp=1.3):
    """Alpha (H, W) of one Gaussian (camera-space centre and covariance, camera at the origin
    looking down +z) written out from the 3DGS paper / gsplat in float64, independently of the
    kernels: J of the perspective map at the centre with x/z, y/z clamped to 1.3 tan_fov
    (tan_fovx = 0.5 W / fx; cx = W / 2), 2-D covariance J cov J^T + 0.3 I, pixel centres at
    (i + 0.5, j + 0.5), alpha = min(0.999, o exp(-d^T cov2d^-1 d / 2)). Returns (alpha, the
    squared Mahalanobis distance)."""
    x, y, z = (float(v) for v in mean_cam)
    limx, limy = clamp * 0.5 * W / fx, clamp * 0.5 * H / fy
    tx, ty = z * min(max(x / z, -limx), limx), z * min(max(y / z, -limy), limy)
    J = np.array([[fx / z, 0.0, -fx * tx / z**2], [0.0, fy / z, -fy * ty / z**2]])
    cov2d = J @ np.asarray(cov_cam, np.float64) @ J.T + 0.3 * np.eye(2)
    u, v = fx * x / z + W / 2, fy * y / z + H / 2
    px, py = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([px - u, py - v], -1)
    m = np.einsum("hwi,ij,hwj->hw", d, np.linalg.inv(cov2d), d)
    return np.minimum(0.999, opacity * np.exp(-0.5 * m)), m


@pytest.mark.parametrize("axis,sign", [(0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)])
def test_a_gaussian_just_off_screen_is_clamped_at_1p3_the_half_fov(device, axis, sign):
    """The EWA Jacobian takes the centre clamped to 1.3x the half field of view (3DGS, gsplat:
    lim = (W - cx) / fx + 0.3 tan_fovx). The kernel used 0.3 W / fx (1.6x): a large Gaussian
    whose centre is at 1.45x the half fov, reaching into the image, was drawn with the
    unclamped Jacobian (alpha off by ~1e-2). Checked against the closed form above, on both
    sides of both axes."""
    from dynmesh_warp.render import Camera

    W, H, fx, fy = 64, 48, 50.0, 45.0
    cam = Camera(np.eye(3), np.zeros(3), fx, fy, W / 2, H / 2, W, H)
    z = 2.0
    p = np.array([0.0, 0.0, z])
    p[axis] = sign * 1.45 * 0.5 * (W / fx if axis == 0 else H / fy) * z
    S = np.array([0.9, 0.7, 0.5])
    cov = np.diag(S**2)
    op = 0.8
    want, m = _ewa_alpha_3dgs(p, cov, op, fx, fy, W, H)
    out = Renderer(device).render(p[None].astype(np.float32), cov[None].astype(np.float32),
                                  rgb_to_sh(np.array([[0.2, 0.6, 0.9]])), np.array([op], np.float32), [cam])
    alpha = out.alpha.numpy()[0]
    near = m < 9.0  # within 3 sigma: every such pixel lies in a tile the splat touches
    assert near.sum() > 100 and want[near].max() > 0.1  # it reaches well into the image
    np.testing.assert_allclose(alpha[near], want[near], atol=2e-5)
    # the old 1.6x clamp gives another footprint (what the test tells apart)
    old, _ = _ewa_alpha_3dgs(p, cov, op, fx, fy, W, H, clamp=1.6)
    assert np.abs(old[near] - want[near]).max() > 1e-3


@pytest.mark.parametrize("background", [(0.0, 0.0, 0.0), (1.0, 1.0, 1.0)])
def test_a_bright_splat_renders_its_unclipped_colour(device, background):
    """3DGS clamps the DC colour at 0 only: f_dc 3.0 is 1.346, and the image (not the colour) is
    clipped to [0, 1]. A splat read as f_dc (3.0, 1.0, -3.0), bound to a mesh and drawn through
    ``render_world``'s colour path, against the closed form min(1, c alpha + bg (1 - alpha)) with
    alpha written out in float64 (``_ewa_alpha_3dgs``). The binding clipped the colour to 1
    before: 0.364 darker at alpha 0.8 over black."""
    from dynmesh_warp.gaussians import bind_splats
    from dynmesh_warp.render import Camera, _binding_colours
    from dynmesh_warp.splat_io import SplatCloud

    W, H, fx, fy = 48, 40, 40.0, 40.0
    cam = Camera(np.eye(3), np.zeros(3), fx, fy, W / 2, H / 2, W, H)
    p, S = np.array([0.1, -0.05, 2.0]), np.array([0.3, 0.25, 0.01])
    cloud = SplatCloud.from_activated(p[None], S[None], [[1.0, 0, 0, 0]], [[1.0, 1.0, 1.0]], [0.8])
    cloud.data["f_dc_0"], cloud.data["f_dc_1"], cloud.data["f_dc_2"] = 3.0, 1.0, -3.0
    V = np.array([[-1, -1, 2], [1, -1, 2], [1, 1, 2], [-1, 1, 2]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    g = bind_splats(cloud, V, F, device=device)
    import warp as wp

    g.update(wp.array(V, dtype=wp.vec3, device=device), wp.array(F.reshape(-1), dtype=wp.int32, device=device))
    r = Renderer(device)
    sh, op = _binding_colours(r, g.binding, device)
    out = r.render(g.state.centers, g.state.covariances, sh, op, [cam], background=background)
    rgb = out.rgb.numpy()[0]
    alpha, m = _ewa_alpha_3dgs(p, np.diag(S**2), 0.8, fx, fy, W, H)
    col = np.maximum(0.5 + 0.28209479177387814 * np.array([3.0, 1.0, -3.0]), 0.0)  # 1.346, 0.782, 0
    want = np.clip(col * alpha[..., None] + np.asarray(background) * (1 - alpha[..., None]), 0.0, 1.0)
    near = m < 9.0
    assert alpha[near].max() > 0.7
    np.testing.assert_allclose(rgb[near], want[near], atol=1e-4)
    assert rgb.max() <= 1.0 and rgb.min() >= 0.0
    if background[0] == 0.0:
        assert rgb[..., 0].max() > 1.0 * alpha.max() + 0.2  # brighter than a colour clipped to 1 could be


_GOOD = dict(R=np.eye(3), t=np.zeros(3), fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64, height=48)


@pytest.mark.parametrize("field,value,said", [
    ("fx", 0.0, "Camera: fx must be a finite focal length > 0 [px], got 0"),
    ("fx", -50.0, "Camera: fx must be a finite focal length > 0 [px], got -50"),
    ("fx", float("nan"), "Camera: fx must be a finite focal length > 0 [px], got nan"),
    ("fy", float("inf"), "Camera: fy must be a finite focal length > 0 [px], got inf"),
    ("cx", float("nan"), "Camera: cx must be finite [px], got nan"),
    ("cy", float("-inf"), "Camera: cy must be finite [px], got -inf"),
    ("R", np.eye(3) * 1.1, "Camera: R must be a rotation (orthonormal, det +1, to 0.0001), got [[1.1, 0.0, 0.0]"),
    ("R", np.diag([1.0, 1.0, -1.0]), "det -1"),
    ("R", np.array([[1, 0.2, 0], [0, 1, 0], [0, 0, 1]]), "max |R R^T - I| 0.2"),
    ("R", np.full((3, 3), np.nan), "Camera: R must be finite, got [[nan"),
    ("R", np.eye(4), "Camera: R must be (3, 3) and t (3,), got R (4, 4)"),
    ("t", np.array([0.0, np.nan, 0.0]), "Camera: t must be finite [m], got [0.0, nan, 0.0]"),
    ("width", 0, "Camera: width must be a positive integer [px], got 0"),
    ("width", 64.0, "Camera: width must be a positive integer [px], got 64.0"),
    ("height", -48, "Camera: height must be a positive integer [px], got -48"),
    ("height", True, "Camera: height must be a positive integer [px], got True"),
])
def test_a_bad_camera_value_is_named_when_the_camera_is_made(field, value, said):
    """fx 0 or < 0, a non-rotation R, NaN anywhere rendered without a word (NaN: an all-background
    image); width 0 an empty image, a float width a TypeError deep inside Warp. Now each is a
    ValueError naming the field and its value where the camera is made; a good camera is made
    (and renders, the tests above)."""
    import re

    from dynmesh_warp.render import Camera

    Camera(**_GOOD)
    with pytest.raises(ValueError, match=re.escape(said)):
        Camera(**{**_GOOD, field: value})


@pytest.mark.parametrize("kw,said", [
    ({"fov_y_deg": 0}, "look_at: fov_y_deg must be in (0, 180) degrees, got 0"),
    ({"fov_y_deg": 180.0}, "look_at: fov_y_deg must be in (0, 180) degrees, got 180.0"),
    ({"fov_y_deg": float("nan")}, "look_at: fov_y_deg must be in (0, 180) degrees, got nan"),
    ({"up": (0, 0, 0)}, "look_at: up must be a finite, non-zero 3-vector, got [0.0, 0.0, 0.0]"),
    ({"up": (0, 0, np.nan)}, "look_at: up must be a finite, non-zero 3-vector, got [0.0, 0.0, nan]"),
    ({"up": (0, 0, -2)}, "look_at: up [0.0, 0.0, -2.0] is parallel to the view direction [0.0, 0.0, -1.0]"),
    ({"width": 64.5}, "look_at: width must be a positive integer [px], got 64.5"),
    ({"height": 0}, "look_at: height must be a positive integer [px], got 0"),
])
def test_look_at_refuses_what_makes_no_camera(kw, said):
    """fov 0 was a ZeroDivisionError, up (0, 0, 0) or along the view a NaN camera with only a
    RuntimeWarning (the docs said look_at guards against NaN cameras)."""
    import re
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning on the way
        with pytest.raises(ValueError, match=re.escape(said)):
            look_at([0, 0, 3], [0, 0, 0], **{"up": (0, 1, 0), **kw})
        cam = look_at([0, 0, 3], [0, 0, 0], up=(0, 1, 0), fov_y_deg=179.0, width=np.int64(8), height=8)
    assert np.isfinite(cam.R).all() and cam.fx > 0


def test_a_camera_changed_after_it_was_made_is_refused_by_the_render():
    """The render checks the cameras again when their values change (a camera's fields can be
    set after it is made): a NaN or zero set later is named with the camera's index."""
    means, covs, sh, op = _scene(20, 1, 0)
    cams = orbit_cameras([0, 0, 0], 3.5, 2, width=16, height=16)
    r = Renderer("cpu")
    r.render(means, covs, sh, op, cams)
    cams[1].fx = 0.0
    with pytest.raises(ValueError, match=r"render: camera 1: fx must be a finite focal length > 0 \[px\], got 0"):
        r.render(means, covs, sh, op, cams)
    cams[1].fx, cams[0].t = 10.0, np.array([0.0, np.nan, 1.0])
    with pytest.raises(ValueError, match=r"render: camera 0: t must be finite"):
        r.render(means, covs, sh, op, cams)
    cams[0].t, cams[0].width, cams[1].width = np.zeros(3), 16.0, 16.0
    with pytest.raises(ValueError, match=r"render: camera 0: width must be a positive integer \[px\], got 16.0"):
        r.render(means, covs, sh, op, cams)


@pytest.mark.parametrize("fps, dt", [(100.0, 1 / 240), (25.0, 1 / 240), (24.0, 0.005), (30.0, 1 / 60)])
def test_each_frame_shows_its_own_time(fps, dt):
    """Frame k shows the world at k / fps to within dt / 2: --fps 100 at dt = 1/240 took 2 steps a
    frame (1/120 s: the images of --fps 120), --fps 25 ran 4 % fast (a new user's)."""
    from dynmesh_warp.render import frame_steps

    steps = frame_steps(200, fps, dt)
    assert steps[0] == 0 and (steps >= 0).all()
    shown = np.cumsum(steps) * dt
    assert np.abs(shown - np.arange(200) / fps).max() <= dt / 2 + 1e-12


@pytest.mark.parametrize("fps", [24.0, 30.0, 60.0, 12.5])
def test_a_gif_plays_at_its_frame_rate(tmp_path, fps):
    """GIF delays are whole 1/100 s: one 40 ms delay played 24 fps at 25, and 60 fps was written
    with 10 ms delays that browsers play as 100 ms. Read back with Pillow: every delay at least
    20 ms, and the frames' times within 10 ms of k / fps (frames left out above 50 fps)."""
    from PIL import Image

    from dynmesh_warp.render import _write_video

    n = 30
    frames = [np.full((8, 8, 3), 8 * k, np.uint8) for k in range(n)]
    _write_video(tmp_path / "v.gif", frames, fps)
    gif = Image.open(tmp_path / "v.gif")
    delays = []
    for i in range(gif.n_frames):
        gif.seek(i)
        delays.append(gif.info["duration"])
    every = n // gif.n_frames if gif.n_frames < n else 1
    assert min(delays) >= 20 and (every == 1) == (fps <= 50)
    starts = np.concatenate([[0], np.cumsum(delays)])[:-1] / 1000.0
    assert np.abs(starts - np.arange(gif.n_frames) * every / fps).max() <= 0.0101, delays
