"""Newton adapter: Newton bodies against our deforming mesh (CPU, skipped without newton).

Surfaces are small 16x16 / 24x24 ``scenes.grid_sheet`` sheets moved up over time. Newton's
CPU kernels compile once (~1 min cold, cached in Warp's kernel cache after); runs are a few
hundred steps.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import warp as wp
from conftest import project_to_mesh
from reference import brute_nearest
from scipy.optimize import brentq

from dynmesh_warp.scenes import grid_sheet
from dynmesh_warp.sequence import FixedTopologySequence
from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, World

newton = pytest.importorskip("newton")

from dynmesh_warp.newton_adapter import DeformingMeshShape, NewtonWorld  # noqa: E402

FPS = 24.0
RISE = 0.4  # [m] over the first second, then the sheet holds (playback clamp)


def rising_sheet(n: int = 16, rise: float = RISE, frames: int = 25, dimples=None) -> FixedTopologySequence:
    """A flat 2 m sheet at z = 0 rising linearly by ``rise`` over (frames-1)/FPS s; optional
    Gaussian dimples (centre xy, depth, width) pressed into it (a rest spot for a sphere)."""
    V0, F = grid_sheet(n, 2.0)
    z = np.zeros(len(V0))
    for c, depth, width in dimples or []:
        z -= depth * np.exp(-((V0[:, :2] - np.asarray(c)) ** 2).sum(1) / width**2)
    V = np.repeat(V0[None], frames, 0).astype(np.float64)
    V[:, :, 2] = np.linspace(0.0, rise, frames)[:, None] + z[None]
    return FixedTopologySequence(V.astype(np.float32), F, fps=FPS, name="rising_sheet")


def box_world(seq, update_bounds=True, solver="xpbd", pos=(0.2, 0.1, 0.1)):
    b = newton.ModelBuilder()
    body = b.add_body(xform=wp.transform(wp.vec3(*pos), wp.quat_identity()))
    b.add_shape_box(body, hx=0.1, hy=0.1, hz=0.1)
    return NewtonWorld(SurfaceModel(seq, "cpu", playback="clamp"), b, solver=solver, update_bounds=update_bounds)


def test_import_does_not_import_newton():
    code = "import sys, dynmesh_warp, dynmesh_warp.newton_adapter; assert 'newton' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_surface_gets_its_own_mesh_and_current_state(device):
    """Two adapters on identical geometry plus a plain newton.Mesh with the same content: three
    different wp.Mesh objects; update() writes the interpolated frame, velocities and bounds."""
    seq = rising_sheet(16)
    b = newton.ModelBuilder()
    a1 = DeformingMeshShape(SurfaceModel(seq, device, playback="clamp"))
    a2 = DeformingMeshShape(SurfaceModel(seq, device, playback="clamp"))
    s1, s2 = a1.add_to_builder(b), a2.add_to_builder(b)
    s3 = b.add_shape_mesh(-1, mesh=newton.Mesh(seq.V[0], seq.F.reshape(-1), compute_inertia=False))
    model = b.finalize(device=device)
    t = wp.array([0.3], dtype=wp.float64, device=device)
    a1.bind(model, t)
    a2.bind(model, wp.zeros(1, dtype=wp.float64, device=device))
    ptr = model.shape_source_ptr.numpy()
    assert len({int(ptr[s1]), int(ptr[s2]), int(ptr[s3])}) == 3
    # writing to one leaves the other (and the plain one) untouched
    k = int(np.floor(0.3 * FPS))
    alpha = 0.3 * FPS - k
    expect = (1 - alpha) * seq.V[k].astype(np.float64) + alpha * seq.V[k + 1]
    np.testing.assert_allclose(a1.mesh.points.numpy(), expect, atol=1e-6)
    np.testing.assert_allclose(a1.mesh.velocities.numpy(), (seq.V[k + 1] - seq.V[k]) * FPS, atol=1e-4)
    np.testing.assert_allclose(a2.mesh.points.numpy(), seq.V[0], atol=1e-7)
    # bounds of shape s1 = NumPy min / max / max-norm of the current points; s2 still frame 0
    lo, hi, rad = (x.numpy() for x in (model.shape_collision_aabb_lower, model.shape_collision_aabb_upper,
                                        model.shape_collision_radius))
    np.testing.assert_allclose(lo[s1], expect.min(0), atol=1e-6)
    np.testing.assert_allclose(hi[s1], expect.max(0), atol=1e-6)
    np.testing.assert_allclose(rad[s1], np.linalg.norm(expect, axis=1).max(), atol=1e-6)
    np.testing.assert_allclose(hi[s2], seq.V[0].max(0), atol=1e-6)
    # the BVH was refit: BVH closest-point queries match a brute-force search on the new points
    q = np.array([[0.1, -0.2, 0.5], [-0.7, 0.3, -0.2], [0.33, 0.6, 0.05]])
    _, _, _, dist = project_to_mesh(a1.mesh, q, device)
    ref, _, _ = brute_nearest(q, expect, seq.F)
    np.testing.assert_allclose(dist, ref, atol=1e-5)


def test_rising_surface_lifts_box_and_bounds_update_is_needed():
    """A box resting on a sheet that rises 0.4 m in 1 s rides on it (z = sheet + half height);
    with the per-sub-step bounds update switched off Newton's broad phase keeps the first frame's
    AABB and the box is lost (thrown off or falls through)."""
    seq = rising_sheet(16)
    zs = {}
    for ub in (True, False):
        w = box_world(seq, update_bounds=ub)
        track = []
        for i in range(360):  # 1.5 s at 1/240 s
            w.step()
            if (i + 1) % 60 == 0:
                track.append((w.time, float(w.body_transforms()[0, 2])))
        zs[ub] = track
        if ub:
            assert np.isfinite(w.body_transforms()).all()
    for t, z in zs[True]:
        sheet = RISE * min(t, 1.0)
        assert abs(z - (sheet + 0.1)) < 4e-3, (t, z, sheet)  # 4 mm: lag of one sub-step of rise + solver slop
    t_end, z_end = zs[False][-1]
    assert abs(z_end - (RISE + 0.1)) > 0.1, zs[False]


def _rest_height(V, F, p, r):
    """Reference: the height at which a sphere of radius r centred over p's xy just touches the
    mesh (brute-force closest point over all triangles, root-found along z within 2 cm of p)."""
    f = lambda z: float(brute_nearest(np.array([[p[0], p[1], z]]), V, F)[0][0]) - r  # noqa: E731
    return brentq(f, p[2] - 0.02, p[2] + 0.02, xtol=1e-7)


def test_spheres_rest_at_same_heights_as_our_world(device):
    """Spheres dropped into three dimples of a rising sheet come to rest at the same heights in
    our World and in Newton (XPBD), both within 1.5 mm of the brute-force touching height."""
    dimples = [((-0.5, -0.5), 0.05, 0.3), ((0.5, -0.5), 0.10, 0.3), ((0.0, 0.5), 0.15, 0.3)]
    seq = rising_sheet(24, rise=0.2, dimples=dimples)
    r = 0.06
    pos = np.array([[c[0], c[1], 0.3] for c, _, _ in dimples], np.float32)
    steps = 480  # 2 s: 1 s of rise, 1 s holding
    surf = SurfaceModel(seq, device, playback="clamp")
    model = Model(surf, SphereModel([r] * 3, 1.0, device), PhysicsParams(dt=1 / 240))
    ours = World(model, State(model, pos))
    b = newton.ModelBuilder()
    for p in pos:
        body = b.add_body(xform=wp.transform(wp.vec3(*[float(x) for x in p]), wp.quat_identity()))
        b.add_shape_sphere(body, radius=r)
    nw = NewtonWorld(SurfaceModel(seq, device, playback="clamp"), b, dt=1 / 240)
    for _ in range(steps):
        ours.step()
        nw.step()
    p_ours = ours.sphere_positions()
    p_newton = nw.body_transforms()[:, :3]
    V_end = seq.V[-1].astype(np.float64)
    for p in (p_ours, p_newton):
        ref = np.array([_rest_height(V_end, seq.F, q, r) for q in p])
        np.testing.assert_allclose(p[:, 2], ref, atol=1.5e-3)
    # they stay in their dimples (different heights) and agree with each other
    np.testing.assert_allclose(p_newton[:, 2], p_ours[:, 2], atol=2e-3)
    # within one grid cell (2 m / 23) of the dimple's centre: the shallowest dimple's faceted bottom
    # is nearly flat over a cell, and Newton on CUDA (atomic order) left that sphere 3.4 cm off once
    # in an 8-worker run on an H200 (0.4-1.8 cm otherwise)
    np.testing.assert_allclose(p_newton[:, :2], pos[:, :2], atol=2.0 / 23)
    assert np.all(np.diff(p_ours[:, 2]) < -0.03)


def test_scene_yaml_runs_newton_bodies(tmp_path, device):
    """A scene with a ``newton:`` section runs through run_scene: a box and a scene sphere drop
    onto a flat sheet and rest on it; summary and trajectories are written; bad bodies are
    reported with their field."""
    from dynmesh_warp.config import SceneError, load_scene_config
    from dynmesh_warp.run import run_scene

    seq = rising_sheet(16, rise=0.0, frames=2)
    npz = tmp_path / "sheet.npz"
    np.savez(npz, V=seq.V, F=seq.F, fps=FPS)
    scene = {
        "name": "nt", "device": device,
        "surface": {"source": str(npz)},
        "spheres": [{"position": [0.5, 0.5, 0.3], "radius": 0.05, "mass": 1.0}],
        "newton": {"solver": "xpbd", "bodies": [
            {"type": "box", "position": [-0.3, 0.0, 0.3], "half_extents": [0.1, 0.1, 0.05]}]},
        "run": {"steps": 240, "output": str(tmp_path / "out")},
        "physics": {"margin": 0.05, "sphere_body": "solid"},  # the built-in world's: said to be ignored
    }
    import yaml

    path = tmp_path / "nt.yaml"
    path.write_text(yaml.safe_dump(scene))
    with pytest.warns(UserWarning, match=r"physics\.margin, physics\.sphere_body: the built-in world's .* ignored"):
        summary = run_scene(load_scene_config(path), progress=False, log=lambda *a: None)
    q = np.asarray(summary["final"]["body_q"])
    assert summary["engine"] == "newton" and q.shape == (2, 7)
    np.testing.assert_allclose(q[:, 2], [0.05, 0.05], atol=3e-3)  # box half height, sphere radius
    assert (tmp_path / "out" / "summary.json").is_file()
    assert np.load(tmp_path / "out" / "trajectories.npz")["body_q"].shape[1:] == (2, 7)
    scene["newton"]["bodies"][0].pop("half_extents")
    path.write_text(yaml.safe_dump(scene))
    with pytest.raises(SceneError, match=r"newton\.bodies\.0.*half_extents"):
        load_scene_config(path)


def test_newton_scene_gets_the_ground_plane_and_clear_solver_errors(tmp_path, device):
    """physics.ground reaches Newton too (a box rests on the plane above the sheet); an unknown
    solver option is a SceneError naming newton.solver_options, not a traceback."""
    from dynmesh_warp.config import SceneError, load_scene_config
    from dynmesh_warp.newton_adapter import build_newton_world

    seq = rising_sheet(16, rise=0.0, frames=2)
    npz = tmp_path / "sheet.npz"
    np.savez(npz, V=seq.V, F=seq.F, fps=FPS)
    data = {"device": device, "surface": {"source": str(npz)}, "spheres": [], "physics": {"ground": 0.3},
            "newton": {"solver": "xpbd", "bodies": [
                {"type": "box", "position": [0.0, 0.0, 0.6], "half_extents": [0.1, 0.1, 0.05]}]}}
    w = build_newton_world(load_scene_config(data=data))
    for _ in range(240):
        w.step()
    assert w.body_transforms()[0, 2] == pytest.approx(0.35, abs=3e-3)  # on the plane, not the sheet (0.05)
    # a box under the ground is refused as a sphere is (a new user's was thrown up at 48 m/s); one
    # starting 4 cm into the sheet is warned of (it left at 6.4 m/s)
    data["newton"]["bodies"][0]["position"] = [0.0, 0.0, 0.3]
    with pytest.raises(SceneError, match=r"newton\.bodies\.0: centre z = 0.3 starts below the ground plane"):
        build_newton_world(load_scene_config(data=data))
    data["physics"] = {}
    data["newton"]["bodies"][0].update(position=[0.0, 0.0, 0.01], half_extents=[0.1, 0.1, 0.05])
    with pytest.warns(UserWarning, match=r"newton\.bodies\.0 \(box\) starts 0.04 m into the surface"):
        build_newton_world(load_scene_config(data=data))
    data["newton"]["solver_options"] = {"iterationz": 3}
    with pytest.raises(SceneError, match=r"newton\.solver_options.*iterationz"):
        build_newton_world(load_scene_config(data=data))


def test_newton_world_raises_substeps_for_its_thinnest_body(tmp_path, device):
    """The built-in world's sub-step rule, with the Newton bodies' thickness: a sheet oscillating
    at up to 8.5 m/s moves 3.5 cm in one sub-step of 1/240 s, over half a 5 cm box (a new user's
    box fell through it, unsaid): raised to 2 with a warning; auto_substeps off: only warned of."""
    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.newton_adapter import build_newton_world

    seq = rising_sheet(11, rise=0.0, frames=2)
    zs = 0.5 * np.sin(2 * np.pi * np.arange(8) / 8)
    np.savez(tmp_path / "osc.npz", V=np.stack([seq.V[0] + np.float32([0, 0, z]) for z in zs]), F=seq.F, fps=24.0)
    data = {"device": device, "surface": {"source": str(tmp_path / "osc.npz"), "playback": "loop"}, "spheres": [],
            "newton": {"solver": "xpbd", "bodies": [
                {"type": "box", "position": [-0.3, 0.0, 0.8], "half_extents": [0.08, 0.06, 0.05]}]}}
    speed = float(np.abs(np.diff(np.r_[zs, zs[0]])).max() * 24.0)  # 8.49 m/s, the loop's steepest
    need = int(np.ceil(speed * (1 / 240) / 0.025))
    assert need == 2
    with pytest.warns(UserWarning, match=r"raising substeps from 1 to 2 so it moves < half the thinnest Newton body"):
        w = build_newton_world(load_scene_config(data=data))
    assert w.substeps == need
    data["physics"] = {"auto_substeps": False}
    with pytest.warns(UserWarning, match=r"auto_substeps is off .* set physics.substeps to 2"):
        assert build_newton_world(load_scene_config(data=data)).substeps == 1
    # restitution > 0 on a moving surface: XPBD's restitution reads a riding body's velocity as if
    # the surface stood still (a new user's box on a floor rising at 1 m/s read 0.024 m/s): said
    data["physics"] = {"substeps": 3}
    with pytest.warns(UserWarning, match=r"restitution 0.3 turns on Newton XPBD's restitution.*restitution: 0"):
        build_newton_world(load_scene_config(data=data))
    data["physics"] = {"substeps": 3, "restitution": 0.0}  # enough sub-steps already: kept, nothing said
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert build_newton_world(load_scene_config(data=data)).substeps == 3


def test_viewer_shows_newton_bodies_and_the_recording_replays_them(tmp_path, device):
    """--record / --viewer on a scene with a ``newton:`` section draws every Newton shape at its
    pose, the deforming surface and its Gaussians (decoded from the .viser recording)."""
    pytest.importorskip("viser")
    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.gaussians import gaussians_for_surface
    from dynmesh_warp.newton_adapter import build_newton_world
    from dynmesh_warp.run import main
    from dynmesh_warp.viewer import NewtonViewer, SceneStateTracker, decode_viser_recording, scene_splat_centers

    data = {"name": "nv", "device": device, "surface": {"source": "builtin:wave_bowl", "params": {"n": 16, "frames": 6}},
            "spheres": [{"position": [0.3, 0.0, 0.9], "radius": 0.06}], "gaussians": {"count": 300},
            "newton": {"solver": "xpbd", "bodies": [
                {"type": "box", "position": [0.0, 0.0, 1.0], "half_extents": [0.1, 0.08, 0.05]},
                {"type": "capsule", "position": [-0.3, 0.2, 1.0], "radius": 0.05, "half_height": 0.1}]}}
    cfg = load_scene_config(data=data)
    nw = build_newton_world(cfg, device=device)
    g = gaussians_for_surface(nw.surface.sequence, cfg, nw.device)
    rec = tmp_path / "nv.viser"
    v = NewtonViewer(nw, g, port=0, realtime=False, record=rec, show_mesh=True, log=lambda *a: None)
    try:
        v.run(max_frames=5)
        X = nw.shape_transforms()
        P = nw.surface_points().numpy().copy()
        C = g.state.centers.numpy().copy()
    finally:
        v.close()
    assert nw.time > 0.1 and np.abs(X[[s["index"] for s in nw.shapes()], 2] - 1.0).max() > 0.01  # they moved
    replay = SceneStateTracker()
    for _, m in decode_viser_recording(rec.read_bytes())["messages"]:
        replay.apply(m)
    shapes = nw.shapes()
    assert sorted(s["type"] for s in shapes) == ["box", "capsule", "sphere"]
    for s in shapes:
        node = replay.nodes[f"/bodies/shape_{s['index']}"]
        np.testing.assert_allclose(np.asarray(node["position"], float), X[s["index"], :3], atol=1e-6)
        x, y, z, w = X[s["index"], 3:]
        wxyz = np.asarray(node.get("wxyz", (1.0, 0.0, 0.0, 0.0)), float)  # identity is not sent
        assert abs(abs(np.dot(wxyz, [w, x, y, z])) - 1.0) < 1e-6
    box = next(s for s in shapes if s["type"] == "box")
    Vb = replay.nodes[f"/bodies/shape_{box['index']}"]["vertices"].reshape(-1, 3)
    np.testing.assert_allclose(Vb.max(0), [0.1, 0.08, 0.05], atol=1e-6)  # drawn at its half extents
    assert np.array_equal(replay.nodes["/mesh"]["vertices"].reshape(-1, 3), P)
    # the splats, streamed as rigidly moving groups: each centre within the stream's fit error
    err = np.linalg.norm(scene_splat_centers(replay.nodes, v.stream.members) - C, axis=1)
    assert err.max() <= v.stream.error["max"] * v.scene_scale + 1e-5
    # the command line takes the same path
    out = tmp_path / "cli.viser"
    path = tmp_path / "nv.yaml"
    import yaml

    path.write_text(yaml.safe_dump(data))
    assert main([str(path), "--viewer", "none", "--steps", "8", "--record", str(out), "--port", "0",
                 "--device", device]) == 0
    nodes = SceneStateTracker()
    for _, m in decode_viser_recording(out.read_bytes())["messages"]:
        nodes.apply(m)
    assert sum(k.startswith("/bodies/") for k in nodes.nodes) == 3


def test_graph_capture_on_second_step_loads_only_used_modules(cuda_device):
    """NewtonWorld runs step 1 eagerly (loading exactly the modules Newton's pipeline and solver
    use) and captures step 2 without force-loading every module (which compiled all of Newton on
    a cold cache). The replayed graph follows the eager run."""

    @wp.kernel(module="unique")
    def unrelated(a: wp.array(dtype=float)):
        a[wp.tid()] = 1.0

    def world(use_graph):
        b = newton.ModelBuilder()
        body = b.add_body(xform=wp.transform(wp.vec3(0.2, 0.1, 0.1), wp.quat_identity()))
        b.add_shape_box(body, hx=0.1, hy=0.1, hz=0.1)
        return NewtonWorld(SurfaceModel(rising_sheet(), cuda_device, playback="clamp"), b, use_graph=use_graph)

    g, e = world(True), world(False)
    g.step()
    assert not g.graph_captured  # step 1 ran eagerly
    g.step()
    assert g.graph_captured
    for _ in range(118):
        g.step()
    for _ in range(120):
        e.step()
    assert not unrelated.module.execs, "capture loaded a module the step does not use"
    np.testing.assert_allclose(g.body_transforms()[:, :3], e.body_transforms()[:, :3], atol=2e-3)
    # 0.5 s in, the sheet has risen 0.2 m: the box (half height 0.1 m) rides on it
    assert abs(g.body_transforms()[0, 2] - (0.5 * RISE + 0.1)) < 0.01


def test_both_engines_satisfy_the_simulation_protocol(device):
    """The viewer and runners read one protocol (runtime.Simulation); the built-in world and the
    Newton world both provide it (no stand-in object for either)."""
    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.newton_adapter import build_newton_world
    from dynmesh_warp.runtime import Simulation
    from dynmesh_warp.scene import build_world

    data = {"device": device, "surface": {"source": "builtin:wave_bowl", "params": {"n": 8, "frames": 4}},
            "spheres": [{"position": [0.0, 0.0, 0.9], "radius": 0.06}]}
    w = build_world(load_scene_config(data=data))
    N = w.surface.num_vertices
    assert isinstance(w, Simulation) and w.editable and w.dt > 0
    assert w.surface_points().shape[0] == N and w.sphere_radii().shape == (1,)
    data["newton"] = {"solver": "xpbd", "bodies": [{"type": "box", "position": [0.0, 0.0, 1.0],
                                                    "half_extents": [0.1, 0.1, 0.05]}]}
    nw = build_newton_world(load_scene_config(data=data))
    assert isinstance(nw, Simulation) and not nw.editable
    assert nw.sphere_positions().shape == (0, 3) and nw.surface_points().shape[0] == N
    assert nw.surface_indices().shape == w.surface_indices().shape
    assert not isinstance(object(), Simulation)  # the check can fail


def test_one_builder_for_both_engines(device):
    """scene.build_model is the one builder: the built-in and the Newton world start from the same
    surface, spawned spheres (positions, radii, masses) and ground."""
    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.newton_adapter import build_newton_world
    from dynmesh_warp.scene import build_model, build_world, load_surface, scene_ground

    data = {"device": device, "surface": {"source": "builtin:wave_bowl", "params": {"n": 8, "frames": 4}},
            "spheres": {"count": 3, "radius": 0.05, "mass": 2.0, "seed": 7}, "physics": {"ground": "auto"}}
    cfg = load_scene_config(data=data)
    seq = load_surface(cfg)
    model, state = build_model(cfg, seq, device)
    w = build_world(cfg)
    np.testing.assert_array_equal(w.sphere_positions(), state.sphere_pos.numpy())
    assert model.params.ground_height == scene_ground(cfg, seq) == pytest.approx(float(seq.V[..., 2].min()))
    np.testing.assert_array_equal(model.spheres.mass_np, [2.0] * 3)
    data["newton"] = {"solver": "xpbd", "bodies": []}
    nw = build_newton_world(load_scene_config(data=data))
    np.testing.assert_allclose(nw.body_transforms()[:, :3], state.sphere_pos.numpy(), atol=1e-7)
    np.testing.assert_array_equal(nw.surface.frames.numpy(), model.surface.frames.numpy())


def test_replicated_newton_worlds_each_equal_the_single_world(device):
    """build_newton_world(num_worlds=4): Newton's own batching (ModelBuilder.replicate) with the
    deforming surface shared by every world; each world's bodies follow exactly the trajectory of
    the one-world run (the copies do not touch each other), and num_worlds < 1 is refused."""
    from dynmesh_warp.config import SceneError, load_scene_config
    from dynmesh_warp.newton_adapter import build_newton_world

    data = {"device": device, "surface": {"source": "builtin:wave_bowl", "params": {"n": 10, "frames": 6}},
            # restitution 0: XPBD's restitution pass (on with restitution > 0) is not bit-reproducible
            # from run to run on CUDA (bench/results/newton_restitution_repro_cuda_h100.json)
            "spheres": {"count": 2, "radius": 0.06, "seed": 3}, "physics": {"ground": "auto", "restitution": 0.0},
            "newton": {"solver": "xpbd", "bodies": [{"type": "box", "position": [0.1, 0.0, 1.0],
                                                      "half_extents": [0.08, 0.08, 0.05]}]}}
    one = build_newton_world(load_scene_config(data=data))
    many = build_newton_world(load_scene_config(data=data), num_worlds=4)
    B = one.body_transforms().shape[0]
    assert B == 3 and many.body_transforms().shape[0] == 4 * B
    for _ in range(120):  # 0.5 s: the bodies land on the moving bowl
        one.step()
        many.step()
    ref = one.body_transforms()
    assert np.abs(ref[:, 2] - 1.0).max() > 0.05  # they moved
    got = many.body_transforms().reshape(4, B, -1)
    for w in range(4):
        np.testing.assert_allclose(got[w], ref, atol=1e-5)
    with pytest.raises(SceneError, match="num_worlds"):
        build_newton_world(load_scene_config(data=data), num_worlds=0)


def test_render_world_draws_newton_bodies(device):
    """render_world on a Newton world draws its bodies (Simulation.rigid_shapes: shape type,
    size and world pose) composited with the splats: a box seen from straight above shows its
    top face at the depth of the body's pose, in the body's colour, over the surface's splats."""
    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.gaussians import gaussians_for_surface
    from dynmesh_warp.newton_adapter import build_newton_world
    from dynmesh_warp.render import look_at, render_world

    data = {"device": device, "surface": {"source": "builtin:wave_bowl", "params": {"n": 10, "frames": 4}},
            "spheres": [],
            "newton": {"solver": "xpbd", "bodies": [{"type": "box", "position": [0.0, 0.0, 1.2],
                                                      "half_extents": [0.2, 0.15, 0.1]}]}}
    cfg = load_scene_config(data=data)
    nw = build_newton_world(cfg)
    for _ in range(3):
        nw.step()
    shapes = nw.rigid_shapes()
    assert [s["type"] for s in shapes] == ["box"]
    np.testing.assert_allclose(shapes[0]["pose"], nw.body_transforms()[0], atol=1e-6)
    np.testing.assert_allclose(shapes[0]["scale"], [0.2, 0.15, 0.1], atol=1e-7)
    g = gaussians_for_surface(nw.surface.sequence, cfg, nw.device)
    g.update(nw.surface_points(), nw.surface_indices())
    x, y, z = (float(v) for v in nw.body_transforms()[0, :3])
    cam = look_at([x, y, 4.0], [x, y, 0.0], up=(0.0, 1.0, 0.0), width=33, height=33, fov_y_deg=20)
    out = render_world(nw, g, [cam])
    depth, rgb = out.depth.numpy()[0], out.rgb.numpy()[0]
    assert depth[16, 16] == pytest.approx(4.0 - (z + 0.1), abs=2e-3)  # the top face, 0.1 above the centre
    np.testing.assert_allclose(rgb[16, 16], [0.35, 0.5, 0.85], atol=1e-3)  # body colour, lit head-on
    # at the image's edge the splatted surface shows (the box is 0.4 x 0.3 m, the view ~1.4 m wide)
    assert np.abs(rgb[1, 1] - np.array([0.35, 0.5, 0.85])).max() > 0.05 and depth[1, 1] > depth[16, 16] + 0.3


