"""dynmesh_warp: rigid bodies on deforming meshes from dynamic 3D reconstructions, on NVIDIA Warp.

The public surface is small; see ``__all__``. Importing the package does not import viser or
newton (the viewer and the Newton adapter are imported on use).
"""

from .config import SceneConfig, SceneError, load_scene_config
from .scene import build_world, load_surface
from .sequence import FixedTopologySequence, MeshDataError, VaryingTopologySequence, validate_mesh
from .world import Contacts, Model, PhysicsParams, SphereModel, State, SurfaceModel, VaryingSurfaceModel, World

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
    "World",
]
