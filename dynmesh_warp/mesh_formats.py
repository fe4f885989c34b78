"""Mesh file formats: one reader and one writer per extension, in two registries (issue 13).

``READERS`` maps an extension (lower case, with the dot) to ``reader(path) -> (V, F)`` and
``WRITERS`` maps one to ``writer(fh, V, F)`` (a binary file object); :func:`register_format`
adds a format. ``read_mesh`` falls back to meshio for an extension with no reader, and
``write_mesh_file`` to trimesh (``.stl``, ``.glb``, ``.gltf``) or meshio. The formats and the
decisions behind them (vertex order kept, fan triangulation, errors naming the file) are in
docs/data.md; ``dynmesh_warp.io`` is the public face (``read_mesh``, ``write_mesh``).
"""

from __future__ import annotations

import errno
import os
import re
import struct
from pathlib import Path

import numpy as np

from .outputs import atomic_path
from .sequence import MeshDataError, unit_colors, validate_mesh

__all__ = ["READERS", "WRITERS", "MESH_EXTENSIONS", "register_format", "mesh_extension", "file_problem", "read_mesh",
           "read_vertex_colors", "write_mesh_file", "write_mesh"]

_OWN_READERS = (".obj", ".off")
_TRIMESH_READERS = (".ply", ".stl", ".glb", ".gltf")
# Extensions meshio can read but which are usually not meshes in a data folder
# (read_mesh still reads them when given such a file explicitly).
_NOT_FRAME_EXTENSIONS = {".svg", ".xml", ".dat", ".node"}


#: animation formats people have that are not read, by extension, for a hint instead of a parse error
UNREAD_ANIMATIONS = {".abc": "Alembic", ".fbx": "FBX", ".usd": "USD", ".usda": "USD", ".usdc": "USD",
                     ".usdz": "USD", ".bvh": "BVH (a skeleton without a surface)", ".blend": "Blender"}


#: ``asset.extras`` of a glTF file whose z-up coordinates were turned to glTF's +Y up on writing
#: (``write_mesh``, ``gltf_animation.write_gltf_animation``): the readers turn them back, so a save
#: and a load give the coordinates saved. A tool that writes the file again drops it, and the file
#: is then read as any glTF (+Y up), so a scene turns it the same way up (docs/data.md)
Z_UP_MARK = {"dynmesh_warp": {"turned_from_up_axis": "z"}}
GLTF_SUFFIXES = (".glb", ".gltf")


def z_to_y(V: np.ndarray) -> np.ndarray:
    """z-up coordinates as +Y up: (x, y, z) -> (x, z, -y), exactly (a permutation and a sign)."""
    return V[..., [0, 2, 1]] * np.array([1, 1, -1], V.dtype)


def y_to_z(V: np.ndarray) -> np.ndarray:
    """The inverse of :func:`z_to_y`: (x, y, z) -> (x, -z, y)."""
    return V[..., [0, 2, 1]] * np.array([1, -1, 1], V.dtype)


def srgb_to_linear(c) -> np.ndarray:
    """sRGB colours in [0, 1] as linear light (glTF's ``COLOR_0`` space)."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, np.power((c + 0.055) / 1.055, 2.4))


def linear_to_srgb(c) -> np.ndarray:
    """The inverse of :func:`srgb_to_linear` (the space a PLY's or OBJ's colours are in)."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def gltf_marked(doc) -> bool:
    """Whether a glTF JSON document carries :data:`Z_UP_MARK` (its coordinates turned from z-up)."""
    asset = doc.get("asset", {}) if isinstance(doc, dict) else {}
    extras = asset.get("extras") if isinstance(asset, dict) else None
    return isinstance(extras, dict) and extras.get("dynmesh_warp") == Z_UP_MARK["dynmesh_warp"]