def test_render_cli_renders_a_newton_scene_with_its_bodies(tmp_path, device):
    """python -m dynmesh_warp.render on a newton: scene renders the Newton world (before, it
    silently rendered the built-in world without the bodies): the figure shows body-coloured
    pixels where the boxes and capsules are."""
    import yaml
    from PIL import Image

    from dynmesh_warp.render import main

    data = {"name": "nb", "device": device, "surface": {"source": "builtin:wave_bowl", "params": {"n": 12, "frames": 4}},
            "spheres": [],
            "newton": {"solver": "xpbd", "bodies": [{"type": "box", "position": [0.0, 0.0, 0.8],
                                                      "half_extents": [0.25, 0.2, 0.15]}]}}
    scene = tmp_path / "nb.yaml"
    scene.write_text(yaml.safe_dump(data))
    fig = tmp_path / "strip.png"
    assert main([str(scene), "--figure", str(fig), "--moments", "2", "--frames", "3", "--width", "64",
                 "--height", "48", "--no-progress"]) == 0
    img = np.asarray(Image.open(fig)).astype(float) / 255.0
    blue = (img[..., 2] > img[..., 0] + 0.2)  # the body colour (0.35, 0.5, 0.85) shaded; the splats are beige
    assert blue.sum() > 20


def test_rigid_shapes_leave_out_sites_and_invisible_shapes():
    """What the renderer draws of a Newton world: visible shapes only (an MJCF's sites and
    collision-only shapes are not drawn), each with its world pose (body pose x local transform)."""
    seq = rising_sheet(8)
    b = newton.ModelBuilder()
    body = b.add_body(xform=wp.transform(wp.vec3(0.1, 0.2, 0.5), wp.quat_identity()))
    b.add_shape_box(body, hx=0.1, hy=0.1, hz=0.1, xform=wp.transform(wp.vec3(0.0, 0.0, 0.05), wp.quat_identity()))
    b.add_shape_sphere(body, radius=0.05, as_site=True)
    hidden = newton.ModelBuilder.ShapeConfig(is_visible=False)
    b.add_shape_capsule(body, radius=0.02, half_height=0.1, cfg=hidden)
    nw = NewtonWorld(SurfaceModel(seq, "cpu", playback="clamp"), b)
    shapes = nw.rigid_shapes()
    assert [s["type"] for s in shapes] == ["box"]
    np.testing.assert_allclose(shapes[0]["pose"][:3], [0.1, 0.2, 0.55], atol=1e-6)
    assert len(nw.shapes()) == 3  # all three exist; two are not for display


