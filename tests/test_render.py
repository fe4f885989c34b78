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
