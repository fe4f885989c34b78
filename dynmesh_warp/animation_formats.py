"""Single-file animations: one file holds every frame of a fixed-topology mesh sequence.

Three formats animated-mesh data comes in, read and written byte for byte as their producers
do (docs/data.md, "Single-file animations"):

- ``.anime`` (DeformingThings4D, ~2,000 animal and humanoid animations): little-endian int32
  ``nf, nv, nt``; float32 (nv, 3) vertices of frame 0; int32 (nt, 3) faces; float32
  (nf - 1, nv, 3) offsets of frames 1 .. nf - 1 from frame 0. No frame rate.
- ``.pc2`` (PointCache2: Blender's Mesh Cache modifier, 3ds Max, Houdini): a 32-byte
  little-endian header ``"POINTCACHE2\\0"``, int32 version (1), int32 points, float32 start
  frame, float32 sampling (frames per sample), int32 samples; then float32 (samples, points, 3).
  Vertices only: the faces come from a mesh file (``topology``). No frame rate (the sampling is
  in frames of the producing scene).
- ``.mdd`` (LightWave / Blender MDD): big-endian int32 frames, int32 points; float32 times
  [frames] in seconds; float32 (frames, points, 3). Vertices only, like PC2. The frame rate is
  read from the times. Old Blender exporters wrote the rest pose as one more block than the
  header counts: such a file is read without that first block.

A point cache in the other byte order than its spec's (a big-endian PC2, a little-endian MDD) is
read so, with a warning, where its header read so fits the file and its numbers are finite.

``read_animation(path, topology=None) -> (V (T, N, 3) float32, F (M, 3) int64, fps or None)``;
``write_animation(path, V, F, fps)`` writes one (for PC2 / MDD also the topology mesh next to
it, ``<stem>.obj``, which ``read_animation`` finds by itself). Every size is checked against the
header before anything is read, so a truncated or corrupt file is an error naming the file and
what disagrees, never a huge allocation or a wrong reshape.
"""

from __future__ import annotations

import errno
import os
import struct
import warnings
from pathlib import Path

import numpy as np

from .mesh_formats import MESH_EXTENSIONS, mesh_extension, read_mesh, write_mesh
from .outputs import atomic_path
from .sequence import MAX_COORDINATE, MeshDataError

__all__ = ["ANIMATION_EXTENSIONS", "CACHE_EXTENSIONS", "VERTEX_ONLY_EXTENSIONS", "read_animation", "write_animation",
           "find_topology", "topology_faces", "written_topology"]

#: extensions of single-file animations (lower case, with the dot)
ANIMATION_EXTENSIONS = (".anime", ".pc2", ".mdd")
#: those that hold vertices only: their faces come from a mesh file (``topology``)
CACHE_EXTENSIONS = (".pc2", ".mdd")
#: every file that may hold vertices only (its faces from ``topology``): point caches, ``.npy``,
#: and npz files without a face array
VERTEX_ONLY_EXTENSIONS = CACHE_EXTENSIONS + (".npz", ".npy")

_PC2_HEADER = struct.Struct("<12siiffi")  # the spec's byte order; _read_pc2 also reads the other
_PC2_MAGIC = b"POINTCACHE2\0"


def _bad(path, msg: str) -> MeshDataError:
    return MeshDataError(f"{path}: {msg}")


def _size_check(path, size: int, expected: int, what: str) -> None:
    if size != expected:
        raise _bad(path, f"{what} make {expected:,} bytes, but the file has {size:,} "
                         f"({'truncated' if size < expected else 'extra data after the last frame'})")


def _counts(path, **counts) -> None:
    for name, n in counts.items():
        if n <= 0:
            raise _bad(path, f"header: {name} = {n} (must be > 0); not a valid file of this format")


