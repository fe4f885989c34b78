"""Shared fixtures of the test suite: Warp on the CPU, quiet; small meshes. The NumPy oracles
are in ``reference.py``."""

from __future__ import annotations

from pathlib import Path

import os

import numpy as np
import pytest
import warp as wp

wp.config.quiet = True
if hasattr(wp, "LOG_WARNING"):
    wp.config.log_level = wp.LOG_WARNING  # no per-module load lines in test output
wp.init()

# Unit tests run on Warp's CPU device (CI has no GPU). DYNMESH_TEST_DEVICE=cuda:0 runs the
# device-parametrized tests (kernels, world, swept collider, Gaussians, metrics) on a GPU.
TEST_DEVICE = os.environ.get("DYNMESH_TEST_DEVICE", "cpu")

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def device():
    """The Warp device of the tests: "cpu" unless DYNMESH_TEST_DEVICE says otherwise."""
    return TEST_DEVICE


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def deformed_icosphere():
    """(V float32 (N,3), F int32 (M,3)): a level-2 icosphere with a fixed random radial bump."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    r = np.random.default_rng(7)
    V = np.asarray(m.vertices) * (1.0 + 0.25 * r.random((len(m.vertices), 1)))
    V = V + r.normal(0, 0.02, V.shape)
    return V.astype(np.float32), np.asarray(m.faces, np.int32)


# ---------------------------------------------------------------------------------------------
# Independent NumPy references (vectorised brute force, float64)
# ---------------------------------------------------------------------------------------------


def project_to_mesh(mesh: "wp.Mesh", queries: np.ndarray, device, max_dist: float = 1.0e6):
    """Run the engine's project_points_to_mesh kernel; return NumPy (closest, face, bary, dist)."""
    from dynmesh_warp.kernels.geometry import project_points_to_mesh

    Q = len(queries)
    q = wp.array(np.asarray(queries, np.float32), dtype=wp.vec3, device=device)
    closest = wp.zeros(Q, dtype=wp.vec3, device=device)
    face = wp.zeros(Q, dtype=wp.int32, device=device)
    bary = wp.zeros(Q, dtype=wp.vec3, device=device)
    dist = wp.zeros(Q, dtype=float, device=device)
    wp.launch(project_points_to_mesh, dim=Q, inputs=[mesh.id, q, float(max_dist)],
              outputs=[closest, face, bary, dist], device=device)
    return closest.numpy(), face.numpy(), bary.numpy(), dist.numpy()


