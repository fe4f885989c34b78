"""Shared command-line helpers: one-line argument errors, a quiet Warp start, and how the
command lines stop on SIGINT (Ctrl-C) and SIGTERM (``kill``, ``timeout``).

Stopping (docs/scene.md#interrupted-runs). Every CLI's ``main`` runs under
:func:`interruptible_main`, which installs handlers for both signals:

- Inside :func:`checking_stops` (the step loop of ``run``, the frame loops of ``convert`` and
  ``evaluate``, the viewer's frame loop, the writing of outputs) the first signal only sets a
  flag. The loop sees it at its next step or frame boundary (:func:`stop_requested`), stops,
  writes what it has done (marked interrupted) and the CLI exits 130 (SIGINT) or 143 (SIGTERM)
  after one line on stderr.
- Elsewhere (loading, compiling, a stage with no boundaries to check) the first signal raises
  :class:`Interrupted` at once: temporary outputs are removed, old outputs stay, same exit codes.
- A second signal exits at once, even while the main thread is inside a long native call (a
  watcher thread reads the signal numbers CPython writes to its wakeup file descriptor): the
  temporary files and folders of writes in progress are removed (a folder being renamed into
  place is let finish first, so a user's files moved into it are never lost) and the process
  ends with ``os._exit``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import signal
import sys
import threading
import time
import warnings

__all__ = ["Parser", "quiet_warp", "Interrupted", "interruptible_main", "checking_stops", "raising_stops",
           "stop_requested", "stop_reason", "stop_signal", "signal_name", "STOP_SIGNALS"]

#: the signals that stop a command line
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: seconds after a first signal before saying that the stop is under way (a quick stop says nothing twice)
_ACK_AFTER_S = 1.0
#: a second stop signal this soon after the first is the same stop: coreutils ``timeout`` sends
#: its signal to the command and then again to its process group, so a command it stops gets it
#: twice within microseconds (found by a new user: ``timeout -s INT`` exited "at once", writing
#: nothing); a person's second Ctrl-C comes later (the first says to send it again after 1 s)
_SAME_STOP_S = 0.3


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``error: ... (see --help)``, exit 2), like every other
    check of the command lines, instead of the usage block."""

    def error(self, message):
        self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def quiet_warp(device: str | None = None):
    """Silence Warp's start-up banner and per-module load lines (CLIs print their own summary).

    ``device``: the ``--device`` asked for. Warp's note about a missing NVIDIA driver is dropped
    unless it names a CUDA device (there it says why the device is missing, next to the
    CLI's own error)."""
    import warp as wp

    wp.config.quiet = True
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        wp.config.log_level = wp.LOG_WARNING
    _init_without_driver_note(wp, keep=bool(device) and str(device).strip().lower().startswith("cuda"))


#: what Warp's native library prints on a machine without an NVIDIA driver; the CLIs name the
#: devices there themselves when one is asked for (scene.resolve_device), so it is dropped
_NO_DRIVER_NOTE = b"Could not find or load the NVIDIA CUDA driver"


