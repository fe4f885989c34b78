"""Reading and writing animated mesh sequences and single meshes.

Entry points
------------
``load_sequence(path, fps=None, kind="auto", subdir=None)``
    Loads a :class:`~dynmesh_warp.sequence.FixedTopologySequence` or
    :class:`~dynmesh_warp.sequence.VaryingTopologySequence` from whatever ``path`` is:

    * **a ``.npz`` file**, in one of two layouts:

      - *fixed topology* (the layout of the shared data sets): ``V`` float32 (T, N, 3),
        ``F`` int32 (M, 3), optional ``fps`` (0-d float) and ``name`` (0-d str);
      - *varying topology* (written by :func:`save_sequence`): the frames packed CSR-style,
        ``V_packed`` float32 (sum N_t, 3) all frames' vertices one after another,
        ``F_packed`` int32 (sum M_t, 3) all frames' faces, each frame's indices local to that
        frame (0-based into its own vertices), ``V_offsets`` int64 (T+1,) and ``F_offsets``
        int64 (T+1,) with frame t's rows in ``[offsets[t], offsets[t+1])``
        (``offsets[0] == 0``, ``offsets[-1] ==`` number of rows), plus optional ``fps`` and
        ``name`` as above. The layout is recognised by its keys (``V`` vs ``V_offsets``).

    * **a single mesh file** (any format :func:`read_mesh` reads): a one-frame sequence.

    * **a folder of per-frame mesh files** (``.obj``, ``.ply``, ``.off``, ``.stl``, ``.glb``,
      ``.gltf`` or an extension meshio reads). Frames are ordered by the *last integer in the
      file stem*, numerically (``frame_2.ply`` before ``frame_10.ply``, ``horse9.obj``
      before ``horse10.obj``). Hidden files and non-mesh files (``.json``, ``.png``,
      ``.txt``, ``.mtl``, ... and ``.svg``/``.xml``/``.dat``, which meshio could read but
      which are rarely meshes) are ignored. It is an error when a mesh file's stem has no
      integer, when two files have the same integer, or when the folder holds meshes of
      more than one extension (ambiguous). Gaps in the numbering are allowed (a
      :class:`UserWarning` lists the missing indices): frame ``t`` of the sequence is the
      ``t``-th file in order, and error messages give both the file and that frame number.

    * **a DG-Mesh scene folder**, i.e. a folder with a ``dynamic_mesh/`` subfolder (exported
      reconstruction, ``frame_{i}.ply``) and/or a ``mesh_gt/`` subfolder (ground truth,
      ``<name>{i}.obj``). When one of them exists it is loaded; when both exist
      ``dynamic_mesh`` is preferred. Pass ``subdir="mesh_gt"`` (or any subfolder name) to
      choose explicitly. The DG-Mesh subfolders take precedence over mesh files lying
      directly in the scene folder (Gaussian-splatting output folders hold e.g. an
      ``input.ply`` next to them).

    ``kind="auto"`` returns a fixed-topology sequence when every frame has the first frame's
    vertex count and an identical face array (this applies to folders and to varying npz
    files alike), otherwise a varying one, whose ``frame_sources`` holds the per-frame file
    paths for folders. ``kind="fixed"`` forces fixed topology and raises
    :class:`MeshDataError` naming the offending file and frame when frames disagree;
    ``kind="varying"`` always returns a varying sequence.

    Frame rate: the ``fps`` argument wins; else the npz ``fps``; else
    :data:`DEFAULT_FPS` (24.0) for folders, single meshes and npz files without ``fps``.

``read_mesh(path, frame=None) -> (V float32 (N, 3), F int32 (M, 3))``
    One mesh file. Vertex order is always preserved exactly as stored in the file: nothing
    is merged, reordered or dropped (also not unreferenced vertices), so per-frame files of a
    fixed-topology animation load with identical face arrays.

    * ``.obj`` and ``.off`` are parsed by small readers in this module. OBJ: only ``v`` and
      ``f`` records are used (``vt``/``vn``/``g``/``usemtl``/``l``/... are ignored;
      ``f 1/2/3`` uses the vertex index; negative indices are relative as per the OBJ
      spec); index 0 and indices past the vertex count are reported, never dropped
      (trimesh's OBJ loader crashes with an IndexError on those).
    * ``.ply``, ``.stl``, ``.glb``, ``.gltf`` are read with trimesh using ``process=False``
      (no vertex merging). STL stores no shared vertices, so an STL mesh is a triangle soup
      with 3 vertices per face. Multi-mesh glTF scenes are flattened (transforms applied,
      meshes concatenated in scene order).
    * Everything else goes through meshio; its ``triangle``, ``quad`` and ``polygon`` cells
      are used, other cell types (lines, vertices, volume cells) are ignored.
    * **Polygons are triangulated**: a face ``(v0, v1, ..., vk)`` with more than three
      vertices becomes the fan ``(v0, v_i, v_i+1)``, i.e. k-1 triangles, a quad gives two.
      (For PLY the triangulation is trimesh's, which is the same fan for n-gons but groups
      the triangles by polygon size.) A fan is exact for convex planar polygons, which is
      what mesh exporters write.
    * Errors: a missing file raises :class:`FileNotFoundError`; an unreadable or corrupt
      file, a file with no vertices, a file with no faces ("no triangle faces": points or
      lines only), NaN/inf coordinates and out-of-range face indices raise
      :class:`MeshDataError` whose message names the file (and ``frame`` when given).

``save_sequence(seq, path, fmt=None)``
    ``path`` ending in ``.npz``: the fixed layout (``V``, ``F``, ``fps`` float32, ``name``,
    exactly like the shared data sets) for a fixed sequence, the packed varying layout for a
    varying one. Otherwise ``path`` is a folder and ``fmt`` is ``"ply"`` (binary
    little-endian, float32 coordinates) or ``"obj"`` (ASCII, 9 significant digits, which
    round-trips float32 exactly): files ``frame_{i:04d}.{fmt}``.

``write_mesh(path, V, F)``
    One mesh; the format follows the extension (own writers for ``.ply``/``.obj``/``.off``,
    trimesh for ``.stl``/``.glb``, meshio for anything else).

``frame_index_from_name(name) -> int``
    The last integer in a file name's stem (``"mesh_gt/bird12.obj"`` -> 12), used for frame
    ordering; other modules use it to pair frames of two folders by index.

Atomic writes
-------------
Every write goes to a temporary file (or, for folders, a temporary hidden sibling folder
``.<name>.tmp-*``) in the destination's directory, which is renamed into place with
:func:`os.replace` only when complete, so an interrupted save leaves no partial output.
An existing destination folder is replaced only at that last step (it is renamed aside,
the new one renamed in, then the old one deleted); to avoid deleting unrelated data, an
existing folder is only replaced when everything in it was written by this tool (the
manifest ``.dynmesh_outputs.json`` lists it), otherwise :class:`FileExistsError` is raised;
``overwrite=True`` replaces it keeping the files this tool did not write.
"""

