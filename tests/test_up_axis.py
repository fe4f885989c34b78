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


def test_carried_lists_every_field_a_copy_keeps():
    """``sequence.carried`` is the one list of what a copy keeps: a field added to the sequences
    and not to it fails here (the up axis was lost by copies that named their fields by hand)."""
    import dataclasses

    from dynmesh_warp.sequence import VaryingTopologySequence, carried

    seq = articulated_figure(frames=2, resolution=16)
    y = FixedTopologySequence(seq.V, seq.F, 30.0, "s", source="src.glb", up_axis="y")
    # what a copy takes anew: the frames, and what belongs to frame 0's vertices (passed where they are the same)
    per_frame = {"V", "F", "frames", "frame_sources", "colors"}
    for cls, obj in ((FixedTopologySequence, y), (VaryingTopologySequence, y.to_varying())):
        assert set(carried(obj)) == {f.name for f in dataclasses.fields(cls)} - per_frame
    assert carried(y) == {"fps": 30.0, "name": "s", "source": "src.glb", "up_axis": "y"}
    assert carried(y, fps=60.0)["fps"] == 60.0
    with pytest.raises(TypeError, match="unknown field"):
        carried(y, up="y")


def test_convert_turns_a_sheet_up_along_the_inputs_up_axis(tmp_path):
    """A y-up input's sheet, wound inconsistently, is made consistent and turned to face +Y (up,
    against gravity) before the fit; it was turned along +Z, which a horizontal y-up sheet has no
    side for: it came out facing down."""
    import trimesh

    from dynmesh_warp.convert import to_fixed_topology
    from dynmesh_warp.sequence import VaryingTopologySequence

    n = 12
    g = np.linspace(-0.5, 0.5, n)
    X, Z = np.meshgrid(g, g, indexing="ij")
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            F += [(a, a + n, a + 1), (a + 1, a + n, a + n + 1)]
    F = np.array(F, np.int32)
    V0 = np.c_[X.ravel(), np.zeros(n * n), Z.ravel()]
    assert trimesh.Trimesh(V0, F, process=False).face_normals[:, 1].mean() < -0.99  # wound facing -y (down)
    rng = np.random.default_rng(0)
    Fm = F.copy()
    flip = rng.random(len(F)) < 0.2  # an exporter's random flips: the majority still faces down
    Fm[flip] = Fm[flip][:, ::-1]
    frames = [((V0 + [0.0, 0.02 * t, 0.0]).astype(np.float32), Fm) for t in range(3)]  # rising
    var = VaryingTopologySequence(frames, fps=24.0, name="sheet", up_axis="y")
    out = to_fixed_topology(var, device="cpu", iterations=1, refine_rounds=0)
    normals = trimesh.Trimesh(out.V[0], out.F, process=False).face_normals
    assert (normals[:, 1] > 0.99).all()  # every face up (+y) once made consistent
    # the same sheet said z-up keeps the majority's side: +Z has no up or down side to give it
    var_z = VaryingTopologySequence(frames, fps=24.0, name="sheet", up_axis="z")
    out_z = to_fixed_topology(var_z, device="cpu", iterations=1, refine_rounds=0)
    assert (trimesh.Trimesh(out_z.V[0], out_z.F, process=False).face_normals[:, 1] < -0.99).all()
