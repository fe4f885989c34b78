"""3D Gaussian splatting as Warp kernels (issue 16; dynmesh_warp/render.py): project, bin into
16 x 16 tiles, sort by (camera, tile, depth), composite front to back per pixel.

The maths follow the reference 3DGS rasteriser as gsplat implements it: pinhole cameras in the
OpenCV/COLMAP convention (x right, y down, z forward; world-to-camera ``R``, ``t``), the EWA
Jacobian with the camera-space position clamped to 1.3 x the half field of view, a 0.3 px^2
dilation of the 2-D covariance, a 3-sigma radius, alpha = min(0.999, opacity exp(-sigma)),
Gaussians under alpha 1/255 skipped, and a pixel finished once its transmittance would fall
to 1e-4 (that Gaussian not composited). Colour from spherical harmonics up to degree 3 with the
view direction from the camera centre, + 0.5, clamped at 0. Rigid spheres are ray-cast per pixel
and composited by depth with the splats (a splat behind the nearest sphere is hidden); other
rigid shapes (Newton's boxes, capsules, cylinders, ellipsoids, meshes) are cast first by
``cast_rigid_shapes`` into an opaque layer the compositing treats the same way.
"""

from typing import Any

import warp as wp

# the compositing's exp and divisions in fast-math form (as gsplat's CUDA build): the images
# differ from exact float maths by float rounding only (tests/test_render.py: the NumPy
# reference's tolerance)
wp.set_module_options({"fast_math": True})

TILE = wp.constant(16)
#: the key of an unused entry of a fixed-capacity render (sorts after every real key): the
#: 64-bit keys' (tile << 32 | depth in micrometres) ...
EMPTY_KEY = wp.constant(wp.int64(9223372036854775807))
#: ... and the compact 32-bit keys' (tile << rank bits | depth rank), unsigned
EMPTY_KEY32 = wp.constant(wp.uint32(4294967295))
#: the compact keys' depth rank: no depth (a culled Gaussian sorts after every visible one)
NO_DEPTH = wp.constant(3.0e38)

SH_C0 = wp.constant(0.28209479177387814)
SH_C1 = wp.constant(0.4886025119029199)
SH_C2_0 = wp.constant(1.0925484305920792)
SH_C2_1 = wp.constant(-1.0925484305920792)
SH_C2_2 = wp.constant(0.31539156525252005)
SH_C2_3 = wp.constant(-1.0925484305920792)
SH_C2_4 = wp.constant(0.5462742152960396)
SH_C3_0 = wp.constant(-0.5900435899266435)
SH_C3_1 = wp.constant(2.890611442640554)
SH_C3_2 = wp.constant(-0.4570457994644658)
SH_C3_3 = wp.constant(0.3731763325901154)
SH_C3_4 = wp.constant(-0.4570457994644658)
SH_C3_5 = wp.constant(1.445305721320277)
SH_C3_6 = wp.constant(-0.5900435899266435)


@wp.func
def evaluate_sh(sh: wp.array3d[float], g: int, degree: int, d: wp.vec3) -> wp.vec3:
    """Colour of Gaussian g seen along unit direction d: SH coefficients sh[g, k, :] (k < 16, the
    3DGS order), up to ``degree``, + 0.5, clamped at 0."""
    c = SH_C0 * wp.vec3(sh[g, 0, 0], sh[g, 0, 1], sh[g, 0, 2])
    if degree > 0:
        x = d[0]
        y = d[1]
        z = d[2]
        c = c - SH_C1 * y * wp.vec3(sh[g, 1, 0], sh[g, 1, 1], sh[g, 1, 2])
        c = c + SH_C1 * z * wp.vec3(sh[g, 2, 0], sh[g, 2, 1], sh[g, 2, 2])
        c = c - SH_C1 * x * wp.vec3(sh[g, 3, 0], sh[g, 3, 1], sh[g, 3, 2])
        if degree > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            c = c + SH_C2_0 * x * y * wp.vec3(sh[g, 4, 0], sh[g, 4, 1], sh[g, 4, 2])
            c = c + SH_C2_1 * y * z * wp.vec3(sh[g, 5, 0], sh[g, 5, 1], sh[g, 5, 2])
            c = c + SH_C2_2 * (2.0 * zz - xx - yy) * wp.vec3(sh[g, 6, 0], sh[g, 6, 1], sh[g, 6, 2])
            c = c + SH_C2_3 * x * z * wp.vec3(sh[g, 7, 0], sh[g, 7, 1], sh[g, 7, 2])
            c = c + SH_C2_4 * (xx - yy) * wp.vec3(sh[g, 8, 0], sh[g, 8, 1], sh[g, 8, 2])
            if degree > 2:
                c = c + SH_C3_0 * y * (3.0 * xx - yy) * wp.vec3(sh[g, 9, 0], sh[g, 9, 1], sh[g, 9, 2])
                c = c + SH_C3_1 * x * y * z * wp.vec3(sh[g, 10, 0], sh[g, 10, 1], sh[g, 10, 2])
                c = c + SH_C3_2 * y * (4.0 * zz - xx - yy) * wp.vec3(sh[g, 11, 0], sh[g, 11, 1], sh[g, 11, 2])
                c = c + SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * wp.vec3(sh[g, 12, 0], sh[g, 12, 1], sh[g, 12, 2])
                c = c + SH_C3_4 * x * (4.0 * zz - xx - yy) * wp.vec3(sh[g, 13, 0], sh[g, 13, 1], sh[g, 13, 2])
                c = c + SH_C3_5 * z * (xx - yy) * wp.vec3(sh[g, 14, 0], sh[g, 14, 1], sh[g, 14, 2])
                c = c + SH_C3_6 * x * (xx - 3.0 * yy) * wp.vec3(sh[g, 15, 0], sh[g, 15, 1], sh[g, 15, 2])
    c = c + wp.vec3(0.5)
    return wp.vec3(wp.max(c[0], 0.0), wp.max(c[1], 0.0), wp.max(c[2], 0.0))


