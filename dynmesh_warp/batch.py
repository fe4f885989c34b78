"""Batched environments (issue 15): ``num_envs`` worlds in one Model/State, one step for all.

Every env plays the same reconstruction (one copy of its frames on the device) with spheres of
its own and **its own clock**: a time [s], a playback rate and a playback mode, each settable
per env at reset. Contacts of env e use the surface at env e's time. There is no per-env and
no per-step refit: the swept BVH of every frame pair is built once at load (memory: frames x
one BVH over the faces, ``BatchModel.memory_bytes``), and each sphere queries the one of its
env's frame pair (kernels/batch.py).

Layout: static data in :class:`BatchModel`, per-step data in :class:`BatchState`, contacts in
``world.Contacts`` (all flat over E * S spheres, env-major); the step is one public stage,
:func:`step_envs`; :class:`BatchedWorld` owns the CUDA graph, the host clock and resets.
Physics, contact and playback rules are the single world's (``world.World`` with the swept
collider): a batched world of E envs equals E single worlds run separately
(``tests/test_batch.py``).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import warp as wp

from .choices import (
    DEFAULT_BATCH_SWEPT_SEARCH,
    PLAYBACK_CODES,
    SEED_PREVIOUS_FACE,
    SPHERE_INERTIA,
    Playback,
    SweptSearch,
    device_kind,
    parse,
)
from .kernels.batch import (
    advance_env_clocks,
    collide_and_integrate_env_spheres,
    collide_env_heavy_spheres_tiled,
    collide_env_sphere_grid,
    collide_env_sphere_tiled,
    collide_env_spheres_bounded,
    compute_pair_bounds,
    count_face_cells,
    emit_face_cells,
    find_cell_ranges,
    gather_cell_boxes,
    resolve_and_integrate_env_spheres,
    reset_env_clocks,
    reset_env_spheres,
)
from .kernels.frames import add_points_offset, update_frame_vertices
from .config import MAX_TIME_OFFSET
from .runtime import free_bytes
from .world import (Contacts, PhysicsParams, SphereModel, SurfaceModel, check_substep_budget, fallen_past_note, physics_summary,
                    frame_pair_host, playback_cycle_host, required_substeps, resolve_playback, seam_note, warn_spins_kept)

__all__ = ["BatchModel", "BatchState", "BatchedWorld", "step_envs", "env_clocks", "TIME_SLICES",
           "BATCH_TILE_THREADS", "HYBRID_BUDGET", "default_batch_search", "HYBRID_BLOCKS", "ContactQuery",
           "build_batched_world", "EnvView", "EnvGrid"]


#: time slices per frame pair of the pair BVHs: a face's box covers 1/TIME_SLICES of its motion
#: between two frames. 1 by default: on horse_gallop 4 slices cut a sphere's candidate faces by
#: 2-10 % only (325 -> 319 at the worst; the count is set by the mesh's density, not its motion)
#: and cost 4x the memory (docs/envs.md)
TIME_SLICES = 1

#: threads per sphere of the batch's tiled search (measured on an H100, docs/envs.md: 32 beat
#: 8, 16 and 64 from 1,024 envs up in the landing window)
BATCH_TILE_THREADS = 32
#: the hybrid search: a thread walking a sphere's query hands the sphere to a thread block once
#: it meets more than HYBRID_BUDGET candidate faces (8 beat 32 and 128 in the landing window,
#: H100); HYBRID_BLOCKS blocks take the handed-over spheres (a fixed launch: one graph)
HYBRID_BUDGET = 8
HYBRID_BLOCKS = 4096
#: the grid search's cell edge in sphere radii (the largest sphere's), and the most cells a
#: slot's grid may have (the edge grows until it fits). 3 radii: a query box (2 x (r + margin +
#: speed x dt) a side) spans at most 2 cells an axis; measured on an H100 (docs/envs.md) 3 beat
#: 2, 2.5, 3.5, 4 and 5 at 4,096 envs landing (9,040 vs 8,091 / 8,260 / 8,814 / 8,405 / 7,584)
GRID_CELL_RADII = 3.0
GRID_MAX_CELLS = 1 << 16


#: device memory of one sphere of a batch [bytes]: radius, inverse mass, env index, position,
#: velocity, spin, and its contact (face, point, normal, depth, velocity, pinch memory of 64 bytes)
SPHERE_BYTES = 4 + 4 + 4 + 12 + 12 + 12 + (4 + 12 + 12 + 4 + 12 + 64)
#: ... and of one env's clock: time (float64), rate, playback
CLOCK_BYTES = 8 + 4 + 4


class BatchModel:
    """Static data of E envs on one deforming surface.

    Attributes:
        surface: the shared :class:`~dynmesh_warp.world.SurfaceModel` (frames (T, N) [m]).
        num_envs: E; spheres_per_env: S.
        spheres: :class:`~dynmesh_warp.world.SphereModel` of all E * S spheres (env-major).
        sphere_env: (E * S,) int32, the env of each sphere.
        params: :class:`~dynmesh_warp.world.PhysicsParams` shared by the envs.
        time_slices: slices per frame pair (``TIME_SLICES``); pair_lowers, pair_uppers:
            (T * slices, M) vec3 [m], each face's box over slice j of frame pair k (frames k and
            (k + 1) mod T), slot k * slices + j; pair_bvh: (T * slices,) uint64 ids of one
            ``wp.Bvh`` per slot.
        epsilon: tie distance of the closest-feature search [m] (1e-3 x mean edge length).
        grid_cell: the grid search's cell edge [m], ``grid_cell_radii`` (``GRID_CELL_RADII``)
            times the largest sphere radius, or larger where a slot would exceed GRID_MAX_CELLS.
    """

    def __init__(self, surface: SurfaceModel, num_envs: int, radius, mass, params: PhysicsParams,
                 time_slices: int = TIME_SLICES, grid_cell_radii: float = GRID_CELL_RADII):
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if not isinstance(surface, SurfaceModel):
            raise TypeError("batched envs need a fixed-topology surface (world.SurfaceModel); convert a "
                            "varying-topology input first (surface.conversion)")
        radius = np.asarray(radius, np.float32).reshape(-1)
        if radius.size < 1:
            raise ValueError("batched envs need at least one sphere per env")
        self.surface = surface
        self.device = surface.device
        self.num_envs = int(num_envs)
        self.spheres_per_env = int(radius.size)
        E, S = self.num_envs, self.spheres_per_env
        mass = np.broadcast_to(np.asarray(mass, np.float64), radius.shape)
        self.spheres = SphereModel(np.tile(radius, E), np.tile(mass, E), self.device)
        self.sphere_env = wp.array(np.repeat(np.arange(E, dtype=np.int32), S), dtype=wp.int32, device=self.device)
        self.params = params
        if int(time_slices) < 1:
            raise ValueError(f"time_slices must be >= 1, got {time_slices}")
        self.time_slices = int(time_slices)
        T, M = surface.num_frames, surface.num_faces
        n = T * self.time_slices
        self.pair_lowers = wp.zeros((n, M), dtype=wp.vec3, device=self.device)
        self.pair_uppers = wp.zeros((n, M), dtype=wp.vec3, device=self.device)
        wp.launch(compute_pair_bounds, (n, M), inputs=[surface.frames, surface.indices, self.time_slices],
                  outputs=[self.pair_lowers, self.pair_uppers], device=self.device)
        self._bvhs = [wp.Bvh(self.pair_lowers[k], self.pair_uppers[k], leaf_size=4) for k in range(n)]
        self.pair_bvh = wp.array([b.id for b in self._bvhs], dtype=wp.uint64, device=self.device)
        self.epsilon = 1.0e-3 * float(surface.average_edge_length.mean())
        if not float(grid_cell_radii) > 0:
            raise ValueError(f"grid_cell_radii must be > 0, got {grid_cell_radii}")
        self.grid_cell = float(grid_cell_radii) * float(radius.max())
        self.cell_faces = None  # the grid search's tables: built by build_grids when a world uses it

    def build_grids(self):
        """Each slot's uniform grid of the faces' pair boxes, for the grid search (built once on
        the device, the first time a world searches with it; kernels/batch.py): grid_origin
        (slots,) vec3 [m], grid_dims (slots,) vec3i, ``grid_cell`` [m] (grown until a slot has at
        most GRID_MAX_CELLS cells), cell lists ``cell_faces`` with their face boxes
        ``cell_lowers`` / ``cell_uppers`` and [cell_start, cell_end) per slot * cells_per_slot + cell."""
        if self.cell_faces is not None:
            return
        d = self.device
        cell = self.grid_cell
        lo = self.pair_lowers.numpy().min(axis=1)
        hi = self.pair_uppers.numpy().max(axis=1)
        ext = np.maximum(hi - lo, 1e-9)
        cell = max(float(cell), 1e-9)
        while True:
            dims = np.floor(ext / cell).astype(np.int64) + 1
            most = int(dims.prod(axis=1).max())
            if most <= GRID_MAX_CELLS:
                break
            cell *= (most / GRID_MAX_CELLS) ** (1.0 / 3.0) * 1.01
        self.grid_cell = cell
        self.cells_per_slot = most
        slots, M = self.pair_lowers.shape
        self.grid_origin = wp.array(lo.astype(np.float32), dtype=wp.vec3, device=d)
        self.grid_dims = wp.array(dims.astype(np.int32), dtype=wp.vec3i, device=d)
        counts = wp.zeros((slots, M), dtype=wp.int32, device=d)
        wp.launch(count_face_cells, (slots, M), inputs=[self.pair_lowers, self.pair_uppers, self.grid_origin,
                                                       self.grid_dims, 1.0 / cell], outputs=[counts], device=d)
        flat = counts.flatten()
        offsets = wp.zeros(slots * M, dtype=wp.int32, device=d)
        wp.utils.array_scan(flat, offsets, inclusive=False)
        last = slots * M - 1  # the list size: the scan's last entry plus the last count (two values read back)
        total = int(offsets[last:].numpy()[0] + flat[last:].numpy()[0])
        keys = wp.zeros(2 * total, dtype=wp.int32, device=d)
        values = wp.zeros(2 * total, dtype=wp.int32, device=d)
        wp.launch(emit_face_cells, (slots, M), inputs=[self.pair_lowers, self.pair_uppers, self.grid_origin,
                                                      self.grid_dims, 1.0 / cell, most, offsets],
                  outputs=[keys, values], device=d)
        wp.utils.radix_sort_pairs(keys, values, total)
        self.cell_start = wp.zeros(slots * most, dtype=wp.int32, device=d)
        self.cell_end = wp.zeros(slots * most, dtype=wp.int32, device=d)
        wp.launch(find_cell_ranges, total, inputs=[keys, total], outputs=[self.cell_start, self.cell_end], device=d)
        self.cell_faces = values[:total]
        self._grid_values = values  # the cell lists are a view of the sort's values: kept alive with them
        self.cell_lowers = wp.zeros(total, dtype=wp.vec3, device=d)  # each entry's face box, inline
        self.cell_uppers = wp.zeros(total, dtype=wp.vec3, device=d)
        wp.launch(gather_cell_boxes, total, inputs=[self.pair_lowers, self.pair_uppers, most, keys, self.cell_faces],
                  outputs=[self.cell_lowers, self.cell_uppers], device=d)

    @property
    def memory_bytes(self) -> dict:
        """Device memory of the batch [bytes]: the pair boxes and BVHs (per frame pair; a BVH's
        nodes estimated at 2M - 1 of 32 bytes each), the shared frames, and per env (spheres,
        contacts, clock)."""
        T, M, N = self.surface.num_frames, self.surface.num_faces, self.surface.num_vertices
        frames = T * N * 12 + 3 * M * 4
        T = T * self.time_slices  # slots
        leaves = math.ceil(M / 4)
        boxes = 2 * T * M * 12
        bvh_nodes = T * (2 * leaves - 1) * 32 + T * M * 4  # nodes + primitive indices
        per_env = self.spheres_per_env * SPHERE_BYTES + CLOCK_BYTES
        grids = (0 if self.cell_faces is None  # the grid search's, once built
                 else self.cell_start.size * 8 + self.cell_faces.size * 28 + T * (12 + 12))
        return {"pair_boxes": boxes, "pair_bvh_nodes_estimate": bvh_nodes, "pair_grids": grids, "frames": frames,
                "per_env": per_env,
                "total_estimate": boxes + bvh_nodes + grids + frames + per_env * self.num_envs}


class BatchState:
    """Per-step data of E envs: env_time (E,) float64 [s], env_rate (E,) float32 (1 = real time),
    env_playback (E,) int32 (``choices.PLAYBACK_CODES``), sphere_pos / sphere_vel / sphere_spin
    (E * S,) vec3 [m], [m/s], [rad/s] (spins given to ``sphere_body: point`` spheres are kept, warned of,
    and change nothing). Owns its
    arrays (never aliases the model)."""

    def __init__(self, model: BatchModel, positions, velocities=None, times=0.0, rates=1.0, playback=None,
                 spins=None):
        E, S, d = model.num_envs, model.spheres_per_env, model.device
        pos = _per_env(positions, E, S, "positions")
        vel = np.zeros_like(pos) if velocities is None else _per_env(velocities, E, S, "velocities")
        spin = np.zeros_like(pos) if spins is None else _per_env(spins, E, S, "spins")
        warn_spins_kept(spin, model.params.sphere_body, "BatchState")
        self.sphere_pos = wp.array(pos, dtype=wp.vec3, device=d)
        self.sphere_vel = wp.array(vel, dtype=wp.vec3, device=d)
        self.sphere_spin = wp.array(spin, dtype=wp.vec3, device=d)
        t, r, m = _clocks(model, times, rates, playback)
        self.env_time = wp.array(t, dtype=wp.float64, device=d)
        self.env_rate = wp.array(r, dtype=float, device=d)
        self.env_playback = wp.array(m, dtype=wp.int32, device=d)


def _per_env(a, E: int, S: int, what: str, mask=None) -> np.ndarray:
    """(S, 3) for every env or (E, S, 3) per env -> (E * S, 3) float32, checked (the rows of the
    envs where ``mask`` (E,) is true only, when given: the others are not read)."""
    a = np.asarray(a, np.float32)
    if a.shape == (S, 3):
        a = np.broadcast_to(a, (E, S, 3))
    if a.shape != (E, S, 3):
        raise ValueError(f"{what}: expected ({S}, 3) or ({E}, {S}, 3), got {a.shape}")
    if not np.isfinite(a if mask is None else a[np.asarray(mask, bool)]).all():
        raise ValueError(f"{what}: non-finite values" + ("" if mask is None else " in the envs being reset"))
    return np.ascontiguousarray(a.reshape(E * S, 3))


def _clocks(model: BatchModel, times, rates, playback, mask=None):
    E = model.num_envs
    t = np.broadcast_to(np.asarray(times, np.float64), (E,)).copy()
    r = np.broadcast_to(np.asarray(rates, np.float32), (E,)).copy()
    read = slice(None) if mask is None else np.asarray(mask, bool)  # (a reset reads the reset envs' only)
    if not (np.isfinite(t[read]).all() and np.isfinite(r[read]).all()) or (r[read] < 0).any():
        raise ValueError("env clocks: times must be finite and rates finite and >= 0")
    if (np.abs(t[read]) > MAX_TIME_OFFSET).any():  # 1e30 froze the env's clock (t + dt == t), unsaid
        raise ValueError(f"env clocks: times must be within +-{MAX_TIME_OFFSET:g} s (envs.time_offset's bound; far "
                         f"beyond it float64 rounding stops the clock), got {float(np.abs(t[read]).max()):g}")
    if playback is None:
        m = np.full(E, model.surface.playback, np.int32)
    else:
        one = isinstance(playback, (str, Playback)) or np.ndim(playback) == 0
        vals = [playback] * E if one else list(playback)  # one mode of another type: parse names it
        if len(vals) != E:
            raise ValueError(f"playback: expected one mode or {E}, got {len(vals)}")
        modes = [parse(Playback, v, "playback") for v in vals]
        # each mode resolved once (auto measures the sequence's seam: one pass over its frames)
        code = {mode: PLAYBACK_CODES[Playback(resolve_playback(model.surface.sequence, mode))] for mode in set(modes)}
        m = np.array([code[x] for x in modes], np.int32)
    return t, r, m


def default_batch_search(kind: str, spheres: int) -> SweptSearch:
    """The batch's contact search for ``spheres`` spheres on a device of ``kind`` ("cpu" or
    "cuda"): the first row of ``DEFAULT_BATCH_SWEPT_SEARCH[kind]`` that fits."""
    for up_to, search in DEFAULT_BATCH_SWEPT_SEARCH[kind]:
        if up_to is None or spheres <= up_to:
            return search
    raise AssertionError("DEFAULT_BATCH_SWEPT_SEARCH has no catch-all row")


def _at_least(value, default: int, name: str, lo: int) -> int:
    v = int(default if value is None else value)
    if v < lo:
        raise ValueError(f"{name} must be >= {lo}, got {value}")
    return v


class ContactQuery:
    """Scratch of the split contact query (tiled and hybrid searches): per sphere the closest
    feature found, its weights and tie-normal sum, and the env time [s] the query read ((E * S,)
    arrays); the hybrid's handed-over
    spheres (``heavy``, count in ``heavy_count[0]``)."""

    def __init__(self, count: int, device):
        n = max(count, 1)
        self.dist = wp.zeros(n, dtype=float, device=device)
        self.face = wp.zeros(n, dtype=wp.int32, device=device)
        self.w = wp.zeros(n, dtype=wp.vec3, device=device)
        self.n = wp.zeros(n, dtype=wp.vec3, device=device)
        self.time = wp.zeros(n, dtype=wp.float64, device=device)
        self.heavy = wp.zeros(n, dtype=wp.int32, device=device)
        self.heavy_count = wp.zeros(1, dtype=wp.int32, device=device)


def step_envs(model: BatchModel, state: BatchState, contacts: Contacts, sub_dt: float, substeps: int,
              extra_speed: float, search: SweptSearch = SweptSearch.SERIAL, query: ContactQuery | None = None,
              tile_threads: int = BATCH_TILE_THREADS, budget: int = HYBRID_BUDGET, blocks: int = HYBRID_BLOCKS):
    """The step of every env: ``substeps`` sub-steps of contact + integration at each env's
    own time, each followed by the env clocks' advance. The contact query of a sphere (a sphere
    near a finely meshed surface has hundreds of candidate faces): ``serial``, one thread per
    sphere (fused with the integration); ``tiled``, one block of ``tile_threads`` threads per
    sphere; ``hybrid``, one thread per sphere, and a sphere with more than ``budget`` candidates
    handed to one of ``blocks`` blocks. The split searches need ``query`` (scratch). Device work
    only (capturable)."""
    m, s, c, p = model, state, contacts, model.params
    surf = m.surface
    ground = int(p.ground_height is not None)
    gh = float(p.ground_height if p.ground_height is not None else 0.0)
    g = wp.vec3(*[float(x) for x in p.gravity])
    n = m.spheres.count
    physics = [g, p.restitution, p.friction, p.rest_speed, ground, gh, surf.fps, int(surf.interpolate),
               SPHERE_INERTIA[p.sphere_body]]
    args = [surf.frames, surf.indices, m.pair_bvh, m.pair_lowers, m.pair_uppers, m.spheres.radius, m.sphere_env,
            surf.fps, int(surf.interpolate), m.time_slices, s.env_time, s.env_playback, s.sphere_pos, s.sphere_vel]
    tail = [sub_dt, extra_speed, p.margin, m.epsilon]
    if search != SweptSearch.SERIAL and query is None:
        raise ValueError(f"the {search} search needs a ContactQuery scratch")
    if search == SweptSearch.GRID and m.cell_faces is None:
        raise ValueError("the grid search needs the model's grids: call BatchModel.build_grids() first "
                         "(BatchedWorld does)")
    for _ in range(substeps):
        if search == SweptSearch.SERIAL:
            wp.launch(collide_and_integrate_env_spheres, n,
                      inputs=[surf.frames, surf.indices, m.pair_bvh, m.pair_lowers, m.pair_uppers, m.spheres.radius,
                              m.spheres.inv_mass, m.sphere_env, *physics, m.time_slices, s.env_time, s.env_rate,
                              s.env_playback, *tail, int(SEED_PREVIOUS_FACE[device_kind(m.device)])],
                      outputs=[s.sphere_pos, s.sphere_vel, s.sphere_spin, c.face, c.point, c.normal, c.depth, c.velocity,
                               c.memory],
                      device=m.device)
        else:
            records = [query.dist, query.face, query.w, query.n, query.time]
            if search == SweptSearch.TILED:
                wp.launch_tiled(collide_env_sphere_tiled, dim=n, inputs=[*args, *tail], outputs=records,
                                block_dim=int(tile_threads), device=m.device)
            elif search == SweptSearch.GRID:
                wp.launch_tiled(collide_env_sphere_grid, dim=n,
                                inputs=[surf.frames, surf.indices, m.grid_origin, m.grid_dims, 1.0 / m.grid_cell,
                                        m.cells_per_slot, m.cell_start, m.cell_end, m.cell_faces, m.cell_lowers,
                                        m.cell_uppers, m.spheres.radius, m.sphere_env, surf.fps, int(surf.interpolate),
                                        m.time_slices, s.env_time, s.env_playback, s.sphere_pos, s.sphere_vel, *tail],
                                outputs=records, block_dim=int(tile_threads), device=m.device)
            else:
                query.heavy_count.zero_()
                wp.launch(collide_env_spheres_bounded, n, inputs=[*args, int(budget), *tail],
                          outputs=[*records, query.heavy_count, query.heavy], device=m.device)
                nb = max(1, min(int(blocks), n))
                wp.launch_tiled(collide_env_heavy_spheres_tiled, dim=nb,
                                inputs=[*args, query.heavy_count, query.heavy, nb, *tail], outputs=records,
                                block_dim=int(tile_threads), device=m.device)
            if n:  # every env has its spheres (sphere_env sorted): the first of each advances its clock
                wp.launch(resolve_and_integrate_env_spheres, n,
                          inputs=[surf.frames, surf.indices, m.spheres.radius, m.spheres.inv_mass, m.sphere_env,
                                  *physics, s.env_rate, s.env_playback, *records, *tail, wp.float64(sub_dt)],
                          outputs=[s.sphere_pos, s.sphere_vel, s.sphere_spin, s.env_time, c.face, c.point, c.normal, c.depth,
                                   c.velocity, c.memory],
                          device=m.device)
                continue
        wp.launch(advance_env_clocks, m.num_envs, inputs=[s.env_rate, wp.float64(sub_dt)], outputs=[s.env_time],
                  device=m.device)


class BatchedWorld:
    """E envs stepped together: one CUDA graph per step on a GPU (the first step eager, as the
    single world); the sub-step count follows the single world's rule at the fastest env rate
    (``max_rate``). ``reset`` sets chosen envs' spheres and clocks on the device.

    ``search``: the contact query's search (``choices.SweptSearch``; None: ``physics.swept_search``
    or ``DEFAULT_BATCH_SWEPT_SEARCH`` for the device); ``tile_threads`` (the tiled and hybrid
    searches' block), ``budget`` and ``blocks`` (the hybrid's hand-over): see :func:`step_envs`."""

    def __init__(self, model: BatchModel, state: BatchState, max_rate: float | None = None,
                 use_graph: bool | None = None, search: str | SweptSearch | None = None,
                 tile_threads: int | None = None, budget: int | None = None, blocks: int | None = None):
        self.model, self.state = model, state
        self.device = model.device
        p = model.params.freeze()  # the step and its graph are made from these values
        fastest = float(state.env_rate.numpy().max())
        if max_rate is not None and fastest > float(max_rate) * (1 + 1e-6):
            # (a new user's max_rate 1 with an env at 30: one sub-step where 6 were needed, and the
            # sphere fell through a rising floor; reset refused the same rate)
            raise ValueError(f"max_rate {float(max_rate):g}: the state's env rates reach {fastest:g}; the sub-steps are "
                             "chosen for max_rate, so it must be at least the fastest env's rate")
        rate = fastest if max_rate is None else float(max_rate)
        self.max_rate = rate
        r_min = float(model.spheres.radius_np.min())
        speed = model.surface.max_speed * rate
        self.substeps = max(1, int(p.substeps))
        if p.auto_substeps and model.surface.interpolate:
            need = required_substeps(speed, p.dt, r_min)
            if need > self.substeps:
                note = seam_note(model.surface)
                if rate != 1.0 and p.max_substeps is not None:  # name the envs' rate (a new user's 1e6 was not)
                    fit = p.max_substeps * 0.5 * r_min / (p.dt * max(model.surface.max_speed, 1e-30))
                    note += (f" (the fastest env's rate {rate:g} x the surface's own {model.surface.max_speed:.3g} m/s: "
                             f"envs.rate up to {fit:.3g} fits)")
                check_substep_budget(need, speed, r_min, p, note)
                warnings.warn(f"surface moves up to {speed:.3g} m/s (at rate {rate:g}){note}: "
                              "raising substeps from "
                              f"{self.substeps} to {need} so it moves < r/2 per sub-step", stacklevel=2)
                self.substeps = need
        self.sub_dt = p.dt / self.substeps
        self.extra_speed = float(np.linalg.norm(p.gravity)) * self.sub_dt
        self.contacts = Contacts(model.spheres.count, device=self.device)
        search = search if search is not None else p.swept_search
        self.search = (default_batch_search(device_kind(self.device), model.spheres.count) if search is None
                       else parse(SweptSearch, search, "swept_search"))
        if self.search in (SweptSearch.FACES, SweptSearch.SPHERE_GRID):
            raise ValueError(f"swept_search '{self.search}' is a single world's search; a batched world searches "
                             "'serial', 'tiled', 'hybrid' or 'grid'")
        self.tile_threads = _at_least(tile_threads, BATCH_TILE_THREADS, "tile_threads", 1)
        self.budget = _at_least(budget, HYBRID_BUDGET, "budget", 0)
        self.blocks = _at_least(blocks, HYBRID_BLOCKS, "blocks", 1)
        self.query = ContactQuery(model.spheres.count, self.device) if self.search != SweptSearch.SERIAL else None
        if self.search == SweptSearch.GRID:
            model.build_grids()
        self.use_graph = self.device.is_cuda if use_graph is None else bool(use_graph) and self.device.is_cuda
        self._graph = None
        self.step_count = 0
        self._t0 = float(state.env_time.numpy()[0])
        E = model.num_envs
        self._mask = wp.zeros(E, dtype=wp.int32, device=self.device)

    @property
    def num_envs(self) -> int:
        return self.model.num_envs

    @property
    def memory_bytes(self) -> dict:
        """:attr:`BatchModel.memory_bytes` with ``per_env`` counted from this world's arrays
        [bytes]: every array of one entry per env or per sphere (the spheres' model, the state,
        the contacts and their pinch memory, the split searches' query record, the reset mask),
        divided by E. The model's own figure is an estimate of the spheres and clocks alone (a
        new user measured 740 B an env of 5 spheres against the 416 it said)."""
        m = self.model
        E, n = m.num_envs, m.spheres.count
        held = [m.spheres, m.sphere_env, self.state, self.contacts, self.query, self._mask]
        arrays = [a for h in held if h is not None
                  for a in ([h] if isinstance(h, wp.array) else vars(h).values()) if isinstance(a, wp.array)]
        per_env = sum(a.capacity for a in arrays if a.shape[0] in (E, n) and a.ndim == 1) / E
        out = dict(m.memory_bytes)
        total = out["total_estimate"] - out["per_env"] * E
        out["per_env"] = int(round(per_env))
        out["total_estimate"] = int(total + per_env * E)
        return out

    @property
    def dt(self) -> float:
        return self.model.params.dt

    def _step_body(self):
        step_envs(self.model, self.state, self.contacts, self.sub_dt, self.substeps, self.extra_speed, self.search,
                  self.query, self.tile_threads, self.budget, self.blocks)

    def capture(self):
        if not self.use_graph or self._graph is not None:
            return
        with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
            self._step_body()
        self._graph = cap.graph

    def step(self):
        """Advance every env by one step (``params.dt`` of its own clock times its rate)."""
        if self.use_graph and self._graph is None and self.step_count > 0:
            self.capture()
        if self._graph is not None:
            wp.capture_launch(self._graph)
        else:
            self._step_body()
        self.step_count += 1

    def reset(self, env_mask, positions=None, velocities=None, times=None, rates=None, playback=None, spins=None):
        """Reset the envs where ``env_mask`` (E,) is true: their spheres to ``positions`` /
        ``velocities`` / ``spins`` ((S, 3) or (E, S, 3) [m], [m/s], [rad/s]; rows of other envs are
        ignored: not read, not checked) and their clocks to ``times`` [s] / ``rates`` / ``playback`` (scalars or (E,)). What
        is not given is kept.
        The other envs are untouched; the captured graph stays valid (arrays are written, not
        replaced)."""
        m, s = self.model, self.state
        E, S = m.num_envs, m.spheres_per_env
        given = np.asarray(env_mask)
        if given.dtype != bool or given.shape not in ((), (E,)):
            # a list of env indices was read as a mask ([0, 1, 2] left env 0 as it was; found by a
            # new user): refused, with the conversion to say
            raise ValueError(f"env_mask: expected booleans, one per env ({E},) or one for all, got dtype {given.dtype} "
                             f"shape {given.shape}; for env indices idx use a mask: m = np.zeros({E}, bool); m[idx] = True")
        mask = np.broadcast_to(given, (E,)).astype(np.int32)
        self._mask.assign(mask)

        def given_or_kept(now, value, what):  # (a spin zeroed, a rolling ball kept its speed and slipped again)
            rows = now.numpy().reshape(E, S, 3) if value is None else value
            return _per_env(rows, E, S, what, mask)  # (other envs' rows are not read: a NaN there was refused)

        new_pos, new_vel, new_spin = (given_or_kept(now, value, what) for now, value, what in (
            (s.sphere_pos, positions, "positions"), (s.sphere_vel, velocities, "velocities"),
            (s.sphere_spin, spins, "spins")))
        if spins is not None:
            warn_spins_kept(new_spin.reshape(E, S, 3)[mask.astype(bool)], m.params.sphere_body, "BatchedWorld.reset")
        new_pos, new_vel, new_spin = (wp.array(a, dtype=wp.vec3, device=self.device) for a in (new_pos, new_vel, new_spin))
        t, r, pb = _clocks(m, s.env_time.numpy() if times is None else times,
                           s.env_rate.numpy() if rates is None else rates, playback, mask)
        if playback is None:
            pb = s.env_playback.numpy()
        if rates is not None and float(np.max(r)) > self.max_rate * (1 + 1e-6):
            raise ValueError(f"rates: {float(np.max(r)):g} exceeds the rate the sub-steps were chosen for "
                             f"({self.max_rate:g}); build the world with max_rate=")
        wp.launch(reset_env_spheres, m.spheres.count, inputs=[m.sphere_env, self._mask, new_pos, new_vel, new_spin],
                  outputs=[s.sphere_pos, s.sphere_vel, s.sphere_spin, self.contacts.memory], device=self.device)
        wp.launch(reset_env_clocks, E,
                  inputs=[self._mask, wp.array(t, dtype=wp.float64, device=self.device),
                          wp.array(r, dtype=float, device=self.device),
                          wp.array(pb, dtype=wp.int32, device=self.device)],
                  outputs=[s.env_time, s.env_rate, s.env_playback], device=self.device)

    # -- the Simulation protocol (runtime.Simulation; the runner reads it) ----------------------
    editable = False
    checkpointable = False
    body_noun = "sphere"

    @property
    def surface(self):
        return self.model.surface

    @property
    def t0(self) -> float:
        return self._t0

    @property
    def time(self) -> float:
        """Env 0's clock [s] (a host read)."""
        return float(self.state.env_time.numpy()[0])

    @property
    def substep_count(self) -> int:
        return self.step_count * self.substeps

    @property
    def graph_captured(self) -> bool:
        return self._graph is not None

    def surface_points(self):
        return self.model.surface.frames[0]  # the viewer shows no batch (frame 0 for a caller that asks)

    def surface_indices(self):
        return self.model.surface.indices

    def rigid_shapes(self) -> list:
        """Rigid shapes other than the built-in spheres, for rendering: none here."""
        return []

    def sphere_radii(self) -> np.ndarray:
        return self.model.spheres.radius_np

    def sample(self) -> dict:
        """``position`` and ``velocity`` (E * S, 3) and ``env_time`` (E,) of every env."""
        return {"position": self.state.sphere_pos.numpy().copy(), "velocity": self.state.sphere_vel.numpy().copy(),
                "env_time": self.env_times()}

    def trajectory_constants(self) -> dict:
        return {"radius": self.model.spheres.radius_np, "sphere_env": self.model.sphere_env.numpy(),
                "env_rate": self.state.env_rate.numpy()}

    def contact_count(self) -> int:
        return int((self.contacts.face.numpy() >= 0).sum())

    def run_summary(self) -> dict:
        pos, vel = self.state.sphere_pos.numpy(), self.state.sphere_vel.numpy()
        surf = self.model.surface
        return {"collider": "swept (pair BVHs, batched)", "swept_search": str(self.search), "num_envs": self.num_envs,
                "spheres_per_env": self.model.spheres_per_env,
                "surface": {"frames": surf.num_frames, "fps": surf.fps, "faces": surf.num_faces},
                "physics": physics_summary(self.model.params),
                "memory_bytes": self.memory_bytes,
                "final": {"finite": bool(np.isfinite(pos).all() and np.isfinite(vel).all())}}

    def run_line(self) -> tuple[str, str]:
        # spheres that fell past the surface, said as the single world says it (a new user's listed
        # spheres started under a rising sheet in the envs whose clocks started later, and fell
        # with only "4/16 spheres in contact" said)
        hint = ("an env whose clock starts later (envs.time_offset) may begin with a listed sphere under a "
                "surface that has moved there: envs.time_offset: 0, or spawned spheres; " if self.num_envs > 1 else "")
        return (f"{self.num_envs} envs x {self.model.spheres_per_env} spheres",
                f"{self.contact_count()}/{self.model.spheres.count} spheres in contact"
                + fallen_past_note(self.model.surface.sequence, self.model.params, self.state.sphere_pos.numpy(), hint))

    # -- read-out (host copies) -----------------------------------------------------------------
    def sphere_positions(self) -> np.ndarray:
        """(E, S, 3) [m]."""
        return self.state.sphere_pos.numpy().reshape(self.num_envs, -1, 3).copy()

    def sphere_velocities(self) -> np.ndarray:
        """(E, S, 3) [m/s]."""
        return self.state.sphere_vel.numpy().reshape(self.num_envs, -1, 3).copy()

    def sphere_spins(self) -> np.ndarray:
        """(E, S, 3) angular velocities [rad/s] (zero where ``physics.sphere_body`` is ``point``)."""
        return self.state.sphere_spin.numpy().reshape(self.num_envs, -1, 3).copy()

    def env_times(self) -> np.ndarray:
        """(E,) float64 [s]."""
        return self.state.env_time.numpy().copy()