def gltf_json(path):
    """A .glb's JSON chunk (reading only the header and that chunk, which the specification puts
    first, not the binary buffer) or a .gltf's JSON, parsed; None when it is neither (unreadable,
    not JSON, not laid out so)."""
    import json

    try:
        with open(path, "rb") as fh:
            head = fh.read(20)
            if head[:4] == b"glTF" and len(head) == 20:
                size, kind = struct.unpack_from("<II", head, 12)
                return json.loads(fh.read(size).decode("utf-8")) if kind == 0x4E4F534A else None
            return json.loads((head + fh.read()).decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None


def _marked_gltf_bytes(data: bytes, glb: bool) -> bytes:
    """A glTF file's bytes with :data:`Z_UP_MARK` in its ``asset.extras`` (the JSON chunk of a .glb
    rewritten, padded with spaces to 4 bytes as the specification asks)."""
    import json

    if not glb:
        doc = json.loads(data.decode("utf-8"))
        doc.setdefault("asset", {})["extras"] = Z_UP_MARK
        return json.dumps(doc).encode("utf-8")
    n = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + n].decode("utf-8"))
    doc.setdefault("asset", {})["extras"] = Z_UP_MARK
    js = json.dumps(doc).encode("utf-8")
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + data[20 + n:]
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


def _meshio_extensions() -> set[str]:
    try:
        import meshio

        return {e.lower() for e in meshio.extension_to_filetypes}
    except Exception:  # pragma: no cover - meshio is a dependency, but stay importable
        return set()


MESH_EXTENSIONS: set[str] = (set(_OWN_READERS) | set(_TRIMESH_READERS) | _meshio_extensions()) - _NOT_FRAME_EXTENSIONS
"""File extensions (lower case, with dot) treated as per-frame meshes in a folder
(:func:`register_format` adds to it)."""


def mesh_extension(name: str) -> str | None:
    """The mesh extension of a file name (handles ``.vol.gz``-style double suffixes)."""
    lower = name.lower()
    for ext in MESH_EXTENSIONS:
        if ext.count(".") > 1 and lower.endswith(ext):
            return ext
    ext = os.path.splitext(lower)[1]
    return ext if ext in MESH_EXTENSIONS else None


# --------------------------------------------------------------------------- reading


class _ReadError(Exception):
    """Raised by the format readers with a reason; read_mesh adds the file and frame."""


def _not_found(path: Path) -> FileNotFoundError:
    return FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(path))


def file_problem(path) -> str | None:
    """Why ``path`` is not a readable file, in words ("file not found", "a folder, not a file", "a
    symbolic link to X, which does not exist"), or None when it is a file."""
    path = Path(path).expanduser()
    if path.is_file():
        return None
    if path.is_symlink() and not path.exists():
        return f"a symbolic link to {os.readlink(path)}, which does not exist"
    if path.is_dir():
        return "a folder, not a file"
    return "file not found" if not path.exists() else "not a regular file"


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
    text = path.read_text(encoding="utf-8-sig", errors="replace")
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


def _obj_records(lines):
    """(line number, record) of OBJ text: a line ending in a backslash continues on the next
    (the format's line continuation), and a ``#`` starts a comment to the end of the line."""
    pending, start = "", 0
    for lineno, line in enumerate(lines, 1):
        line = line.split("#", 1)[0]
        if not pending:
            start = lineno
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        yield start, pending + line
        pending = ""
    if pending:
        yield start, pending


def _read_obj_lines(lines) -> tuple[np.ndarray, np.ndarray]:
    verts: list[list[float]] = []
    polys: list[list[int]] = []
    for lineno, line in _obj_records(lines):
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
    text = path.read_text(encoding="utf-8-sig", errors="replace")
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
    V = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    F = getattr(loaded, "faces", None)  # a PointCloud has no faces
    F = np.zeros((0, 3), dtype=np.int64) if F is None else np.asarray(F).reshape(-1, 3)
    if path.suffix.lower() in GLTF_SUFFIXES and gltf_marked(gltf_json(path)):
        V = y_to_z(V)  # this project's z-up data, turned to +Y up on writing: as it was saved
    return V, F


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
              "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
              "double": "f8", "float64": "f8"}
"""PLY property types (the specification's names and their sized aliases) -> NumPy type codes."""


