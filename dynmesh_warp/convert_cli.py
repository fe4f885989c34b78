"""The plumbing of the ``convert`` command line (``python -m dynmesh_warp.convert``, whose
``main`` is :func:`dynmesh_warp.convert.main`): its argument parser, the output path's checks
(what a folder output holds, where a run writes beside an output it may not replace, removing a
partial output), the journal it opens for ``--resume`` and the time estimate it prints."""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import time
from pathlib import Path

from .choices import DEFAULT_FRAME_ORDER, DEFAULT_STRATEGY, STRATEGIES, FrameOrder, values
from .cli import Parser
from .convert_journal import ConversionJournal
from .sequence import MeshDataError


class FrameEstimate:
    """The ``convert`` CLI's estimate, called by the frame loop after each frame it fits
    (``convert_fit.FRAME_TIMER``): at the second fitted frame (the first includes compilation)
    it prints the time the conversion will take, what has passed since it began (the input's
    checks, the converter's set-up, frames taken from a journal) plus that frame's time for each
    frame left, when that is over ``limit_s``, naming faster options. Once per conversion."""

    def __init__(self, device, strategy: str, limit_s: float = 60.0):
        self.device, self.strategy, self.limit_s = str(device), strategy, limit_s
        self.start = time.perf_counter()
        self.fitted = 0
        self.done = False
        self.last_s = 0.0  # the last fitted frame's time [s]

    def stop_hint(self) -> str:
        """What a stop's acknowledgement adds (``cli.set_stop_hint``): the frame in progress may
        take as long as the last one did, where that is long."""
        if self.last_s < 10.0:
            return ""
        return f"after the frame being fitted: about {_duration(self.last_s)}, as long as the last one took"

    def __call__(self, seconds: float, done: int, frames: int) -> None:
        self.fitted += 1
        self.last_s = float(seconds)
        if self.done or self.fitted < 2:
            return
        self.done = True
        total = time.perf_counter() - self.start + seconds * max(frames - done, 0)
        if total > self.limit_s:
            faster = [] if self.device.startswith("cuda") else ["--device cuda (a GPU)"]
            if self.strategy != "projection":
                faster.append("--strategy projection (fastest, least accurate)")
            _note(f"estimate: {seconds:.1f} s per frame, about {_duration(total)} for {frames} frames on "
                  f"{self.device}, the first run (key-frame trials may follow)"
                  + (f"; faster: {', '.join(faster)}" if faster else ""))


def _duration(s: float) -> str:
    return f"{s / 3600:.1f} h" if s >= 5400 else f"{s / 60:.0f} min" if s >= 90 else f"{s:.0f} s"


def _note(msg: str) -> None:
    try:
        from tqdm import tqdm

        tqdm.write(msg, file=sys.stderr)
    except ImportError:  # pragma: no cover
        print(msg, file=sys.stderr)


#: suffixes an output path must not have: a folder of frames is written without an extension
_FILE_SUFFIXES = {".json", ".txt", ".csv", ".zip", ".npy", ".png", ".yaml", ".yml", ".h5", ".pkl"}


def _say_frame_numbers(seq) -> None:
    """A note when the input's files are numbered otherwise than 0, 1, ...: the messages (key
    frame, poor frames, segments) count the frames in the input's order from 0."""
    from .sequence_layouts import frame_keys

    src = getattr(seq, "frame_sources", None)
    if not src:
        return
    try:
        keys = frame_keys(src)[0]
    except MeshDataError:
        return
    numbers = [keys[0], keys[-1]]
    if numbers != [0, len(src) - 1]:
        print(f"note: frames are counted 0..{len(src) - 1} in the input's order: frame 0 is {Path(src[0]).name}, "
              f"frame {len(src) - 1} is {Path(src[-1]).name}", file=sys.stderr)


def input_frame_numbers(path, num_frames: int) -> list | None:
    """The numbers of a folder input's ``num_frames`` frame files in its order (``frame_0001.ply``
    ... -> 1, ...; a DG-Mesh scene folder's, in the subfolder the loader reads), which a folder
    output's files take; None for another input, names without numbers, or another count of files."""
    from .sequence_layouts import frame_keys, list_frame_files, resolve_folder

    try:
        if not Path(path).is_dir():
            return None
        numbers = frame_keys(list_frame_files(resolve_folder(Path(path), None), quiet=True))[0]
    except (MeshDataError, OSError, ValueError):
        return None
    if any(isinstance(n, float) for n in numbers):  # time stamps: the output numbers its frames 0, 1, ...
        return None
    return numbers if len(numbers) == num_frames else None


#: the names ``convert`` writes into a folder output (and finds an earlier run's frames by)
_FOLDER_FRAMES = ("frame_*.ply", "frame_*.obj")


def _holds_output(output) -> bool:
    """Whether ``output`` holds a sequence already: the file exists, or the folder has frames."""
    p = Path(output).expanduser()
    return p.is_file() or (p.is_dir() and any(any(p.glob(pattern)) for pattern in _FOLDER_FRAMES))


def _beside_path(output, name: str = "partial") -> Path:
    """Where ``convert`` writes when ``output`` holds a sequence it may not replace (an
    interrupted run's frames; ``name`` "new": a run whose output appeared during the work):
    :func:`~dynmesh_warp.outputs.beside_path`, also skipping names whose point-cache faces file
    (``<stem>.obj``) is taken, so nothing there is replaced."""
    from .animation_formats import written_topology
    from .outputs import beside_path

    def faces_taken(q):
        faces = written_topology(q)
        return faces is not None and faces.exists()

    return beside_path(output, name, faces_taken)


