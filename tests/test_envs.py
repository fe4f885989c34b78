"""The Gymnasium vector env on the batched world (issue 15; dynmesh_warp/envs.py): spaces,
seeding, same-step autoreset, termination, and that the observation's height probes equal the
NumPy oracle of the surface at each env's time."""

from __future__ import annotations

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from dynmesh_warp.envs import FLOOR_DROP, RideSurfaceEnv  # noqa: E402
from reference import surface_at  # noqa: E402


def _env_cfg(device):
    from dynmesh_warp.config import load_scene_config

    return load_scene_config(data={"device": device, "surface": {"source": "builtin:pulsing_blob",
                                                                  "params": {"subdivisions": 2, "frames": 12}}})


def _env(device, **kw):
    return RideSurfaceEnv(scene=_env_cfg(device), **kw)


def test_spaces_reset_and_step_follow_the_vector_api(device):
    env = _env(device, num_envs=6, seed=1)
    assert isinstance(env, gym.vector.VectorEnv) and env.num_envs == 6
    assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    obs, info = env.reset(seed=11)
    assert obs.shape == (6, 18) and obs.dtype == np.float32 and env.observation_space.contains(obs)
    a = env.action_space.sample()
    assert a.shape == (6, 2)
    obs2, r, term, trunc, info = env.step(a)
    assert obs2.shape == (6, 18) and r.shape == (6,) and r.dtype == np.float32
    assert term.dtype == bool and trunc.dtype == bool and info["final_obs"].shape == (6, 18)
    # bounded where the value is (contact flag, phase sin and cos), and every observation within them
    sp = env.single_observation_space
    np.testing.assert_array_equal(sp.low[15:], [0.0, -1.0, -1.0])
    np.testing.assert_array_equal(sp.high[15:], [1.0, 1.0, 1.0])
    assert np.isinf(sp.low[:15]).all() and np.isinf(sp.high[:15]).all()
    for _ in range(30):
        o = env.step(env.action_space.sample())[0]
        assert env.observation_space.contains(o), o[:, 15:]
    # deterministic seeding: the same seed and actions give the same rollout
    again = _env(device, num_envs=6)
    o, _ = again.reset(seed=11)
    np.testing.assert_array_equal(o, obs)
    np.testing.assert_array_equal(again.step(a)[0], obs2)
    o3, _ = again.reset(seed=12)
    assert not np.allclose(o3, obs)


def test_reset_mask_resets_only_the_masked_envs(device):
    """Gymnasium's ``reset(options={"reset_mask": m})``: the masked envs start new episodes (the
    same first observation as a full reset with that seed gives them), the others go on
    unchanged; it was ignored and every env reset. A bad mask or an unknown option is refused."""
    env = _env(device, num_envs=4)
    first, _ = env.reset(seed=5)
    a = np.full((4, 2), 0.5, np.float32)
    for _ in range(3):
        moved, *_ = env.step(a)
    m = np.array([True, False, True, False])
    obs, _ = env.reset(seed=5, options={"reset_mask": m})
    np.testing.assert_array_equal(obs[m], first[m])
    np.testing.assert_array_equal(obs[~m], moved[~m])
    # a reset env's pinch memory is cleared, as BatchedWorld.reset clears it (a new user found 16
    # floats of the last episode's carried into the next); the other envs' is left as it was
    memory = env.world.contacts.memory
    memory.fill_(1.0)
    env.reset(options={"reset_mask": m})
    np.testing.assert_array_equal(memory.numpy()[m], 0.0)
    np.testing.assert_array_equal(memory.numpy()[~m], 1.0)
    for bad in (np.ones(3, bool), np.ones(4, np.int32)):
        with pytest.raises(ValueError, match=r"reset_mask: expected \(4,\) booleans"):
            env.reset(options={"reset_mask": bad})
    with pytest.raises(ValueError, match=r"reset options: unknown \['reset_msk'\]"):
        env.reset(options={"reset_msk": m})


