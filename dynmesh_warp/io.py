"""Reading and writing animated mesh sequences and single meshes: the public face.

``load_sequence(path, fps=None, kind="auto", subdir=None, frame_order="stored")`` reads an npz
(fixed ``V``/``F`` or the packed varying layout), one mesh file, a folder of per-frame meshes
or a DG-Mesh scene folder; ``save_sequence(seq, path, fmt=None)`` writes an npz or a folder of
``frame_{i:04d}.{ply,obj}``; ``read_mesh`` / ``write_mesh`` one mesh; ``frame_index_from_name``
the frame number of a file name. docs/data.md is the format spec (layouts, ordering rules,
decisions, errors).

Where the work is done: ``mesh_formats`` (one reader and one writer per extension, in
registries; ``register_format`` adds one), ``sequence_layouts`` (npz layouts, folder rules,
DG-Mesh folders, frame order). Every write is atomic through ``outputs`` (a temporary sibling
renamed into place; a folder swapped in at the end, replaced only when the tool wrote all of
it, see docs/scene.md, Outputs).
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np

from .animation_formats import (
    ANIMATION_EXTENSIONS,
    CACHE_EXTENSIONS,
    VERTEX_ONLY_EXTENSIONS,
    read_animation,
    topology_faces,
    topology_mesh,
    write_animation,
)
from .choices import Y_UP_FORMATS, FrameOrder, parse
from .gltf_animation import (GENERATOR, GLTF_EXTENSIONS, gltf_generator, gltf_has_animation,
                             gltf_turned_from_z, read_gltf_animation, write_gltf_animation)
from .mesh_formats import (MESH_EXTENSIONS, file_problem, mesh_extension, read_mesh, read_vertex_colors, write_mesh,
                           write_mesh_file)
from .outputs import OutputExistsError, OutputFolder, OutputKind, atomic_path, check_name_length
from .sequence import FixedTopologySequence, MeshDataError, VaryingTopologySequence
from .sequence_layouts import (
    DEFAULT_FPS,
    DGMESH_SUBDIRS,
    fix_frame_order,
    frame_index_from_name,
    list_frame_files,
    load_folder,
    load_npz,
    load_vertex_array,
    npz_arrays,
    resolve_folder,
)

__all__ = [
    "DEFAULT_FPS",
    "MESH_EXTENSIONS",
    "DGMESH_SUBDIRS",
    "ANIMATION_EXTENSIONS",
    "ANIMATED_FILE_OUTPUTS",
    "frame_index_from_name",
    "load_sequence",
    "read_mesh",
    "save_sequence",
    "write_mesh",
]

_KINDS = ("auto", "fixed", "varying")

#: one-file outputs of a fixed-topology sequence besides the npz: the single-file animations
#: and an animated GLB (``save_sequence``; ``convert`` checks its output against the same list)
ANIMATED_FILE_OUTPUTS = ANIMATION_EXTENSIONS + (".glb",)


def _one_file(V, F, fps, file_fps, name: str, path: Path, kind: str, frame_order: str | None = None, colors=None):
    """The fixed sequence of a one-file animation: ``fps`` if given, else the file's, else
    DEFAULT_FPS; the frame-order check of an npz when ``frame_order`` is given; varying when
    ``kind`` asks for it."""
    fps = fps if fps is not None else (file_fps if file_fps is not None else DEFAULT_FPS)
    seq = FixedTopologySequence(V, F, fps=fps, name=name, source=str(path), colors=colors)
    if frame_order is not None:
        seq = fix_frame_order(seq, frame_order, path)
    return seq.to_varying() if kind == "varying" else seq


def _topology_colors(path: Path, num_points: int, topology):
    """The vertex colours of the mesh that gives a vertex-only sequence its faces, or None."""
    return read_vertex_colors(topology_mesh(path, num_points, topology), num_points)


def _no_topology(path: Path, what: str) -> ValueError:
    return ValueError(f"{path}: topology= applies to vertex-only files (point caches {', '.join(CACHE_EXTENSIONS)}, "
                      f"an .npy or an npz of vertices without faces), but {what}")


def load_sequence(
    path, fps: float | None = None, kind: str = "auto", subdir: str | None = None,
    frame_order: str = "stored", topology=None, animation=None,
) -> FixedTopologySequence | VaryingTopologySequence:
    """Load an animated mesh sequence from a ``.npz`` file, a single-file animation, a mesh
    file or a folder.

    Args:
        path: a ``.npz`` file, a single-file animation (``.anime`` of DeformingThings4D, a
            ``.pc2`` or ``.mdd`` point cache, an animated ``.glb`` / ``.gltf``: skins, morph
            targets and node animation sampled at ``fps``), a single mesh file, a folder of
            per-frame meshes, or a DG-Mesh scene folder (with ``dynamic_mesh/`` and/or
            ``mesh_gt/``).
        fps: frame rate; overrides the file's (npz ``fps``, MDD frame times). Default: the
            file's, else 24.0.
        kind: ``"auto"`` (fixed when all frames share vertex count and faces, else
            varying), ``"fixed"`` (raise :class:`MeshDataError` naming the file and frame
            when they do not) or ``"varying"``.
        subdir: for a folder, load ``path / subdir`` (e.g. ``"mesh_gt"``); by default a
            DG-Mesh ``dynamic_mesh`` subfolder is preferred over ``mesh_gt``.
        frame_order: ``"stored"`` keeps the frames of an npz as stored (a warning is given when
            they look sorted as text: 1, 10, 11, ..., 2, 20, ...); ``"text_sorted"`` undoes such
            a text sort (frame numbers from 1, or from 0 when that moves less per frame);
            ``"auto"`` undoes it only when detected (with a warning saying so).
        topology: for a vertex-only file (a ``.pc2`` / ``.mdd`` point cache, an ``.npy``
            array (T, N, 3), an npz of vertices without faces), the mesh file that gives its
            faces; default: the one mesh next to it with the same stem.
        animation: for an animated ``.glb`` / ``.gltf``, the name or index of the animation to
            sample (default: the first).

    Raises:
        FileNotFoundError: ``path`` (or ``path / subdir``) does not exist.
        MeshDataError: empty folder, ambiguous or unnumbered files, unreadable/invalid
            meshes, or frames that cannot form the requested ``kind``.

    docs/data.md gives the layouts and ordering rules.
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
    path = Path(path).expanduser()
    if not path.exists():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(path))
    if animation is not None and (path.is_dir() or path.suffix.lower() not in GLTF_EXTENSIONS):
        raise ValueError(f"{path}: animation= picks one animation of an animated .glb / .gltf, but this is "
                         f"{'a folder' if path.is_dir() else 'a ' + (path.suffix or 'file without extension')}")
    if path.is_dir():
        if topology is not None:
            raise _no_topology(path, "this is a folder")
        if parse(FrameOrder, frame_order, "frame_order") != FrameOrder.STORED:  # accepted and ignored before
            raise ValueError(f"{path}: frame_order (--frame-order) {frame_order!r} reorders an npz's frames; a "
                             "folder's frames are ordered by the numbers in their file names")
        folder = resolve_folder(path, subdir)
        _warn_if_interrupted(folder)
        return load_folder(folder, fps, kind, name=path.name or str(path))
    if subdir is not None:
        raise ValueError(f"{path}: subdir= applies to folders, but this is a file")
    if not path.is_file():  # a pipe waited for a writer for ever, /dev/zero was read until memory ran out
        raise MeshDataError(f"{path}: {file_problem(path)} (a pipe, a device or a socket): give a mesh or sequence "
                            "file, or a folder of frames")
    frame_order = parse(FrameOrder, frame_order, "frame_order").value
    suffix = path.suffix.lower()
    if suffix in ANIMATION_EXTENSIONS:
        V, F, file_fps = read_animation(path, topology)
        return _one_file(V, F, fps, file_fps, path.stem, path, kind, frame_order,
                         colors=_topology_colors(path, V.shape[1], topology) if suffix in CACHE_EXTENSIONS else None)
    if suffix in VERTEX_ONLY_EXTENSIONS:  # .npz, .npy: vertices only, or an npz with its faces
        V, file_fps, name = load_vertex_array(path)
        if V is not None:  # vertices only: the faces come from a mesh
            return _one_file(V, topology_faces(path, V.shape[1], topology), fps, file_fps, name, path, kind,
                             frame_order, colors=_topology_colors(path, V.shape[1], topology))
    if topology is not None:
        raise _no_topology(path, "this one has its own faces")
    if suffix == ".npz":
        _warn_if_interrupted(path)
        return fix_frame_order(load_npz(path, fps, kind), frame_order, path)
    animated = suffix in GLTF_EXTENSIONS and gltf_has_animation(path)
    if animation is not None and not animated:
        raise ValueError(f"{path}: animation= picks one animation of an animated .glb / .gltf, but this file "
                         f"has none")
    if animated:
        V, F, file_fps, colors = read_gltf_animation(path, fps, animation, colors=True)
        return _one_file(V, F, None, file_fps, path.stem, path, kind, colors=colors)
    if suffix in GLTF_EXTENSIONS:
        # the scene as it stands, by the glTF reader's rules (a skinned mesh's own node transform
        # is not applied: through trimesh a new user's static skinned file sat 5 m off the same
        # file's animated frame 0, its parts in another order)
        V, F, _, colors = read_gltf_animation(path, rest=True, colors=True)
        V = V[0]
    else:
        V, F = read_mesh(path)
        colors = read_vertex_colors(path, len(V))
    fps = DEFAULT_FPS if fps is None else fps
    seq = FixedTopologySequence(V[None], F, fps=fps, name=path.stem, source=str(path), colors=colors)
    return seq.to_varying() if kind == "varying" else seq



