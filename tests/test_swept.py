"""The swept-bounds collider (refit once per frame) against the refit-every-step reference."""

import numpy as np
import pytest

from dynmesh_warp.scenes import pulsing_blob, wave_bowl
from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, SweptCollider, World
from conftest import TEST_DEVICE


def _worlds(seq, pos, vel, radius, t0, collider_kw):
    out = []
    for col, kw in collider_kw:
        model = Model(SurfaceModel(seq, TEST_DEVICE, playback="loop", interpolate=True),
                      SphereModel(radius, 1.0, TEST_DEVICE), PhysicsParams(auto_substeps=False))
        w = World(model, State(model, pos, vel, t0=t0), collider=col)
        if kw is not None:
            w.collider = SweptCollider(w.model, w.state, w.ctx, **kw)
        out.append(w)
    return out


def _contacts_at(w):
    w.update_surface()
    w.collider.update(w.model, w.state, w.ctx)
    w.collider.collide(w.model, w.state, w.contacts, w.ctx)
    return w.contacts.numpy()


def _wave_sheet(n: int, frames: int, name: str = "sheet"):
    """A 2 m grid sheet of n x n vertices with a travelling wave (5 cm, one period a loop)."""
    from dynmesh_warp.scenes import grid_sheet
    from dynmesh_warp.sequence import FixedTopologySequence

    V0, F = grid_sheet(n, 2.0)
    V = np.repeat(V0[None], frames, 0).astype(np.float32)
    for t in range(frames):
        V[t, :, 2] = 0.05 * np.sin(3 * V0[:, 0] + 2 * np.pi * t / frames)
    return FixedTopologySequence(V, F, fps=24.0, name=name)


@pytest.mark.parametrize("make_seq", [lambda: wave_bowl(n=24, frames=12), lambda: pulsing_blob(subdivisions=2, frames=12)])
def test_swept_contacts_equal_refit_reference(make_seq):
    seq = make_seq()
    rng = np.random.default_rng(3)
    S = 64
    checked = beyond = 0
    for trial in range(6):
        t0 = float(rng.uniform(0, seq.num_frames / seq.fps * 1.5))  # includes loop wrap
        # sphere centres near the interpolated surface, on both sides of it
        k = int(np.floor(t0 * seq.fps))
        a = t0 * seq.fps - k
        V = (1 - a) * seq.V[k % seq.num_frames] + a * seq.V[(k + 1) % seq.num_frames]
        base = V[rng.integers(0, len(V), S)]
        pos = base + rng.normal(scale=0.04, size=(S, 3))
        vel = rng.normal(scale=0.5, size=(S, 3))
        radius = rng.uniform(0.02, 0.06, S).astype(np.float32)
        ref, *swept = _worlds(seq, pos, vel, radius, t0, [
            ("refit", None), ("swept", {"search": "serial"}), ("swept", {"search": "tiled", "tile_threads": 64}),
            ("swept", {"search": "tiled", "tile_threads": 8}), ("swept", {"search": "tiled", "tile_threads": 1}),
            ("swept", {"search": "faces"}), ("swept", {"search": "sphere_grid"})])
        c_ref = _contacts_at(ref)
        for w in swept:
            c = _contacts_at(w)
            np.testing.assert_array_equal(c["face"] >= 0, c_ref["face"] >= 0)
            m = c_ref["face"] >= 0
            np.testing.assert_allclose(c["point"][m], c_ref["point"][m], atol=2e-5)
            # the normal is (p - c)/|p - c|: compare it where the centre is not on the surface
            # (there a 1e-6 difference in c, e.g. from FMA on a GPU, turns it noticeably)
            far = m & (np.linalg.norm(pos - c_ref["point"], axis=1) > 1e-3)
            np.testing.assert_allclose(c["normal"][far], c_ref["normal"][far], atol=2e-3)
            np.testing.assert_allclose(np.linalg.norm(c["normal"][m], axis=1), 1.0, atol=1e-5)
            np.testing.assert_allclose(c["depth"][m], c_ref["depth"][m], atol=2e-5)
            np.testing.assert_allclose(c["velocity"][m], c_ref["velocity"][m],
                                       atol=2e-3 * max(1.0, np.abs(c_ref["velocity"]).max()))
            checked += int(m.sum())
            # closest feature beyond r + margin (found by the second, reach-wide box query)
            beyond += int((m & (np.linalg.norm(pos - c_ref["point"], axis=1) > radius + 1.5e-3)).sum())
    assert checked > 50  # the states really produced contacts
    assert beyond > 10  # and the second search box was needed for some