def test_a_seeded_masked_reset_leaves_the_other_envs_streams_alone(device):
    """A seeded reset seeds the envs it starts only (Gymnasium's vector API): the others keep their
    seed and episode count, so their later episodes are those they would have played without it.
    Every env's episode count was zeroed and the batch re-seeded: a new user's env 1 replayed its
    first episode. The vector env's own ``np_random`` takes the seed, as Gymnasium's does."""
    twins = [_env(device, num_envs=2, seed=0, max_steps=6) for _ in range(2)]
    a = np.full((2, 2), 0.3, np.float32)
    for env in twins:
        env.reset(seed=0)
        for _ in range(13):  # env 1 in its third episode
            env.step(a)
    twins[0].reset(seed=1, options={"reset_mask": np.array([True, False])})
    np.testing.assert_array_equal(twins[0].env_episode.numpy(), [1, 3])
    for _ in range(20):  # through three more of env 1's resets
        o0, *_ = twins[0].step(a)
        o1, *_ = twins[1].step(a)
        np.testing.assert_array_equal(o0[1], o1[1])
    draws = []
    for env in twins:
        env.reset(seed=123)
        assert env.np_random_seed == 123
        draws.append(env.np_random.random())
    assert draws[0] == draws[1]


def test_actions_are_taken_as_applied_and_checked(device):
    """The reward's action penalty uses the action as the physics applies it (clipped to the
    action space): an action of 1000 gives the rollout and the reward of 1.0. NaN or infinite
    actions and any shape but (E, 2) (a (2, E) array was reshaped, scrambling the envs) are
    refused, naming the envs or the shape."""
    E = 4
    ones, big = np.ones((E, 2), np.float32), np.full((E, 2), 1000.0, np.float32)
    out = []
    for a in (ones, big):
        env = _env(device, num_envs=E)
        env.reset(seed=3)
        out.append(env.step(a))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    bad = ones.copy()
    bad[2, 1] = np.nan
    bad[3, 0] = np.inf
    with pytest.raises(ValueError, match=r"actions of env\(s\) \[2, 3\] are NaN or infinite"):
        env.step(bad)
    with pytest.raises(ValueError, match=r"actions must have shape \(4, 2\) .* got \(2, 4\)"):
        env.step(np.zeros((2, E), np.float32))
    with pytest.raises(ValueError, match="actions must be real numbers, got complex complex128"):
        env.step(np.full((E, 2), 0.5 + 3j))  # its imaginary part was dropped with NumPy's warning only
    # a finite float64 action beyond float32 (1e40) is clipped like 1000, not refused as infinite
    huge = _env(device, num_envs=E)
    huge.reset(seed=3)
    np.testing.assert_array_equal(huge.step(np.full((E, 2), 1e40))[0], out[0][0])


