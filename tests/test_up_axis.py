"""A sequence's up axis survives what the package derives from it (docs/data.md): re-meshing,
conversion, the sequence's own copies. A re-meshed glTF "reconstruction" lost it: its source
no longer named the file that said +Y up, so it and its conversion were read z-up (a new user's
fox lay on its side)."""
import numpy as np
import pytest

from dynmesh_warp.config import SceneError, load_scene_config
from dynmesh_warp.io import load_sequence, save_sequence, sequence_up_axis
from dynmesh_warp.remesh import remesh_sequence
from dynmesh_warp.scene import load_surface
from dynmesh_warp.sequence import FixedTopologySequence
from dynmesh_warp.scenes import articulated_figure


def _y_up_figure(tmp_path):
    """The articulated figure (z-up) turned to +Y up and saved as a glTF-derived npz would be."""
    seq = articulated_figure(frames=3, resolution=24)
    V = seq.V[:, :, [0, 2, 1]] * np.array([1.0, 1.0, -1.0], np.float32)  # (x, y, z) -> (x, z, -y): y up
    y = FixedTopologySequence(V, seq.F, seq.fps, "figure_y", up_axis="y")  # a rotation: faces kept
    save_sequence(y, tmp_path / "gt.npz")
    return seq, load_sequence(tmp_path / "gt.npz")


def test_remesh_and_convert_keep_the_up_axis(tmp_path):
    from dynmesh_warp.convert import to_fixed_topology

    z_up, gt = _y_up_figure(tmp_path)
    assert gt.up_axis is None and sequence_up_axis(gt) == "y"  # said by its file, as a glTF's is
    var = remesh_sequence(gt, resolution=24, device="cpu")
    assert var.up_axis == "y"
    save_sequence(var, tmp_path / "var.npz")
    assert sequence_up_axis(load_sequence(tmp_path / "var.npz")) == "y"
    out = to_fixed_topology(var, device="cpu", iterations=1, refine_rounds=0)
    assert sequence_up_axis(out) == "y"
    save_sequence(out, tmp_path / "fixed.npz")
    # played as a scene (up axis auto), each stands as the z-up original does: its height along z
    # (thin arms may go at this coarse re-mesh, so the height is what is compared)
    for path in ("gt.npz", "var.npz", "fixed.npz"):
        cfg = load_scene_config(data={"surface": {"source": str(tmp_path / path), "playback": "loop"}})
        played = load_surface(cfg)
        V0 = np.asarray(played.V[0] if hasattr(played, "V") else played.frames[0][0])
        ext = V0.max(0) - V0.min(0)
        ref = z_up.V[0].max(0) - z_up.V[0].min(0)
        assert int(np.argmax(ext)) == 2 and abs(ext[2] - ref[2]) < 0.15 * ref[2], (path, ext, ref)


def test_a_sequences_own_copies_keep_the_up_axis():
    seq = articulated_figure(frames=4, resolution=20)
    y = FixedTopologySequence(seq.V, seq.F, seq.fps, "s", up_axis="y")
    assert y.reordered([1, 0]).up_axis == "y"
    assert y.upsampled(2).up_axis == "y"
    assert y.to_varying().up_axis == "y"
    assert y.to_varying().to_fixed().up_axis == "y"


def test_a_yaml_mapping_without_spaces_is_explained():
    with pytest.raises(SceneError, match=r"spheres\.count:40: unknown key \(YAML needs a space after the colon: count: 40\)"):
        load_scene_config(overrides=["spheres={count:40,radius:0.03}"])
