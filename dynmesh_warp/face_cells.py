"""The cells collider, measured for issue 14 and not kept (docs/benchmarks.md, "a grid of face
clusters rebuilt every step"): face clusters' boxes at the current time listed in a uniform grid
every sub-step, and a contact query over the grid (kernels/cells.py). Its contacts equal the
refit path's (tests/test_cells.py), its per-step upkeep is a third of ``wp.Mesh.refit``'s at
10^6 vertices, but its query is 1.8-3x ``mesh_query_point``'s on the scaling table, so on an
H200 it is slower than the refit collider on every row measured (0.48-0.68x its steps/s). Not a
``Collider`` choice: ``bench/cells_probe.py`` and the tests put it into a world
(:func:`use_cells_collider`).

A cluster is a leaf of a median-split k-d tree over the faces' centroids on the first frame (each
box split across its longest edge, 2^D leaves of at most ``cluster_size`` faces): a compact patch
of the surface that stays one as it deforms (the topology is fixed). Morton order cut into runs
was tried first: on a sheet its runs jump across octree cells, the median cluster was 4x the
patch its faces cover and the largest spanned the sheet. The grid spans every frame's vertices
(the interpolated surface never leaves their box); its cell edge is ``cell_extents`` times the
median cluster's largest box edge, grown until the grid has at most ``max_cells`` cells. A
cluster's box at any blend of two frames is no larger than the larger of its boxes on the two
frames, so the number of (cluster, cell) entries a step can list is bounded from the frames
alone: the lists' capacity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .kernels.cells import (
    blend_cluster_points,
    collide_sphere_cells,
    compute_sub_bounds,
    count_cluster_cells,
    scatter_cluster_cells,
)
from .world import ColliderBase, Contacts, Model, State, StepContext

#: faces a cluster (a k-d tree's leaf) and a sub-box within it, the grid's cell edge in median
#: cluster box edges, the most cells its grid may have (the edge grows until it fits); the probe's
#: best on the 10^6-vertex rows (bench/results/cells_probe_cuda_h200_*.json)
CELLS_CLUSTER_FACES = 32
CELLS_SUB_FACES = 4
CELLS_CELL_EXTENTS = 1.0
CELLS_MAX_CELLS = 1 << 22
#: the query's order: 1 defers the sub-boxes that pass and evaluates them nearest first
CELLS_NEAREST_FIRST = 1


@dataclass(frozen=True)
class FaceCells:
    """cluster_faces (C * cluster_size,) int32 face indices (each cluster's faces, then -1);
    cluster_indices (3 * C * cluster_size,) int32 their corners as indices into the vertices in
    cluster order ``vertex_order`` (N,) (new -> original; a padding slot repeats the face before
    it); sub_size faces a sub-box (cluster_size a multiple of it); grid_origin (3,) [m],
    grid_dims (3,) int, cell [m]; capacity: the most (cluster, cell) entries any step lists."""

    cluster_faces: np.ndarray
    cluster_indices: np.ndarray
    vertex_order: np.ndarray
    cluster_size: int
    sub_size: int
    grid_origin: np.ndarray
    grid_dims: np.ndarray
    cell: float
    capacity: int

    @property
    def num_clusters(self) -> int:
        return len(self.cluster_faces) // self.cluster_size

    @property
    def num_cells(self) -> int:
        return int(np.prod(self.grid_dims))


def kd_clusters(points: np.ndarray, cluster_size: int) -> np.ndarray:
    """(C * cluster_size,) int32: the points (M, 3) in 2^D leaves of a median-split k-d tree
    (D the least with M / 2^D <= cluster_size), leaf j in slots [j * cluster_size, ...), -1 after
    its points. Level by level, every box is split across its longest edge at its middle
    position in the order (one sort a level over all boxes: key = box index + rank within it)."""
    c = np.asarray(points, np.float64)
    M, K = len(c), int(cluster_size)
    D = max(0, int(np.ceil(np.log2(M / K)))) if M > K else 0
    perm = np.arange(M)
    for level in range(D):
        n = 1 << level
        starts = (np.arange(n, dtype=np.int64) * M) // n
        sizes = np.diff(np.append(starts, M))
        seg = np.repeat(np.arange(n), sizes)
        pts = c[perm]
        lo = np.minimum.reduceat(pts, starts, axis=0)
        hi = np.maximum.reduceat(pts, starts, axis=0)
        axis = np.argmax(hi - lo, axis=1)
        coord = pts[np.arange(M), axis[seg]]
        span = np.maximum((hi - lo)[np.arange(n), axis], 1e-30)
        key = seg + np.minimum((coord - lo[seg, axis[seg]]) / span[seg], 0.999999)
        perm = perm[np.argsort(key, kind="stable")]
    P = 1 << D
    starts = (np.arange(P, dtype=np.int64) * M) // P
    leaf = np.repeat(np.arange(P), np.diff(np.append(starts, M)))
    out = np.full(P * K, -1, np.int32)
    out[leaf * K + (np.arange(M) - starts[leaf])] = perm
    return out


def cluster_extents(V: np.ndarray, F: np.ndarray, cluster_faces: np.ndarray, cluster_size: int) -> np.ndarray:
    """(C, 3) the largest box edge of each cluster over the frames V (T, N, 3) [m], per axis."""
    C = len(cluster_faces) // cluster_size
    faces = cluster_faces.reshape(C, cluster_size)
    filled = np.where(faces >= 0, faces, faces[:, :1])  # padding repeats the cluster's first face
    ext = np.zeros((C, 3), np.float64)
    for Vt in V:
        tri = Vt[F[filled]]  # (C, K, 3 vertices, 3)
        lo = tri.min(axis=(1, 2))
        hi = tri.max(axis=(1, 2))
        np.maximum(ext, hi - lo, out=ext)
    return ext


def cluster_vertex_order(F: np.ndarray, cluster_faces: np.ndarray, num_vertices: int):
    """Vertices in the order the clusters first use them (then any no face uses): (order (N,)
    int32 new -> original, cluster_indices (3 * len(cluster_faces),) int32 the slots' corners
    renumbered; a padding slot repeats the face before it, its cluster's last)."""
    slot = np.arange(len(cluster_faces))
    real = np.maximum.accumulate(np.where(cluster_faces >= 0, slot, 0))  # padding -> the real slot before it
    corners = F[cluster_faces[real]].reshape(-1)
    _, first = np.unique(corners, return_index=True)
    used = corners[np.sort(first)]
    order = np.concatenate([used, np.setdiff1d(np.arange(num_vertices), used)])
    inverse = np.empty(num_vertices, np.int64)
    inverse[order] = np.arange(num_vertices)
    return order.astype(np.int32), inverse[corners].astype(np.int32)


def build_face_cells(V: np.ndarray, F: np.ndarray, cluster_size: int, cell_extents: float,
                     max_cells: int, sub_size: int = 4) -> FaceCells:
    """The clusters and grid of a fixed-topology surface: frames V (T, N, 3) [m], faces F (M, 3)."""
    V = np.asarray(V, np.float32)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    K, B = int(cluster_size), int(sub_size)
    if K < 2 or len(F) == 0 or B < 1 or K % B:
        raise ValueError(f"build_face_cells: cluster_size {K}, sub_size {B} and {len(F)} faces: need K >= 2 a "
                         "multiple of sub_size >= 1, and >= 1 face")
    cluster_faces = kd_clusters(V[0][F].mean(axis=1), K)
    order, cluster_indices = cluster_vertex_order(F, cluster_faces, V.shape[1])
    ext = cluster_extents(V, F, cluster_faces, K)
    lo = V.reshape(-1, 3).min(axis=0).astype(np.float64)
    hi = V.reshape(-1, 3).max(axis=0).astype(np.float64)
    span = np.maximum(hi - lo, 1e-9)
    cell = float(cell_extents) * float(np.median(ext.max(axis=1)))
    cell = max(cell, float(span.max()) * 1e-6, 1e-9)
    while True:
        # the origin half a cell below the lowest vertex (float rounding at the box's faces stays
        # inside), so the grid spans span + cell
        dims = np.floor((span + cell) / cell).astype(np.int64) + 1
        if int(np.prod(dims)) <= max_cells:
            break
        cell *= (float(np.prod(dims)) / max_cells) ** (1.0 / 3.0) * 1.01
    origin = lo - 0.5 * cell
    # a box of edge e overlaps at most floor(e / cell) + 2 cells an axis (and never more than the grid's)
    per_axis = np.minimum(np.floor(ext / cell).astype(np.int64) + 2, dims[None, :])
    capacity = int(np.prod(per_axis, axis=1).sum())
    if int(np.prod(dims)) > 2**31 - 1 or capacity > 2**31 - 1:
        raise ValueError(f"build_face_cells: {int(np.prod(dims))} cells / {capacity} entries exceed int32")
    return FaceCells(cluster_faces, cluster_indices, order, K, B, origin.astype(np.float32), dims.astype(np.int32),
                     cell, capacity)


class CellsCollider(ColliderBase):
    """Fixed topology: the faces in clusters of at most ``CELLS_CLUSTER_FACES`` (k-d tree leaves,
    fixed at start), and every sub-step each cluster's box at the current blend listed in every
    cell of a uniform grid it overlaps; each sphere then walks the clusters of its query box's
    cells, evaluating the interpolated triangles itself (kernels/cells.py). Its upkeep is one
    pass over the vertices, one over the faces and a counting sort of the clusters a step, no
    BVH; its query meets the clusters at the step's own time, so the surface's motion between
    frames does not widen it (the swept boxes' cost on a surface that moves more than a triangle
    a step). Contacts equal the refit path's (the same rule). Put into a world with
    :func:`use_cells_collider`."""

    name = "cells"
    capturable = True
    needs_points = False

    def __init__(self, model: Model, state: State, ctx: StepContext):
        surf = model.surface
        d = ctx.device
        cells = build_face_cells(surf.sequence.V, surf.faces(), CELLS_CLUSTER_FACES, CELLS_CELL_EXTENTS,
                                 CELLS_MAX_CELLS, CELLS_SUB_FACES)
        self.cells = cells
        self.cluster_faces = wp.array(cells.cluster_faces, dtype=wp.int32, device=d)
        self.cluster_indices = wp.array(cells.cluster_indices, dtype=wp.int32, device=d)
        self.vertex_order = wp.array(cells.vertex_order, dtype=wp.int32, device=d)
        C, G = cells.num_clusters, cells.num_cells
        self.cluster_points = wp.zeros(surf.num_vertices, dtype=wp.vec3, device=d)
        self.sub_lower = wp.zeros(C * (cells.cluster_size // cells.sub_size), dtype=wp.vec3, device=d)
        self.sub_upper = wp.zeros_like(self.sub_lower)
        self.cluster_lower = wp.zeros(C, dtype=wp.vec3, device=d)
        self.cluster_upper = wp.zeros(C, dtype=wp.vec3, device=d)
        self.cell_count = wp.zeros(G, dtype=wp.int32, device=d)
        self.cell_start = wp.zeros(G, dtype=wp.int32, device=d)
        self.cell_fill = wp.zeros(G, dtype=wp.int32, device=d)
        self.cell_clusters = wp.zeros(max(cells.capacity, 1), dtype=wp.int32, device=d)
        self.grid = [wp.vec3(*cells.grid_origin.tolist()), wp.vec3i(*cells.grid_dims.tolist()), 1.0 / cells.cell]
        # tie tolerance of the closest-feature search, as wp.Mesh and the swept collider
        self.epsilon = 1.0e-3 * float(surf.average_edge_length.mean())
        self.nearest_first = int(CELLS_NEAREST_FIRST)

    def update(self, model: Model, state: State, ctx: StepContext):
        """The vertices, the sub-boxes' and clusters' boxes at the current time and the grid's
        cell lists (every sub-step): ``blend``, ``bound``, ``sort``."""
        self.blend(model, state, ctx)
        self.bound(model, state, ctx)
        self.sort(model, state, ctx)

    def blend(self, model: Model, state: State, ctx: StepContext):
        surf = model.surface
        ctx.launch(blend_cluster_points, surf.num_vertices,
                   [surf.frames, self.vertex_order, state.sim_time, surf.fps, surf.playback, int(surf.interpolate)],
                   [self.cluster_points])

    def bound(self, model: Model, state: State, ctx: StepContext):
        cl = self.cells
        ctx.launch(compute_sub_bounds, cl.num_clusters * (cl.cluster_size // cl.sub_size),
                   [self.cluster_faces, self.cluster_indices, self.cluster_points, cl.sub_size],
                   [self.sub_lower, self.sub_upper])

    def sort(self, model: Model, state: State, ctx: StepContext):
        cl = self.cells
        C = cl.num_clusters
        self.cell_count.zero_()
        self.cell_fill.zero_()
        ctx.launch(count_cluster_cells, C, [self.sub_lower, self.sub_upper, cl.cluster_size // cl.sub_size, *self.grid],
                   [self.cluster_lower, self.cluster_upper, self.cell_count])
        wp.utils.array_scan(self.cell_count, self.cell_start, inclusive=False)
        ctx.launch(scatter_cluster_cells, C, [self.cluster_lower, self.cluster_upper, *self.grid, self.cell_start],
                   [self.cell_fill, self.cell_clusters])

    def collide(self, model: Model, state: State, contacts: Contacts, ctx: StepContext):
        m, s, c = model, state, contacts
        surf = m.surface
        ctx.launch(collide_sphere_cells, m.spheres.count,
                   [surf.frames, surf.indices, m.spheres.radius, self.cluster_faces, self.cluster_indices,
                    s.sim_time, s.sphere_pos, s.sphere_vel,
                    self.cluster_points, self.sub_lower, self.sub_upper, self.cluster_lower, self.cluster_upper,
                    self.cell_count, self.cell_start, self.cell_clusters, *self.grid, self.cells.cluster_size,
                    self.cells.sub_size, self.nearest_first, surf.fps, surf.playback, int(surf.interpolate),
                    self.epsilon, ctx.sub_dt, ctx.extra_speed, m.params.margin],
                   [c.face, c.point, c.normal, c.depth, c.velocity])



def use_cells_collider(world):
    """Replace the collider of ``world`` (a fixed-topology world, before its first step) with a
    :class:`CellsCollider`; the vertex buffer and normals are then kept only when asked
    (``render_state``), as for the swept collider. Returns the world."""
    if world.graph_captured:
        raise ValueError("use_cells_collider: the world has captured its step already; call it before the first step")
    if world.model.surface.topology != "fixed":
        raise ValueError(f"use_cells_collider: a {world.model.surface.topology}-topology surface; the cells collider "
                         "plays one fixed topology (convert the sequence first)")
    world.collider = CellsCollider(world.model, world.state, world.ctx)
    world.render_state = False
    return world