from __future__ import annotations

import errno
import json
import os
import re
import tempfile
import warnings
import zipfile
from pathlib import Path

import numpy as np

from .choices import FrameOrder, parse
from .sequence import (
    FixedTopologySequence,
    MeshDataError,
    VaryingTopologySequence,
    validate_mesh,
)

__all__ = [
    "DEFAULT_FPS",
    "MESH_EXTENSIONS",
    "DGMESH_SUBDIRS",
    "frame_index_from_name",
    "load_sequence",
    "read_mesh",
    "save_sequence",
    "write_mesh",
]

DEFAULT_FPS = 24.0
"""Frame rate assumed for folders, single meshes and npz files that carry no ``fps``."""

DGMESH_SUBDIRS = ("dynamic_mesh", "mesh_gt")
"""DG-Mesh subfolders recognised in a scene folder, in order of preference."""

_OWN_READERS = (".obj", ".off")
_TRIMESH_READERS = (".ply", ".stl", ".glb", ".gltf")
# Extensions meshio can read but which are usually not meshes in a data folder
# (read_mesh still reads them when given such a file explicitly).
_NOT_FRAME_EXTENSIONS = {".svg", ".xml", ".dat", ".node"}


def _meshio_extensions() -> set[str]:
    try:
        import meshio

        return {e.lower() for e in meshio.extension_to_filetypes}
    except Exception:  # pragma: no cover - meshio is a dependency, but stay importable
        return set()


MESH_EXTENSIONS: frozenset[str] = frozenset(
    (set(_OWN_READERS) | set(_TRIMESH_READERS) | _meshio_extensions()) - _NOT_FRAME_EXTENSIONS
)
"""File extensions (lower case, with dot) treated as per-frame meshes in a folder."""

_KINDS = ("auto", "fixed", "varying")
_INT_RE = re.compile(r"\d+")


# --------------------------------------------------------------------------- names


def _mesh_extension(name: str) -> str | None:
    """The mesh extension of a file name (handles ``.vol.gz``-style double suffixes)."""
    lower = name.lower()
    for ext in MESH_EXTENSIONS:
        if ext.count(".") > 1 and lower.endswith(ext):
            return ext
    ext = os.path.splitext(lower)[1]
    return ext if ext in MESH_EXTENSIONS else None


