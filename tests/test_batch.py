"""Batched environments (issue 15; dynmesh_warp/batch.py): E envs in one Model/State with their
own clocks equal E single worlds run separately; a reset touches only the envs it names; the
pair BVH slots bound the interpolated surface at every time (NumPy oracle)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from dynmesh_warp.batch import BatchedWorld, BatchModel, BatchState
from dynmesh_warp.scenes import pulsing_blob, wave_bowl
from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, World
from reference import surface_at


def _spheres(S, rng):
    pos = np.column_stack([rng.uniform(-0.5, 0.5, (S, 2)), rng.uniform(0.25, 0.5, S)]).astype(np.float32)
    vel = np.column_stack([rng.uniform(-0.3, 0.3, (S, 2)), np.zeros(S)]).astype(np.float32)
    return pos, vel


def _params(body="point"):
    return PhysicsParams(restitution=0.3, friction=0.5, ground_height=-0.4, sphere_body=body)


@pytest.mark.parametrize("playback,search,budget,body", [
    ("loop", "serial", None, "point"), ("pingpong", "serial", None, "point"), ("clamp", "serial", None, "point"),
    ("loop", "tiled", None, "point"), ("pingpong", "tiled", None, "point"), ("loop", "hybrid", 2, "point"),
    ("clamp", "hybrid", 0, "point"), ("loop", "grid", None, "point"), ("pingpong", "grid", None, "point"),
    ("loop", "serial", None, "solid"), ("pingpong", "tiled", None, "shell")])
def test_batched_envs_equal_single_worlds(device, playback, search, budget, body):
    """... with each search: serial, tiled (a block per sphere) and hybrid (a thread per sphere,
    handing a sphere with more than ``budget`` candidate faces to a block; budget 0 hands over
    every sphere near the surface). The single worlds keep the serial search, the reference.
    Spheres that roll (``body`` solid, shell) keep their spins the same too."""
    seq = wave_bowl(n=20, frames=10)
    rng = np.random.default_rng(5)
    E, S = 4, 6
    pos, vel = _spheres(S, rng)
    radius = np.full(S, 0.06, np.float32)
    times = np.array([0.0, 0.13, 0.37, 0.41 + 10 / 24.0])  # includes a time past the end (loop / turn / hold)
    surf = SurfaceModel(seq, device, playback=playback)
    bm = BatchModel(surf, E, radius, 1.0, _params(body))
    bw = BatchedWorld(bm, BatchState(bm, pos, vel, times=times), search=search, tile_threads=8,
                      budget=budget, blocks=3)
    assert bw.search == search
    singles = []
    for e in range(E):
        m = Model(SurfaceModel(seq, device, playback=playback), SphereModel(radius, 1.0, device), _params(body))
        w = World(m, State(m, pos, vel, t0=float(times[e])), collider="swept", swept_search="serial")
        assert w.substeps == bw.substeps
        singles.append(w)
    touched = handed = 0
    for i in range(150):
        bw.step()
        for w in singles:
            w.step()
        if i % 10 == 9:
            touched += int((bw.contacts.face.numpy() >= 0).sum())
        if search == "hybrid":
            handed += int(bw.query.heavy_count.numpy()[0])
    P = bw.sphere_positions()
    # (spheres that roll carry the contacts' last-bit differences (the batch's pair BVH and the
    # world's swept search) into their spins: on an H200 4.4e-5 m after 150 steps, 2e-5 on the CPU)
    tol = 2e-5 if body == "point" else 1e-4
    for e, w in enumerate(singles):
        np.testing.assert_allclose(P[e], w.sphere_positions(), atol=tol, err_msg=f"env {e}")
        np.testing.assert_allclose(bw.sphere_velocities()[e], w.sphere_velocities(), atol=10 * tol)
        assert bw.env_times()[e] == pytest.approx(w.time, abs=1e-12)
        np.testing.assert_allclose(bw.state.sphere_spin.numpy().reshape(E, S, 3)[e], w.sphere_spins(), rtol=1e-3,
                                   atol=2e-3)  # (spins of 10-20 rad/s: 2.6e-3 apart on an H200)
    spins = np.abs(bw.state.sphere_spin.numpy()).max()
    assert (spins > 0.1) if body != "point" else (spins == 0.0)  # friction spun them, or nothing does
    assert touched > 0  # the spheres did meet the moving surface
    assert not np.allclose(P[0], P[1])  # different clocks, different outcomes
    if search == "hybrid":
        assert handed > 0  # spheres did go to the blocks


@pytest.mark.parametrize("cell", [None, 0.02])
def test_grid_search_finds_the_brute_force_closest_face(device, cell):
    """The grid search (a uniform grid of each slot's face boxes, cells walked by a thread
    block): its closest distance and face equal brute force over every face of the surface at
    each env's time (NumPy), for points near and away from the moving surface; with fine cells
    (0.02 m: faces listed in several cells, each must be met once) and the default ones. Every
    face is in the cell lists of the cells its box overlaps."""
    import warp as wp
    from reference import closest_on_triangles, surface_at

    from dynmesh_warp.batch import ContactQuery
    from dynmesh_warp.kernels.batch import collide_env_sphere_grid

    seq = wave_bowl(n=14, frames=6)
    surf = SurfaceModel(seq, device)
    K = 200
    rng = np.random.default_rng(7)
    times = rng.uniform(0, seq.num_frames / seq.fps, K)
    pts = np.empty((K, 3))
    for i in range(K):  # near a random face of the surface at that env's time, up to ~0.2 m off it
        Vt = surface_at(seq, float(times[i]))
        pts[i] = rng.dirichlet([1, 1, 1]) @ Vt[seq.F[rng.integers(len(seq.F))]] + rng.normal(0, 0.08, 3)
    r = 0.06
    bm = BatchModel(surf, K, np.full(1, r), 1.0, _params(), **({} if cell is None else {"grid_cell_radii": cell / r}))
    assert bm.cell_faces is None and bm.memory_bytes["pair_grids"] == 0  # built only when a world uses it
    from dynmesh_warp.batch import step_envs
    from dynmesh_warp.world import Contacts

    with pytest.raises(ValueError, match="build_grids"):
        step_envs(bm, BatchState(bm, pts.reshape(K, 1, 3), times=times), Contacts(K, device), 1.0 / 240, 1, 0.0,
                  search="grid", query=ContactQuery(K, device))
    bm.build_grids()
    assert bm.memory_bytes["pair_grids"] > 0
    if cell is not None:  # fine cells (grown from 0.02 m only as far as GRID_MAX_CELLS asks)
        assert cell <= bm.grid_cell < 0.05
    # every face is listed in each cell of its box
    starts, ends, faces = bm.cell_start.numpy(), bm.cell_end.numpy(), bm.cell_faces.numpy()
    lo = bm.pair_lowers.numpy()
    org, dims = bm.grid_origin.numpy(), bm.grid_dims.numpy()
    for slot in (0, lo.shape[0] - 1):
        for f in rng.integers(0, lo.shape[1], 20):
            a = np.clip(np.floor((lo[slot, f] - org[slot]) / bm.grid_cell).astype(int), 0, dims[slot] - 1)
            cz, cy, cx = a[2], a[1], a[0]
            c = slot * bm.cells_per_slot + (cz * dims[slot][1] + cy) * dims[slot][0] + cx
            assert f in faces[starts[c]:ends[c]]
    st = BatchState(bm, pts.reshape(K, 1, 3), times=times)
    q = ContactQuery(K, device)
    dt, extra, margin = 1.0 / 240, 0.0, bm.params.margin
    wp.launch_tiled(collide_env_sphere_grid, dim=K,
                    inputs=[surf.frames, surf.indices, bm.grid_origin, bm.grid_dims,
                            1.0 / bm.grid_cell, bm.cells_per_slot, bm.cell_start, bm.cell_end, bm.cell_faces,
                            bm.cell_lowers, bm.cell_uppers, bm.spheres.radius, bm.sphere_env, surf.fps,
                            int(surf.interpolate), bm.time_slices, st.env_time, st.env_playback, st.sphere_pos,
                            st.sphere_vel, dt, extra, margin, bm.epsilon],
                    outputs=[q.dist, q.face, q.w, q.n, q.time], block_dim=8, device=device)
    # the same records as the tiled search over the pair BVH, tie normals included (a face met
    # twice would count twice there)
    from dynmesh_warp.kernels.batch import collide_env_sphere_tiled

    qt = ContactQuery(K, device)
    wp.launch_tiled(collide_env_sphere_tiled, dim=K,
                    inputs=[surf.frames, surf.indices, bm.pair_bvh, bm.pair_lowers, bm.pair_uppers, bm.spheres.radius,
                            bm.sphere_env, surf.fps, int(surf.interpolate), bm.time_slices, st.env_time,
                            st.env_playback, st.sphere_pos, st.sphere_vel, dt, extra, margin, bm.epsilon],
                    outputs=[qt.dist, qt.face, qt.w, qt.n, qt.time], block_dim=8, device=device)
    np.testing.assert_array_equal(q.face.numpy() >= 0, qt.face.numpy() >= 0)  # (tied faces may differ)
    np.testing.assert_allclose(q.dist.numpy(), qt.dist.numpy(), atol=1e-6)
    np.testing.assert_allclose(q.n.numpy(), qt.n.numpy(), atol=1e-5)
    np.testing.assert_array_equal(q.time.numpy(), times)  # the env time each query read, for the resolve stage
    dist, face = q.dist.numpy(), q.face.numpy()
    reach = r + margin
    hits = 0
    for i in range(K):
        Vt = surface_at(seq, float(times[i])).astype(np.float64)
        A, B, C = (Vt[seq.F[:, j]] for j in range(3))
        d_all = np.linalg.norm(closest_on_triangles(pts[i], A, B, C) - pts[i], axis=1)
        best = d_all.min()
        if best < reach - 1e-4:
            hits += 1
            assert dist[i] == pytest.approx(best, abs=2e-5), i
            assert d_all[face[i]] <= best + 2e-5
        elif best > reach + 1e-4:
            assert face[i] == -1
    assert 30 < hits < K


def test_reset_touches_only_the_named_envs(device):
    seq = wave_bowl(n=16, frames=8)
    rng = np.random.default_rng(2)
    E, S = 5, 3
    pos, vel = _spheres(S, rng)
    times = np.linspace(0.0, 0.3, E)

    def world():
        bm = BatchModel(SurfaceModel(seq, device), E, np.full(S, 0.05), 1.0, _params())
        return BatchedWorld(bm, BatchState(bm, pos, vel, times=times))

    a, b = world(), world()
    for _ in range(40):
        a.step()
        b.step()
    new = np.broadcast_to(np.array([0.0, 0.0, 0.9], np.float32), (S, 3))
    mask = np.array([False, True, False, True, False])
    a.reset(mask, positions=new, velocities=np.zeros((S, 3)), times=0.5)
    Pa, Pb = a.sphere_positions(), b.sphere_positions()
    np.testing.assert_array_equal(Pa[~mask], Pb[~mask])
    np.testing.assert_array_equal(Pa[mask], np.broadcast_to(new, (2, S, 3)))
    np.testing.assert_array_equal(a.env_times()[mask], [0.5, 0.5])
    np.testing.assert_array_equal(a.env_times()[~mask], b.env_times()[~mask])
    for _ in range(30):
        a.step()
        b.step()
    np.testing.assert_array_equal(a.sphere_positions()[~mask], b.sphere_positions()[~mask])
    with pytest.raises(ValueError, match="positions"):
        a.reset(mask, positions=np.zeros((S + 1, 3)))
    # env indices are not a mask ([0, 1, 2] was read as [False, True, True], leaving env 0 as it was)
    for bad in ([0, 1, 2], [1, 0, 1, 0, 1], np.ones(4, bool)):
        with pytest.raises(ValueError, match="env_mask: expected booleans, one per env"):
            a.reset(bad)
    # one playback mode of another type was a TypeError ("'int' object is not iterable")
    with pytest.raises(ValueError, match=r"playback must be one of \['auto', 'loop', 'clamp', 'pingpong'\], got 1"):
        a.reset(mask, playback=1)
    a.reset(mask, playback="pingpong")
    # rows of envs not being reset are not read (a NaN there, the usual RL buffer, was refused);
    # the reset envs' are checked
    buf = np.full((E, S, 3), np.nan, np.float32)
    buf[mask] = new
    a.reset(mask, positions=buf, velocities=np.where(np.isnan(buf), np.nan, 0.0))
    np.testing.assert_array_equal(a.sphere_positions()[mask], np.broadcast_to(new, (2, S, 3)))
    buf[1, 0, 2] = np.nan
    with pytest.raises(ValueError, match="positions: non-finite values in the envs being reset"):
        a.reset(mask, positions=buf)
    # a clock beyond float64's steps is refused, as envs.time_offset is (1e30 froze the env's clock)
    with pytest.raises(ValueError, match=r"times must be within \+-1e\+09 s"):
        a.reset(mask, times=1e30)


def test_batch_edges_a_new_user_found(device):
    """max_rate under the state's rates was taken (one sub-step where six were needed: a sphere on a
    floor rising at 1 m/s in an env at rate 30 fell through it), as reset refuses; spins given to
    point masses are warned of, as State does; World.set_time has the batch's time bound."""
    from dynmesh_warp.scenes import grid_sheet

    V0, F = grid_sheet(5, 2.0)
    V = np.stack([V0 + np.float32([0.0, 0.0, k / 24.0]) for k in range(24)]).astype(np.float32)
    from dynmesh_warp.sequence import FixedTopologySequence

    seq = FixedTopologySequence(V, F, fps=24.0)
    bm = BatchModel(SurfaceModel(seq, device), 2, np.full(1, 0.05), 1.0, _params())
    pos = np.array([[0.0, 0.0, 0.06]], np.float32)
    with pytest.raises(ValueError, match="max_rate 1: the state's env rates reach 30"):
        BatchedWorld(bm, BatchState(bm, pos, rates=[1.0, 30.0]), max_rate=1.0)
    assert BatchedWorld(bm, BatchState(bm, pos, rates=[1.0, 30.0])).substeps == 6
    with pytest.warns(UserWarning, match="BatchState: spins given to spheres that do not rotate"):
        BatchState(bm, pos, spins=np.array([[0.0, 30.0, 0.0]], np.float32))
    w = BatchedWorld(bm, BatchState(bm, pos))
    with pytest.warns(UserWarning, match="BatchedWorld.reset: spins given to spheres that do not rotate"):
        w.reset(np.array([True, False]), spins=np.array([[0.0, 30.0, 0.0]], np.float32))
    m = Model(SurfaceModel(seq, device), SphereModel(np.full(1, 0.05), 1.0, device), _params())
    with pytest.raises(ValueError, match=r"set_time: the time must be within \+-1e\+09 s"):
        World(m, State(m, pos)).set_time(1e30)


