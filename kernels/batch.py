"""Batched environments (issue 15): many worlds in one Model/State, each with its own clock.

Every env plays the same reconstruction, each at its own time, so no single vertex buffer or
BVH fits them all. Instead the swept BVH of every frame pair is built once at load
(``compute_pair_bounds``; slot k holds the faces' boxes over frames k and k+1, slot T-1 the
loop's wrap pair (T-1, 0)); a sphere of env e picks the slot of e's frame pair and evaluates the
interpolated triangles itself, exactly as the single-clock swept collider does. Nothing is
refit per step or per env.

Flat layout: env e owns spheres ``sphere_env == e`` (E * S spheres in all, env-major).
"""

import warp as wp

from .collide import contact_reach
from .frames import PLAYBACK_LOOP, blend_pair, wrap_frame
from .integrate import advance_sphere
from .swept import closest_on_swept_bvh, write_swept_contact


@wp.func
def pair_slot(k0: int, k1: int, num_frames: int) -> int:
    """The BVH slot of frame pair (k0, k1): min(k0, k1) for neighbours, T-1 for the loop's
    wrap pair (T-1, 0), and for a held frame (k0 == k1, clamped at the end) the pair that
    contains it."""
    if k0 == k1:
        return wp.min(k0, wp.max(num_frames - 2, 0))
    lo = wp.min(k0, k1)
    hi = wp.max(k0, k1)
    if hi == lo + 1:
        return lo
    return num_frames - 1


@wp.kernel
def compute_pair_bounds(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    # Out:
    lowers: wp.array2d[wp.vec3],
    uppers: wp.array2d[wp.vec3],
):
    """Box of each face over every frame pair: slot k (T slots) spans frames k and (k+1) mod T.

    frames (T, N) [m]; indices (3M,); lowers/uppers (T, M) [m]. Launch (T, M)."""
    k, f = wp.tid()
    T = frames.shape[0]
    k1 = wrap_frame(k + 1, T, PLAYBACK_LOOP)  # the last slot is the wrap pair (T-1, 0)
    lo = frames[k, indices[3 * f]]
    hi = lo
    for c in range(3):
        a = frames[k, indices[3 * f + c]]
        b = frames[k1, indices[3 * f + c]]
        lo = wp.min(lo, wp.min(a, b))
        hi = wp.max(hi, wp.max(a, b))
    lowers[k, f] = lo
    uppers[k, f] = hi


@wp.kernel
def collide_and_integrate_env_spheres(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    pair_bvh: wp.array[wp.uint64],
    sphere_radius: wp.array[float],
    inv_mass: wp.array[float],
    sphere_env: wp.array[wp.int32],
    gravity: wp.vec3,
    restitution: float,
    friction: float,
    rest_speed: float,
    ground: int,
    ground_height: float,
    fps: wp.float64,
    interpolate: int,
    # State in:
    env_time_in: wp.array[wp.float64],
    env_rate_in: wp.array[float],
    env_playback_in: wp.array[wp.int32],
    # In:
    dt: float,
    extra_speed: float,
    margin: float,
    epsilon: float,
    # State out:
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
    # Out:
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    """One sub-step of every sphere of every env: contact with the surface at its env's time
    (``env_time_in[e]`` [s], played at ``env_rate_in[e]`` x, playback code
    ``env_playback_in[e]``), then the continuous response of ``integrate_spheres``. The
    surface velocity at the contact is scaled by the env's rate. One thread per sphere;
    (E * S,) arrays; dt [s] is the sub-step."""
    s = wp.tid()
    e = sphere_env[s]
    T = frames.shape[0]
    rate = env_rate_in[e]
    k0, k1, alpha = blend_pair(env_time_in[e], fps, T, env_playback_in[e], interpolate)
    p = sphere_pos_out[s]
    v = sphere_vel_out[s]
    r = sphere_radius[s]
    reach = contact_reach(r, v, extra_speed, dt, margin)
    bvh = pair_bvh[pair_slot(k0, k1, T)]
    min_dist, min_face, min_w, acc_n = closest_on_swept_bvh(bvh, frames, indices, k0, k1, alpha, p, reach, epsilon)
    write_swept_contact(s, p, r, reach, min_dist, min_face, min_w, acc_n, frames, indices, k0, k1, alpha,
                        fps * wp.float64(rate), contact_face, contact_point, contact_normal, contact_depth,
                        contact_velocity)
    p, v = advance_sphere(p, v, inv_mass[s], r, gravity, dt, restitution, friction, rest_speed, ground,
                          ground_height, contact_face[s], contact_normal[s], contact_depth[s], contact_velocity[s])
    sphere_pos_out[s] = p
    sphere_vel_out[s] = v


@wp.kernel
def advance_env_clocks(
    # State in:
    env_rate_in: wp.array[float],
    # In:
    dt: wp.float64,
    # State out:
    env_time_out: wp.array[wp.float64],
):
    """env_time_out[e] += env_rate_in[e] * dt [s] (float64, as the single world's clock)."""
    e = wp.tid()
    env_time_out[e] = env_time_out[e] + wp.float64(env_rate_in[e]) * dt


@wp.kernel
def reset_env_spheres(
    # Model:
    sphere_env: wp.array[wp.int32],
    # In:
    env_mask: wp.array[wp.int32],
    new_pos: wp.array[wp.vec3],
    new_vel: wp.array[wp.vec3],
    # State out:
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
):
    """Spheres of the envs with env_mask[e] != 0 from new_pos / new_vel ((E * S,) [m], [m/s]);
    the other envs' spheres are left untouched. One thread per sphere."""
    s = wp.tid()
    if env_mask[sphere_env[s]] == 0:
        return
    sphere_pos_out[s] = new_pos[s]
    sphere_vel_out[s] = new_vel[s]


@wp.kernel
def reset_env_clocks(
    # In:
    env_mask: wp.array[wp.int32],
    new_time: wp.array[wp.float64],
    new_rate: wp.array[float],
    new_playback: wp.array[wp.int32],
    # State out:
    env_time_out: wp.array[wp.float64],
    env_rate_out: wp.array[float],
    env_playback_out: wp.array[wp.int32],
):
    """Clocks of the envs with env_mask[e] != 0 (time [s], rate, playback code); (E,) arrays."""
    e = wp.tid()
    if env_mask[e] == 0:
        return
    env_time_out[e] = new_time[e]
    env_rate_out[e] = new_rate[e]
    env_playback_out[e] = new_playback[e]