def frame_index_from_name(name) -> int:
    """Return the last integer in the stem of a file name or path.

    ``"frame_0010.ply"`` -> 10, ``"horse9.obj"`` -> 9, ``"mesh_gt/bird3.obj"`` -> 3,
    ``"scan_v2_017.obj"`` -> 17. Only the final path component is looked at and only its
    stem (the last extension is removed). Raises :class:`MeshDataError` (a ``ValueError``)
    naming ``name`` when the stem holds no integer.
    """
    stem = Path(str(name)).stem
    ext = _mesh_extension(Path(str(name)).name)
    if ext and ext.count(".") > 1:  # frame_3.vol.gz -> frame_3
        stem = Path(str(name)).name[: -len(ext)]
    found = _INT_RE.findall(stem)
    if not found:
        raise MeshDataError(
            f"{name}: file name has no integer frame index (frames in a folder are ordered "
            "by the last integer in the file name, e.g. frame_12.ply)"
        )
    return int(found[-1])


# --------------------------------------------------------------------------- reading


class _ReadError(Exception):
    """Raised by the format readers with a reason; read_mesh adds the file and frame."""


def _not_found(path: Path) -> FileNotFoundError:
    return FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(path))


def _fan(polygons) -> np.ndarray:
    """Fan-triangulate a list of index sequences (each of length >= 3), keeping order."""
    tris = []
    for poly in polygons:
        if len(poly) == 3:
            tris.append(poly)
        else:
            v0 = poly[0]
            tris.extend((v0, poly[i], poly[i + 1]) for i in range(1, len(poly) - 1))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


_OBJ_V_RE = re.compile(r"^[ \t]*v[ \t]+([^\n]*)", re.M)
_OBJ_F_RE = re.compile(r"^[ \t]*f[ \t]+([^\n]*)", re.M)
_OBJ_SLASH_RE = re.compile(r"/\S*")


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """OBJ reader: ``v`` and ``f`` records only, order preserved, bad indices kept.

    A vectorised path handles the common case (3 coordinates per ``v``, positive indices,
    triangles); anything else (polygons, negative indices, extra fields, malformed
    records) goes through the line-by-line reader, which reports the offending line.
    """
    text = path.read_text(encoding="utf-8", errors="replace")
    fast = _read_obj_fast(text)
    return fast if fast is not None else _read_obj_lines(text.splitlines())


def _read_obj_fast(text: str):
    v_rows = _OBJ_V_RE.findall(text)
    f_rows = _OBJ_F_RE.findall(text)
    # every record must have exactly 3 fields (a 4-field row and a 2-field row would
    # otherwise add up to a plausible total)
    if any(len(r.split()) != 3 for r in v_rows) or any(len(r.split()) != 3 for r in f_rows):
        return None
    v_tok = " ".join(v_rows).split()
    f_str = " ".join(f_rows)
    if "/" in f_str:
        f_str = _OBJ_SLASH_RE.sub("", f_str)
    f_tok = f_str.split()
    try:
        V = np.array(v_tok, dtype=np.float64).reshape(-1, 3)
        F = np.array(f_tok, dtype=np.int64).reshape(-1, 3)
    except ValueError:
        return None
    if F.size and F.min() <= 0:  # relative (negative) or invalid 0 indices
        return None
    return V, F - 1


def _read_obj_lines(lines) -> tuple[np.ndarray, np.ndarray]:
    verts: list[list[float]] = []
    polys: list[list[int]] = []
    for lineno, line in enumerate(lines, 1):
        line = line.lstrip()
        if not line or line[0] not in "vf":  # fast skip of vt/vn/#/g/usemtl/l/...
            continue
        parts = line.split()
        tag = parts[0]
        if tag == "v":
            if len(parts) < 4:
                raise _ReadError(f"line {lineno}: vertex needs 3 coordinates: {line.strip()!r}")
            try:
                verts.append([float(parts[1]), float(parts[2]), float(parts[3])])
            except ValueError:
                raise _ReadError(
                    f"line {lineno}: bad vertex coordinates: {line.strip()!r}"
                ) from None
        elif tag == "f":
            if len(parts) < 4:
                raise _ReadError(
                    f"line {lineno}: face needs at least 3 vertices: {line.strip()!r}"
                )
            n = len(verts)
            poly = []
            for tok in parts[1:]:
                try:
                    i = int(tok.split("/", 1)[0])
                except ValueError:
                    raise _ReadError(f"line {lineno}: bad face index {tok!r}") from None
                if i == 0:
                    raise _ReadError(
                        f"line {lineno}: face index 0 is invalid (OBJ indices start at 1)"
                    )
                # 1-based; negative indices count back from the latest vertex.
                poly.append(i - 1 if i > 0 else n + i)
            polys.append(poly)
    V = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    return V, _fan(polys)


