"""Sequence layouts on disk: the two npz layouts (fixed ``V``/``F``; varying packed
``V_packed``/``F_packed``/``V_offsets``/``F_offsets``), folders of per-frame meshes ordered by
the number in the file name that counts them (:func:`frame_keys`), DG-Mesh scene folders, and the frame-order check of an npz.
docs/data.md is the format spec; ``dynmesh_warp.io`` is the public face (``load_sequence``,
``save_sequence``).
"""

from __future__ import annotations

import errno
import json
import os
import re
import warnings
import zipfile
from pathlib import Path

import numpy as np

from .mesh_formats import MESH_EXTENSIONS, file_problem, mesh_extension, read_mesh, read_vertex_colors
from .sequence import FixedTopologySequence, MeshDataError, VaryingTopologySequence

__all__ = ["DEFAULT_FPS", "DGMESH_SUBDIRS", "frame_index_from_name", "load_npz", "load_vertex_array", "npz_arrays",
           "list_frame_files",
           "load_folder", "resolve_folder", "fix_frame_order", "finish_kind"]

DEFAULT_FPS = 24.0
"""Frame rate assumed for folders, single meshes and npz files that carry no ``fps``."""

DGMESH_SUBDIRS = ("dynamic_mesh", "mesh_gt")
"""DG-Mesh subfolders recognised in a scene folder, in order of preference."""

_INT_RE = re.compile(r"\d+")


def frame_index_from_name(name) -> int:
    """Return the last integer in the stem of a file name or path.

    ``"frame_0010.ply"`` -> 10, ``"horse9.obj"`` -> 9, ``"mesh_gt/bird3.obj"`` -> 3,
    ``"scan_v2_017.obj"`` -> 17. Only the final path component is looked at and only its
    stem (the last extension is removed). Raises :class:`MeshDataError` (a ``ValueError``)
    naming ``name`` when the stem holds no integer.
    """
    found = _frame_number(name)
    if found is None:
        raise MeshDataError(
            f"{name}: file name has no integer frame index (frames in a folder are ordered "
            "by the last integer in the file name, e.g. frame_12.ply)"
        )
    return int(found.group())


def _stem(name) -> str:
    base = Path(str(name)).name
    ext = mesh_extension(base)
    return base[: -len(ext)] if ext and ext.count(".") > 1 else Path(base).stem  # frame_3.vol.gz -> frame_3


def _numbers(name, whole: bool = False) -> tuple[str, list]:
    """(the text looked at, the integer matches in it): a file's stem (``whole``: a folder's whole
    name, whose dots are no extension: ``t0.05``)."""
    text = Path(str(name)).name if whole else _stem(name)
    return text, list(_INT_RE.finditer(text))


def _frame_number(name) -> re.Match | None:
    """The frame number in a file name or path (:func:`frame_index_from_name`'s rule: the last
    integer of the final component's stem) as a match on that component, or None."""
    found = _numbers(name)[1]
    return found[-1] if found else None


def _varying(seen: list) -> list | None:
    """The positions of the integers that differ between the names (``seen``: :func:`_numbers` of
    each), or None where the names hold different counts of integers, or none."""
    n = len(seen[0][1]) if seen else 0
    if not n or any(len(m) != n for _t, m in seen):
        return None
    return [k for k in range(n) if len({m[k].group() for _t, m in seen}) > 1]


def _decimal_keys(seen: list, k: int) -> list:
    """Each name's decimal of integers k - 1 and k (``seen``: :func:`_numbers` of each), with a
    time stamp's minus (``t-0.5``; not a separator after a digit, as in a date ``2024-05-01``)."""
    out = []
    for t, m in seen:
        at = m[k - 1].start()
        neg = at >= 1 and t[at - 1] == "-" and (at < 2 or not t[at - 2].isdigit())
        out.append((-1.0 if neg else 1.0) * float(f"{m[k - 1].group()}.{m[k].group()}"))
    return out


