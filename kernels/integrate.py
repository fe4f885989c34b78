"""Stage 4: sphere dynamics — gravity, continuous contact response, time advance."""

import warp as wp

from .frames import store_frame_key

# CUDA fast math (approximate division and square root), as the contact kernels of the same step
# (kernels/collide.py, swept.py): the sphere update's divisions and square roots lose the IEEE
# sequences' slow-path calls; results move by float rounding only (docs/physics.md, "Fast math").
wp.set_module_options({"fast_math": True})


#: a contact whose normal has a cosine below this with the sphere's contact at its last sub-step
#: (``Contacts.last_normal``) or with the other side of its last pinch (``Contacts.other_normal``)
#: makes a pinch: the sphere is wedged between two parts of the surface and is resolved against
#: both (``resolve_pinch``; docs/physics.md, "A sphere pinched")
PINCH_COS = wp.constant(-0.5)


@wp.func
def project_two(n1: wp.vec3, b1: float, n2: wp.vec3, b2: float):
    """The smallest correction x with dot(x, n1) >= b1 and dot(x, n2) >= b2 (unit normals):
    one constraint alone where that satisfies the other, else both exactly; where no x meets
    both (two planes facing each other closer than the sphere allows) the least-squares split
    along n1, (b1 - b2) / 2 (the middle)."""
    x1 = wp.max(b1, 0.0) * n1
    x2 = wp.max(b2, 0.0) * n2
    if b1 <= 0.0 and b2 <= 0.0:
        return wp.vec3(0.0)
    if wp.dot(x1, n2) >= b2:
        return x1
    if wp.dot(x2, n1) >= b1:
        return x2
    d = wp.dot(n1, n2)
    det = 1.0 - d * d
    if det > 1.0e-4:
        a = (b1 - d * b2) / det
        b = (b2 - d * b1) / det
        if a >= 0.0 and b >= 0.0:
            return a * n1 + b * n2
    return 0.5 * (b1 - b2) * n1


@wp.func
def resolve_pinch(
    p: wp.vec3,
    v: wp.vec3,
    r: float,
    dt: float,
    n: wp.vec3,
    depth: float,
    vs: wp.vec3,
    n2: wp.vec3,
    c2: wp.vec3,
    vs2: wp.vec3,
):
    """A sphere wedged between its contact (normal n, depth, surface velocity vs) and the other
    part of the surface it touched at its last sub-step (plane through c2 with normal n2, moving
    at vs2, so through c2 + vs2 dt now): its centre moved the least distance that puts it at r in
    front of both planes, its velocity changed the least to stop approaching either (the normal
    relative velocity 0: the squeeze-out between closing parts comes out of the two together),
    then it moves on for dt. Where the planes are closer than 2 r the centre goes to the middle.
    Returns (position, velocity)."""
    b2 = r - wp.dot(p - (c2 + vs2 * dt), n2)
    p = p + project_two(n, depth, n2, b2)
    dv = project_two(n, -wp.dot(v - vs, n), n2, -wp.dot(v - vs2, n2))
    v = v + dv
    return p + v * dt, v


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
    n2: wp.vec3,
    c2: wp.vec3,
    vs2: wp.vec3,
):
    """One sphere over dt with its contact (face >= 0: normal n, depth [m], surface velocity vs
    [m/s]) and the optional ground plane: the continuous response of ``integrate_spheres``
    (shared with the batched step, kernels/batch.py). ``n2``, ``c2``, ``vs2``: the plane facing
    the contact (``pinch_partner``; n2 zero: none); within half a radius of touching both, its
    centre in front of both, it is a pinch, resolved against both (``resolve_pinch``). Returns
    (position, velocity, 1 when pinched else 0)."""
    pinched = int(0)
    if inv_mass == 0.0:
        return p + v * dt, v, pinched
    v = v + gravity * dt
    b2 = r - wp.dot(p - (c2 + vs2 * dt), n2)
    if face >= 0 and wp.length(n2) > 0.0 and depth >= -0.5 * r and depth <= r and b2 >= -0.5 * r and b2 <= r:
        # (near both, within half a radius, the centre in front of both: between two parts, not
        # inside a thin one; a plane farther off takes no part: a kept one may have moved on)
        p, v = resolve_pinch(p, v, r, dt, n, depth, vs, n2, c2, vs2)
        pinched = 1
    elif face >= 0:
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
    return p, v, pinched


@wp.func
def pinch_partner(
    n: wp.vec3,
    last_normal: wp.vec3,
    last_point: wp.vec3,
    last_velocity: wp.vec3,
    other_normal: wp.vec3,
    other_point: wp.vec3,
    other_velocity: wp.vec3,
):
    """The plane (normal, point, velocity) on the other side of a pinch from a contact with
    normal n: the sphere's last contact, or the other side of its last pinch, whichever faces n
    (cosine under ``PINCH_COS``); a zero normal where neither does."""
    if wp.dot(n, last_normal) < PINCH_COS:
        return last_normal, last_point, last_velocity
    if wp.dot(n, other_normal) < PINCH_COS:
        return other_normal, other_point, other_velocity
    return wp.vec3(0.0), wp.vec3(0.0), wp.vec3(0.0)