def stored_up_axis(path) -> str:
    """The up axis of the coordinates a file or folder holds, as far as it says: ``"y"`` for glTF
    (``.glb`` / ``.gltf``, or a folder whose frames all are; +Y up by its specification) unless
    this project wrote it from z-up data (turned to +Y up and marked, ``mesh_formats.Z_UP_MARK``,
    which the reader turns back; or, written before that, ``asset.generator`` ``GENERATOR`` with the
    z-up coordinates as they were), ``"y"`` for an npz this project wrote from +Y-up data (its ``up_axis`` entry), else
    ``"z"``. What ``surface.up_axis: auto`` takes; the writers keep it (a new user's glTF
    converted to an npz or a .glb came back turned 90 degrees from the input)."""
    path = Path(str(path))
    try:
        if path.is_dir():  # its frames, as the folder loader lists them (one extension)
            path = list_frame_files(path, quiet=True)[0]
        ext = mesh_extension(path.name) or path.suffix.lower()
        if ext == ".npz":
            with np.load(path, allow_pickle=False) as z:
                return "y" if "up_axis" in z.files and str(z["up_axis"]) == "y" else "z"
    except (OSError, ValueError):  # MeshDataError too: a folder the loader cannot read
        return "z"
    if ext not in Y_UP_FORMATS:
        return "z"
    if gltf_turned_from_z(path):  # this project's z-up data, turned to +Y up and read back turned again
        return "z"
    # the earlier files: z-up as they were, their generator exactly GENERATOR (one that only starts
    # so is another writer's, or ours re-saved: +Y up)
    return "z" if gltf_generator(path) == GENERATOR else "y"