def test_run_newton_scene_with_envs_uses_newtons_own_batching(tmp_path, device):
    """``run --envs 3`` on a newton: scene: three replicated Newton worlds (one clock), each
    resting where the one-world run rests; env-steps/s reported; per-env clocks, which Newton's
    batching cannot give, are refused naming the fields; --view-envs too."""
    import yaml

    from dynmesh_warp.config import SceneError, load_scene_config
    from dynmesh_warp.run import main, run_scene

    seq = rising_sheet(12, rise=0.0, frames=2)
    npz = tmp_path / "sheet.npz"
    np.savez(npz, V=seq.V, F=seq.F, fps=FPS)
    scene = {"name": "ne", "device": device, "surface": {"source": str(npz)},
             "spheres": [{"position": [0.5, 0.5, 0.3], "radius": 0.05, "mass": 1.0}],
             "newton": {"solver": "xpbd", "bodies": [
                 {"type": "box", "position": [-0.3, 0.0, 0.3], "half_extents": [0.1, 0.1, 0.05]}]},
             "physics": {"restitution": 0.0},  # bit-equal copies: see test_replicated_newton_worlds_...
             "envs": {"count": 3}, "run": {"steps": 120, "output": str(tmp_path / "out")}}
    path = tmp_path / "ne.yaml"
    path.write_text(yaml.safe_dump(scene))
    summary = run_scene(load_scene_config(path), progress=False, log=lambda *a: None)
    q = np.asarray(summary["final"]["body_q"])
    assert q.shape == (6, 7) and summary["num_envs"] == 3 and summary["env_steps_per_second"] > 0
    np.testing.assert_allclose(q[0::2, 2], 0.05, atol=5e-3)  # each world's box on the sheet
    np.testing.assert_allclose(q[1::2, 2], 0.05, atol=5e-3)  # and its sphere
    # the worlds are copies: bit for bit on the CPU here; on CUDA Newton's contact sums run in any order and a
    # box resting on mesh contacts drifts apart (1.3e-6 alone, 8.4e-5 under 8 test workers on an H200, a later
    # run 3.7 mm in x / y; docs/envs.md: Newton's own, plain Newton does the same): its height agrees, the
    # sphere's rest too, and the box within a centimetre
    if str(device) == "cpu":
        np.testing.assert_allclose(q[:2], q[2:4], atol=1e-5)
    else:
        np.testing.assert_allclose(q[[0, 2], 2], q[[0, 2], 2][::-1], atol=1e-3)
        np.testing.assert_allclose(q[:2, :3], q[2:4, :3], atol=1e-2)
    for bad in ({"time_offset": "random"}, {"rate": [0.5, 1.5]}):
        scene["envs"] = {"count": 3, **bad}
        path.write_text(yaml.safe_dump(scene))
        with pytest.raises(SceneError, match="one clock"):
            run_scene(load_scene_config(path), progress=False, log=lambda *a: None, overwrite=True)
    assert main([str(path), "--view-envs", "1", "--record", str(tmp_path / "rec")]) == 2  # the one-clock refusal