@pytest.mark.parametrize("search", [None, "serial", "tiled", "faces", "sphere_grid"])
def test_swept_world_matches_refit_world_trajectories(search):
    """Over 240 steps (24 frame changes: the swept boxes and their tree refit each time)."""
    seq = wave_bowl(n=24, frames=12)
    rng = np.random.default_rng(0)
    pos = np.c_[rng.uniform(-0.5, 0.5, (4, 2)), np.full(4, 0.5)]
    ref, sw = _worlds(seq, pos, None, np.full(4, 0.06, np.float32), 0.0,
                      [("refit", None), ("swept", None if search is None else {"search": search})])
    touched = 0
    for _ in range(240):
        ref.step()
        sw.step()
        f_ref, f_sw = ref.contacts.face.numpy(), sw.contacts.face.numpy()
        np.testing.assert_array_equal(f_sw >= 0, f_ref >= 0)
        touched += int((f_sw >= 0).sum())
    np.testing.assert_allclose(sw.sphere_positions(), ref.sphere_positions(), atol=1e-3)
    assert touched > 50


@pytest.mark.parametrize("seed", [True, False])
def test_seeded_serial_search_equals_the_unseeded_one(monkeypatch, seed):
    """choices.SEED_PREVIOUS_FACE (the CPU default seeds each sphere's serial search with its
    previous contact face, CUDA does not): either way the swept world follows the refit
    reference over 240 steps with contacts, and the seeded and unseeded runs give the same
    contact faces and positions."""
    from dynmesh_warp import choices

    seq = wave_bowl(n=24, frames=12)
    rng = np.random.default_rng(4)
    pos = np.c_[rng.uniform(-0.5, 0.5, (5, 2)), np.full(5, 0.5)]
    runs = {}
    for flag in (seed, not seed):
        monkeypatch.setitem(choices.SEED_PREVIOUS_FACE, "cpu", flag)
        monkeypatch.setitem(choices.SEED_PREVIOUS_FACE, "cuda", flag)
        ref, sw = _worlds(seq, pos, None, np.full(5, 0.06, np.float32), 0.0,
                          [("refit", None), ("swept", {"search": "serial"})])
        faces = []
        for _ in range(240):
            ref.step()
            sw.step()
            faces.append(sw.contacts.face.numpy().copy())
        np.testing.assert_allclose(sw.sphere_positions(), ref.sphere_positions(), atol=1e-3)
        runs[flag] = (np.array(faces), sw.sphere_positions())
    assert (runs[True][0] >= 0).sum() > 50  # contacts, so the seed was used
    np.testing.assert_array_equal(runs[True][0], runs[False][0])
    np.testing.assert_allclose(runs[True][1], runs[False][1], atol=1e-6)


def test_fixed_collider_measures_and_keeps_the_faster(monkeypatch):
    """``fixed``: without interpolation refit (nothing measured); with it, both candidates timed
    on trial states (the world's own state untouched) and the faster kept, whichever it is."""
    import dynmesh_warp.world as world_mod

    seq = wave_bowl(n=16, frames=6)
    model = Model(SurfaceModel(seq, TEST_DEVICE, interpolate=False), SphereModel([0.05], 1.0, TEST_DEVICE), PhysicsParams())
    w = World(model, State(model, [[0, 0, 1]]))
    assert w.collider.name == "refit" and w.collider_costs is None
    model = Model(SurfaceModel(seq, TEST_DEVICE, interpolate=True), SphereModel([0.05, 0.05], 1.0, TEST_DEVICE),
                  PhysicsParams())
    state = State(model, [[0, 0, 1], [0.2, 0, 1]], t0=0.1)
    w = World(model, state)
    costs = w.collider_costs
    # CUDA: each search a candidate (with 2 spheres the face-parallel one, not the sphere grid)
    searches = [s for s in world_mod.SWEPT_MEASURED_SEARCHES[TEST_DEVICE.split(":")[0]] if s != "sphere_grid"]
    assert set(costs) == {"refit", *([f"swept/{s}" for s in searches] or ["swept"])}
    assert all(np.isfinite(v) and v > 0 for v in costs.values())
    assert w.collider.name == min(costs, key=costs.get).partition("/")[0]
    np.testing.assert_allclose(w.sphere_positions(), [[0, 0, 1], [0.2, 0, 1]])  # trials ran on copies
    assert float(state.sim_time.numpy()[0]) == 0.1
    assert w.run_summary()["collider_choice"]["measured_steps_per_s"]["refit"] > 0
    for swept, refit in ((2.0, 1.0), (1.0, 2.0)):  # the choice follows the costs
        monkeypatch.setattr(world_mod, "measure_colliders",
                            lambda m, s, c, a=swept, b=refit: {k: (b if k == "refit" else a) for k in c})
        assert World(model, State(model, [[0, 0, 1], [0.2, 0, 1]])).collider.name == ("swept" if swept < refit else "refit")