def _key_choice(seen: list):
    """Which of the names' numbers is the frame's (:func:`frame_keys`; ``seen``: :func:`_numbers`
    of each name): ``(kind, k, keys)`` with kind ``"int"`` (integer k of each name) or ``"dec"``
    (integers k - 1 and k joined by a dot: a decimal) and each name's key, or None where there are fewer than two
    names, they hold different counts of integers, none differs, or no differing number has
    distinct values (then the last integer)."""
    varying = _varying(seen) if len(seen) > 1 else None
    if not varying:
        return None
    vals = [[x.group() for x in m] for _t, m in seen]

    def joined(k):  # integers k - 1 and k written "a.b" in every name
        return k > 0 and all(t[m[k - 1].end():m[k].start()] == "." for t, m in seen)

    # a decimal where its integer part differs too (0.9, 1.0) or a fraction has a leading zero
    # (0.05); else "shot1.8" ... "shot1.11" is name 1, frame 8 .. 11 (1.10 read as a decimal came
    # before 1.8: a new user's)
    dec = {k for k in varying if joined(k) and (k - 1 in varying or any(len(v[k]) > 1 and v[k][0] == "0"
                                                                        for v in vals))}
    choices = []
    for k in varying:
        if k + 1 in dec:
            continue  # the integer part of a decimal
        keys = _decimal_keys(seen, k) if k in dec else [int(v[k]) for v in vals]
        if len(set(keys)) == len(keys):
            steps = np.diff(np.sort(np.asarray(keys, float)))
            choices.append((float(steps.max() / steps.min()), -k, ("dec" if k in dec else "int", k, keys)))
    # the number that counts the frames: of those with distinct values, the one whose sorted values
    # step most evenly (frame_000_iter30000, frame_001_iter29500: the frame, not the iteration), the
    # last on a tie
    return min(choices)[2] if choices else None


def frame_keys(files, whole: bool = False) -> tuple[list, str]:
    """The number each of a folder's frame ``files`` is ordered by, and the rule in words
    (``whole``: the files are folders, their whole names read).

    Where every name holds as many numbers, the frame's is one that differs between the files,
    with distinct values: the one whose values step most evenly (a suffix that all share,
    ``frame_000_iter30000`` or ``frame_0000_v2``, is not it, nor is an iteration counter that
    differs; the last on a tie); a decimal time stamp (``mesh_t0.05``: a fraction with a leading
    zero, or an integer part that differs too) by its value (by the last integer ``mesh_t0.1``
    came first: a new user's frames read 0, 2, 4, 6, 8, 1, 3, ...). Otherwise the last integer
    (:func:`frame_index_from_name`, which raises naming a file without one). Keys are ``int``,
    or ``float`` for time stamps."""
    files = list(files)
    seen = [_numbers(f, whole) for f in files]
    choice = _key_choice(seen)
    if choice is None:  # (a name without an integer raises, naming it)
        keys = [int(m[-1].group()) if m else frame_index_from_name(f) for f, (_t, m) in zip(files, seen)]
        return keys, f"the last integer in the {'name' if whole else 'file name'}"
    kind, k, keys = choice
    n = len(seen[0][1])
    where = "the last number" if k == n - 1 else f"number {k + 1} of {n}, the one that counts the frames,"
    return keys, f"{where} in the name" + (" (a decimal: ordered by its value)" if kind == "dec" else "")


# npz array names: the canonical V (T, N, 3) / F (M, 3) first, then common aliases
_NPZ_VERTEX_KEYS = ("V", "vertices", "verts", "points")
#: an npz's per-vertex colours of frame 0: (N, 3), float in [0, 1] or uint8 (docs/data.md)
NPZ_COLOR_KEY = "vertex_colors"
_NPZ_FACE_KEYS = ("F", "faces", "triangles")


def _npz_scalar(data, key, path, cast):
    if key not in data.files:
        return None
    try:
        return cast(np.asarray(data[key]).reshape(()).item())
    except Exception as e:
        raise MeshDataError(f"{path}: bad '{key}' entry ({e})") from e


def _open_npz(path: Path):
    """``np.load`` of an npz (no pickles), or a :class:`MeshDataError` naming the file."""
    if not zipfile.is_zipfile(path):
        raise MeshDataError(f"{path}: not an npz file (a zip archive of arrays, as numpy.savez writes)")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as e:
        raise MeshDataError(f"{path}: cannot read npz file ({type(e).__name__}: {e})") from e


