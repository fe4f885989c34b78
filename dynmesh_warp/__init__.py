"""dynmesh_warp: rigid bodies on deforming meshes from dynamic 3D reconstructions, on NVIDIA Warp.

The public surface is small; see ``__all__``. Importing the package does not import viser or
newton (the viewer and the Newton adapter are imported on use).
"""

import importlib.util as _ilu
import os as _os
import sys as _sys


def _map_source_kernels():
    """In a source checkout that shadows the installed package (``python -m pytest`` from the
    repository root puts it first on sys.path), map ``<repo>/kernels`` to ``dynmesh_warp.kernels``
    as the installed package does through ``package-dir``."""
    name = __name__ + ".kernels"
    if name in _sys.modules or _ilu.find_spec(name) is not None:
        return
    folder = _os.path.join(_os.path.dirname(_os.path.dirname(_os.path.abspath(__file__))), "kernels")
    init = _os.path.join(folder, "__init__.py")
    if _os.path.isfile(init):
        spec = _ilu.spec_from_file_location(name, init, submodule_search_locations=[folder])
        module = _ilu.module_from_spec(spec)
        _sys.modules[name] = module
        spec.loader.exec_module(module)


_map_source_kernels()


def _quiet_start_up_interrupt():
    """``python -m dynmesh_warp.<command>`` (runpy sets ``sys.argv[0]`` to ``"-m"`` while it
    imports the package): a Ctrl-C before the command installs its own handlers, i.e. while Warp
    and the rest are imported, ends with one line and exit 130 instead of a 37-line traceback
    from ``import warp`` (a new user). Library imports are left alone."""
    if _sys.argv[:1] != ["-m"] or _sys.excepthook is not _sys.__excepthook__:
        return

    def hook(kind, value, tb):
        if issubclass(kind, KeyboardInterrupt):
            print("interrupted during start-up; nothing was done", file=_sys.stderr)
            _sys.exit(130)
        _sys.__excepthook__(kind, value, tb)

    hook.start_up_only = True  # cli.handle_stop_signals puts the default back once its handlers are in
    _sys.excepthook = hook


_quiet_start_up_interrupt()

from .config import SceneConfig, SceneError, load_scene_config  # noqa: E402
from .scene import build_model, build_world, load_surface  # noqa: E402
from .sequence import FixedTopologySequence, MeshDataError, VaryingTopologySequence, validate_mesh  # noqa: E402
from .world import (  # noqa: E402
    Contacts,
    Model,
    PhysicsParams,
    SphereModel,
    State,
    StepContext,
    SurfaceModel,
    VaryingSurfaceModel,
    World,
)

#: public names imported on first use (the conversion, I/O, Gaussians and viewer modules pull in
#: SciPy, scikit-image, viser...): name -> module
_LAZY = {
    "load_sequence": "io", "save_sequence": "io",
    "to_fixed_topology": "convert", "to_piecewise_fixed": "convert", "ConversionInfo": "convert",
    "Gaussians": "gaussians", "gaussians_for_world": "gaussians",
    "Viewer": "viewer", "NewtonViewer": "viewer",
    "Simulation": "runtime",
    "run_simulation": "runner",
    "BatchedWorld": "batch", "build_batched_world": "batch",
    "RideSurfaceEnv": "envs", "RideSurfaceSingleEnv": "envs",
    "Renderer": "render", "Camera": "render", "render_world": "render", "render_envs": "render",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__version__ = "0.1.0"

__all__ = [
    "FixedTopologySequence",
    "VaryingTopologySequence",
    "MeshDataError",
    "validate_mesh",
    "SceneConfig",
    "SceneError",
    "load_scene_config",
    "build_world",
    "load_surface",
    "PhysicsParams",
    "SurfaceModel",
    "VaryingSurfaceModel",
    "SphereModel",
    "Model",
    "State",
    "Contacts",
    "StepContext",
    "World",
    "Simulation",
    "load_sequence",
    "save_sequence",
    "to_fixed_topology",
    "to_piecewise_fixed",
    "ConversionInfo",
    "Gaussians",
    "gaussians_for_world",
    "Viewer",
    "NewtonViewer",
    "run_simulation",
    "build_model",
    "BatchedWorld",
    "build_batched_world",
    "RideSurfaceEnv",
    "RideSurfaceSingleEnv",
    "Renderer",
    "Camera",
    "render_world",
    "render_envs",
]
