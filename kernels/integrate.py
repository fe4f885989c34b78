"""Stage 4: sphere dynamics — gravity, continuous contact response, time advance."""

import warp as wp

from .frames import store_frame_key

# CUDA fast math (approximate division and square root), as the contact kernels of the same step
# (kernels/collide.py, swept.py): the sphere update's divisions and square roots lose the IEEE
# sequences' slow-path calls; results move by float rounding only (docs/physics.md, "Fast math").
wp.set_module_options({"fast_math": True})

#: a contact whose normal has a cosine below this with the sphere's other remembered plane
#: (``Contacts.last_*``: its contact of the last sub-step; ``Contacts.other_*``: the other side
#: of its last pinch) faces it: the sphere may be pinched between two parts of the surface
#: (``pinch_partner``; docs/physics.md, "A sphere pinched between two surfaces")
PINCH_COS = wp.constant(-0.5)
#: sub-steps a pinch's other side is kept without being the closest contact again: it ages out
#: (a plate that rises away releases the sphere at once or within these sub-steps)
PINCH_KEEP = wp.constant(4.0)
#: each sphere's pinch memory, one 16-float vector (``Contacts.memory``): [0:3] the last
#: sub-step's contact normal (zero: none), [3:6] its surface velocity, [6:9] the other side of the
#: last pinch, its normal (zero: none), [9:12] its velocity, [12] the last contact's plane offset
#: dot(normal, point) [m], [13] the other side's as last seen [m], [14] sub-steps since the other
#: side was seen, [15] PINCH_KEEP after a pinch, counting down to 0
pinch_memory = wp.types.vector(length=16, dtype=wp.float32)
#: how much nearer (x r) a pinch leaves the centre to the side that was not its contact
PINCH_LEAN = wp.constant(1.0e-3)


@wp.func
def project_two(n1: wp.vec3, b1: float, n2: wp.vec3, b2: float, most: float):
    """The smallest correction x with dot(x, n1) >= b1 and dot(x, n2) >= b2 (unit normals) and
    the two multipliers (x = a n1 + b n2 where one or both constraints bind): one constraint
    alone where that satisfies the other, else both exactly; where no x meets both (two planes
    facing each other, closer than the constraints allow), or meeting both takes a correction
    longer than ``most`` (two planes all but parallel: a finger's bottom edge, normal
    (1, 0, -0.01), against the other finger's face sent a gripped sphere 1 m down through the
    floor in one sub-step; a new user's), the least-squares split along n1, (b1 - b2) / 2 (the
    middle), with the multipliers each constraint alone would need."""
    a1 = wp.max(b1, 0.0)
    a2 = wp.max(b2, 0.0)
    if b1 <= 0.0 and b2 <= 0.0:
        return wp.vec3(0.0), 0.0, 0.0
    if a1 * wp.dot(n1, n2) >= b2:
        return a1 * n1, a1, 0.0
    if a2 * wp.dot(n1, n2) >= b1:
        return a2 * n2, 0.0, a2
    d = wp.dot(n1, n2)
    det = 1.0 - d * d
    if det > 1.0e-4:
        a = (b1 - d * b2) / det
        b = (b2 - d * b1) / det
        x = a * n1 + b * n2
        if a >= 0.0 and b >= 0.0 and wp.length(x) <= most:
            return x, a, b
    return 0.5 * (b1 - b2) * n1, a1, a2


@wp.func
def apply_friction(v: wp.vec3, vs: wp.vec3, n: wp.vec3, friction: float, jn: float) -> wp.vec3:
    """Coulomb friction of one contact (normal n, surface velocity vs) with normal impulse jn
    [m/s]: up to friction * jn of the tangential relative velocity removed."""
    vrel = v - vs
    vt = vrel - wp.dot(vrel, n) * n
    lt = wp.length(vt)
    if lt > 0.0 and jn > 0.0:
        v = v - vt * wp.min(1.0, friction * jn / lt)
    return v


