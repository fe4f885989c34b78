"""Stage 5: 3D Gaussians bound to the faces of the physics mesh (rendering representation).

Each Gaussian g belongs to a face f with barycentric weights b (of the face's vertices i0, i1,
i2), an offset along the face normal, and a rotation and scale expressed in the face frame:

    e1 = normalize(p1 - p0),  e3 = normalize((p1 - p0) x (p2 - p0)),  e2 = e3 x e1
    R_f = [e1 e2 e3] (columns),  s_f = sqrt(area_f)
    centre   = b0 p0 + b1 p1 + b2 p2 + (offset * s_f) e3
    rotation = R_f * R_local,   scale = s_f * scale_local
    cov      = R diag(scale^2) R^T

so a Gaussian follows any rigid or similarity (uniform scale) motion of its face exactly.
Quaternions here are Warp's ``wp.quat`` = (x, y, z, w).
"""

import warp as wp

from .frames import frame_pair


@wp.func
def face_frame_rotation(p0: wp.vec3, p1: wp.vec3, p2: wp.vec3) -> wp.mat33:
    """Rotation whose columns are the face frame (e1, e2, e3); identity for a degenerate face."""
    a = p1 - p0
    n = wp.cross(a, p2 - p0)
    la = wp.length(a)
    ln = wp.length(n)
    if la <= 0.0 or ln <= 0.0:
        return wp.identity(n=3, dtype=float)
    e1 = a / la
    e3 = n / ln
    e2 = wp.cross(e3, e1)
    return wp.matrix_from_cols(e1, e2, e3)


@wp.func
def face_frame_scale(p0: wp.vec3, p1: wp.vec3, p2: wp.vec3) -> float:
    """Length scale of a face: sqrt(area) [m]."""
    return wp.sqrt(0.5 * wp.length(wp.cross(p1 - p0, p2 - p0)))


@wp.func
def gaussian_on_face(p0: wp.vec3, p1: wp.vec3, p2: wp.vec3, b: wp.vec3, offset: float, local_rotation: wp.quat,
                     local_scale: wp.vec3):
    """One bound Gaussian on the face (p0, p1, p2) [m]: (centre [m], world rotation, std devs [m],
    covariance [m^2]) from its barycentric weights, normal offset and face-frame rotation and
    scales (see ``update_gaussians``)."""
    rf = face_frame_rotation(p0, p1, p2)
    sf = face_frame_scale(p0, p1, p2)
    e3 = wp.vec3(rf[0, 2], rf[1, 2], rf[2, 2])
    center = b[0] * p0 + b[1] * p1 + b[2] * p2 + (offset * sf) * e3
    q = wp.normalize(wp.quat_from_matrix(rf) * local_rotation)
    s = local_scale * sf
    r = wp.quat_to_matrix(q)
    d = wp.diag(wp.vec3(s[0] * s[0], s[1] * s[1], s[2] * s[2]))
    return center, q, s, r * d * wp.transpose(r)


@wp.kernel
def update_gaussians(
    # In:
    points: wp.array[wp.vec3],
    indices: wp.array[wp.int32],
    face: wp.array[wp.int32],
    bary: wp.array[wp.vec3],
    offset: wp.array[float],
    local_rotation: wp.array[wp.quat],
    local_scale: wp.array[wp.vec3],
    # Out:
    centers: wp.array[wp.vec3],
    rotations: wp.array[wp.quat],
    scales: wp.array[wp.vec3],
    covariances: wp.array[wp.mat33],
):
    """World centre, rotation, scale and covariance of each Gaussian from the current vertices.

    points (N,) current vertices [m]; indices (3M,) flat triangles; face (G,) int32 in [0, M);
    bary (G,) weights of the face's vertices; offset (G,) along the normal [face scales];
    local_rotation (G,) unit quat in the face frame; local_scale (G,) std devs [face scales].
    centers (G,) [m]; rotations (G,) unit quat (world); scales (G,) std devs [m];
    covariances (G,) R diag(scale^2) R^T [m^2].
    """
    g = wp.tid()
    f = face[g]
    p0 = points[indices[3 * f + 0]]
    p1 = points[indices[3 * f + 1]]
    p2 = points[indices[3 * f + 2]]
    center, q, s, cov = gaussian_on_face(p0, p1, p2, bary[g], offset[g], local_rotation[g], local_scale[g])
    centers[g] = center
    rotations[g] = q
    scales[g] = s
    covariances[g] = cov


@wp.kernel
def update_env_gaussians(
    # Model:
    frames: wp.array2d[wp.vec3],
    indices: wp.array[wp.int32],
    fps: wp.float64,
    interpolate: int,
    # State in:
    env_time_in: wp.array[wp.float64],
    env_playback_in: wp.array[wp.int32],
    # In:
    face: wp.array[wp.int32],
    bary: wp.array[wp.vec3],
    offset: wp.array[float],
    local_rotation: wp.array[wp.quat],
    local_scale: wp.array[wp.vec3],
    # Out:
    centers: wp.array[wp.vec3],
    covariances: wp.array[wp.mat33],
):
    """Gaussian g of env e on the surface at that env's own time (launch (E, G)): the face's
    three vertices blended from frames k and k+1 of ``frames`` (T, N) [m] at env_time_in[e]
    [s] with its playback mode, exactly as ``update_frame_vertices`` does for one clock, then
    ``gaussian_on_face``. centers / covariances (E * G,) [m] / [m^2], env-major."""
    e, g = wp.tid()
    G = face.shape[0]
    k0, k1, alpha = frame_pair(env_time_in[e], fps, frames.shape[0], env_playback_in[e])
    if interpolate == 0:
        alpha = 0.0
    f = face[g]
    i0 = indices[3 * f + 0]
    i1 = indices[3 * f + 1]
    i2 = indices[3 * f + 2]
    p0 = frames[k0, i0] + alpha * (frames[k1, i0] - frames[k0, i0])
    p1 = frames[k0, i1] + alpha * (frames[k1, i1] - frames[k0, i1])
    p2 = frames[k0, i2] + alpha * (frames[k1, i2] - frames[k0, i2])
    center, q, s, cov = gaussian_on_face(p0, p1, p2, bary[g], offset[g], local_rotation[g], local_scale[g])
    centers[e * G + g] = center
    covariances[e * G + g] = cov


