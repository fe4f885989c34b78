"""Checkpoints of a run (``run --checkpoint-every N``, ``run --resume PATH``; docs/scene.md).

A checkpoint is one ``.npz`` file (written atomically, NumPy arrays only, no pickles):

- ``format``: :data:`FORMAT`; ``meta``: JSON text with the scene name, the step it was
  written at, the run's step count, the checkpoint interval, the device, the number of contact
  samples so far and the scene's fingerprint (:func:`scene_fingerprint`);
- the world's state (:meth:`World.checkpoint_state <dynmesh_warp.world.World.checkpoint_state>`):
  ``time``, ``sim_time``, ``substep_count``, ``sphere_pos``, ``sphere_vel``, ``sphere_spin`` (zero in a
  checkpoint written before spheres could rotate, which it then was), ``frame_key``, ``frame_changed``,
  ``contact_face`` (each sphere's last contact face: the seeded searches read it),
  ``contact_memory`` (the integrator's pinch memory, 16 floats a sphere) and the collider's
  ``collider_*`` arrays;
- ``radius`` and ``inv_mass`` of the spheres (compared with the scene's, sphere by sphere);
- ``traj_time``, ``traj_position``, ``traj_velocity``: the trajectory samples taken so far (every
  ``run.record_every`` steps), so a resumed run writes the whole trajectory.

:func:`load_checkpoint` checks the file (every field present, of the right type, shape and
finite) and :meth:`Checkpoint.check` checks it against the world built from the scene; each
failure is a :class:`CheckpointError` (a ``SceneError``: exit 2) naming the file and the field.
"""

from __future__ import annotations

import hashlib
import json
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import SceneError

__all__ = ["CheckpointError", "Checkpoint", "FORMAT", "CHECKPOINT_NAME", "scene_fingerprint", "save_checkpoint",
           "load_checkpoint"]

#: file name of the checkpoint in a run's output folder
CHECKPOINT_NAME = "checkpoint.npz"
#: the ``format`` field of the files this version writes and reads
# 2: the clock's frame_key / frame_changed are state fields; 3: the trajectory samples start at
# step 0 (a checkpoint of 2, resumed, would mix two grids) and the fingerprint holds the spheres' start
# 4: the integrator's pinch memory (``contact_memory``, 16 floats a sphere; Contacts.memory)
FORMAT = "dynmesh_warp.checkpoint/4"
#: the format before: read too, the pinch memory started empty (a warning says so)
PREVIOUS_FORMAT = "dynmesh_warp.checkpoint/3"


class CheckpointError(SceneError):
    """A checkpoint that cannot be read, or that was written for another scene; one line naming
    the file and the field."""


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def scene_fingerprint(world) -> dict:
    """What a checkpoint must agree on with the world it is restored into, keyed by the scene
    field it comes from: the surface (frames, vertex and face counts, fps, playback,
    interpolation, a digest of every vertex position and face), the sphere count, a digest of the
    spheres' starting positions and velocities, the physics
    parameters, the sub-steps actually used and the collider."""
    m = world.model
    surf, p = m.surface, m.params
    arrays, nv, nf = surf.geometry_digest_inputs()
    kind, geom = surf.topology, _digest(*arrays)
    col = world.collider.name + (f"/{world.collider.every}" if world.collider.name == "rebuild" else "")
    return {
        "surface.topology": kind,
        "surface.frames": int(surf.num_frames),
        "surface.vertices": nv,
        "surface.faces": nf,
        "surface.fps": float(surf.fps),
        "surface.playback": surf.playback_name,
        "surface.interpolate": bool(surf.interpolate),
        "surface.data (vertex positions and faces)": geom,
        "spheres.count": int(m.spheres.count),
        # where the scene's spheres start: a resume with another start (a new user's --set of a
        # sphere's position) continued the old trajectory with exit 0
        "spheres.start (positions and velocities)": _digest(*world.initial_spheres()),
        "physics.dt": float(p.dt),
        "physics.substeps (used)": int(world.substeps),
        "physics.gravity": [float(g) for g in p.gravity],
        "physics.restitution": float(p.restitution),
        "physics.friction": float(p.friction),
        "physics.rest_speed": float(p.rest_speed),
        "physics.margin": float(p.margin),
        "physics.ground": None if p.ground_height is None else float(p.ground_height),
        "physics.sphere_body": str(p.sphere_body),
        "physics.collider": col,
    }