def test_pair_slots_bound_the_interpolated_surface(device):
    """The slot a sphere picks holds boxes that contain every face of the surface interpolated at
    its env's time, for each playback mode (NumPy oracle of the surface at a time)."""
    seq = pulsing_blob(subdivisions=1, frames=7)
    F = seq.F
    for playback, slices in (("loop", 1), ("loop", 3), ("pingpong", 3), ("clamp", 3)):
        bm = BatchModel(SurfaceModel(seq, device, playback=playback), 1, [0.05], 1.0, PhysicsParams(),
                        time_slices=slices)
        lo, hi = bm.pair_lowers.numpy(), bm.pair_uppers.numpy()
        T = seq.num_frames
        for t in np.linspace(0.0, 3.0 * T / seq.fps, 97):
            k = int(np.floor(t * seq.fps))
            # the playback's frame pair (pingpong reflects at the ends), then the slot rule of
            # kernels/batch.pair_slot
            k0, k1 = _wrap(k, T, playback), _wrap(k + 1, T, playback)
            a = t * seq.fps - k
            if playback == "pingpong":
                Vt = seq.V[k0].astype(np.float64) * (1 - a) + seq.V[k1].astype(np.float64) * a
            else:
                Vt = surface_at(seq, t, playback).astype(np.float64)  # the NumPy oracle
            tri = Vt[F]  # (M, 3, 3)
            if k0 == k1:  # held at an end: the pair containing it, at its end
                pair = min(k0, max(T - 2, 0))
                u = 0.0 if k0 == pair else 1.0
            elif abs(k0 - k1) == 1:
                pair, u = min(k0, k1), (a if k0 < k1 else 1.0 - a)
            else:  # the loop's wrap pair (T-1, 0)
                pair, u = T - 1, a
            slot = pair * bm.time_slices + min(int(u * bm.time_slices), bm.time_slices - 1)
            assert (tri.min(axis=1) >= lo[slot] - 1e-6).all() and (tri.max(axis=1) <= hi[slot] + 1e-6).all(), (
                playback, t, slot)
    mem = bm.memory_bytes
    assert mem["per_env"] > 0 and mem["pair_boxes"] == 2 * T * bm.time_slices * len(F) * 12
    assert bm.time_slices == 3  # time slices of the frame intervals were checked, not only whole intervals