def test_swept_bvh_refit_only_on_frame_change():
    seq = wave_bowl(n=16, frames=6)
    model = Model(SurfaceModel(seq, TEST_DEVICE), SphereModel([0.05], 1.0, TEST_DEVICE), PhysicsParams(dt=1 / 240))
    w = World(model, State(model, [[0, 0, 1]]), collider="swept", use_graph=False)  # count host calls
    calls = []
    orig = w.collider.refit_frame
    w.collider.refit_frame = lambda model, state, ctx: (calls.append(ctx.time), orig(model, state, ctx))
    for _ in range(40):  # 40 steps at 240 Hz: about 4 frames at 24 fps
        w.step()
    # expected: the steps n at whose start (n / 240 s, exactly) the frame n * 24 // 240 changes,
    # at the clock accumulated as on the device (which lands a few ulps short of some of those
    # boundaries: on them all the same, docs/physics.md; the step after a boundary before)
    assert seq.fps == 24.0
    t, k_prev, expected = 0.0, 0, []
    for n in range(40):
        k = n * 24 // 240
        if k != k_prev:
            expected.append(t)
            k_prev = k
        t += 1 / 240
    assert len(expected) == 3
    np.testing.assert_array_equal(calls, expected)
    lo, hi = w.collider.lowers.numpy(), w.collider.uppers.numpy()
    k = 3 % seq.num_frames  # the third boundary: frame 3
    tri = np.stack([seq.V[k][seq.F], seq.V[(k + 1) % seq.num_frames][seq.F]], 1).reshape(len(seq.F), 6, 3)
    np.testing.assert_allclose(lo, tri.min(1), atol=1e-6)
    np.testing.assert_allclose(hi, tri.max(1), atol=1e-6)


@pytest.mark.parametrize("scene", ["wave_bowl", "pulsing_blob"])
def test_no_tunnelling_over_1e5_steps(scene):
    """Issue #8: 10^5 steps of the default (swept) collider on the built-in scenes; no sphere centre
    ever ends behind the surface (height field for the bowl, winding number for the closed blob)."""
    from reference import grid_height, surface_at, winding_number

    rng = np.random.default_rng(5)
    S, r = 6, 0.05
    if scene == "wave_bowl":
        n = 24
        seq = wave_bowl(n=n, frames=12)
        pos = np.column_stack([rng.uniform(-0.5, 0.5, (S, 2)), rng.uniform(0.4, 0.8, S)])
        ground = None
    else:
        seq = pulsing_blob(subdivisions=2, frames=12)
        # dropped near the top of the breathing blob; high friction keeps them riding on it
        pos = np.array([0.0, 0.0, 0.6]) + np.column_stack([rng.uniform(-0.12, 0.12, (S, 2)), np.full(S, 0.68)])
        ground = float(seq.V[:, :, 2].min())  # any that roll off rest around it and are pushed by it
    model = Model(SurfaceModel(seq, TEST_DEVICE, playback="loop", interpolate=True),
                  SphereModel(np.full(S, r, np.float32), 1.0, TEST_DEVICE),
                  PhysicsParams(restitution=0.3 if scene == "wave_bowl" else 0.0,
                                friction=0.5 if scene == "wave_bowl" else 2.0, ground_height=ground))
    w = World(model, State(model, pos), collider="swept")
    touched = 0
    for i in range(100_000):
        w.step()
        if i % 50 == 49:
            touched += int((w.contacts.face.numpy() >= 0).sum())
        if i % 500 == 499 or (i < 2000 and i % 50 == 49):  # densely while they ride the surface
            P = w.sphere_positions().astype(np.float64)
            assert np.isfinite(P).all(), f"step {i}: non-finite state"
            Vt = surface_at(seq, w.time, "loop")
            if scene == "wave_bowl":
                hz = grid_height(Vt, n, 2.0, P[:, :2])
                on = np.isfinite(hz)
                assert (P[on, 2] > hz[on]).all(), f"step {i}: a centre is below the bowl"
            else:
                assert (winding_number(Vt, seq.F, P) < 0.5).all(), f"step {i}: a centre is inside the blob"
    # not vacuous: the spheres were on the moving surface (bowl: riding the waves, often airborne;
    # blob: riding its top until its breathing, at about g, throws them off onto the ground)
    assert touched >= (0.1 * S * 2000 if scene == "wave_bowl" else 10)


