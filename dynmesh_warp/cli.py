"""Shared command-line helpers."""

from __future__ import annotations


def quiet_warp():
    """Silence Warp's start-up banner and per-module load lines (CLIs print their own summary)."""
    import warp as wp

    wp.config.quiet = True
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        wp.config.log_level = wp.LOG_WARNING