@wp.func
def spin_friction(vt: wp.vec3, w: wp.vec3, n: wp.vec3, r: float, friction: float, jn: float, inertia: float):
    """Coulomb friction of one contact on a sphere that rotates (``inertia`` = I / (m r^2) > 0;
    ``choices.SPHERE_INERTIA``): vt is the centre's velocity relative to the surface across the
    normal n [m/s], w the spin [rad/s], jn the normal impulse [m/s]. The contact point's slip,
    vt + w x (-r n), is removed up to friction * jn: a tangential impulse dv (per unit mass) moves
    the centre by dv and the spin by -(n x dv) / (inertia r), so the slip changes by
    (1 + 1 / inertia) dv, and dv = -slip inertia / (1 + inertia) stops it (rolling); less where
    friction cannot (sliding). Returns (vt, w)."""
    slip = vt + wp.cross(w, -r * n)
    ls = wp.length(slip)
    if ls > 0.0 and jn > 0.0:
        dv = -slip * wp.min(inertia / (1.0 + inertia), friction * jn / ls)
        vt = vt + dv
        w = w - wp.cross(n, dv) / (inertia * r)
    return vt, w


@wp.func
def tangential_friction(vt: wp.vec3, w: wp.vec3, n: wp.vec3, r: float, friction: float, jn: float, inertia: float):
    """Coulomb friction on vt, the centre's velocity relative to the surface across the normal n
    [m/s], with normal impulse jn [m/s]: a sphere that does not rotate (``inertia`` 0) keeps
    max(0, 1 - friction jn / |vt|) of it, and its spin w as it is; one that does, ``spin_friction``.
    The time-of-impact responses' rule (the mesh's and the ground plane's). Returns (vt, w)."""
    if inertia > 0.0:
        vt2, w2 = spin_friction(vt, w, n, r, friction, jn, inertia)
        return vt2, w2
    lt = wp.length(vt)
    if lt > 0.0:
        return vt * wp.max(0.0, 1.0 - friction * jn / lt), w
    return vt, w


@wp.func
def contact_friction(v: wp.vec3, w: wp.vec3, vs: wp.vec3, n: wp.vec3, r: float, friction: float, jn: float,
                     inertia: float):
    """Coulomb friction of one contact (normal n, surface velocity vs, normal impulse jn [m/s])
    on the sphere's velocity v and spin w: ``apply_friction`` where the sphere does not rotate
    (``inertia`` 0: w unchanged), ``spin_friction`` where it does. Returns (v, w)."""
    if inertia == 0.0:
        return apply_friction(v, vs, n, friction, jn), w
    vrel = v - vs
    vn = wp.dot(vrel, n)
    vt, w2 = spin_friction(vrel - vn * n, w, n, r, friction, jn, inertia)
    return vs + vn * n + vt, w2


@wp.func
def pinch_partner(n: wp.vec3, vs: wp.vec3, m: pinch_memory, dt: float):
    """The plane facing a contact of normal n (cosine under ``PINCH_COS``) in a sphere's memory
    ``m``: its contact of the last sub-step, else the other side of its last pinch while it was
    seen no more than ``PINCH_KEEP`` sub-steps ago. Returns (normal (zero: none), offset now [m]
    (the plane is dot(normal, x) = offset, carried on one sub-step at the velocity it had when
    seen), velocity, age in sub-steps). A plane seen two or more sub-steps ago: its offset as
    of the last sub-step (``m[13]``, carried on every sub-step by ``advance_and_store_sphere``
    at the velocity it had when seen, never past the contact's point) carried one more; its
    velocity returned is the contact's (``vs``), its own may be stale (a plate that stopped or
    turned back would drag the sphere after it until it aged out)."""
    last_n = wp.vec3(m[0], m[1], m[2])
    if wp.dot(n, last_n) < PINCH_COS:
        last_v = wp.vec3(m[3], m[4], m[5])
        return last_n, m[12] + wp.dot(last_v, last_n) * dt, last_v, 1.0
    other_n = wp.vec3(m[6], m[7], m[8])
    age = m[14] + 1.0
    if wp.dot(n, other_n) < PINCH_COS and age <= PINCH_KEEP:
        return other_n, m[13] + wp.dot(wp.vec3(m[9], m[10], m[11]), other_n) * dt, vs, age
    return wp.vec3(0.0), 0.0, wp.vec3(0.0), 0.0


