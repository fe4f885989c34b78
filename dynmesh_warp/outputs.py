"""Output safety, shared by every writer (``run``, ``--record``, ``convert``, ``evaluate``).

- Atomic writing: a file appears whole or not at all (a temporary sibling renamed into place),
  with the user's umask (``0666 & ~umask`` files, ``0777 & ~umask`` folders).
- :func:`check_output`: before any work, refuse (:class:`OutputError`, one line) an output that
  is, contains or lies inside an input (real paths, symlinks resolved), an existing output
  without ``overwrite``, a file where a folder is expected (and the reverse), an unknown
  extension, a folder that cannot be created or written.
- :class:`OutputFolder`: a folder output is written into a temporary sibling folder and
  renamed into place at the end; an existing folder is replaced keeping every entry this tool
  did not write where it is (the folder's manifest :data:`MANIFEST` lists what it wrote), so
  ``--overwrite`` never deletes or moves the user's files. On an error the old folder stays as
  it was. The manifest also says what the folder holds (:class:`OutputKind`): ``--overwrite``
  replaces an output of the same kind only (a render into a run's folder replaced the run's
  trajectories).
- The temporaries of writes in progress are registered, so a hard exit (a second Ctrl-C,
  :mod:`dynmesh_warp.cli`) removes them (:func:`abandon_temporaries`) without cutting a
  rename into place in two.
"""

from __future__ import annotations

import contextlib
import enum
import errno
import json
import math
import os
import re
import shutil
import tempfile
import threading
from pathlib import Path

import numpy as np

__all__ = ["atomic_write_bytes", "atomic_write_json", "atomic_write_npz", "atomic_path", "OutputError",
           "OutputExistsError", "check_output", "OutputFolder", "MANIFEST", "read_manifest", "read_manifest_status",
           "read_status", "foreign_entries", "apply_umask", "OutputKind", "read_manifest_kind",
           "add_to_manifest", "temporary", "abandon_temporaries", "beside_path", "entries"]

#: name of the manifest in every folder this tool writes: JSON {"tool": ..., "files": [names],
#: "holds": an OutputKind's value, "status": {...}}
MANIFEST = ".dynmesh_outputs.json"


class OutputKind(str, enum.Enum):
    """What a folder output holds (its manifest's ``"holds"``). ``--overwrite`` replaces only an
    output of the same kind: ``render --out`` into a run's output folder deleted the run's
    ``trajectories.npz`` and ``summary.json`` (both "this tool's" files) with exit 0."""

    RUN = "run"  #: ``run --output``: summary.json, trajectories.npz, a checkpoint
    RENDER = "render"  #: ``render --out``: frame_NNNN.png
    EVALUATION = "evaluation"  #: ``evaluate --out``: results, tables, plots
    SEQUENCE = "sequence"  #: a sequence of per-frame meshes (``convert``'s folder output, ``io.save_sequence``)

    @property
    def described(self) -> str:
        return {"run": "a run's outputs", "render": "rendered frames", "evaluation": "an evaluation's results",
                "sequence": "a sequence's frames"}[self.value]


#: temporary files and folders of writes in progress (path -> is a folder), for a hard exit
_TEMPORARIES: dict[str, bool] = {}
#: held while a temporary is renamed into place (or removed), so a hard exit never cuts it in two
_COMMIT = threading.RLock()


@contextlib.contextmanager
def temporary(path, folder: bool = False):
    """Register ``path`` (a temporary file or folder being written) for the duration of the
    block; the block's own clean-up still removes it. Used by every atomic writer."""
    key = str(path)
    _TEMPORARIES[key] = folder
    try:
        yield
    finally:
        _TEMPORARIES.pop(key, None)


