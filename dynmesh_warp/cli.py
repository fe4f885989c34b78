"""Shared command-line helpers."""

from __future__ import annotations

import argparse


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``error: ... (see --help)``, exit 2), like every other
    check of the command lines, instead of the usage block."""

    def error(self, message):
        self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def quiet_warp():
    """Silence Warp's start-up banner and per-module load lines (CLIs print their own summary)."""
    import warp as wp

    wp.config.quiet = True
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        wp.config.log_level = wp.LOG_WARNING
    _init_without_driver_note(wp)
    _exit_cleanly_on_sigterm()


def _exit_cleanly_on_sigterm():
    """SIGTERM (``timeout``, ``kill``) raises SystemExit like Ctrl-C raises KeyboardInterrupt, so
    the temporary output files and folders are removed and the old outputs stay."""
    import signal
    import sys
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))


#: what Warp's native library prints on a machine without an NVIDIA driver; the CLIs name the
#: devices there themselves when one is asked for (scene.resolve_device), so it is dropped
_NO_DRIVER_NOTE = b"Could not find or load the NVIDIA CUDA driver"


def _init_without_driver_note(wp):
    """``wp.init()`` with its native stderr captured: the no-driver note of a CPU-only machine is
    dropped (error messages stay one line), anything else is passed on."""
    import os
    import sys
    import tempfile

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