def test_swept_search_with_hundreds_of_faces_per_sphere():
    """A fine sheet (120 x 120) and wide spheres: each sphere has hundreds of faces in its reach
    box (the case the tiled search is for: one thread would walk them all); every search gives
    the refit reference's contacts."""
    seq = _wave_sheet(120, 6, "fine")
    rng = np.random.default_rng(5)
    S = 12
    xy = rng.uniform(-0.8, 0.8, (S, 2))
    z = 0.05 * np.sin(3 * xy[:, 0]) + rng.uniform(-0.03, 0.12, S)
    pos = np.c_[xy, z].astype(np.float32)
    vel = rng.normal(scale=0.3, size=(S, 3)).astype(np.float32)
    radius = np.full(S, 0.1, np.float32)
    ref, serial, tiled, faces, grid = _worlds(seq, pos, vel, radius, 0.0, [
        ("refit", None), ("swept", {"search": "serial"}), ("swept", {"search": "tiled", "tile_threads": 16}),
        ("swept", {"search": "faces"}), ("swept", {"search": "sphere_grid"})])
    c_ref = _contacts_at(ref)
    lo, hi = serial.collider.lowers.numpy(), serial.collider.uppers.numpy()
    reach = radius + 1e-3
    in_box = [int(np.all((lo <= pos[s] + reach[s]) & (hi >= pos[s] - reach[s]), axis=1).sum()) for s in range(S)]
    assert min(in_box) > 256  # hundreds of faces in every sphere's reach box
    m = c_ref["face"] >= 0
    assert m.sum() >= 4
    for w in (serial, tiled, faces, grid):
        c = _contacts_at(w)
        np.testing.assert_array_equal(c["face"] >= 0, m)
        np.testing.assert_allclose(c["point"][m], c_ref["point"][m], atol=2e-5)
        np.testing.assert_allclose(c["depth"][m], c_ref["depth"][m], atol=2e-5)
        far = m & (np.linalg.norm(pos - c_ref["point"], axis=1) > 1e-3)
        np.testing.assert_allclose(c["normal"][far], c_ref["normal"][far], atol=2e-3)


def _blob_model():
    seq = pulsing_blob(subdivisions=2, frames=12)
    return Model(SurfaceModel(seq, TEST_DEVICE, interpolate=True), SphereModel([0.05, 0.05], 1.0, TEST_DEVICE),
                 PhysicsParams())


