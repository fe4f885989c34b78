"""Re-mesh a fixed-topology sequence into a DG-Mesh-like varying-topology one (evaluation data).

``remesh_sequence(seq, resolution=96, num_frames=None, noise=0.0, seed=0, device=None,
progress=False, band=2.0) -> VaryingTopologySequence``

Per frame: a signed-distance field on a regular grid (one grid for the whole sequence: the
bounding box of all frames, ``resolution`` cells along its longest side, 2 cells of padding),
then marching cubes (scikit-image) at level 0, faces oriented outward (positive signed volume).

The field is computed exactly only in a narrow band: grid points within ``band`` grid spacings
of a triangle are marked by a per-triangle kernel and get the distance to the mesh with the
sign of the generalized winding number (robust to small holes: horse_gallop has a slit in one
hoof). Every other grid point gets +-band*h, the sign taken per connected component of the
non-band region (scipy.ndimage.label) from the winding number at one of its points. Marching
cubes only looks at sign changes, which all lie inside the band, so this equals a full
signed-distance grid at a fraction of the cost.

``num_frames`` resamples time first: frame k of the output is the linear interpolation of the
input at time k * (T - 1) / (num_frames - 1). ``noise`` adds Gaussian noise of standard
deviation ``noise * h`` (h: grid spacing) to the output vertices (seeded by ``seed``).

``error`` adds a reconstruction-like error (:func:`reconstruction_error`): a spatially smooth,
slowly varying offset along the vertex normals whose RMS over each frame's vertices is
``error`` x frame 0's bounding-box diagonal (0.01 is a reconstruction's error level: the
DG-Mesh scenes' Chamfer distances correspond to ~1 %). White vertex noise is not like a
reconstruction's error, which is smooth over the surface and coherent in time.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .kernels.remesh import compute_signed_distances, mark_band_voxels
from .geometry import orient_outward
from .io import sequence_up_axis
from .sequence import FixedTopologySequence, MeshDataError, VaryingTopologySequence

__all__ = ["remesh_sequence", "resample_time", "grid_for", "remesh_frame", "reconstruction_error",
           "vertex_normals"]


def resample_time(seq: FixedTopologySequence, num_frames: int) -> np.ndarray:
    """(num_frames, N, 3) float32: linear interpolation of seq.V at num_frames evenly spaced
    times spanning the first to the last frame."""
    num_frames = int(num_frames)
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    T = seq.num_frames
    if T == 1 or num_frames == 1:
        return np.repeat(seq.V[:1], num_frames, axis=0)
    u = np.linspace(0.0, T - 1, num_frames)
    i = np.minimum(np.floor(u).astype(int), T - 2)
    a = (u - i).astype(np.float32)[:, None, None]
    return ((1 - a) * seq.V[i] + a * seq.V[i + 1]).astype(np.float32)


def grid_for(frames_V, resolution: int, pad: int = 2):
    """(origin (3,), h, dims (3,)) of the grid over the bounding box of all vertex arrays."""
    lo = np.min([v.min(axis=0) for v in frames_V], axis=0).astype(np.float64)
    hi = np.max([v.max(axis=0) for v in frames_V], axis=0).astype(np.float64)
    ext = float((hi - lo).max())
    if not ext > 0:
        raise MeshDataError("remesh: the sequence has a zero-size bounding box")
    h = ext / int(resolution)
    dims = np.ceil((hi - lo) / h).astype(int) + 1 + 2 * pad
    origin = lo - pad * h
    return origin, h, dims


#: a grid point whose signed distance is exactly 0 gets this fraction of a cell instead (outside)
ON_SURFACE_NUDGE = 1e-3


def remesh_frame(V, F, origin, h, dims, band: float = 2.0, device=None):
    """Marching-cubes re-mesh of one (V, F) on the given grid: (V' float32, F' int32), outward."""
    from scipy import ndimage
    from skimage.measure import marching_cubes

    device = wp.get_device(device)
    nx, ny, nz = (int(d) for d in dims)
    pts = wp.array(np.ascontiguousarray(V, np.float32), dtype=wp.vec3, device=device)
    idx = wp.array(np.ascontiguousarray(F, np.int32).reshape(-1), dtype=wp.int32, device=device)
    mesh = wp.Mesh(points=pts, indices=idx, support_winding_number=True)
    org = wp.vec3(*[float(x) for x in origin])
    mask_w = wp.zeros(nx * ny * nz, dtype=wp.int32, device=device)
    wp.launch(mark_band_voxels, dim=len(F), inputs=[pts, idx, org, float(h), nx, ny, nz, float(band)],
              outputs=[mask_w], device=device)
    mask = mask_w.numpy().reshape(nx, ny, nz).astype(bool)
    far = band * h
    qmax = float(10 * far + 10 * h * max(dims))

    def signed(flat_idx):
        ijk = np.stack(np.unravel_index(flat_idx, (nx, ny, nz)), axis=1)
        q = wp.array((origin + h * ijk).astype(np.float32), dtype=wp.vec3, device=device)
        out = wp.empty(len(flat_idx), dtype=float, device=device)
        if len(flat_idx):
            wp.launch(compute_signed_distances, dim=len(flat_idx), inputs=[mesh.id, q, qmax],
                      outputs=[out], device=device)
        return out.numpy()

    field = np.full((nx, ny, nz), far, np.float32)
    ii = np.flatnonzero(mask)
    band_sdf = signed(ii)
    field.reshape(-1)[ii] = np.clip(band_sdf, -far, far)
    # far region: one sign per connected component, from the band points bordering it (they
    # lie >= ~band*h/2 from the surface); a component whose border disagrees (the surface has a
    # hole wider than the band, so inside and outside connect) gets the winding number at
    # every one of its points.
    labels, nlab = ndimage.label(~mask)
    deep = np.zeros_like(mask)
    deep.reshape(-1)[ii] = np.abs(band_sdf) > 0.5 * far
    lut = np.ones(nlab + 1, np.float32)
    for k, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        sl = tuple(slice(max(a.start - 1, 0), a.stop + 1) for a in sl)
        comp = labels[sl] == k
        ring = ndimage.binary_dilation(comp) & deep[sl]
        sgn = np.sign(field[sl][ring])
        if sgn.size and (sgn < 0).all():
            lut[k] = -1.0
        elif sgn.size == 0 or (sgn > 0).all():
            lut[k] = 1.0
        else:
            lut[k] = 0.0  # mixed: evaluate each point
    fill = lut[labels] * far
    field[~mask] = fill[~mask]
    mixed = np.flatnonzero((~mask & (lut[labels] == 0.0)).reshape(-1))
    if mixed.size:
        field.reshape(-1)[mixed] = np.where(signed(mixed) < 0, -far, far)
    if field.min() >= 0 or field.max() <= 0:
        raise MeshDataError("remesh: no surface found on the grid (mesh inside-out or too thin for "
                            "the resolution?)")
    # a grid point exactly on the surface (a planar face on a grid plane: an axis-aligned box's
    # faces at the grid's edges) would put marching-cubes vertices on the grid point from every
    # cell around it, duplicates that leave non-manifold edges; count it as just outside
    field[field == 0.0] = ON_SURFACE_NUDGE * h
    verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=(h, h, h))
    verts = (verts + origin).astype(np.float32)
    faces = orient_outward(verts, faces.astype(np.int32))
    return verts, faces.astype(np.int32)


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(N, 3) float64 unit area-weighted vertex normals ((0, 0, 0) for unreferenced vertices)."""
    V = np.asarray(V, np.float64)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n = np.zeros_like(V)
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)


