"""Closed choices shared by the library, the scene schema and the CLIs, each with its default in
one place. Bottom layer: imports nothing from the package."""

from __future__ import annotations

__all__ = ["STRATEGIES", "DEFAULT_STRATEGY"]

#: topology conversion strategies (dynmesh_warp.convert, docs/conversion.md)
STRATEGIES = ("projection", "tracking", "regularized", "graph")
#: the default conversion: the embedded deformation graph (best on every sequence of docs/evaluation.md)
DEFAULT_STRATEGY = "graph"