def sequence_up_axis(seq) -> str:
    """The axis ``seq``'s coordinates are up along: its ``up_axis`` where it says (a scene's
    surface: z), else what its source file says (:func:`stored_up_axis`: glTF, or an npz / .glb
    this project wrote from one, is y); a sequence made in memory or built in is z."""
    if seq.up_axis is not None:
        return seq.up_axis
    if not seq.source or str(seq.source).startswith("builtin:"):
        return "z"
    return stored_up_axis(seq.source)


def _y_up(seq) -> bool:
    return sequence_up_axis(seq) == "y"


def _save_npz(seq, path: Path, status: dict | None = None) -> None:
    arrays = npz_arrays(seq, status)
    if _y_up(seq):  # read back turned, as its glTF source is (surface.up_axis: auto)
        arrays["up_axis"] = np.asarray("y")
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as fh:  # a file object: numpy adds no ".npz"
        np.savez(fh, **arrays)
        fh.flush()
        os.fsync(fh.fileno())


def _save_folder(seq, folder: Path, fmt: str, overwrite: bool = False, status: dict | None = None) -> None:
    """The frames as ``frame_{i:04d}.{fmt}``, numbered as the ``status``' ``frame_numbers`` say (a
    folder input's own file numbers, which ``convert`` keeps: a new user's frame_0001..0006 came out as
    frame_0000..0005, off by one for a tool pairing files by name), else from its ``first_frame`` (a
    stopped conversion's frames keep their input frame numbers: frames 1..19 were written as
    frame_0000..0018, which a tool reading the names takes for frames 0..18), else from 0."""
    first = int((status or {}).get("first_frame", 0) or 0)
    numbers = (status or {}).get("frame_numbers") or list(range(first, first + seq.num_frames))
    if len(numbers) != seq.num_frames or len(set(numbers)) != len(numbers):
        raise ValueError(f"{folder}: frame_numbers must give each of the {seq.num_frames} frames its own number")
    # the frame rate in the manifest, which the folder loader reads back (a folder of frames says
    # none: a new user's 30 fps conversion read back at 24)
    status = {**(status or {}), "fps": float(seq.fps)}
    with OutputFolder(folder, overwrite=overwrite, status=status, holds=OutputKind.SEQUENCE) as tmp:
        for t in range(seq.num_frames):
            V, F = seq.frame(t)
            # the colours of frame 0's vertices; a fixed sequence's are every frame's
            colors = seq.colors if (t == 0 or isinstance(seq, FixedTopologySequence)) else None
            write_mesh_file(tmp / f"frame_{int(numbers[t]):04d}.{fmt}", V, F, colors)