def abandon_temporaries(timeout: float = 2.0) -> list:
    """Remove every registered temporary (the process is about to exit at once); a rename into
    place in progress is let finish first (up to ``timeout`` seconds). A folder whose rename
    into place is still going on after that is left where it is: the rename moves files in and
    out of it, and removing it then lost files (a new user's second Ctrl-C, 0.6 s after the first,
    deleted the user's files an ``--overwrite`` had been moving, before the commit below stopped
    moving them). Returns those folders left (empty when every temporary was removed)."""
    got = _COMMIT.acquire(timeout=timeout)
    left = []
    try:
        for p, folder in list(_TEMPORARIES.items()):
            if folder:
                if got:
                    shutil.rmtree(p, ignore_errors=True)
                else:
                    left.append(p)
            else:
                try:
                    os.unlink(p)
                except OSError:
                    pass
    finally:
        if got:
            _COMMIT.release()
    return left


class OutputError(ValueError):
    """An output path that must not or cannot be written; the message is one line."""


class OutputExistsError(OutputError, FileExistsError):
    """The output exists (or holds a file this tool did not write) and may not be replaced."""


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def apply_umask(path, folder: bool = False) -> None:
    """Give ``path`` the permissions a plain ``open``/``mkdir`` would (mkstemp/mkdtemp make 0600/0700)."""
    os.chmod(path, (0o777 if folder else 0o666) & ~_umask())


#: the OSError numbers of a write the file system refused (no space, over a quota or the file-size
#: limit, read-only): re-raised naming the output they were for (:func:`_for_output`); the CLIs say
#: them in one line (``cli.interruptible_main``)
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS})


def write_error_text(e: OSError) -> str:
    """The one line for a write the file system refused (:data:`WRITE_ERRNOS`): the output, why,
    and that nothing of it was put in place (the CLIs say it so)."""
    where = f"{e.filename}: " if e.filename else ""
    return (f"error: {where}{e.strerror or e} while writing; nothing of that output was put in place (outputs are "
            "atomic: an earlier one there is unchanged)")


def _for_output(exc, path) -> OSError | None:
    """A write error of the file system (:data:`WRITE_ERRNOS`) named by the output ``path`` it was for
    (NumPy's savez names no file, and a temporary's name means nothing to the user); else None."""
    if isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS:
        return OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))
    return None


class atomic_path:
    """Context manager yielding a temporary path next to ``path``; renamed onto it on success.

    On an exception (or interruption) the temporary file is removed and ``path`` is untouched.
    """

    def __init__(self, path, suffix: str = ""):
        self.path = Path(path)
        self.suffix = suffix or "".join(self.path.suffixes)

    def __enter__(self) -> Path:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=".tmp" + self.suffix, dir=self.path.parent)
        os.close(fd)
        self.tmp = Path(tmp)
        self._reg = temporary(self.tmp)
        self._reg.__enter__()
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        with _COMMIT:
            try:
                if exc_type is None:
                    apply_umask(self.tmp)  # mkstemp makes 0600; give the usual permissions
                    os.replace(self.tmp, self.path)
                else:
                    self.tmp.unlink(missing_ok=True)
            finally:
                self._reg.__exit__(None, None, None)
        named = _for_output(exc, self.path)
        if named is not None:
            raise named from exc
        return False


def atomic_write_bytes(path, data: bytes):
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def _strict(o):
    """``o`` with NumPy values made plain and NaN/inf floats made None (strict JSON has no NaN)."""
    if isinstance(o, dict):
        return {k: _strict(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_strict(v) for v in o]
    if isinstance(o, np.ndarray):
        return _strict(o.tolist())
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def atomic_write_json(path, obj):
    """Write ``obj`` as strict JSON (NaN/inf written as null), atomically."""
    text = json.dumps(_strict(obj), indent=2, default=_jsonable, allow_nan=False)
    atomic_write_bytes(path, (text + "\n").encode())


def atomic_write_npz(path, **arrays):
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)


# --------------------------------------------------------------------------- path checks


def _real(p) -> Path:
    return Path(os.path.realpath(Path(p).expanduser()))