def _read_anime(path: Path, size: int):
    with open(path, "rb") as fh:
        head = fh.read(12)
        if len(head) < 12:
            raise _bad(path, f"{size} bytes: too short for the .anime header (3 int32)")
        nf, nv, nt = struct.unpack("<3i", head)
        _counts(path, frames=nf, vertices=nv, faces=nt)
        _size_check(path, size, 12 + 12 * nv + 12 * nt + 12 * nv * (nf - 1),
                    f"header: {nf} frames x {nv} vertices, {nt} faces")
        v0 = np.fromfile(fh, dtype="<f4", count=3 * nv).reshape(nv, 3)
        F = np.fromfile(fh, dtype="<i4", count=3 * nt).reshape(nt, 3).astype(np.int64)
        off = np.fromfile(fh, dtype="<f4", count=3 * nv * (nf - 1)).reshape(nf - 1, nv, 3)
    V = np.empty((nf, nv, 3), np.float32)
    V[0] = v0
    V[1:] = v0[None] + off
    return V, F, None


_ORDER = {"<": "little", ">": "big"}


#: _either_order takes the other byte order when its header fits the file, its finite numbers are
#: coordinates (within sequence.MAX_COORDINATE: numbers read in the wrong order have wild exponents)
#: and at most this fraction of them are not finite (a few NaN are the data's own: the load names them)
OTHER_ORDER_NONFINITE = 0.5


def _either_order(read, path: Path, size: int, spec: str, fmt: str):
    """``read(path, size, byte_order)`` in the spec's byte order, else in the other one where the
    header read so fits the file exactly and its numbers are finite but for a few (a file written by a
    tool that got the byte order wrong), with a warning saying so; else the spec order's error,
    with a hint where only the other order's header fits (a new user's big-endian PC2 was
    reported as "201326592 samples x 2013265920 points ... (truncated)" without one)."""
    try:
        return read(path, size, spec)
    except MeshDataError as e:
        other = ">" if spec == "<" else "<"
        try:
            out = read(path, size, other)
        except MeshDataError:
            raise e from None
        said = (f"read {_ORDER[other]}-endian, its header fits the file: a {_ORDER[other]}-endian {fmt}? {fmt} is "
                f"{_ORDER[spec]}-endian by its spec")
        arrays = [np.asarray(a, np.float64) for a in out if isinstance(a, np.ndarray)]
        bad = sum(int(np.count_nonzero(~np.isfinite(a))) for a in arrays)
        wild = any(bool((np.abs(a[np.isfinite(a)]) > MAX_COORDINATE).any()) for a in arrays)
        if wild or bad > OTHER_ORDER_NONFINITE * max(sum(a.size for a in arrays), 1):
            raise MeshDataError(f"{e}; {said}, but its data do not read as numbers so") from None
        # a few NaN among numbers: the file's own (the load's check names the frame and vertex; a
        # new user's one NaN made the whole file "a corrupt header")
        warnings.warn(f"{path}: {said}; read {_ORDER[other]}-endian (write {fmt} {_ORDER[spec]}-endian)", stacklevel=3)
        return out


def _read_pc2(path: Path, size: int):
    return _either_order(_read_pc2_as, path, size, "<", "PC2")


def _read_pc2_as(path: Path, size: int, order: str):
    with open(path, "rb") as fh:
        head = fh.read(_PC2_HEADER.size)
        if len(head) < _PC2_HEADER.size or not head.startswith(b"POINTCACHE2"):
            raise _bad(path, "not a PC2 point cache (it must start with 'POINTCACHE2')")
        _, _version, n, _start, _sampling, T = struct.unpack(order + _PC2_HEADER.format[1:], head)
        _counts(path, points=n, samples=T)
        _size_check(path, size, _PC2_HEADER.size + 12 * n * T, f"header: {T} samples x {n} points")
        V = np.fromfile(fh, dtype=order + "f4", count=3 * n * T).reshape(T, n, 3)
    return V.astype(np.float32), None, None


def _read_mdd(path: Path, size: int):
    return _either_order(_read_mdd_as, path, size, ">", "MDD")