class EnvView:
    """One env of a :class:`BatchedWorld` seen as a single simulation (the read side of
    ``runtime.Simulation``: surface at the env's own time, its spheres, its clock), for the
    viewer; ``step()`` steps the whole batch. Not editable (reset, seek and drop are the single
    world's)."""

    editable = False
    checkpointable = False
    body_noun = "sphere"
    num_envs = 1

    def __init__(self, world: BatchedWorld, env: int = 0):
        if not 0 <= int(env) < world.num_envs:
            raise IndexError(f"env {env}: the batch has {world.num_envs} envs")
        self.batch, self.env = world, int(env)
        self.model = world.model
        self.surface = world.model.surface
        self.device = world.device
        self.render_state = True
        self.points = wp.zeros(self.surface.num_vertices, dtype=wp.vec3, device=self.device)
        self._velocities = wp.zeros(self.surface.num_vertices, dtype=wp.vec3, device=self.device)
        self.t0 = self.time

    @property
    def time(self) -> float:
        return float(self.batch.state.env_time.numpy()[self.env])

    @property
    def dt(self) -> float:
        return self.batch.dt

    @property
    def substeps(self) -> int:
        return self.batch.substeps

    @property
    def substep_count(self) -> int:
        return self.batch.substep_count

    @property
    def use_graph(self) -> bool:
        return self.batch.use_graph

    def step(self):
        self.batch.step()

    def capture(self):
        self.batch.capture()

    def surface_points(self):
        """The surface's vertices (N,) at this env's time (its rate and playback mode)."""
        e = self.env
        mode = int(self.batch.state.env_playback.numpy()[e])
        wp.launch(update_frame_vertices, self.surface.num_vertices,
                  inputs=[self.surface.frames, self.batch.state.env_time[e:e + 1], self.surface.fps, mode,
                          int(self.surface.interpolate)],
                  outputs=[self.points, self._velocities], device=self.device)
        return self.points

    def surface_indices(self):
        return self.surface.indices

    def sphere_positions(self) -> np.ndarray:
        return self.batch.sphere_positions()[self.env]

    def rigid_shapes(self) -> list:
        """Rigid shapes other than the built-in spheres, for rendering: none here."""
        return []

    def sphere_radii(self) -> np.ndarray:
        S = self.model.spheres_per_env
        return self.model.spheres.radius_np[self.env * S:(self.env + 1) * S]