def _wrap(k, T, playback):
    if playback == "clamp":
        return min(max(k, 0), T - 1)
    if playback == "pingpong":
        period = 2 * (T - 1)
        m = k % period
        return period - m if m >= T else m
    return k % T


def test_default_search_follows_the_sphere_count():
    from dynmesh_warp.batch import default_batch_search
    from dynmesh_warp.choices import DEFAULT_BATCH_SWEPT_SEARCH

    assert all(default_batch_search("cpu", n) == "serial" for n in (1, 10**4, 10**6))
    rows = DEFAULT_BATCH_SWEPT_SEARCH["cuda"]
    assert rows[-1][0] is None  # a catch-all row
    for (up_to, search), (_, after) in zip(rows, rows[1:]):
        assert default_batch_search("cuda", up_to) == search and default_batch_search("cuda", up_to + 1) == after


def test_batch_needs_a_fixed_surface_and_spheres(device):
    seq = wave_bowl(n=8, frames=4)
    with pytest.raises(ValueError, match="num_envs"):
        BatchModel(SurfaceModel(seq, device), 0, [0.05], 1.0, PhysicsParams())
    with pytest.raises(ValueError, match="grid_cell_radii"):
        BatchModel(SurfaceModel(seq, device), 1, [0.05], 1.0, PhysicsParams(), grid_cell_radii=0.0)
    with pytest.raises(ValueError, match="at least one sphere"):
        BatchModel(SurfaceModel(seq, device), 2, [], 1.0, PhysicsParams())
    bm = BatchModel(SurfaceModel(seq, device), 2, [0.05], 1.0, PhysicsParams())
    with pytest.raises(ValueError, match="non-finite"):
        BatchState(bm, [[0.0, 0.0, np.nan]])
    assert wp.get_device(bm.device) == wp.get_device(device)
    st = BatchState(bm, [[0.0, 0.0, 0.5]])
    with pytest.raises(ValueError, match="swept_search"):
        BatchedWorld(bm, st, search="nearest")
    with pytest.raises(ValueError, match="tile_threads"):
        BatchedWorld(bm, st, search="tiled", tile_threads=0)
    for single in ("faces", "sphere_grid"):  # a single world's searches
        with pytest.raises(ValueError, match=f"swept_search '{single}'"):
            BatchedWorld(bm, st, search=single)
    with pytest.raises(ValueError, match="budget"):
        BatchedWorld(bm, st, search="hybrid", budget=-1)
    bm_tiled = BatchModel(SurfaceModel(seq, device), 2, [0.05], 1.0, PhysicsParams(swept_search="tiled"))
    assert BatchedWorld(bm_tiled, BatchState(bm_tiled, [[0.0, 0.0, 0.5]])).search == "tiled"  # physics.swept_search