def _read_mdd_as(path: Path, size: int, order: str):
    with open(path, "rb") as fh:
        head = fh.read(8)
        if len(head) < 8:
            raise _bad(path, f"{size} bytes: too short for the MDD header (2 int32)")
        T, n = struct.unpack(order + "2i", head)
        _counts(path, frames=T, points=n)
        base = 8 + 4 * T
        rest = 0
        if size == base + 12 * n * (T + 1):  # old Blender exporters: an uncounted rest pose first
            rest = 1
        else:
            _size_check(path, size, base + 12 * n * T, f"header: {T} frames x {n} points")
        times = np.fromfile(fh, dtype=order + "f4", count=T).astype(np.float64)
        fh.seek(base + 12 * n * rest)
        V = np.fromfile(fh, dtype=order + "f4", count=3 * n * T).reshape(T, n, 3)
    fps = None
    if T >= 2:
        dt = np.diff(times)
        if np.all(np.isfinite(dt)) and np.all(dt > 0):
            fps = round(float(1.0 / np.median(dt)), 3)  # float32 times: 24.000006 -> 24.0
    return V.astype(np.float32), None, fps


_READERS = {".anime": _read_anime, ".pc2": _read_pc2, ".mdd": _read_mdd}


def find_topology(path, num_points: int | None = None) -> Path:
    """The mesh file that gives a point cache its faces when none is named: the one file next
    to it with the same stem and a mesh extension (``walk.pc2`` -> ``walk.obj``). Where there are
    several (a ``walk.glb`` written beside ``walk.pc2`` and its ``walk.obj``), those with
    ``num_points`` vertices (when given), and of those the ``<stem>.obj`` that ``write_animation``
    writes beside a point cache; else an error naming them."""
    path = Path(path)
    found = sorted(p for p in path.parent.glob(f"{path.stem}.*")
                   if p != path and p.is_file() and mesh_extension(p.name))
    if len(found) > 1 and num_points is not None:
        fits = []
        for p in found:
            try:
                if len(read_mesh(p)[0]) == num_points:
                    fits.append(p)
            except (MeshDataError, OSError, ValueError):
                pass  # an unreadable candidate gives no faces
        own = path.with_suffix(".obj")
        found = [own] if own in fits and len(fits) > 1 else fits or found
    if len(found) == 1:
        return found[0]
    if not found:
        raise MeshDataError(
            f"{path}: {'a ' + path.suffix + ' point cache' if path.suffix.lower() in CACHE_EXTENSIONS else 'this file'} "
            f"holds vertex positions only (no faces: an npz names them F, faces or triangles); its faces come from a mesh "
            f"with the same vertices, and none was found next to it ({path.stem}.obj, .ply, ...). Name one: "
            f"load_sequence(..., topology='mesh.obj'), surface.topology in a scene file, or convert's --topology")
    raise MeshDataError(f"{path}: several meshes could give its faces ({', '.join(p.name for p in found)}); "
                        f"name one with topology=")


def topology_mesh(path, num_points: int, topology=None) -> Path:
    """The mesh file that gives the vertex-only sequence ``path`` its faces: ``topology``, by
    default :func:`find_topology`'s (``FileNotFoundError`` when it is not there)."""
    mesh = Path(topology).expanduser() if topology is not None else find_topology(path, num_points)
    if not mesh.is_file():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(mesh))
    return mesh


def topology_faces(path, num_points: int, topology=None) -> np.ndarray:
    """The faces (M, 3) of a vertex-only sequence ``path`` with ``num_points`` points a frame
    (a point cache, an npz or npy of vertices): from the mesh file ``topology``, by default
    :func:`find_topology`'s; its vertex count must equal ``num_points`` (:class:`MeshDataError`
    naming both files)."""
    mesh = topology_mesh(path, num_points, topology)
    V0, F = read_mesh(mesh)
    if len(V0) != num_points:
        raise MeshDataError(f"{path}: {num_points} points a frame, but its topology {mesh} has {len(V0)} "
                            f"vertices; vertex positions need the mesh they were written from")
    return np.asarray(F, np.int64)


