"""Journals of conversions: what an interrupted ``convert`` had done, so that it resumes
(``convert --resume``; docs/conversion.md, "Stopping and resuming").

A conversion is a chain of runs (the run from the key frame, key-frame trials, the floater retry,
template segments), each tracking a template frame by frame. Every frame a run fits is written to
the journal as it is done; a resumed conversion does the same chain again, but a frame the
journal holds is taken from it (the converted vertices, the per-frame figures and what the fit
changed in the converter's state) instead of being fitted. Only the fits are skipped: the cheap
work between them (loading the frames, the key frame, the options) runs again, so the resumed
conversion is the uninterrupted one (bit for bit on the CPU, tested).

A journal is a folder beside the output, ``<output name>.convert-journal`` (:func:`journal_path`):

- ``journal.json``: :data:`FORMAT`, the command's identity (input, strategy, options, template,
  frame rate, frame order: a resume must give the same) and, after a stop, the partial output
  written (its path, size and time: ``--resume`` may replace exactly that);
- ``run_NNNN.json``: the identity of the run that started NNNN-th (its strategy, options, key
  frame, frame count, template and node spacing);
- ``run_NNNN_IIIIII.npz``: that run's I-th frame fitted (NumPy arrays only, no pickles): ``t``,
  ``input`` (a digest of the input frame's vertices and faces), ``X`` (N, 3) float32 [m], the
  per-frame figures and the step's state change (:meth:`~dynmesh_warp.convert._Converter.step_record`).

Each file is written atomically (a temporary file renamed), so a run killed at any point keeps
every frame written before. A record is used only where its run's identity, its place in the
run's order, its frame and its input digest all match; from the first one that does not, the
journal is cut (the frames are fitted again). Records written on another device are used too (a
conversion stopped on a GPU may go on on the CPU): the result is then a valid conversion, not the
bit-exact uninterrupted one of either device.
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import shutil
import threading
import warnings
from pathlib import Path

import numpy as np

from .outputs import MANIFEST, _strict, atomic_path, atomic_write_json

__all__ = ["FORMAT", "JOURNAL_SUFFIX", "JournalError", "ConversionJournal", "RunJournal", "journal_path",
           "frame_digest", "read_journal", "fit_count"]

FORMAT = "dynmesh_warp.convert-journal/1"
JOURNAL_SUFFIX = ".convert-journal"
_HEAD = "journal.json"


class JournalError(ValueError):
    """A journal that cannot be used: one line naming the folder and what is wrong."""


def journal_path(output) -> Path:
    """The journal folder of a conversion writing ``output``: ``<output>.convert-journal`` beside it."""
    p = Path(output).expanduser()
    return p.with_name(p.name.rstrip("/") + JOURNAL_SUFFIX)


def frame_digest(*arrays) -> str:
    """A digest of arrays (dtype, shape and bytes): an input frame's identity in a record."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.data)
    return h.hexdigest()


def fit_count(folder) -> int:
    """The frame fits a journal folder holds (all runs; 0 where there is no folder)."""
    folder = Path(folder)
    try:
        return len(list(folder.glob("run_*_*.npz"))) if folder.is_dir() else 0
    except OSError:  # a name the file system refuses (too long: is_dir raised, after the output's own error)
        return 0


def _stamp(path: Path) -> tuple | None:
    """(size, mtime_ns) of an output: a file's, or a folder output's manifest's; None if absent."""
    try:
        st = (path / MANIFEST if path.is_dir() else path).stat()
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns


def _canonical(obj) -> str:
    return json.dumps(_strict(obj), sort_keys=True, default=str)


