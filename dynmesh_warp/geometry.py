"""Host geometry of one triangle mesh shared by every module (NumPy, float64): face areas, the
signed volume and the one orientation rule. Bottom layer: imports nothing from the package."""

from __future__ import annotations

import numpy as np

__all__ = ["bbox_diagonal", "face_areas", "surface_area", "signed_volume", "orient_outward", "mesh_orientation", "orient_faces",
           "winding_inconsistent",
           "distinct_faces", "flat_faces", "has_area", "weld_vertices", "motion_groups", "fit_group_motions", "rotation_to_wxyz",
           "up_from_gravity", "frame_across", "face_rim_flags"]


def bbox_diagonal(V) -> float:
    """The length of the bounding box's diagonal of points V (N, 3) [units of V]; 0 for none: the
    scale the conversion's thresholds and ``evaluate``'s units note are read against."""
    if not len(V):
        return 0.0
    # per coordinate over a transposed copy: the same numbers as V.max(axis=0) - V.min(axis=0),
    # 30x faster (NumPy reduces an (N, 3) array's axis 0 with strided steps; convert asks this of
    # every frame, ~1,300 times for 200 frames: 0.7 s of the GPU conversion's 9 s)
    C = np.ascontiguousarray(np.asarray(V).reshape(-1, 3).T)
    return float(np.linalg.norm(C.max(axis=1) - C.min(axis=1)))


def face_areas(V, F) -> np.ndarray:
    """(M,) area of each triangle of (V (N, 3), F (M, 3)) [units of V squared]."""
    (x, y, z), (i, j, k) = _columns(V, F)
    # the cross product by components, gathered per coordinate: the same numbers as np.cross and
    # the norm, 3x faster (convert takes every frame's area to choose its key frame)
    ex, ey, ez = x[j] - x[i], y[j] - y[i], z[j] - z[i]
    gx, gy, gz = x[k] - x[i], y[k] - y[i], z[k] - z[i]
    cx = ey * gz - ez * gy
    cy = ez * gx - ex * gz
    cz = ex * gy - ey * gx
    return 0.5 * np.sqrt(cx * cx + cy * cy + cz * cz)


def _columns(V, F) -> tuple:
    """((x, y, z), (i, j, k)): the coordinates of V (N, 3) as three contiguous float64 columns and
    the faces F (M, 3) as three contiguous index columns (gathers per coordinate are several times
    faster than gathers of (N, 3) rows)."""
    C = np.ascontiguousarray(np.asarray(V, np.float64).reshape(-1, 3).T)
    G = np.ascontiguousarray(np.asarray(F).reshape(-1, 3).T)
    return (C[0], C[1], C[2]), (G[0], G[1], G[2])


def surface_area(V, F) -> float:
    """Total area of the mesh."""
    return float(face_areas(V, F).sum())


def signed_volume(V, F) -> float:
    """Volume enclosed by the triangles, positive when they face outward (divergence theorem),
    taken about the vertex centroid so that a small hole biases it little."""
    (x, y, z), (i, j, k) = _columns(V, F)
    used = np.zeros(len(x), bool)  # a mask, not np.unique: convert asks this of every input frame
    used[i], used[j], used[k] = True, True, True
    x, y, z = (c - c[used].mean() for c in (x, y, z))
    # a . (b x c) per face by coordinates (convert asks this of every input frame: 4x faster than
    # rows and np.cross)
    ax, ay, az, bx, by, bz, cx, cy, cz = x[i], y[i], z[i], x[j], y[j], z[j], x[k], y[k], z[k]
    return float((ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)).sum() / 6.0)