def read_animation(path, topology=None):
    """Read a single-file animation: ``(V (T, N, 3) float32, F (M, 3) int64, fps or None)``.

    ``topology``: for a point cache (``.pc2``, ``.mdd``), the mesh file whose faces (and vertex
    count) go with it; default: :func:`find_topology`. Raises ``FileNotFoundError`` for a
    missing file and :class:`MeshDataError` naming the file for anything that disagrees (header
    against size, vertex counts of cache and mesh, a topology given for an ``.anime``)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in _READERS:
        raise ValueError(f"{path}: not a single-file animation ({', '.join(ANIMATION_EXTENSIONS)})")
    if not path.is_file():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(path))
    V, F, fps = _READERS[ext](path, path.stat().st_size)
    if ext in CACHE_EXTENSIONS:
        F = topology_faces(path, V.shape[1], topology)
    elif topology is not None:
        raise MeshDataError(f"{path}: an {ext} file holds its own faces; topology= is for point caches "
                            f"({', '.join(CACHE_EXTENSIONS)}) and vertex-only arrays")
    return V, np.asarray(F, np.int64), fps


def written_topology(path) -> Path | None:
    """The mesh file :func:`write_animation` writes next to ``path`` (a point cache's faces:
    ``<stem>.obj``); None for a format that holds its faces."""
    path = Path(path)
    return path.with_suffix(".obj") if path.suffix.lower() in CACHE_EXTENSIONS else None


def write_animation(path, V, F, fps: float, overwrite: bool = False, colors=None) -> list[Path]:
    """Write ``V`` (T, N, 3) on faces ``F`` (M, 3) as ``path`` (``.anime``, ``.pc2`` or ``.mdd``),
    atomically; a point cache also gets its topology, ``<stem>.obj`` next to it (frame 0,
    :func:`written_topology`), unless that file already holds the same faces on as many
    vertices. A mesh there that is not the cache's topology is replaced only with
    ``overwrite`` (else :class:`~dynmesh_warp.outputs.OutputExistsError`, before anything is
    written). ``colors`` (N, 3) in [0, 1]: written to the point cache's ``<stem>.obj`` (the other
    formats have no place for them). Returns the files written."""
    from .outputs import OutputExistsError

    path = Path(path)
    ext = path.suffix.lower()
    if ext not in _READERS:
        raise ValueError(f"{path}: not a single-file animation ({', '.join(ANIMATION_EXTENSIONS)})")
    V = np.asarray(V, np.float32)
    F = np.asarray(F)
    T, n = V.shape[:2]
    written = [path]
    mesh = written_topology(path)
    if mesh is not None and mesh.exists():
        try:
            V0, F0 = read_mesh(mesh)
            same = len(V0) == n and np.array_equal(np.asarray(F0), F)
        except (MeshDataError, OSError):
            same = False
        if same:
            mesh = None  # already there: kept
        elif not overwrite:
            raise OutputExistsError(f"{mesh}: exists and is not the topology of {path.name} (other faces or "
                                    f"vertex count); move it, write the cache under another name, or overwrite")
    with atomic_path(path, suffix=ext) as tmp, open(tmp, "wb") as fh:
        if ext == ".anime":
            fh.write(struct.pack("<3i", T, n, len(F)))
            fh.write(V[0].astype("<f4").tobytes())
            fh.write(F.astype("<i4").tobytes())
            fh.write((V[1:] - V[0][None]).astype("<f4").tobytes())
        elif ext == ".pc2":
            fh.write(_PC2_HEADER.pack(_PC2_MAGIC, 1, n, 0.0, 1.0, T))
            fh.write(V.astype("<f4").tobytes())
        elif ext == ".mdd":
            fh.write(struct.pack(">2i", T, n))
            fh.write((np.arange(T) / float(fps)).astype(">f4").tobytes())
            fh.write(V.astype(">f4").tobytes())
        fh.flush()
        os.fsync(fh.fileno())
    if mesh is not None:
        write_mesh(mesh, V[0], F, colors)
        written.append(mesh)
    return written


assert not set(ANIMATION_EXTENSIONS) & MESH_EXTENSIONS, "an animation extension would also read as a mesh"
