"""Stage 4: sphere dynamics — gravity, continuous contact response, time advance."""

import warp as wp

from .frames import store_frame_key

# CUDA fast math (approximate division and square root), as the contact kernels of the same step
# (kernels/collide.py, swept.py): the sphere update's divisions and square roots lose the IEEE
# sequences' slow-path calls; results move by float rounding only (docs/physics.md, "Fast math").
wp.set_module_options({"fast_math": True})


@wp.func
def advance_sphere(
    p: wp.vec3,
    v: wp.vec3,
    inv_mass: float,
    r: float,
    gravity: wp.vec3,
    dt: float,
    restitution: float,
    friction: float,
    rest_speed: float,
    ground: int,
    ground_height: float,
    face: int,
    n: wp.vec3,
    depth: float,
    vs: wp.vec3,
):
    """One sphere over dt with its contact (face >= 0: normal n, depth [m], surface velocity vs
    [m/s]) and the optional ground plane: the continuous response of ``integrate_spheres``
    (shared with the batched step, kernels/batch.py). Returns (position, velocity)."""
    if inv_mass == 0.0:
        return p + v * dt, v
    v = v + gravity * dt
    if face >= 0:
        gap = -depth
        if gap < 0.0:
            p = p - n * gap
            gap = 0.0
        vrel = v - vs
        vn = wp.dot(vrel, n)
        if vn < 0.0 and -vn * dt >= gap:
            toi = gap / (-vn)
            vn_new = float(0.0)
            if -vn > rest_speed:
                vn_new = -restitution * vn
            jn = vn_new - vn
            vt = vrel - vn * n
            lt = wp.length(vt)
            if lt > 0.0:
                vt = vt * wp.max(0.0, 1.0 - friction * jn / lt)
            v_new = vs + vn_new * n + vt
            p = p + v * toi + v_new * (dt - toi)
            v = v_new
        else:
            p = p + v * dt
    else:
        p = p + v * dt
    if ground != 0:
        if p[2] - r < ground_height:
            p = wp.vec3(p[0], p[1], ground_height + r)
            if v[2] < 0.0:
                vn = v[2]
                vn_new = float(0.0)
                if -vn > rest_speed:
                    vn_new = -restitution * vn
                vt = wp.vec3(v[0], v[1], 0.0)
                lt = wp.length(vt)
                if lt > 0.0:
                    vt = vt * wp.max(0.0, 1.0 - friction * (vn_new - vn) / lt)
                v = wp.vec3(vt[0], vt[1], vn_new)
    return p, v


@wp.kernel
def integrate_spheres(
    # Model:
    inv_mass: wp.array[float],
    sphere_radius: wp.array[float],
    gravity: wp.vec3,
    dt: float,
    restitution: float,
    friction: float,
    rest_speed: float,
    ground: int,
    ground_height: float,
    time_step: wp.float64,
    fps: wp.float64,
    num_frames: int,
    mode: int,
    # In:
    contact_face: wp.array[wp.int32],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
    # State out:
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
    sim_time_out: wp.array[wp.float64],
    frame_key_out: wp.array[wp.int32],
    frame_changed_out: wp.array[wp.int32],
):
    """Advance each sphere by dt with a continuous (time-of-impact) contact response.

    Velocities are relative to the surface velocity at the contact, so a moving surface lifts
    and carries the spheres on it. If the sphere would reach the surface within the step
    (gap <= approach speed * dt) it moves to the time of impact, its normal relative velocity
    is reflected with ``restitution`` (set to zero below ``rest_speed`` [m/s], which makes
    resting contact stable), Coulomb friction removes up to ``friction`` * normal impulse of
    the tangential relative velocity, and it moves on for the rest of the step. A sphere
    already penetrating is first projected out along the contact normal.
    inv_mass (S,) [1/kg]: 0 marks a kinematic sphere (moves with its velocity, no forces).
    With ``ground`` set, a static plane z = ground_height (normal +z) also stops the spheres
    (same restitution and friction, applied after the mesh contact).

    Thread 0 also advances the device clock, sim_time_out[0] += time_step (no thread of this kernel
    reads it), and keeps the clock's frame pair: frame_key_out[0] = k0 * num_frames + k1 at the
    new time, frame_changed_out[0] = 1 when that differs from the old key, else 0 (State: a
    collider that rebuilds per frame pair reads it at the next sub-step). Launch with max(S, 1)
    threads.
    """
    s = wp.tid()
    if s == 0:
        t = sim_time_out[0] + time_step
        sim_time_out[0] = t
        store_frame_key(t, fps, num_frames, mode, frame_key_out, frame_changed_out)
    if s >= inv_mass.shape[0]:
        return
    p, v = advance_sphere(sphere_pos_out[s], sphere_vel_out[s], inv_mass[s], sphere_radius[s], gravity, dt,
                          restitution, friction, rest_speed, ground, ground_height, contact_face[s],
                          contact_normal[s], contact_depth[s], contact_velocity[s])
    sphere_pos_out[s] = p
    sphere_vel_out[s] = v


@wp.kernel
def advance_time(
    # In:
    dt: wp.float64,
    # State out:
    sim_time_out: wp.array[wp.float64],
):
    """sim_time_out[0] += dt (one thread; keeps the clock on the device for graph capture)."""
    sim_time_out[0] = sim_time_out[0] + dt