def test_newton_restitution_friction_and_bodies_inside_follow_the_scene(tmp_path, device):
    """Three findings of a new user, each on the default solver (XPBD):
    - physics.restitution was ignored (Newton's XPBD leaves it off): a sphere dropped from 0.5 m
      with restitution 1 did not bounce; it now comes back up;
    - newton.surface_mu was given to every body as well: with friction 1 on the bodies and
      surface_mu 0, a box slid down a 20-degree slope as on ice; the combined friction now holds it;
    - a sphere or box placed inside a closed surface ran and fell out through it (the built-in
      engine refuses it): now refused, naming the entry."""
    from dynmesh_warp.config import SceneError, load_scene_config
    from dynmesh_warp.newton_adapter import build_newton_world

    seq = rising_sheet(16, rise=0.0, frames=2)
    np.savez(tmp_path / "flat.npz", V=seq.V, F=seq.F, fps=FPS)
    drop = {"device": device, "surface": {"source": str(tmp_path / "flat.npz")}, "spheres": [],
            "physics": {"restitution": 1.0},
            "newton": {"bodies": [{"type": "sphere", "position": [0.0, 0.0, 0.5], "radius": 0.05}]}}
    w = build_newton_world(load_scene_config(data=drop))
    z = []
    for _ in range(180):
        w.step()
        z.append(float(w.body_transforms()[0, 2]))
    bottom = int(np.argmin(z))
    assert z[bottom] < 0.1 and max(z[bottom:]) > 0.3  # down to the sheet, then back up
    # a 20-degree slope (x up to the left), friction 1 on the box, 0 on the surface: Newton
    # combines the two (0.5 > tan 20 = 0.36), so the box stays
    V = seq.V.astype(np.float64).copy()
    V[..., 2] = -np.tan(np.radians(20.0)) * V[..., 0]
    np.savez(tmp_path / "slope.npz", V=V.astype(np.float32), F=seq.F, fps=FPS)
    slope = {"device": device, "surface": {"source": str(tmp_path / "slope.npz")}, "spheres": [],
             "physics": {"friction": 1.0, "restitution": 0.0},
             "newton": {"surface_mu": 0.0, "bodies": [{"type": "box", "position": [0.0, 0.0, 0.06],
                                                       "half_extents": [0.05, 0.05, 0.05],
                                                       "rotation": [0.0, float(np.sin(np.radians(10))), 0.0,
                                                                    float(np.cos(np.radians(10)))]}]}}
    w = build_newton_world(load_scene_config(data=slope))
    x0 = float(w.body_transforms()[0, 0])
    for _ in range(240):
        w.step()
    assert abs(float(w.body_transforms()[0, 0]) - x0) < 0.05
    blob = {"device": device, "surface": {"source": "builtin:pulsing_blob", "params": {"subdivisions": 2}},
            "spheres": [{"position": [0.0, 0.0, 0.6], "radius": 0.05}], "newton": {}}
    with pytest.raises(SceneError, match=r"spheres.0: position \[0.0, 0.0, 0.6\] starts inside the closed surface"):
        build_newton_world(load_scene_config(data=blob))
    blob["spheres"] = []
    blob["newton"] = {"bodies": [{"type": "box", "position": [0.0, 0.0, 0.6], "half_extents": [0.05, 0.05, 0.05]}]}
    with pytest.raises(SceneError, match=r"newton.bodies.0: position \[0.0, 0.0, 0.6\] starts inside the closed"):
        build_newton_world(load_scene_config(data=blob))