def _read_off(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """ASCII OFF reader (``OFF``/``COFF``/``NOFF``/... headers, n-gon faces).

    Vertex lines may carry extra fields (normals, colours); only x y z are used.
    """
    text = path.read_text(encoding="utf-8", errors="replace")
    if "#" in text:
        text = "\n".join(ln.split("#", 1)[0] for ln in text.splitlines())
    tokens = text.split()
    # Fast path: "[OFF] nv nf ne", then exactly 3 numbers per vertex, triangles only.
    pos = 1 if tokens and tokens[0].endswith("OFF") else 0
    try:
        nv, nf, _ = (int(x) for x in tokens[pos:pos + 3])
        body = tokens[pos + 3:]
        if nv >= 0 and nf >= 0 and len(body) == 3 * nv + 4 * nf and all(c == "3" for c in body[3 * nv::4]):
            V = np.array(body[:3 * nv], dtype=np.float64).reshape(-1, 3)
            F = np.array(body[3 * nv:], dtype=np.int64).reshape(-1, 4)[:, 1:]
            return V, F
    except ValueError:
        pass
    # General path, line by line: extra per-vertex fields, polygons, errors.
    lines = [ln.split() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise _ReadError("empty OFF file")
    head = lines[0]
    if re.fullmatch(r"(ST)?C?N?OFF", head[0]):
        if len(head) > 1 and head[1].upper() == "BINARY":
            raise _ReadError("binary OFF is not supported")
        if len(head) > 1:  # "OFF nv nf ne" on one line
            counts, data = head[1:], lines[1:]
        else:
            counts, data = (lines[1] if len(lines) > 1 else []), lines[2:]
    elif head[0].isdigit():  # header-less
        counts, data = head, lines[1:]
    else:
        raise _ReadError(f"not an OFF file (header {head[0]!r})")
    try:
        nv, nf = int(counts[0]), int(counts[1])
    except (ValueError, IndexError):
        raise _ReadError(f"bad OFF counts line {' '.join(counts)!r}") from None
    if nv < 0 or nf < 0:
        raise _ReadError(f"negative OFF counts {nv} vertices, {nf} faces")
    if len(data) < nv + nf:
        raise _ReadError(
            f"OFF file is truncated: expected {nv} vertex and {nf} face lines, "
            f"found {len(data)}"
        )
    try:
        V = np.array([x for ln in data[:nv] for x in ln[:3]], dtype=np.float64).reshape(-1, 3)
        polys = []
        for ln in data[nv:nv + nf]:
            k = int(ln[0])
            if k < 3 or len(ln) < k + 1:
                raise _ReadError(f"bad OFF face {' '.join(ln)!r}")
            polys.append([int(x) for x in ln[1:k + 1]])
    except ValueError as e:
        raise _ReadError(f"bad OFF data ({e})") from None
    return V, _fan(polys)


def _read_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    loaded = trimesh.load(str(path), process=False, maintain_order=True)
    if isinstance(loaded, trimesh.Scene):
        geoms = list(loaded.dump())
        if not geoms:
            raise _ReadError("no mesh data found (empty or unreadable file)")
        meshes = [g for g in geoms if isinstance(g, trimesh.Trimesh)]
        if not meshes:
            n = sum(len(getattr(g, "vertices", ())) for g in geoms)
            return np.zeros((n, 3)), np.zeros((0, 3), dtype=np.int64)
        loaded = meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
    V = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    F = getattr(loaded, "faces", None)  # a PointCloud has no faces
    F = np.zeros((0, 3), dtype=np.int64) if F is None else np.asarray(F).reshape(-1, 3)
    return V.reshape(-1, 3), F


def _read_meshio(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import meshio

    m = meshio.read(str(path))
    polys = []
    for block in m.cells:
        if block.type == "triangle":
            polys.append(np.asarray(block.data, dtype=np.int64))
        elif block.type == "quad" or block.type.startswith("polygon"):
            polys.append(_fan(np.asarray(block.data, dtype=np.int64).tolist()))
    F = np.concatenate(polys) if polys else np.zeros((0, 3), dtype=np.int64)
    V = np.asarray(m.points, dtype=np.float64)
    if V.ndim == 2 and V.shape[1] == 2:  # planar formats: z = 0
        V = np.concatenate([V, np.zeros((len(V), 1))], axis=1)
    return V, F


def read_mesh(path, frame: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read one triangle mesh file into ``(V float32 (N, 3), F int32 (M, 3))``.

    Vertex order is preserved as stored (no merging or reordering); polygons are
    fan-triangulated. ``frame`` only labels error messages. See the module docstring for
    formats and decisions.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        MeshDataError: the file is unreadable or corrupt, has no vertices, has no triangle
            faces (points/lines only), has NaN/inf coordinates or out-of-range face indices.
            The message names the file (and ``frame`` when given).
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise _not_found(path)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "expected a mesh file, got a folder", str(path))
    where = f"{path}" if frame is None else f"{path}, frame {frame}"
    ext = _mesh_extension(path.name) or path.suffix.lower()
    try:
        if ext == ".obj":
            V, F = _read_obj(path)
        elif ext == ".off":
            V, F = _read_off(path)
        elif ext in _TRIMESH_READERS:
            V, F = _read_trimesh(path)
        else:
            V, F = _read_meshio(path)
    except _ReadError as e:
        raise MeshDataError(f"{where}: {e}") from None
    except Exception as e:  # corrupt/unsupported file: surface the reason with the name
        reason = f"{type(e).__name__}: {e}".rstrip(": ")
        raise MeshDataError(f"{where}: cannot read mesh file ({reason})") from e
    V = np.asarray(V)
    F = np.asarray(F)
    if V.size == 0:
        raise MeshDataError(f"{where}: mesh is empty (no vertices)")
    if F.size == 0:
        raise MeshDataError(
            f"{where}: no triangle faces ({len(V)} vertices but no faces; "
            "point clouds and line sets are not meshes)"
        )
    return validate_mesh(V, F, source=str(path), frame=frame)


# npz array names: the canonical V (T, N, 3) / F (M, 3) first, then common aliases
_NPZ_VERTEX_KEYS = ("V", "vertices", "verts", "points")
_NPZ_FACE_KEYS = ("F", "faces", "triangles")


def _npz_scalar(data, key, path, cast):
    if key not in data.files:
        return None
    try:
        return cast(np.asarray(data[key]).reshape(()).item())
    except Exception as e:
        raise MeshDataError(f"{path}: bad '{key}' entry ({e})") from e


def _load_npz(path: Path, fps, kind: str):
    if not zipfile.is_zipfile(path):
        raise MeshDataError(f"{path}: not an npz file (a zip archive of arrays, as numpy.savez writes)")
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as e:
        raise MeshDataError(f"{path}: cannot read npz file ({type(e).__name__}: {e})") from e
    with data:
        keys = set(data.files)
        name = _npz_scalar(data, "name", path, str) or path.stem
        file_fps = _npz_scalar(data, "fps", path, float)
        fps = fps if fps is not None else (file_fps if file_fps is not None else DEFAULT_FPS)
        vkey = next((k for k in _NPZ_VERTEX_KEYS if k in keys), None)
        fkey = next((k for k in _NPZ_FACE_KEYS if k in keys), None)
        try:
            if vkey and fkey:
                V, F = np.asarray(data[vkey]), np.asarray(data[fkey])
                if V.ndim == 2:  # one frame (N, 3): a static mesh
                    V = V[None]
                if F.ndim == 2 and F.shape[1] == 4:  # quads: two triangles each, as for files
                    F = F[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3)
                seq = FixedTopologySequence(V, F, fps=fps, name=name, source=str(path))
                return seq.to_varying() if kind == "varying" else seq
            packed = {"V_packed", "F_packed", "V_offsets", "F_offsets"}
            if packed <= keys:
                frames = _unpack_frames(
                    path, data["V_packed"], data["F_packed"], data["V_offsets"],
                    data["F_offsets"],
                )
            else:
                raise MeshDataError(
                    f"{path}: unknown npz layout; expected arrays 'V' and 'F' (fixed "
                    f"topology; also read as {', '.join(_NPZ_VERTEX_KEYS[1:])} / "
                    f"{', '.join(_NPZ_FACE_KEYS[1:])}) or {sorted(packed)} (varying topology), "
                    f"found {sorted(keys)}"
                )
        except MeshDataError:
            raise
        except Exception as e:  # e.g. a corrupt member inside the zip
            raise MeshDataError(f"{path}: cannot read npz data ({type(e).__name__}: {e})") from e
    seq = VaryingTopologySequence(frames, fps=fps, name=name, source=str(path))
    return _finish_kind(seq, kind)


def _unpack_frames(path, Vp, Fp, vo, fo):
    Vp, Fp, vo, fo = (np.asarray(a) for a in (Vp, Fp, vo, fo))
    for key, off, rows in (("V_offsets", vo, len(Vp)), ("F_offsets", fo, len(Fp))):
        if off.ndim != 1 or len(off) < 2 or not np.issubdtype(off.dtype, np.integer):
            raise MeshDataError(f"{path}: '{key}' must be a 1-D integer array of length T+1")
        if off[0] != 0 or off[-1] != rows or np.any(np.diff(off) < 0):
            raise MeshDataError(
                f"{path}: '{key}' must start at 0, not decrease and end at {rows} "
                f"(got {off[0]} ... {off[-1]})"
            )
    if len(vo) != len(fo):
        raise MeshDataError(
            f"{path}: 'V_offsets' and 'F_offsets' disagree on the frame count "
            f"({len(vo) - 1} vs {len(fo) - 1})"
        )
    return [(Vp[vo[t]:vo[t + 1]], Fp[fo[t]:fo[t + 1]]) for t in range(len(vo) - 1)]


def _finish_kind(seq: VaryingTopologySequence, kind: str):
    """Apply ``kind`` to a varying sequence ("auto" -> fixed when topology is identical)."""
    if kind == "varying":
        return seq
    if kind == "fixed" or seq.is_fixed_topology():
        return seq.to_fixed()
    return seq


def _list_frame_files(folder: Path) -> list[Path]:
    """Mesh files in ``folder`` ordered by the last integer in their stem."""
    files = [
        p for p in folder.iterdir()
        if not p.name.startswith(".") and _mesh_extension(p.name) and p.is_file()
    ]
    if not files:
        subdirs = sorted(p.name for p in folder.iterdir()
                         if p.is_dir() and not p.name.startswith("."))
        hint = f"; subfolders: {', '.join(subdirs)} (pass subdir=...)" if subdirs else ""
        npz = sorted(p.name for p in folder.glob("*.npz"))
        if npz:
            hint += f"; it holds .npz files ({', '.join(npz[:3])}{' ...' if len(npz) > 3 else ''}): load one directly"
        raise MeshDataError(
            f"{folder}: no mesh files found (looked for {', '.join(sorted(MESH_EXTENSIONS))})"
            f"{hint}"
        )
    exts = sorted({_mesh_extension(p.name) for p in files})
    if len(exts) > 1:
        examples = ", ".join(
            next(p.name for p in sorted(files) if _mesh_extension(p.name) == e) for e in exts
        )
        raise MeshDataError(
            f"{folder}: ambiguous folder, it holds meshes of several extensions "
            f"({', '.join(exts)}; e.g. {examples}); keep one format per folder"
        )
    by_index: dict[int, Path] = {}
    for p in sorted(files):
        i = frame_index_from_name(p)  # raises naming the file
        if i in by_index:
            raise MeshDataError(
                f"{folder}: two files have frame index {i}: {by_index[i]} and {p}"
            )
        by_index[i] = p
    order = sorted(by_index)
    # the first gaps only: indices may be far apart (frame_0, frame_99999999999)
    missing = [i for a, b in zip(order, order[1:]) for i in range(a + 1, min(b, a + 12))][:11]
    if missing:
        more = order[-1] - order[0] + 1 - len(order) > 10
        shown = ", ".join(map(str, missing[:10])) + (" ..." if more else "")
        warnings.warn(
            f"{folder}: frame numbering has gaps (missing {shown}); frames are taken in "
            "order and played at a constant fps",
            stacklevel=4,  # _list_frame_files <- _load_folder <- load_sequence <- caller
        )
    return [by_index[i] for i in order]


def _load_folder(folder: Path, fps, kind: str, name: str):
    files = _list_frame_files(folder)
    frames = [read_mesh(p, frame=t) for t, p in enumerate(files)]
    fps = DEFAULT_FPS if fps is None else fps
    seq = VaryingTopologySequence(
        frames, fps=fps, name=name, source=str(folder),
        frame_sources=[str(p) for p in files],
    )
    return _finish_kind(seq, kind)


def _resolve_folder(path: Path, subdir: str | None) -> Path:
    """Pick the folder holding the frames (``subdir``, a DG-Mesh subfolder, or ``path``)."""
    if subdir is not None:
        folder = path / subdir
        if not folder.is_dir():
            raise _not_found(folder)
        return folder
    for sub in DGMESH_SUBDIRS:  # preference order: dynamic_mesh, then mesh_gt
        if (path / sub).is_dir():
            return path / sub
    return path


def load_sequence(
    path, fps: float | None = None, kind: str = "auto", subdir: str | None = None,
    frame_order: str = "stored",
) -> FixedTopologySequence | VaryingTopologySequence:
    """Load an animated mesh sequence from a ``.npz`` file, a mesh file or a folder.

    Args:
        path: a ``.npz`` file, a single mesh file, a folder of per-frame meshes, or a
            DG-Mesh scene folder (with ``dynamic_mesh/`` and/or ``mesh_gt/``).
        fps: frame rate; overrides the npz ``fps``. Default: the npz ``fps``, else 24.0.
        kind: ``"auto"`` (fixed when all frames share vertex count and faces, else
            varying), ``"fixed"`` (raise :class:`MeshDataError` naming the file and frame
            when they do not) or ``"varying"``.
        subdir: for a folder, load ``path / subdir`` (e.g. ``"mesh_gt"``); by default a
            DG-Mesh ``dynamic_mesh`` subfolder is preferred over ``mesh_gt``.
        frame_order: ``"stored"`` keeps the frames of an npz as stored (a warning is given when
            they look sorted as text: 1, 10, 11, ..., 2, 20, ...); ``"text_sorted"`` undoes such
            a text sort (frame numbers from 1, or from 0 when that moves less per frame);
            ``"auto"`` undoes it only when detected (with a warning saying so).

    Raises:
        FileNotFoundError: ``path`` (or ``path / subdir``) does not exist.
        MeshDataError: empty folder, ambiguous or unnumbered files, unreadable/invalid
            meshes, or frames that cannot form the requested ``kind``.

    See the module docstring for the layouts and ordering rules.
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
    path = Path(path).expanduser()
    if not path.exists():
        raise _not_found(path)
    if path.is_dir():
        folder = _resolve_folder(path, subdir)
        return _load_folder(folder, fps, kind, name=path.name or str(path))
    if subdir is not None:
        raise ValueError(f"{path}: subdir= applies to folders, but this is a file")
    frame_order = parse(FrameOrder, frame_order, "frame_order").value
    if path.suffix.lower() == ".npz":
        return _fix_frame_order(_load_npz(path, fps, kind), frame_order, path)
    V, F = read_mesh(path)
    fps = DEFAULT_FPS if fps is None else fps
    seq = FixedTopologySequence(V[None], F, fps=fps, name=path.stem, source=str(path))
    return seq.to_varying() if kind == "varying" else seq


def _fix_frame_order(seq, frame_order: str, path: Path):
    """Detect (warn) or undo a text sort of the frames of a fixed-topology npz."""
    if not isinstance(seq, FixedTopologySequence):
        return seq
    from .sequence import detect_text_sorted_frames, text_sorted_permutation

    start = detect_text_sorted_frames(seq.V)
    if frame_order == "text_sorted":
        if start is None:
            start = 1
        return seq.reordered(text_sorted_permutation(seq.num_frames, start))
    if frame_order == "auto" and start is not None:
        warnings.warn(f"{path}: the frames look sorted as text (1, 10, 11, ..., 2, 20, ...): restored "
                      "numeric order (frame_order='auto')", stacklevel=3)
        return seq.reordered(text_sorted_permutation(seq.num_frames, start))
    if start is not None:
        warnings.warn(
            f"{path}: the frames look sorted as text (1, 10, 11, ..., 2, 20, ...): numeric order moves "
            "far less per frame. Load with frame_order='text_sorted' (scene: surface.frame_order: "
            "text_sorted) to restore it.", stacklevel=3)
    return seq


# --------------------------------------------------------------------------- writing


def _write_ply(fh, V: np.ndarray, F: np.ndarray) -> None:
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    fh.write(header.encode("ascii"))
    fh.write(np.ascontiguousarray(V, dtype="<f4").tobytes())
    faces = np.empty(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = F
    fh.write(faces.tobytes())


def _write_obj(fh, V: np.ndarray, F: np.ndarray) -> None:
    # %.9g round-trips float32 exactly.
    fh.write(("v %.9g %.9g %.9g\n" * len(V) % tuple(V.astype(np.float64).ravel()))
             .encode("ascii"))
    fh.write(("f %d %d %d\n" * len(F) % tuple((F.astype(np.int64) + 1).ravel()))
             .encode("ascii"))


def _write_off(fh, V: np.ndarray, F: np.ndarray) -> None:
    fh.write(f"OFF\n{len(V)} {len(F)} 0\n".encode("ascii"))
    fh.write(("%.9g %.9g %.9g\n" * len(V) % tuple(V.astype(np.float64).ravel()))
             .encode("ascii"))
    fh.write(("3 %d %d %d\n" * len(F) % tuple(F.astype(np.int64).ravel())).encode("ascii"))


_OWN_WRITERS = {".ply": _write_ply, ".obj": _write_obj, ".off": _write_off}


def _write_mesh_file(path: Path, V: np.ndarray, F: np.ndarray) -> None:
    """Write one mesh to ``path`` (not atomic; callers write to a temporary name)."""
    ext = path.suffix.lower()
    if ext in _OWN_WRITERS:
        with open(path, "wb") as fh:
            _OWN_WRITERS[ext](fh, V, F)
            fh.flush()
            os.fsync(fh.fileno())
    elif ext in (".stl", ".glb", ".gltf"):
        import trimesh

        trimesh.Trimesh(V, F, process=False).export(str(path))
    else:
        import meshio

        meshio.write(str(path), meshio.Mesh(V, [("triangle", F)]))


def _current_umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def _atomic_file(path: Path, write) -> None:
    """Call ``write(tmp_path)`` on a temporary sibling of ``path``, then rename into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}",
                               dir=path.parent)
    os.close(fd)
    from .outputs import _COMMIT, temporary

    with temporary(tmp):  # a hard exit (second Ctrl-C) removes it
        try:
            write(Path(tmp))
            with _COMMIT:
                os.chmod(tmp, 0o666 & ~_current_umask())  # mkstemp makes 0600: give the user's umask
                os.replace(tmp, path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise


def write_mesh(path, V, F) -> None:
    """Write one triangle mesh atomically; the format follows the extension of ``path``.

    ``.ply`` (binary, float32), ``.obj`` and ``.off`` use this module's writers, which keep
    vertex order; ``.stl``/``.glb``/``.gltf`` go through trimesh (``process=False``) and
    other extensions through meshio. The mesh is validated first (``MeshDataError``).
    """
    path = Path(path).expanduser()
    V, F = validate_mesh(V, F, source=str(path))
    _atomic_file(path, lambda tmp: _write_mesh_file(tmp, V, F))


def _save_npz(seq, path: Path, status: dict | None = None) -> None:
    if isinstance(seq, FixedTopologySequence):
        arrays = {"V": seq.V, "F": seq.F}
    else:
        Vs = [v for v, _ in seq.frames]
        Fs = [f for _, f in seq.frames]
        arrays = {
            "V_packed": np.concatenate(Vs).astype(np.float32),
            "F_packed": np.concatenate(Fs).astype(np.int32),
            "V_offsets": np.concatenate([[0], np.cumsum([len(v) for v in Vs])]).astype(np.int64),
            "F_offsets": np.concatenate([[0], np.cumsum([len(f) for f in Fs])]).astype(np.int64),
        }
    arrays["fps"] = np.asarray(seq.fps, dtype=np.float32)
    arrays["name"] = np.asarray(str(seq.name))
    if status is not None:
        arrays["status"] = np.asarray(json.dumps(status))

    def write(tmp: Path):
        with open(tmp, "wb") as fh:  # a file object keeps numpy from appending ".npz"
            np.savez(fh, **arrays)
            fh.flush()
            os.fsync(fh.fileno())

    _atomic_file(path, write)


def _save_folder(seq, folder: Path, fmt: str, overwrite: bool = False, status: dict | None = None) -> None:
    from .outputs import OutputFolder

    with OutputFolder(folder, overwrite=overwrite, status=status) as tmp:
        for t in range(seq.num_frames):
            V, F = seq.frame(t)
            _write_mesh_file(tmp / f"frame_{t:04d}.{fmt}", V, F)


def save_sequence(seq, path, fmt: str | None = None, overwrite: bool = False, status: dict | None = None) -> None:
    """Save a sequence atomically to a ``.npz`` file or a folder of per-frame meshes.

    Args:
        seq: a :class:`FixedTopologySequence` or :class:`VaryingTopologySequence`.
        path: ``*.npz`` for one file (fixed layout ``V``/``F``/``fps``/``name``, or the
            packed varying layout ``V_packed``/``F_packed``/``V_offsets``/``F_offsets``/
            ``fps``/``name``); otherwise a folder that receives ``frame_{i:04d}.{fmt}``.
        fmt: ``"ply"`` or ``"obj"`` for a folder (required there); ``None``/``"npz"`` for
            an ``.npz`` path.

    An existing folder is replaced at the very end, and only when everything in it was written
    by this tool (listed in its manifest, see :mod:`dynmesh_warp.outputs`); else
    :class:`FileExistsError`, unless ``overwrite`` (then the files this tool did not write
    are kept in the new folder).

    ``status``: a JSON-ready dict saved with the sequence (the npz's ``status`` array, JSON
    text; a folder's manifest, under ``"status"``), e.g. ``convert``'s frame counts and whether it
    was interrupted. Readers ignore it.
    """
    if not isinstance(seq, (FixedTopologySequence, VaryingTopologySequence)):
        raise TypeError(f"expected a FixedTopologySequence or VaryingTopologySequence, "
                        f"got {type(seq).__name__}")
    path = Path(path).expanduser()
    fmt = fmt.lower().lstrip(".") if fmt else None
    if path.suffix.lower() == ".npz":
        if fmt not in (None, "npz"):
            raise ValueError(f"{path}: fmt={fmt!r} conflicts with the .npz extension")
        _save_npz(seq, path, status)
        return
    if fmt == "npz":
        raise ValueError(f"{path}: an npz output path must end in .npz")
    if fmt not in ("ply", "obj"):
        raise ValueError(
            f"{path}: to save a folder of frames give fmt='ply' or fmt='obj' "
            f"(got {fmt!r}); use a .npz path for a single file"
        )
    _save_folder(seq, path, fmt, overwrite, status)