def _warn_if_interrupted(path: Path) -> None:
    """Warn when ``path`` (an npz, or a folder with this tool's manifest) was written by a run
    that was stopped (its status says ``"complete": false``): a new user's interrupted
    conversion played in a scene with no word that it held only some of the frames."""
    import warnings

    from .outputs import stopped_note, stopped_status

    status = stopped_status(path)
    if status is not None:
        held = stopped_note(status)
        warnings.warn(f"{path}: written by a run that was stopped ({status.get('interrupted_by') or 'interrupted'}): it "
                      f"holds {held}", stacklevel=3)


def save_sequence(seq, path, fmt: str | None = None, overwrite: bool = False, status: dict | None = None) -> None:
    """Save a sequence atomically to a ``.npz`` file or a folder of per-frame meshes.

    Args:
        seq: a :class:`FixedTopologySequence` or :class:`VaryingTopologySequence`.
        path: ``*.npz`` for one file (fixed layout ``V``/``F``/``fps``/``name``, or the
            packed varying layout ``V_packed``/``F_packed``/``V_offsets``/``F_offsets``/
            ``fps``/``name``); ``*.anime``, ``*.pc2`` or ``*.mdd`` for a single-file animation
            of a fixed-topology sequence (a point cache also gets its faces as ``<stem>.obj``,
            :mod:`~dynmesh_warp.animation_formats`); ``*.glb`` for an animated glTF (frames as
            morph targets, :func:`~dynmesh_warp.gltf_animation.write_gltf_animation`); otherwise
            a folder that receives
            ``frame_{i:04d}.{fmt}``.
        fmt: ``"ply"`` or ``"obj"`` for a folder (required there); ``None``/``"npz"`` for
            an ``.npz`` path.

    An existing file is replaced only with ``overwrite`` (else
    :class:`~dynmesh_warp.outputs.OutputExistsError`, a :class:`FileExistsError`, before anything
    is written). An existing folder is replaced at the very end, and only when everything in it
    was written by this tool (listed in its manifest, see :mod:`dynmesh_warp.outputs`); else
    :class:`FileExistsError`, unless ``overwrite`` (then the files this tool did not write are
    kept where they are).

    ``status``: a JSON-ready dict saved with the sequence (the npz's ``status`` array, JSON
    text; a folder's manifest, under ``"status"``), e.g. ``convert``'s frame counts and whether it
    was interrupted. Readers ignore it.
    """
    if not isinstance(seq, (FixedTopologySequence, VaryingTopologySequence)):
        raise TypeError(f"expected a FixedTopologySequence or VaryingTopologySequence, "
                        f"got {type(seq).__name__}")
    path = Path(path).expanduser()
    check_name_length(path, str(path), "save_sequence")  # before the work, not at the temporary's name
    fmt = fmt.lower().lstrip(".") if fmt else None
    single_file = path.suffix.lower() in ANIMATED_FILE_OUTPUTS or path.suffix.lower() == ".npz"
    if single_file and not overwrite and (path.exists() or path.is_symlink()):
        # a new user's own .npz was replaced with overwrite=False
        raise OutputExistsError(f"{path}: exists; pass overwrite=True to replace it")
    if path.suffix.lower() in ANIMATED_FILE_OUTPUTS:
        if fmt not in (None, path.suffix.lower()[1:]):
            raise ValueError(f"{path}: fmt={fmt!r} conflicts with the {path.suffix} extension")
        if not isinstance(seq, FixedTopologySequence):
            raise ValueError(f"{path}: a {path.suffix} animation holds one set of faces for every frame; this "
                             f"sequence's topology varies (convert it first, or save a .npz or a folder)")
        if path.suffix.lower() == ".glb":
            write_gltf_animation(path, seq.V, seq.F, seq.fps, y_up=_y_up(seq), colors=seq.colors)
        else:
            write_animation(path, seq.V, seq.F, seq.fps, overwrite=bool(overwrite), colors=seq.colors)
            _warn_up_axis_lost(seq, path)
            _warn_animation_loses(seq, path)
        return
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
    _warn_up_axis_lost(seq, path)