def _within(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def _manifest_doc(folder) -> dict:
    """The JSON object of ``folder``'s manifest ({} when there is none or it is unreadable)."""
    try:
        doc = json.loads((Path(folder) / MANIFEST).read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def read_manifest(folder) -> set[str]:
    """Names this tool wrote in ``folder`` (empty when it has no readable manifest)."""
    files = _manifest_doc(folder).get("files", [])
    return {str(n) for n in files if isinstance(n, str) and "/" not in n} if isinstance(files, list) else set()


def read_manifest_status(folder) -> dict | None:
    """The ``status`` a run stored in ``folder``'s manifest (:class:`OutputFolder`'s ``status``,
    e.g. ``{"complete": false, ...}`` for a stopped run), or None."""
    status = _manifest_doc(folder).get("status")
    return status if isinstance(status, dict) else None


def read_status(path) -> dict | None:
    """The ``status`` a run of this tool stored with its output at ``path``: an npz's ``status``
    member (JSON) or a folder's manifest (:func:`read_manifest_status`); None where there is none
    or it cannot be read."""
    path = Path(path)
    if path.is_dir():
        status = read_manifest_status(path)
    else:
        import numpy as np

        try:
            with np.load(path, allow_pickle=False) as z:
                status = json.loads(str(z["status"])) if "status" in z.files else None
        except Exception:  # noqa: BLE001 - unreadable here (a corrupt zip member too): the loader reports what is wrong
            return None
    return status if isinstance(status, dict) else None


def stopped_status(path) -> dict | None:
    """The status of a stopped run's output at ``path`` (:func:`read_status`) when it says
    ``"complete": false``, else None."""
    status = read_status(path)
    return status if status is not None and status.get("complete") is False else None


def stopped_note(status: dict) -> str:
    """What a stopped run's output holds, from :func:`stopped_status`: "input frames a..b of 0..N-1"."""
    first, n, total = int(status.get("first_frame", 0) or 0), status.get("frames"), status.get("input_frames")
    return f"input frames {first}..{first + int(n) - 1} of 0..{int(total) - 1}" if n is not None and total is not None \
        else "part of the frames"


def read_manifest_kind(folder) -> OutputKind | None:
    """What ``folder``'s manifest says it holds (None: no manifest, or one written before the
    manifest said it, or an unknown kind)."""
    try:
        return OutputKind(_manifest_doc(folder).get("holds"))
    except ValueError:
        return None


def _other_kind(folder: Path, holds: OutputKind | None, name: str | None = None) -> OutputKind | None:
    """The kind of output ``folder`` holds where it is not ``holds`` and some of it is still there
    (with ``name``: where that entry is one of its files)."""
    other = read_manifest_kind(folder) if holds is not None and folder.is_dir() else None
    present = {name} if name is not None else set(os.listdir(folder)) if other is not None else set()
    if other is None or other == OutputKind(holds) or not (read_manifest(folder) & present):
        return None
    return other


def add_to_manifest(folder, name: str, holds: OutputKind | None = None) -> None:
    """List ``name`` (a file just written into ``folder`` during a run, e.g. a checkpoint) in the
    folder's manifest, so the folder stays one this tool wrote (``--overwrite`` rules)."""
    folder = Path(folder)
    doc = _manifest_doc(folder)
    files = sorted(read_manifest(folder) | {name})
    kind = {"holds": OutputKind(holds).value} if holds is not None else {}
    atomic_write_json(folder / MANIFEST, {**doc, "tool": "dynmesh_warp", "files": files, **kind})


#: the names of this tool's own temporaries: ``atomic_path``'s ``.{stem}.XXXXXXXX.tmp{suffix}`` and
#: ``OutputFolder``'s ``.{name}.tmp-XXXXXXXX`` / ``.{name}.old-XXXXXXXX`` (mkstemp's / mkdtemp's 8
#: characters). A run killed while it wrote (SIGKILL, a power cut) leaves one behind; it is this
#: tool's, not the user's (a new user's killed checkpoint write left one, and ``--resume`` was then
#: refused, "holds .checkpoint....tmp.npz, which this tool did not write", and ``--overwrite`` kept it
#: for ever as the user's)
TEMPORARY_NAME = re.compile(r"^\..+\.(?:[a-z0-9_]{8}\.tmp(?:\.[A-Za-z0-9]+)*|(?:tmp|old)-[a-z0-9_]{8})$")


def foreign_entries(folder: Path) -> list[str]:
    """Entries of an existing ``folder`` that this tool did not write (sorted): not its manifest's
    files, nor a temporary of its own left by a killed run (:data:`TEMPORARY_NAME`), which a
    replacement of the folder removes with this tool's other files."""
    ours = read_manifest(folder)
    return sorted(e for e in os.listdir(folder) if e != MANIFEST and e not in ours and not TEMPORARY_NAME.match(e))


def _nearest_existing(real: Path) -> Path:
    """The nearest ancestor of ``real`` that exists (a folder, or a file in the way)."""
    anc = real.parent
    while not os.path.lexists(anc):
        anc = anc.parent
    return anc


def _check_creatable(real: Path, shown: str, what: str) -> None:
    """The nearest existing ancestor of ``real`` must be a writable folder (nothing is created
    here; a probe folder is made and removed at once, which also catches read-only file systems
    for root, for whom ``os.access`` always says yes)."""
    anc = _nearest_existing(real)
    if not anc.is_dir():
        raise OutputError(f"{what} {shown}: cannot create it, {anc} is a file, not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise OutputError(f"{what} {shown}: the folder {anc} is not writable")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".dynmesh-probe-", dir=anc))
    except OSError as e:
        raise OutputError(f"{what} {shown}: the folder {anc} is not writable ({e.strerror or e})") from None


#: the bytes the names this tool writes beside an output add to its name, at most: a temporary
#: (``.{name}.tmp-XXXXXXXX``, ``.{stem}.XXXXXXXX.tmp{suffix}``), a conversion's journal
#: (``{name}.convert-journal``) and its own temporary, ``<stem>.partial-2<suffix>``
SIBLING_NAME_BYTES = 32


def check_name_length(real: Path, shown: str, what: str) -> None:
    """The output's name, with what this tool writes beside it, must fit the file system's limit
    (a new user's 245-byte name passed, then the run failed after the work writing its temporary
    sibling: ENAMETOOLONG, a traceback)."""
    n = len(os.fsencode(real.name))
    try:
        limit = os.pathconf(_nearest_existing(real), "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    if n + SIBLING_NAME_BYTES > limit:
        raise OutputError(f"{what} {shown}: its name is {n} bytes; this tool writes files beside it whose names are up "
                          f"to {SIBLING_NAME_BYTES} bytes longer (temporaries, a journal), beyond this file system's "
                          f"{limit}: give a name of at most {limit - SIBLING_NAME_BYTES} bytes")


def check_output(path, *, kind: str, what: str, inputs=(), overwrite: bool = False, suffixes=None,
                 writes=(), holds: OutputKind | None = None) -> Path:
    """Check an output path before any work; return its real path. Raises :class:`OutputError`
    with one line naming ``what`` (e.g. ``--output``) and the path. Writes nothing.

    overwrite: replace an existing output (a folder keeps the entries this tool did not write);
    ``"ours"``: replace a folder only when everything in it was written by this tool.
    kind: ``"folder"`` or ``"file"``; inputs: paths the command reads (files or folders);
    suffixes: allowed file extensions (``kind="file"``); writes: ``fnmatch`` patterns of the
    names the tool will write into a folder (an existing foreign file of such a name would be
    lost, so it is refused even with ``overwrite``); holds: what the folder will hold
    (:class:`OutputKind`): a folder holding another kind of output is refused even with
    ``overwrite`` (only an output of the same kind is replaced), and so is a file that is part of
    another kind's folder output.
    """
    import fnmatch

    if path is None or not str(path).strip():
        raise OutputError(f"{what}: empty path")
    shown = str(path)
    real = _real(path)
    if os.path.islink(Path(path).expanduser()) and not os.path.exists(Path(path).expanduser()):
        # a link to nothing: what would be written is the link's target, a path the user did not
        # name (it was found only after the work, by the write)
        raise OutputError(f"{what} {shown}: a symbolic link to {os.readlink(Path(path).expanduser())}, which does not "
                          "exist; remove the link or name the output itself")
    if kind == "file" and shown.endswith(("/", os.sep)):
        raise OutputError(f"{what} {shown}: names a folder (trailing '{os.sep}'), a file is expected")
    name = Path(shown.rstrip("/" + os.sep)).name
    if name != name.strip():  # "out.npz " wrote a folder of frames named so: its extension read ".npz "
        raise OutputError(f"{what} {shown!r}: the name begins or ends with white space (a typo?); name the output "
                          "without it")
    check_name_length(real, shown, what)
    if kind == "file" and suffixes and real.suffix.lower() not in suffixes and Path(shown).suffix.lower() not in suffixes:
        raise OutputError(f"{what} {shown}: unknown extension {Path(shown).suffix or '(none)'!r}; "
                          f"expected {' or '.join(sorted(suffixes))}")
    for inp in inputs:
        if inp is None:
            continue
        ri = _real(inp)
        if real == ri:
            raise OutputError(f"{what} {shown}: this is the input {inp}; choose another output")
        if _within(ri, real):
            raise OutputError(f"{what} {shown}: it contains the input {inp}; choose another output")
        if ri.is_dir() and _within(real, ri):
            raise OutputError(f"{what} {shown}: it lies inside the input folder {inp}; choose an output outside it")
    if os.path.lexists(real):
        if kind == "folder":
            if not real.is_dir():
                raise OutputError(f"{what} {shown}: is a file, a folder is expected")
            entries = [e for e in os.listdir(real)]
            clash = [e for e in foreign_entries(real) if any(fnmatch.fnmatch(e, w) for w in writes)]
            if clash:  # said first: --overwrite would not help (a new user was told to add it, then refused)
                raise OutputExistsError(f"{what} {shown}: holds {clash[0]}, which this tool did not write and "
                                        "would replace; move it away or choose another output")
            other = _other_kind(real, holds)
            if other is not None:
                ours = sorted(read_manifest(real) & set(entries))
                raise OutputExistsError(f"{what} {shown}: holds {other.described} ({', '.join(ours[:3])}"
                                        f"{', ...' if len(ours) > 3 else ''}), which --overwrite does not replace with "
                                        f"{OutputKind(holds).described}; choose another folder (or remove that "
                                        "output first)")
            if entries and overwrite == "ours":  # replace a folder only this tool wrote (the Python API)
                foreign = foreign_entries(real)
                if foreign:
                    raise OutputExistsError(f"{what} {shown}: holds {foreign[0]}, which this tool did not "
                                            "write; refusing to replace the folder (pass overwrite=True to "
                                            "replace only what this tool wrote)")
            elif entries and not overwrite:
                raise OutputExistsError(f"{what} {shown}: folder exists and is not empty{_stopped_text(real)}; add "
                                        "--overwrite to replace what this tool wrote there (other files are kept)")
            if not os.access(real, os.W_OK | os.X_OK):
                raise OutputError(f"{what} {shown}: the folder is not writable")
        else:
            if real.is_dir():
                raise OutputError(f"{what} {shown}: is a folder, a file is expected")
            other = _other_kind(real.parent, holds, real.name)
            if other is not None:
                # a file of another command's folder output (convert OUT.npz over a run's
                # trajectories.npz replaced it with exit 0, and the run's manifest still listed it)
                raise OutputExistsError(f"{what} {shown}: is one of {other.described} in {real.parent}, which "
                                        f"--overwrite does not replace with {OutputKind(holds).described}; choose "
                                        "another path")
            if not overwrite:
                raise OutputExistsError(f"{what} {shown}: file exists{_stopped_text(real)}; add --overwrite to replace it")
    _check_creatable(real, shown, what)
    return real


def _stopped_text(path: Path) -> str:
    """ " (the output of a stopped run: it holds ...)" for a stopped run's output at ``path``, else
    "" (a new user, told only "file exists" after a Ctrl-C, could not tell that the file was
    partial)."""
    status = stopped_status(path)
    return "" if status is None else f" (the output of a stopped run: it holds {stopped_note(status)})"


def entries(folder) -> set:
    """The names in ``folder`` (empty when it is not a folder): what a command line notes when it
    checks its output folder, for :class:`OutputFolder`'s ``checked``."""
    folder = Path(folder).expanduser()
    return set(os.listdir(folder)) if folder.is_dir() else set()


def beside_path(path, name: str = "partial", taken=None) -> Path:
    """A free name beside ``path`` for an output that may not replace it: ``<stem>.<name><suffix>``
    (a folder: ``<folder>.<name>``), numbered ``.<name>-2`` ... where that is taken (exists, or
    ``taken(candidate)`` is true: e.g. a point cache's faces file)."""
    p = Path(path).expanduser()
    for n in range(1, 10 ** 6):
        tag = f".{name}" if n == 1 else f".{name}-{n}"
        q = p.with_name(p.stem + tag + p.suffix) if p.suffix else p.with_name(p.name + tag)
        if not os.path.lexists(q) and not (taken is not None and taken(q)):
            return q
    raise OutputError(f"{path}: no free name beside it for this run's output")


def _copy_folder_attributes(src: Path, dst: Path) -> None:
    """Give ``dst`` the permission bits (setgid included) and group of ``src``, where allowed (a
    replaced output folder came back 0755 root:root from 2775 root:nogroup: a new user's)."""
    st = os.stat(src)
    with contextlib.suppress(OSError):
        os.chown(dst, -1, st.st_gid)
    with contextlib.suppress(OSError):
        os.chmod(dst, st.st_mode & 0o7777)


class OutputFolder:
    """Write a folder output atomically: ``with OutputFolder(path) as tmp:`` write into ``tmp``
    (a hidden temporary sibling); on success it becomes ``path``, with a manifest of what was
    written. An existing ``path`` is replaced only when everything in it was written by this
    tool (the new folder takes the old one's permission bits and group), or with
    ``overwrite=True``, which keeps the entries this tool did not write where they are: the
    tool's old entries move out of the folder and the new ones in (the user's files never move,
    so no interruption can misplace them). On an exception nothing changes (unless ``keep_on_error`` was set,
    e.g. after partial results worth keeping) and the temporary folder is removed.
    ``status``: a JSON-ready dict stored in the manifest under ``"status"`` (e.g. an
    interrupted conversion's frame counts); ``holds``: what the folder holds
    (:class:`OutputKind`, stored as ``"holds"``); a folder found holding another kind of output
    at the commit is not replaced (the result goes to ``<name>.new``).

    Where the result goes (``written``, the path after the commit): ``path``, except that a
    result marked ``interrupted`` (set it before the block ends) never replaces an earlier
    output of this tool there: it goes beside it, ``<name>.partial`` (a new user's complete
    30,000-step run became an interrupted one under ``--overwrite``); and with ``checked``, the
    entries the folder held when a command line checked it before the work (:func:`entries`),
    a folder that gained entries meanwhile (another run's output, the user's files) is left as it
    is: without ``overwrite`` whatever it gained, with it where a gained entry is not this tool's
    and has a name the result writes. The result then goes to ``<name>.new`` (a new user's long
    run silently replaced a short run's output that had appeared meanwhile; one with a user's
    ``summary.json`` threw the finished work away). Without ``checked``, a folder holding entries
    this tool did not write is :class:`OutputExistsError` unless ``overwrite``."""

    def __init__(self, path, overwrite: bool = False, keep_on_error: bool = False, status: dict | None = None,
                 interrupted: bool = False, checked: set | None = None, holds: OutputKind | None = None):
        self.path = _real(path)
        self.written = self.path
        self.beside = None  # why the result went beside path: "partial" or "new" (None: it did not)
        self.overwrite = bool(overwrite)
        self.keep_on_error = keep_on_error
        self.status = status
        self.interrupted = interrupted
        self.checked = checked
        self.holds = None if holds is None else OutputKind(holds)
        self.tmp = None

    def __enter__(self) -> Path:
        parent = self.path.parent
        if not parent.is_dir():
            parent.mkdir(parents=True, exist_ok=True)  # with the umask's permissions
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.tmp-", dir=parent))
        self._reg = temporary(self.tmp, folder=True)
        self._reg.__enter__()
        apply_umask(self.tmp, folder=True)  # mkdtemp makes 0700
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        with _COMMIT:
            try:
                if exc_type is None or self.keep_on_error:
                    try:
                        self.commit()
                    except BaseException:
                        shutil.rmtree(self.tmp, ignore_errors=True)
                        raise
                else:
                    shutil.rmtree(self.tmp, ignore_errors=True)
            finally:
                self._reg.__exit__(None, None, None)
        named = _for_output(exc, self.path)
        if named is not None:
            raise named from exc
        return False

    def commit(self):
        tmp, target = self.tmp, self.path
        written = sorted(e for e in os.listdir(tmp) if e != MANIFEST)
        keep = []
        if self.interrupted and target.is_dir() and read_manifest(target):
            self.beside = "partial"
        elif self.checked is not None and target.is_dir():
            gained = entries(target) - set(self.checked)
            if gained and (not self.overwrite or set(foreign_entries(target)) & gained & (set(written) | {MANIFEST})):
                self.beside = "new"
        if not self.beside and _other_kind(target, self.holds) is not None:  # another kind of output
            self.beside = "new"  # appeared there during the work (check_output refuses it before)
        if self.beside:
            target = beside_path(target, self.beside)
        if os.path.lexists(target):
            if not target.is_dir():
                raise OutputExistsError(f"{target}: is a file, a folder is expected")
            keep = foreign_entries(target)
            if keep and not self.overwrite:
                raise OutputExistsError(f"{target}: holds {keep[0]}, which this tool did not write; "
                                        "refusing to replace the folder")
            clash = [e for e in keep if e in written]
            if clash:
                raise OutputExistsError(f"{target}: holds {clash[0]}, which this tool did not write and "
                                        "would replace")
        self.written = target
        atomic_write_json(tmp / MANIFEST, {"tool": "dynmesh_warp", "files": written,
                                           **({"holds": self.holds.value} if self.holds is not None else {}),
                                           **({"status": self.status} if self.status is not None else {})})
        if not keep and not os.path.lexists(target):
            try:
                os.replace(tmp, target)
                return
            except OSError as e:  # made meanwhile by another process (a new user's two saves at once)
                if e.errno not in (errno.ENOTEMPTY, errno.EEXIST) or not target.is_dir():
                    raise
            return self.commit()  # again, onto the folder that is there now (by its own rules)
        old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
        cwd = Path.cwd().resolve()
        if not keep and not (cwd == target or _within(cwd, target)):
            # only this tool's files: swap the folders (two renames), keeping the folder's mode and
            # group; not where the process stands (run --output . left the user's shell in a
            # deleted folder: a new user's), which takes the entry-by-entry path below
            _copy_folder_attributes(target, tmp)
            try:
                os.replace(target, old)  # onto an empty folder: atomic
            except BaseException:
                os.rmdir(old)
                raise
            try:
                os.replace(tmp, target)
            except BaseException:
                os.replace(old, target)
                raise
            shutil.rmtree(old, ignore_errors=True)
            return
        # the user's entries stay: this tool's old entries move out, the new ones in (renames)
        foreign = set(keep)
        ours = [e for e in os.listdir(target) if e not in foreign]
        out, into = [], []
        try:
            for e in ours:
                os.replace(target / e, old / e)
                out.append(e)
            for e in written + [MANIFEST]:
                os.replace(tmp / e, target / e)
                into.append(e)
        except BaseException:
            for e in into:
                os.replace(target / e, tmp / e)
            for e in out:
                os.replace(old / e, target / e)
            os.rmdir(old)
            raise
        shutil.rmtree(old, ignore_errors=True)  # only what this tool wrote before
        shutil.rmtree(tmp, ignore_errors=True)  # empty now