@wp.func
def remember_contact(
    s: int,
    pinched: int,
    n2: wp.vec3,
    c2: wp.vec3,
    vs2: wp.vec3,
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_velocity: wp.array[wp.vec3],
    contact_last_normal: wp.array[wp.vec3],
    contact_last_point: wp.array[wp.vec3],
    contact_last_velocity: wp.array[wp.vec3],
    contact_other_normal: wp.array[wp.vec3],
    contact_other_point: wp.array[wp.vec3],
    contact_other_velocity: wp.array[wp.vec3],
):
    """Sphere s's contact of this sub-step kept for the next (``Contacts.last_*``), and where it
    was ``pinched`` the other side's plane (n2 through c2 moving at vs2;
    ``Contacts.other_*``, its point as last seen): the next sub-step's closest contact may be
    either side, and the pinch must see the opposite one. Normals zero for none."""
    if contact_face[s] >= 0:
        contact_last_normal[s] = contact_normal[s]
        contact_last_point[s] = contact_point[s]
        contact_last_velocity[s] = contact_velocity[s]
    else:
        contact_last_normal[s] = wp.vec3(0.0)
    if pinched != 0:
        contact_other_normal[s] = n2
        contact_other_point[s] = c2  # (as last seen: a plane kept over sub-steps is not carried on)
        contact_other_velocity[s] = vs2
    else:
        contact_other_normal[s] = wp.vec3(0.0)


@wp.func
def advance_sphere_with_memory(
    s: int,
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
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
    contact_last_normal: wp.array[wp.vec3],
    contact_last_point: wp.array[wp.vec3],
    contact_last_velocity: wp.array[wp.vec3],
    contact_other_normal: wp.array[wp.vec3],
    contact_other_point: wp.array[wp.vec3],
    contact_other_velocity: wp.array[wp.vec3],
):
    """``advance_sphere`` for sphere s with its contact of this sub-step and its pinch memory
    (``pinch_partner`` before, ``remember_contact`` after): what the world's and the batched
    step's integration share. Returns (position, velocity)."""
    n2, c2, vs2 = pinch_partner(contact_normal[s], contact_last_normal[s], contact_last_point[s],
                                contact_last_velocity[s], contact_other_normal[s], contact_other_point[s],
                                contact_other_velocity[s])
    p, v, pinched = advance_sphere(p, v, inv_mass, r, gravity, dt, restitution, friction, rest_speed, ground,
                                   ground_height, contact_face[s], contact_normal[s], contact_depth[s],
                                   contact_velocity[s], n2, c2, vs2)
    remember_contact(s, pinched, n2, c2, vs2, contact_face, contact_point, contact_normal, contact_velocity,
                     contact_last_normal, contact_last_point, contact_last_velocity, contact_other_normal,
                     contact_other_point, contact_other_velocity)
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
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
    # State out:
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
    sim_time_out: wp.array[wp.float64],
    frame_key_out: wp.array[wp.int32],
    frame_changed_out: wp.array[wp.int32],
    # Out:
    contact_last_normal: wp.array[wp.vec3],
    contact_last_point: wp.array[wp.vec3],
    contact_last_velocity: wp.array[wp.vec3],
    contact_other_normal: wp.array[wp.vec3],
    contact_other_point: wp.array[wp.vec3],
    contact_other_velocity: wp.array[wp.vec3],
):
    """Advance each sphere by dt with a continuous (time-of-impact) contact response.

    Velocities are relative to the surface velocity at the contact, so a moving surface lifts
    and carries the spheres on it. If the sphere would reach the surface within the step
    (gap <= approach speed * dt) it moves to the time of impact, its normal relative velocity
    is reflected with ``restitution`` (set to zero below ``rest_speed`` [m/s], which makes
    resting contact stable), Coulomb friction removes up to ``friction`` * normal impulse of
    the tangential relative velocity, and it moves on for the rest of the step. A sphere
    already penetrating is first projected out along the contact normal. A sphere whose contact
    faces the one it had at its last sub-step or the other side of its last pinch
    (``contact_last_*``, ``contact_other_*`` (S,) vec3: normal, point, surface velocity; read,
    then set by ``remember_contact``; normals zero for none) is pinched between two parts of the
    surface and resolved against both (``resolve_pinch``).
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
    p, v = advance_sphere_with_memory(s, sphere_pos_out[s], sphere_vel_out[s], inv_mass[s], sphere_radius[s],
                                      gravity, dt, restitution, friction, rest_speed, ground, ground_height,
                                      contact_face, contact_point, contact_normal, contact_depth, contact_velocity,
                                      contact_last_normal, contact_last_point, contact_last_velocity,
                                      contact_other_normal, contact_other_point, contact_other_velocity)
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
