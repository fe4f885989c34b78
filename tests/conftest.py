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

# The device matrix, in one run: the tests that take the ``device`` fixture (kernels, world,
# swept collider, Gaussians, metrics, conversion, Newton adapter) run on the CPU always and on
# CUDA too when a GPU is present (CI has none). DYNMESH_TEST_DEVICES=cpu,cuda:0 (or the older
# DYNMESH_TEST_DEVICE=cuda:0) chooses the devices; TEST_DEVICE, the first, is the device of the
# tests that are not parametrized.
def _test_devices() -> list[str]:
    env = os.environ.get("DYNMESH_TEST_DEVICES") or os.environ.get("DYNMESH_TEST_DEVICE")
    if env:
        return [d.strip() for d in env.split(",") if d.strip()]
    return ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


DEVICES = _test_devices()
TEST_DEVICE = DEVICES[0]

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session", params=DEVICES)
def device(request):
    """A Warp device of the matrix (``DEVICES``): each test taking it runs once per device."""
    return request.param


@pytest.fixture
def cuda_device(device):
    """The matrix's device where it is a GPU; the test is skipped on the CPU."""
    if not str(device).startswith("cuda"):
        pytest.skip("needs a CUDA device (CUDA graph capture)")
    return device


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




@pytest.fixture(autouse=True)
def _short_collider_trials(monkeypatch):
    """``collider: fixed`` measures both colliders on a trial run when a world is built (2
    simulated s, up to 0.5 s of wall time each): hundreds of worlds in the suite would spend
    minutes there. Tests keep the measurement but on a 0.05 s trial; the tests of the choice
    itself (tests/test_swept.py) time it in full where they need to."""
    import dynmesh_warp.world as world_mod

    monkeypatch.setattr(world_mod, "CHOICE_HORIZON", 0.05)
    monkeypatch.setattr(world_mod, "CHOICE_SECONDS", 0.05)