def test_memory_per_env_counts_every_array_of_an_env(device):
    """The per-env memory a batch reports (summary.json's ``memory_bytes``) against a count by
    hand of what each sphere and env holds: radius, inverse mass, env index, position, velocity,
    spin (4 + 4 + 4 + 12 + 12 + 12), its contact (face, point, normal, depth, velocity: 4 + 12 + 12 + 4 + 12)
    and pinch memory (64), the clock (8 + 4 + 4) and the reset mask (4); a split search adds the
    query record (dist, face, weights, normal sum, time, hand-over: 4 + 4 + 12 + 12 + 8 + 4). A
    new user measured 740 B an env of 5 spheres where 416 was said (contacts' pinch memory and the
    mask left out)."""
    seq = wave_bowl(n=8, frames=4)
    S, E = 3, 5
    bm = BatchModel(SurfaceModel(seq, device), E, [0.05] * S, 1.0, PhysicsParams())
    sphere = 4 + 4 + 4 + 12 + 12 + 12 + (4 + 12 + 12 + 4 + 12) + 64
    for search, query in (("serial", 0), ("grid", 4 + 4 + 12 + 12 + 8 + 4)):
        bw = BatchedWorld(bm, BatchState(bm, np.zeros((S, 3), np.float32) + [0.0, 0.0, 0.5]), search=search)
        assert bw.memory_bytes["per_env"] == S * (sphere + query) + 8 + 4 + 4 + 4, search
    assert bm.memory_bytes["per_env"] == S * sphere + 8 + 4 + 4  # the model's estimate: no mask, no query