def winding_numbers(V, F, P) -> np.ndarray:
    """(Q,) the generalised winding number of the triangle mesh (V, F) around each point of P
    (Q, 3): the solid angles of its faces seen from the point over 4 pi (Van Oosterom and
    Strackee's formula), about +1 inside a closed surface wound outward, -1 wound inward, 0
    outside. float64, O(Q x faces) on the host."""
    tri = np.asarray(V, np.float64)[np.asarray(F).reshape(-1, 3)]
    out = np.empty(len(P))
    for i, p in enumerate(np.asarray(P, np.float64).reshape(-1, 3)):
        a, b, c = (tri[:, k] - p for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la \
            + np.einsum("ij,ij->i", c, a) * lb
        out[i] = 2.0 * np.arctan2(num, den).sum() / (4.0 * np.pi)
    return out


def points_inside(V, F, P, closed: bool | None = None) -> np.ndarray:
    """Indices of the points P (Q, 3) behind the faces of the mesh (V, F) where it is closed:
    winding number > 1/2 with the faces as they are wound (inside a surface facing outward; a
    surface facing inward, a room or a tunnel, has its inside in front of its faces, where
    contacts hold a body: a new user's sphere in a room kept with ``orientation: keep`` was
    refused, though the physics held it on the floor). ``closed``: whether the whole mesh is, when
    already known; None: decided piece by piece (connected pieces, :func:`mesh_orientation`); none
    inside an open piece, whose inside is not defined."""
    P = np.asarray(P, np.float64).reshape(-1, 3)
    if not len(P) or closed is False:
        return np.zeros(0, np.int64)
    if closed:
        return np.flatnonzero(winding_numbers(V, F, P) > 0.5)
    # piece by piece: an outward crate in an inward room, a rock on a ground sheet (their winding
    # numbers add up to 0, or the sheet leaves the whole open: spheres inside the crate or the
    # rock fell through, unrefused; found by a new user)
    F = np.asarray(F)
    inside = np.zeros(len(P), bool)
    n, label = _face_pieces(V, F)
    V = np.asarray(V)
    for k in range(n):
        # the piece on its own vertices (mesh_orientation welds what it is given: the whole
        # vertex array again for every piece otherwise)
        used, Fk = np.unique(F[label == k], return_inverse=True)
        Vk, Fk = V[used], Fk.reshape(-1, 3)
        if mesh_orientation(Vk, Fk) in ("outward", "inward"):
            inside |= winding_numbers(Vk, Fk, P) > 0.5
    return np.flatnonzero(inside)


def _face_pieces(V, F) -> tuple:
    """``(n, label (M,))``: the faces' connected pieces (sharing a vertex position)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    W = np.asarray(weld_vertices(V, F)[1], np.int64)
    if not len(W):
        return 0, np.zeros(0, np.int64)
    M, nv = len(W), int(W.max()) + 1
    g = coo_matrix((np.ones(3 * M, np.int8), (np.repeat(np.arange(M), 3), M + W.reshape(-1))), shape=(M + nv, M + nv))
    n, lab = connected_components(g, directed=False)
    face_lab = lab[:M]
    _, face_lab = np.unique(face_lab, return_inverse=True)
    return int(face_lab.max()) + 1, face_lab.reshape(-1)


def orient_outward(V, F) -> np.ndarray:
    """``F``, with every face flipped when the signed volume is negative (a closed mesh whose
    triangles face inward); the same rule as :func:`mesh_orientation`."""
    return np.ascontiguousarray(F[:, ::-1]) if signed_volume(V, F) < 0 else F


#: a mesh (or patch) *has an inside* when at most this fraction of its edges lie on a boundary ...
CLOSED_MAX_BOUNDARY = 0.1
#: ... and its holes are small: the norm of its vector area (zero for a closed surface, the
#: area itself for a flat sheet) at most this fraction of its area ...
CLOSED_MAX_OPENING = 0.1
#: ... unless its largest hole is large (its rim over this many times the square root of its
#: area) and opens upward (against gravity): then it is a *container* (a cup, a bucket, a box
#: without its lid), faced into its opening, where dropped bodies land. A new user's deep cup
#: (r = 0.3 m, 1.8 m deep: its opening 8 % of its vector area, its rim 1.9 m against the square
#: root of its area 1.9 m) counted as closed and was turned outward: its balls fell through its
#: bottom. A large hole opening sideways or down (a turntable scan's missing bottom, a blob cut
#: by the reconstruction's grid) keeps the closed rule: such scans face outward as before
CONTAINER_MIN_HOLE = 0.5
#: the opening's direction counts as upward within this angle of the scene's up [degrees]
CONTAINER_MAX_TILT = 60.0
#: ... and a container is no flat sheet: the norm of its vector area at most this fraction of
#: its area (a sheet's is 1; the deep cup's 0.08, a shallow dish's ~0.5) ...
CONTAINER_MAX_OPENING = 0.6
#: ... and its mouth is most of its top: the norm of its vector area (the opening's area seen
#: along up) at least this fraction of its footprint (its bounding box across up): a cup 0.79, a
#: box without its lid 1; a torus scanned with a hole on top 0.02 (a hole, not a mouth: kept
#: closed, facing outward; found by a new user)
CONTAINER_MIN_MOUTH = 0.3


def up_from_gravity(gravity) -> np.ndarray:
    """The scene's up (3,), a unit vector against ``gravity`` [m/s^2] (+z without gravity): where
    dropped bodies come from. The one rule of spawning, orientation and the fell-past note."""
    g = np.asarray(gravity, np.float64).reshape(3)
    n = float(np.linalg.norm(g))
    return -g / n if n > 0 else np.array([0.0, 0.0, 1.0])


def frame_across(up) -> np.ndarray:
    """(3, 3) an orthonormal frame whose rows are two directions across ``up`` (3,) and ``up``
    itself (normalised)."""
    u = np.asarray(up, np.float64).reshape(3)
    u = u / (np.linalg.norm(u) or 1.0)
    e1 = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(u, e1), u])


def _footprint(V, up, label=None, n: int = 1) -> np.ndarray:
    """(n,) the area of the bounding box of the points V (N, 3) across ``up`` (3,), per ``label``
    (N,) group (default all 0)."""
    P = np.asarray(V, np.float64).reshape(-1, 3) @ frame_across(up)[:2].T
    g = np.zeros(len(P), np.int64) if label is None else np.asarray(label, np.int64)
    lo, hi = np.full((n, 2), np.inf), np.full((n, 2), -np.inf)
    np.minimum.at(lo, g, P)
    np.maximum.at(hi, g, P)
    return np.where(np.isfinite(lo).all(1), np.prod(np.maximum(hi - lo, 0.0), axis=1), 0.0)


def _piece_kind(boundary_edges, edges, vector_area, area, largest_hole, volume, up, footprint) -> tuple:
    """The one rule of :func:`mesh_orientation` and :func:`orient_faces`, per piece: ``(has an
    inside, is a container)`` (bool arrays). ``vector_area`` (P, 3) and ``area`` (P,) [units^2],
    ``largest_hole`` (P,) the rim of its longest boundary loop (:func:`_hole_rims`), ``volume``
    (P,) signed, about its centroid, ``up`` (3,) the scene's up, ``footprint`` (P,) its bounding
    box's area across up (:func:`_footprint`). A piece with an inside: few
    boundary edges and small holes (a scan or reconstruction with holes), so that a sheet of any
    size (whose boundary is a small fraction of a fine mesh's edges) has none; a container: few
    boundary edges, no flat sheet, and a large hole whose opening (through the hole, out of the
    piece: against the vector area of a piece facing outward) points up."""
    S = np.asarray(vector_area, np.float64).reshape(-1, 3)
    area = np.asarray(area, np.float64).reshape(-1)
    norm = np.linalg.norm(S, axis=1)
    few = np.asarray(boundary_edges) <= CLOSED_MAX_BOUNDARY * np.asarray(edges)
    large = np.asarray(largest_hole) > CONTAINER_MIN_HOLE * np.sqrt(area)
    u = np.asarray(up, np.float64)
    u = u / (np.linalg.norm(u) or 1.0)
    opening = -np.sign(np.asarray(volume, np.float64)) * (S @ u) / np.maximum(norm, 1e-300)
    container = few & large & (norm > 0) & (opening >= np.cos(np.radians(CONTAINER_MAX_TILT))) \
        & (norm <= CONTAINER_MAX_OPENING * area) & (norm >= CONTAINER_MIN_MOUTH * np.asarray(footprint))
    inside = few & (norm <= CLOSED_MAX_OPENING * area) & ~container
    return inside, container


def _hole_rims(V, E, group=None, groups: int = 1) -> np.ndarray:
    """(groups,) the length of the longest boundary loop in each group: ``E`` (B, 2) the boundary
    edges (each on one face), ``group`` (B,) the group (patch) of each edge (default all 0). A
    loop is a connected set of boundary edges; zero where a group has none."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    out = np.zeros(int(groups))
    E = np.asarray(E, np.int64).reshape(-1, 2)
    if not len(E):
        return out
    V = np.asarray(V, np.float64)
    n = int(E.max()) + 1
    _, loop = connected_components(coo_matrix((np.ones(len(E), np.int8), (E[:, 0], E[:, 1])), shape=(n, n)),
                                   directed=False)
    lab = loop[E[:, 0]]
    length = np.bincount(lab, np.linalg.norm(V[E[:, 1]] - V[E[:, 0]], axis=1))
    g = np.zeros(len(E), np.int64) if group is None else np.asarray(group, np.int64)
    np.maximum.at(out, g, length[lab])
    return out


def mesh_orientation(V, F, up=(0.0, 0.0, 1.0)) -> str:
    """How the triangles of a mesh face.

    ``"outward"`` / ``"inward"``: a mesh with an inside (closed, or with holes as a scan has:
    :func:`_piece_kind`), with consistent winding; the sign of its volume about the vertex
    centroid decides. ``"open"``: a sheet, a terrain, a container opening upward (along ``up``,
    against gravity: a cup), or an edge shared by more than two faces (fins and flat faces on a
    closed surface aside: :func:`_orientation_of`): no inside to tell. ``"inconsistent"``: two faces
    run through a shared edge in the same direction. Vertices at one position are one (a
    flat-shaded export, each face with its own corners, is the closed mesh it shows)."""
    V0, F0 = np.asarray(V, np.float64), np.asarray(F, np.int64)
    V, F = weld_vertices(V0, F0)[:2]
    if F is F0:
        return _orientation_of(V, F, up)
    # faces that repeat a vertex once welded (marching cubes where the field is 0 at a grid
    # point gives coincident vertices) or are listed again are no surface, as orient_faces leaves
    # them out; where the welded mesh still reads as open (two sheets touching at such a point
    # share an edge four times: a new user's spheres inside a human were then not refused), the
    # mesh as indexed decides
    got = _orientation_of(V, F[distinct_faces(F)[1]], up)
    return got if got != "open" else _orientation_of(V0, F0, up)


#: the most faces (a fraction of the mesh's) that :func:`_orientation_of` leaves out as an
#: exporter's debris on a closed surface (fins, flat faces on its edges) before it decides
DEBRIS_FRACTION = 0.05


def _orientation_of(V, F, up, peel: bool = True) -> str:
    """:func:`mesh_orientation` of the mesh as indexed. An edge shared by more than two faces
    reads as open, unless the faces that make it so are debris on the surface, left out first
    (``peel``; at most ``DEBRIS_FRACTION`` of the faces): flat faces (:func:`flat_faces`) and fins,
    a face with an edge on no other face and one shared by more than two. A new user's closed
    frame wound inward with 30 fins (0.3 % of its faces) read as open, was not turned outward as
    its neighbours were, and came out crumpled (1.7x the input's area)."""
    if not len(F):
        return "open"
    directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    n = int(max(int(F.max()) + 1, 1))
    undirected = np.sort(directed, axis=1)
    _, first, inverse, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_index=True,
                                          return_inverse=True, return_counts=True)
    cr = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    if np.any(counts > 2):
        if not peel:
            return "open"
        per_face = counts[inverse.reshape(3, len(F))].T  # (M, 3): how many faces share each edge
        debris = flat_faces(V, F) | ((per_face == 1).any(axis=1) & (per_face > 2).any(axis=1))
        if not debris.any() or debris.sum() > DEBRIS_FRACTION * len(F):
            return "open"
        return _orientation_of(V, F[~debris], up, peel=False)
    rim = _hole_rims(V, undirected[first[counts == 1]])
    vol = signed_volume(V, F)
    inside, _ = _piece_kind(np.count_nonzero(counts == 1), len(counts), 0.5 * cr.sum(axis=0),
                            0.5 * np.linalg.norm(cr, axis=1).sum(), rim, vol, up, _footprint(V[F.reshape(-1)], up))
    if not inside[0]:
        return "open"
    if winding_inconsistent(F):
        return "inconsistent"
    return "outward" if vol > 0 else "inward"


def _patches(F: np.ndarray) -> tuple:
    """Faces joined through edges shared by exactly two faces (a *patch*: a manifold piece).

    Returns ``(patch label (M,), number of patches, rewind (M,) bool, orientable (M,) bool,
    boundary edges per patch, edges per patch, rim edges (B, 2), the patch of each (B,))``, the
    rim edges being those on one face only. ``rewind`` marks the faces to flip so that
    every patch's winding is consistent (neighbours run through their shared edge in opposite
    directions), the side kept being the one of larger face count; ``orientable`` is False on
    patches with no consistent winding (a Moebius strip), whose faces are never marked.
    Edges shared by one face, or by more than two (non-manifold), bound a patch."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(F, np.int64)
    M = len(F)
    n = int(F.max()) + 1 if M else 1
    d = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])  # half-edges, face i at rows i, M+i, 2M+i
    face = np.tile(np.arange(M), 3)
    key = np.minimum(d[:, 0], d[:, 1]) * n + np.maximum(d[:, 0], d[:, 1])
    order = np.argsort(key, kind="stable")
    k = key[order]
    start = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    count = np.diff(np.r_[start, len(k)])
    pair = start[count == 2]  # manifold edges: half-edges order[pair], order[pair + 1]
    ha, hb = order[pair], order[pair + 1]
    fa, fb = face[ha], face[hb]
    same = d[ha, 0] == d[hb, 0]  # the two faces run through the edge the same way: one must flip
    # the double cover: node f (side kept) and M + f (side flipped); a consistent pair joins
    # (a, b) and (a', b'), a clashing pair joins (a, b') and (a', b)
    r = np.concatenate([fa, fa + M])
    c = np.concatenate([np.where(same, fb + M, fb), np.where(same, fb, fb + M)])
    g = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(2 * M, 2 * M))
    _, cover = connected_components(g, directed=False)
    a, b = cover[:M], cover[M:]
    orientable = a != b
    size = np.bincount(a, minlength=2 * M)  # faces per side class
    rewind = orientable & ((size[a] < size[b]) | ((size[a] == size[b]) & (a > b)))
    pg = coo_matrix((np.ones(len(fa), np.int8), (fa, fb)), shape=(M, M))
    npatch, label = connected_components(pg, directed=False)
    edges_of = face[order[start]]  # one face of each undirected edge
    boundary = np.bincount(label[edges_of[count != 2]], minlength=npatch)
    edges = np.bincount(label[edges_of], minlength=npatch)
    rim = order[start[count == 1]]  # the half-edges on one face only: the holes' rims
    return label, npatch, rewind, orientable, boundary, edges, d[rim], label[face[rim]]


def face_rim_flags(F) -> np.ndarray:
    """(M,) int32 per face of ``F`` (M, 3): bit k (0-2) set where the face's edge opposite its
    corner k lies on one face only (a rim: a hole's, a sheet's or a partial scan's edge), bit 3 + k
    where corner k is a vertex of some rim edge. All zero on a closed mesh."""
    F = np.asarray(F, np.int64).reshape(-1, 3)
    M = len(F)
    flags = np.zeros(M, np.int32)
    if not M:
        return flags
    n = int(F.max()) + 1
    a, b = F[:, [1, 2, 0]].T.ravel(), F[:, [2, 0, 1]].T.ravel()  # row k M + i: face i's edge opposite corner k
    key = np.minimum(a, b) * n + np.maximum(a, b)
    _, inverse, count = np.unique(key, return_inverse=True, return_counts=True)
    rim = (count[inverse] == 1).reshape(3, M)
    on_rim = np.zeros(n, bool)
    on_rim[a[rim.ravel()]] = on_rim[b[rim.ravel()]] = True
    for k in range(3):
        flags |= rim[k].astype(np.int32) << k
        flags |= on_rim[F[:, k]].astype(np.int32) << (3 + k)
    return flags


#: a face is flat (no area: its corners on a line) when its height over its longest edge is at
#: most this fraction of that edge plus this fraction of the largest |coordinate| (float32
#: rounding: an edge's midpoint stored in float32 lies up to ~1e-7 x the coordinates off the
#: edge). Marching-cubes slivers are far thicker (smallest angles >= ~5e-4 rad measured on the
#: issue-12 inputs, against 1e-6 here plus the rounding term)
FLAT_FACE = 1e-6


def flat_faces(V, F) -> np.ndarray:
    """(M,) bool: the faces of (V, F) whose three corners lie on a line (``FLAT_FACE``): no area
    and no winding in this pose (an exporter's degenerate triangles)."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    if len(F) == 0:
        return np.zeros(0, bool)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    twice = np.linalg.norm(np.cross(b - a, c - a), axis=1)  # height x longest edge
    longest = np.sqrt(np.max(np.stack([np.einsum("ij,ij->i", e, e) for e in (b - a, c - b, a - c)]), axis=0))
    scale = float(np.abs(V[np.unique(F)]).max()) if V.size else 0.0
    return twice <= FLAT_FACE * longest * (longest + scale)


def has_area(V, F, chunk: int = 4096) -> bool:
    """Whether some face of (V, F) is not flat (:func:`flat_faces`), looked for a chunk of faces
    at a time (a real mesh answers in the first): ``convert`` refuses a frame without, and a
    scene a surface without (a new user's faces [a, b, b] let every sphere fall through)."""
    F = np.asarray(F).reshape(-1, 3)
    return any(not flat_faces(V, F[s:s + chunk]).all() for s in range(0, len(F), chunk))


def distinct_faces(F, flat=None) -> tuple:
    """``(live, first, copy_of)`` of the faces ``F`` (M, 3): ``live`` the indices of the faces
    with three different vertices (one that repeats a vertex has no area in any pose) and, given
    ``flat`` ((M,) bool, :func:`flat_faces`), not flat;
    ``first`` the index of the first listing of each different triangle among them (a face
    listed again, in either winding, is one triangle); ``copy_of`` (len(live),) the position in
    ``first`` of each live face's triangle. The one rule of ``convert`` (which drops the others)
    and :func:`orient_faces` (which winds every copy as the first)."""
    F = np.asarray(F)
    ok = (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])
    live = np.flatnonzero(ok if flat is None else ok & ~np.asarray(flat, bool))
    L = F[live].astype(np.int64)
    a, b, c = L[:, 0], L[:, 1], L[:, 2]
    lo, hi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
    if len(L) and 0 <= lo.min() and hi.max() < 1 << 21:  # one int64 key a row (its vertices sorted), in
        # the sorted rows' lexicographic order: a 1-D unique, ~10x faster than the row-wise one (convert
        # runs it on every frame)
        mid = a + b + c - lo - hi
        _, first, copy_of = np.unique((lo << 42) | (mid << 21) | hi, return_index=True, return_inverse=True)
    else:
        _, first, copy_of = np.unique(np.sort(L, axis=1), axis=0, return_index=True, return_inverse=True)
    return live, live[first], copy_of.reshape(-1)


def _may_repeat_rows(A: np.ndarray) -> bool:
    """False when no two rows of ``A`` (N, k) are bit for bit equal, decided by a 64-bit hash of
    each row (1-D sort); True when two hashes meet (then the rows may be equal)."""
    B = np.ascontiguousarray(A)
    words = B.view(np.uint8).reshape(len(B), -1)
    if words.shape[1] % 4:
        return True
    u = words.view(np.uint32).astype(np.uint64)
    h = np.zeros(len(B), np.uint64)
    for j in range(u.shape[1]):
        h = (h ^ u[:, j]) * np.uint64(0x100000001B3) + np.uint64(j + 1)
    h.sort()
    return bool(np.any(h[1:] == h[:-1]))


def _sum_by(label: np.ndarray, X: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) the rows of ``X`` (M, 3) summed per ``label`` (M,)."""
    return np.stack([np.bincount(label, X[:, i], minlength=n) for i in range(3)], 1)


def orient_faces(V, F, up=(0.0, 0.0, 1.0), down_fraction: float = 0.25) -> tuple:
    """``(F', report)``: the faces ``F`` wound so that one-sided contacts hold, patch by patch
    (manifold pieces, see :func:`_patches`, of the mesh with coincident vertices welded):

    1. every patch's winding is made consistent (the minority of its faces flipped);
    2. a patch with an inside (closed, or with holes as a scan has: :func:`_piece_kind`) faces
       outward: flipped when its volume (about its own centroid) is negative;
    3. a container (a large hole opening up: a cup, a bucket, a box without a lid) faces into
       itself, where dropped bodies land: flipped when its volume is positive;
    4. an open patch (a sheet, a terrain) faces ``up`` (against gravity, where falling bodies come
       from) when its area-weighted normal points down by more than ``down_fraction`` of its
       area; one with no clear up or down side (a wall, a flag) is left as it is.

    ``report``: ``{"rewound": faces flipped by 1, "inward": closed patches flipped, "container":
    containers flipped to face into themselves, "down": open patches flipped, "non_orientable":
    patches with no consistent winding (left as they are), "patches": number of patches}``. ``F``
    is returned itself when nothing changes."""
    F = np.asarray(F)
    V = np.asarray(V, np.float64)
    report = {"rewound": 0, "inward": 0, "down": 0, "container": 0, "non_orientable": 0, "patches": 0}
    if len(F) == 0:
        return F, report
    # pieces by position, not by index: a triangle soup or a mesh with seams is one piece; a face
    # listed twice (either winding) is decided once, its copies wound as the first
    Vw, W = weld_vertices(V, F)[:2]
    # faces that repeat a vertex or lie flat have no area and no winding: left as they are (their
    # edges would tie the pieces in knots: a flat face on an edge makes it non-manifold, and the
    # pieces split there were wound apart; found by a new user)
    live, first, copy_of = distinct_faces(W, flat_faces(V, F))
    if len(live) == 0:
        return F, report
    Fu = F[first]
    label, npatch, rewind, orientable, boundary, edges, rim_edges, rim_patch = _patches(W[first])
    report["patches"] = int(npatch)
    report["rewound"] = int(rewind.sum())
    report["non_orientable"] = int(len(np.unique(label[~orientable])))
    G = np.where(rewind[:, None], Fu[:, ::-1], Fu)
    a, b, c = V[G[:, 0]], V[G[:, 1]], V[G[:, 2]]
    cr = np.cross(b - a, c - a)  # twice the vector area of each face
    # volume about each patch's vertex centroid (a small hole biases it little)
    w = np.bincount(label, minlength=npatch).astype(np.float64)
    o = (_sum_by(label, a + b + c, npatch) / (3 * w[:, None]))[label]
    vol = np.bincount(label, np.einsum("ij,ij->i", a - o, np.cross(b - o, c - o)), minlength=npatch)
    up = np.asarray(up, np.float64)
    up = up / (np.linalg.norm(up) or 1.0)
    facing = np.bincount(label, cr @ up, minlength=npatch)
    area = np.bincount(label, np.linalg.norm(cr, axis=1), minlength=npatch)
    closed, container = _piece_kind(boundary, edges, 0.5 * _sum_by(label, cr, npatch), 0.5 * area,
                                    _hole_rims(Vw, rim_edges, rim_patch, npatch), vol, up,
                                    _footprint(np.concatenate([a, b, c]), up, np.tile(label, 3), npatch))
    ok = np.bincount(label, ~orientable, minlength=npatch) == 0
    inward = ok & closed & (vol < 0)
    into = ok & container & (vol > 0)  # a container facing out of itself: dropped bodies would pass its bottom
    down = ok & ~closed & ~container & (facing < -down_fraction * area)
    report["inward"], report["down"], report["container"] = int(inward.sum()), int(down.sum()), int(into.sum())
    # each face (every copy) turned to the winding its unique face ends with
    wanted = _winding(W[first]) ^ rewind ^ (inward | down | into)[label]
    turn = np.zeros(len(F), bool)
    turn[live] = _winding(W[live]) != wanted[copy_of]
    if not turn.any():
        return F, report
    return np.ascontiguousarray(np.where(turn[:, None], F[:, ::-1], F), dtype=F.dtype), report


def winding_inconsistent(F) -> bool:
    """Two faces of ``F`` run through a shared edge in the same direction (a directed edge listed
    twice): the faces are not wound consistently. One sort of the 3M directed edges (~2 ms for 20k
    faces)."""
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if not len(F):
        return False
    key = np.sort(F.ravel() * (int(F.max()) + 1) + F[:, [1, 2, 0]].ravel())
    return bool(np.any(key[1:] == key[:-1]))


def _winding(F: np.ndarray) -> np.ndarray:
    """(M,) bool: the cyclic order of each face's vertex indices, (i, j, k) with i the smallest:
    True when j < k. Two listings of one triangle wind the same way iff these agree."""
    F = np.asarray(F)
    r = np.argmin(F, axis=1)[:, None]
    rolled = np.take_along_axis(F, (r + np.arange(3)) % 3, axis=1)
    return rolled[:, 1] < rolled[:, 2]


def weld_vertices(V, F) -> tuple:
    """``(V', F', merged)``: vertices at exactly the same position merged into one, the first of
    each kept in its order, the faces renumbered. A triangle soup (every face with its own three
    vertices, as STL or some OBJ exporters write it) becomes a connected mesh again; ``merged``
    is how many vertices went. Only exact repeats are merged: marching cubes makes distinct
    vertices closer than any tolerance would be safe for. ``V`` and ``F`` are returned themselves
    when no two vertices coincide."""
    V = np.asarray(V)
    F = np.asarray(F)
    if len(V) < 2 or not _may_repeat_rows(V):  # the common case, without the row-wise unique
        return V, F, 0
    _, first, inverse = np.unique(V, axis=0, return_index=True, return_inverse=True)
    if len(first) == len(V):
        return V, F, 0
    keep = np.sort(first)  # the first vertex of each position, in input order
    remap = np.searchsorted(keep, first)[inverse.reshape(-1)]  # each position's new index
    return V[keep], remap[F].astype(F.dtype), len(V) - len(keep)


def motion_groups(V, F, groups: int, frames: int = 16, sample: int = 20000, iterations: int = 12,
                  seed: int = 0) -> np.ndarray:
    """(M,) int64 group of each face of the animated mesh (V (T, N, 3), F (M, 3)): k-means, with
    farthest-point seeds, of the faces' centroid trajectories over up to ``frames`` evenly spaced
    frames, so faces that move together (a limb segment) share a group. Fitted on at most
    ``sample`` faces, then every face goes to its nearest centre. ``groups`` is capped at M; the
    labels are 0..K-1 with no empty group. Used to stream bound Gaussians as rigidly moving
    groups (the viewer)."""
    V = np.asarray(V, np.float64)
    V = V[None] if V.ndim == 2 else V
    F = np.asarray(F)
    T, M = V.shape[0], len(F)
    K = int(max(1, min(groups, M)))
    sub = V[np.unique(np.linspace(0, T - 1, min(T, max(1, frames))).round().astype(int))]
    X = sub[:, F].mean(axis=2).transpose(1, 0, 2).reshape(M, -1)  # (M, 3t) trajectories
    rng = np.random.default_rng(seed)
    fit = X if M <= sample else X[rng.choice(M, sample, replace=False)]

    def nearest(P, C):
        out = np.empty(len(P), np.int64)
        cc = (C * C).sum(1)
        for a in range(0, len(P), 4096):
            out[a:a + 4096] = (cc[None] - 2.0 * P[a:a + 4096] @ C.T).argmin(1)
        return out

    seeds = [int(rng.integers(len(fit)))]
    d = ((fit - fit[seeds[0]]) ** 2).sum(1)
    for _ in range(K - 1):
        j = int(d.argmax())
        seeds.append(j)
        d = np.minimum(d, ((fit - fit[j]) ** 2).sum(1))
    C = fit[seeds].copy()
    for _ in range(iterations):
        lab = nearest(fit, C)
        cnt = np.bincount(lab, minlength=K)
        for j in range(X.shape[1]):
            C[:, j] = np.where(cnt > 0, np.bincount(lab, fit[:, j], K) / np.maximum(cnt, 1), C[:, j])
    lab = nearest(X, C)
    return np.unique(lab, return_inverse=True)[1].astype(np.int64)  # no empty group


def fit_group_motions(ref_local, points, labels, groups: int):
    """Best rigid motion of each group (Kabsch): ``ref_local`` (G, 3) reference positions, each
    relative to its group's reference centroid; ``points`` (G, 3) the same points now; ``labels``
    (G,) their groups in [0, groups). Returns (R (K, 3, 3), t (K, 3), err (G,)): points ≈
    R[label] @ ref_local + t[label] (t is the group's current centroid), err each point's
    distance to its fit [units of points]."""
    ref = np.asarray(ref_local, np.float64)
    P = np.asarray(points, np.float64)
    lab = np.asarray(labels)
    K = int(groups)
    cnt = np.maximum(np.bincount(lab, minlength=K), 1).astype(np.float64)
    t = np.stack([np.bincount(lab, P[:, j], K) for j in range(3)], 1) / cnt[:, None]
    b = P - t[lab]
    H = np.empty((K, 3, 3))
    for i in range(3):
        for j in range(3):
            H[:, i, j] = np.bincount(lab, ref[:, i] * b[:, j], K)
    U, _, Vt = np.linalg.svd(H)
    D = np.ones((K, 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    D[D[:, 2] == 0, 2] = 1.0
    R = np.einsum("kji,kj,klj->kil", Vt, D, U)  # V diag(D) U^T
    err = np.linalg.norm(np.einsum("kij,kj->ki", R[lab], ref) + t[lab] - P, axis=1)
    return R, t, err


def rotation_to_wxyz(R) -> np.ndarray:
    """(K, 4) unit quaternions (w, x, y, z) of rotation matrices R (K, 3, 3)."""
    R = np.asarray(R, np.float64).reshape(-1, 3, 3)
    tr = np.trace(R, axis1=1, axis2=2)
    q = np.empty((len(R), 4))
    m = [R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]]
    c0 = tr > 0
    s = np.sqrt(np.maximum(tr + 1.0, 1e-30)) * 2.0
    q[c0] = np.stack([0.25 * s, (R[:, 2, 1] - R[:, 1, 2]) / s, (R[:, 0, 2] - R[:, 2, 0]) / s,
                      (R[:, 1, 0] - R[:, 0, 1]) / s], 1)[c0]
    for i, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
        ci = ~c0 & (m[i] >= m[a]) & (m[i] >= m[b])
        c0 = c0 | ci
        s = np.sqrt(np.maximum(1.0 + 2.0 * m[i] - tr, 1e-30)) * 2.0
        v = np.empty((len(R), 4))
        v[:, 0] = (R[:, b, a] - R[:, a, b]) / s
        v[:, 1 + i] = 0.25 * s
        v[:, 1 + a] = (R[:, a, i] + R[:, i, a]) / s
        v[:, 1 + b] = (R[:, b, i] + R[:, i, b]) / s
        q[ci] = v[ci]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)