def load_npz(path: Path, fps, kind: str):
    with _open_npz(path) as data:
        keys = set(data.files)
        name = _npz_scalar(data, "name", path, str) or path.stem
        file_fps = _npz_scalar(data, "fps", path, float)
        fps = fps if fps is not None else (file_fps if file_fps is not None else DEFAULT_FPS)
        vkey = next((k for k in _NPZ_VERTEX_KEYS if k in keys), None)
        fkey = next((k for k in _NPZ_FACE_KEYS if k in keys), None)
        try:
            colors = np.asarray(data[NPZ_COLOR_KEY]) if NPZ_COLOR_KEY in keys else None
            if vkey and fkey:
                V, F = np.asarray(data[vkey]), np.asarray(data[fkey])
                if V.ndim not in (2, 3) or V.shape[-1] != 3:
                    raise MeshDataError(f"{path}: array '{vkey}' has shape {V.shape}; expected (T, N, 3) "
                                        "(frames of N vertices) or (N, 3) (one frame)")
                if V.ndim == 2:  # one frame (N, 3): a static mesh
                    V = V[None]
                if F.ndim == 2 and F.shape[1] == 4:  # quads: two triangles each, as for files
                    F = F[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3)
                seq = FixedTopologySequence(V, F, fps=fps, name=name, source=str(path), colors=colors)
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
            if "allow_pickle" in str(e):  # lists of per-frame arrays (np.savez(V=[...], F=[...])): object arrays
                raise MeshDataError(
                    f"{path}: it holds object arrays (per-frame lists saved with np.savez, read only with pickle, "
                    "which is not used); save varying-topology frames packed: V_packed (sum N, 3), F_packed "
                    "(sum M, 3), V_offsets and F_offsets (T + 1,), or with dynmesh_warp.io.save_sequence "
                    "(docs/data.md)") from None
            raise MeshDataError(f"{path}: cannot read npz data ({type(e).__name__}: {e})") from e
    seq = VaryingTopologySequence(frames, fps=fps, name=name, source=str(path), colors=colors)
    return finish_kind(seq, kind)


def npz_holds_faces(path) -> bool:
    """An npz with faces of its own (``F``/``faces``/``triangles``, or the packed varying layout):
    no mesh file next to it gives its faces (``convert`` took a ``horse.glb`` beside ``horse.npz``
    for the npz's faces, and refused ``convert horse.npz horse.glb`` as writing over its input).
    False for an unreadable file (its load says why)."""
    try:
        with _open_npz(Path(path)) as data:
            keys = set(data.files)
    except Exception:
        return False
    return any(k in keys for k in _NPZ_FACE_KEYS) or {"V_packed", "F_packed"} <= keys


def load_vertex_array(path: Path):
    """The vertices of a vertex-only file: an ``.npy`` array, or an npz holding vertices
    (``V``/``vertices``/``verts``/``points``) but no faces, as SMPL / AMASS exports and
    simulation caches often do: ``(V (T, N, 3) or None, fps or None, name)``; ``V`` None when
    the npz has faces (the other layouts). A single frame (N, 3) becomes (1, N, 3)."""
    if path.suffix.lower() == ".npy":
        try:
            V, fps, name = np.load(path, allow_pickle=False), None, path.stem
        except Exception as e:
            raise MeshDataError(f"{path}: cannot read npy file ({type(e).__name__}: {e})") from e
    else:
        with _open_npz(path) as data:
            keys = set(data.files)
            vkey = next((k for k in _NPZ_VERTEX_KEYS if k in keys), None)
            if vkey is None or any(k in keys for k in _NPZ_FACE_KEYS):
                return None, None, path.stem
            try:
                V = np.asarray(data[vkey])
            except Exception as e:  # a corrupt member inside the zip (its header, its data)
                raise MeshDataError(f"{path}: cannot read npz array '{vkey}' ({type(e).__name__}: {e})") from e
            fps = _npz_scalar(data, "fps", path, float)
            name = _npz_scalar(data, "name", path, str) or path.stem
    if V.ndim not in (2, 3) or V.shape[-1] != 3 or not np.issubdtype(V.dtype, np.number):
        raise MeshDataError(f"{path}: vertex array of shape {V.shape} ({V.dtype}); expected (T, N, 3) or (N, 3) numbers")
    return (V[None] if V.ndim == 2 else V), fps, name


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


def finish_kind(seq: VaryingTopologySequence, kind: str):
    """Apply ``kind`` to a varying sequence ("auto" -> fixed when topology is identical)."""
    if kind == "varying":
        return seq
    if kind == "fixed" or seq.is_fixed_topology():
        return seq.to_fixed()
    return seq