def test_env_view_shows_one_env_at_its_own_time(device):
    """EnvView (what the viewer shows of a batch): the surface at the env's own time (NumPy
    oracle), that env's spheres and clock; stepping it steps the batch."""
    seq = wave_bowl(n=12, frames=6)
    from dynmesh_warp.batch import EnvView

    bm = BatchModel(SurfaceModel(seq, device, playback="loop"), 3, [0.05, 0.07], 1.0, PhysicsParams())
    pos = np.array([[0.0, 0.0, 0.5], [0.2, 0.1, 0.6]], np.float32)
    bw = BatchedWorld(bm, BatchState(bm, pos, times=[0.0, 0.11, 0.2]))
    v = EnvView(bw, 2)
    for _ in range(5):
        v.step()
    assert v.time == pytest.approx(bw.env_times()[2]) and bw.step_count == 5
    np.testing.assert_allclose(v.surface_points().numpy(), surface_at(seq, v.time, "loop"), atol=1e-5)
    np.testing.assert_array_equal(v.sphere_positions(), bw.sphere_positions()[2])
    np.testing.assert_array_equal(v.sphere_radii(), np.array([0.05, 0.07], np.float32))
    with pytest.raises(IndexError):
        EnvView(bw, 3)


def test_env_grid_shows_several_envs_side_by_side(device, tmp_path):
    """EnvGrid (the viewer's grid of a few envs): tile i is env envs[i]'s surface at its own time
    (NumPy oracle) shifted by its offset, with that env's spheres; tiles do not overlap; the
    viewer runs on it (a headless recording, the splats streamed in groups)."""
    pytest.importorskip("viser")
    from dynmesh_warp.batch import EnvGrid
    from dynmesh_warp.gaussians import gaussians_for_surface
    from dynmesh_warp.viewer import Viewer

    seq = wave_bowl(n=12, frames=6)
    bm = BatchModel(SurfaceModel(seq, device, playback="loop"), 4, [0.05], 1.0, PhysicsParams())
    bw = BatchedWorld(bm, BatchState(bm, [[0.0, 0.0, 0.5]], times=[0.0, 0.11, 0.2, 0.33]))
    grid = EnvGrid(bw, [3, 1, 2])
    for _ in range(3):
        grid.step()
    P = grid.surface_points().numpy()
    N = seq.num_vertices
    times = bw.env_times()
    for i, e in enumerate([3, 1, 2]):
        np.testing.assert_allclose(P[i * N:(i + 1) * N], surface_at(seq, times[e], "loop") + grid.offsets[i], atol=1e-5)
        np.testing.assert_allclose(grid.sphere_positions()[i], bw.sphere_positions()[e][0] + grid.offsets[i], atol=1e-6)
    lo = [P[i * N:(i + 1) * N].min(0) for i in range(3)]
    hi = [P[i * N:(i + 1) * N].max(0) for i in range(3)]
    assert all((hi[i][:2] < lo[j][:2]).any() or (hi[j][:2] < lo[i][:2]).any()
               for i in range(3) for j in range(i + 1, 3))  # apart in x or y
    assert grid.surface_indices().shape[0] == 3 * 3 * seq.num_faces and grid.sphere_radii().shape == (3,)
    g = gaussians_for_surface(grid.surface.sequence, None, grid.device)
    v = Viewer(grid, g, port=0, realtime=False, record=tmp_path / "grid.viser", log=lambda *a: None)
    try:
        v.run(max_frames=3)
        assert v.stream is not None and v.stream.error["max"] < 0.05
    finally:
        v.close()
    assert (tmp_path / "grid.viser").stat().st_size > 0
    with pytest.raises(IndexError):
        EnvGrid(bw, [0, 4])