def test_fixed_measures_each_swept_search_and_keeps_the_fastest(monkeypatch):
    """Where several searches are measured (CUDA: tiled, serial), ``fixed`` runs a trial of each
    and the world keeps the chosen one; a search named in physics.swept_search is the only one."""
    import dynmesh_warp.world as world_mod

    monkeypatch.setitem(world_mod.SWEPT_MEASURED_SEARCHES, TEST_DEVICE.split(":")[0], ("tiled", "serial"))
    seen = []
    for fake, search in (({"swept/tiled": 2.0, "swept/serial": 1.0, "refit": 3.0}, "serial"),
                         ({"swept/tiled": 1.0, "swept/serial": 2.0, "refit": 3.0}, "tiled")):
        monkeypatch.setattr(world_mod, "measure_colliders", lambda m, s, c, fake=fake: (seen.append(tuple(c)), fake)[1])
        model = _blob_model()
        w = World(model, State(model, [[0, 0, 1], [0.2, 0, 1]]))
        assert seen[-1] == ("swept/tiled", "swept/serial", "refit")
        assert w.collider.name == "swept" and w.collider.search == search and w.swept_search == search
        assert w.run_summary()["swept_search"] == search
    # the face-parallel search is a candidate only up to SWEPT_FACES_MAX_SPHERES spheres, the
    # sphere grid only above it
    monkeypatch.setitem(world_mod.SWEPT_MEASURED_SEARCHES, TEST_DEVICE.split(":")[0], ("tiled", "faces", "sphere_grid"))
    monkeypatch.setattr(world_mod, "measure_colliders", lambda m, s, c: (seen.append(tuple(c)), {k: 1.0 for k in c})[1])
    World(_blob_model(), State(_blob_model(), [[0, 0, 1], [0.2, 0, 1]]))
    assert seen[-1] == ("swept/tiled", "swept/faces", "refit")
    monkeypatch.setattr(world_mod, "SWEPT_FACES_MAX_SPHERES", 1)
    World(_blob_model(), State(_blob_model(), [[0, 0, 1], [0.2, 0, 1]]))
    assert seen[-1] == ("swept/tiled", "swept/sphere_grid", "refit")
    model = _blob_model()
    model.params.swept_search = "serial"
    monkeypatch.setattr(world_mod, "measure_colliders", lambda m, s, c: (seen.append(tuple(c)), {"swept": 1.0, "refit": 2.0})[1])
    w = World(model, State(model, [[0, 0, 1], [0.2, 0, 1]]))
    assert seen[-1] == ("swept", "refit") and w.collider.search == "serial"


def test_measured_choice_does_not_count_the_compile_steps(monkeypatch):
    """The eager step (kernel compile) and the capture (module loads on a cold kernel cache) are
    not timed: a cold cache made the swept trial look 1 s per step on an H100 and ``fixed``
    chose refit at a third of swept's speed."""
    import time as _time

    import dynmesh_warp.world as world_mod

    calls = {}
    orig = world_mod.World.step

    def slow_first_two(self):
        calls[id(self)] = calls.get(id(self), 0) + 1
        if calls[id(self)] <= 2:
            _time.sleep(0.6)  # a compile
        return orig(self)

    monkeypatch.setattr(world_mod.World, "step", slow_first_two)
    model = _blob_model()
    costs = world_mod.measure_colliders(model, State(model, [[0, 0, 1], [0.2, 0, 1]], t0=0.1), ["swept", "refit"],
                                        horizon=0.05, budget_s=0.3)
    assert set(costs) == {"swept", "refit"} and all(0 < v < 0.1 for v in costs.values())


def test_bad_swept_search_is_refused_naming_the_field():
    with pytest.raises(ValueError, match="swept_search"):
        PhysicsParams(swept_search="nearest")
    model = _blob_model()
    with pytest.raises(ValueError, match="swept_search"):
        SweptCollider(model, State(model, [[0, 0, 1], [0.2, 0, 1]]), World(model, State(model, [[0, 0, 1], [0.2, 0, 1]]),
                                                                             collider="refit").ctx, search="pairs")
    # the batch's hybrid search is not a single world's: refused naming the field, also from
    # the scene's physics.swept_search
    with pytest.raises(ValueError, match="swept_search 'hybrid'"):
        World(model, State(model, [[0, 0, 1], [0.2, 0, 1]]), collider="swept", swept_search="hybrid")
    model = _blob_model()  # a built world's parameters are fixed
    model.params.swept_search = "hybrid"
    with pytest.raises(ValueError, match="swept_search 'hybrid'"):
        World(model, State(model, [[0, 0, 1], [0.2, 0, 1]]), collider="swept")