def list_frame_files(folder: Path, quiet: bool = False) -> list[Path]:
    """Mesh files in ``folder`` ordered by their frame numbers (:func:`frame_keys`). ``quiet``: no
    warnings on the numbering (for a second look at a folder the loader has read and warned of:
    a new user's gaps were said three times)."""
    named = [p for p in folder.iterdir() if not p.name.startswith(".") and mesh_extension(p.name)]
    broken = sorted(p.name for p in named if p.is_symlink() and not p.exists())
    if broken:  # a frame that is not there must not vanish from the numbering unremarked
        raise MeshDataError(f"{folder / broken[0]}: {file_problem(folder / broken[0])}"
                            + (f" ({len(broken) - 1} more such frame(s))" if len(broken) > 1 else ""))
    odd = sorted(p.name for p in named if p.exists() and not p.is_file() and not p.is_dir())
    if odd:  # a pipe named as a frame was left out of the numbering unremarked
        raise MeshDataError(f"{folder / odd[0]}: not a regular file (a pipe, a device or a socket)"
                            + (f" ({len(odd) - 1} more such frame(s))" if len(odd) > 1 else ""))
    files = [p for p in named if p.is_file()]
    if not files:
        per_frame = _frame_subfolders(folder)
        if per_frame:
            return per_frame
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
    exts = sorted({mesh_extension(p.name) for p in files})
    if len(exts) > 1:
        examples = ", ".join(
            next(p.name for p in sorted(files) if mesh_extension(p.name) == e) for e in exts
        )
        raise MeshDataError(
            f"{folder}: ambiguous folder, it holds meshes of several extensions "
            f"({', '.join(exts)}; e.g. {examples}); keep one format per folder"
        )
    by_index: dict = {}
    files = sorted(files)
    keys, rule = frame_keys(files)  # raises naming a file without a number
    for i, p in zip(keys, files):
        if i in by_index:
            raise MeshDataError(
                f"{folder}: two files have frame index {i:g} ({rule}): {by_index[i]} and {p}; name the frames "
                "with one number that counts them (frame_0000.ply, frame_0001.ply, ...)"
            )
        by_index[i] = p
    order = sorted(by_index)
    if quiet or any(isinstance(i, float) for i in order):  # (time stamps: no gaps or strides to speak of)
        return [by_index[i] for i in order]
    series = _name_series(files)
    if len(series) > 1:  # a new user's frame_0003, mesh_0004 and "frame_0005 (copy)" were joined unsaid
        shown = ", ".join(f"{name!r} ({n} file(s))" for name, n in series[:4]) + (" ..." if len(series) > 4 else "")
        warnings.warn(f"{folder}: its files are named in {len(series)} different ways ({shown}, the frame number as "
                      "#): they are taken as one sequence by their numbers; keep one series of frames per folder",
                      stacklevel=4)  # list_frame_files <- load_folder <- load_sequence <- caller
    # the first gaps only: indices may be far apart (frame_0, frame_99999999999)
    missing = [i for a, b in zip(order, order[1:]) for i in range(a + 1, min(b, a + 12))][:11]
    steps = set(np.diff(order).tolist()) if len(order) > 2 else set()
    if len(steps) == 1 and min(steps) > 1:
        # numbered at a stride (frame_000, frame_010, ...): an export of every k-th frame, not
        # missing ones (a new user's was warned of "gaps (missing 1, 2, 3 ...)" with no word on fps)
        k = min(steps)
        warnings.warn(
            f"{folder}: frames are numbered every {k} ({order[0]}, {order[1]}, {order[2]}, ...): taken in order "
            f"and played at a constant fps, one file a frame; if they were exported every {k}th frame of a "
            f"capture, their rate is the capture's fps / {k} (surface.fps in a scene, convert --fps)",
            stacklevel=4,  # list_frame_files <- load_folder <- load_sequence <- caller
        )
    elif missing:
        more = order[-1] - order[0] + 1 - len(order) > 10
        shown = ", ".join(map(str, missing[:10])) + (" ..." if more else "")
        warnings.warn(
            f"{folder}: frame numbering has gaps (missing {shown}); frames are taken in "
            "order and played at a constant fps",
            stacklevel=4,  # list_frame_files <- load_folder <- load_sequence <- caller
        )
    return [by_index[i] for i in order]


def _frame_subfolders(folder: Path) -> list[Path] | None:
    """The frames of a folder of one subfolder a frame (``0000/mesh.ply``, ``0001/mesh.ply``, ...,
    as per-frame reconstruction outputs are written): where every numbered subfolder holds exactly
    one mesh file, of one extension, those files ordered by the subfolders' numbers
    (:func:`frame_keys`); None where the folder is not laid out so (a new user's was refused with
    "pass subdir=...", which picks one subfolder: one frame)."""
    subdirs = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
    subdirs = [d for d in subdirs if _INT_RE.search(d.name)]
    if len(subdirs) < 2:
        return None
    files, odd = [], []
    for d in subdirs:
        inside = [p for p in d.iterdir() if not p.name.startswith(".") and p.is_file() and mesh_extension(p.name)]
        if len(inside) == 1:
            files.append(inside[0])
        else:
            odd.append((d, len(inside)))
    if odd and len(files) >= len(subdirs) // 2 + 1:  # the layout, but for these: say which
        d, k = odd[0]
        raise MeshDataError(f"{folder}: read as one mesh a subfolder (the frames), but {d.name} holds {k} mesh "
                            f"files" + (f" ({len(odd) - 1} more such subfolder(s))" if len(odd) > 1 else "")
                            + "; keep one mesh file in each frame's subfolder")
    if odd:
        return None
    if len({mesh_extension(p.name) for p in files}) != 1:
        return None
    keys = frame_keys(subdirs, whole=True)[0]
    if len(set(keys)) != len(keys):
        return None
    return [files[i] for i in sorted(range(len(files)), key=lambda i: keys[i])]