@dataclass
class Checkpoint:
    """A checkpoint read by :func:`load_checkpoint` (already checked on its own)."""

    path: Path
    meta: dict
    state: dict  # World.checkpoint_state()
    radius: np.ndarray
    inv_mass: np.ndarray
    times: list
    positions: list
    velocities: list

    @property
    def step(self) -> int:
        return int(self.meta["step"])

    @property
    def checkpoint_every(self) -> int:
        return int(self.meta["checkpoint_every"])

    @property
    def contact_samples(self) -> int:
        return int(self.meta["contact_samples"])

    def check_record_every(self, record_every: int) -> None:
        """Refuse a resumed run that samples its trajectory at another ``run.record_every`` than
        the checkpoint's samples (a trajectory of mixed spacing); checkpoints that predate the
        field are not checked."""
        have = self.meta.get("record_every")
        if have is not None and int(have) != int(record_every):
            raise CheckpointError(f"--resume {self.path}: its trajectory is sampled every {have} steps "
                                  f"(run.record_every), this run asks {record_every}; resume with "
                                  f"run.record_every={have}")

    def check(self, world) -> None:
        """Refuse (:class:`CheckpointError`) a checkpoint written for another scene, naming the
        first field that differs and both values."""
        want = scene_fingerprint(world)
        # (a checkpoint from before spheres could rotate: its spheres were point masses)
        have = {"physics.sphere_body": "point", **self.meta["fingerprint"]}
        for key, value in want.items():
            if key not in have:
                raise CheckpointError(f"--resume {self.path}: field {key!r} missing from the checkpoint's scene "
                                      "fingerprint; written by another version?")
            if have[key] != value:
                raise CheckpointError(
                    f"--resume {self.path}: written for another scene: {key} is {have[key]!r} in the checkpoint but "
                    f"{value!r} here; resume with the scene file, data and options it was written with "
                    f"(scene {self.meta.get('scene')!r})")
        for name, mine, theirs in (("radius", world.model.spheres.radius_np, self.radius),
                                   ("mass", world.model.spheres.inv_mass.numpy(), self.inv_mass)):
            bad = np.flatnonzero(np.asarray(mine, np.float32) != np.asarray(theirs, np.float32))
            if bad.size:
                i = int(bad[0])
                shown = (lambda v: v) if name == "radius" else (lambda v: (1.0 / v) if v > 0 else float("inf"))
                raise CheckpointError(f"--resume {self.path}: written for another scene: spheres.{i}.{name} is "
                                      f"{shown(float(theirs[i])):.6g} in the checkpoint but {shown(float(mine[i])):.6g} here")
        for k, a in world.checkpoint_state().items():
            if k not in self.state:
                raise CheckpointError(f"--resume {self.path}: missing field {k!r} (the collider "
                                      f"{want['physics.collider']!r} keeps it); written by another version?")
            if np.asarray(self.state[k]).shape != np.asarray(a).shape:
                raise CheckpointError(f"--resume {self.path}: field {k!r} has shape {np.asarray(self.state[k]).shape}, "
                                      f"the scene needs {np.asarray(a).shape}")

    def restore(self, world) -> None:
        """:meth:`check`, then put the state into ``world``."""
        self.check(world)
        world.restore_checkpoint_state(self.state)


def save_checkpoint(path, world, *, scene: str, step: int, steps: int, checkpoint_every: int,
                    contact_samples: int, times, positions, velocities, record_every: int | None = None) -> None:
    """Write ``world``'s state at ``step`` and the trajectory samples so far to ``path``
    (atomically; the old file stays until the new one is complete)."""
    from .outputs import atomic_write_npz

    state = world.checkpoint_state()
    S = world.model.spheres.count
    meta = {"scene": scene, "step": int(step), "steps": int(steps), "checkpoint_every": int(checkpoint_every),
            "device": str(world.device), "contact_samples": int(contact_samples),
            "fingerprint": scene_fingerprint(world)}
    if record_every is not None:  # the trajectory's sampling: a resumed run must keep it
        meta["record_every"] = int(record_every)
    atomic_write_npz(
        path, format=np.asarray(FORMAT), meta=np.asarray(json.dumps(meta)), **state,
        radius=world.model.spheres.radius_np, inv_mass=world.model.spheres.inv_mass.numpy(),
        traj_time=np.asarray(times, np.float64).reshape(-1),
        traj_position=np.asarray(positions, np.float32).reshape(-1, S, 3),
        traj_velocity=np.asarray(velocities, np.float32).reshape(-1, S, 3))


#: state fields every checkpoint has: name -> (dtype kind, shape with "S" for the sphere count)
_STATE_FIELDS = {"time": ("f", ()), "sim_time": ("f", (1,)), "substep_count": ("i", ()),
                 "sphere_pos": ("f", ("S", 3)), "sphere_vel": ("f", ("S", 3)), "sphere_spin": ("f", ("S", 3)),
                 "frame_key": ("i", (1,)), "frame_changed": ("i", (1,)), "contact_face": ("i", ("S",)),
                 "contact_memory": ("f", ("S", 16))}


