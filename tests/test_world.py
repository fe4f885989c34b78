"""World tests: sphere dynamics against analytic references, no tunnelling, collider agreement.

Every expectation comes from outside the engine: closed-form mechanics (lifting, carrying by
friction, restitution apex e^2 h, sliding on an incline at g (sin - mu cos)), a NumPy height
field / winding number of the surface at the world's time, or another collider.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from reference import brute_nearest, grid_height, surface_at, winding_number
from dynmesh_warp import scenes
from dynmesh_warp import world as world_mod
from dynmesh_warp.sequence import FixedTopologySequence
from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, VaryingSurfaceModel, World
from conftest import TEST_DEVICE

G = 9.81
DT = 1.0 / 240.0
# every concrete collider the world offers ("fixed" is an alias chosen from the surface)
COLLIDERS = [c for c in getattr(world_mod, "COLLIDER_CHOICES", ("fixed", "rebuild")) if c != "fixed"] or ["fixed"]


def make_world(seq, positions, radius=0.1, collider="fixed", playback="clamp", interpolate=True,
               velocities=None, device=TEST_DEVICE, rebuild_every="step", **params) -> World:
    surf = SurfaceModel(seq, device, playback=playback, interpolate=interpolate)
    positions = np.asarray(positions, np.float32).reshape(-1, 3)
    radius = np.broadcast_to(np.asarray(radius, np.float32), (len(positions),))
    model = Model(surf, SphereModel(radius, 1.0, device), PhysicsParams(**{"dt": DT, **params}))
    state = State(model, positions, velocities)
    return World(model, state, collider=collider, rebuild_every=rebuild_every)


def run(world: World, steps: int):
    """Step and record (time, positions, velocities) after every step."""
    ts, ps, vs = [], [], []
    for _ in range(steps):
        world.step()
        ts.append(world.time)
        ps.append(np.array(world.sphere_positions(), copy=True))  # .numpy() on the CPU is a view
        vs.append(np.array(world.sphere_velocities(), copy=True))
    return np.asarray(ts), np.asarray(ps), np.asarray(vs)


def moving_sheet(velocity, frames, fps=24.0, n=5, size=4.0, rotation=None) -> FixedTopologySequence:
    """A flat grid sheet translating at a constant velocity [m/s] (frame k at k / fps)."""
    V0, F = scenes.grid_sheet(n, size)
    V0 = V0.astype(np.float64)
    if rotation is not None:
        V0 = V0 @ np.asarray(rotation).T
    V = np.stack([V0 + np.asarray(velocity) * (k / fps) for k in range(frames)])
    return FixedTopologySequence(V.astype(np.float32), F, fps=fps)


# ---------------------------------------------------------------------------------------------
# dynamics against closed-form mechanics
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("collider", COLLIDERS)
def test_rising_surface_lifts_sphere(collider):
    u, fps, T, r = 0.4, 24.0, 60, 0.1  # surface rises 0.4 m/s until t = 59/24 s, then stops (clamp)
    seq = moving_sheet((0, 0, u), T, fps)
    # starts moving with the surface (from rest it would be an impact at 0.4 m/s, and bounce)
    w = make_world(seq, [[0.2, -0.1, r]], r, collider=collider, playback="clamp", velocities=[[0, 0, u]])
    t, p, v = run(w, int(2.2 / DT))
    # tracks surface + radius, moving with the surface's speed
    np.testing.assert_allclose(p[:, 0, 2], u * t + r, atol=2e-3)
    np.testing.assert_allclose(v[5:, 0, 2], u, atol=2e-3)
    np.testing.assert_allclose(p[:, 0, :2], [[0.2, -0.1]] * len(t), atol=1e-5)  # no sideways drift
    # past the last frame (clamp) the surface stops: the sphere flies up u^2/2g, lands, rests
    t2, p2, v2 = run(w, int(1.2 / DT))
    z_end = u * (T - 1) / fps
    assert p2[:, 0, 2].max() == pytest.approx(z_end + r + u * u / (2 * G), abs=2e-3)
    assert p2[-1, 0, 2] == pytest.approx(z_end + r, abs=1e-3)
    assert abs(v2[-1, 0, 2]) < 1e-2


@pytest.mark.parametrize("collider", COLLIDERS)
def test_sliding_surface_carries_sphere_by_friction(collider):
    u, mu, fps, r = 0.5, 0.5, 24.0, 0.1
    seq = moving_sheet((u, 0, 0), 50, fps, n=5, size=6.0)
    w = make_world(seq, [[0, 0, r]], r, collider=collider, playback="clamp", friction=mu)
    t, p, v = run(w, int(1.5 / DT))
    # Coulomb: relative speed u decays at mu g; afterwards the sphere moves with the surface,
    # u^2 / (2 mu g) behind where a stuck sphere would be
    t_stick = u / (mu * G)
    sliding = t < t_stick - 0.02
    np.testing.assert_allclose(v[sliding, 0, 0], mu * G * t[sliding], atol=0.03)
    stuck = t > t_stick + 0.05
    np.testing.assert_allclose(v[stuck, 0, 0], u, atol=1e-3)
    np.testing.assert_allclose(p[stuck, 0, 0], u * t[stuck] - u * u / (2 * mu * G), atol=3e-3)
    np.testing.assert_allclose(p[:, 0, 2], r, atol=1e-3)
    np.testing.assert_allclose(v[:, 0, 1:], 0.0, atol=1e-3)


def _static_sheet(n=5, size=4.0, rotation=None):
    return moving_sheet((0, 0, 0), 1, 24.0, n=n, size=size, rotation=rotation)


@pytest.mark.parametrize("e", [0.6, 0.3])
def test_restitution_rebound_apex(e):
    h, r = 0.5, 0.1
    w = make_world(_static_sheet(), [[0.1, 0.2, r + h]], r, restitution=e)
    t, p, v = run(w, int(1.3 / DT))
    z, vz = p[:, 0, 2], v[:, 0, 2]
    up = np.flatnonzero((vz[1:] > 0) & (vz[:-1] <= 0)) + 1  # steps where a bounce happened
    assert len(up) >= 1
    i0 = up[0]
    i1 = up[1] if len(up) > 1 else len(z)
    t_impact = math.sqrt(2 * h / G)
    assert t[i0] == pytest.approx(t_impact, abs=2 * DT)
    assert vz[i0] == pytest.approx(e * math.sqrt(2 * G * h), rel=0.03)
    apex = z[i0:i1].max() - r
    assert apex == pytest.approx(e * e * h, rel=0.05)
    assert z.min() >= r - 1e-3  # never sinks into the floor


@pytest.mark.parametrize("collider", COLLIDERS)
def test_each_step_takes_the_velocity_of_the_frame_interval_it_crosses(collider):
    """A sheet zig-zagging in x (+1 m/s over frames 0 -> 1, -1 m/s over 1 -> 2, ...) under a
    resting sphere, dt = 1 / 240 at 24 fps (10 steps a frame): every step's contact takes the
    velocity of the interval it crosses. The clock is summed from dt, so most steps meant to
    start on a frame boundary start a few ulps before it; they took the previous interval's
    velocity, of the wrong sign here (a new user: 16 of 24 boundary steps)."""
    fps, T, r = 24.0, 30, 0.05
    V0, F = scenes.grid_sheet(5, 4.0)
    x = np.concatenate([[0.0], np.cumsum([(1.0 if k % 2 == 0 else -1.0) / fps for k in range(T - 1)])])
    seq = FixedTopologySequence(np.stack([V0 + [xk, 0.0, 0.0] for xk in x]).astype(np.float32), F, fps=fps)
    w = make_world(seq, [[0.0, 0.0, r]], r, collider=collider, friction=1.0)
    wrong = []
    for n in range(240):
        k = n // 10  # the interval the step [n dt, (n + 1) dt] lies in
        w.step()
        assert w.contacts.face.numpy()[0] >= 0
        vx = float(w.contacts.velocity.numpy()[0][0])
        if vx != pytest.approx(1.0 if k % 2 == 0 else -1.0, abs=1e-4):
            wrong.append((n, k, vx))
    assert not wrong


def test_zero_restitution_does_not_bounce():
    h, r = 0.5, 0.1
    w = make_world(_static_sheet(), [[0.0, 0.0, r + h]], r, restitution=0.0)
    t, p, v = run(w, int(1.0 / DT))
    after = t > math.sqrt(2 * h / G) + 2 * DT
    assert after.sum() > 100
    np.testing.assert_allclose(p[after, 0, 2], r, atol=1e-4)
    np.testing.assert_allclose(v[after, 0], 0.0, atol=1e-3)


def _incline(theta):
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])  # about x: +z normal -> (0, -s, c)
    return R, R @ [0, 0, 1], R @ [0, 1, 0]


@pytest.mark.parametrize("mu, slides", [(0.5, False), (0.2, True), (0.0, True)])
def test_friction_on_incline(mu, slides):
    theta = math.radians(20.0)  # tan = 0.364
    r = 0.1
    R, n, up_slope = _incline(theta)
    w = make_world(_static_sheet(size=4.0, rotation=R), [r * n], r, friction=mu)
    t, p, v = run(w, int(0.8 / DT))
    d = (p[:, 0] - r * n) @ (-up_slope)  # distance travelled downhill
    gap = p[:, 0] @ n - r
    np.testing.assert_allclose(gap, 0.0, atol=1e-3)  # stays on the plane
    if not slides:
        assert np.abs(p[:, 0] - r * n).max() < 1e-3
        assert np.abs(v[-1, 0]).max() < 1e-3
    else:
        a = G * (math.sin(theta) - mu * math.cos(theta))
        # semi-implicit Euler travels a dt^2 n(n+1)/2 after n steps: 1/n above the continuous curve
        np.testing.assert_allclose(d[60:], 0.5 * a * t[60:] ** 2, rtol=0.025)
        np.testing.assert_allclose(v[-1, 0] @ (-up_slope), a * t[-1], rtol=0.02)


@pytest.mark.parametrize("body, k, mu", [("solid", 0.4, 0.5), ("shell", 2.0 / 3.0, 0.5), ("solid", 0.4, 0.05),
                                         ("point", 0.0, 0.5)])
def test_ball_on_incline_rolls_or_slides(body, k, mu):
    """physics.sphere_body: a body that rotates rolls down a 20-degree slope at g sin / (1 + k)
    (k = I / m r^2; 5/7 and 3/5 g sin) with spin v / r where tan <= (1 + 1/k) mu, and slides at
    g (sin - mu cos) spinning up at mu g cos / (k r) where friction cannot hold it (closed forms of
    rigid-body mechanics); the point mass sticks (tan 20 < 0.5) and never spins."""
    theta = math.radians(20.0)
    r = 0.1
    R, n, up_slope = _incline(theta)
    w = make_world(_static_sheet(size=4.0, rotation=R), [r * n], r, friction=mu, sphere_body=body)
    t, p, v = run(w, int(0.8 / DT))
    down = v[:, 0] @ (-up_slope)
    spin = w.sphere_spins()[0]
    np.testing.assert_allclose(p[:, 0] @ n - r, 0.0, atol=1e-3)  # stays on the plane
    if k == 0.0:
        assert np.abs(down).max() < 1e-3 and not spin.any()
        return
    rolls = math.tan(theta) <= (1 + 1 / k) * mu
    a = G * math.sin(theta) / (1 + k) if rolls else G * (math.sin(theta) - mu * math.cos(theta))
    np.testing.assert_allclose(down[-1], a * t[-1], rtol=0.01)
    axis = np.cross(n, -up_slope)  # rolling down the slope turns the ball about n x (downhill)
    if rolls:
        np.testing.assert_allclose(spin @ axis * r, down[-1], rtol=1e-3)
    else:
        np.testing.assert_allclose(spin @ axis, mu * G * math.cos(theta) / (k * r) * t[-1], rtol=0.01)
    np.testing.assert_allclose(spin - (spin @ axis) * axis, 0.0, atol=1e-4)


def test_ball_launched_sliding_rolls_on_at_five_sevenths():
    """A solid ball launched sliding at v0 on a level floor (mu = 0.5): friction slows the centre
    and spins the ball until the contact point stops slipping at t = 2 v0 / (7 mu g), then it
    rolls on at 5/7 v0 for ever (no rolling resistance); the point mass stops at v0^2 / (2 mu g)."""
    r, v0, mu = 0.05, 2.0, 0.5
    t_roll = 2 * v0 / (7 * mu * G)
    for body, v_end in (("solid", 5.0 / 7.0 * v0), ("point", 0.0)):
        w = make_world(_static_sheet(size=8.0), [[-1.5, 0.0, r]], r, friction=mu, sphere_body=body,
                       velocities=[[v0, 0.0, 0.0]])
        t, p, v = run(w, int(0.6 / DT))
        np.testing.assert_allclose(v[-1, 0], [v_end, 0.0, 0.0], atol=2e-3)
        if body == "solid":
            i = int(np.searchsorted(t, t_roll + 2 * DT))
            np.testing.assert_allclose(v[i:, 0, 0], v_end, atol=2e-3)  # rolling from then on
            j = int(np.searchsorted(t, 0.5 * t_roll))
            np.testing.assert_allclose(v[j, 0, 0], v0 - mu * G * t[j], atol=2e-2)  # sliding before
            np.testing.assert_allclose(w.sphere_spins()[0], [0.0, v_end / r, 0.0], rtol=1e-3, atol=1e-3)
        else:
            np.testing.assert_allclose(p[-1, 0, 0] + 1.5, v0 ** 2 / (2 * mu * G), rtol=0.02)


def test_contacts_numpy_are_copies_that_later_steps_leave_alone():
    """``Contacts.numpy()`` copies (on the CPU ``.numpy()`` is a view: a new user's log of five
    steps' contacts on a rising floor read five times the last); the point rises with the floor."""
    w = make_world(moving_sheet((0.0, 0.0, 0.5), 48, fps=24.0), [[0.1, 0.2, 0.1]], 0.1)
    log = []
    for _ in range(5):
        w.step()
        log.append(w.contacts.numpy())
    z = np.array([c["point"][0, 2] for c in log])
    np.testing.assert_allclose(np.diff(z), 0.5 * DT, rtol=1e-3)


@pytest.mark.parametrize("collider", ["refit", "swept", "rebuild"])
def test_centre_level_with_a_sheet_past_its_rim_is_pushed_off_the_rim(collider):
    """A sphere (r 5 cm) centred exactly in a static sheet's plane, 3 cm past its rim: the closest
    point is on the rim, the contact normal points from it to the centre (-x) and the depth is
    r - 3 cm (closed form). The side there is a tie of the query's sign that the colliders broke
    differently: refit and rebuild pulled the sphere 8 cm onto the sheet."""
    V0, F = scenes.grid_sheet(5, 2.0)
    w = make_world(FixedTopologySequence(V0[None].astype(np.float32), F, fps=24.0), [[-1.03, 0.3, 0.0]], 0.05,
                   collider=collider, gravity=(0.0, 0.0, 0.0), restitution=0.0)
    w.step()
    c = w.contacts.numpy()
    np.testing.assert_allclose(c["normal"][0], [-1.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(c["depth"][0], 0.02, atol=1e-6)
    np.testing.assert_allclose(w.sphere_positions()[0], [-1.05, 0.3, 0.0], atol=1e-6)


def test_ball_on_a_belt_rolls_at_two_sevenths_spinning_against_its_travel():
    """A solid ball set at rest on a belt moving at U (mu = 0.5) is dragged and spun until its
    contact point moves with the belt; angular momentum about the contact point is conserved, so
    it ends at v = 2U/7 with omega r = 5U/7 against its travel (v - omega r = U along the belt).
    docs/physics.md had the spin as 2U/7; a later user computed it."""
    r, U = 0.05, 1.0
    w = make_world(moving_sheet((U, 0.0, 0.0), 240, fps=240.0, size=8.0), [[0.0, 0.0, r]], r, friction=0.5,
                   sphere_body="solid")
    run(w, int(0.5 / DT))
    np.testing.assert_allclose(w.sphere_velocities()[0], [2.0 * U / 7.0, 0.0, 0.0], atol=1e-4)
    np.testing.assert_allclose(w.sphere_spins()[0] * r, [0.0, -5.0 * U / 7.0, 0.0], atol=1e-4)


def test_rolling_batch_reset_keeps_the_spin_and_spins_can_be_given():
    """A batched reset keeps what it is not given, the spin too (zeroed, a ball rolling at 5/7 v0
    slipped again and slowed to 1.02 m/s: a new user's); ``BatchState(spins=)`` and ``reset(spins=)``
    set it, ``sphere_spins()`` reads it; a backspun solid ball on a floor ends at (5 v0 - 2 r w0) / 7
    (closed form); spins given to point masses are kept, change nothing and are warned of; a run's
    summary records the sphere body."""
    from dynmesh_warp.batch import BatchedWorld, BatchModel, BatchState
    from dynmesh_warp.world import physics_summary

    r, v0, mu = 0.05, 2.0, 0.5
    seq = _static_sheet(size=8.0)
    params = PhysicsParams(dt=DT, friction=mu, sphere_body="solid")
    bm = BatchModel(SurfaceModel(seq, TEST_DEVICE, playback="clamp"), 2, [r], 1.0, params)
    bw = BatchedWorld(bm, BatchState(bm, np.float32([[[-3.0, 0, r]], [[-3.0, 0, r]]]),
                                     velocities=np.float32([[[v0, 0, 0]], [[v0, 0, 0]]]),
                                     spins=np.float32([[[0, 0, 0]], [[0, -20.0, 0]]])))
    for _ in range(int(0.5 / DT)):
        bw.step()
    v = bw.sphere_velocities()[:, 0, 0]
    np.testing.assert_allclose(v, [5 / 7 * v0, (5 * v0 - 2 * r * 20.0) / 7], atol=2e-3)  # rolling; backspun
    rolling = bw.sphere_spins()
    bw.reset(np.array([True, False]), times=0.0)  # position, velocity and spin kept
    np.testing.assert_allclose(bw.sphere_spins(), rolling, atol=1e-6)
    for _ in range(60):
        bw.step()
    np.testing.assert_allclose(bw.sphere_velocities()[0, 0, 0], 5 / 7 * v0, atol=2e-3)  # still rolling
    bw.reset(np.array([True, False]), spins=np.zeros((1, 3), np.float32))
    assert not bw.sphere_spins()[0].any() and bw.sphere_spins()[1].any()
    with pytest.warns(UserWarning, match="spins given to spheres that do not rotate"):
        w = make_world(seq, [[0.0, 0.0, r]], r, friction=mu)
        State(w.model, [[0.0, 0.0, r]], spins=[[0.0, -50.0, 0.0]])
    assert physics_summary(params)["sphere_body"] == "solid" and w.run_summary()["physics"]["sphere_body"] == "point"


@pytest.mark.parametrize("e", [0.5, 0.7])
def test_ground_plane_bounces_like_the_mesh_plane(e):
    """The ground plane's contact has the mesh's time of impact: a sphere dropped on it rebounds
    to the same apexes as on a mesh plane at the same height (it was clamped: 4th apex 0.65 x
    e^8 h at dt 1/240, a new user's), each within 10 % of e^2n h."""
    r, h = 0.05, 1.0
    apexes = []
    for ground in (None, 0.0):
        seq = _static_sheet(size=4.0)
        if ground is not None:  # the mesh far below: only the ground plane stops the sphere
            seq = FixedTopologySequence(seq.V - np.float32([0, 0, 5.0]), seq.F, fps=seq.fps)
        w = make_world(seq, [[0.0, 0.0, h + r]], r, restitution=e, friction=0.5, ground_height=ground)
        t, p, v = run(w, int(2.5 / DT))
        vz = v[:, 0, 2]
        top = np.flatnonzero((vz[1:] <= 0) & (vz[:-1] > 0)) + 1  # the steps where it turns down
        apexes.append(p[top[:3], 0, 2] - r)
        assert p[:, 0, 2].min() > r - 1e-6
    np.testing.assert_allclose(apexes[1], apexes[0], rtol=1e-3)
    np.testing.assert_allclose(apexes[1], [h * e ** (2 * k) for k in (1, 2, 3)], rtol=0.1)


def test_fast_sphere_note_names_the_sphere_and_the_substeps():
    """runner.fast_sphere_note: a sphere whose sampled speed took it over its radius in one
    sub-step is named with its radii a sub-step and the sub-steps that keep it within one."""
    from dynmesh_warp.runner import fast_sphere_note

    v = np.zeros((3, 2, 3))
    v[1, 1] = [30.0, 0.0, 0.0]  # 30 m/s x 1/240 s = 2.5 radii of 0.05 m
    note = fast_sphere_note({"velocity": v, "radius": np.array([0.05, 0.05])}, 1 / 240, 1)
    assert "sphere 1: 30 m/s, 2.5 radii a sub-step" in note and "physics.substeps=3" in note
    assert fast_sphere_note({"velocity": v, "radius": np.array([0.05, 0.05])}, 1 / 240, 4) == ""
    assert fast_sphere_note({"velocity": v * 0.1, "radius": np.array([0.05, 0.05])}, 1 / 240, 1) == ""
    v[1, 1] = [1000.0, 0.0, 0.0]  # 84 sub-steps: over the default bound of 64, which the note names too
    note = fast_sphere_note({"velocity": v, "radius": np.array([0.05, 0.05])}, 1 / 240, 1, 64)
    assert "physics.substeps=84 --set physics.max_substeps=84 (its bound, 64, is lower)" in note


# ---------------------------------------------------------------------------------------------
# no tunnelling
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("collider", COLLIDERS)
def test_no_tunnelling_wave_bowl(collider):
    n, size = 32, 2.0
    seq = scenes.wave_bowl(n=n, frames=24)
    rng = np.random.default_rng(0)
    S, r = 24, 0.04
    pos = np.column_stack([rng.uniform(-0.6, 0.6, (S, 2)), rng.uniform(0.5, 1.2, S)])
    vel = rng.normal(0, 0.3, (S, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w = make_world(seq, pos, r, collider=collider, playback="loop", velocities=vel)
    steps = 2400 if collider != "rebuild" else 1200  # 10 s / 5 s: 10 / 5 loops of the 1 s sequence
    worst = np.inf
    for i in range(steps):
        w.step()
        if i % 10 == 0 or i == steps - 1:
            P = w.sphere_positions()
            assert np.isfinite(P).all() and np.isfinite(w.sphere_velocities()).all(), f"NaN at step {i}"
            Vt = surface_at(seq, w.time, "loop")
            hz = grid_height(Vt, n, size, P[:, :2])
            on = np.isfinite(hz)
            clearance = P[on, 2] - hz[on]
            assert (clearance > 0).all(), f"step {i}: centre behind the surface ({clearance.min():.4f} m)"
            worst = min(worst, clearance.min())
    assert worst > 0.5 * r  # never sinks by more than half its radius (vertical clearance)
    in_bowl = (np.abs(w.sphere_positions()[:, :2]) < 1.0).all(axis=1)
    assert in_bowl.mean() >= 0.75  # most are still rolling on the waves (not vacuous)


@pytest.mark.parametrize("collider", COLLIDERS)
def test_no_tunnelling_pulsing_blob_fast_spheres(collider):
    """Spheres shot at the breathing blob at 15 m/s (0.06 m per step, twice their radius):
    continuous contact must stop every one of them outside, centre at least r/2 from the surface."""
    seq = scenes.pulsing_blob(subdivisions=2, frames=24)
    c = np.array([0.0, 0.0, 0.6])
    rng = np.random.default_rng(1)
    S, r = 24, 0.03
    d = rng.normal(size=(S, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pos = c + 1.2 * d
    vel = -15.0 * d + rng.normal(0, 0.5, (S, 3))
    w = make_world(seq, pos, r, collider=collider, playback="loop", velocities=vel, restitution=0.2,
                   gravity=(0.0, 0.0, 0.0))
    hits = np.zeros(S, bool)
    steps = 1500 if collider != "rebuild" else 300
    for i in range(steps):  # impacts start at step ~11
        w.step()
        if i < 80 or i % 25 == 0:
            P = w.sphere_positions().astype(np.float64)
            assert np.isfinite(P).all(), f"NaN at step {i}"
            Vt = surface_at(seq, w.time)
            wn = winding_number(Vt, seq.F, P)
            assert (wn < 0.5).all(), f"step {i}: sphere centre inside the blob: {np.flatnonzero(wn >= 0.5)}"
            dist = brute_nearest(P, Vt, seq.F)[0]
            assert dist.min() > 0.5 * r, f"step {i}: a centre is {dist.min():.4f} m from the surface"
            hits |= dist < 1.5 * r
    assert hits.all()  # every sphere did reach the blob (the test is not vacuous)


def test_no_tunnelling_blob_sweeping_through_spheres():
    """The blob translates at 3 m/s through a row of resting spheres (no gravity): the surface
    motion must push them, never pass over them."""
    T, fps, speed = 25, 24.0, 3.0
    base = scenes.pulsing_blob(subdivisions=3, frames=T)
    shift = np.array([speed, 0.0, 0.0]) * (np.arange(T) / fps)[:, None] - [1.5, 0, 0]
    seq = FixedTopologySequence((base.V[:T] + shift[:, None, :]).astype(np.float32), base.F, fps=fps)
    S, r = 9, 0.03
    pos = np.column_stack([np.full(S, 0.2), np.linspace(-0.3, 0.3, S), np.full(S, 0.6)])
    w = make_world(seq, pos, r, playback="clamp", restitution=0.0, friction=0.3, gravity=(0.0, 0.0, 0.0))
    for i in range(int(1.2 / DT)):
        w.step()
        P = w.sphere_positions()
        assert np.isfinite(P).all()
        if i % 3 == 0:
            wn = winding_number(surface_at(seq, w.time, "clamp"), seq.F, P)
            assert (wn < 0.5).all(), f"step {i}: sphere centre inside the moving blob"
    assert (P[:, 0] > 0.5).all()  # they were pushed ahead of the blob


def test_the_sub_step_rule_turned_off_says_spheres_may_tunnel():
    """With auto_substeps off, a surface moving over r/2 a sub-step is said (a new user's sheet
    at 20 m/s passed through a sphere without a word); the number of sub-steps the rule would take
    is named. Slow enough, or with the rule on, nothing of the kind is said."""
    r = 0.05
    fast = moving_sheet((0.0, 0.0, 20.0), 4)  # 20 m/s x dt 1/240: 0.083 m a step, over r/2
    with pytest.warns(UserWarning, match=r"auto_substeps is off .* spheres may tunnel; .* physics.substeps to 4"):
        make_world(fast, [[0.0, 0.0, 0.5]], r, auto_substeps=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_world(moving_sheet((0.0, 0.0, 5.0), 4), [[0.0, 0.0, 0.5]], r, auto_substeps=False)  # 0.021 m: under
        make_world(fast, [[0.0, 0.0, 0.5]], r, auto_substeps=False, substeps=4)
    with pytest.warns(UserWarning, match="raising substeps from 1 to 4"):
        make_world(fast, [[0.0, 0.0, 0.5]], r)


# ---------------------------------------------------------------------------------------------
# colliders agree; rebuild variants; varying topology
# ---------------------------------------------------------------------------------------------


def _bowl_world(collider, interpolate=True, fps=None, rebuild_every="step", steps=0):
    seq = scenes.wave_bowl(n=24, frames=12)
    if fps is not None:
        seq = FixedTopologySequence(seq.V, seq.F, fps=fps)
    rng = np.random.default_rng(3)
    pos = np.column_stack([rng.uniform(-0.5, 0.5, (8, 2)), rng.uniform(0.4, 0.8, 8)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return make_world(seq, pos, 0.06, collider=collider, playback="loop", interpolate=interpolate,
                          rebuild_every=rebuild_every)


@pytest.mark.parametrize("other", [c for c in COLLIDERS if c != "refit"] + ["fixed"])
def test_colliders_give_the_same_trajectories(other):
    ref = "refit" if "refit" in COLLIDERS else "fixed"
    a, b = _bowl_world(ref), _bowl_world(other)
    _, pa, va = run(a, 400)
    _, pb, vb = run(b, 400)
    assert np.isfinite(pa).all()
    np.testing.assert_allclose(pb, pa, atol=1e-4)
    np.testing.assert_allclose(vb, va, atol=1e-2)
    # the spheres did hit the surface during the comparison
    assert (np.diff(np.sign(va[:, :, 2]), axis=0) > 0).any()


def test_rebuild_every_frame_matches_refit():
    """Interpolation off: one BVH per reconstruction frame gives the refit path's trajectories."""
    ref = "refit" if "refit" in COLLIDERS else "fixed"
    a = _bowl_world(ref, interpolate=False)
    b = _bowl_world("rebuild", interpolate=False, rebuild_every="frame")
    built = []
    orig = b.collider.update

    def counting_update(model, state, ctx):
        before = b.collider.mesh
        orig(model, state, ctx)
        built.append(b.collider.mesh is not before)

    b.collider.update = counting_update
    _, pa, _ = run(a, 400)
    _, pb, _ = run(b, 400)
    np.testing.assert_allclose(pb, pa, atol=1e-4)
    # 400 steps of 1/240 s at 24 fps span frames 0..39: frame 0's BVH is built by the
    # constructor, then one new BVH at each of the 39 frame changes, none in between
    assert len(built) == 400 and int(np.sum(built)) == 39


def test_rebuild_every_frame_with_interpolation_is_refused_or_rebuilds_every_step():
    """With interpolation the surface changes every step: either the world refuses
    rebuild_every='frame' with a message saying why, or it rebuilds at every step."""
    try:
        b = _bowl_world("rebuild", interpolate=True, rebuild_every="frame")
    except ValueError as e:
        assert "interpolat" in str(e)
        return
    a = _bowl_world("refit" if "refit" in COLLIDERS else "fixed", interpolate=True)
    _, pa, _ = run(a, 200)
    _, pb, _ = run(b, 200)
    np.testing.assert_allclose(pb, pa, atol=1e-4)


def test_rebuild_every_frame_host_frame_matches_device_frame():
    """The rebuild-per-frame collider decides on the host (World.current_frame_key) when the
    device's vertex buffer changes frame. Both must agree at every step, or for one step the
    BVH is stale (points moved to the next frame, BVH not rebuilt). At 30 fps and dt = 1/240
    the frame boundaries fall exactly on step times, where float rounding decides."""
    T, fps = 12, 30.0
    V0, F = scenes.grid_sheet(4, 2.0)
    V = np.stack([V0 + np.array([0, 0, 0.01 * k], np.float32) for k in range(T)])
    seq = FixedTopologySequence(V, F, fps=fps)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w = make_world(seq, [[5.0, 5.0, 5.0]], 0.1, collider="rebuild", playback="loop", interpolate=False,
                       rebuild_every="frame")
    bad = []
    for i in range(1000):
        w.update_surface()  # the vertex buffer at the current device time (what the next sub-step uses)
        k_dev = int(round(float(w.state.points.numpy()[0, 2] - V0[0, 2]) / 0.01))
        k_host = w.current_frame_key()
        if k_dev != k_host:
            bad.append((i, w.time, k_dev, k_host))
        w.step()
    assert not bad, f"{len(bad)} steps where host frame != device frame, first: {bad[:3]}"


def test_varying_topology_runs_with_rebuild_and_rejects_fixed():
    # 24 frames: the surface moves less than r/2 per frame, so holding each frame (no correspondence,
    # no interpolation) cannot carry a resting sphere's centre through it; pingpong avoids the
    # torus<->sphere jump a loop would make
    seq = scenes.torus_to_sphere(frames=24, resolution=20, fps=24.0)
    pos = [[0.0, 0.0, 1.3], [0.45, 0.0, 1.2], [-0.3, 0.3, 1.4]]
    for collider in ("fixed", "refit", "swept"):
        if collider not in getattr(world_mod, "COLLIDER_CHOICES", ("fixed", "rebuild")):
            continue
        surf = VaryingSurfaceModel(seq, TEST_DEVICE)
        model = Model(surf, SphereModel([0.05] * 3, 1.0, TEST_DEVICE), PhysicsParams(dt=DT))
        with pytest.raises(ValueError, match="rebuild"):
            World(model, State(model, pos), collider=collider)
    for every in ("step", "frame", "segment"):
        surf = VaryingSurfaceModel(seq, TEST_DEVICE, playback="pingpong", interpolate=every != "frame")
        model = Model(surf, SphereModel([0.05] * 3, 1.0, TEST_DEVICE), PhysicsParams(dt=DT, restitution=0.2))
        w = World(model, State(model, pos), collider="rebuild", rebuild_every=every)
        touched = 0
        for i in range(400):  # 1.67 s = 40 frames, pingpong over 24 (topology changes each frame)
            w.step()
            touched += int((w.contacts.face.numpy() >= 0).sum())
            if i % 20 == 0 or i == 399:
                P = w.sphere_positions()
                assert np.isfinite(P).all()
                k = w.frame  # the frame the last sub-step collided against (host and device agree)
                Vk, Fk = seq.frames[k]
                assert (winding_number(Vk, Fk, P) < 0.5).all(), f"step {i}: centre inside frame {k}"
        # spheres landed on the changing surface (and later roll off the rounding shape; the one
        # over the torus hole falls through it before the shape closes)
        assert touched > 100


def test_world_rejects_unknown_collider_and_playback():
    seq = _static_sheet()
    surf = SurfaceModel(seq, TEST_DEVICE)
    model = Model(surf, SphereModel([0.1], 1.0, TEST_DEVICE), PhysicsParams())
    with pytest.raises(ValueError, match="collider"):
        World(model, State(model, [[0, 0, 1]]), collider="bvh")
    with pytest.raises(ValueError, match="playback"):
        SurfaceModel(seq, TEST_DEVICE, playback="bounce")


def test_reset_reproduces_the_trajectory():
    w = _bowl_world("refit" if "refit" in COLLIDERS else "fixed")
    p0 = np.array(w.sphere_positions(), copy=True)
    _, p1, _ = run(w, 150)
    w.reset()
    assert w.time == 0.0
    assert float(w.state.sim_time.numpy()[0]) == 0.0
    np.testing.assert_array_equal(w.sphere_positions(), p0, err_msg="reset() did not restore the initial positions")
    np.testing.assert_array_equal(w.sphere_velocities(), 0.0, err_msg="reset() did not restore the initial velocities")
    _, p2, _ = run(w, 150)
    np.testing.assert_array_equal(p1, p2)


def test_add_spheres_refuses_non_finite_positions_and_velocities():
    """A NaN position or an infinite velocity given to add_spheres (which turned the world NaN)
    is a ValueError naming the new sphere's index; the world is left as it was."""
    seq = moving_sheet((0.0, 0.0, 0.0), frames=8)
    w = make_world(seq, [[0.0, 0.0, 0.3]], radius=0.1)
    before = w.sphere_positions().copy()
    with pytest.raises(ValueError, match=r"sphere 2: position \[nan, 0.0, 1.0\] is not finite"):
        w.add_spheres([[0.1, 0.0, 1.0], [np.nan, 0.0, 1.0]], 0.05)
    with pytest.raises(ValueError, match=r"sphere 1: velocity \[inf, 0.0, 0.0\] is not finite"):
        w.add_spheres([[0.1, 0.0, 1.0]], 0.05, velocities=[[np.inf, 0.0, 0.0]])
    assert w.model.spheres.count == 1
    np.testing.assert_array_equal(w.sphere_positions(), before)


def test_a_refused_add_spheres_leaves_reset_working_and_shapes_are_checked():
    """A new user's findings: add_spheres refused for a bad radius or mass had already extended
    what reset() restores (the next reset failed on arrays of different sizes); positions given
    as (3, S) rows of x, y and z were read as scrambled spheres; an unknown collider name in
    build_world failed with an AttributeError from another error's path; a bad device argument
    was reported as the CLI's --device."""
    from dynmesh_warp import build_world, load_scene_config
    from dynmesh_warp.world import SphereModel, State

    seq = moving_sheet((0.0, 0.0, 0.0), frames=8)
    w = make_world(seq, [[0.0, 0.0, 0.3], [0.5, 0.0, 0.3]], radius=0.1)
    p0 = w.sphere_positions().copy()
    run(w, 5)
    for kw in ({"radius": -0.1}, {"radius": 0.0}, {"radius": float("nan")}, {"radius": 0.1, "mass": -1.0}):
        with pytest.raises(ValueError, match="sphere (radius|mass)"):
            w.add_spheres([[0.0, 0.3, 1.0]], **kw)
    assert w.model.spheres.count == 2
    w.reset()
    np.testing.assert_array_equal(w.sphere_positions(), p0)
    w.add_spheres([[0.0, 0.3, 1.0]], 0.05)  # a good one still goes in; reset removes it (the scene's own spheres)
    assert w.model.spheres.count == 3 and np.allclose(w.sphere_positions()[2], [0.0, 0.3, 1.0])
    w.reset()
    assert w.model.spheres.count == 2
    np.testing.assert_array_equal(w.sphere_positions(), p0)
    with pytest.raises(ValueError, match=r"sphere positions: expected \(2, 3\) \[x, y, z\] rows, one per sphere, "
                                         r"got shape \(3, 2\)"):
        State(w.model, np.array([[0.0, 0.5], [0.0, 0.0], [0.3, 0.3]]))
    with pytest.raises(ValueError, match=r"sphere radius: expected one value per sphere, shape \(S,\), got shape"):
        SphereModel(np.full((2, 3), 0.1), 1.0)
    with pytest.raises(ValueError, match=r"sphere mass: expected one value or one per sphere \(2\)"):
        SphereModel([0.1, 0.1], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match=r"collider must be one of .*got 'refti'"):
        build_world(load_scene_config(), device="cpu", collider="refti", sequence=seq)
    from dynmesh_warp.config import SceneError

    with pytest.raises(SceneError, match="the device argument 'nodevice': not available here"):
        build_world(load_scene_config(), device="nodevice", sequence=seq)  # it named the CLI's --device
    # a scene given as a dict or a YAML path, as RideSurfaceEnv takes it (an AttributeError before)
    from dynmesh_warp.batch import build_batched_world

    scene = {"surface": {"source": "builtin:pulsing_blob", "params": {"subdivisions": 1, "frames": 4}}}
    assert build_world(scene, device="cpu").model.surface.num_vertices == 42
    with pytest.raises(TypeError, match="scene: expected a SceneConfig .* got int"):
        build_world(3, device="cpu")
    with pytest.raises(SceneError, match="num_envs must be a whole number, got 2.7"):
        build_batched_world(scene, device="cpu", num_envs=2.7)  # ran 2 envs
    assert build_batched_world(scene, device="cpu", num_envs=2.0).num_envs == 2
    with pytest.raises(ValueError, match=r"sphere velocities: expected \(2, 3\)"):
        State(w.model, p0, np.zeros((3, 3)))
    # another world's checkpoint (another sphere count): Warp's copy error named neither
    other = make_world(seq, [[0.0, 0.0, 0.3]], radius=0.1)
    with pytest.raises(ValueError, match="checkpoint state: it holds 1 spheres, this world has 2"):
        w.restore_checkpoint_state(other.checkpoint_state())


def test_the_loop_seam_is_named_when_it_sets_the_surface_speed():
    """A sheet moving at 0.5 m/s for 1 s, played with the default loop: the jump back to frame 0
    (0.5 m in a frame, 12 m/s) sets the sub-steps, and the warning says so and what to set (a new
    user's conveyor was reported at 24 m/s with no word of the seam); clamp raises nothing; a
    periodic motion (the seam no faster than the motion) gets no note."""
    from dynmesh_warp.world import seam_note

    seq = moving_sheet((0.5, 0.0, 0.0), frames=25)
    with pytest.warns(UserWarning, match=r"surface moves up to 12 m/s \(the jump from the last frame back to the "
                                         r"first under surface.playback: loop; within the animation 0.5 m/s: .*clamp"):
        make_world(seq, [[0.0, 0.0, 0.3]], radius=0.02, playback="loop")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_world(seq, [[0.0, 0.0, 0.3]], radius=0.02, playback="clamp")
    V = np.concatenate([seq.V[:13], seq.V[12::-1][1:]])  # there and back: the seam is a small step
    back = FixedTopologySequence(V, seq.F, fps=seq.fps)
    assert seam_note(SurfaceModel(back, TEST_DEVICE, playback="loop")) == ""


def test_add_spheres_applies_the_substep_rule():
    """Smaller spheres added while running get the same sub-step rule as spheres given at the
    start (the surface moves < r/2 per sub-step), and stay on the right side of the surface."""
    seq = moving_sheet((0.0, 0.0, 2.0), frames=48)  # rising at 2 m/s
    w = make_world(seq, [[0.0, 0.0, 0.3]], radius=0.1)
    assert w.substeps == 1  # 2 m/s * dt = 8.3 mm < r/2
    with pytest.warns(UserWarning, match="raising substeps from 1 to 9"):
        w.add_spheres([[0.5, 0.5, 0.05]], 0.002)
    assert w.substeps == 9 and w.sub_dt == pytest.approx(DT / 9)
    for _ in range(120):
        w.step()
        z_sheet = 2.0 * w.time
        assert (w.sphere_positions()[:, 2] > z_sheet).all()


# ---------------------------------------------------------------------------------------------
# graph capture (CUDA only: the device matrix runs it where a GPU is present)
# ---------------------------------------------------------------------------------------------

def test_capture_loads_only_the_step_modules(cuda_device):
    """Capturing the step must not load Warp modules the step does not use: with
    force_module_load=True every module imported in the process (all of Newton's) compiled on
    a cold cache, for minutes. The captured step must match the eager one."""
    import warp as wp

    @wp.kernel(module="unique")
    def unrelated(a: wp.array(dtype=float)):
        a[wp.tid()] = 1.0

    seq = moving_sheet((0.0, 0.0, 0.3), frames=12)
    pos = [[0.0, 0.0, 0.25], [0.5, 0.3, 0.4]]
    graph, eager = make_world(seq, pos, device=cuda_device), make_world(seq, pos, device=cuda_device)
    eager.use_graph = False
    assert graph.use_graph
    graph.step()
    assert not graph.graph_captured  # the first step runs eagerly (it loads the step's modules)
    _, p_graph, _ = run(graph, 59)
    _, p_eager, _ = run(eager, 60)
    assert graph.graph_captured
    assert not unrelated.module.execs, "capture loaded a module the step does not use"
    np.testing.assert_allclose(p_graph[-1], p_eager[-1], atol=1e-5)


def test_varying_state_owns_its_buffers_and_shows_the_played_frame():
    """State never aliases Model: the varying surface's current frame is copied into the state's
    own buffers (views of the first N_k entries); writing them leaves the model's frames intact."""
    seq = scenes.torus_to_sphere(frames=6, resolution=14, fps=24.0)
    surf = VaryingSurfaceModel(seq, TEST_DEVICE, playback="pingpong", interpolate=False)
    model = Model(surf, SphereModel([0.05], 1.0, TEST_DEVICE), PhysicsParams(dt=DT))
    w = World(model, State(model, [[0.0, 0.0, 2.0]]), collider="rebuild", rebuild_every="step")
    model_ptrs = {a.ptr for a in surf.segment_frames}
    for t in (0.0, 0.05, 0.13, 0.25, 0.41):  # pingpong over 6 frames: 0 1 3 4 1 (after the turn)
        w.set_time(t)
        k = world_mod.frame_pair_host(t, surf.fps, surf.num_frames, surf.playback)[0]
        V, F = seq.frames[k]
        assert w.state.points.ptr not in model_ptrs
        np.testing.assert_array_equal(w.state.points.numpy(), V)
        np.testing.assert_array_equal(w.current_indices().numpy().reshape(-1, 3), F)
        assert w.state.face_normals.shape[0] == len(F) and w.state.velocities.shape[0] == len(V)
        Vh, Fh = surf.host_mesh_at(t)
        np.testing.assert_array_equal(Vh, V.astype(np.float64))
        np.testing.assert_array_equal(Fh, F)
    w.state.points.fill_(7.0)  # the state's copy, not the model's frame
    s_k = surf.segment_at(k)
    np.testing.assert_array_equal(surf.segment_frames[s_k].numpy()[k - surf.segment_start[s_k]], V)


def test_set_sphere_equals_starting_there():
    """World.set_sphere between steps gives the trajectory of a world that started with the
    sphere there (bit for bit on the CPU), keeps the other spheres, and refuses bad input."""
    seq = moving_sheet([0.0, 0.0, 0.3], frames=12)
    pos = [[0.0, 0.0, 0.6], [0.5, 0.3, 0.8]]
    new_p, new_v = [-0.4, 0.2, 0.9], [0.3, 0.0, -1.0]
    a = make_world(seq, pos, collider="swept")
    a.set_sphere(1, new_p, new_v)
    np.testing.assert_array_equal(a.sphere_positions()[0], np.float32(pos[0]))
    np.testing.assert_array_equal(a.sphere_positions()[1], np.float32(new_p))
    b = make_world(seq, [pos[0], new_p], collider="swept")
    b.state.sphere_vel.assign(np.array([[0, 0, 0], new_v], np.float32))
    for _ in range(120):
        a.step()
        b.step()
    np.testing.assert_array_equal(a.sphere_positions(), b.sphere_positions())
    assert (a.sphere_positions()[:, 2] > seq.V[:, :, 2].min()).all()
    with pytest.raises(IndexError, match="sphere 2"):
        a.set_sphere(2, new_p)
    with pytest.raises(ValueError, match="sphere 0: position .* not finite"):
        a.set_sphere(0, [0.0, np.nan, 1.0])


def test_reset_restores_the_scenes_own_spheres():
    """Spheres added between steps (the viewer's Drop sphere) are gone after reset(); the scene's
    spheres are back at their initial state and the world steps as a fresh one does."""
    seq = moving_sheet((0.0, 0.0, 0.2), frames=8)
    pos = [[0.0, 0.0, 0.3], [0.4, 0.2, 0.5]]
    w, fresh = make_world(seq, pos), make_world(seq, pos)
    run(w, 20)
    w.add_spheres([[0.1, 0.1, 0.8]], 0.05)
    run(w, 20)
    assert w.model.spheres.count == 3
    w.reset()
    assert w.model.spheres.count == 2 and w.contacts.face.shape[0] == 2
    np.testing.assert_array_equal(w.sphere_positions(), fresh.sphere_positions())
    _, pa, _ = run(w, 30)
    _, pb, _ = run(fresh, 30)
    np.testing.assert_allclose(pa, pb, atol=1e-6)


def test_restored_state_resumes_bit_for_bit_with_the_seeded_searches():
    """The seeded searches read each sphere's last contact face before writing it, so a
    checkpoint keeps it: resumed at step 3,665 of the default scene without it, one velocity
    differed by one float32 ulp a step later (CI caught it in the run/--resume test). Every step
    after a restore at several steps equals the uninterrupted run's, bit for bit."""
    from dynmesh_warp import build_world, load_scene_config

    cfg = load_scene_config()
    total = 3700
    ref = build_world(cfg, device="cpu", collider="swept")
    want = []
    for _ in range(total):
        ref.step()
        want.append(ref.sphere_velocities().copy())
    for k in (3665, 1234):
        a = build_world(cfg, device="cpu", collider="swept")
        for _ in range(k):
            a.step()
        b = build_world(cfg, device="cpu", collider="swept")
        b.restore_checkpoint_state(a.checkpoint_state())
        for i in range(k, total):
            b.step()
            np.testing.assert_array_equal(b.sphere_velocities(), want[i], err_msg=f"resumed at {k}, step {i + 1}")


@pytest.mark.parametrize("collider", ["refit", "swept", "rebuild"])
@pytest.mark.parametrize("render_state", [False, True])
def test_the_surface_read_after_a_step_is_at_the_world_time(collider, render_state):
    """A sheet rising at 0.5 m/s, 2 sub-steps a step: the vertex buffer read after a step
    (surface_points(), and state.points directly where render_state keeps it) is the sheet at
    world.time, for every collider. A new user's refit and rebuild worlds returned it one sub-step
    behind (2 mm here), so renders and Gaussians posed from it lagged the spheres."""
    seq = moving_sheet((0.0, 0.0, 0.5), frames=24)
    w = make_world(seq, [[0.0, 0.0, 1.0]], collider=collider, substeps=2)
    w.render_state = render_state
    for _ in range(7):
        w.step()
        z = seq.V[0, 0, 2] + 0.5 * w.time
        np.testing.assert_allclose(w.surface_points().numpy()[:, 2], z, atol=1e-6)
        if render_state:
            np.testing.assert_allclose(w.state.points.numpy()[:, 2], z, atol=1e-6)


def test_a_built_world_refuses_new_physics_parameters_and_a_non_finite_time():
    """A new user set dt, gravity and substeps on a built world: the step kept the old values
    while World.dt reported the new dt. Assignment is refused once a world is built from the
    parameters (a copy for a new model is not frozen); set_time(NaN / inf) is refused (the
    surface became NaN and the spheres fell through it)."""
    w = make_world(moving_sheet((0.0, 0.0, 0.0), frames=4), [[0.0, 0.0, 1.0]], collider="refit")
    p = w.model.params
    for name, value in (("dt", 1.0 / 120.0), ("gravity", (0.0, 0.0, -1.0)), ("substeps", 3), ("restitution", 0.9)):
        with pytest.raises(ValueError, match=rf"physics {name}: the parameters are fixed once a world is built"):
            setattr(p, name, value)
    assert w.dt == DT and p.substeps == 1
    q = p.model_copy(update={"dt": 0.01})
    q.restitution = 0.9
    assert (q.dt, q.restitution, p.dt, p.restitution) == (0.01, 0.9, DT, 0.3)
    for bad in (float("nan"), float("inf"), -float("inf")):
        with pytest.raises(ValueError, match="set_time: the time must be a finite number of seconds"):
            w.set_time(bad)
    assert np.isfinite(w.time)


@pytest.mark.parametrize("collider", COLLIDERS)
def test_a_sphere_entirely_behind_the_surface_has_no_contact(collider):
    """docs/physics.md: a centre behind the surface but within r is pushed out to the front; a
    sphere entirely behind it has no contact. The kernels kept every sphere behind within the
    query's reach (``depth > 0 or side > 0``: depth = r + dist behind), so a sphere 7 cm under a
    sheet falling away at 20 m/s was moved through it to the front and bounced (a new user's
    closed-form check). Free flight (semi-implicit Euler) against the integrator's own formula;
    a centre 2 cm behind (within r) is still pushed out to the front."""
    seq = moving_sheet((0.0, 0.0, 0.0), 3)
    r = 0.05
    w = make_world(seq, [[0.3, 0.2, -0.12], [-0.4, 0.1, -0.06], [0.1, -0.3, -0.02]], radius=r, collider=collider,
                   velocities=[[0.0, 0.0, -20.0], [0.0, 0.0, -3.0], [0.0, 0.0, 0.0]], restitution=0.3)
    _, ps, vs = run(w, 3)
    for i, (z0, vz0) in enumerate(((-0.12, -20.0), (-0.06, -3.0))):
        v = vz0 - G * DT * np.arange(1, 4)
        z = z0 + np.cumsum(v) * DT
        np.testing.assert_allclose(ps[:, i, 2], z, atol=1e-5, err_msg=f"sphere {i} (behind by {-z0 - r:.2f} m)")
        np.testing.assert_allclose(vs[:, i, 2], v, atol=1e-4)
    assert ps[0, 2, 2] > 0.0, "a centre within r behind the surface is pushed out to the front"


# -- a sphere pinched between two surfaces that close on it (docs/physics.md) -------------------


def _box_faces(lo, hi):
    """A closed, outward-facing box (8 vertices, 12 triangles)."""
    V = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], np.float64)
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                  [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int32)
    return V, F


def _plates(gap_at, fps, seconds):
    """A fixed 10 cm slab (top face z = 0) and a second one above it whose bottom face is at
    z = gap_at(t)."""
    bot, F = _box_faces((-0.5, -0.5, -0.1), (0.5, 0.5, 0.0))
    top, _ = _box_faces((-0.5, -0.5, 0.0), (0.5, 0.5, 0.1))
    frames = [np.vstack([bot, top + [0.0, 0.0, gap_at(k / fps)]]) for k in range(int(seconds * fps) + 1)]
    return FixedTopologySequence(np.asarray(frames, np.float32), np.vstack([F, F + 8]), fps=fps)


@pytest.mark.parametrize("collider", COLLIDERS)
def test_a_sphere_pinched_between_closing_plates_stays_between_them(collider):
    """A new user's sphere (r = 5 cm) on a slab, a second slab lowered onto it until the gap is
    3 cm (under r), then to nothing: with one contact per sphere each sub-step pushed the centre
    out of the nearer slab by the whole overlap, into the other, until it went through one (it
    fell out of the bottom slab). A contact facing the other side of the pinch, the two closing,
    is resolved against both: the centre stays between the plates, at the middle once the gap
    is under 2 r (closed form: gap / 2), and where the gap closes completely, at the interface."""
    r = 0.05
    for final in (0.03, 0.0):
        seq = _plates(lambda t: 0.2 + (final - 0.2) * min(t, 1.0), 60, 1.5)
        # (0, 0): on the diagonal edge of each plate's two triangles; (0.058, 0.033): where, the
        # gap closed, the closest face found was the bottom plate's every time (a tie) and the top
        # plate's plane, remembered where it was last seen, aged out: the sphere was pushed up
        # into the top plate (on CUDA at (0.1, 0))
        for x, y in ((0.1, 0.0), (0.0, 0.0), (0.058, 0.033)):
            w = make_world(seq, [[x, y, r + 1e-4]], radius=r, collider=collider)
            t, ps, _ = run(w, int(1.5 / DT))
            gap = 0.2 + (final - 0.2) * np.minimum(t, 1.0)
            z = ps[:, 0, 2]
            assert (z > -1e-3).all() and (z < gap + 1e-3).all(), (collider, final, x, y, z.min())
            assert z[-1] == pytest.approx(final / 2, abs=1e-3), (collider, final, x, y)


@pytest.mark.parametrize("collider", COLLIDERS)
def test_a_closing_jaw_squeezes_a_frictionless_sphere_out_along_its_bisector(collider):
    """A slab hinged at x = -0.5 closing from 30 degrees to 0 in 1 s onto a fixed slab, a
    frictionless sphere (r = 5 cm) between them (a new user's check). Closed form while it touches
    both: it rides the bisector, x = -0.5 + r / tan(theta / 2), vx = r theta' / (2 sin^2(theta / 2)).
    With one contact per sphere it reached x = 0.12 m, 0.66 m/s at 6 degrees with one sub-step and
    then sank through the bottom slab; resolved against both contacts, the closed form within
    2 % (x) and 6 % (vx), the default sub-steps."""
    fps, r, th0 = 240, 0.05, np.radians(30.0)
    bot, F = _box_faces((-0.5, -0.3, -0.1), (0.5, 0.3, 0.0))
    top0, _ = _box_faces((-0.5, -0.3, 0.0), (0.5, 0.3, 0.1))
    frames = []
    for k in range(int(1.2 * fps) + 1):
        th = max(0.0, th0 * (1 - k / fps))
        c, s = np.cos(th), np.sin(th)
        x, z = top0[:, 0] + 0.5, top0[:, 2]
        frames.append(np.vstack([bot, np.stack([-0.5 + c * x - s * z, top0[:, 1], s * x + c * z], 1)]))
    seq = FixedTopologySequence(np.asarray(frames, np.float32), np.vstack([F, F + 8]), fps=fps)
    w = make_world(seq, [[0.0, 0.0, r + 1e-4]], radius=r, collider=collider, friction=0.0, restitution=0.0)
    t, ps, vs = run(w, int(0.8 / DT))
    for when in (0.7, 0.8):  # theta 9 and 6 degrees
        i = int(np.argmin(np.abs(t - when)))
        th = th0 * (1 - t[i])
        x = -0.5 + r / np.tan(th / 2)
        vx = r * th0 / (2 * np.sin(th / 2) ** 2)
        assert ps[i, 0, 0] == pytest.approx(x, rel=0.02), (collider, when)
        assert vs[i, 0, 0] == pytest.approx(vx, rel=0.06), (collider, when)
        assert ps[i, 0, 2] > 0.9 * r  # above the bottom slab, not through it


def _fingers(bottom: float, lift=lambda t: 0.0, fps: float = 120.0, seconds: float = 1.4):
    """A floor slab (top face z = 0) and two finger boxes (30 cm tall, their bottom faces at z =
    ``bottom`` + lift(t)) closing from a 0.3 m gap to 0.09 m in 0.5 s (a gripper)."""
    floor, F = _box_faces((-1, -1, -0.1), (1, 1, 0.0))
    left, _ = _box_faces((-0.1, -0.2, bottom), (0.0, 0.2, bottom + 0.3))
    right, _ = _box_faces((0.0, -0.2, bottom), (0.1, 0.2, bottom + 0.3))
    frames = []
    for k in range(int(seconds * fps) + 1):
        t = k / fps
        g = 0.3 - 0.21 * min(t / 0.5, 1.0)
        frames.append(np.vstack([floor, left + [-g / 2, 0, lift(t)], right + [g / 2, 0, lift(t)]]))
    return FixedTopologySequence(np.asarray(frames, np.float32), np.vstack([F, F + 8, F + 16]), fps=fps)


@pytest.mark.parametrize("collider", COLLIDERS)
def test_a_gripped_sphere_is_not_sent_through_the_floor(collider):
    """A new user's gripper: two fingers close to 9 cm on a sphere (r = 5 cm) resting on a floor.
    With the fingers' bottom edges at the centre's height, an edge's contact normal (1, 0, -0.01)
    against the other finger's face solved the two constraints exactly, with multipliers ~100: the
    centre moved ~1 m down, through the floor, in one sub-step (z = -16 m after 1 s). Then the
    fingers grasp and lift away: the sphere was sent 0.94 m down as their edges passed its centre.
    The exact two-plane solve now takes at most r a sub-step. The sphere never goes through the
    floor (its centre stays above z = -r / 2) and ends on it, at the middle. Left (docs/physics.md):
    while pinched it can dip into the floor for a few sub-steps, up to a radius on CUDA (the floor
    is a third surface; the pinch takes two)."""
    r = 0.05
    for mu in (0.0, 0.5):
        w = make_world(_fingers(0.05), [[0.013, 0.0, r + 1e-4]], radius=r, collider=collider, friction=mu,
                       restitution=0.0)
        _, ps, _ = run(w, int(1.0 / DT))
        assert ps[:, 0, 2].min() > -0.5 * r and ps[-1, 0, 2] == pytest.approx(r, abs=0.01), (mu, ps[:, 0, 2].min())
        assert abs(ps[-1, 0, 0]) < 0.01
    lift = _fingers(0.0, lift=lambda t: 0.005 + 0.5 * max(t - 0.7, 0.0))
    w = make_world(lift, [[0.013, 0.0, r + 1e-4]], radius=r, collider=collider, friction=1.0, restitution=0.0)
    t, ps, _ = run(w, int(1.3 / DT))
    assert ps[:, 0, 2].min() > -0.5 * r
    np.testing.assert_allclose(ps[t > 1.0, 0, 2], r, atol=1e-3)  # left on the floor as the fingers rise


@pytest.mark.parametrize("collider", COLLIDERS)
def test_plates_closing_fast_to_nothing_leave_the_sphere_at_the_interface(collider):
    """Plates closing to no gap at 1 m/s (0.2 m in 0.2 s, 60 fps): the pinch's velocity carried the
    centre up to v dt / 2 past the remembered plane, the pinch was no longer seen (the centre
    "behind" it) and the one-contact response pushed the sphere 5 cm up, into the top plate (a new
    user's: 4 of 30 starts on swept, 7 on rebuild). After a pinch the centre may lie up to r / 2
    behind the other side. Every start ends at the interface, none over 1 cm into a plate."""
    r = 0.05
    seq = _plates(lambda t: 0.2 * (1 - min(t / 0.2, 1.0)), 60, 0.6)
    xy = np.random.default_rng(1).uniform(-0.4, 0.4, (8, 2))
    for x, y in xy:
        w = make_world(seq, [[x, y, r + 1e-4]], radius=r, collider=collider)
        _, ps, _ = run(w, int(0.6 / DT))
        z = ps[:, 0, 2]
        assert abs(z[-1]) < 1e-3 and z.min() > -0.01, (x, y, z[-1], z.min())


def _closing_plates():
    """Plates closing to a 6 cm gap (< 2 r for r = 5 cm) in 1 s, held there."""
    return _plates(lambda t: 0.2 - 0.14 * min(t, 1.0), 60, 2.0)


@pytest.mark.parametrize("collider", COLLIDERS)
def test_a_reset_or_a_placed_sphere_forgets_the_pinch(collider):
    """The pinch memory (``Contacts.memory``) is per-step state: a world reset while its sphere is
    pinched runs on exactly as a new world (the remembered closing plate would otherwise squeeze
    the first sub-step after the reset: a phantom plate 1 cm over a sphere resting on the floor),
    and a sphere placed anew (``set_sphere``) remembers no contact; a sphere added keeps the
    others' memory."""
    r, start = 0.05, [[0.1, 0.0, 0.05 + 1e-4]]
    fresh = make_world(_closing_plates(), start, radius=r, collider=collider)
    _, p_fresh, v_fresh = run(fresh, 60)
    w = make_world(_closing_plates(), start, radius=r, collider=collider)
    run(w, int(0.9 / DT))
    assert np.abs(w.contacts.memory.numpy()[0, 6:9]).max() > 0.5  # pinched: the other side kept
    w.reset()
    _, p, v = run(w, 60)
    np.testing.assert_array_equal(p, p_fresh)
    np.testing.assert_array_equal(v, v_fresh)
    run(w, int(0.9 / DT))
    before = w.contacts.memory.numpy().copy()
    w.add_spheres([[0.3, 0.3, 0.05 + 1e-4]], r)
    np.testing.assert_array_equal(w.contacts.memory.numpy()[0], before[0])
    w.set_sphere(0, [0.1, 0.0, 0.05 + 1e-4])
    assert not w.contacts.memory.numpy()[0].any()


def test_a_batched_reset_forgets_the_pinch_of_the_envs_it_resets(device):
    """The batched world's reset (``BatchedWorld.reset``) clears the pinch memory of the envs it
    resets only: env 0 reset while pinched runs on as a new batch's env 0, bit for bit, and env
    1, pinched and not reset, keeps its memory."""
    from dynmesh_warp.batch import BatchedWorld, BatchModel, BatchState

    r = 0.05
    pos = np.array([[0.1, 0.0, r + 1e-4]], np.float32)

    def batch():
        surf = SurfaceModel(_closing_plates(), device, playback="clamp")
        bm = BatchModel(surf, 2, np.full(1, r, np.float32), 1.0, PhysicsParams(dt=DT))
        return BatchedWorld(bm, BatchState(bm, pos, np.zeros_like(pos), times=np.zeros(2)))

    fresh = batch()
    ref = []
    for _ in range(60):
        fresh.step()
        ref.append(fresh.state.sphere_pos.numpy()[0].copy())
    bw = batch()
    for _ in range(int(0.9 / DT)):
        bw.step()
    kept = bw.contacts.memory.numpy()[1].copy()
    assert np.abs(kept[6:9]).max() > 0.5
    bw.reset(np.array([True, False]), positions=np.stack([pos, pos]), velocities=np.zeros((2, 1, 3), np.float32),
             times=np.zeros(2))
    assert not bw.contacts.memory.numpy()[0].any()
    np.testing.assert_array_equal(bw.contacts.memory.numpy()[1], kept)
    got = []
    for _ in range(60):
        bw.step()
        got.append(bw.state.sphere_pos.numpy()[0].copy())
    np.testing.assert_array_equal(np.array(got), np.array(ref))


@pytest.mark.parametrize("collider", COLLIDERS)
def test_a_plate_that_lifts_away_releases_the_pinched_sphere(collider):
    """A plate closes on a sphere resting on a floor to a gap of 8 cm (< 2 r), holds 0.2 s, then
    rises away at 0.5 m/s. Closed form: the centre at gap / 2 = 4 cm while held, then back at
    z = r on the floor. One contact per sphere sent it through the plate (it rode on top of the
    plate, z = 0.23 m at 0.6 s); the fix that was taken back kept the plate's plane after the
    plate had gone and held the sphere 1 cm inside the floor for 5 s. The other side of a pinch
    is forgotten unless it is seen again."""
    r = 0.05
    seq = _plates(lambda t: 0.2 - 0.12 * min(t / 0.5, 1.0) + 0.5 * max(t - 0.7, 0.0), 60, 2.0)
    w = make_world(seq, [[0.1, 0.0, r + 1e-4]], radius=r, collider=collider, friction=0.5)
    t, ps, vs = run(w, int(1.5 / DT))
    z = ps[:, 0, 2]
    held = (t > 0.55) & (t < 0.7)
    np.testing.assert_allclose(z[held], 0.04, atol=1e-3)
    after = t > 0.95  # the plate 12.5 cm up
    np.testing.assert_allclose(z[after], r, atol=1e-4)
    assert np.abs(vs[after, 0]).max() < 1e-3


def _tilted_groove(r: float, beta: float, th: float = 40.0):
    """A V-groove of opening ``th`` degrees along y (walls 0.5 m, 4 m long, normals into the V)
    tilted ``beta`` about x: (V, F, R the tilt, p0 a sphere of radius r resting in it at y = 1)."""
    a = np.radians(th) / 2
    ys = np.linspace(-2.0, 2.0, 17)
    V = np.array([q for y in ys for q in ([-0.5 * np.sin(a), y, 0.5 * np.cos(a)], [0.0, y, 0.0],
                                          [0.5 * np.sin(a), y, 0.5 * np.cos(a)])])
    F = []
    for j in range(16):
        for k in range(2):
            q = [3 * j + k, 3 * j + k + 1, 3 * (j + 1) + k + 1, 3 * (j + 1) + k]
            F += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    F = np.array(F, np.int32)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    F[n[:, 2] < 0] = F[n[:, 2] < 0][:, ::-1]  # normals into the V
    R = np.array([[1, 0, 0], [0, np.cos(beta), -np.sin(beta)], [0, np.sin(beta), np.cos(beta)]])
    return V @ R.T, F, R, R @ np.array([0.0, 1.0, r / np.sin(a) + 1e-4])


@pytest.mark.parametrize("collider", COLLIDERS)
def test_a_turning_groove_is_no_pinch(collider):
    """The tilted groove turning rigidly (0.5 rad/s about the vertical through the sphere's start,
    60 fps): its walls do not close on each other, so no sub-step is a pinch (``Contacts.memory``'s
    countdown stays 0). The interpolated vertices of a rotation close a little (chords, not arcs):
    counted as a pinch, the trajectory left the one-contact response's from step 5 (a new user's)."""
    r, beta = 0.05, np.radians(30.0)
    V, F, _, p0 = _tilted_groove(r, beta)
    c = np.array([0.0, 0.866, 0.5])
    frames = []
    for k in range(62):
        g = 0.5 * k / 60
        Rz = np.array([[np.cos(g), -np.sin(g), 0], [np.sin(g), np.cos(g), 0], [0, 0, 1]])
        frames.append((V - c) @ Rz.T + c)
    seq = FixedTopologySequence(np.asarray(frames, np.float32), F, fps=60.0)
    for mu in (0.0, 0.5):
        w = make_world(seq, [p0], radius=r, collider=collider, friction=mu, restitution=0.0)
        for _ in range(240):
            w.step()
            assert w.contacts.memory.numpy()[0, 15] == 0.0, (mu, w.time)


@pytest.mark.parametrize("collider", COLLIDERS)
def test_a_static_v_groove_keeps_its_friction(collider):
    """A static V-groove (40 degrees, walls' normals facing each other) tilted 30 degrees, a
    sphere (r = 5 cm) resting in it: its walls do not close on each other, so it is no pinch and
    the one-contact response (friction, resting) is as it was. mu = 0.5 holds it (closed form: no
    sliding, mu cos(30) / sin(20) > sin(30); the response creeps a few cm); mu = 0 slides at
    g sin(30). The fix that was taken back counted it as a pinch: friction vanished and the
    sphere slid 2.46 m in 1 s."""
    r, beta = 0.05, np.radians(30.0)
    V, F, R, p0 = _tilted_groove(r, beta)
    seq = FixedTopologySequence(np.stack([V, V]).astype(np.float32), F, fps=24.0)
    down = -(R @ [0.0, 1.0, 0.0])
    for mu, lo, hi in ((0.5, 0.0, 0.1), (0.0, 0.98 * 0.5 * G * np.sin(beta), 1.02 * 0.5 * G * np.sin(beta))):
        w = make_world(seq, [p0], radius=r, collider=collider, friction=mu, restitution=0.0)
        _, ps, _ = run(w, int(1.0 / DT))
        s = (ps[-1, 0] - p0) @ down
        assert lo <= s <= hi, (collider, mu, s)
        height = (ps[:, 0] @ (R @ [0.0, 0.0, 1.0]))
        assert height.min() > 0.98 * r / np.sin(np.radians(20.0)), (collider, mu)  # in the groove, not through a wall