def read_journal(folder) -> dict:
    """``journal.json`` of the journal at ``folder``, checked; :class:`JournalError` when the folder
    is not a journal this tool wrote (or one of another format)."""
    folder = Path(folder)
    head = folder / _HEAD
    if os.path.lexists(folder) and not folder.is_dir():  # a user's file of the journal's name: not ours to remove
        raise JournalError(f"{folder}: a file where convert keeps its journal (not a journal this tool wrote, so it "
                           "is left as it is): move it away, or choose another output")
    try:
        doc = json.loads(head.read_text())
    except FileNotFoundError:
        raise JournalError(f"{folder}: not a conversion journal (no {_HEAD}); it was not written by convert, so "
                           "it is left as it is: move it away") from None
    except (OSError, ValueError) as e:
        raise JournalError(f"{folder}/{_HEAD}: unreadable ({e}); remove the folder to start the conversion over") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else None
        raise JournalError(f"{folder}/{_HEAD}: format {got!r}, this version reads {FORMAT!r}; remove the folder "
                           "to start the conversion over")
    return doc


class ConversionJournal:
    """The journal of one conversion (module docstring). ``identity``: what the conversion is
    (JSON-able; a resume must give an equal one). ``resume``: go on from the journal at ``folder``
    (which must exist, be a journal and have this identity); else start one there (``folder`` must
    not exist). Nothing is written before the first run starts."""

    def __init__(self, folder, identity: dict, resume: bool = False):
        self.folder = Path(folder)
        self.identity = json.loads(_canonical(identity))
        self.doc = {"format": FORMAT, "tool": "dynmesh_warp convert", "identity": self.identity}
        self._runs = 0  # runs started so far
        self.replaying = False  # the records found are being used (until the first miss)
        self.replayed = 0  # frames taken from the journal
        self.written = 0  # frames given to it to write
        self.failed = None  # why writing stopped (a full disk: the conversion goes on without a journal)
        self._warned = False  # ... said once
        self._queue = None  # the writer thread's (path, frame (V, F), t, arrays), while it runs
        self._writer = None
        if resume:
            doc = read_journal(self.folder)
            old = doc.get("identity", {})
            diff = sorted(k for k in set(old) | set(self.identity) if old.get(k) != self.identity.get(k))
            if diff:
                k = diff[0]
                raise JournalError(f"{self.folder}: the interrupted conversion had {k} {old.get(k)!r}, this command "
                                   f"{self.identity.get(k)!r}; give the same to resume it (or remove the folder to "
                                   "start over)")
            self.doc = doc
            self.replaying = True
        elif os.path.lexists(self.folder):
            raise JournalError(f"{self.folder}: exists; remove it, or give --resume to go on with it")
        self.resumed = resume

    # --- on disk
    def _open(self):
        if not self.folder.is_dir():
            try:
                self.folder.mkdir(parents=True)
            except FileExistsError:  # made since this journal was opened: another conversion's
                raise JournalError(f"{self.folder}: appeared during the work (another conversion of the same output?); "
                                   "run one conversion per output") from None
            atomic_write_json(self.folder / _HEAD, self.doc)

    def frames(self) -> int:
        """Frame records in the journal folder (all runs), once the ones given are written."""
        self.flush()
        return fit_count(self.folder)

    # --- the writer thread: a record's digest and file are made off the conversion's thread
    # (about 2 ms a frame of a 10k-vertex template on a 2-core CPU: 5-10 % of a GPU conversion's frame)
    def _put(self, path: Path, frame: tuple, t: int, arrays: dict) -> None:
        if self.failed is not None:
            return
        if self._writer is None:
            self._queue = queue.Queue(maxsize=8)
            self._writer = threading.Thread(target=self._write_records, name="conversion-journal", daemon=True)
            self._writer.start()
        self._queue.put((path, frame, t, arrays))

    def _write_records(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                if self.failed is None:
                    path, frame, t, arrays = item
                    try:
                        with atomic_path(path, suffix=".npz") as tmp:
                            with open(tmp, "wb") as f:
                                np.savez(f, t=np.int64(t), input=np.str_(frame_digest(*frame)), **arrays)
                    except OSError as e:  # a full disk, a folder removed: no journal, not no conversion
                        self.failed = f"{path}: {e}"
            finally:
                self._queue.task_done()

    def flush(self) -> None:
        """Wait until every record given is written; warn once if writing failed."""
        if self._writer is not None:
            self._queue.join()
        if self.failed is not None and not self._warned:
            self._warned = True
            warnings.warn(f"conversion journal: could not write {self.failed}; the conversion goes on without a "
                          "journal (a stop from here on cannot be resumed past the frames written)", stacklevel=2)

    def close(self) -> None:
        """Write what is left and end the writer thread."""
        self.flush()
        if self._writer is not None:
            self._queue.put(None)
            self._writer.join()
            self._writer = self._queue = None

    def note_partial(self, path) -> None:
        """Record the partial output a stopped conversion wrote (``--resume`` may replace it)."""
        p = Path(path)
        stamp = _stamp(p)
        if stamp is None:
            return
        self.doc["partial"] = {"path": str(p.resolve()), "size": stamp[0], "mtime_ns": stamp[1]}
        if self.folder.is_dir():
            atomic_write_json(self.folder / _HEAD, self.doc)

    def partial(self) -> Path | None:
        """The partial output recorded by :meth:`note_partial`, when it is still as written."""
        rec = self.doc.get("partial")
        if not isinstance(rec, dict):
            return None
        p = Path(str(rec.get("path")))
        return p if _stamp(p) == (rec.get("size"), rec.get("mtime_ns")) else None

    def remove(self) -> None:
        """Delete the journal (the conversion is complete)."""
        self.close()
        shutil.rmtree(self.folder, ignore_errors=True)

    def _cut(self, run: int, index: int) -> None:
        """Delete the records from run ``run``'s ``index``-th frame on and every later run; replay ends."""
        self.replaying = False
        if not self.folder.is_dir():
            return
        for p in self.folder.glob("run_*"):
            parts = p.name.split(".")[0].split("_")
            try:
                r = int(parts[1])
                i = int(parts[2]) if len(parts) > 2 else None
            except (IndexError, ValueError):
                continue
            if r > run or (r == run and (i is None and index == 0 or i is not None and i >= index)):
                p.unlink(missing_ok=True)

    # --- runs
    def run(self, header: dict) -> "RunJournal":
        """The journal of the next run to start, whose identity is ``header``."""
        n = self._runs
        self._runs += 1
        header = json.loads(_canonical(header))
        path = self.folder / f"run_{n:04d}.json"
        if self.replaying:
            try:
                old = json.loads(path.read_text())
            except (OSError, ValueError):
                old = None
            if old != header:
                self._cut(n, 0)
        if not self.replaying:
            self._open()
            atomic_write_json(path, header)
        return RunJournal(self, n)


class RunJournal:
    """The frame records of one run (:meth:`ConversionJournal.run`)."""

    def __init__(self, journal: ConversionJournal, number: int):
        self.journal = journal
        self.number = number

    def _path(self, index: int) -> Path:
        return self.journal.folder / f"run_{self.number:04d}_{index:06d}.npz"

    def replay(self, index: int, t: int, frame: tuple) -> dict | None:
        """The record of this run's ``index``-th frame when the journal holds it for frame ``t`` of
        the same input ``frame`` (V, F); else None (and the journal is cut there)."""
        j = self.journal
        if not j.replaying:
            return None
        digest = frame_digest(*frame)
        try:
            with np.load(self._path(index), allow_pickle=False) as z:
                rec = {k: z[k] for k in z.files}
        except (OSError, ValueError, KeyError, EOFError):  # missing, or cut short by a crash
            rec = None
        if rec is None or int(rec.get("t", -1)) != t or str(rec.get("input", "")) != digest:
            j._cut(self.number, index)
            return None
        j.replayed += 1
        return rec

    def write(self, index: int, t: int, frame: tuple, **arrays) -> None:
        """Write this run's ``index``-th frame: frame ``t``, fitted to the input ``frame`` (V, F)
        (its digest is what a resume compares); ``arrays``: NumPy arrays or scalars, copied here (the
        file is written by the journal's writer thread)."""
        j = self.journal
        j._open()
        j._put(self._path(index), frame, t, {k: np.array(v, copy=True) for k, v in arrays.items()})
        j.written += 1