@wp.func
def resolve_pinch(
    p: wp.vec3,
    v: wp.vec3,
    r: float,
    dt: float,
    friction: float,
    n: wp.vec3,
    depth: float,
    vs: wp.vec3,
    n2: wp.vec3,
    d2: float,
    vs2: wp.vec3,
    w: wp.vec3,
    inertia: float,
):
    """A sphere pinched between its contact (normal n, depth, surface velocity vs) and the plane
    facing it (dot(n2, x) = d2, moving at vs2): its centre moved the least distance that puts
    it r in front of both (the middle where the planes are closer than 2 r), and PINCH_LEAN r
    nearer the plane that was not this sub-step's contact, so that the next sub-step's closest
    contact is that side if it is still there (each side is seen again, or ages out); its
    velocity changed the least to approach neither (restitution 0: a squeeze), then Coulomb
    friction of each side with that side's normal impulse (``contact_friction``: w, the spin, and
    ``inertia`` as there); then it moves on for dt. Returns (position, velocity, spin)."""
    depth2 = r - (wp.dot(n2, p) - d2)
    x, a1, a2 = project_two(n, depth, n2, depth2 - PINCH_LEAN * r, r)  # (at most r a sub-step)
    p = p + x
    dv, j1, j2 = project_two(n, -wp.dot(v - vs, n), n2, -wp.dot(v - vs2, n2), r / dt)
    v = v + dv
    if friction > 0.0:
        v, w = contact_friction(v, w, vs, n, r, friction, j1, inertia)
        v, w = contact_friction(v, w, vs2, n2, r, friction, j2, inertia)
    return p + v * dt, v, w


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
    d2: float,
    vs2: wp.vec3,
    pinched_last: float,
    w: wp.vec3,
    inertia: float,
):
    """One sphere over dt with its contact (face >= 0: normal n, depth [m], surface velocity vs
    [m/s]) and the optional ground plane: the continuous response of ``integrate_spheres``
    (shared with the batched step, kernels/batch.py). ``n2``, ``d2``, ``vs2``: the plane facing
    the contact (``pinch_partner``: dot(n2, x) = d2 now, moving at vs2; n2 zero: none);
    ``pinched_last`` > 0 where a pinch was resolved within the last PINCH_KEEP sub-steps. The
    sphere is pinched where it touches both (or reaches them within dt, or would be pushed into
    one by resolving the other alone), its centre not behind the plane (by up to r / 2 after a
    recent pinch), and either the two close on each other (their relative velocity along the
    normals, dot(vs - vs2, n - n2) > 0.01 r per second and over half of |vs - vs2| |n - n2|:
    mostly closing; a static or rigidly moving groove is no pinch, and keeps the one-contact
    response) or it was pinched recently (a gap that closed and stays closed): then it is
    resolved against both at once (``resolve_pinch``). ``w``: the sphere's spin [rad/s] and
    ``inertia`` its moment of inertia over m r^2 (0: it does not rotate, w is kept as given):
    friction turns it (``spin_friction``), so a ball rolls; nothing else changes it (no rolling
    resistance). Returns (position, velocity, spin, 1 when pinched else 0)."""
    pinched = int(0)
    if inv_mass == 0.0:
        return p + v * dt, v, w, pinched
    v = v + gravity * dt
    if face >= 0 and wp.length_sq(n2) > 0.0:
        depth2 = r - (wp.dot(n2, p) - d2)
        tol = 0.02 * r
        # (touching, or touched within dt at the relative normal velocity, or touched once the
        # other side's overlap alone is resolved: a push out of one side into the other)
        facing = wp.max(0.0, -wp.dot(n, n2))
        reach1 = depth + wp.max(0.0, depth2) * facing + wp.max(0.0, -wp.dot(v - vs, n)) * dt + tol
        reach2 = depth2 + wp.max(0.0, depth) * facing + wp.max(0.0, -wp.dot(v - vs2, n2)) * dt + tol
        # (the centre not behind the remembered plane; after a pinch, up to r / 2 behind it: a gap
        # closing to nothing at over 0.6 m/s left the centre that far past it, and the one-contact
        # response then pushed the sphere up into the top plate; a new user's)
        behind = tol
        if pinched_last > 0.0:
            behind = 0.5 * r
        # closing: the two surfaces' relative velocity mostly along their normals, towards each
        # other (a rigidly rotating groove's interpolated vertices close a little, at a small
        # fraction of their relative speed: counted as a pinch, it changed an ordinary contact)
        rel = vs - vs2
        closing = wp.dot(rel, n - n2)
        if reach1 >= 0.0 and reach2 >= 0.0 and depth2 <= r + behind:
            if pinched_last > 0.0 or (closing > 0.01 * r and closing > 0.5 * wp.length(rel) * wp.length(n - n2)):
                pinched = 1
    if pinched != 0:
        p, v, w = resolve_pinch(p, v, r, dt, friction, n, depth, vs, n2, d2, vs2, w, inertia)
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
            vt, w = tangential_friction(vrel - vn * n, w, n, r, friction, jn, inertia)
            v_new = vs + vn_new * n + vt
            p = p + v * toi + v_new * (dt - toi)
            v = v_new
        else:
            p = p + v * dt
    else:
        p = p + v * dt
    if ground != 0:
        if p[2] - r < ground_height:
            if v[2] < 0.0:
                # the time of impact, as for the mesh: the sphere crossed the plane tau ago (at
                # most dt), bounces there and moves on for tau with its new velocity (a clamp
                # alone lost the bounce's height: a new user's 4th bounce at e = 0.5 reached
                # 0.65 x e^8 h at dt 1/240, the mesh plane's 1.09 x)
                vn = v[2]
                tau = wp.min(dt, (ground_height + r - p[2]) / (-vn))
                vn_new = float(0.0)
                if -vn > rest_speed:
                    vn_new = -restitution * vn
                vt_old = wp.vec3(v[0], v[1], 0.0)
                vt, w = tangential_friction(vt_old, w, wp.vec3(0.0, 0.0, 1.0), r, friction, vn_new - vn, inertia)
                v = wp.vec3(vt[0], vt[1], vn_new)
                shift = (vt - vt_old) * tau
                p = wp.vec3(p[0] + shift[0], p[1] + shift[1], ground_height + r + vn_new * tau)
            else:
                p = wp.vec3(p[0], p[1], ground_height + r)
    return p, v, w, pinched