@pytest.mark.parametrize("playback,cycle_frames", [("loop", 12), ("pingpong", 22), ("clamp", 11)])
def test_random_env_starts_span_one_cycle_of_the_playback(playback, cycle_frames):
    """``envs.time_offset: random`` draws each env's start uniformly over one cycle of its
    playback, as the RL env's reset does: loop T frames, pingpong 2 (T - 1) (forward and back),
    clamp T - 1 (not on the held last frame). A new user found every mode drawn over T / fps:
    2 of 64 pingpong envs started past the turn, 2 of 64 clamp envs on the held last frame."""
    from dynmesh_warp.batch import build_batched_world
    from dynmesh_warp.config import SceneConfig

    cfg = SceneConfig.model_validate({"surface": {"source": "builtin:wave_bowl", "params": {"n": 8, "frames": 12},
                                                  "playback": playback},
                                      "spheres": {"count": 1, "radius": 0.05},
                                      "envs": {"count": 400, "time_offset": "random", "seed": 3}})
    w = build_batched_world(cfg, device="cpu")
    frames = w.env_times() * w.model.surface.fps
    assert frames.min() >= 0.0 and frames.max() < cycle_frames
    # uniform over the cycle: each quarter holds about a quarter of the starts (binomial, 400 draws)
    counts = np.histogram(frames, bins=4, range=(0.0, cycle_frames))[0]
    assert (np.abs(counts - 100) < 40).all(), counts


