"""Independent NumPy references (vectorised brute force, float64) the tests compare the kernels
with: closest points on triangles, nearest surface points, the surface of a sequence at a time,
a height field's height, the winding number. Pure NumPy, no Warp."""

from __future__ import annotations

import math

import numpy as np


def brute_closest_points(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Closest point on each triangle (A[j],B[j],C[j]) to each point P[i]: (Q, M, 3) float64."""
    return closest_on_triangles(np.asarray(P, np.float64)[:, None, :],
                                *(np.asarray(x, np.float64)[None] for x in (A, B, C)))



def closest_on_triangles(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Closest point of triangle (A, B, C) to P, all (..., 3) broadcastable, float64.

    Written independently of the engine: minimise over the interior projection (when inside)
    and the three clamped edge projections, which covers every Voronoi region.
    """
    P, A, B, C = (np.asarray(x, np.float64) for x in (P, A, B, C))

    def seg(a, b):
        ab = b - a
        t = np.einsum("...k,...k->...", P - a, ab) / np.maximum(np.einsum("...k,...k->...", ab, ab), 1e-300)
        t = np.clip(t, 0.0, 1.0)
        return a + t[..., None] * ab

    n = np.cross(B - A, C - A)
    nn = np.einsum("...k,...k->...", n, n)
    nn_safe = np.maximum(nn, 1e-300)
    proj = P - (np.einsum("...k,...k->...", P - A, n) / nn_safe)[..., None] * n
    # inside test via signed areas of the sub-triangles
    s0 = np.einsum("...k,...k->...", np.cross(B - proj, C - proj), n)
    s1 = np.einsum("...k,...k->...", np.cross(C - proj, A - proj), n)
    s2 = np.einsum("...k,...k->...", np.cross(A - proj, B - proj), n)
    inside = (s0 >= 0) & (s1 >= 0) & (s2 >= 0) & (nn > 0)
    cands = [seg(A, B), seg(B, C), seg(C, A)]
    best = cands[0]
    bd = np.linalg.norm(P - best, axis=-1)
    for c in cands[1:]:
        d = np.linalg.norm(P - c, axis=-1)
        better = d < bd
        best = np.where(better[..., None], c, best)
        bd = np.where(better, d, bd)
    dproj = np.linalg.norm(P - proj, axis=-1)
    use = inside & (dproj < bd)
    return np.where(use[..., None], proj, best)



def brute_nearest(P: np.ndarray, V: np.ndarray, F: np.ndarray):
    """Brute-force nearest surface point over ALL triangles: (dist (Q,), face (Q,), point (Q,3))."""
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    out_d, out_f, out_p = [], [], []
    for chunk in np.array_split(np.asarray(P), max(1, len(P) // 64)):
        cp = brute_closest_points(chunk, A, B, C)
        d = np.linalg.norm(cp - np.asarray(chunk, np.float64)[:, None, :], axis=-1)
        j = d.argmin(axis=1)
        out_d.append(d[np.arange(len(chunk)), j])
        out_f.append(j)
        out_p.append(cp[np.arange(len(chunk)), j])
    return np.concatenate(out_d), np.concatenate(out_f), np.concatenate(out_p)



def surface_at(seq, t: float, mode: str = "loop") -> np.ndarray:
    """NumPy reference of the interpolated vertices at time t (loop or clamp playback)."""
    s = t * seq.fps
    k = math.floor(s)
    a = s - k
    T = seq.num_frames
    if mode == "clamp":
        k0, k1 = min(k, T - 1), min(k + 1, T - 1)
    else:
        k0, k1 = k % T, (k + 1) % T
    return seq.V[k0].astype(np.float64) * (1 - a) + seq.V[k1].astype(np.float64) * a



def grid_height(V: np.ndarray, n: int, size: float, xy: np.ndarray) -> np.ndarray:
    """Height of a grid_sheet-topology height field at points xy (K,2), from its two triangles
    per cell ((v00, v10, v11) for u >= w, (v00, v11, v01) otherwise); NaN off the sheet."""
    h = size / (n - 1)
    g = (xy + size / 2) / h
    i = np.clip(np.floor(g[:, 0]).astype(int), 0, n - 2)
    j = np.clip(np.floor(g[:, 1]).astype(int), 0, n - 2)
    u, w = g[:, 0] - i, g[:, 1] - j
    z = V[:, 2]
    z00, z10, z01, z11 = z[j * n + i], z[j * n + i + 1], z[(j + 1) * n + i], z[(j + 1) * n + i + 1]
    lower = z00 + u * (z10 - z00) + w * (z11 - z10)
    upper = z00 + w * (z01 - z00) + u * (z11 - z01)
    out = np.where(u >= w, lower, upper)
    off = (np.abs(xy) > size / 2).any(axis=1)
    return np.where(off, np.nan, out)



def winding_number(V: np.ndarray, F: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Generalised winding number of points P (Q,3) w.r.t. a closed mesh (van Oosterom-Strackee
    solid angles summed over all faces): ~1 inside an outward-oriented mesh, ~0 outside."""
    V = np.asarray(V, np.float64)
    P = np.asarray(P, np.float64)
    a, b, c = (V[F[:, i]][None] - P[:, None] for i in range(3))  # (Q, M, 3)
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    dot = lambda x, y: np.einsum("qmk,qmk->qm", x, y)  # noqa: E731
    num = dot(a, np.cross(b, c))
    den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
    return 2.0 * np.arctan2(num, den).sum(axis=1) / (4 * np.pi)



SH_C = (0.28209479177387814, 0.4886025119029199,
        (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396),
        (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435))


def sh_color(sh: np.ndarray, degree: int, d: np.ndarray) -> np.ndarray:
    """3DGS spherical-harmonics colour (the reference implementation's basis and order), + 0.5,
    clamped at 0. sh (K, 3), d (3,) unit."""
    x, y, z = d
    c = SH_C[0] * sh[0]
    if degree > 0:
        c = c - SH_C[1] * y * sh[1] + SH_C[1] * z * sh[2] - SH_C[1] * x * sh[3]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        c2 = SH_C[2]
        c = (c + c2[0] * x * y * sh[4] + c2[1] * y * z * sh[5] + c2[2] * (2 * zz - xx - yy) * sh[6]
             + c2[3] * x * z * sh[7] + c2[4] * (xx - yy) * sh[8])
        if degree > 2:
            c3 = SH_C[3]
            c = (c + c3[0] * y * (3 * xx - yy) * sh[9] + c3[1] * x * y * z * sh[10]
                 + c3[2] * y * (4 * zz - xx - yy) * sh[11] + c3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[12]
                 + c3[4] * x * (4 * zz - xx - yy) * sh[13] + c3[5] * z * (xx - yy) * sh[14]
                 + c3[6] * x * (xx - 3 * yy) * sh[15])
    return np.maximum(c + 0.5, 0.0)


def render_splats(means, covs, sh, degree, opacity, cam, spheres=None, sphere_color=(0.85, 0.25, 0.2),
                  background=(1.0, 1.0, 1.0), near=0.01, tile=16):
    """A plain NumPy 3DGS renderer with the same maths as kernels/render.py (float32 like the
    kernels): EWA projection (1.3x field-of-view clamp, 0.3 px^2 dilation, 3-sigma radius),
    Gaussians sorted per tile by depth (micrometre keys, then index), alpha = min(0.999, o e^-s),
    skip < 1/255, stop before transmittance <= 1e-4; spheres ray-cast and opaque. Returns
    (rgb (H, W, 3), alpha (H, W))."""
    f32 = np.float32
    W, H = cam.width, cam.height
    R, t = np.asarray(cam.R, f32), np.asarray(cam.t, f32)
    fx, fy, cx, cy = (f32(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
    tx_n, ty_n = (W + tile - 1) // tile, (H + tile - 1) // tile
    proj = []
    centre = -(R.T @ t)
    for g in range(len(means)):
        p = R @ means[g].astype(f32) + t
        if p[2] < near:
            continue
        rz = f32(1) / p[2]
        # 1.3x the half field of view (gsplat: + 0.3 tan_fov, tan_fov = 0.5 W / fx)
        tfx, tfy = f32(0.5) * f32(W) / fx, f32(0.5) * f32(H) / fy
        lxp, lxn = (f32(W) - cx) / fx + f32(0.3) * tfx, cx / fx + f32(0.3) * tfx
        lyp, lyn = (f32(H) - cy) / fy + f32(0.3) * tfy, cy / fy + f32(0.3) * tfy
        tx = p[2] * np.clip(p[0] * rz, -lxn, lxp)
        ty = p[2] * np.clip(p[1] * rz, -lyn, lyp)
        J = np.array([[fx * rz, 0, -fx * tx * rz * rz], [0, fy * rz, -fy * ty * rz * rz]], f32)
        cov = J @ (R @ covs[g].astype(f32) @ R.T) @ J.T
        a, b, d = cov[0, 0] + f32(0.3), cov[0, 1], cov[1, 1] + f32(0.3)
        det = a * d - b * b
        if det <= 0:
            continue
        mid = f32(0.5) * (a + d)
        r = int(np.ceil(3.0 * np.sqrt(mid + np.sqrt(max(f32(0.1), mid * mid - det)))))
        u, v = fx * p[0] * rz + cx, fy * p[1] * rz + cy
        x0, x1 = np.clip(int(np.floor((u - r) / tile)), 0, tx_n), np.clip(int(np.floor((u + r) / tile)) + 1, 0, tx_n)
        y0, y1 = np.clip(int(np.floor((v - r) / tile)), 0, ty_n), np.clip(int(np.floor((v + r) / tile)) + 1, 0, ty_n)
        if r <= 0 or (x1 - x0) * (y1 - y0) <= 0:
            continue
        dvec = means[g] - centre
        col = sh_color(np.asarray(sh[g], f32), degree, dvec / np.linalg.norm(dvec))
        proj.append((int(min(p[2] * 1e6, 2147483647.0)), g, u, v, np.array([d / det, -b / det, a / det]), p[2],
                     col, (x0, x1, y0, y1)))
    proj.sort(key=lambda e: (e[0], e[1]))
    rgb = np.zeros((H, W, 3))
    alpha = np.zeros((H, W))
    bg = np.asarray(background)
    for py in range(H):
        for px in range(W):
            tcx, tcy = px // tile, py // tile
            x, y = px + 0.5, py + 0.5
            dc = np.array([(x - cx) / fx, (y - cy) / fy, 1.0])
            dc /= np.linalg.norm(dc)
            dw = R.T.astype(np.float64) @ dc
            z_s, hit = np.inf, None
            if spheres is not None:
                for k, (sc, sr) in enumerate(zip(*spheres)):
                    oc = centre - sc
                    bb = oc @ dw
                    disc = bb * bb - (oc @ oc - sr * sr)
                    if disc >= 0:
                        s = -bb - np.sqrt(disc)
                        if 0 < s and s * dc[2] < z_s:
                            z_s, hit = s * dc[2], (k, s)
            T, acc, early = 1.0, np.zeros(3), False
            for _, g, u, v, q, z, col, (x0, x1, y0, y1) in proj:
                if not (x0 <= tcx < x1 and y0 <= tcy < y1):
                    continue
                if z > z_s:
                    break
                dx, dy = u - x, v - y
                sig = 0.5 * (q[0] * dx * dx + q[2] * dy * dy) + q[1] * dx * dy
                if sig < 0:
                    continue
                al = min(0.999, opacity[g] * np.exp(-sig))
                if al < 1 / 255:
                    continue
                if T * (1 - al) <= 1e-4:
                    early = True
                    break
                acc += col * al * T
                T *= 1 - al
            if hit is not None and not early:
                k, s = hit
                nrm = centre + dw * s - spheres[0][k]
                nrm /= np.linalg.norm(nrm)
                acc += np.asarray(sphere_color) * (0.25 + 0.75 * max(0.0, -(nrm @ dw))) * T
                T = 0.0
            rgb[py, px] = np.clip(acc + bg * T, 0.0, 1.0)  # colours clamped at 0 only; the image at 1
            alpha[py, px] = 1 - T
    return rgb, alpha


def _quat_matrix(q):
    """Rotation matrix of a unit quaternion (x, y, z, w)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, np.float64)).as_matrix()


def _sdf_local(kind, p, size):
    """Exact signed distance of the standard primitives (Inigo Quilez's forms), p (..., 3)."""
    if kind == "box":
        q = np.abs(p) - size
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
    if kind == "capsule":
        r, h = size[0], size[1]
        z = np.clip(p[..., 2], -h, h)
        return np.linalg.norm(p - np.stack([0 * z, 0 * z, z], -1), axis=-1) - r
    if kind == "cylinder":
        r, h = size[0], size[1]
        d = np.stack([np.linalg.norm(p[..., :2], axis=-1) - r, np.abs(p[..., 2]) - h], -1)
        return np.minimum(d.max(axis=-1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1)
    if kind == "sphere":
        return np.linalg.norm(p, axis=-1) - size[0]
    raise ValueError(kind)


def cast_shapes_sdf(shapes, origin, dirs, max_steps=400, eps=1e-7, far=100.0):
    """Reference ray caster by sphere tracing the exact SDFs (a method independent of the
    kernels' closed-form intersections): shapes as ``render.RigidShapes`` takes them (sphere,
    box, capsule, cylinder), rays origin (3,) + s dirs (R, 3) unit. Returns (s (R,) with inf for
    a miss, index of the shape hit (R,), world normal (R, 3) from the SDF's gradient)."""
    origin = np.asarray(origin, np.float64)
    dirs = np.asarray(dirs, np.float64)
    best = np.full(len(dirs), np.inf)
    which = np.full(len(dirs), -1)
    nrm = np.zeros((len(dirs), 3))
    for j, sh in enumerate(shapes):
        Rm, t, size = _quat_matrix(sh["pose"][3:]), np.asarray(sh["pose"][:3], np.float64), np.asarray(sh["scale"], float)
        o, d = Rm.T @ (origin - t), dirs @ Rm
        s = np.zeros(len(dirs))
        alive = np.ones(len(dirs), bool)
        hit = np.zeros(len(dirs), bool)
        for _ in range(max_steps):
            dist = _sdf_local(sh["type"], o + d * s[:, None], size)
            hit |= alive & (dist < eps)
            alive &= ~hit & (s < far)
            if not alive.any():
                break
            s = np.where(alive, s + dist, s)
        p = o + d * s[:, None]
        g = np.stack([(_sdf_local(sh["type"], p + e, size) - _sdf_local(sh["type"], p - e, size)) / 2e-6
                      for e in np.eye(3) * 1e-6], -1)
        g /= np.linalg.norm(g, axis=-1, keepdims=True) + 1e-30
        closer = hit & (s < best)
        best[closer], which[closer], nrm[closer] = s[closer], j, (g @ Rm.T)[closer]
    return best, which, nrm


def ray_cast_triangles(origin, dirs, V, F):
    """Brute-force Moller-Trumbore: the nearest hit distance s (R,) (inf for a miss) of rays
    origin (3,) + s dirs (R, 3) against every triangle V[F]."""
    o = np.asarray(origin, np.float64)
    d = np.asarray(dirs, np.float64)
    A, B, C = (np.asarray(V, np.float64)[np.asarray(F)[:, k]] for k in range(3))
    e1, e2 = B - A, C - A  # (M, 3)
    p = np.cross(d[:, None, :], e2[None])  # (R, M, 3)
    det = (p * e1[None]).sum(-1)
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = o - A  # (M, 3)
    u = (p * tv[None]).sum(-1) * inv
    q = np.cross(tv, e1)  # (M, 3)
    v = (d @ q.T) * inv
    s = (q * e2).sum(-1)[None] * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 0)
    return np.where(hit, s, np.inf).min(axis=1)