@wp.kernel
def project_gaussians(
    # Model:
    means: wp.array[wp.vec3],
    covariances: wp.array[wp.mat33],
    sh: wp.array3d[float],
    sh_degree: int,
    # In:
    view_rotation: wp.array[wp.mat33],
    view_translation: wp.array[wp.vec3],
    intrinsics: wp.array[wp.vec4],
    width: int,
    height: int,
    near: float,
    camera_stride: int,
    shade_ambient: float,
    # Out:
    mean2d: wp.array2d[wp.vec2],
    conic: wp.array2d[wp.vec3],
    depth: wp.array2d[float],
    radius: wp.array2d[wp.int32],
    tiles_touched: wp.array[wp.int32],
    color: wp.array2d[wp.vec3],
):
    """Screen-space footprint of Gaussian g in camera c (launch (C, G)): mean2d [px], conic (the
    inverse 2-D covariance a, b, c), depth [m] (camera z), radius [px] (0: culled), the number of
    16 x 16 tiles it touches (flat (C * G,), for the prefix sum) and its colour from SH.
    means [m] and covariances [m^2] in world: (G,), seen by every camera (camera_stride 0), or
    (C * G,) with camera c's own G at c * camera_stride (camera_stride = G: one scene per camera,
    e.g. per env); sh (G, K, 3) shared; view_rotation / view_translation (C,) world-to-camera;
    intrinsics (C,) (fx, fy, cx, cy) [px]. ``shade_ambient`` in [0, 1]: the colour times
    ambient + (1 - ambient) |n . l|, n the Gaussian's flat axis (the eigenvector of its smallest
    covariance eigenvalue: the face normal for Gaussians bound to faces, at their current pose),
    l a head light along the camera's viewing direction tilted down (so the shape reads);
    negative: unlit."""
    c, g = wp.tid()
    G = mean2d.shape[1]
    j = c * camera_stride + g
    R = view_rotation[c]
    p = R * means[j] + view_translation[c]
    radius[c, g] = 0
    tiles_touched[c * G + g] = 0
    if p[2] < near:
        return
    k = intrinsics[c]
    fx = k[0]
    fy = k[1]
    cx = k[2]
    cy = k[3]
    # EWA: clamp the position to 1.3x the half field of view, as the reference does (gsplat:
    # lim = edge / f + 0.3 tan_fov, tan_fov = 0.5 size / f; 0.3 size / f here made it 1.6x)
    tan_fovx = 0.5 * float(width) / fx
    tan_fovy = 0.5 * float(height) / fy
    lim_x_pos = (float(width) - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (float(height) - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    rz = 1.0 / p[2]
    tx = p[2] * wp.clamp(p[0] * rz, -lim_x_neg, lim_x_pos)
    ty = p[2] * wp.clamp(p[1] * rz, -lim_y_neg, lim_y_pos)
    J = wp.mat33(fx * rz, 0.0, -fx * tx * rz * rz, 0.0, fy * rz, -fy * ty * rz * rz, 0.0, 0.0, 0.0)
    cov_cam = R * covariances[j] * wp.transpose(R)
    cov = J * cov_cam * wp.transpose(J)
    a = cov[0, 0] + 0.3
    b = cov[0, 1]
    d = cov[1, 1] + 0.3
    det = a * d - b * b
    if det <= 0.0:
        return
    inv = 1.0 / det
    mid = 0.5 * (a + d)
    lam = mid + wp.sqrt(wp.max(0.1, mid * mid - det))
    r = int(wp.ceil(3.0 * wp.sqrt(lam)))
    u = fx * p[0] * rz + cx
    v = fy * p[1] * rz + cy
    # tiles of the box [u - r, u + r] x [v - r, v + r]
    tiles_x = (width + TILE - 1) / TILE
    tiles_y = (height + TILE - 1) / TILE
    x0 = wp.clamp(int(wp.floor((u - float(r)) / float(TILE))), 0, tiles_x)
    x1 = wp.clamp(int(wp.floor((u + float(r)) / float(TILE))) + 1, 0, tiles_x)
    y0 = wp.clamp(int(wp.floor((v - float(r)) / float(TILE))), 0, tiles_y)
    y1 = wp.clamp(int(wp.floor((v + float(r)) / float(TILE))) + 1, 0, tiles_y)
    n = (x1 - x0) * (y1 - y0)
    if n <= 0 or r <= 0:
        return
    mean2d[c, g] = wp.vec2(u, v)
    conic[c, g] = wp.vec3(d * inv, -b * inv, a * inv)
    depth[c, g] = p[2]
    radius[c, g] = r
    tiles_touched[c * G + g] = n
    # view direction from the camera centre (world): centre = -R^T t
    centre = -(wp.transpose(R) * view_translation[c])
    col = evaluate_sh(sh, g, sh_degree, wp.normalize(means[j] - centre))
    if shade_ambient >= 0.0:
        Q, ev = wp.eig3(covariances[j])
        m = int(0)
        if ev[1] < ev[m]:
            m = 1
        if ev[2] < ev[m]:
            m = 2
        nrm = wp.vec3(Q[0, m], Q[1, m], Q[2, m])
        light = wp.normalize(wp.vec3(R[2, 0], R[2, 1], R[2, 2] - 0.5))
        col = col * (shade_ambient + (1.0 - shade_ambient) * wp.abs(wp.dot(nrm, light)))
    color[c, g] = col


@wp.func
def store_key(keys: wp.array[wp.int64], i: int, key: wp.int64):
    """Key i of a sort (overloaded per key width: 64-bit, or compact uint32)."""
    keys[i] = key


@wp.func
def store_key(keys: wp.array[wp.uint32], i: int, key: wp.int64):  # noqa: F811 (a Warp overload)
    keys[i] = wp.uint32(key)


@wp.func
def load_key(keys: wp.array[wp.int64], i: int) -> wp.int64:
    """Key i of a sort as 64 bits (overloaded per key width)."""
    return keys[i]


@wp.func
def load_key(keys: wp.array[wp.uint32], i: int) -> wp.int64:  # noqa: F811 (a Warp overload)
    """A compact key widened (EMPTY_KEY32 -> EMPTY_KEY), so one code path reads both kinds."""
    k = keys[i]
    if k == EMPTY_KEY32:
        return EMPTY_KEY
    return wp.int64(k)


@wp.kernel
def emit_depth_keys(
    # In:
    depth: wp.array2d[float],
    radius: wp.array2d[wp.int32],
    # Out:
    depth_keys: wp.array[float],
    depth_order: wp.array[wp.int32],
):
    """The compact keys' first sort's input (launch (C, G)): each (camera, Gaussian)'s camera
    depth [m] (NO_DEPTH where culled) and its flat index c * G + g."""
    c, g = wp.tid()
    i = c * depth.shape[1] + g
    z = NO_DEPTH
    if radius[c, g] > 0:
        z = depth[c, g]
    depth_keys[i] = z
    depth_order[i] = i


@wp.kernel
def scatter_depth_rank(
    # In:
    depth_order: wp.array[wp.int32],
    # Out:
    depth_rank: wp.array[wp.int32],
):
    """depth_rank[c * G + g] = the position of (c, g) in the depth-sorted order (launch (C G,)):
    a rank orders the Gaussians of each camera by depth like the depth itself."""
    j = wp.tid()
    depth_rank[depth_order[j]] = j


@wp.kernel
def emit_tile_keys(
    # In:
    mean2d: wp.array2d[wp.vec2],
    depth: wp.array2d[float],
    radius: wp.array2d[wp.int32],
    offsets: wp.array[wp.int32],
    depth_rank: wp.array[wp.int32],
    shift: int,
    width: int,
    height: int,
    capacity: int,
    # Out:
    keys: wp.array[Any],
    values: wp.array[wp.int32],
    overflow: wp.array[wp.int32],
):
    """One (key, value) per (Gaussian, touched tile), value = the Gaussian, written from the
    exclusive prefix sum ``offsets`` of the tile counts. Launch (C, G). The key is
    (camera * tiles + tile) << ``shift`` | the depth's order: 64-bit keys (``shift`` 32, no
    ``depth_rank``): the depth in micrometres (31 bits: up to 2,147 m); compact uint32 keys:
    ``depth_rank`` (C G,) of ``scatter_depth_rank`` in the low ``shift`` bits. Entries at or
    beyond ``capacity`` are not written; overflow[0] counts them (a fixed-capacity render)."""
    c, g = wp.tid()
    r = radius[c, g]
    if r <= 0:
        return
    G = mean2d.shape[1]
    tiles_x = (width + TILE - 1) / TILE
    tiles_y = (height + TILE - 1) / TILE
    m = mean2d[c, g]
    x0 = wp.clamp(int(wp.floor((m[0] - float(r)) / float(TILE))), 0, tiles_x)
    x1 = wp.clamp(int(wp.floor((m[0] + float(r)) / float(TILE))) + 1, 0, tiles_x)
    y0 = wp.clamp(int(wp.floor((m[1] - float(r)) / float(TILE))), 0, tiles_y)
    y1 = wp.clamp(int(wp.floor((m[1] + float(r)) / float(TILE))) + 1, 0, tiles_y)
    low = wp.int64(0)
    if depth_rank.shape[0] > 0:
        low = wp.int64(depth_rank[c * G + g])
    else:
        low = wp.int64(wp.min(depth[c, g] * 1.0e6, 2147483647.0))
    i = offsets[c * G + g]
    for ty in range(y0, y1):
        for tx in range(x0, x1):
            if i < capacity:
                tile = wp.int64(c * tiles_x * tiles_y + ty * tiles_x + tx)
                store_key(keys, i, (tile << wp.int64(shift)) | low)
                values[i] = g
            else:
                wp.atomic_add(overflow, 0, 1)
            i += 1


@wp.func
def mark_tile_range(keys: wp.array[Any], i: int, key: wp.int64, shift: int, count: int,
                    tile_start: wp.array[wp.int32], tile_end: wp.array[wp.int32]):
    """Sorted key i's (``key``, already loaded) part in [tile_start, tile_end) of each (camera,
    tile): it starts its tile's run if the key before is of another tile, and ends the run before
    it (untouched tiles keep 0, 0; the tile is the key >> ``shift``). Empty keys (the unused tail
    of a fixed-capacity render, sorted last) end the list."""
    if key == EMPTY_KEY:
        if i > 0:
            prev_key = load_key(keys, i - 1)
            if prev_key != EMPTY_KEY:
                tile_end[int(prev_key >> wp.int64(shift))] = i
        return
    tile = int(key >> wp.int64(shift))
    if i == 0:
        tile_start[tile] = 0
    else:
        prev = int(load_key(keys, i - 1) >> wp.int64(shift))
        if prev != tile:
            tile_start[tile] = i
            tile_end[prev] = i
    if i == count - 1:
        tile_end[tile] = count


@wp.kernel
def gather_sorted_splats(
    # In:
    keys: wp.array[Any],
    values: wp.array[wp.int32],
    shift: int,
    count: int,
    tiles_per_camera: int,
    mean2d: wp.array2d[wp.vec2],
    conic: wp.array2d[wp.vec3],
    depth: wp.array2d[float],
    color: wp.array2d[wp.vec3],
    opacity: wp.array[float],
    # Out:
    tile_start: wp.array[wp.int32],
    tile_end: wp.array[wp.int32],
    sorted_xy_opacity_depth: wp.array[wp.vec4],
    sorted_conic: wp.array[wp.vec3],
    sorted_color: wp.array[wp.vec3],
):
    """Each tile's range of the sorted keys (``mark_tile_range``) and each sorted key's splat
    data in key order (launch (count,)): the rasteriser then reads a tile's splats as one
    contiguous run instead of through the Gaussian index: the centre [px], opacity and depth
    [m] together (what every splat's test reads), the conic, and the colour (read only for a
    splat that is composited)."""
    i = wp.tid()
    key = load_key(keys, i)
    mark_tile_range(keys, i, key, shift, count, tile_start, tile_end)
    if key == EMPTY_KEY:
        return
    c = int(key >> wp.int64(shift)) / tiles_per_camera
    g = values[i]
    m = mean2d[c, g]
    sorted_xy_opacity_depth[i] = wp.vec4(m[0], m[1], opacity[g], depth[c, g])
    sorted_conic[i] = conic[c, g]
    sorted_color[i] = color[c, g]


#: the key kernels' concrete overloads per key width (wp.int64 or wp.uint32): (emit_tile_keys,
#: gather_sorted_splats). Launching these, not the generic kernels, spares the per-launch
#: overload lookup on the host (~13 us a launch on the CPU VM)
KEY_KERNELS = {dt: tuple(wp.overload(k, {"keys": wp.array[dt]}) for k in (emit_tile_keys, gather_sorted_splats))
               for dt in (wp.int64, wp.uint32)}


@wp.func
def pixel_ray(intrinsics: wp.vec4, view_rotation: wp.mat33, view_translation: wp.vec3, px: int, py: int):
    """The ray through pixel (px, py)'s centre of a pinhole camera (OpenCV convention;
    intrinsics fx, fy, cx, cy [px]; world-to-camera R, t): (origin [m], unit direction in world,
    unit direction in the camera frame)."""
    dc = wp.normalize(wp.vec3((float(px) + 0.5 - intrinsics[2]) / intrinsics[0],
                              (float(py) + 0.5 - intrinsics[3]) / intrinsics[1], 1.0))
    o = -(wp.transpose(view_rotation) * view_translation)
    return o, wp.transpose(view_rotation) * dc, dc


#: rigid shape kinds of ``cast_rigid_shapes`` (``render.RigidShapes``); sizes [m] per kind:
#: sphere (r, -, -), box half extents, capsule / cylinder (r, half height, -) along local z,
#: ellipsoid semi-axes, mesh the scale of its vertices
SHAPE_SPHERE = wp.constant(0)
SHAPE_BOX = wp.constant(1)
SHAPE_CAPSULE = wp.constant(2)
SHAPE_CYLINDER = wp.constant(3)
SHAPE_ELLIPSOID = wp.constant(4)
SHAPE_MESH = wp.constant(5)
NO_HIT = wp.constant(1.0e30)


@wp.func
def intersect_sphere_local(o: wp.vec3, d: wp.vec3, r: float):
    """Ray o + s d (d unit) against a sphere of radius r at the origin: (s, outward normal);
    s = NO_HIT if missed or behind."""
    b = wp.dot(o, d)
    disc = b * b - (wp.dot(o, o) - r * r)
    s = float(NO_HIT)
    n = wp.vec3(0.0)
    if disc >= 0.0:
        s0 = -b - wp.sqrt(disc)
        if s0 > 0.0:
            s = s0
            n = (o + d * s0) / r
    return s, n


@wp.func
def nearest_sphere(o: wp.vec3, d: wp.vec3, centers: wp.array[wp.vec3], radii: wp.array[float], first: int,
                   count: int):
    """Ray o + s d (d unit) against spheres first .. first + count - 1: (s of the nearest hit,
    its index; -1 if none)."""
    best = float(NO_HIT)
    hit = int(-1)
    for k in range(first, first + count):
        s, n = intersect_sphere_local(o - centers[k], d, radii[k])
        if s < best:
            best = s
            hit = k
    return best, hit


@wp.func
def intersect_box_local(o: wp.vec3, d: wp.vec3, h: wp.vec3):
    """Ray o + s d against the box |x_i| <= h_i (slab test): (s of entry, the entered face's
    outward normal); NO_HIT if missed, behind, or the origin inside."""
    t0 = float(-NO_HIT)
    t1 = float(NO_HIT)
    axis = int(-1)
    sgn = float(0.0)
    ok = int(1)
    for i in range(3):
        if wp.abs(d[i]) < 1.0e-12:
            if wp.abs(o[i]) > h[i]:
                ok = 0
        else:
            inv = 1.0 / d[i]
            ta = (-h[i] - o[i]) * inv
            tb = (h[i] - o[i]) * inv
            sa = float(-1.0)
            if ta > tb:
                tmp = ta
                ta = tb
                tb = tmp
                sa = 1.0
            if ta > t0:
                t0 = ta
                axis = i
                sgn = sa
            t1 = wp.min(t1, tb)
    s = float(NO_HIT)
    n = wp.vec3(0.0)
    if ok == 1 and axis >= 0 and t0 <= t1 and t0 > 0.0:
        s = t0
        n[axis] = sgn
    return s, n


@wp.func
def intersect_cylinder_side(o: wp.vec3, d: wp.vec3, r: float, h: float):
    """Ray o + s d against the side x^2 + y^2 = r^2 of a cylinder along z, kept where |z| <= h:
    (s, outward normal); NO_HIT if missed."""
    s = float(NO_HIT)
    n = wp.vec3(0.0)
    a = d[0] * d[0] + d[1] * d[1]
    if a > 1.0e-12:
        b = o[0] * d[0] + o[1] * d[1]
        c = o[0] * o[0] + o[1] * o[1] - r * r
        disc = b * b - a * c
        if disc >= 0.0:
            t = (-b - wp.sqrt(disc)) / a
            z = o[2] + t * d[2]
            if t > 0.0 and wp.abs(z) <= h:
                s = t
                p = o + d * t
                n = wp.vec3(p[0], p[1], 0.0) / r
    return s, n


@wp.func
def intersect_capsule_local(o: wp.vec3, d: wp.vec3, r: float, h: float):
    """Ray o + s d against the capsule of radius r around the segment z in [-h, h]: (s, normal)."""
    s, n = intersect_cylinder_side(o, d, r, h)
    # the end spheres
    for k in range(2):
        cz = h * (2.0 * float(k) - 1.0)
        c0 = wp.vec3(0.0, 0.0, cz)
        t, nn = intersect_sphere_local(o - c0, d, r)
        if t < s:
            s = t
            n = nn
    return s, n


@wp.func
def intersect_cylinder_local(o: wp.vec3, d: wp.vec3, r: float, h: float):
    """Ray o + s d against the closed cylinder x^2 + y^2 <= r^2, |z| <= h: (s, normal)."""
    s, n = intersect_cylinder_side(o, d, r, h)
    if wp.abs(d[2]) > 1.0e-12:
        for k in range(2):
            cz = h * (2.0 * float(k) - 1.0)
            t = (cz - o[2]) / d[2]
            p = o + d * t
            if t > 0.0 and t < s and p[0] * p[0] + p[1] * p[1] <= r * r:
                s = t
                n = wp.vec3(0.0, 0.0, 2.0 * float(k) - 1.0)
    return s, n


@wp.kernel
def cast_rigid_shapes(
    # Model:
    shape_kind: wp.array[wp.int32],
    shape_size: wp.array[wp.vec3],
    shape_mesh: wp.array[wp.uint64],
    shape_color: wp.array[wp.vec3],
    # In:
    shape_pose: wp.array[wp.transform],
    view_rotation: wp.array[wp.mat33],
    view_translation: wp.array[wp.vec3],
    intrinsics: wp.array[wp.vec4],
    # Out:
    solid: wp.array3d[wp.vec4],
):
    """The nearest rigid shape along each pixel's ray (launch (C, H, W)), Lambert-shaded from
    the camera like the spheres: solid[c, y, x] = (r, g, b, camera z [m]) with z = NO_HIT where
    no shape is hit. Each shape is intersected in its own frame (``shape_pose``: world pose,
    position [m] + unit quaternion); sizes and kinds as the SHAPE_* constants say; a mesh shape
    by ``wp.mesh_query_ray`` on its vertices divided by its scale."""
    c, py, px = wp.tid()
    o, dw, dc = pixel_ray(intrinsics[c], view_rotation[c], view_translation[c], px, py)
    best = float(NO_HIT)
    nrm = wp.vec3(0.0)
    best_k = int(-1)
    for j in range(shape_kind.shape[0]):
        X = shape_pose[j]
        q = wp.transform_get_rotation(X)
        ol = wp.quat_rotate_inv(q, o - wp.transform_get_translation(X))
        dl = wp.quat_rotate_inv(q, dw)
        kind = shape_kind[j]
        sz = shape_size[j]
        s = float(NO_HIT)
        nl = wp.vec3(0.0)
        if kind == SHAPE_SPHERE:
            s, nl = intersect_sphere_local(ol, dl, sz[0])
        elif kind == SHAPE_BOX:
            s, nl = intersect_box_local(ol, dl, sz)
        elif kind == SHAPE_CAPSULE:
            s, nl = intersect_capsule_local(ol, dl, sz[0], sz[1])
        elif kind == SHAPE_CYLINDER:
            s, nl = intersect_cylinder_local(ol, dl, sz[0], sz[1])
        elif kind == SHAPE_ELLIPSOID:
            # the unit sphere in coordinates divided by the semi-axes; s keeps its meaning
            ou = wp.cw_div(ol, sz)
            du = wp.cw_div(dl, sz)
            a = wp.dot(du, du)
            b = wp.dot(ou, du)
            disc = b * b - a * (wp.dot(ou, ou) - 1.0)
            if disc >= 0.0:
                t = (-b - wp.sqrt(disc)) / a
                if t > 0.0:
                    s = t
                    nl = wp.normalize(wp.cw_div(ou + du * t, sz))
        elif kind == SHAPE_MESH:
            hit = wp.mesh_query_ray(shape_mesh[j], wp.cw_div(ol, sz), wp.cw_div(dl, sz), best)
            if hit.result:
                s = hit.t
                nl = wp.normalize(wp.cw_div(hit.normal, sz))
        if s < best:
            best = s
            nrm = wp.quat_rotate(q, nl)
            best_k = j
    out = wp.vec4(0.0, 0.0, 0.0, NO_HIT)
    if best_k >= 0:
        shade = 0.25 + 0.75 * wp.abs(wp.dot(wp.normalize(nrm), dw))
        col = shape_color[best_k] * shade
        out = wp.vec4(col[0], col[1], col[2], best * dc[2])
    solid[c, py, px] = out


#: splats a tile's block loads into shared memory per round (``rasterize_gaussians_shared``):
#: one per thread of the TILE x TILE block
RASTER_BATCH = wp.constant(256)


@wp.func
def occluder_at_pixel(
    c: int,
    px: int,
    py: int,
    view_rotation: wp.array[wp.mat33],
    view_translation: wp.array[wp.vec3],
    intrinsics: wp.array[wp.vec4],
    sphere_centers: wp.array[wp.vec3],
    sphere_radii: wp.array[float],
    spheres_per_camera: int,
    solid: wp.array3d[wp.vec4],
    has_solid: int,
):
    """What is opaque at pixel (px, py) of camera c: the nearest ray-cast sphere of the
    camera's range, or a rigid shape of ``solid`` nearer than it. Returns (its camera depth z
    [m], NO_HIT if none; the sphere index, -1 none, -2 a rigid shape; the ray's s at the sphere
    [m]; the ray origin and unit direction in world; the shape layer's texel)."""
    o, dw, dc = pixel_ray(intrinsics[c], view_rotation[c], view_translation[c], px, py)
    first = int(0)
    count = sphere_centers.shape[0]
    if spheres_per_camera > 0:
        first = c * spheres_per_camera
        count = spheres_per_camera
    s_hit, sk = nearest_sphere(o, dw, sphere_centers, sphere_radii, first, count)
    z_sphere = float(NO_HIT)
    if sk >= 0:
        z_sphere = s_hit * dc[2]
    # an opaque rigid shape nearer than the nearest sphere (cast_rigid_shapes) takes its place
    solid_px = wp.vec4(0.0, 0.0, 0.0, NO_HIT)
    if has_solid != 0:
        solid_px = solid[c, py, px]
        if solid_px[3] < z_sphere:
            z_sphere = solid_px[3]
            sk = -2
    return z_sphere, sk, s_hit, o, dw, solid_px


@wp.func
def splat_alpha(xy_opacity_depth: wp.vec4, conic: wp.vec3, x: float, y: float) -> float:
    """A splat's alpha at pixel centre (x, y) [px]: min(0.999, opacity exp(-sigma)), 0 where
    sigma < 0 (a degenerate conic)."""
    dx = xy_opacity_depth[0] - x
    dy = xy_opacity_depth[1] - y
    sigma = 0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy
    if sigma < 0.0:
        return 0.0
    return wp.min(0.999, xy_opacity_depth[2] * wp.exp(-sigma))


@wp.func
def write_pixel(
    c: int,
    px: int,
    py: int,
    T: float,
    acc: wp.vec3,
    acc_z: float,
    saturated: int,
    z_sphere: float,
    sk: int,
    s_hit: float,
    o: wp.vec3,
    dw: wp.vec3,
    solid_px: wp.vec4,
    sphere_centers: wp.array[wp.vec3],
    sphere_color: wp.vec3,
    background: wp.vec3,
    rgb: wp.array3d[wp.vec3],
    alpha: wp.array3d[float],
    expected_depth: wp.array3d[float],
):
    """A pixel's splats composited (transmittance T, colour and depth sums) closed by its
    opaque occluder (``occluder_at_pixel``) unless the splats saturated it, over the background;
    the colour clipped to [0, 1]."""
    if sk >= 0 and saturated != 1:  # the sphere, opaque, behind the splats composited so far
        pw = o + dw * s_hit
        nrm = wp.normalize(pw - sphere_centers[sk])
        shade = 0.25 + 0.75 * wp.max(0.0, -wp.dot(nrm, dw))
        acc = acc + sphere_color * (shade * T)
        acc_z = acc_z + z_sphere * T
        T = 0.0
    elif sk == -2 and saturated != 1:  # a rigid shape, opaque, shaded by cast_rigid_shapes
        acc = acc + wp.vec3(solid_px[0], solid_px[1], solid_px[2]) * T
        acc_z = acc_z + z_sphere * T
        T = 0.0
    # the image clipped to [0, 1] here only: a bright splat's colour (SH clamped at 0, not at 1,
    # as 3DGS) may take the composited sum above 1
    out = acc + background * T
    rgb[c, py, px] = wp.vec3(wp.clamp(out[0], 0.0, 1.0), wp.clamp(out[1], 0.0, 1.0), wp.clamp(out[2], 0.0, 1.0))
    alpha[c, py, px] = 1.0 - T
    ez = float(0.0)
    if T < 1.0:
        ez = acc_z / (1.0 - T)
    expected_depth[c, py, px] = ez


@wp.kernel
def rasterize_gaussians(
    # In:
    sorted_xy_opacity_depth: wp.array[wp.vec4],
    sorted_conic: wp.array[wp.vec3],
    sorted_color: wp.array[wp.vec3],
    tile_start: wp.array[wp.int32],
    tile_end: wp.array[wp.int32],
    view_rotation: wp.array[wp.mat33],
    view_translation: wp.array[wp.vec3],
    intrinsics: wp.array[wp.vec4],
    sphere_centers: wp.array[wp.vec3],
    sphere_radii: wp.array[float],
    spheres_per_camera: int,
    sphere_color: wp.vec3,
    solid: wp.array3d[wp.vec4],
    has_solid: int,
    background: wp.vec3,
    width: int,
    height: int,
    # Out:
    rgb: wp.array3d[wp.vec3],
    alpha: wp.array3d[float],
    expected_depth: wp.array3d[float],
):
    """Front-to-back compositing of the depth-sorted splats of each pixel's tile, one thread per
    pixel reading the splats from global memory (the CPU's rasteriser; launch
    (C, tiles_y * tiles_x * TILE * TILE) in tile-major order; the splats in key order from
    ``gather_sorted_splats``); the nearest ray-cast
    sphere, if any, is opaque at its depth (Lambert-shaded from the camera) and hides what lies
    behind it. rgb (C, H, W) in [0, 1] over ``background``; alpha = 1 - transmittance;
    expected_depth = sum(w z) / sum(w) [m] (0 where nothing). spheres_per_camera 0: every
    camera sees every sphere; S > 0: camera c sees spheres c * S .. c * S + S - 1 (per env)."""
    c, k = wp.tid()
    tiles_x = (width + TILE - 1) / TILE
    tiles_y = (height + TILE - 1) / TILE
    # tile-major pixel order: each run of TILE * TILE threads (a 256-thread block) is one tile,
    # so a warp's threads walk the same splat list (the same loads, the same trip count)
    t = k / (TILE * TILE)
    local = k - t * (TILE * TILE)
    ty = t / tiles_x
    px = (t - ty * tiles_x) * TILE + local % TILE
    py = ty * TILE + local / TILE
    if px >= width or py >= height:
        return
    tile = c * tiles_x * tiles_y + t
    x = float(px) + 0.5
    y = float(py) + 0.5
    z_sphere, sk, s_hit, o, dw, solid_px = occluder_at_pixel(c, px, py, view_rotation, view_translation, intrinsics,
                                                             sphere_centers, sphere_radii, spheres_per_camera, solid,
                                                             has_solid)
    T = float(1.0)
    acc = wp.vec3(0.0)
    acc_z = float(0.0)
    saturated = int(0)
    for i in range(tile_start[tile], tile_end[tile]):
        mo = sorted_xy_opacity_depth[i]
        zg = mo[3]
        if zg > z_sphere:
            break
        a = splat_alpha(mo, sorted_conic[i], x, y)
        if a < 1.0 / 255.0:
            continue
        next_t = T * (1.0 - a)
        if next_t <= 1.0e-4:
            saturated = 1
            break
        acc = acc + sorted_color[i] * (a * T)
        acc_z = acc_z + zg * (a * T)
        T = next_t
    write_pixel(c, px, py, T, acc, acc_z, saturated, z_sphere, sk, s_hit, o, dw, solid_px, sphere_centers,
                sphere_color, background, rgb, alpha, expected_depth)


@wp.func
def composite_tile_pixel(
    blk: int,
    local: int,
    sorted_xy_opacity_depth: wp.array[wp.vec4],
    sorted_conic: wp.array[wp.vec3],
    sorted_color: wp.array[wp.vec3],
    tile_start: wp.array[wp.int32],
    tile_end: wp.array[wp.int32],
    view_rotation: wp.array[wp.mat33],
    view_translation: wp.array[wp.vec3],
    intrinsics: wp.array[wp.vec4],
    sphere_centers: wp.array[wp.vec3],
    sphere_radii: wp.array[float],
    spheres_per_camera: int,
    sphere_color: wp.vec3,
    solid: wp.array3d[wp.vec4],
    has_solid: int,
    background: wp.vec3,
    width: int,
    height: int,
    rgb: wp.array3d[wp.vec3],
    alpha: wp.array3d[float],
    expected_depth: wp.array3d[float],
):
    """Pixel ``local`` (row-major in the tile) of tile ``blk`` (camera-major) composited from the
    tile's splats staged in shared memory RASTER_BATCH at a time; the loads and the block sum are
    collective: every thread of the block calls this the same number of times."""
    tiles_x = (width + TILE - 1) / TILE
    tiles_y = (height + TILE - 1) / TILE
    c = blk / (tiles_x * tiles_y)
    t = blk - c * (tiles_x * tiles_y)
    ty = t / tiles_x
    end = tile_end[blk]
    px = (t - ty * tiles_x) * TILE + local % TILE
    py = ty * TILE + local / TILE
    inside = px < width and py < height
    x = float(px) + 0.5
    y = float(py) + 0.5
    # only the occluder's depth stays live through the loop (fewer registers); the rest of it is
    # cast again for the pixel's last write
    z_sphere = float(NO_HIT)
    running = int(0)  # takes more splats
    if inside:
        z_sphere, _sk, _s, _o, _d, _texel = occluder_at_pixel(c, px, py, view_rotation, view_translation, intrinsics,
                                                              sphere_centers, sphere_radii, spheres_per_camera, solid,
                                                              has_solid)
        running = 1
    T = float(1.0)
    acc = wp.vec3(0.0)
    acc_z = float(0.0)
    saturated = int(0)
    b = tile_start[blk]
    while b < end:
        s_xyod = wp.tile_load(sorted_xy_opacity_depth, shape=(RASTER_BATCH,), offset=(b,), storage="shared")
        s_conic = wp.tile_load(sorted_conic, shape=(RASTER_BATCH,), offset=(b,), storage="shared")
        s_color = wp.tile_load(sorted_color, shape=(RASTER_BATCH,), offset=(b,), storage="shared")
        if running != 0:
            for j in range(wp.min(RASTER_BATCH, end - b)):
                mo = s_xyod[j]
                zg = mo[3]
                if zg > z_sphere:
                    running = 0
                    break
                a = splat_alpha(mo, s_conic[j], x, y)
                if a < 1.0 / 255.0:
                    continue
                next_t = T * (1.0 - a)
                if next_t <= 1.0e-4:
                    saturated = 1
                    running = 0
                    break
                acc = acc + s_color[j] * (a * T)
                acc_z = acc_z + zg * (a * T)
                T = next_t
        if wp.tile_sum(wp.tile(running))[0] == 0:
            break
        b = b + RASTER_BATCH
    if inside:
        z_sphere, sk, s_hit, o, dw, solid_px = occluder_at_pixel(c, px, py, view_rotation, view_translation,
                                                                 intrinsics, sphere_centers, sphere_radii,
                                                                 spheres_per_camera, solid, has_solid)
        write_pixel(c, px, py, T, acc, acc_z, saturated, z_sphere, sk, s_hit, o, dw, solid_px, sphere_centers,
                    sphere_color, background, rgb, alpha, expected_depth)


def _shared_rasteriser(walk_pixels: bool):
    """The shared-memory rasteriser's kernel: one pixel per thread (``walk_pixels`` False, CUDA,
    block_dim = TILE * TILE), or each thread walking the block's pixels in turn (True: a CPU
    block is one thread, which then composites the whole tile; the same images, for tests)."""

    @wp.kernel(module="unique", module_options={"fast_math": True})
    def rasterize_gaussians_shared(
        # In:
        sorted_xy_opacity_depth: wp.array[wp.vec4],
        sorted_conic: wp.array[wp.vec3],
        sorted_color: wp.array[wp.vec3],
        tile_start: wp.array[wp.int32],
        tile_end: wp.array[wp.int32],
        view_rotation: wp.array[wp.mat33],
        view_translation: wp.array[wp.vec3],
        intrinsics: wp.array[wp.vec4],
        sphere_centers: wp.array[wp.vec3],
        sphere_radii: wp.array[float],
        spheres_per_camera: int,
        sphere_color: wp.vec3,
        solid: wp.array3d[wp.vec4],
        has_solid: int,
        background: wp.vec3,
        width: int,
        height: int,
        # Out:
        rgb: wp.array3d[wp.vec3],
        alpha: wp.array3d[float],
        expected_depth: wp.array3d[float],
    ):
        """``rasterize_gaussians``' compositing with the tile's splats staged in shared memory
        (``wp.launch_tiled`` over (C * tiles_y * tiles_x,), a block of TILE * TILE threads, one
        per pixel of the tile): each round the block loads RASTER_BATCH sorted splats together
        (one coalesced load per thread), then every thread composites them for its pixel from
        shared memory; the block stops once no pixel of the tile takes more splats (saturated,
        or past its occluder). The same maths in the same order: the images equal
        ``rasterize_gaussians``' bit for bit (tested)."""
        blk, lane = wp.tid()
        if wp.static(walk_pixels):
            for local in range(lane, TILE * TILE, wp.block_dim()):
                composite_tile_pixel(blk, local, sorted_xy_opacity_depth, sorted_conic, sorted_color, tile_start,
                                     tile_end, view_rotation, view_translation, intrinsics, sphere_centers,
                                     sphere_radii, spheres_per_camera, sphere_color, solid, has_solid, background,
                                     width, height, rgb, alpha, expected_depth)
        else:
            composite_tile_pixel(blk, lane, sorted_xy_opacity_depth, sorted_conic, sorted_color, tile_start,
                                 tile_end, view_rotation, view_translation, intrinsics, sphere_centers, sphere_radii,
                                 spheres_per_camera, sphere_color, solid, has_solid, background, width, height, rgb,
                                 alpha, expected_depth)

    return rasterize_gaussians_shared


#: the shared-memory rasteriser per device kind (``_shared_rasteriser``): a thread per pixel on
#: CUDA; on the CPU, where a block is one thread, that thread walks the tile's pixels
RASTERIZE_SHARED = {"cuda": _shared_rasteriser(walk_pixels=False), "cpu": _shared_rasteriser(walk_pixels=True)}