def _same_path(a, b) -> bool:
    return Path(os.path.realpath(Path(a).expanduser())) == Path(os.path.realpath(Path(b).expanduser()))


def _remove_output(path: Path) -> None:
    """Remove a partial output this tool wrote (a file, with a point cache's faces; or a folder's
    listed files and its manifest, the folder too when that leaves it empty)."""
    from .animation_formats import written_topology
    from .outputs import MANIFEST, read_manifest

    if path.is_dir():
        for name in read_manifest(path) | {MANIFEST}:
            (path / name).unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            path.rmdir()
        return
    faces = written_topology(path)
    path.unlink(missing_ok=True)
    if faces is not None:
        faces.unlink(missing_ok=True)


def _open_journal(a, opts: dict, inputs: list) -> ConversionJournal:
    """The journal of this command's conversion (``convert_journal``): the interrupted one's with
    ``--resume``; else a new one, refused where an interrupted conversion's journal is there."""
    from .convert_journal import fit_count, journal_path, read_journal

    folder = journal_path(a.output)
    real = lambda q: None if q is None else os.path.realpath(Path(q).expanduser())  # noqa: E731
    identity = {"input": real(a.input), "template": real(a.template), "topology": real(a.topology),
                "strategy": a.strategy, "options": opts, "fps": a.fps, "frame_order": a.frame_order}
    if a.resume:
        if not os.path.lexists(folder):
            raise ValueError(f"--resume: no interrupted conversion of {a.output} to go on with ({folder} is not there)")
        return ConversionJournal(folder, identity, resume=True)
    if os.path.lexists(folder):
        read_journal(folder)  # a folder of that name that is no journal is named as such
        n = fit_count(folder)
        if n == 0:  # killed before its first fit was written: nothing to go on from
            shutil.rmtree(folder, ignore_errors=True)
            return ConversionJournal(folder, identity)
        raise ValueError(f"output {a.output}: an interrupted conversion of it left {n} frame fits in {folder}; give "
                         "--resume to go on from them, or remove that folder to start over")
    return ConversionJournal(folder, identity)


@contextlib.contextmanager
def _keeping_journal(journal: ConversionJournal):
    """A journal with no frame fitted is removed however the conversion ends (nothing to go on from)."""
    try:
        yield
    finally:
        journal.close()
        if not journal.frames():
            journal.remove()


def _parser() -> Parser:
    """The argument parser of ``python -m dynmesh_warp.convert``."""
    p = Parser(
        prog="python -m dynmesh_warp.convert",
        description="Convert a varying-topology mesh sequence into a fixed-topology one.")
    p.add_argument("input", help="sequence: .npz, a folder of per-frame meshes (.obj, .ply, .off, ...), a DG-Mesh "
                   "scene folder, an animated .glb/.gltf, or a point cache (.pc2, .mdd, .anime; docs/data.md)")
    p.add_argument("output", help="output .npz; a .pc2 or .mdd point cache (its faces written as <stem>.obj), "
                                  ".anime, or an animated .glb (morph targets); or a folder (frame_XXXX.ply/.obj, "
                                  "see --fmt)")
    p.add_argument("--strategy", choices=STRATEGIES, default=DEFAULT_STRATEGY,
                   help=f"conversion strategy (default {DEFAULT_STRATEGY}; docs/conversion.md)")
    p.add_argument("--template", default=None,
                   help="template mesh file (default: the key frame, see --key-frame)")
    p.add_argument("--topology", default=None,
                   help="faces of a vertex-only input (a .pc2/.mdd point cache, .npy, or an npz of vertices): a mesh "
                        "file with as many vertices (default: the mesh of the same name next to it)")
    p.add_argument("--key-frame", default=None,
                   help="frame the template comes from and tracking starts at, forward then backward "
                        "(default 'auto': the frame of largest surface area, closed where most are, and of about "
                        "that area the one with 2x the vertices or more when there is one: every output frame "
                        "gets its resolution; frame 0 with --template)")
    p.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (as run, evaluate and render)")
    p.add_argument("--reanchor-interval", type=int, default=None, help="tracking: frames between re-anchors (0: never)")
    p.add_argument("--tracked-weight", type=float, default=None, help="tracking: weight of the tracked positions at a re-anchor")
    p.add_argument("--iterations", type=int, default=None, help="regularized: outer iterations per frame")
    p.add_argument("--smooth-iterations", type=int, default=None, help="regularized: displacement smoothing steps")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="a strategy option (repeatable), e.g. --option refine_rounds=0 --option iterations=2 "
                        "(the graph strategy's fast settings; docs/conversion.md lists the options)")
    p.add_argument("--fmt", default=None, choices=["ply", "obj"], help="per-frame format for a folder output (default ply)")
    p.add_argument("--fps", type=float, default=None, help="override the input frame rate")
    p.add_argument("--frame-order", choices=values(FrameOrder), default=DEFAULT_FRAME_ORDER.value,
                   help="an npz input's frames: text_sorted undoes a text sort (1, 10, 11, ..., 2, ...; "
                        "numbering from 1 for a varying-topology npz); auto: where detected (fixed topology "
                        "only); docs/data.md")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output (in a folder: only files this tool wrote; others are kept)")
    p.add_argument("--as-is", action="store_true",
                   help="a fixed-topology input written to the output's format as it is, no template fitted (a "
                        "lossless .glb, point cache or frames of an animation); refused for varying topology")
    p.add_argument("--resume", action="store_true",
                   help="go on with an interrupted conversion of this output from the frames it had fitted (its "
                        "journal, <output>.convert-journal); give the same input and options")
    return p
