"""Stage 0 (evaluation data): inside/outside fields on a grid for re-meshing by marching cubes.

Grid convention: voxel (i, j, k) of a grid with dims (nx, ny, nz) sits at
origin + h * (i, j, k) and has flat index (i * ny + j) * nz + k (C order, like NumPy).
"""

import warp as wp

from .geometry import closest_point_on_triangle


@wp.kernel
def mark_band_voxels(
    # In:
    points: wp.array[wp.vec3],
    indices: wp.array[wp.int32],
    origin: wp.vec3,
    h: float,
    nx: int,
    ny: int,
    nz: int,
    band: float,
    # Out:
    mask: wp.array[wp.int32],
):
    """Mark every grid point within ``band`` (in grid spacings) of each triangle.

    points (N,) [m]; indices (3M,) flat triangles; origin [m], h [m] grid spacing;
    mask (nx*ny*nz,) set to 1 near the surface (zero it first; concurrent writes all write 1).
    """
    f = wp.tid()
    a = points[indices[3 * f + 0]]
    b = points[indices[3 * f + 1]]
    c = points[indices[3 * f + 2]]
    r = band * h
    lo = (wp.min(wp.min(a, b), c) - origin) / h
    hi = (wp.max(wp.max(a, b), c) - origin) / h
    i0 = wp.max(int(wp.floor(lo[0] - band)), 0)
    j0 = wp.max(int(wp.floor(lo[1] - band)), 0)
    k0 = wp.max(int(wp.floor(lo[2] - band)), 0)
    i1 = wp.min(int(wp.ceil(hi[0] + band)), nx - 1)
    j1 = wp.min(int(wp.ceil(hi[1] + band)), ny - 1)
    k1 = wp.min(int(wp.ceil(hi[2] + band)), nz - 1)
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            for k in range(k0, k1 + 1):
                p = origin + h * wp.vec3(float(i), float(j), float(k))
                w = closest_point_on_triangle(p, a, b, c)
                q = w[0] * a + w[1] * b + w[2] * c
                if wp.length(p - q) <= r:
                    mask[(i * ny + j) * nz + k] = 1


@wp.kernel
def compute_signed_distances(
    # In:
    mesh: wp.uint64,
    queries: wp.array[wp.vec3],
    max_dist: float,
    # Out:
    sdf: wp.array[float],
):
    """Signed distance to a mesh, negative inside, with the sign from the generalized winding
    number (robust for meshes with small holes or slits). The mesh must be built with
    ``support_winding_number=True``. queries (Q,) [m]; sdf (Q,) [m], +-max_dist when the
    surface is farther than max_dist."""
    i = wp.tid()
    p = queries[i]
    q = wp.mesh_query_point_sign_winding_number(mesh, p, max_dist, 2.0, 0.5)
    if q.result:
        c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        sdf[i] = q.sign * wp.length(p - c)
    else:
        sdf[i] = q.sign * max_dist