def test_every_search_finds_the_outside_beyond_a_sharp_edge(monkeypatch):
    """Beyond the sharp edge of a thin wedge (6 degrees) one face's normal points away from a
    slightly off-axis centre: only the pseudo-normal of the tied faces (both faces of the edge)
    tells outside from inside. Every search equals the refit reference there; with a face's own
    normal alone the spheres would be deep inside."""
    from dynmesh_warp.sequence import FixedTopologySequence

    h = np.tan(np.radians(3.0))
    ring = np.array([[1.0, 0.0], [0.0, h], [0.0, -h]])  # tip, base corners (counter-clockwise)
    V0 = np.array([[x, y, z] for z in (-0.5, 0.5) for x, y in ring], np.float32)
    F = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5],  # sides
                  [0, 2, 1], [3, 4, 5]], np.int32)  # end caps
    seq = FixedTopologySequence(np.stack([V0, V0]), F, fps=24.0, name="wedge")
    d = np.array([0.01, 0.02, 0.03, 0.015])
    pos = np.c_[1.0 + d, np.array([0.5, -0.5, 0.6, -0.4]) * d, np.zeros(4)].astype(np.float32)
    radius = np.full(4, 0.05, np.float32)
    ref, *others = _worlds(seq, pos, None, radius, 0.0, [("refit", None), ("swept", {"search": "serial"}),
                                                         ("swept", {"search": "tiled", "tile_threads": 8}),
                                                         ("swept", {"search": "faces"}),
                                                         ("swept", {"search": "sphere_grid"})])
    c_ref = _contacts_at(ref)
    dist = np.hypot(d, pos[:, 1])
    assert (c_ref["face"] >= 0).all()
    np.testing.assert_allclose(c_ref["depth"], radius - dist, atol=1e-5)  # outside: r - distance
    import dynmesh_warp.world as world_mod

    for serial in (False, True):  # the sphere grid's resolve: a block a sphere, or one thread (many spheres)
        monkeypatch.setattr(world_mod, "SPHERE_GRID_SERIAL_RESOLVE", 1 if serial else 10**9)
        for w in others if not serial else others[-1:]:
            c = _contacts_at(w)
            np.testing.assert_array_equal(c["face"] >= 0, True)
            np.testing.assert_allclose(c["depth"], c_ref["depth"], atol=1e-5)
            np.testing.assert_allclose(c["normal"], c_ref["normal"], atol=1e-4)


@pytest.mark.parametrize("serial_resolve", [False, True], ids=["block_resolve", "serial_resolve"])
@pytest.mark.parametrize("buckets, cell_size", [(None, None), (1, 0.03), (None, 0.002)],
                         ids=["default", "one_bucket_fine_cells", "every_face_list"])
def test_sphere_grid_levels_and_collisions_keep_the_reference_contacts(monkeypatch, buckets, cell_size, serial_resolve):
    """The sphere_grid search lists each sphere in the grid level its search radius fits (level 0,
    the 4x coarser level 1, or the list every face tests) and hashes cells into buckets. Forced
    into each case (one bucket for every cell: every entry a collision; cells so small that the
    spheres go to level 1 or to the every-face list), its contacts stay the refit reference's,
    over a wave sheet with spheres on both sides and moving; with either resolve kernel (a block
    a sphere, or one thread a sphere from SPHERE_GRID_SERIAL_RESOLVE spheres on)."""
    import warp as wp

    import dynmesh_warp.world as world_mod

    monkeypatch.setattr(world_mod, "SPHERE_GRID_SERIAL_RESOLVE", 1 if serial_resolve else 10**9)
    seq = _wave_sheet(40, 6)
    rng = np.random.default_rng(7)
    S = 48
    xy = rng.uniform(-0.9, 0.9, (S, 2))
    pos = np.c_[xy, 0.05 * np.sin(3 * xy[:, 0]) + rng.uniform(-0.08, 0.08, S)].astype(np.float32)
    vel = rng.normal(scale=1.0, size=(S, 3)).astype(np.float32)
    radius = rng.uniform(0.02, 0.08, S).astype(np.float32)
    ref, grid = _worlds(seq, pos, vel, radius, 0.013, [("refit", None), ("swept", {"search": "sphere_grid"})])
    col = grid.collider
    if cell_size is not None:
        col.grid.cell_size = wp.vec2(cell_size, 4.0 * cell_size)
    if buckets == 1:  # every cell in one bucket: every other cell's entry is a collision to skip
        col.grid.num_buckets = 1
        col.grid.bucket_count = wp.zeros(2, dtype=wp.int32, device=TEST_DEVICE)
        col.grid.bucket_start = wp.zeros(2, dtype=wp.int32, device=TEST_DEVICE)
    levels = set()
    for _ in range(3):  # the first without a seed, then seeded by the previous contact faces
        c_ref, c = _contacts_at(ref), _contacts_at(grid)
        m = c_ref["face"] >= 0
        np.testing.assert_array_equal(c["face"] >= 0, m)
        np.testing.assert_allclose(c["point"][m], c_ref["point"][m], atol=2e-5)
        np.testing.assert_allclose(c["depth"][m], c_ref["depth"][m], atol=2e-5)
        levels |= set(np.unique(col.grid.sphere_level.numpy()).tolist())
        assert m.sum() >= 8
    assert col.grid.bucket_count.numpy().sum() == 0  # counted back down for the next step
    if buckets == 1:
        assert col.grid.bucket_start.numpy()[-1] > 100  # every entry in the one bucket
    expected = {None: {0}, 0.03: {1}, 0.002: {2}}[cell_size]
    assert expected <= levels, levels