#: the single-file animations that store no frame rate (read back at the ``fps`` argument, else 24)
_NO_FPS = (".pc2", ".anime")


def _warn_animation_loses(seq, path: Path) -> None:
    """What a single-file animation cannot hold, said when written (a new user's 30 fps sequence
    read back at 24 from a .pc2, and an .anime dropped its colours, unsaid)."""
    import warnings

    lost = []
    ext = path.suffix.lower()
    if ext in _NO_FPS and float(seq.fps) != DEFAULT_FPS:
        lost.append(f"its frame rate ({seq.fps:g} fps: read it back with fps={seq.fps:g}, surface.fps or convert's "
                    f"--fps; it reads as {DEFAULT_FPS:g})")
    if ext == ".anime" and seq.colors is not None:
        lost.append("its vertex colours")
    if lost:
        warnings.warn(f"{path}: a {ext} file does not store {' and '.join(lost)}; a .npz or .glb keeps them",
                      stacklevel=3)


def _warn_up_axis_lost(seq, path: Path) -> None:
    """A format that cannot say its up axis (frames, point caches, .anime), written from +Y-up
    coordinates (a glTF input): say how to read it back the input's way up."""
    if _y_up(seq):
        import warnings

        held = "(glTF)" if str(seq.source).lower().endswith((".glb", ".gltf")) else "(its up_axis entry)"
        warnings.warn(f"{path}: its coordinates are +Y up, as its source {seq.source} {held} holds them, and this "
                      "format cannot say so: read it back with surface.up_axis: y (--set surface.up_axis=y), or "
                      "write a .npz or .glb, which keep it", stacklevel=3)