def test_env_arguments_seeds_and_close_are_checked(device):
    """decimation 0 (no physics ran) and a bad radius are refused at construction; a list of
    seeds (one seed drives the batch) is a ValueError, not int()'s TypeError; after close(),
    reset and step refuse, and so does a step before the first reset."""
    with pytest.raises(ValueError, match="decimation must be an integer >= 1, got 0"):
        _env(device, num_envs=2, decimation=0)
    with pytest.raises(ValueError, match="radius must be a finite positive number"):
        _env(device, num_envs=2, radius=float("nan"))
    # the task is laid out along z: a y-up scene (gravity along -y) pushed its ball into the floor
    y_up = _env_cfg(device).model_copy(deep=True)
    y_up.physics.gravity = (0.0, -9.81, 0.0)
    with pytest.raises(ValueError, match=r"need gravity along -z .* physics.gravity is \[0.0, -9.81, 0.0\]"):
        RideSurfaceEnv(scene=y_up, num_envs=2)
    # a new user's: NaN / inf / 0 / negative max_distance gave NaN rewards, -inf rewards or
    # episodes that never end; a bad target failed later without its name
    for bad in (float("nan"), float("inf"), 0.0, -1.0):
        with pytest.raises(ValueError, match="max_distance must be a finite positive number"):
            _env(device, num_envs=2, max_distance=bad)
    for bad in ([0.0, 1.0], [0.0, 0.0, float("nan")], 1.0):
        with pytest.raises(ValueError, match=r"target must be a finite point \[x, y, z\]"):
            _env(device, num_envs=2, target=bad)
    env = _env(device, num_envs=3)
    with pytest.raises(RuntimeError, match=r"call reset\(\) before the first step\(\)"):
        env.step(np.zeros((3, 2), np.float32))  # a new user's: it stepped envs never placed
    with pytest.raises(ValueError, match=r"seed: one integer for the batch .* got \[1, 2, 3\]"):
        env.reset(seed=[1, 2, 3])
    env.reset(seed=np.int64(4))
    # a seed's every bit counts (2**32 + 5 took 5's episodes, 2**40 took 0's: a new user's)
    obs = {s: env.reset(seed=s)[0].copy() for s in (5, 2**32 + 5, 0, 2**40, -1)}
    assert not np.array_equal(obs[5], obs[2**32 + 5]) and not np.array_equal(obs[0], obs[2**40])
    assert np.array_equal(env.reset(seed=2**40)[0], obs[2**40])
    assert not env.closed
    env.close()
    assert env.closed  # Gymnasium's VectorEnv.closed
    with pytest.raises(RuntimeError, match="closed"):
        env.step(np.zeros((3, 2), np.float32))
    with pytest.raises(RuntimeError, match="closed"):
        env.reset()


def test_unseeded_envs_draw_their_own_episodes_and_gym_make_takes_gymnasiums_episode_length(device):
    """No seed: fresh entropy, as Gymnasium's reset() without one (every env made without a seed
    played seed 0's episodes, so a new user's unseeded workers collected the same data); a seed
    still reproduces. gym.make's episode length is Gymnasium's ``max_episode_steps`` (its
    TimeLimit; the env's own limit is off): the env's own 500 cut ``max_episode_steps=700`` at 500."""
    from dynmesh_warp.envs import ENV_ID, MAX_STEPS, NO_STEP_LIMIT

    a, b = _env(device, num_envs=2), _env(device, num_envs=2)
    assert not np.array_equal(a.reset()[0], b.reset()[0])
    np.testing.assert_array_equal(a.reset(seed=3)[0], b.reset(seed=3)[0])
    c, d = _env(device, num_envs=2, seed=7), _env(device, num_envs=2, seed=7)
    np.testing.assert_array_equal(c.reset()[0], d.reset()[0])
    with pytest.raises(ValueError, match="seed: one integer for the batch, or None"):
        _env(device, num_envs=2, seed=1.5)
    env = gym.make(ENV_ID, scene=_env_cfg(device))
    assert env.spec.max_episode_steps == MAX_STEPS and env.unwrapped.vector_env.max_steps == NO_STEP_LIMIT
    env = gym.make(ENV_ID, scene=_env_cfg(device), max_episode_steps=MAX_STEPS + 200)
    assert env.spec.max_episode_steps == MAX_STEPS + 200 and env.unwrapped.vector_env.max_steps == NO_STEP_LIMIT
    env.reset(seed=0)
    state = env.unwrapped.vector_env.world.state
    start = state.sphere_pos.numpy() + [0.0, 0.0, 1.0]  # clear of the breathing blob's top
    trunc, k = False, 0
    while not trunc:  # a ball held in place runs to the wrapper's limit, past the env's old 500
        state.sphere_pos.assign(start)
        state.sphere_vel.zero_()
        _, _, term, trunc, _ = env.step(np.zeros(2, np.float32))
        k += 1
        if term:
            break
    assert not term and k == MAX_STEPS + 200
    vec = gym.make_vec(ENV_ID, num_envs=2, scene=_env_cfg(device))
    assert vec.max_steps == MAX_STEPS
    with pytest.raises(ValueError, match="max_steps .* and max_episode_steps .* are one setting"):
        _env(device, num_envs=2, max_steps=7, max_episode_steps=9)