@wp.func
def advance_and_store_sphere(
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
    inertia: float,
    contact_face: wp.array[wp.int32],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
    contact_memory: wp.array[pinch_memory],
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
    sphere_spin_out: wp.array[wp.vec3],
):
    """``advance_sphere`` for sphere s (centre p, velocity v) with its contact of this sub-step
    (``contact_*[s]``) and its pinch memory (``contact_memory[s]``, ``pinch_memory``), stored:
    position, velocity and, where the sphere rotates (``inertia`` > 0, as in ``advance_sphere``),
    its spin (a point mass's spin is neither read nor written). What the world's and the batched
    step's integration share: the plane facing the contact (``pinch_partner``) before, and after,
    the contact kept as the last one and, where it was a pinch against the last contact, that
    contact kept as the other side."""
    face = contact_face[s]
    n = contact_normal[s]
    depth = contact_depth[s]
    vs = contact_velocity[s]
    w = wp.vec3(0.0)
    if inertia > 0.0:
        w = sphere_spin_out[s]
    m = contact_memory[s]
    n2 = wp.vec3(0.0)
    d2 = float(0.0)
    vs2 = wp.vec3(0.0)
    age = float(0.0)
    # the other side carried on one sub-step at the velocity it had when seen (m[13] is its plane
    # as of the last sub-step: a side not seen again moves on, it is not held where it was seen)
    carried = m[13] + wp.dot(wp.vec3(m[9], m[10], m[11]), wp.vec3(m[6], m[7], m[8])) * dt
    if face >= 0:
        n2, d2, vs2, age = pinch_partner(n, vs, m, dt)
        if age > 1.0:
            # (a side not seen since does not pass the contact's point: two surfaces closing on
            # each other stop where they meet)
            d2 = wp.min(d2, wp.dot(n2, p) - (r - depth) * wp.dot(n2, n))
            carried = d2
    p1, v1, w1, pinched = advance_sphere(p, v, inv_mass, r, gravity, dt, restitution, friction, rest_speed, ground,
                                         ground_height, face, n, depth, vs, n2, d2, vs2, m[15], w, inertia)
    other_age = m[14] + 1.0
    if pinched != 0:
        if age == 1.0:  # the partner was the last contact: it becomes the other side
            for k in range(6):
                m[6 + k] = m[k]
            m[13] = m[12]
            other_age = 1.0
        elif (r - depth) + (wp.dot(n2, p) - d2) > 4.0 * PINCH_LEAN * r:
            other_age = age
        else:
            # (the two planes one: a gap closed to nothing, where the contact found is either
            # of two coplanar faces and leaning cannot make the other the closest; it is not
            # aged while they stay one, and a plane that moves off ages again)
            other_age = 1.0
    if pinched == 0 or age != 1.0:
        m[13] = carried
    m[14] = wp.min(other_age, PINCH_KEEP + 1.0)
    if face >= 0:
        for k in range(3):
            m[k] = n[k]
            m[3 + k] = vs[k]
        m[12] = wp.dot(n, p) - (r - depth)
    else:
        m[0] = 0.0
        m[1] = 0.0
        m[2] = 0.0
    m[15] = wp.max(m[15] - 1.0, 0.0)
    if pinched != 0:
        m[15] = PINCH_KEEP
    contact_memory[s] = m
    sphere_pos_out[s] = p1
    sphere_vel_out[s] = v1
    if inertia > 0.0:
        sphere_spin_out[s] = w1


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
    inertia: float,
    # In:
    contact_face: wp.array[wp.int32],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
    # State out:
    sphere_pos_out: wp.array[wp.vec3],
    sphere_vel_out: wp.array[wp.vec3],
    sphere_spin_out: wp.array[wp.vec3],
    sim_time_out: wp.array[wp.float64],
    frame_key_out: wp.array[wp.int32],
    frame_changed_out: wp.array[wp.int32],
    # Out:
    contact_memory: wp.array[pinch_memory],
):
    """Advance each sphere by dt with a continuous (time-of-impact) contact response.

    Velocities are relative to the surface velocity at the contact, so a moving surface lifts
    and carries the spheres on it. If the sphere would reach the surface within the step
    (gap <= approach speed * dt) it moves to the time of impact, its normal relative velocity
    is reflected with ``restitution`` (set to zero below ``rest_speed`` [m/s], which makes
    resting contact stable), Coulomb friction removes up to ``friction`` * normal impulse of
    the tangential relative velocity, and it moves on for the rest of the step. A sphere
    already penetrating is first projected out along the contact normal. A sphere pinched
    between its contact and the plane facing it that it remembers (``contact_memory`` (S,)
    ``pinch_memory``: read, then set by ``advance_and_store_sphere``) is resolved against both
    (``resolve_pinch``).
    inv_mass (S,) [1/kg]: 0 marks a kinematic sphere (moves with its velocity, no forces).
    With ``ground`` set, a static plane z = ground_height (normal +z) also stops the spheres
    (same restitution and friction, applied after the mesh contact).
    inertia: the spheres' moment of inertia over m r^2 (``choices.SPHERE_INERTIA``; 0: they do
    not rotate); sphere_spin_out (S,) vec3 [rad/s]: their angular velocity, which friction
    changes where inertia > 0 (a ball rolls).

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
    advance_and_store_sphere(s, sphere_pos_out[s], sphere_vel_out[s], inv_mass[s], sphere_radius[s], gravity, dt,
                             restitution, friction, rest_speed, ground, ground_height, inertia, contact_face,
                             contact_normal, contact_depth, contact_velocity, contact_memory, sphere_pos_out,
                             sphere_vel_out, sphere_spin_out)


@wp.kernel
def advance_time(
    # In:
    dt: wp.float64,
    # State out:
    sim_time_out: wp.array[wp.float64],
):
    """sim_time_out[0] += dt (one thread; keeps the clock on the device for graph capture)."""
    sim_time_out[0] = sim_time_out[0] + dt