def test_batched_envs_starting_later_do_not_start_inside_the_surface():
    """Envs start at random times (envs.time_offset: random) but every env got the scene's spheres
    placed for frame 0: a new user's raised arm held spheres of 3 of 8 envs inside it, and they
    fell out through it with no word. A listed sphere inside the closed surface at an env's start
    frame is now refused naming the env; spawned spheres are dropped above every frame."""
    import trimesh

    from dynmesh_warp.batch import build_batched_world
    from dynmesh_warp.config import SceneConfig, SceneError
    from dynmesh_warp.sequence import FixedTopologySequence

    m = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    V0 = np.asarray(m.vertices, np.float32)
    lift = np.linspace(0.0, 0.5, 24, dtype=np.float32)  # the ball rises 0.5 m over one second
    seq = FixedTopologySequence(V0[None] + lift[:, None, None] * np.float32([0, 0, 1]), np.asarray(m.faces), fps=24.0)
    listed = {"surface": {"source": "builtin:wave_bowl", "playback": "clamp"}, "physics": {"ground": None},
              "spheres": [{"position": [0.0, 0.0, 0.45], "radius": 0.05}]}  # above the ball at frame 0 only
    cfg = SceneConfig.model_validate({**listed, "envs": {"count": 8, "time_offset": "random", "seed": 1}})
    with pytest.raises(SceneError, match=r"env \d+ starts at t = .* on frame \d+: spheres.0: position \[0.0, 0.0, 0.45\] "
                                         r"starts inside the closed surface \(frame \d+\).*envs.time_offset: 0"):
        build_batched_world(cfg, device="cpu", sequence=seq)
    same = SceneConfig.model_validate({**listed, "envs": {"count": 8, "time_offset": 0.0}})
    assert build_batched_world(same, device="cpu", sequence=seq).model.num_envs == 8
    spawn = SceneConfig.model_validate({**listed, "spheres": {"count": 3, "radius": 0.05, "height": 0.1},
                                        "envs": {"count": 8, "time_offset": "random", "seed": 1}})
    w = build_batched_world(spawn, device="cpu", sequence=seq)
    z = w.sphere_positions()[..., 2]
    assert z.min() >= float(seq.V[..., 2].max()) + 0.1  # above the highest point of any frame


def test_a_batch_that_cannot_fit_the_free_memory_is_refused_before_it_is_allocated(monkeypatch):
    """A new user's --envs 100000000 was killed by the out-of-memory killer (24 GB resident on a
    23 GB machine); the batch's least size (BYTES_PER_ENV, BYTES_PER_SPHERE) against the
    device's free memory is checked first, naming both."""
    import dynmesh_warp.batch as batch
    from dynmesh_warp.config import SceneError

    scene = {"surface": {"source": "builtin:pulsing_blob", "params": {"subdivisions": 1, "frames": 4}}}
    monkeypatch.setattr(batch, "free_bytes", lambda device=None: 1_000_000)
    with pytest.raises(SceneError, match=r"envs.count 10,000: needs about 9.5 MiB on cpu, 1.0 MiB free; fewer envs"):
        batch.build_batched_world(scene, device="cpu", num_envs=10_000)  # 10,000 x 384 bytes > 1 MB
    assert batch.build_batched_world(scene, device="cpu", num_envs=100).num_envs == 100
    assert batch.free_bytes(wp.get_device("cpu")) > 0  # the host's available memory is known here