def _ply_header(path: Path) -> tuple[str, list, int]:
    """(format, [(element, count, [(property, type or (count type, item type))])], byte offset of
    the data) from a PLY file's header; types are the header's words, checked where read."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    end = re.search(rb"end_header\r?\n", head)
    if not head.startswith(b"ply") or end is None:
        raise _ReadError("not a PLY file, or its header has no end_header line")
    fmt, elements = "", []
    for line in head[:end.start()].decode("latin-1").splitlines():
        tok = line.split()
        if len(tok) >= 2 and tok[0] == "format":
            fmt = tok[1]
        elif len(tok) == 3 and tok[0] == "element":
            try:
                elements.append((tok[1], int(tok[2]), []))
            except ValueError:
                raise _ReadError(f"header: element {tok[1]} has a count that is not a whole number: {tok[2]!r}") from None
        elif len(tok) >= 3 and tok[0] == "property" and elements:
            typ = (tok[2], tok[3]) if tok[1] == "list" and len(tok) == 5 else tok[1]
            elements[-1][2].append((tok[-1], typ))
    return fmt, elements, end.end()


def _ply_type(element: str, prop: str, typ: str, endian: str) -> np.dtype:
    if typ not in _PLY_TYPES:
        raise _ReadError(f"header: element {element} property {prop} has an unknown type {typ!r}")
    return np.dtype(endian + _PLY_TYPES[typ])


def _ply_binary(path: Path, elements: list, start: int, endian: str) -> tuple[dict, bool]:
    """The elements of a binary PLY, ``{element: {property: values}}`` (a list property as
    ``(items, counts)``), and whether every list property holds as many items in every row as in
    the first (the only layout trimesh's binary reader reads: Blender's quads among triangles or
    n-gons failed with "PLY is unexpected length!", or read garbage when the sizes happened to add
    up). Rows of varying lists are walked one by one; their items are gathered at once."""
    buf = path.read_bytes()
    u8 = np.frombuffer(buf, np.uint8)
    off, out, uniform = start, {}, True

    def truncated(name, n):
        return _ReadError(f"truncated: element {name} ({n} rows, as the header declares) reaches past the end "
                          f"of the file ({len(buf) - start:,} bytes of data)")

    for name, n, props in elements:
        types = [(p, (_ply_type(name, p, t[0], endian), _ply_type(name, p, t[1], endian)) if isinstance(t, tuple)
                  else _ply_type(name, p, t, endian)) for p, t in props]
        # every row as the first: one structured view (checked: every count as the first row's)
        fields, pos = [], off
        try:
            for p, t in types:
                if isinstance(t, tuple):
                    k = int(np.frombuffer(buf, t[0], 1, pos)[0]) if n else 0
                    fields += [(p + "#count", t[0]), (p, t[1], (k,))]
                    pos += t[0].itemsize + k * t[1].itemsize
                else:
                    fields.append((p, t))
                    pos += t.itemsize
        except ValueError:  # the first row's count lies past the end
            raise truncated(name, n) from None
        try:
            dt = np.dtype(fields)
        except ValueError:  # a corrupt first count (negative, or beyond any file)
            dt = None
        if dt is not None and off + n * dt.itemsize <= len(buf):
            rows = np.frombuffer(buf, dt, n, off)
            if all(np.all(rows[p + "#count"] == dt[p].shape[0]) for p, t in types if isinstance(t, tuple)):
                out[name] = {p: (rows[p].reshape(-1), np.full(n, dt[p].shape[0])) if isinstance(t, tuple)
                             else rows[p] for p, t in types}
                off += n * dt.itemsize
                continue
        if all(not isinstance(t, tuple) for _, t in types):
            raise truncated(name, n)
        uniform = False  # lists of varying length: walk the rows
        walk = [(p, t, struct.Struct(endian + t[0].char).unpack_from if isinstance(t, tuple) else None) for p, t in types]
        starts = {p: [] for p, _ in types}
        counts = {p: [] for p, t in types if isinstance(t, tuple)}
        try:
            for _ in range(n):
                for p, t, unpack in walk:
                    if unpack is None:
                        starts[p].append(off)
                        off += t.itemsize
                    else:
                        k = unpack(buf, off)[0]
                        off += t[0].itemsize
                        starts[p].append(off)
                        counts[p].append(k)
                        off += k * t[1].itemsize
        except struct.error:
            raise truncated(name, n) from None
        if off > len(buf):
            raise truncated(name, n)
        cols = {}
        for p, t in types:
            item = t[1] if isinstance(t, tuple) else t
            at = np.asarray(starts[p], np.int64)
            if isinstance(t, tuple):
                k = np.asarray(counts[p], np.int64)
                if k.size and k.min() < 0:
                    raise _ReadError(f"element {name} row {int(np.argmax(k < 0))}: property {p} has "
                                     f"{int(k.min())} items")
                first = np.repeat(np.cumsum(k) - k, k)
                at = np.repeat(at, k) + (np.arange(int(k.sum())) - first) * item.itemsize
            vals = u8[at[:, None] + np.arange(item.itemsize)].reshape(-1).view(item)
            cols[p] = (vals, k) if isinstance(t, tuple) else vals
        out[name] = cols
    return out, uniform


def _fan_lists(items: np.ndarray, counts: np.ndarray, element: str = "face") -> np.ndarray:
    """Fan triangles (v0, vi, vi+1) of polygons stored one after another (``counts`` items
    each), in polygon order, as :func:`_fan` makes them."""
    counts = np.asarray(counts, np.int64)
    if counts.size and counts.min() < 3:
        i = int(np.argmax(counts < 3))
        raise _ReadError(f"{element} {i} has {int(counts[i])} vertex indices (a face needs at least 3)")
    first = np.cumsum(counts) - counts
    per = counts - 2
    poly = np.repeat(np.arange(len(counts)), per)
    j = np.arange(int(per.sum())) - np.repeat(np.cumsum(per) - per, per) + 1
    base = first[poly]
    items = np.asarray(items, np.int64)
    return np.stack([items[base], items[base + j], items[base + j + 1]], axis=1).reshape(-1, 3)


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A PLY file through trimesh, checked against its header: an ASCII file cut short (trimesh
    reads what is there without a word) or a vertex count unlike the header's is an error. A
    binary file whose face lists vary in length (quads among triangles or n-gons, as Blender
    writes them) is read by :func:`_ply_binary` and fan-triangulated in face order."""
    fmt, elements, start = _ply_header(path)
    counts = {name: n for name, n, _ in elements}
    nv, nf = counts.get("vertex", 0), counts.get("face", 0)
    if fmt == "ascii":
        with open(path, "rb") as fh:
            fh.seek(start)
            lines = sum(1 for line in fh if line.strip())
        need = sum(counts.values())  # an ASCII element is one line each
        if lines < need:
            raise _ReadError(f"truncated: the header declares {nv} vertices and {nf} faces"
                             + (f" ({need} elements in all)" if need != nv + nf else "")
                             + f" but the file has {lines} data lines")
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        data, uniform = _ply_binary(path, elements, start, "<" if fmt == "binary_little_endian" else ">")
        if not uniform:
            vert = data.get("vertex", {})
            if not all(c in vert and not isinstance(vert[c], tuple) for c in "xyz"):
                raise _ReadError("the vertex element has no x, y, z properties")
            lists = {p: v for p, v in data.get("face", {}).items() if isinstance(v, tuple)}
            name = next((p for p in ("vertex_indices", "vertex_index") if p in lists), None)
            if name is None and len(lists) == 1:
                name = next(iter(lists))
            if name is None:
                raise _ReadError(f"the face element has no vertex_indices list (its lists: {sorted(lists)})")
            V = np.stack([np.asarray(vert[c], np.float64) for c in "xyz"], axis=1).reshape(-1, 3)
            return V, _fan_lists(*lists[name])
    V, F = _read_trimesh(path)
    if len(V) != nv:
        raise _ReadError(f"the header declares {nv} vertices but {len(V)} were read (truncated or corrupt)")
    if len(F) < nf:
        raise _ReadError(f"the header declares {nf} faces but {len(F)} triangles were read (truncated or corrupt)")
    return V, F


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


