"""Soak test (issue #17): long runs of the paper scene and the built-in scenes with spheres
dropped continuously, checking every N steps that no sphere centre is inside the surface and
that every value stays finite.

    python bench/soak.py --device cpu --steps 100000            # bench/results/soak_cpu.json
    python bench/soak.py --device cuda --steps 1000000          # bench/results/soak_cuda.json
    python bench/soak.py --scenes paper --steps 20000 --out /tmp/soak.json

Scenes: ``paper`` (examples/horse_gallop.yaml on ../shared/data/horse_gallop.npz, swept
collider, ground) and the built-in surfaces ``wave_bowl``, ``pulsing_blob``, ``rigid_motion``,
``articulated_figure`` (fixed topology, swept collider, a ground plane under each but the
open sheet wave_bowl) and
``torus_to_sphere`` (varying topology, rebuild collider, no ground: with one, a sphere resting
in the torus's hole is engulfed when the hole closes, which no collider can prevent; spheres
falling through the hole fall away and are dropped again). Every scene runs ``--steps``
physics steps.

Spheres: the scene's own, plus one dropped every ``--drop-every`` steps above the surface at a
seeded random spot (like the viewer's "drop sphere" button) until ``--max-spheres``; from then
on the lowest sphere (at rest on the ground, or fallen away) is taken out and dropped again
(a new sphere in the same slot), so spheres keep arriving for the whole run at a bounded cost.
``--recycle oldest`` takes the oldest sphere instead (slots in turn: with 32 spheres and a drop
every 60 steps, the one dropped 1,920 steps = 8 s earlier, at rest by then); it needs no read-back
of the spheres, so the GPU runs the steps between checks without waiting for the host (used for
the 10^6-step GPU run).

Checks, every ``--check-every`` steps (and at the last step), computed here in NumPy float64,
independently of the step's kernels:

- finite: every sphere position and velocity;
- tunnelled: a sphere centre inside the surface at the world's time (frames k, k+1 blended as
  the scene plays them; a varying-topology surface holds frame k). Closed surfaces (and the
  horse, closed but for 19 edges of small holes): generalized winding number (solid angles
  summed over all faces) >= 0.5. The open height-field sheet (wave_bowl, no ground: spheres
  that fall off its rim fall away): the centre below the sheet at its (x, y), farther than a
  radius from the rim in (x, y) (closer, a sphere may have gone round the rim's edge).

The JSON (``bench/results/soak_<device>.json`` unless ``--out``) names the machine and device
and, per scene: steps, steps/s, spheres dropped, checks, tunnelled and non-finite counts (with
the first few events), and how many sphere checks found the sphere in contact with the surface
(the run is not vacuous). Ctrl-C writes what was done, marked ``"interrupted": true``; with
``--checkpoint PATH`` (one scene) it also writes the run's state there, and ``--resume PATH`` (same
options) continues it in a new process to the same end (``"segments"`` in the JSON): a 10^6-step
GPU run longer than one machine slot is one simulation in two processes.
Exit status 0 when every scene passed (0 tunnelled, 0 non-finite), else 1.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS, ROOT, SHARED_DATA, describe_device, write_json  # noqa: E402

BUILTIN = ("wave_bowl", "pulsing_blob", "rigid_motion", "articulated_figure", "torus_to_sphere")
ALL_SCENES = ("paper",) + BUILTIN


def scene_config(name: str):
    from dynmesh_warp import load_scene_config

    if name == "paper":
        return load_scene_config(ROOT / "examples" / "horse_gallop.yaml")
    spheres = {"count": 5, "radius": 0.05, "height": 0.3, "spread": 0.5, "seed": 0}
    physics = {"ground": "auto" if name != "wave_bowl" else None}  # open sheet: what falls off the rim falls away
    surface = {"source": f"builtin:{name}", "playback": "loop"}
    if name == "torus_to_sphere":  # varying topology: as examples/torus_to_sphere_rebuild.yaml
        surface.update(params={"frames": 48, "resolution": 32}, playback="pingpong")
        # a new BVH when the faces change (every frame here), refit between: the default
        # rebuild_every (segment); "frame" needs the frames held (interpolate: false)
        physics.update(collider="rebuild", ground=None)
    return load_scene_config(data={"name": f"soak_{name}", "surface": surface, "spheres": spheres,
                                   "physics": physics})


# --------------------------------------------------------------------------- the checks


def winding_number(V: np.ndarray, F: np.ndarray, P: np.ndarray, chunk: int = 8) -> np.ndarray:
    """Generalized winding number of points P (Q, 3) w.r.t. the triangle mesh (V, F) (van
    Oosterom-Strackee solid angles): ~1 inside a closed outward-oriented mesh, ~0 outside."""
    V = np.asarray(V, np.float64)
    out = np.empty(len(P))
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    for s in range(0, len(P), chunk):
        p = np.asarray(P[s:s + chunk], np.float64)[:, None]
        a, b, c = A[None] - p, B[None] - p, C[None] - p
        la, lb, lc = (np.sqrt(np.einsum("qmk,qmk->qm", x, x)) for x in (a, b, c))
        num = np.einsum("qmk,qmk->qm", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("qmk,qmk->qm", a, b) * lc + np.einsum("qmk,qmk->qm", b, c) * la
               + np.einsum("qmk,qmk->qm", c, a) * lb)
        out[s:s + chunk] = 2.0 * np.arctan2(num, den).sum(axis=1) / (4.0 * np.pi)
    return out


def sheet_height(V: np.ndarray, F: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Height of a height-field sheet (every face's normal has +z) at the points xy (Q, 2): the
    face whose (x, y) projection holds the point, barycentric z; NaN off the sheet."""
    V = np.asarray(V, np.float64)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    e1, e2 = (b - a)[:, :2], (c - a)[:, :2]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    out = np.full(len(xy), np.nan)
    for i, p in enumerate(np.asarray(xy, np.float64)):
        d = p[None] - a[:, :2]
        u = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
        v = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
        tol = 1e-9
        hit = np.flatnonzero((u >= -tol) & (v >= -tol) & (u + v <= 1 + tol))
        if hit.size:
            j = hit[0]
            out[i] = a[j, 2] + u[j] * (b[j, 2] - a[j, 2]) + v[j] * (c[j, 2] - a[j, 2])
    return out