def test_sphere_grid_puts_large_spheres_of_a_mixed_set_on_level_1():
    """Cells are sized by the median sphere; level 1 is made wide enough for the largest sphere
    at rest, so a few large spheres among many small ones go to level 1 (not to the list every
    face tests) and the contacts stay the refit reference's."""
    seq = _wave_sheet(40, 4)
    rng = np.random.default_rng(11)
    S = 40
    xy = rng.uniform(-0.8, 0.8, (S, 2))
    radius = np.full(S, 0.01, np.float32)
    radius[:4] = 0.3  # four large among small ones
    pos = np.c_[xy, 0.05 * np.sin(3 * xy[:, 0]) + radius + rng.uniform(-0.005, 0.0, S)].astype(np.float32)
    ref, grid = _worlds(seq, pos, None, radius, 0.0, [("refit", None), ("swept", {"search": "sphere_grid"})])
    c_ref, c = _contacts_at(ref), _contacts_at(grid)
    m = c_ref["face"] >= 0
    assert m[:4].all() and m.sum() >= 20
    np.testing.assert_array_equal(c["face"] >= 0, m)
    np.testing.assert_allclose(c["point"][m], c_ref["point"][m], atol=2e-5)
    np.testing.assert_allclose(c["depth"][m], c_ref["depth"][m], atol=2e-5)
    level = grid.collider.grid.sphere_level.numpy()
    assert (level[:4] == 1).all() and (level[4:] == 0).all(), level


def test_seeded_refit_query_gives_the_unseeded_contacts(monkeypatch):
    """choices.SEED_REFIT_QUERY: the refit collider's query reaches no farther than the previous
    contact face's distance (+ twice Warp's tie epsilon). Over 240 steps with contacts the
    seeded and unseeded refit worlds give the same contact faces, points and positions, and the
    seed was in use (contacts on consecutive steps)."""
    from dynmesh_warp import choices
    import dynmesh_warp.world as world_mod

    seq = wave_bowl(n=24, frames=12)
    rng = np.random.default_rng(8)
    pos = np.c_[rng.uniform(-0.5, 0.5, (6, 2)), np.full(6, 0.4)]
    runs = {}
    for flag in (True, False):
        monkeypatch.setattr(world_mod, "SEED_REFIT_QUERY", {**choices.SEED_REFIT_QUERY, "cpu": flag, "cuda": flag})
        (w,) = _worlds(seq, pos, None, np.full(6, 0.06, np.float32), 0.0, [("refit", None)])
        assert w.collider.seed is flag
        faces, points = [], []
        for _ in range(240):
            w.step()
            faces.append(w.contacts.face.numpy().copy())
            points.append(w.contacts.point.numpy().copy())
        runs[flag] = (np.array(faces), np.array(points), w.sphere_positions())
    f = runs[True][0]
    assert ((f[1:] >= 0) & (f[:-1] >= 0)).sum() > 100  # seeded steps
    np.testing.assert_array_equal(runs[True][0], runs[False][0])
    m = runs[True][0] >= 0
    np.testing.assert_allclose(runs[True][1][m], runs[False][1][m], atol=1e-6)
    np.testing.assert_allclose(runs[True][2], runs[False][2], atol=1e-6)