READERS = {".obj": _read_obj, ".off": _read_off, **{e: _read_trimesh for e in _TRIMESH_READERS}, ".ply": _read_ply}
"""Extension -> ``reader(path) -> (V (N, 3), F (M, 3))``; other extensions go through meshio.
A reader raises any exception for a bad file; ``read_mesh`` names the file and frame."""


def read_mesh(path, frame: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read one triangle mesh file into ``(V float32 (N, 3), F int32 (M, 3))``.

    Vertex order is preserved as stored (no merging or reordering); polygons are
    fan-triangulated. ``frame`` only labels error messages. docs/data.md lists the formats
    and decisions.

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
    if not path.is_file():  # a pipe would be waited on for ever, a device read without end
        raise MeshDataError(f"{where}: not a regular file (a pipe, a device or a socket)")
    ext = mesh_extension(path.name) or path.suffix.lower()
    if ext in UNREAD_ANIMATIONS and ext not in READERS:
        raise MeshDataError(f"{where}: {UNREAD_ANIMATIONS[ext]} files are not read (docs/data.md). Export the "
                            f"animated mesh as a .pc2 or .mdd point cache with its mesh (Blender, Maya, 3ds Max and "
                            f"Houdini all write one) or as one .obj/.ply per frame")
    try:
        V, F = READERS.get(ext, _read_meshio)(path)
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


#: a PLY vertex element's colour properties, in the order looked for (MeshLab/Open3D/trimesh write
#: red green blue; some scanners r g b; older tools diffuse_red ...)
PLY_COLOR_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))