def test_listed_spheres_under_an_open_sheet_in_a_later_env_are_said_to_have_fallen():
    """An open sheet rising 0.5 m/s, spheres listed just above it for frame 0, envs starting at
    random times: in the envs that start later the spheres begin under the sheet and fall; a new
    user's run said only "4/16 spheres in contact". The run line now says how many fell past the
    surface and the envs' start times as a cause; envs all starting at 0 keep theirs."""
    from dynmesh_warp.batch import build_batched_world
    from dynmesh_warp.config import SceneConfig
    from dynmesh_warp.sequence import FixedTopologySequence

    n = 12
    g = np.linspace(-1.0, 1.0, n)
    X, Y = np.meshgrid(g, g, indexing="ij")
    V0 = np.stack([X.ravel(), Y.ravel(), np.full(n * n, 0.5)], 1).astype(np.float32)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    F = np.concatenate([np.stack([a, a + n, a + n + 1], 1), np.stack([a, a + n + 1, a + 1], 1)])
    lift = np.float32(0.5) * np.arange(30, dtype=np.float32) / 24
    seq = FixedTopologySequence(V0[None] + lift[:, None, None] * np.float32([0, 0, 1]), F, fps=24.0)
    listed = {"surface": {"source": "builtin:wave_bowl", "playback": "clamp"}, "physics": {"ground": None},
              "spheres": [{"position": [0.1, 0.2, 0.56], "radius": 0.05}]}
    lines = {}
    for offset in ("random", 0.0):
        cfg = SceneConfig.model_validate({**listed, "envs": {"count": 8, "time_offset": offset, "seed": 0}})
        w = build_batched_world(cfg, device="cpu", sequence=seq)
        for _ in range(240):
            w.step()
        lines[offset] = w.run_line()[1]
        z = w.sphere_positions()[:, 0, 2]
        fell = int((z < 0.5 - 0.5 * float(np.linalg.norm(np.ptp(seq.V.reshape(-1, 3), axis=0)))).sum())
        if fell:
            assert f"{fell} of 8 spheres fell past the surface" in lines[offset] and "envs.time_offset: 0" in lines[offset]
        else:
            assert "fell past" not in lines[offset]
    assert "fell past" in lines["random"] and "fell past" not in lines[0.0]


def test_an_env_start_time_beyond_float64_steps_is_refused():
    """envs.time_offset 1e30 was accepted and froze every env clock (t + dt == t in float64)."""
    from dynmesh_warp.config import EnvsConfig

    with pytest.raises(ValueError, match=r"(?s)time_offset.*at most 1e\+09 s"):
        EnvsConfig(count=4, time_offset=1e30)
    assert EnvsConfig(count=4, time_offset=3600.0).time_offset == 3600.0


def test_a_rate_beyond_the_work_budget_names_envs_rate():
    """envs.rate [1, 1e6] stopped the run naming the surface speed, the radius and dt but not
    the rate that set it (a new user's): the error now names envs.rate and the rate that fits."""
    from dynmesh_warp.batch import build_batched_world
    from dynmesh_warp.config import SceneConfig
    from dynmesh_warp.world import WorkBudgetError

    cfg = SceneConfig.model_validate({"surface": {"source": "builtin:wave_bowl", "params": {"n": 8, "frames": 12}},
                                      "spheres": {"count": 1, "radius": 0.05}, "envs": {"count": 4, "rate": [1, 1e6]}})
    with pytest.raises(WorkBudgetError, match=r"the fastest env's rate 1e\+06 x the surface's own .* envs.rate up to \S+ fits"):
        build_batched_world(cfg, device="cpu")


def test_a_scene_collider_other_than_swept_is_refused_with_envs(tmp_path):
    """``--collider rebuild`` with envs was refused, but the scene's own ``physics.collider: rebuild``
    was dropped unsaid (the run used the swept pair BVHs; a new user's): refused alike, before any work."""
    from dynmesh_warp.config import SceneConfig, SceneError
    from dynmesh_warp.run import run_scene

    base = {"surface": {"source": "builtin:wave_bowl", "params": {"n": 8, "frames": 12}}, "device": "cpu",
            "spheres": {"count": 1, "radius": 0.05}, "envs": {"count": 2}, "run": {"steps": 2, "output": str(tmp_path)}}
    for physics in ({"collider": "rebuild"}, {"collider": "refit"}, {"rebuild_every": "frame"}):
        with pytest.raises(SceneError, match=r"batched envs \(envs.count > 1\) use the swept pair BVHs"):
            run_scene(SceneConfig.model_validate({**base, "physics": physics}), progress=False, log=lambda *a: None)
    assert not any(tmp_path.iterdir())