def test_a_reset_episode_starts_out_of_contact(device):
    """An episode's first observation does not carry the last step's contact (obs 15): a reset
    with the same seed gives the same first observation after a rollout as before it."""
    env = _env(device, num_envs=4)
    o1, _ = env.reset(seed=3)
    a = np.zeros((4, 2), np.float32)
    contact = False
    for _ in range(40):
        contact |= bool(env.step(a)[0][:, 15].any())
    assert contact  # the balls touched the surface meanwhile
    o2, _ = env.reset(seed=3)
    np.testing.assert_array_equal(o1, o2)
    assert not o2[:, 15].any()


def test_render_images_one_per_env_at_its_own_phase(device):
    """Camera observations when asked: (E, H, W, 3) images in [0, 1], the surface drawn, each
    env's picture its own (own phase); equal to render_envs on the env's batch (tested against
    rendering each env alone in tests/test_render.py)."""
    from dynmesh_warp.render import render_envs

    env = _env(device, num_envs=4, seed=2)
    env.reset(seed=5)
    env.step(env.action_space.sample())
    img = env.render_images(width=32, height=24, gaussians=800)
    assert img.shape == (4, 24, 32, 3) and np.isfinite(img).all() and img.min() >= 0.0 and img.max() <= 1.0
    assert (np.abs(img - 1.0).max(axis=-1) > 0.05).mean() > 0.02  # not just the white background
    assert np.abs(img[0] - img[1]).max() > 0.05
    _, g, r, cam = env._camera_state
    np.testing.assert_array_equal(render_envs(env.world, g, cam, renderer=r).rgb.numpy(), img)


def test_same_step_autoreset_and_termination(device):
    env = _env(device, num_envs=4, max_steps=3, seed=2)
    env.reset(seed=2)
    zero = np.zeros((4, 2), np.float32)
    for _ in range(2):
        _, _, term, trunc, _ = env.step(zero)
        assert not trunc.any()
    obs, r, term, trunc, info = env.step(zero)
    assert (trunc | term).all()  # every episode ended at max_steps (or earlier by falling)
    assert info["_final_obs"].all()
    # Gymnasium's same-step keys as its SyncVectorEnv gives them (final_info was missing: a new user's)
    assert info["final_info"] == {} and info["_final_info"].dtype == bool and info["_final_info"].all()
    assert not np.allclose(info["final_obs"], obs)  # obs is the new episode's first, final_obs the last
    np.testing.assert_array_equal(env.env_steps.numpy(), 0)
    # pushing hard in one direction carries the ball off its reach: terminated, reward -1 included
    env = _env(device, num_envs=3, max_steps=10_000, seed=3)
    env.reset(seed=3)
    ended = np.zeros(3, bool)
    for _ in range(400):
        _, r, term, trunc, _ = env.step(np.tile([1.0, 0.0], (3, 1)).astype(np.float32))
        assert not trunc.any()
        assert (r[term] < 0).all()
        ended |= term
    assert ended.all()


def test_height_probes_equal_the_surface_at_each_envs_time(device):
    """Observation entries 6..14: the surface height below a 3 x 3 grid around the ball, relative
    to the ball, at the env's own time; checked against a brute-force ray cast of the NumPy
    surface (reference.surface_at) at that time."""
    env = _env(device, num_envs=5, seed=4)
    obs, _ = env.reset(seed=4)
    for _ in range(3):
        obs, *_ = env.step(np.zeros((5, 2), np.float32))
    seq = env.world.model.surface.sequence
    times = env.world.env_times()
    P = env.world.sphere_positions()[:, 0]
    spacing = 0.5 * env.max_distance / 3.0
    for e in range(5):
        V = surface_at(seq, float(times[e]), "loop")
        tri = V[seq.F]
        j = 6
        for iy in range(3):
            for ix in range(3):
                x, y = P[e, 0] + (ix - 1) * spacing, P[e, 1] + (iy - 1) * spacing
                h = _ray_down(tri, x, y)
                want = (h if h is not None else env.floor) - P[e, 2]
                assert obs[e, j] == pytest.approx(want, abs=2e-5), (e, ix, iy)
                j += 1