@wp.kernel
def bind_gaussians_to_faces(
    # In:
    points: wp.array[wp.vec3],
    indices: wp.array[wp.int32],
    face: wp.array[wp.int32],
    centers: wp.array[wp.vec3],
    rotations: wp.array[wp.quat],
    scales: wp.array[wp.vec3],
    # Out:
    bary: wp.array[wp.vec3],
    offset: wp.array[float],
    local_rotation: wp.array[wp.quat],
    local_scale: wp.array[wp.vec3],
):
    """Express world Gaussians in the frame of their (already chosen, nearest) face.

    points (N,) rest vertices [m]; indices (3M,); face (G,) int32 in [0, M); centers (G,) [m];
    rotations (G,) quat (world, normalized here); scales (G,) std devs [m].
    bary (G,): weights of the centre's orthogonal projection onto the face's plane (they may
    leave [0, 1] slightly for centres nearest an edge, so the rest pose is reproduced exactly);
    offset (G,) signed normal distance [face scales]; local_rotation (G,) quat in the face
    frame; local_scale (G,) [face scales]. A degenerate face (zero area) gets offset 0,
    bary (1, 0, 0) and the world scale unchanged.
    """
    g = wp.tid()
    f = face[g]
    p0 = points[indices[3 * f + 0]]
    p1 = points[indices[3 * f + 1]]
    p2 = points[indices[3 * f + 2]]
    rf = face_frame_rotation(p0, p1, p2)
    sf = face_frame_scale(p0, p1, p2)
    c = centers[g]
    qf = wp.quat_from_matrix(rf)
    local_rotation[g] = wp.normalize(wp.quat_inverse(qf) * wp.normalize(rotations[g]))
    if sf <= 0.0:
        bary[g] = wp.vec3(1.0, 0.0, 0.0)
        offset[g] = 0.0
        local_scale[g] = scales[g]
        return
    e3 = wp.vec3(rf[0, 2], rf[1, 2], rf[2, 2])
    h = wp.dot(c - p0, e3)
    q = c - h * e3
    v0 = p1 - p0
    v1 = p2 - p0
    v2 = q - p0
    d00 = wp.dot(v0, v0)
    d01 = wp.dot(v0, v1)
    d11 = wp.dot(v1, v1)
    d20 = wp.dot(v2, v0)
    d21 = wp.dot(v2, v1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary[g] = wp.vec3(1.0 - v - w, v, w)
    offset[g] = h / sf
    local_scale[g] = scales[g] / sf


#: the largest std dev [m] the viewer's float16 covariance holds (255^2 = 65,025 < 65,504, float16's
#: largest; the off-diagonal terms are at most the largest variance)
F16_MAX_STD = wp.constant(255.0)


@wp.kernel
def pack_splat_covariances(
    # In:
    rotations: wp.array[wp.quat],
    scales: wp.array[wp.vec3],
    min_scale: float,
    min_ratio: float,
    # Out:
    cov_triu: wp.array2d[wp.float16],
):
    """Upper-triangle covariance (xx, xy, xz, yy, yz, zz) in float16 for the viewer, with each
    std dev clamped to >= max(min_scale, min_ratio * largest std dev) so thin Gaussians keep a
    positive-definite covariance after float16 rounding, and to <= ``F16_MAX_STD`` [m] so it stays
    within float16's range (65,504; a new user's 300 m background splat was sent as inf).

    rotations (G,) unit quat; scales (G,) std devs [m]; min_scale [m]; min_ratio (unitless);
    cov_triu (G, 6) float16 [m^2].
    """
    g = wp.tid()
    s = scales[g]
    s0 = wp.abs(s[0])
    s1 = wp.abs(s[1])
    s2 = wp.abs(s[2])
    lo = wp.max(min_scale, min_ratio * wp.max(s0, wp.max(s1, s2)))
    s0 = wp.min(wp.max(s0, lo), F16_MAX_STD)
    s1 = wp.min(wp.max(s1, lo), F16_MAX_STD)
    s2 = wp.min(wp.max(s2, lo), F16_MAX_STD)
    r = wp.quat_to_matrix(rotations[g])
    c = r * wp.diag(wp.vec3(s0 * s0, s1 * s1, s2 * s2)) * wp.transpose(r)
    cov_triu[g, 0] = wp.float16(c[0, 0])
    cov_triu[g, 1] = wp.float16(c[0, 1])
    cov_triu[g, 2] = wp.float16(c[0, 2])
    cov_triu[g, 3] = wp.float16(c[1, 1])
    cov_triu[g, 4] = wp.float16(c[1, 2])
    cov_triu[g, 5] = wp.float16(c[2, 2])