def load_checkpoint(path) -> Checkpoint:
    """Read and check a checkpoint file on its own (not yet against a scene: :meth:`Checkpoint.check`)."""
    shown = str(path)
    path = Path(path).expanduser()
    where = f"--resume {shown}"
    if not path.is_file():
        raise CheckpointError(f"{where}: file not found" if not path.exists() else f"{where}: not a file")
    if not zipfile.is_zipfile(path):
        raise CheckpointError(f"{where}: not a checkpoint (not an .npz file, which is a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 (any read error is the file's)
        raise CheckpointError(f"{where}: cannot read it ({type(e).__name__}: {e})") from None

    def need(k):
        if k not in data:
            raise CheckpointError(f"{where}: missing field {k!r}; not a checkpoint of this tool, or written by "
                                  "another version")
        return data[k]

    fmt = need("format")
    if fmt.shape != () or fmt.dtype.kind != "U" or str(fmt) not in (FORMAT, PREVIOUS_FORMAT):
        raise CheckpointError(f"{where}: field 'format' is {str(fmt)[:80]!r}, expected {FORMAT!r} (or "
                              f"{PREVIOUS_FORMAT!r})")
    previous = str(fmt) == PREVIOUS_FORMAT and "contact_memory" not in data
    try:
        meta = json.loads(str(need("meta")))
        if not isinstance(meta, dict):
            raise ValueError("not an object")
    except ValueError as e:
        raise CheckpointError(f"{where}: field 'meta' is not valid JSON ({e})") from None
    for k, typ in (("step", int), ("steps", int), ("checkpoint_every", int), ("contact_samples", int),
                   ("fingerprint", dict)):
        v = meta.get(k)
        if not isinstance(v, typ) or isinstance(v, bool) or (typ is int and v < 0):
            raise CheckpointError(f"{where}: field 'meta.{k}' is {v!r}, expected "
                                  + ("a non-negative integer" if typ is int else "an object"))
    v = meta.get("record_every")  # optional (checkpoints that predate it have none)
    if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 1):
        raise CheckpointError(f"{where}: field 'meta.record_every' is {v!r}, expected a positive integer")
    if meta["step"] < 1:
        raise CheckpointError(f"{where}: field 'meta.step' is {meta['step']}, expected at least 1")
    S = meta["fingerprint"].get("spheres.count")
    if not isinstance(S, int) or isinstance(S, bool) or S < 0:
        raise CheckpointError(f"{where}: field 'meta.fingerprint.spheres.count' is {S!r}, expected a count")

    def array(k, kind, shape):
        a = need(k)
        want = tuple(S if d == "S" else d for d in shape)
        if a.dtype.kind != kind or a.shape != want:
            raise CheckpointError(f"{where}: field {k!r} is {a.dtype} {a.shape}, expected "
                                  f"{'float' if kind == 'f' else 'integer'} {want}")
        if kind == "f" and not np.isfinite(a).all():
            raise CheckpointError(f"{where}: field {k!r} holds NaN or inf")
        return a

    if previous:  # (written before the pinch memory: it starts empty, as at a reset)
        data["contact_memory"] = np.zeros((S, 16), np.float32)
        warnings.warn(f"{where}: a checkpoint of the previous format ({PREVIOUS_FORMAT}), written before the "
                      "integrator kept a pinch memory: resumed with none (a sphere pinched at that step is "
                      "resolved afresh; otherwise the run goes on as it would have)", stacklevel=2)
    data.setdefault("sphere_spin", np.zeros((S, 3), np.float32))  # (written before spheres could rotate)
    state = {k: array(k, kind, shape) for k, (kind, shape) in _STATE_FIELDS.items()}
    for k, a in data.items():
        if k.startswith("collider_"):
            if a.dtype.kind not in "fi":
                raise CheckpointError(f"{where}: field {k!r} is {a.dtype}, expected numbers")
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                raise CheckpointError(f"{where}: field {k!r} holds NaN or inf")
            state[k] = a
    if float(state["time"]) != float(state["sim_time"][0]):
        raise CheckpointError(f"{where}: fields 'time' ({float(state['time'])!r}) and 'sim_time' "
                              f"({float(state['sim_time'][0])!r}) disagree")
    radius = array("radius", "f", ("S",))
    inv_mass = array("inv_mass", "f", ("S",))
    tt = need("traj_time")
    if tt.ndim != 1:
        raise CheckpointError(f"{where}: field 'traj_time' has shape {tt.shape}, expected one dimension")
    K = tt.shape[0]
    tt = array("traj_time", "f", (K,))
    tp = array("traj_position", "f", (K, "S", 3))
    tv = array("traj_velocity", "f", (K, "S", 3))
    return Checkpoint(path=path, meta=meta, state=state, radius=radius, inv_mass=inv_mass, times=list(tt),
                      positions=list(tp), velocities=list(tv))