def _name_series(files: list[Path]) -> list[tuple[str, int]]:
    """The ways ``files`` are named, each one's frame number (:func:`_frame_number`) written
    ``#``, each with its count, most common first: one for a sequence's frames (``frame_#.obj``)."""
    from collections import Counter

    seen = [_numbers(p) for p in files]
    varying = _varying(seen) or []

    def pattern(p: Path, m: list) -> str:
        if not varying:  # the last integer as #
            last = _frame_number(p)
            return p.name if last is None else p.name[:last.start()] + "#" + p.name[last.end():]
        name, out, at = p.name, "", 0
        for k in varying:  # every number that differs between the names as # (a date that changes too)
            out += name[at:m[k].start()] + "#"
            at = m[k].end()
        return out + name[at:]

    # most common first, then by name (ties in the files' listing order read differently on another file system)
    return sorted(Counter(pattern(p, m) for p, (_t, m) in zip(files, seen)).items(), key=lambda x: (-x[1], x[0]))


def load_folder(folder: Path, fps, kind: str, name: str):
    files = list_frame_files(folder)
    frames = [read_mesh(p, frame=t) for t, p in enumerate(files)]
    colors = read_vertex_colors(files[0], len(frames[0][0])) if files else None  # frame 0's (docs/data.md)
    if fps is None:  # the rate this tool wrote the frames at (its manifest's status), else the default
        from .outputs import read_manifest_status

        fps = (read_manifest_status(folder) or {}).get("fps")
        fps = DEFAULT_FPS if isinstance(fps, bool) or not isinstance(fps, (int, float)) else fps
    seq = VaryingTopologySequence(
        frames, fps=fps, name=name, source=str(folder),
        frame_sources=[str(p) for p in files], colors=colors,
    )
    return finish_kind(seq, kind)


def resolve_folder(path: Path, subdir: str | None) -> Path:
    """Pick the folder holding the frames (``subdir``, a DG-Mesh subfolder, or ``path``)."""
    if subdir is not None:
        folder = path / subdir
        if not folder.is_dir():
            raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(folder))
        return folder
    for sub in DGMESH_SUBDIRS:  # preference order: dynamic_mesh, then mesh_gt
        if (path / sub).is_dir():
            return path / sub
    return path


def fix_frame_order(seq, frame_order: str, path: Path):
    """Detect (warn) or undo a text sort of the frames of a fixed-topology npz; undo it for a
    varying-topology npz when asked (``text_sorted``: numbering from 1; without vertex
    correspondence the order is not detected, it was left as stored, unsaid)."""
    from .sequence import carried, detect_text_sorted_frames, text_sorted_permutation

    if not isinstance(seq, FixedTopologySequence):
        if frame_order == "text_sorted" and seq.num_frames > 1:
            order = text_sorted_permutation(seq.num_frames, 1)
            return type(seq)([seq.frames[int(i)] for i in order], **carried(seq),
                             frame_sources=[seq.frame_sources[int(i)] for i in order] if seq.frame_sources else None)
        return seq

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


def npz_arrays(seq, status: dict | None = None) -> dict:
    """The arrays of ``seq`` in its npz layout: ``V``/``F`` for fixed topology, the packed
    ``V_packed``/``F_packed``/``V_offsets``/``F_offsets`` for varying; ``fps``, ``name`` and,
    when given, ``status`` (JSON text)."""
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
    if seq.colors is not None:
        arrays[NPZ_COLOR_KEY] = seq.colors
    arrays["fps"] = np.asarray(seq.fps, dtype=np.float64)  # float32 read 29.97 back as 29.9699993
    arrays["name"] = np.asarray(str(seq.name))
    if status is not None:
        arrays["status"] = np.asarray(json.dumps(status))
    return arrays
