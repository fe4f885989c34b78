"""Spheres on real reconstruction-like data: the horse gallop of Sumner & Popovic,
"Deformation Transfer for Triangle Meshes", SIGGRAPH 2004 (24 frames, 8431 vertices,
16843 faces, y-up; see /work/shared/data/README.md). Skipped when the data is absent."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from reference import surface_at, winding_number
from dynmesh_warp.sequence import FixedTopologySequence
from dynmesh_warp.world import Model, PhysicsParams, SphereModel, State, SurfaceModel, World
from conftest import TEST_DEVICE

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
HORSE = DATA / "horse_gallop.npz"


@pytest.fixture(scope="module")
def horse():
    if not HORSE.is_file():
        pytest.skip(f"{HORSE} not present")
    d = np.load(HORSE)
    return FixedTopologySequence(d["V"], d["F"], fps=float(d["fps"]), name="horse_gallop", source=str(HORSE))


@pytest.mark.parametrize("collider", ["fixed", "refit"])
def test_spheres_on_galloping_horse_stay_outside(horse, collider):
    V0 = horse.V[0]
    r = 0.05
    # five spheres just above the back (y is up), from the rump to the withers
    zs = np.linspace(-0.6, 0.1, 5)
    pos = []
    for z in zs:
        near = np.abs(V0[:, 2] - z) < 0.03
        top = V0[near][np.argmax(V0[near, 1])]
        pos.append([top[0], top[1] + r + 0.02, z])
    surf = SurfaceModel(horse, TEST_DEVICE, playback="loop")
    model = Model(surf, SphereModel(np.full(5, r), 1.0, TEST_DEVICE), PhysicsParams(dt=1 / 240, gravity=(0.0, -9.81, 0.0)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legs move at ~14 m/s: auto sub-steps are raised
        w = World(model, State(model, np.asarray(pos, np.float32)), collider=collider)
    assert w.substeps >= 2  # surface speed * dt > r / 2 forces sub-steps
    touched = np.zeros(5, bool)
    for i in range(200):
        w.step()
        touched |= w.contacts.face.numpy() >= 0
        if i % 5 == 0 or i == 199:
            P = w.sphere_positions()
            assert np.isfinite(P).all() and np.isfinite(w.sphere_velocities()).all(), f"NaN at step {i}"
            wn = winding_number(surface_at(horse, w.time), horse.F, P)
            assert (wn < 0.5).all(), f"step {i}: a sphere centre is inside the horse: {wn}"
    assert touched.all()  # every sphere landed on the horse at some point
