"""The RL task of the batched envs (issue 15; dynmesh_warp/envs.py): a ball to keep on the
deforming surface near a target, with the surface around it observed through height probes.

All on the device (no host round trip per step): actions into velocities, height probes (a
downward ray against the env's frame-pair BVH, the interpolated triangles evaluated here),
observation, reward and termination, and the reset of finished envs at a random phase.
"""

import warp as wp

from .batch import pair_slot
from .frames import PLAYBACK_CLAMP, PLAYBACK_PINGPONG, blend_pair
from .integrate import pinch_memory
from .swept import interpolated_triangle

#: probe grid around the ball: PROBE_SIDE x PROBE_SIDE points
PROBE_SIDE = wp.constant(3)
#: observation layout per env: ball position relative to the target (3), ball velocity (3),
#: probe heights relative to the ball (PROBE_SIDE^2), in contact (1), phase of the clock (2)
OBS_DIM = wp.constant(3 + 3 + 9 + 1 + 2)


@wp.func
def intersect_down(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Distance t >= 0 along -z from p to triangle (a, b, c) and whether it hits
    (Moller-Trumbore with d = (0, 0, -1))."""
    d = wp.vec3(0.0, 0.0, -1.0)
    e1 = b - a
    e2 = c - a
    h = wp.cross(d, e2)
    det = wp.dot(e1, h)
    hit = int(0)
    t = float(0.0)
    if wp.abs(det) > 1.0e-12:
        inv = 1.0 / det
        s = p - a
        u = inv * wp.dot(s, h)
        q = wp.cross(s, e1)
        v = inv * wp.dot(d, q)
        t = inv * wp.dot(e2, q)
        if u >= 0.0 and v >= 0.0 and u + v <= 1.0 and t >= 0.0:
            hit = 1
    return t, hit


@wp.func
def playback_cycle(num_frames: int, mode: int) -> float:
    """Frames of one cycle of the surface's playback: ``num_frames`` for loop (frame T wraps to
    0), 2 (T - 1) for pingpong (forward and back), T - 1 for clamp (played once, then held);
    at least 1."""
    T = float(num_frames)
    c = T
    if mode == PLAYBACK_PINGPONG:
        c = 2.0 * (T - 1.0)
    elif mode == PLAYBACK_CLAMP:
        c = T - 1.0
    return wp.max(c, 1.0)


@wp.func
def playback_phase(time: wp.float64, fps: wp.float64, num_frames: int, mode: int) -> float:
    """The env's phase angle [rad] in its surface's playback at ``time`` [s]: 2 pi x the fraction
    of the cycle (``playback_cycle``) for loop and pingpong, whose sin and cos then repeat with
    the surface; pi x the fraction of the sequence played for clamp, held at pi once the last
    frame holds (a half turn, so each (sin, cos) names one time of the sequence)."""
    u = float(time * fps) / playback_cycle(num_frames, mode)
    if mode == PLAYBACK_CLAMP:
        return 3.141592653589793 * wp.clamp(u, 0.0, 1.0)
    return 6.283185307179586 * (u - wp.floor(u))


@wp.func
def surface_height_at(
    bvh: wp.uint64, frames: wp.array2d[wp.vec3], indices: wp.array[wp.int32], k0: int, k1: int, alpha: float,
    x: float, y: float, top: float,
):
    """Height of the highest point of the interpolated surface below (x, y, top) [m] and whether
    there is one."""
    p = wp.vec3(x, y, top)
    query = wp.bvh_query_ray(bvh, p, wp.vec3(0.0, 0.0, -1.0))
    f = int(0)
    best = float(1.0e30)
    found = int(0)
    while wp.bvh_query_next(query, f):
        a, b, c = interpolated_triangle(frames, indices, f, k0, k1, alpha)
        t, hit = intersect_down(p, a, b, c)
        if hit == 1 and t < best:
            best = t
            found = 1
    return top - best, found


@wp.func
def applied_action(a: float) -> float:
    """An action component as the physics and the reward take it: clipped to the action space
    [-1, 1]; a non-finite one (which the NumPy backend refuses before the step) counts as 0."""
    if not wp.isfinite(a):
        return 0.0
    return wp.clamp(a, -1.0, 1.0)


@wp.kernel
def apply_env_actions(
    # Model:
    spheres_per_env: int,
    # In:
    actions: wp.array2d[float],
    accel: float,
    duration: float,
    # State out:
    sphere_vel_out: wp.array[wp.vec3],
):
    """Each env's action (E, 2) in [-1, 1] as a horizontal velocity change of its ball at the
    start of the env step: ``applied_action(action)`` * accel [m/s^2] * duration [s] (the change
    an acceleration held over ``duration`` would give, applied at once: an impulse). One thread
    per env (ball = first sphere)."""
    e = wp.tid()
    ax = applied_action(actions[e, 0])
    ay = applied_action(actions[e, 1])
    s = e * spheres_per_env
    sphere_vel_out[s] = sphere_vel_out[s] + wp.vec3(ax, ay, 0.0) * (accel * duration)


@wp.kernel
def evaluate_ball_task(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    pair_bvh: wp.array[wp.uint64],
    fps: wp.float64,
    interpolate: int,
    slices: int,
    spheres_per_env: int,
    floor_height: float,
    # State in:
    env_time_in: wp.array[wp.float64],
    env_playback_in: wp.array[wp.int32],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    contact_face: wp.array[wp.int32],
    actions: wp.array2d[float],
    env_steps: wp.array[wp.int32],
    env_mask: wp.array[wp.int32],
    obs_only: int,
    target: wp.vec3,
    max_distance: float,
    probe_spacing: float,
    top: float,
    radius: float,
    max_steps: int,
    # Out:
    obs: wp.array2d[float],
    reward: wp.array[float],
    terminated: wp.array[wp.int32],
    truncated: wp.array[wp.int32],
):
    """Observation (E, OBS_DIM), reward, terminated and truncated flags of each env after its
    step. Reward: 1 while the ball is up, minus its squared horizontal distance to the target
    over max_distance [m], minus 0.01 |action|^2 (the action as applied: ``applied_action``). In
    contact (obs 15) is 0 in an episode's first observation (``obs_only``). Terminated: the ball left the target's
    reach or fell to ``floor_height`` [m] (the ground, or with none ``envs.FLOOR_DROP`` ball radii
    under the sequence's lowest point); a height probe that meets no surface below reads
    ``floor_height`` too (a bounded value: with no ground it read -1e6). Phase (obs 16, 17): sin and cos of
    ``playback_phase``. Truncated: env_steps reached max_steps. Only envs with env_mask[e] != 0;
    with obs_only the observation alone (the first of an episode just reset)."""
    e = wp.tid()
    if env_mask[e] == 0:
        return
    s = e * spheres_per_env
    p = sphere_pos_in[s]
    v = sphere_vel_in[s]
    T = frames.shape[0]
    k0, k1, alpha = blend_pair(env_time_in[e], fps, T, env_playback_in[e], interpolate)
    bvh = pair_bvh[pair_slot(k0, k1, alpha, T, slices)]
    rel = p - target
    obs[e, 0] = rel[0]
    obs[e, 1] = rel[1]
    obs[e, 2] = rel[2]
    obs[e, 3] = v[0]
    obs[e, 4] = v[1]
    obs[e, 5] = v[2]
    j = int(6)
    for iy in range(PROBE_SIDE):
        for ix in range(PROBE_SIDE):
            x = p[0] + float(ix - 1) * probe_spacing
            y = p[1] + float(iy - 1) * probe_spacing
            h, found = surface_height_at(bvh, frames, indices, k0, k1, alpha, x, y, top)
            if found == 0:
                h = floor_height
            obs[e, j] = h - p[2]
            j += 1
    contact = float(0.0)
    if obs_only == 0 and contact_face[s] >= 0:  # an episode's first observation: no step has touched it
        contact = 1.0
    obs[e, 15] = contact
    phase = playback_phase(env_time_in[e], fps, T, env_playback_in[e])
    obs[e, 16] = wp.sin(phase)
    obs[e, 17] = wp.cos(phase)
    if obs_only != 0:
        return
    d2 = (rel[0] * rel[0] + rel[1] * rel[1]) / (max_distance * max_distance)
    ax = applied_action(actions[e, 0])
    ay = applied_action(actions[e, 1])
    a2 = ax * ax + ay * ay
    fell = p[2] - radius < floor_height + 0.25 * radius
    gone = d2 > 1.0
    term = int(0)
    if fell or gone:
        term = 1
    reward[e] = 1.0 - d2 - 0.01 * a2 - float(term)
    terminated[e] = term
    trunc = int(0)
    if term == 0 and env_steps[e] >= max_steps:
        trunc = 1
    truncated[e] = trunc


@wp.kernel
def reset_ball_envs(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    pair_bvh: wp.array[wp.uint64],
    fps: wp.float64,
    interpolate: int,
    slices: int,
    spheres_per_env: int,
    # In:
    env_mask: wp.array[wp.int32],
    env_seed: wp.array[wp.int32],
    target: wp.vec3,
    spawn_radius: float,
    push: float,
    top: float,
    radius: float,
    # State out:
    env_time_out: wp.array[wp.float64],
    env_playback_out: wp.array[wp.int32],
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
    sphere_spin_out: wp.array[wp.vec3],
    env_steps_out: wp.array[wp.int32],
    env_episode_out: wp.array[wp.int32],
    contact_memory_out: wp.array[pinch_memory],
):
    """Start a new episode in every env with env_mask[e] != 0: a random time of its playback's
    cycle (uniform over ``playback_cycle`` / fps [s]: a pingpong env starts going back as often
    as forth), the ball over a random point within ``spawn_radius`` [m]
    of the target, just above the surface there, with a random horizontal push of at most
    ``push`` [m/s], its spin stopped and its pinch memory cleared (``BatchedWorld.reset``'s rule). Random numbers from
    (env_seed[e], env, episode): reproducible."""
    e = wp.tid()
    if env_mask[e] == 0:
        return
    ep = env_episode_out[e] + 1
    env_episode_out[e] = ep
    state = wp.rand_init(env_seed[e], e * 7919 + ep * 104729)
    T = frames.shape[0]
    t = wp.float64(wp.randf(state) * playback_cycle(T, env_playback_out[e])) / fps
    env_time_out[e] = t
    k0, k1, alpha = blend_pair(t, fps, T, env_playback_out[e], interpolate)
    bvh = pair_bvh[pair_slot(k0, k1, alpha, T, slices)]
    ang = wp.randf(state) * 6.283185307179586
    rad = spawn_radius * wp.sqrt(wp.randf(state))
    x = target[0] + rad * wp.cos(ang)
    y = target[1] + rad * wp.sin(ang)
    h, found = surface_height_at(bvh, frames, indices, k0, k1, alpha, x, y, top)
    if found == 0:
        h = target[2]
    s = e * spheres_per_env
    sphere_pos_out[s] = wp.vec3(x, y, h + radius * 1.2)
    pang = wp.randf(state) * 6.283185307179586
    pm = push * wp.randf(state)
    sphere_vel_out[s] = wp.vec3(pm * wp.cos(pang), pm * wp.sin(pang), 0.0)
    sphere_spin_out[s] = wp.vec3(0.0)
    contact_memory_out[s] = pinch_memory()  # a pinch of the last episode is not this one's
    env_steps_out[e] = 0


@wp.kernel
def combine_env_flags(
    # In:
    terminated: wp.array[wp.int32],
    truncated: wp.array[wp.int32],
    # Out:
    done: wp.array[wp.int32],
):
    """done[e] = 1 where env e terminated or was truncated, else 0."""
    e = wp.tid()
    done[e] = wp.where(terminated[e] != 0 or truncated[e] != 0, 1, 0)


@wp.kernel
def reset_env_streams(
    # In:
    env_mask: wp.array[wp.int32],
    seed: int,
    # State out:
    env_seed_out: wp.array[wp.int32],
    env_episode_out: wp.array[wp.int32],
):
    """A seeded reset: each env with env_mask[e] != 0 takes ``seed`` and restarts its episode
    count (its next episode draws as the first after that seed); the others keep theirs."""
    e = wp.tid()
    if env_mask[e] != 0:
        env_seed_out[e] = seed
        env_episode_out[e] = 0


@wp.kernel
def count_env_steps(
    # State out:
    env_steps_out: wp.array[wp.int32],
):
    """env_steps_out[e] += 1 (one env step taken)."""
    e = wp.tid()
    env_steps_out[e] = env_steps_out[e] + 1