class _TiledSurface:
    """The surface of an :class:`EnvGrid`: the shared sequence repeated once per shown env,
    each copy shifted by its grid offset (host only: faces, frames for the viewer's camera
    and splat grouping)."""

    def __init__(self, surface, offsets: np.ndarray):
        from .sequence import FixedTopologySequence

        seq, k = surface.sequence, len(offsets)
        N = seq.num_vertices
        V = np.concatenate([seq.V + o.astype(np.float32) for o in offsets], axis=1)
        F = np.concatenate([seq.F + i * N for i in range(k)])
        self.sequence = FixedTopologySequence(V, F, fps=seq.fps, name=f"{seq.name} x{k}")
        self.num_frames, self.fps = seq.num_frames, surface.fps
        self.num_vertices, self.num_faces = k * N, k * surface.num_faces
        self.interpolate = surface.interpolate
        self._base, self._offsets = surface, offsets

    def faces(self) -> np.ndarray:
        return self.sequence.F

    def host_mesh_at(self, time: float):
        V, _ = self._base.host_mesh_at(time)
        return np.concatenate([V + o for o in self._offsets]), self.sequence.F


class EnvGrid(EnvView):
    """Several envs of a :class:`BatchedWorld` side by side as one simulation, for the viewer
    (issue 15: "a grid of a few"): env ``envs[i]`` is drawn shifted by ``offsets[i]`` (a grid,
    columns of ceil(sqrt(k)), 1.3 x the surface's extent apart), each at its own time with its
    own spheres; ``step()`` steps the whole batch. The clock shown is the first env's."""

    def __init__(self, world: BatchedWorld, envs=(0, 1, 2, 3), spacing: float = 1.3):
        envs = [int(e) for e in envs]
        if not envs:
            raise ValueError("EnvGrid: no envs to show")
        for e in envs:
            if not 0 <= e < world.num_envs:
                raise IndexError(f"env {e}: the batch has {world.num_envs} envs")
        super().__init__(world, envs[0])
        self.envs = envs
        V = world.model.surface.sequence.V
        ext = np.ptp(V.reshape(-1, 3), axis=0).astype(np.float64)
        cols = int(math.ceil(math.sqrt(len(envs))))
        self.offsets = np.array([[spacing * ext[0] * (i % cols), -spacing * ext[1] * (i // cols), 0.0]
                                 for i in range(len(envs))])
        self.surface = _TiledSurface(world.model.surface, self.offsets)
        N = world.model.surface.num_vertices
        self.points = wp.zeros(len(envs) * N, dtype=wp.vec3, device=self.device)
        self._one = wp.zeros(N, dtype=wp.vec3, device=self.device)
        self._indices = wp.array(self.surface.sequence.F.reshape(-1), dtype=wp.int32, device=self.device)

    def surface_points(self):
        """(k * N,) the shown envs' surfaces at their own times, each shifted by its offset."""
        base = self.batch.model.surface
        N = base.num_vertices
        modes = self.batch.state.env_playback.numpy()
        for i, e in enumerate(self.envs):
            wp.launch(update_frame_vertices, N,
                      inputs=[base.frames, self.batch.state.env_time[e:e + 1], base.fps, int(modes[e]),
                              int(base.interpolate)],
                      outputs=[self._one, self._velocities], device=self.device)
            wp.launch(add_points_offset, N, inputs=[self._one, wp.vec3(*self.offsets[i].tolist())],
                      outputs=[self.points[i * N:(i + 1) * N]], device=self.device)
        return self.points

    def surface_indices(self):
        return self._indices

    def sphere_positions(self) -> np.ndarray:
        pos = self.batch.sphere_positions()
        return np.concatenate([pos[e] + o for e, o in zip(self.envs, self.offsets)]).astype(np.float32)

    def sphere_radii(self) -> np.ndarray:
        S = self.model.spheres_per_env
        r = self.model.spheres.radius_np
        return np.concatenate([r[e * S:(e + 1) * S] for e in self.envs])


def env_clocks(envs, cycle: float, rng: np.random.Generator | None = None):
    """(times (E,) [s], rates (E,)) of an ``envs:`` section (config.EnvsConfig): start times
    uniform over one cycle of the surface's playback, ``cycle`` [s] (``world.playback_cycle_host``
    / fps: a pingpong env starts going back as often as forth, a clamp env not on the held last
    frame; as the RL env's reset draws them), for "random", or the given offset; rates uniform in
    ``envs.rate``."""
    rng = np.random.default_rng(envs.seed) if rng is None else rng
    E = envs.count
    if envs.time_offset == "random":
        times = rng.uniform(0.0, max(cycle, 0.0), E)
    else:
        times = np.full(E, float(envs.time_offset))
    lo, hi = envs.rate
    rates = rng.uniform(lo, hi, E) if hi > lo else np.full(E, lo)
    return times, rates.astype(np.float32)


def _spheres_for_env_starts(cfg, seq, mode: int, times: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """The scene's spheres where the envs start at other times than 0 (``envs.time_offset``):
    placed for frame 0, they could start inside the surface in an env whose clock starts where
    it has moved there (a new user's raised arm: spheres of 3 of 8 envs fell out through it, with
    no word). Spawned spheres are dropped above the highest point of any frame instead; a listed
    sphere inside the closed surface at an env's start frame is refused, naming the env."""
    from .config import SceneError, spawn_positions
    from .scene import refuse_starts_inside, scene_up, sphere_entries
    from .sequence import surface_vertices

    if not isinstance(cfg.spheres, list):
        return spawn_positions(cfg.spheres, surface_vertices(seq.V, seq.F).reshape(-1, 3), scene_up(cfg))
    entries = sphere_entries(cfg)
    if not entries:
        return pos
    first = {}  # start frame -> first env that starts on it
    for e, t in enumerate(times):
        for k in frame_pair_host(float(t), seq.fps, seq.num_frames, mode)[:2]:
            first.setdefault(k, e)
    for k in sorted(first):
        try:
            refuse_starts_inside(seq.V[k], seq.F, entries, frame=k)  # closed pieces, piece by piece
        except SceneError as err:
            e = first[k]
            raise SceneError(f"env {e} starts at t = {float(times[e]):.4g} s (envs.time_offset: "
                             f"{cfg.envs.time_offset}), on frame {k}: {err}; or start every env at the "
                             "scene's frame 0: envs.time_offset: 0") from None
    return pos


#: the memory a batch takes per env and per sphere of an env [bytes], at least: the clocks and
#: the reset mask (CLOCK_BYTES + 4), and per sphere SPHERE_BYTES plus the split searches' query
#: record (44), rounded up; a new user measured 877 B an env of 5 spheres on the CPU (resident
#: size from 10 to 200,010 envs; this said 384 before). A batch that cannot fit the device's free
#: memory is refused before it is allocated
BYTES_PER_ENV, BYTES_PER_SPHERE = 32, 192


def build_batched_world(cfg, device=None, num_envs: int | None = None, sequence=None) -> BatchedWorld:
    """A :class:`BatchedWorld` of a scene: the one builder (``scene.build_model``) gives the
    surface, spheres and physics; ``envs:`` (or ``num_envs``) the count and clocks. ``cfg``: a
    SceneConfig, a scene YAML's path or a dict of its sections."""
    from .config import SceneError, scene_config
    from .scene import (build_model, load_surface, prepare_surface, refuse_starts_inside, require_fixed_topology,
                        sphere_entries)

    cfg = scene_config(cfg)
    if num_envs is not None and (isinstance(num_envs, bool) or int(num_envs) != num_envs):
        raise SceneError(f"num_envs must be a whole number, got {num_envs!r}")  # 2.7 ran 2 envs
    seq = load_surface(cfg) if sequence is None else prepare_surface(sequence, cfg)
    require_fixed_topology(cfg, seq, "batched envs need")
    model, state = build_model(cfg, seq, device)
    envs = cfg.envs if num_envs is None else cfg.envs.model_copy(update={"count": int(num_envs)})
    if envs.count < 1:
        raise SceneError(f"envs.count must be >= 1, got {envs.count}")
    need = envs.count * (BYTES_PER_ENV + BYTES_PER_SPHERE * model.spheres.count)
    free = free_bytes(model.device)
    if free and need > free:  # a new user's --envs 100000000 was killed by the OOM killer
        def size(b):
            return f"{b / 2**30:,.1f} GiB" if b >= 2**30 else f"{b / 2**20:,.1f} MiB"

        raise SceneError(f"envs.count {envs.count:,}: needs about {size(need)} on {model.device}, {size(free)} free; "
                         "fewer envs (or spheres per env)")
    times, rates = env_clocks(envs, playback_cycle_host(seq.num_frames, model.surface.playback) / seq.fps)
    bm = BatchModel(model.surface, envs.count, model.spheres.radius_np, model.spheres.mass_np, model.params)
    vel = state.sphere_vel.numpy()
    pos = state.sphere_pos.numpy()
    if np.any(times != 0.0) and seq.num_frames > 1:
        pos = _spheres_for_env_starts(cfg, seq, model.surface.playback, times, pos)
    else:  # every env starts on frame 0: the single world's check (it was skipped here: spheres fell out)
        refuse_starts_inside(*seq.frame(0), sphere_entries(cfg))
    bs = BatchState(bm, pos, vel, times=times, rates=rates)
    return BatchedWorld(bm, bs, max_rate=float(max(envs.rate[1], 1e-9)))