def _init_without_driver_note(wp, keep: bool = False):
    """``wp.init()`` with its native stderr captured: the no-driver note of a CPU-only machine is
    dropped (error messages stay one line) unless ``keep``; anything else is passed on."""
    import tempfile

    if keep:
        wp.init()
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real stderr (embedded): just initialise
        wp.init()
        return
    with tempfile.TemporaryFile() as cap:
        os.dup2(cap.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        cap.seek(0)
        rest = [ln for ln in cap.read().splitlines(keepends=True) if _NO_DRIVER_NOTE not in ln]
    if rest:
        sys.stderr.buffer.write(b"".join(rest))
        sys.stderr.flush()


# --------------------------------------------------------------------------- stopping


class Interrupted(KeyboardInterrupt):
    """A stop signal outside a region that checks for stops (raised once, by the handler)."""

    def __init__(self, signum: int):
        super().__init__(signal_name(signum))
        self.signum = int(signum)

    @property
    def exit_code(self) -> int:
        """128 + the signal number: 130 for SIGINT, 143 for SIGTERM (as a shell reports them)."""
        return 128 + self.signum


def signal_name(signum) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class _StopState:
    def __init__(self):
        self.lock = threading.Lock()
        self.reset()

    def reset(self):
        self.signum = None  # the first stop signal received
        self.counted_at = 0.0  # when the last one was counted (time.monotonic)
        self.count = 0  # stop signals received (counted by the watcher when it runs)
        self.checking = 0  # depth of checking_stops()
        self.raised = False  # Interrupted was raised once already
        self.installed = False
        self.watched = False  # a watcher thread counts the signals
        self.done = threading.Event()  # the CLI has finished (no acknowledgement needed)
        self.seen = threading.Event()  # a loop has seen the stop (or it was raised)
        self.hint = None  # () -> str: how long the stop may take (set_stop_hint), said with the acknowledgement


_state = _StopState()


def set_stop_hint(hint) -> None:
    """``hint()`` (a callable returning text, or None) is said after a stop's acknowledgement:
    how long the work in progress may take to reach the point where the stop is acted on
    (``convert``: the frame being fitted; a new user's 390k-vertex frame took 6 minutes after
    Ctrl-C, with nothing said)."""
    _state.hint = hint


def stop_requested() -> bool:
    """True once SIGINT or SIGTERM was received by a CLI (checked at step and frame boundaries)."""
    if _state.signum is None:
        return False
    _state.seen.set()
    return True


def stop_reason() -> str | None:
    """The name of the first stop signal received (``"SIGINT"``, ``"SIGTERM"``), else None: the
    ``stop`` callable the CLIs give their loops."""
    return signal_name(_state.signum) if stop_requested() else None


def stop_signal() -> int | None:
    """The first stop signal received (``signal.SIGINT`` / ``signal.SIGTERM``), else None."""
    return _state.signum


@contextlib.contextmanager
def checking_stops():
    """A region whose loops call :func:`stop_requested` at their boundaries: a first signal there
    only sets the flag (no exception in the middle of a step or of a write)."""
    _state.checking += 1
    try:
        yield
    finally:
        _state.checking -= 1


@contextlib.contextmanager
def raising_stops():
    """Inside :func:`checking_stops`, a stage with no boundaries to check (e.g. re-meshing): a
    signal raises :class:`Interrupted` at once again (also on entry, if one came before)."""
    saved = _state.checking
    _state.checking = 0
    try:
        if _state.installed and _state.signum is not None and not _state.raised:
            _state.raised = True
            _state.seen.set()
            raise Interrupted(_state.signum)
        yield
    finally:
        _state.checking = saved


def _hard_exit(signum: int):
    """The second signal: remove the temporaries of writes in progress and exit at once."""
    try:
        os.write(2, (f"\n{signal_name(signum)} again: exiting at once; unfinished outputs are discarded, "
                     "existing outputs are left as they are\n").encode())
    except OSError:
        pass
    try:
        from .outputs import abandon_temporaries

        left = abandon_temporaries(timeout=2.0)
        if left:  # a rename into place was still going on: say where its files are
            os.write(2, (f"a write into place was in progress: the output beside {', '.join(left)} may hold part "
                         "of the old and part of the new files; those hidden folders (and any .old-* beside them) "
                         "hold the rest of this tool's files (the user's files were not moved)\n").encode())
    except BaseException:  # noqa: BLE001 (exiting whatever happens)
        pass
    os._exit(128 + int(signum))


def _acknowledge(signum: int):
    """A stop that takes longer than a moment (a long frame, a native call) says it is coming."""
    if _state.done.is_set() or _state.seen.is_set() or not _state.installed:
        return
    try:
        hint = _state.hint() if _state.hint is not None else ""
    except Exception:  # noqa: BLE001 (a hint never stops the acknowledgement)
        hint = ""
    try:
        sys.stderr.write(f"\n{signal_name(signum)}: stopping at the next step or frame and writing what is done"
                         + (f" ({hint})" if hint else "") + "; send it again to exit at once (the frame in progress "
                         "is then lost, the ones done are kept for --resume where there is a journal)\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass


def _first(signum: int) -> int:
    """Count a stop signal; returns how many were received."""
    with _state.lock:
        if _state.signum is None:
            _state.signum = int(signum)
            t = threading.Timer(_ACK_AFTER_S, _acknowledge, args=(int(signum),))
            t.daemon = True
            t.start()
        now = time.monotonic()
        if _state.count and now - _state.counted_at < _SAME_STOP_S:
            return _state.count  # the same stop, sent twice (``timeout``: to the command, then its group)
        _state.count += 1
        _state.counted_at = now
        return _state.count


def _on_signal(signum, frame):
    """The Python-level handler (main thread, between bytecodes)."""
    if not _state.watched:
        if _first(signum) >= 2:
            _hard_exit(signum)
    elif _state.signum is None:  # the watcher has not read the byte yet
        with _state.lock:
            _state.signum = _state.signum or int(signum)
    # a stop a loop has already seen is being handled (its output written): a repeat of it (within
    # the same-stop window; later ones exit through the watcher) must not raise in the middle of that
    if _state.checking == 0 and not _state.raised and not _state.seen.is_set():
        _state.raised = True
        _state.seen.set()
        raise Interrupted(_state.signum)


def _watch(fd: int):
    """Read the signal numbers CPython's C handler writes to the wakeup fd; runs even while the
    main thread is inside a native call, so a second signal always exits at once."""
    wanted = {int(s) for s in STOP_SIGNALS}
    try:
        while True:
            try:
                data = os.read(fd, 64)
            except InterruptedError:
                continue
            except OSError:
                return
            if not data:
                return
            for b in data:
                if b in wanted and _first(b) >= 2:
                    _hard_exit(b)
    finally:
        try:
            os.close(fd)
        except OSError:
            pass


@contextlib.contextmanager
def handle_stop_signals():
    """Install the stop handlers (SIGINT, SIGTERM) for the duration of a CLI's ``main``; the
    previous handlers are restored afterwards (``main`` called in-process, e.g. by tests).
    Outside the main thread nothing is installed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _state.reset()
    if getattr(sys.excepthook, "start_up_only", False):  # the package's start-up hook: its time is over
        sys.excepthook = sys.__excepthook__
    old = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    r, w = os.pipe()
    os.set_blocking(w, False)
    try:
        old_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        threading.Thread(target=_watch, args=(r,), name="dynmesh-stop-watcher", daemon=True).start()
        _state.watched = True
    except (ValueError, OSError):  # no wakeup fd here: the Python handler counts
        old_fd = None
        os.close(r)
    for s in STOP_SIGNALS:
        signal.signal(s, _on_signal)
    _state.installed = True
    try:
        yield
    finally:
        _state.done.set()
        _state.raised = True  # nothing left to interrupt: a late signal must not raise in the sleep below
        if _state.count or _state.signum is not None:  # a stop: its second signal (timeout's, to the
            # group) may still be coming. Not counted yet when the watcher thread has not read the
            # first from the wakeup fd: its window starts now (the suite's late-signal test sent
            # the second into the default handler, 1 run in 5)
            rest = _SAME_STOP_S - (time.monotonic() - _state.counted_at) if _state.count else _SAME_STOP_S
            if rest > 0:  # the output was written within the window: the default handler would kill
                time.sleep(rest)  # the exiting process (exit -2, not 130; a loaded CI machine's find)
        for s, h in old.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
        if old_fd is not None:
            signal.set_wakeup_fd(old_fd)
        os.close(w)  # the watcher reads EOF and ends
        _state.installed = False


@contextlib.contextmanager
def user_warnings():
    """While a command line runs, its own warnings (``UserWarning``: what the data or the scene
    may get wrong) print as one line, ``warning: <message>``, without Python's file, line and
    source line; other categories (a library's ``RuntimeWarning`` ...) keep Python's format."""
    shown = warnings.formatwarning

    def short(message, category, filename, lineno, line=None):
        if issubclass(category, UserWarning):
            return f"warning: {message}\n"
        return shown(message, category, filename, lineno, line)

    warnings.formatwarning = short
    try:
        yield
    finally:
        warnings.formatwarning = shown


def interruptible_main(fn):
    """Decorate a CLI's ``main(argv)``: stop handlers installed while it runs; an
    :class:`Interrupted` that reaches it (a signal outside a checking region, before anything
    was written) becomes one line on stderr and exit code 130 / 143."""

    @functools.wraps(fn)
    def main(argv=None) -> int:
        with handle_stop_signals(), user_warnings():
            try:
                return fn(argv)
            except Interrupted as e:
                print(f"interrupted ({signal_name(e.signum)}) before any output was written; existing "
                      "outputs are unchanged", file=sys.stderr)
                return e.exit_code
            except MemoryError:  # a new user's evaluate --resolution 1200: a MemoryError traceback
                print("error: out of memory; nothing more was written (outputs are atomic). Ask for less: a "
                      "lower --resolution, fewer --frames / --envs / spheres, or a smaller image", file=sys.stderr)
                return 1
            except OSError as e:
                from .outputs import WRITE_ERRNOS, write_error_text

                if e.errno not in WRITE_ERRNOS:
                    raise
                # a full disk, a file-size limit, a read-only file system during the work: four chained
                # tracebacks and exit 1 before (a new user's)
                print(f"{write_error_text(e)}. Free space or lift the limit and run again", file=sys.stderr)
                return 1

    return main


#: the command lines, ``python -m dynmesh_warp.<name>`` (README.md)
COMMANDS = {
    "run": "a scene (YAML, a mesh sequence, or none: the built-in default) with physics, viewer, outputs",
    "convert": "a varying-topology sequence to one fixed topology (a template tracked through it)",
    "evaluate": "the conversion's accuracy against a reference (Chamfer / EMD per frame, the paper's Table 1)",
    "render": "a scene's Gaussians (and spheres) to images or a video",
    "distributed": "batched envs across GPUs and machines with Ray",
}



def not_a_command(module: str, what: str) -> None:
    """For ``python -m dynmesh_warp.<module>`` of a module that is no command: says what it
    holds and lists the commands, exit 2 (it did nothing, exit 0)."""
    print(f"dynmesh_warp.{module} {what}; it is not a command. The commands:\n"
          + "\n".join(f"  python -m dynmesh_warp.{k:<12} {v}" for k, v in COMMANDS.items())
          + "\n(each with --help)", file=sys.stderr)
    sys.exit(2)


if __name__ == "__main__":  # a new user's `python -m dynmesh_warp.cli convert ...` did nothing, exit 0
    not_a_command("cli", "holds the commands' shared helpers")