def _ply_colors(path: Path) -> np.ndarray | None:
    fmt, elements, start = _ply_header(path)
    names = {p: t for name, _, props in elements if name == "vertex" for p, t in props}
    rgb = next((c for c in PLY_COLOR_NAMES if all(n in names and not isinstance(names[n], tuple) for n in c)), None)
    if rgb is None:
        faces = {p for name, _, props in elements if name == "face" for p, _ in props}
        if any(all(n in faces for n in c) for c in PLY_COLOR_NAMES):
            import warnings

            warnings.warn(f"{path}: its colours are on its faces, not its vertices: not read (vertex colours "
                          "are: docs/data.md)", stacklevel=4)
        return None
    typ = np.dtype(_PLY_TYPES.get(names[rgb[0]], "f4"))
    top = None if typ.kind == "f" else float(np.iinfo(typ).max)
    if fmt == "ascii":
        skip = 0
        for name, n, props in elements:
            if name == "vertex":
                cols = [i for i, (p, _) in enumerate(props) if p in rgb]
                cols = [cols[[props[i][0] for i in cols].index(c)] for c in rgb]
                with open(path, "rb") as fh:
                    fh.seek(start)
                    rows = [line.split() for line in fh if line.strip()][skip:skip + n]
                try:
                    return unit_colors(np.array([[float(r[i]) for i in cols] for r in rows]).reshape(-1, 3), top)
                except (ValueError, IndexError):
                    raise _ReadError("vertex colours: a vertex line has too few or non-numeric fields") from None
            skip += n
    data, _ = _ply_binary(path, elements, start, ">" if fmt == "binary_big_endian" else "<")
    return unit_colors(np.stack([np.asarray(data["vertex"][c]) for c in rgb], axis=1), top)


def _obj_colors(path: Path) -> np.ndarray | None:
    """``v x y z r g b`` records (MeshLab's, Open3D's): colours when every vertex has them."""
    rows = _OBJ_V_RE.findall(path.read_text(encoding="utf-8-sig", errors="replace"))
    fields = [r.split("#", 1)[0].split() for r in rows]
    some = sum(len(f) >= 6 for f in fields)
    if 0 < some < len(fields):
        import warnings

        warnings.warn(f"{path}: {some} of its {len(fields)} vertices have colours ('v x y z r g b'), the rest none: "
                      "no colours read", stacklevel=4)
    if not fields or some < len(fields):
        return None
    try:
        return unit_colors(np.array([f[3:6] for f in fields], np.float64), None)
    except ValueError:
        raise _ReadError("vertex colours: a 'v x y z r g b' record has a field that is not a number") from None