def _ray_down(tri, x, y):
    """Highest z of the triangles over (x, y) (2-D barycentric test), None if none."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    d = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    ok = np.abs(d) > 1e-14
    d = np.where(ok, d, 1.0)
    l1 = ((b[:, 1] - c[:, 1]) * (x - c[:, 0]) + (c[:, 0] - b[:, 0]) * (y - c[:, 1])) / d
    l2 = ((c[:, 1] - a[:, 1]) * (x - c[:, 0]) + (a[:, 0] - c[:, 0]) * (y - c[:, 1])) / d
    l3 = 1 - l1 - l2
    inside = ok & (l1 >= 0) & (l2 >= 0) & (l3 >= 0)
    if not inside.any():
        return None
    z = l1 * a[:, 2] + l2 * b[:, 2] + l3 * c[:, 2]
    return float(z[inside].max())


def test_torch_backend_shares_device_memory(device):
    torch = pytest.importorskip("torch")
    env = _env(device, num_envs=3, backend="torch")
    obs, _ = env.reset(seed=0)
    assert isinstance(obs, torch.Tensor) and obs.shape == (3, 18)
    obs2, r, term, trunc, info = env.step(torch.zeros((3, 2), device=obs.device))
    assert obs2.data_ptr() == env.obs.ptr  # the Warp array itself, no copy
    assert r.shape == (3,) and term.dtype == torch.bool


def _blob_env(device, playback="loop", **kw):
    from dynmesh_warp.config import load_scene_config

    cfg = load_scene_config(data={"device": device, "surface": {
        "source": "builtin:pulsing_blob", "playback": playback, "params": {"subdivisions": 2, "frames": 12}}})
    return RideSurfaceEnv(scene=cfg, **kw)


def test_a_ball_resting_on_a_flat_sheet_with_no_ground_has_not_fallen(device, tmp_path):
    """With no ground the floor lies under the surface: on a static flat sheet (the sequence's
    lowest point everywhere) a ball spawned on it rests there without terminating (at the lowest
    point itself every env terminated at every step, a new user found). A ball that leaves the
    surface still falls past the floor: the blob test below."""
    from dynmesh_warp import scenes
    from dynmesh_warp.config import load_scene_config
    from dynmesh_warp.io import save_sequence
    from dynmesh_warp.sequence import FixedTopologySequence

    V0, F = scenes.grid_sheet(5, 1.0)
    save_sequence(FixedTopologySequence(np.stack([V0] * 4).astype(np.float32), F, fps=24.0), tmp_path / "sheet.npz")
    cfg = load_scene_config(data={"device": device, "surface": {"source": str(tmp_path / "sheet.npz")}})
    env = RideSurfaceEnv(num_envs=4, scene=cfg, push=0.0, target=[0.0, 0.0, 0.0], max_distance=1.0)
    assert env.world.model.params.ground_height is None and env.floor < float(V0[:, 2].min())
    env.reset(seed=0)
    for _ in range(30):
        _, _, term, _, _ = env.step(np.zeros((4, 2), np.float32))
        assert not term.any()
    assert (env.world.sphere_positions().reshape(-1, 3)[:, 2] > float(V0[:, 2].max())).all()  # on the sheet, not through it


def test_missed_probes_read_the_floor_and_a_ball_below_it_has_fallen(device):
    """With no ground (the built-in blob) a height probe that meets no surface below reads the
    floor, FLOOR_DROP ball radii under the sequence's lowest point (it read -1e6, a new user's
    silent outlier in 216 of 57,600 heights),
    and a ball that drops below it has fallen (terminated, -1). The target is put beside the blob,
    so the balls spawn with no surface under them."""
    probe = _blob_env(device, num_envs=3)
    seq = probe.world.model.surface.sequence
    V = seq.V.reshape(-1, 3)
    assert probe.world.model.params.ground_height is None
    assert probe.floor == pytest.approx(float(V[:, 2].min()) - FLOOR_DROP * probe.radius)
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    target = [float(V[:, 0].max()) + 2.0 * diag, 0.0, probe.floor + 0.2]
    env = _blob_env(device, num_envs=3, seed=7, target=target)
    obs, _ = env.reset(seed=7)
    z = obs[:, 2] + target[2]  # the balls' heights (obs 0..2: position relative to the target)
    np.testing.assert_allclose(obs[:, 6:15] - (env.floor - z)[:, None], 0.0, atol=1e-5)
    fell = np.zeros(3, bool)
    for _ in range(60):
        _, r, term, trunc, info = env.step(np.zeros((3, 2), np.float32))
        last = info["final_obs"]
        done = term | trunc
        np.testing.assert_allclose(last[done, 6:15] - (env.floor - (last[done, 2] + target[2]))[:, None], 0.0,
                                   atol=1e-5)
        assert (r[term] < 0).all()
        fell |= term
    assert fell.all()  # every ball dropped past the floor


@pytest.mark.parametrize("mode", ["loop", "pingpong", "clamp"])
def test_the_phase_follows_the_playback(device, mode):
    """The phase's sin/cos (obs 16, 17) follow the surface's own cycle, in closed form from each
    env's time: loop every T frames, pingpong every 2 (T - 1) frames, clamp pi x the fraction
    played, held at pi (pingpong and clamp had cycled every T frames); episodes start anywhere in
    that cycle (a pingpong env goes back as often as forth)."""
    env = _blob_env(device, playback=mode, num_envs=8, seed=3)
    seq = env.world.model.surface.sequence
    T, fps = seq.num_frames, float(seq.fps)
    cycle, half = {"loop": (T, False), "pingpong": (2 * (T - 1), False), "clamp": (T - 1, True)}[mode]

    def check(obs):
        u = env.world.env_times() * fps / cycle
        want = np.pi * np.clip(u, 0, 1) if half else 2 * np.pi * (u % 1.0)
        np.testing.assert_allclose(obs[:, 16:18], np.stack([np.sin(want), np.cos(want)], 1), atol=2e-5)
        return u

    seen = [check(env.reset(seed=3)[0])]
    assert (seen[0] <= 1.0).all()
    for _ in range(40):  # 40 x decimation x dt: past the end of a clamp's one playback
        seen.append(check(env.step(np.zeros((8, 2), np.float32))[0]))
    starts = [check(env.reset(seed=s)[0]) for s in range(6)]
    if mode == "pingpong":
        assert np.concatenate(starts).max() > T / cycle  # in the way back
    if mode == "clamp":
        assert np.concatenate(seen).max() > 1.0  # held at the last frame meanwhile


def test_single_env_is_the_batch_of_one_through_gymnasium_make(device):
    """``gym.make(ENV_ID)``: a ``gymnasium.Env`` that passes Gymnasium's own checker and gives,
    step for step, what a :class:`RideSurfaceEnv` of one env gives with the same seed and
    actions (the oracle); the episode's last step returns its last observation (the batch's
    ``final_obs``), and a step after it is refused until ``reset``. ``gym.make_vec`` makes the
    batched class itself."""
    from gymnasium.utils.env_checker import check_env

    from dynmesh_warp.envs import ENV_ID, RideSurfaceSingleEnv

    cfg = _env_cfg(device)
    env = gym.make(ENV_ID, scene=cfg, max_episode_steps=6)  # Gymnasium's TimeLimit ends the episode
    assert isinstance(env.unwrapped, RideSurfaceSingleEnv) and env.spec.max_episode_steps == 6
    check_env(env.unwrapped, skip_render_check=True)
    batch = RideSurfaceEnv(num_envs=1, scene=cfg, max_steps=6)
    rng = np.random.default_rng(0)
    for seed in (4, 9):
        o, info = env.reset(seed=seed)
        ob, _ = batch.reset(seed=seed)
        assert o.shape == (18,) and info == {} and env.observation_space.contains(o)
        np.testing.assert_array_equal(o, ob[0])
        for k in range(6):
            a = rng.uniform(-1, 1, 2).astype(np.float32)
            o, r, term, trunc, _ = env.step(a)
            ob, rb, tb, trb, ib = batch.step(a[None])
            assert isinstance(r, float) and r == float(rb[0]) and (term, trunc) == (bool(tb[0]), bool(trb[0]))
            np.testing.assert_array_equal(o, ib["final_obs"][0])
            if term or trunc:
                break
        assert term or (trunc and k == 5)
        if term:  # the env's own end (a TimeLimit's truncation is the wrapper's: Gymnasium steps on)
            with pytest.raises(RuntimeError, match="call reset"):
                env.step(np.zeros(2, np.float32))
    with pytest.raises(ValueError, match=r"give the episode length as max_episode_steps=6"):
        gym.make(ENV_ID, scene=cfg, max_steps=6)
    with pytest.raises(ValueError, match=r"action must have shape \(2,\)"):
        env.reset()
        env.step(np.zeros((1, 2), np.float32))
    vec = gym.make_vec(ENV_ID, num_envs=3, scene=cfg)
    assert isinstance(vec, RideSurfaceEnv) and vec.num_envs == 3 and vec.render() is None
    # Gymnasium's names, which make_vec passes on (a new user's TypeError): the episode length
    # and the render mode, one image per env
    vec = gym.make_vec(ENV_ID, num_envs=2, scene=cfg, max_episode_steps=3, render_mode="rgb_array")
    vec.reset(seed=0)
    trunc = [vec.step(np.zeros((2, 2), np.float32))[3] for _ in range(3)]
    assert vec.max_steps == 3 and trunc[-1].all() and not trunc[0].any()
    img = vec.render()
    assert img.shape == (2, 128, 128, 3) and img.dtype == np.uint8
    with pytest.raises(ValueError, match="num_envs is fixed for one env"):
        RideSurfaceSingleEnv(scene=cfg, num_envs=2)
    with pytest.raises(ValueError, match="render_mode must be None or 'rgb_array'"):
        RideSurfaceSingleEnv(scene=cfg, render_mode="human")
    for bad in ((0, 10), (10,), (1.5, 10), "big"):  # refused before the world is built
        with pytest.raises(ValueError, match=r"render_size must be \(width, height\) in pixels"):
            RideSurfaceSingleEnv(scene=cfg, render_size=bad)


def test_single_env_renders_the_batchs_camera_image(device):
    """``render_mode="rgb_array"``: the env's camera image as uint8 (height, width, 3), the
    vector env's ``render_images`` of that env rounded to 8 bits."""
    from dynmesh_warp.envs import RideSurfaceSingleEnv

    env = RideSurfaceSingleEnv(scene=_env_cfg(device), render_mode="rgb_array", render_size=(20, 12))
    env.reset(seed=2)
    img = env.render()
    assert img.shape == (12, 20, 3) and img.dtype == np.uint8 and img.max() > img.min()
    ref = env.vector_env.render_images(20, 12)[0]
    np.testing.assert_array_equal(img, (np.clip(ref, 0, 1) * 255 + 0.5).astype(np.uint8))
    assert RideSurfaceSingleEnv(scene=_env_cfg(device)).render() is None
