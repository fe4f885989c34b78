"""Stage 3: sphere–mesh contact generation.

A contact is described per sphere by five arrays (see :class:`dynmesh_warp.Contacts`):
face (-1 when none), closest point on the surface, unit normal pointing to the sphere's free
side, depth = radius - signed distance of the centre (> 0 when penetrating), and the surface
velocity at the closest point.

Surfaces are one-sided: the side the triangle normals point to (outward for a closed, outward
oriented mesh) is free space. A centre found behind the surface but closer than its radius is
pushed out to the front; a sphere entirely behind the surface has no contact.
"""

import warp as wp

from .geometry import closest_point_on_triangle

# CUDA fast math (approximate division and square root), as kernels/batch.py and render.py: the
# latency-bound contact queries lose the IEEE sequences' registers and slow-path calls; results
# move by float rounding only (docs/physics.md, "Fast math").
wp.set_module_options({"fast_math": True})



@wp.func
def make_contact(
    p: wp.vec3,
    r: float,
    c: wp.vec3,
    side: float,
    face_normal: wp.vec3,
):
    """Normal (to the free side) and depth for a centre p, closest point c, side sign (+1 front)."""
    d = p - c
    dist = wp.length(d)
    n = face_normal
    if dist > 1.0e-9:
        n = d * (side / dist)
    depth = r - side * dist
    return n, depth


@wp.func
def contact_side(p: wp.vec3, c: wp.vec3, face_normal: wp.vec3, sign: float) -> float:
    """The side (+1 front, -1 behind) of centre p from its closest point c: the query's sign
    (the angle-weighted pseudo-normal over the faces tied within epsilon), except where the
    centre lies straight off the closest face (p - c along its normal, not in the wedge of an
    edge or a corner): there the face's own plane decides. Faces tied from two parts of the
    surface (a sphere at the middle of two plates closing on it) sum opposite normals, and the
    pseudo-normal's sign was noise: a sphere between two plates was told it lay behind one and
    pushed through it. A centre in the closest face's own plane, off its boundary (h = 0 exactly,
    p != c: a sheet's rim, or a convex edge) is in front: the query's sign there is a tie that the
    colliders broke differently (a new user's sphere centred level with a sheet, 3 cm past its rim,
    was pushed off it by the swept collider and pulled 8 cm onto it by refit). Every collider takes
    its side from here."""
    h = wp.dot(p - c, face_normal)
    d2 = wp.length_sq(p - c)
    if h != 0.0 and h * h >= 0.98 * d2:
        return wp.sign(h)
    if h == 0.0 and d2 > 0.0:
        return 1.0
    return sign


@wp.func
def keeps_contact(side: float, depth: float, r: float) -> bool:
    """Whether a closest point makes a contact: on the free side (side +1), or behind the surface
    with the centre closer than r (depth = r + dist < 2 r: the sphere overlaps the surface and is
    pushed out to the front). A sphere entirely behind has none (depth >= 2 r); the rule was
    ``depth > 0 or side > 0``, which kept every sphere behind within the query's reach and pushed
    it through the surface (a new user's sphere 7 cm behind a sheet, falling away at 20 m/s, was
    moved 19 cm to the front and bounced)."""
    return side > 0.0 or depth < 2.0 * r


@wp.func
def contact_reach(r: float, v: wp.vec3, extra_speed: float, dt: float, margin: float) -> float:
    """How far a sphere looks for the surface in one step: r + margin + (|v| + extra_speed) dt.
    Every collider uses this one rule, so their contacts agree."""
    return r + margin + (wp.length(v) + extra_speed) * dt


@wp.kernel
def collide_sphere_mesh(
    # Model:
    indices: wp.array[wp.int32],
    sphere_radius: wp.array[float],
    # State in:
    points_in: wp.array[wp.vec3],
    velocities_in: wp.array[wp.vec3],
    sphere_pos_in: wp.array[wp.vec3],
    sphere_vel_in: wp.array[wp.vec3],
    # In:
    mesh: wp.uint64,
    dt: float,
    extra_speed: float,
    margin: float,
    seed: int,
    tie_distance: float,
    # Out:
    contact_face: wp.array[wp.int32],
    contact_point: wp.array[wp.vec3],
    contact_normal: wp.array[wp.vec3],
    contact_depth: wp.array[float],
    contact_velocity: wp.array[wp.vec3],
):
    """Closest-point contact of each sphere with a BVH mesh (``wp.Mesh``, refit or rebuilt).

    The query reaches radius + margin + (|v| + extra_speed) * dt, where extra_speed bounds the
    velocity gained in one step (gravity), so any surface the sphere's own motion can reach
    during the step is found (continuous contact in the integrator). ``seed`` 1: the sphere's
    previous contact face (``contact_face``, read before it is written) is evaluated first and
    the query reaches no farther than its distance + ``tie_distance`` [m] (the closest face is
    no farther, and the faces tied with it within Warp's epsilon are within that), so the tree
    walk prunes from its first node (``choices.SEED_REFIT_QUERY``).
    """
    s = wp.tid()
    p = sphere_pos_in[s]
    r = sphere_radius[s]
    reach = contact_reach(r, sphere_vel_in[s], extra_speed, dt, margin)
    face = int(-1)
    c = wp.vec3(0.0)
    n = wp.vec3(0.0)
    depth = float(0.0)
    vs = wp.vec3(0.0)
    query = reach
    if seed != 0:
        g = contact_face[s]
        if g >= 0 and g < indices.shape[0] / 3:
            ga = points_in[indices[3 * g + 0]]
            gb = points_in[indices[3 * g + 1]]
            ge = points_in[indices[3 * g + 2]]
            gw = closest_point_on_triangle(p, ga, gb, ge)
            query = wp.min(reach, wp.length(gw[0] * ga + gw[1] * gb + gw[2] * ge - p) + tie_distance)
    q = wp.mesh_query_point_sign_normal(mesh, p, query)
    if q.result:
        i0 = indices[3 * q.face + 0]
        i1 = indices[3 * q.face + 1]
        i2 = indices[3 * q.face + 2]
        a = points_in[i0]
        b = points_in[i1]
        e = points_in[i2]
        w = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)
        c = w[0] * a + w[1] * b + w[2] * e
        fn = wp.normalize(wp.cross(b - a, e - a))
        side = contact_side(p, c, fn, q.sign)
        n, depth = make_contact(p, r, c, side, fn)
        if keeps_contact(side, depth, r):
            face = q.face
            vs = w[0] * velocities_in[i0] + w[1] * velocities_in[i1] + w[2] * velocities_in[i2]
        # else: the sphere lies entirely behind the surface: no contact
    contact_face[s] = face
    contact_point[s] = c
    contact_normal[s] = n
    contact_depth[s] = depth
    contact_velocity[s] = vs