def boundary_edge_list(F: np.ndarray) -> np.ndarray:
    """(B, 2) vertex pairs of the edges used by one face only."""
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    u, counts = np.unique(e, axis=0, return_counts=True)
    return u[counts == 1]


def boundary_edges(F: np.ndarray) -> int:
    """Edges used by one face only (0: closed)."""
    return len(boundary_edge_list(F))


def distance_to_boundary_xy(V: np.ndarray, E: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance in (x, y) of the points xy (Q, 2) to the boundary edges E (B, 2) of (V, F)."""
    a, b = V[E[:, 0], :2], V[E[:, 1], :2]
    ab = b - a
    d = xy[:, None] - a[None]  # (Q, B, 2)
    t = np.clip(np.einsum("qbk,bk->qb", d, ab) / np.maximum(np.einsum("bk,bk->b", ab, ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(d - t[..., None] * ab[None], axis=-1).min(axis=1)


def surface_now(world):
    """(V, F) of the surface at the world's time, as the scene plays it (float64, host)."""
    return world.model.surface.host_mesh_at(world.time)


# --------------------------------------------------------------------------- dropping spheres


class Dropper:
    """One sphere above the surface every ``every`` steps: added until ``cap`` spheres, then the
    lowest one (resting on the ground, or fallen away) dropped again (its slot reset to a new
    position, at rest)."""

    def __init__(self, world, radius: float, every: int, cap: int, seed: int, recycle: str = "lowest"):
        self.world, self.r, self.every, self.cap = world, float(radius), int(every), int(cap)
        self.recycle = recycle
        self.next_slot = 0  # recycle == "oldest": the slot dropped again next
        self.rng = np.random.default_rng(seed)
        self.dropped = 0
        self.touched = np.zeros(world.model.spheres.count, bool)  # per slot: in contact at a check since dropped
        self.touched_done = 0  # recycled spheres that had touched

    def touched_total(self) -> int:
        return self.touched_done + int(self.touched.sum())

    def spot(self):
        """Above a random upward-facing face of the surface now (so most land on it), 3 radii over its top."""
        V, F = surface_now(self.world)
        a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        n = np.cross(b - a, c - a)
        up = np.flatnonzero(n[:, 2] > 0.5 * np.linalg.norm(n, axis=1))
        j = self.rng.choice(up) if up.size else self.rng.integers(len(F))
        xy = (a[j, :2] + b[j, :2] + c[j, :2]) / 3.0 + self.rng.normal(0.0, 0.5 * self.r, 2)
        return np.array([xy[0], xy[1], V[:, 2].max() + 3 * self.r], np.float32)

    def drop(self):
        w = self.world
        p = self.spot()
        if w.model.spheres.count < self.cap:
            w.add_spheres([p], self.r, 1.0)
            self.touched = np.append(self.touched, False)
        else:  # the lowest (or the oldest) sphere is dropped again, in its slot: the same arrays, so a
            # captured CUDA graph stays valid
            if self.recycle == "oldest":  # no read-back: the device goes on with the queued steps
                i = self.next_slot
                self.next_slot = (i + 1) % w.model.spheres.count
            else:
                i = int(np.argmin(w.sphere_positions()[:, 2]))
            self.touched_done += int(self.touched[i])
            self.touched[i] = False
            w.set_sphere(i, p)  # at rest; the collider re-gathers its candidate lists
        self.dropped += 1


def is_soak_checkpoint(path) -> bool:
    """True for a file this script wrote with --checkpoint (an npz holding the ``soak`` record)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return "soak" in z.files
    except Exception:  # not an npz (a folder, a scene, a mesh ...)
        return False


# --------------------------------------------------------------------------- one scene


def soak_scene(name: str, device, steps: int, check_every: int, drop_every: int, max_spheres: int,
               seed: int, stop_flag: dict, log=print, recycle: str = "lowest", checkpoint=None, resume=None,
               collider: str | None = None) -> dict:
    import warp as wp

    from dynmesh_warp.scene import build_world

    cfg = scene_config(name)
    saved = None
    if resume is not None:  # the checkpoint's record, checked before any work
        with np.load(resume, allow_pickle=False) as z:
            saved = json.loads(str(z["soak"]))
        if saved["scene"] != name or saved["args"] != [drop_every, max_spheres, seed, recycle, check_every]:
            raise SystemExit(f"--resume {resume}: written for scene {saved['scene']} with (drop_every, "
                             f"max_spheres, seed, recycle, check_every) = {saved['args']}")
        # the automatic collider is measured (timings differ between calls): a resumed soak keeps
        # the one its checkpoint was written with, as run.py does
        collider = collider or saved.get("collider")
    t_build = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the sub-step rule's notes
        world = build_world(cfg, device=device, collider=collider)
        world.step()  # compile (and capture) outside the timed loop
        wp.synchronize_device(world.device)
    build_s = time.perf_counter() - t_build
    radius = float(np.median(world.model.spheres.radius_np))
    dropper = Dropper(world, radius, drop_every, max_spheres, seed, recycle)
    surf = world.model.surface
    seq = surf.sequence
    frames: dict = {}  # the first frame of each distinct face array (one for fixed topology)
    for k in range(seq.num_frames):
        v, f = seq.frame(k)
        frames.setdefault(id(f), (v, f))
    frames = list(frames.values())
    open_edges = max(boundary_edges(np.asarray(f)) for _, f in frames)
    V0, F0 = np.asarray(frames[0][0], np.float64), np.asarray(frames[0][1])
    n0 = np.cross(V0[F0[:, 1]] - V0[F0[:, 0]], V0[F0[:, 2]] - V0[F0[:, 0]])
    sheet = open_edges > 0 and bool((n0[:, 2] > 0).all())  # an open height field (wave_bowl)
    rim = boundary_edge_list(F0) if sheet else None
    closed = not sheet
    test = "below the height-field sheet" if sheet else "winding number >= 0.5"
    res = {"scene": name, "config": cfg.name, "surface": cfg.surface.source, "boundary_edges": open_edges,
           "inside_test": test + (" (farther than a radius from the rim)" if sheet else ""),
           "collider": world.collider.name, "substeps": world.substeps, "dt": world.model.params.dt,
           "ground": world.model.params.ground_height,
           "initial_spheres": world.model.spheres.count, "sphere_radius": radius, "steps_asked": steps,
           "setup_and_compile_s": round(build_s, 3)}
    log(f"{name}: {surf.num_frames} frames, collider {world.collider.name}, {world.substeps} sub-steps, "
        f"inside test: {test}")
    checks = sphere_checks = contacts = tunnelled = nonfinite = 0
    events: list[dict] = []
    step_s = check_s = 0.0
    worst = -math.inf  # closed: the largest winding number seen; sheet: the lowest centre height above it (negated)
    max_depth = 0.0  # the deepest contact the step reported (sphere surface into the mesh) [m]
    done = 1  # the warm-up step
    next_report = time.perf_counter() + 30.0
    next_drop = drop_every
    segments = []
    if resume is not None:  # continue a run stopped with --checkpoint: the world, the dropper and the tallies
        with np.load(resume, allow_pickle=False) as z:
            extra = int(z["world_sphere_pos"].shape[0]) - world.model.spheres.count
            if extra > 0:
                world.add_spheres(np.zeros((extra, 3), np.float32), radius, 1.0)
            world.restore_checkpoint_state({k[len("world_"):]: z[k] for k in z.files if k.startswith("world_")})
            dropper.touched = z["dropper_touched"].copy()
        for k in ("dropped", "touched_done", "next_slot"):
            setattr(dropper, k, saved["dropper"][k])
        dropper.rng.bit_generator.state = saved["dropper"]["rng"]
        t = saved["tallies"]
        checks, sphere_checks, contacts, tunnelled, nonfinite = (t[k] for k in (
            "checks", "sphere_checks", "contacts", "tunnelled", "nonfinite"))
        events, step_s, check_s, max_depth, done, next_drop = (t[k] for k in (
            "events", "step_s", "check_s", "max_depth", "done", "next_drop"))
        worst = -math.inf if t["worst"] is None else t["worst"]
        segments = saved["segments"]
        log(f"{name}: resumed from {resume} at step {done:,}")
    segment_start = done

    def check():
        nonlocal checks, sphere_checks, contacts, tunnelled, nonfinite, worst, max_depth, check_s
        t0 = time.perf_counter()
        P, Vel = world.sphere_positions(), world.sphere_velocities()
        checks += 1
        sphere_checks += len(P)
        c = world.contacts.numpy()
        hit = c["face"] >= 0
        contacts += int(hit.sum())
        dropper.touched[hit] = True
        if hit.any():
            max_depth = max(max_depth, float(np.nanmax(c["depth"][hit])))
        bad = ~(np.isfinite(P).all(1) & np.isfinite(Vel).all(1))
        if bad.any():
            nonfinite += int(bad.sum())
            if len(events) < 10:
                events.append({"step": done, "kind": "non-finite", "spheres": np.flatnonzero(bad).tolist()})
        ok = ~bad
        if ok.any():
            V, F = surface_now(world)
            Pk = P[ok].astype(np.float64)
            if closed:
                wn = winding_number(V, F, Pk)
                inside = wn >= 0.5
                worst = max(worst, float(wn.max()))
                vals = wn
            else:
                hz = sheet_height(V, F, Pk[:, :2])
                # below the sheet, and farther than a radius from its rim in (x, y): a sphere that
                # went round the rim edge (touching it) is not one that passed through the sheet
                far = distance_to_boundary_xy(V, rim, Pk[:, :2]) > world.model.spheres.radius_np[ok]
                on = np.isfinite(hz) & far
                inside = on & (Pk[:, 2] < hz)
                if on.any():
                    worst = max(worst, float(-(Pk[on, 2] - hz[on]).min()))
                vals = Pk[:, 2] - np.nan_to_num(hz)
            if inside.any():
                tunnelled += int(inside.sum())
                if len(events) < 10:
                    ids = np.flatnonzero(ok)[inside]
                    events.append({"step": done, "t": world.time, "kind": "inside", "spheres": ids.tolist(),
                                   "values": vals[inside].round(4).tolist(), "positions": P[ids].tolist()})
        check_s += time.perf_counter() - t0

    while done < steps and not stop_flag.get("stop"):
        n = min(check_every - done % check_every, steps - done, next_drop - done)
        t0 = time.perf_counter()
        for _ in range(n):
            world.step()
        done += n
        if done == next_drop and done < steps and done % check_every and recycle == "oldest":
            next_drop += drop_every  # queued behind the steps, no wait (the wall time counts as stepping)
            dropper.drop()
            step_s += time.perf_counter() - t0
            continue
        wp.synchronize_device(world.device)
        step_s += time.perf_counter() - t0
        if done % check_every == 0 or done == steps:
            check()
        if done == next_drop:
            next_drop += drop_every
            if done < steps:
                dropper.drop()
        if time.perf_counter() > next_report:
            next_report = time.perf_counter() + 30.0
            log(f"  {name}: step {done:,}/{steps:,}, {done / max(step_s, 1e-9):,.0f} step/s, "
                f"{world.model.spheres.count} spheres, {dropper.dropped} dropped, tunnelled {tunnelled}, "
                f"non-finite {nonfinite}")
    segments = segments + [{"from_step": segment_start, "to_step": done, "device": str(world.device)}]
    if checkpoint is not None and done < steps:
        tallies = {"checks": checks, "sphere_checks": sphere_checks, "contacts": contacts, "tunnelled": tunnelled,
                   "nonfinite": nonfinite, "events": events, "step_s": step_s, "check_s": check_s,
                   "max_depth": max_depth, "done": done, "next_drop": next_drop,
                   "worst": worst if math.isfinite(worst) else None}
        meta = {"scene": name, "args": [drop_every, max_spheres, seed, recycle, check_every], "segments": segments,
                "collider": world.collider.name,
                "dropper": {"dropped": dropper.dropped, "touched_done": dropper.touched_done,
                            "next_slot": dropper.next_slot, "rng": dropper.rng.bit_generator.state},
                "tallies": tallies}
        arrays = {f"world_{k}": np.asarray(v) for k, v in world.checkpoint_state().items()}
        tmp = Path(str(checkpoint) + ".tmp.npz")
        np.savez(tmp, soak=np.array(json.dumps(meta)), dropper_touched=dropper.touched, **arrays)
        os.replace(tmp, checkpoint)  # atomic
        log(f"{name}: checkpoint at step {done:,} written to {checkpoint} (continue with --resume)")
    res.update({
        "segments": segments,
        "steps": done, "interrupted": done < steps, "sim_time_s": world.time,
        "stepping_wall_s": round(step_s, 3), "steps_per_second": round(done / step_s, 1) if step_s else None,
        "checking_wall_s": round(check_s, 3), "final_spheres": world.model.spheres.count,
        "spheres_dropped": dropper.dropped, "checks": checks, "sphere_checks": sphere_checks,
        "sphere_checks_in_contact": contacts, "tunnelled": tunnelled, "non_finite": nonfinite,
        ("max_winding_number" if closed else "min_centre_height_above_sheet_m"):
            None if not math.isfinite(worst) else round(worst if closed else -worst, 6),
        "max_contact_depth_m": round(max_depth, 6),
        "spheres_that_touched_the_surface": dropper.touched_total(),
        "events": events, "passed": tunnelled == 0 and nonfinite == 0,
    })
    log(f"{name}: {done:,} steps at {res['steps_per_second']} step/s, {dropper.dropped} spheres dropped, "
        f"{checks} checks ({sphere_checks:,} sphere checks, {contacts:,} in contact): tunnelled {tunnelled}, "
        f"non-finite {nonfinite} -> {'PASS' if res['passed'] else 'FAIL'}")
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--steps", type=int, default=100_000, help="physics steps per scene")
    p.add_argument("--scenes", default=",".join(ALL_SCENES), help=f"comma-separated, of {', '.join(ALL_SCENES)}")
    p.add_argument("--check-every", type=int, default=100, help="steps between checks")
    p.add_argument("--drop-every", type=int, default=60, help="steps between dropped spheres (60: 0.25 s)")
    p.add_argument("--max-spheres", type=int, default=32, help="spheres in the world at most")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--recycle", choices=("lowest", "oldest"), default="lowest",
                   help="which sphere is dropped again once --max-spheres are in the world")
    p.add_argument("--checkpoint", help="when stopped (Ctrl-C, SIGTERM) before the end, write the run's state "
                   "here (.npz, one scene only) so that --resume continues it on a fresh process")
    p.add_argument("--resume", help="continue from a --checkpoint file (same scene and options)")
    p.add_argument("--out", help="result JSON (default bench/results/soak_<device>.json)")
    a = p.parse_args(argv)
    scenes = [s.strip() for s in a.scenes.split(",") if s.strip()]
    unknown = [s for s in scenes if s not in ALL_SCENES]
    if unknown:
        p.error(f"unknown scenes {unknown}; choose from {', '.join(ALL_SCENES)}")
    if (a.checkpoint or a.resume) and len(scenes) != 1:
        p.error("--checkpoint/--resume need exactly one scene (--scenes NAME)")
    if a.resume and not Path(a.resume).is_file():
        p.error(f"--resume {a.resume}: no such file")
    if a.checkpoint and Path(a.checkpoint).exists() and not is_soak_checkpoint(a.checkpoint):
        p.error(f"--checkpoint {a.checkpoint}: exists and is not a soak checkpoint; it would be replaced "
                "(choose a new path)")
    if "paper" in scenes and not (SHARED_DATA / "horse_gallop.npz").is_file():
        p.error(f"the paper scene needs {SHARED_DATA / 'horse_gallop.npz'}")
    import warp as wp

    from dynmesh_warp.cli import quiet_warp

    quiet_warp(a.device)
    device = wp.get_device(a.device)
    out = Path(a.out) if a.out else RESULTS / f"soak_{'cuda' if device.is_cuda else 'cpu'}.json"
    stop_flag: dict = {}
    import signal

    def on_signal(signum, frame):
        if stop_flag.get("stop"):
            raise KeyboardInterrupt
        stop_flag["stop"] = signal.Signals(signum).name
        print(f"\n{stop_flag['stop']}: stopping at the next check and writing what was done", file=sys.stderr)

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, on_signal)
    t0 = time.perf_counter()
    results = []
    for name in scenes:
        if stop_flag.get("stop"):
            break
        results.append(soak_scene(name, device, a.steps, a.check_every, a.drop_every, a.max_spheres, a.seed,
                                  stop_flag, log=lambda *m: print(*m, flush=True), recycle=a.recycle,
                                  checkpoint=a.checkpoint, resume=a.resume))
    doc = {
        "what": "soak: spheres dropped continuously; every check_every steps no sphere centre inside the surface "
                "(winding number; height field for the open sheet) and all positions/velocities finite",
        "machine": describe_device(device),
        "device": str(device),
        "args": {"steps": a.steps, "check_every": a.check_every, "drop_every": a.drop_every,
                 "max_spheres": a.max_spheres, "seed": a.seed, "recycle": a.recycle, "scenes": scenes},
        "interrupted": stop_flag.get("stop") or False,
        "wall_s": round(time.perf_counter() - t0, 1),
        "total_steps": sum(r["steps"] for r in results),
        "tunnelled": sum(r["tunnelled"] for r in results),
        "non_finite": sum(r["non_finite"] for r in results),
        "passed": all(r["passed"] for r in results) and len(results) == len(scenes) and not stop_flag.get("stop"),
        "scenes": results,
    }
    write_json(out, doc)
    return 0 if doc["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