def reconstruction_error(frames: list, rms: float, seed: int = 0, diag: float | None = None,
                         modes: int = 24, wavelengths=(0.12, 0.5), cycles=(0.5, 2.0)) -> list:
    """Add a smooth, slowly varying error along the normals to every frame (a reconstruction's
    error, unlike white noise).

    The offset at point x of frame t (of T) is e(x, t) = sum_m c_m(t) sin(k_m . x + phi_m):
    ``modes`` plane waves with random directions, wavelengths uniform in ``wavelengths`` x
    ``diag`` and amplitudes c_m(t) = cos(2 pi w_m t / (T - 1) + psi_m) changing by w_m in
    ``cycles`` periods over the sequence; scaled per frame so that its RMS over the frame's
    vertices is ``rms`` x ``diag`` (default: frame 0's bounding-box diagonal), then applied along
    the area-weighted vertex normals. Deterministic for a given ``seed``.

    Args:
        frames: list of (V (N_t, 3), F (M_t, 3)).
    Returns:
        list of (V' float32, F) of the same frames.
    """
    if not (np.isfinite(rms) and rms >= 0):
        raise ValueError(f"error must be a finite number >= 0, got {rms}")
    if rms == 0:
        return list(frames)
    if diag is None:
        v0 = np.asarray(frames[0][0], np.float64)
        diag = float(np.linalg.norm(v0.max(axis=0) - v0.min(axis=0)))
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(modes, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    k = d * (2 * np.pi / (rng.uniform(*wavelengths, modes) * diag))[:, None]
    phi = rng.uniform(0, 2 * np.pi, modes)
    w = rng.uniform(*cycles, modes)
    psi = rng.uniform(0, 2 * np.pi, modes)
    T = len(frames)
    out = []
    for t, (V, F) in enumerate(frames):
        V = np.asarray(V, np.float64)
        c = np.cos(2 * np.pi * w * t / max(T - 1, 1) + psi)
        e = np.sin(V @ k.T + phi) @ c
        e *= rms * diag / max(float(np.sqrt(np.mean(e * e))), 1e-30)
        out.append(((V + e[:, None] * vertex_normals(V, F)).astype(np.float32), F))
    return out


def remesh_sequence(seq, resolution: int = 96, num_frames: int | None = None, noise: float = 0.0,
                    seed: int = 0, device=None, progress: bool = False, band: float = 2.0,
                    error: float = 0.0) -> VaryingTopologySequence:
    """Marching-cubes re-mesh of every frame (module docstring). ``seq`` is a
    FixedTopologySequence (a VaryingTopologySequence also works without ``num_frames``)."""
    if int(resolution) < 4:
        raise ValueError(f"resolution must be >= 4, got {resolution}")
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise must be >= 0, got {noise}")
    if band < 1.0:
        raise ValueError(f"band must be >= 1 grid spacing, got {band}")
    if not (np.isfinite(error) and error >= 0):
        raise ValueError(f"error must be a finite number >= 0, got {error}")
    if isinstance(seq, FixedTopologySequence):
        Vs = resample_time(seq, num_frames) if num_frames is not None else seq.V
        frames = [(v, seq.F) for v in Vs]
        fps = seq.fps * (len(Vs) - 1) / max(seq.num_frames - 1, 1) if num_frames and seq.num_frames > 1 else seq.fps
    elif isinstance(seq, VaryingTopologySequence):
        if num_frames is not None and num_frames != seq.num_frames:
            raise ValueError("remesh: time resampling (num_frames) needs a fixed-topology input")
        frames, fps = seq.frames, seq.fps
    else:
        raise TypeError(f"expected a FixedTopologySequence, got {type(seq).__name__}")
    origin, h, dims = grid_for([v for v, _ in frames], resolution)
    rng = np.random.default_rng(seed)
    it = range(len(frames))
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="remesh", unit="frame")
    out = []
    for t in it:
        v, f = remesh_frame(*frames[t], origin, h, dims, band=band, device=device)
        if noise > 0:
            v = (v + rng.normal(0.0, noise * h, v.shape)).astype(np.float32)
        out.append((v, f))
    if error > 0:
        v0 = np.asarray(frames[0][0], np.float64)
        out = reconstruction_error(out, error, seed=seed,
                                   diag=float(np.linalg.norm(v0.max(axis=0) - v0.min(axis=0))))
    # the up axis is carried: the new source no longer names a file that says it (a new user's
    # glTF fox, re-meshed, was read z-up and lay on its side)
    res = VaryingTopologySequence(out, fps=fps, name=f"{seq.name}_remesh{int(resolution)}",
                                  source=f"remesh({seq.source or seq.name}, resolution={int(resolution)})",
                                  up_axis=sequence_up_axis(seq))
    res.grid_spacing = float(h)
    return res