def _gltf_colors(path: Path) -> np.ndarray | None:
    """A glTF mesh's ``COLOR_0`` (linear) as sRGB, through trimesh as :func:`_read_trimesh` reads
    it (a folder's frames; a single file's are read with its animation)."""
    import trimesh

    loaded = trimesh.load(str(path), process=False, maintain_order=True)
    geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if isinstance(loaded, trimesh.Scene) \
        else [loaded]
    cols = []
    for g in geoms:
        vis = getattr(g, "visual", None)
        if vis is None or getattr(vis, "kind", None) != "vertex":
            return None
        cols.append(np.asarray(vis.vertex_colors)[:, :3] / 255.0)
    return linear_to_srgb(np.concatenate(cols)).astype(np.float32) if cols else None


#: extension -> ``colors(path) -> (N, 3) in [0, 1] or None``
COLOR_READERS = {".ply": _ply_colors, ".obj": _obj_colors, ".glb": _gltf_colors, ".gltf": _gltf_colors}


def read_vertex_colors(path, num_vertices: int | None = None) -> np.ndarray | None:
    """The per-vertex colours a mesh file holds, (N, 3) float32 in [0, 1], or None when it has none
    (or its format's colours are not read: docs/data.md). A PLY's ``red green blue`` (or ``r g b``,
    ``diffuse_*``; integers over their type's maximum), an OBJ's ``v x y z r g b``. Floats above 1
    (but none above 255) are taken as 0..255. ``num_vertices``: the count :func:`read_mesh` gave;
    colours of another count are an error naming the file."""
    path = Path(path).expanduser()
    reader = COLOR_READERS.get(mesh_extension(path.name) or path.suffix.lower())
    if reader is None:
        return None
    try:
        C = reader(path)
    except _ReadError as e:
        raise MeshDataError(f"{path}: {e}") from None
    if C is not None and num_vertices is not None and len(C) != num_vertices:
        raise MeshDataError(f"{path}: {len(C)} vertex colours for {num_vertices} vertices")
    return C


# --------------------------------------------------------------------------- writing


def _byte_colors(colors: np.ndarray) -> np.ndarray:
    return np.round(np.clip(np.asarray(colors, np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)


def _write_ply(fh, V: np.ndarray, F: np.ndarray, colors: np.ndarray | None = None) -> None:
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\n"
        + ("" if colors is None else "property uchar red\nproperty uchar green\nproperty uchar blue\n")
        + f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    fh.write(header.encode("ascii"))
    if colors is None:
        fh.write(np.ascontiguousarray(V, dtype="<f4").tobytes())
    else:
        verts = np.empty(len(V), dtype=[("p", "<f4", (3,)), ("c", "u1", (3,))])
        verts["p"] = V
        verts["c"] = _byte_colors(colors)
        fh.write(verts.tobytes())
    faces = np.empty(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = F
    fh.write(faces.tobytes())


def _write_obj(fh, V: np.ndarray, F: np.ndarray, colors: np.ndarray | None = None) -> None:
    # %.9g round-trips float32 exactly.
    if colors is None:
        fh.write(("v %.9g %.9g %.9g\n" * len(V) % tuple(V.astype(np.float64).ravel()))
                 .encode("ascii"))
    else:  # MeshLab's "v x y z r g b", colours in [0, 1] (4 decimals keep a byte's 1/255 steps)
        rows = np.concatenate([V.astype(np.float64), np.clip(np.asarray(colors, np.float64), 0, 1)], axis=1)
        fh.write(("v %.9g %.9g %.9g %.4f %.4f %.4f\n" * len(V) % tuple(rows.ravel())).encode("ascii"))
    fh.write(("f %d %d %d\n" * len(F) % tuple((F.astype(np.int64) + 1).ravel()))
             .encode("ascii"))


def _write_off(fh, V: np.ndarray, F: np.ndarray) -> None:
    fh.write(f"OFF\n{len(V)} {len(F)} 0\n".encode("ascii"))
    fh.write(("%.9g %.9g %.9g\n" * len(V) % tuple(V.astype(np.float64).ravel()))
             .encode("ascii"))
    fh.write(("3 %d %d %d\n" * len(F) % tuple(F.astype(np.int64).ravel())).encode("ascii"))


WRITERS = {".ply": _write_ply, ".obj": _write_obj, ".off": _write_off}
"""Extension -> ``writer(fh, V, F)`` writing one mesh to a binary file object, keeping vertex
order; other extensions go through trimesh (``.stl``, ``.glb``, ``.gltf``) or meshio."""


def register_format(ext: str, reader=None, writer=None) -> None:
    """Add (or replace) the reader and/or writer of extension ``ext`` (e.g. ``".xyzmesh"``);
    a format with a reader also counts as a per-frame mesh in folders."""
    ext = ext.lower() if ext.startswith(".") else "." + ext.lower()
    if reader is not None:
        READERS[ext] = reader
        MESH_EXTENSIONS.add(ext)
    if writer is not None:
        WRITERS[ext] = writer


def write_mesh_file(path: Path, V: np.ndarray, F: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write one mesh to ``path`` (not atomic; callers write to a temporary name). ``colors``
    (N, 3) in [0, 1]: written by ``.ply`` (uchar ``red green blue``), ``.obj`` (``v x y z r g b``),
    ``.glb``/``.gltf`` (linear ``COLOR_0``, through trimesh); other formats leave them out. A glTF
    is written +Y up, the z-up coordinates turned and marked (:data:`Z_UP_MARK`)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext in WRITERS:
        with open(path, "wb") as fh:
            if colors is not None and WRITERS[ext] in (_write_ply, _write_obj):  # the writers that take colours
                WRITERS[ext](fh, V, F, colors)
            else:
                WRITERS[ext](fh, V, F)
            fh.flush()
            os.fsync(fh.fileno())
    elif ext in GLTF_SUFFIXES:
        # +Y up as glTF says (z-up turned and marked: read back as saved), linear COLOR_0 as it says;
        # the buffers in the one file (a .gltf's were written beside it, as gltf_buffer_0.bin ...)
        import trimesh
        from trimesh.exchange.gltf import export_glb, export_gltf

        vc = None if colors is None else _byte_colors(srgb_to_linear(colors))
        mesh = trimesh.Trimesh(z_to_y(np.asarray(V, np.float64)), F, vertex_colors=vc, process=False)
        data = export_glb(mesh) if ext == ".glb" else export_gltf(mesh, embed_buffers=True)["model.gltf"]
        with open(path, "wb") as fh:
            fh.write(_marked_gltf_bytes(data, ext == ".glb"))
            fh.flush()
            os.fsync(fh.fileno())
    elif ext == ".stl":
        import trimesh

        trimesh.Trimesh(V, F, process=False).export(str(path))
    else:
        import meshio

        meshio.write(str(path), meshio.Mesh(V, [("triangle", F)]))


def write_mesh(path, V, F, colors=None) -> None:
    """Write one triangle mesh atomically; the format follows the extension of ``path``.

    ``.ply`` (binary, float32), ``.obj`` and ``.off`` use this module's writers, which keep
    vertex order; ``.stl``/``.glb``/``.gltf`` go through trimesh (``process=False``) and
    other extensions through meshio. The mesh is validated first (``MeshDataError``).
    """
    path = Path(path).expanduser()
    V, F = validate_mesh(V, F, source=str(path))
    if colors is not None:
        colors = np.asarray(colors, np.float32)
        if colors.shape != V.shape:
            raise MeshDataError(f"{path}: colors must have shape {V.shape} (one RGB per vertex), got {colors.shape}")
    with atomic_path(path, suffix=path.suffix) as tmp:  # the one atomic writer (outputs)
        write_mesh_file(tmp, V, F, colors)
