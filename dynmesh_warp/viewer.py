"""Live viewer with viser: bound Gaussians, the physics mesh and the spheres, streamed per frame.

``python -m dynmesh_warp.run scene.yaml --viewer viser --port 8080`` (see docs/rendering.md).
viser is imported inside functions only, so ``import dynmesh_warp`` never needs it.

Per frame the viewer advances the world by ``speed * (1 / fps)`` simulated seconds (whole
physics steps, the remainder carried over), then sends, inside one ``server.atomic()`` block,
only what changed: mesh vertices and the splat buffer when the surface time moved, sphere
positions when they moved (the whole sphere node when the count changed), the time slider.
GUI callbacks (viser's threads) only queue actions; the frame loop applies them, so all Warp
work stays on one thread.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np

__all__ = ["Viewer", "NewtonViewer", "run_viewer", "decode_viser_recording", "decode_wire_message",
           "SceneStateTracker", "scene_splat_centers", "recording_html", "SPLAT_GROUPS"]

MIN_SCALE_REL = 1.0e-3  # viewer std-dev floor, relative to the scene's bounding-box diagonal
MIN_RATIO = 0.05  # viewer std-dev floor, relative to the Gaussian's largest std dev (float16)


#: direction of the key light baked into the splats' colours (towards the scene: from above, in
#: front of the initial camera)
LIGHT_DIR = (-0.45, 0.6, -0.65)

#: bound Gaussians are streamed as this many rigidly moving groups (docs/rendering.md#what-the-viewer-sends):
#: the splat buffer goes once, then each frame only the groups' poses; 0 sends the whole buffer
#: every frame the surface moves
SPLAT_GROUPS = 128
#: bytes a recording holds per group and frame (two viser messages, position and orientation,
#: with their headers; measured on the default scene): the size estimate printed before recording
GROUP_POSE_BYTES = 192
#: the groups' buffers are sent again from the current pose when a Gaussian's rigid-fit error
#: exceeds this fraction of the scene's bounding-box diagonal, at most once per REKEY_INTERVAL [s]
REKEY_ERROR = 0.05
REKEY_INTERVAL = 1.0

#: the most wall time one viewer frame catches up on [s] (a stall longer than this slows the clock
#: instead of making one frame simulate seconds)
MAX_CATCH_UP = 0.25


def _require_viser():
    try:
        import viser  # noqa: PLC0415
    except ImportError as e:  # pragma: no cover
        raise RuntimeError("the viser viewer needs the optional dependency: pip install 'dynmesh_warp[viewer]'") from e
    return viser


class Viewer:
    """A viser server showing ``world`` (and ``gaussians`` bound to its mesh).

    Programmatic use: ``v = Viewer(world, g, port=0); v.run(max_frames=10); v.close()``
    (port 0: any free port, see ``v.port``). ``record``: path of a ``.viser`` file; every
    frame is appended to a scene recording, written (with a self-contained ``.html`` next to
    it) by :meth:`close`. ``realtime=False`` runs frames back to back (headless recording).
    """

    def __init__(self, world, gaussians=None, port: int = 8080, host: str = "127.0.0.1", fps: float = 30.0,
                 record: str | Path | None = None, realtime: bool = True, speed: float = 1.0,
                 min_scale_rel: float = MIN_SCALE_REL, min_ratio: float = MIN_RATIO,
                 mesh_color=(90, 160, 220), sphere_color=(230, 90, 60), show_mesh: bool | None = None,
                 seed: int = 0, log=print, shade: bool = True, splat_groups: int = SPLAT_GROUPS,
                 hold_until_client: bool = True):
        viser = _require_viser()
        import trimesh

        self.world = world
        self.gaussians = gaussians
        self.shade = bool(shade)
        if int(splat_groups) < 0:
            raise ValueError(f"splat_groups must be >= 0 (0: the whole buffer every frame), got {splat_groups}")
        self.splat_groups = int(splat_groups)
        # realtime: the clock waits for the first browser, so the scene's moment (spheres landing)
        # is not over before the page has opened
        self.hold_until_client = bool(hold_until_client) and bool(realtime)
        self.held_frames = 0  # frames spent waiting for the first browser (not counted in self.frame)
        self._client_seen = False
        self.stream = None  # the grouped splat stream (_SplatGroups) when splat_groups > 0
        self.fps = float(fps)
        self.frame_dt = 1.0 / self.fps
        self.realtime = bool(realtime)
        self.speed = float(speed)
        self.playing = True
        self.frame = 0
        self._owed = 0.0
        self._last_wall = None
        self._rate_window: list = []
        self.achieved_rate = None
        self._actions: list = []
        self._lock = threading.Lock()
        self._rng = np.random.default_rng(seed)
        self.log = log
        self.record_path = Path(record) if record else None
        surf = world.surface
        from .gaussians import SegmentedGaussians

        if gaussians is not None and not isinstance(gaussians, SegmentedGaussians):
            try:
                surf.faces()  # Gaussians are bound to faces every frame shares (or carried per segment)
            except ValueError:
                raise ValueError("Gaussians need a fixed-topology surface, or SegmentedGaussians for a piecewise-"
                                 "fixed one (gaussians_for_surface)") from None
        self._take_faces()  # the current faces (a piecewise-fixed surface changes them per segment, _send)
        V0, _ = surf.host_mesh_at(0.0)
        self.scene_scale = float(np.linalg.norm(V0.max(0) - V0.min(0))) or 1.0
        self.min_scale = min_scale_rel * self.scene_scale
        self.min_ratio = float(min_ratio)
        self.duration = surf.num_frames / surf.fps if surf.num_frames > 1 else 10.0
        if self.realtime:
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        else:  # headless recording: the server is only the recording's scene; announce nothing
            import contextlib
            import io

            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        ico = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        self._ico = (np.asarray(ico.vertices, np.float32), np.asarray(ico.faces, np.uint32))
        self.mesh_color, self.sphere_color = tuple(mesh_color), tuple(sphere_color)
        if show_mesh is None:
            show_mesh = gaussians is None
        self._build_scene(V0, show_mesh)
        self._build_gui(show_mesh)
        if not world.editable:  # reset, seeking and dropping spheres are the built-in world's
            for name in ("gui_reset", "gui_replay", "gui_drop", "gui_time"):
                getattr(self, name).disabled = True
        self._serializer = self.server.get_scene_serializer() if self.record_path else None
        self._closed = False

    # -- scene ---------------------------------------------------------------------------------
    def _take_faces(self) -> bool:
        """Keep the world's current faces (``faces``); true when they are new (a new segment)."""
        indices = self.world.surface_indices()
        if indices.ptr == getattr(self, "_faces_ptr", None):
            return False
        self.faces, self._faces_ptr = indices.numpy().reshape(-1, 3).astype(np.uint32), indices.ptr
        return True

    def _add_mesh(self, visible: bool = True):
        self.mesh = self.server.scene.add_mesh_simple("/mesh", self._points(), self.faces, color=self.mesh_color,
                                                      side="double", visible=visible)

    def _points(self) -> np.ndarray:
        return np.array(self.world.surface_points().numpy(), dtype=np.float32, copy=True)

    def _splat_buffer(self) -> np.ndarray:
        """(G, 8) uint32 viser splat buffer: centre f32 x3, reserved, covariance f16 x6, rgba."""
        g = self.gaussians
        cov = g.splat_covariances_f16(self.min_scale, self.min_ratio)
        centers = np.array(g.state.centers.numpy(), dtype=np.float32, copy=True)
        buf = np.zeros((g.count, 8), np.uint32)
        buf[:, 0:3] = centers.view(np.uint32)
        buf[:, 4:7] = np.ascontiguousarray(cov).view(np.uint32)
        buf[:, 7] = self._shaded_rgba() if self.shade else self._rgba
        return buf

    def _shaded_rgba(self) -> np.ndarray:
        """The splats' RGBA with shading baked from their normals this frame (a key light from
        above and in front of the initial view), so the surface reads as a shape."""
        from .gaussians import shaded_rgb

        g = self.gaussians
        rgb = shaded_rgb(g, LIGHT_DIR)
        rgba = np.concatenate([np.round(rgb * 255), np.round(g.binding.opacity[:, None] * 255)], 1)
        return np.ascontiguousarray(np.clip(rgba, 0, 255).astype(np.uint8)).view(np.uint32).reshape(-1)

    def _build_scene(self, V0, show_mesh: bool):
        sc = self.server.scene
        sc.set_up_direction("+z")
        lo, hi = V0.min(0), V0.max(0)
        c = 0.5 * (lo + hi)
        cam = self.server.initial_camera
        cam.look_at = tuple(float(x) for x in c)
        cam.position = tuple(float(x) for x in c + np.array([1.2, -1.6, 1.0]) * self.scene_scale * 0.5)
        cam.up = (0.0, 0.0, 1.0)
        self._add_mesh(show_mesh)
        params = getattr(getattr(self.world, "model", None), "params", None)
        gz = getattr(params, "ground_height", None)
        self.ground = None
        if gz is not None:  # the ground the spheres land on, drawn: a grid 3 x the scene's size
            size = 3.0 * self.scene_scale
            cell = float(10.0 ** np.floor(np.log10(max(size / 20.0, 1e-9))))
            self.ground = sc.add_grid("/ground", width=size, height=size, plane="xy", cell_size=cell,
                                      section_size=10.0 * cell, plane_color=(236, 236, 232), plane_opacity=1.0,
                                      position=(float(c[0]), float(c[1]), float(gz)))
        self.splats = None
        g = self.gaussians
        if g is not None and g.count:
            rgba = np.concatenate([np.round(g.binding.rgb * 255), np.round(g.binding.opacity[:, None] * 255)], 1)
            self._rgba = np.ascontiguousarray(np.clip(rgba, 0, 255).astype(np.uint8)).view(np.uint32).reshape(-1)
            seq = getattr(self.world.surface, "sequence", None)
            if self.splat_groups > 0 and getattr(seq, "V", None) is not None:
                self._refresh_gaussians()
                self.stream = _SplatGroups(self, np.asarray(seq.V), seq.F, self.splat_groups)
                self.splats = self.stream.parent
            else:
                cov = np.zeros((g.count, 3, 3), np.float32)
                cov[:] = np.eye(3) * 1e-4
                self.splats = sc.add_gaussian_splats("/splats", centers=np.zeros((g.count, 3), np.float32),
                                                     covariances=cov, rgbs=g.binding.rgb,
                                                     opacities=g.binding.opacity[:, None])
                self._refresh_gaussians()  # the state at time 0 (the buffer was the Gaussians' last)
                self.splats.buffer = self._splat_buffer()
        self.spheres = None
        self._sphere_count = -1
        self._send_spheres(force=True)
        self._sent_time = self.world.time
        self._stale = {"mesh": False, "splats": False}
        self._gaussians_stale = True

    def _send_spheres(self, force: bool = False):
        w = self.world
        pos = np.array(w.sphere_positions(), dtype=np.float32, copy=True)  # CPU numpy() is a view
        S = pos.shape[0]
        if S != self._sphere_count or force:
            if self.spheres is not None:
                self.spheres.remove()
                self.spheres = None
            visible = self.gui_show_spheres.value if hasattr(self, "gui_show_spheres") else True
            if S:
                self.spheres = self.server.scene.add_batched_meshes_simple(
                    "/spheres", self._ico[0], self._ico[1], batched_wxyzs=np.tile(np.float32([1, 0, 0, 0]), (S, 1)),
                    batched_positions=pos, batched_scales=w.sphere_radii().astype(np.float32),
                    batched_colors=self.sphere_color, lod="off", visible=visible)
            self._sphere_count = S
            self._last_pos = pos
        elif S and not np.array_equal(pos, self._last_pos):
            self.spheres.batched_positions = pos
            self._last_pos = pos

    # -- GUI -----------------------------------------------------------------------------------
    def _queue(self, action, *args):
        with self._lock:
            self._actions.append((action, args))

    def _build_gui(self, show_mesh: bool):
        gui = self.server.gui
        self.gui_play = gui.add_checkbox("Play", True)
        self.gui_time = gui.add_slider("Time [s]", min=0.0, max=round(self.duration, 3), step=0.01, initial_value=0.0)
        self.gui_speed = gui.add_slider("Speed", min=0.0, max=4.0, step=0.05, initial_value=self.speed)
        self.gui_reset = gui.add_button("Reset")
        self.gui_replay = gui.add_button("Replay drop")
        self.gui_drop = gui.add_button("Drop sphere")
        self.gui_show_splats = gui.add_checkbox("Show splats", self.gaussians is not None)
        self.gui_show_mesh = gui.add_checkbox("Show mesh", show_mesh)
        self.gui_wire = gui.add_checkbox("Wireframe", False)
        self.gui_show_spheres = gui.add_checkbox("Show spheres", True)
        self._slider_guard = False
        self._last_seek = -1e9
        self.gui_rate = gui.add_text("Rate (sim s / wall s)", "-", disabled=True)
        self.gui_splat_error = gui.add_text("Splat error (of the scene size)", "-", disabled=True)

        self.gui_play.on_update(lambda e: self._queue("play", self.gui_play.value))
        self.gui_speed.on_update(lambda e: self._queue("speed", self.gui_speed.value))
        self.gui_reset.on_click(lambda e: self._queue("reset"))
        self.gui_replay.on_click(lambda e: self._queue("replay"))
        self.gui_drop.on_click(lambda e: self._queue("drop"))
        self.gui_show_splats.on_update(lambda e: self._queue("show", "splats", self.gui_show_splats.value))
        self.gui_show_mesh.on_update(lambda e: self._queue("show", "mesh", self.gui_show_mesh.value))
        self.gui_show_spheres.on_update(lambda e: self._queue("show", "spheres", self.gui_show_spheres.value))
        self.gui_wire.on_update(lambda e: self._queue("wire", self.gui_wire.value))

        def on_time(e):
            if not self._slider_guard and getattr(e, "client", None) is not None:
                self._queue("seek", float(self.gui_time.value))

        self.gui_time.on_update(on_time)

    # -- actions (frame-loop thread) -----------------------------------------------------------
    def _refresh_gaussians(self):
        if self.gaussians is not None:
            w = self.world
            self.gaussians.update(w.surface_points(), w.surface_indices())

    def reset(self):
        """Back to the start: the scene's own spheres (dropped ones removed), time t0."""
        self.world.reset()
        self._refresh_gaussians()
        self._owed = 0.0
        self._send_spheres(force=True)

    def replay(self):
        """The scene's moment again: back to the start (``reset``) and playing, so the spheres
        drop onto the surface as they did when the page opened."""
        self.reset()
        self.playing = True
        self.gui_play.value = True

    def seek(self, t: float):
        """Move the surface to time ``t`` [s] (spheres keep their state)."""
        w = self.world
        w.set_time(max(float(t), w.t0))
        self._refresh_gaussians()

    def drop_sphere(self, radius: float | None = None):
        """Add one sphere above the current surface at a seeded random spot (up = +z)."""
        w = self.world
        P = self._points()
        hi = P.max(0)
        radii = w.sphere_radii()
        r = float(np.median(radii)) if len(radii) else 0.03 * self.scene_scale
        r = radius or r
        # above a random vertex of the surface's upper side (the highest vertex near that x, y), so
        # it lands on the surface, not beside it on the ground
        up = P[P[:, 2] >= np.quantile(P[:, 2], 0.5)]
        xy = up[int(self._rng.integers(len(up))), :2]
        near = P[np.linalg.norm(P[:, :2] - xy, axis=1) <= 2 * r]
        top = float(near[:, 2].max()) if len(near) else float(hi[2])
        w.add_spheres([[xy[0], xy[1], top + 4 * r]], r, 1.0)

    def _apply_actions(self):
        with self._lock:
            actions, self._actions = self._actions, []
        for name, args in actions:
            if name == "play":
                self.playing = bool(args[0])
            elif name == "speed":
                self.speed = float(args[0])
            elif name == "reset":
                self.reset()
            elif name == "replay":
                self.replay()
            elif name == "drop":
                self.drop_sphere()
            elif name == "seek":
                self._last_seek = time.monotonic()
                self.seek(args[0])
            elif name == "wire":
                self.mesh.wireframe = bool(args[0])
            elif name == "show":
                node = {"mesh": self.mesh, "splats": self.splats, "spheres": self.spheres}[args[0]]
                if node is not None:
                    node.visible = bool(args[1])
                if args[0] in self._stale and args[1]:
                    self._stale[args[0]] = True

    # -- frame loop ----------------------------------------------------------------------------
    def update(self) -> int:
        """One viewer frame: apply GUI actions, step the world, send what changed. Returns the
        number of physics steps taken."""
        self._apply_actions()
        w = self.world
        n = 0
        if self.hold_until_client and not self._client_seen:
            if not self.server.get_clients():  # nobody is watching yet: hold the clock
                # a held frame does not count towards run(max_frames): `run --duration 10` closed
                # after 10 s of waiting, before anyone had opened the page (found by a new user)
                self.gui_rate.value = "waiting for a browser"
                self.held_frames += 1
                return 0
            self._client_seen = True
            self._last_wall = None  # the clock starts now, at one frame's worth
        now = time.perf_counter()
        # realtime: simulate speed x the wall time since the last frame (a late frame catches up,
        # up to MAX_CATCH_UP seconds of it; frames are dropped, time is not slowed); recording /
        # headless: a fixed frame_dt per frame
        elapsed = self.frame_dt if (not self.realtime or self._last_wall is None) else \
            min(now - self._last_wall, MAX_CATCH_UP)
        self._last_wall = now
        if self._serializer is not None:
            # the recording's clock first: the set-up's messages (the state at time 0) stand for one
            # frame, and the state after this frame's steps comes at the time it has (a new user's
            # recording showed time (j + 1) / fps at j / fps, and never the start)
            self._serializer.insert_sleep(self.frame_dt)
        if self.playing:
            self._owed += self.speed * elapsed
            dt = w.dt
            n = int(self._owed / dt + 1e-9)
            self._owed -= n * dt
            for _ in range(n):
                w.step()
        self._send()
        self.frame += 1
        self._rate_window.append((now, w.time))
        if len(self._rate_window) > 30:
            self._rate_window.pop(0)
        (t0w, t0s), (t1w, t1s) = self._rate_window[0], self._rate_window[-1]
        if t1w > t0w and self.frame % 10 == 0:
            self.achieved_rate = (t1s - t0s) / (t1w - t0w)
            self.gui_rate.value = f"{self.achieved_rate:.2f} (speed {self.speed:g})"
            if self.stream is not None and self.stream.error is not None:
                e = self.stream.error
                self.gui_splat_error.value = (f"p99 {100 * e['p99']:.2f} % / max {100 * e['max']:.2f} % "
                                              f"({self.stream.K} groups)")
        return n

    def _send(self):
        w = self.world
        moved = w.time != self._sent_time
        if moved or self._gaussians_stale:  # once per viewer frame, never per physics step
            self._refresh_gaussians()
            self._gaussians_stale = False
        with self.server.atomic():
            if (moved or self._stale["mesh"]) and self.mesh.visible:
                if self._take_faces():  # a new segment of a piecewise-fixed surface: its faces
                    self.mesh.remove()
                    self._add_mesh()
                else:
                    self.mesh.vertices = self._points()
                self._stale["mesh"] = False
            elif moved:
                self._stale["mesh"] = True
            if self.splats is not None:
                if (moved or self._stale["splats"]) and self.splats.visible:
                    if self.stream is not None:
                        self.stream.update()
                    else:
                        self.splats.buffer = self._splat_buffer()
                    self._stale["splats"] = False
                elif moved:
                    self._stale["splats"] = True
            self._send_spheres()
            if moved and time.monotonic() - self._last_seek > 0.5:  # not while a user drags it
                self._slider_guard = True
                try:
                    t = w.time % self.duration if self.duration > 0 else w.time
                    self.gui_time.value = round(min(t, self.duration), 2)
                finally:
                    self._slider_guard = False
        self._sent_time = w.time

    def run(self, max_frames: int | None = None, stop=None):
        """Frame loop until ``max_frames`` (None: until Ctrl-C); paced to ``fps`` when realtime.
        ``stop``: a callable checked before every frame; a true value (e.g. ``"SIGINT"``) ends the
        loop there and is returned (else None)."""
        from .cli import checking_stops

        try:
            with checking_stops():  # the CLIs' SIGINT/SIGTERM end the loop between frames
                while max_frames is None or self.frame < max_frames:
                    reason = stop() if stop is not None else None
                    if reason:
                        return reason
                    t0 = time.perf_counter()
                    self.update()
                    if self.realtime:
                        rest = self.frame_dt - (time.perf_counter() - t0)
                        while rest > 0 and not (stop is not None and stop()):  # sleep, waking for a stop
                            time.sleep(min(rest, 0.05))
                            rest = self.frame_dt - (time.perf_counter() - t0)
        except KeyboardInterrupt:  # Ctrl-C outside the CLIs (default handler)
            self.log("viewer: interrupted")
            return "SIGINT"
        return None

    def close(self):
        """Write the recording (if any) and stop the server."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._serializer is not None:
                from .outputs import atomic_write_bytes, beside_path

                data = self._serializer.serialize()
                if getattr(self, "interrupted", False) and self.record_path.exists():
                    # a stopped run never replaces an earlier recording (a new user's complete one
                    # became the stopped one under --overwrite): it goes beside it
                    self.record_path = beside_path(self.record_path, "partial",
                                                   lambda q: q.with_suffix(".html").exists())
                atomic_write_bytes(self.record_path, data)
                html = self.record_path.with_suffix(".html")
                atomic_write_bytes(html, recording_html(data).encode("utf-8"))
                size = f"{len(data) / 1e6:.1f} MB" if len(data) >= 1e6 else f"{len(data) / 1e3:.0f} kB"
                self.log(f"recording: {self.record_path} ({size}), {html}")
        finally:
            import contextlib
            import io

            with contextlib.redirect_stdout(io.StringIO()) if not self.realtime else contextlib.nullcontext():
                self.server.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class _SplatGroups:
    """The viewer's Gaussians as K rigidly moving groups (docs/rendering.md#what-the-viewer-sends).

    Faces are grouped by their motion over the whole sequence (:func:`geometry.motion_groups`:
    k-means of centroid trajectories), each Gaussian joins its face's group, and each group is one
    viser splat node under the ``/splats`` frame: its buffer (centres relative to the group's
    centroid, covariances and shaded colours of the reference pose) is sent once; per frame only
    the groups' poses go (Kabsch fit of the reference centres to the current ones,
    :func:`geometry.fit_group_motions`; viser's splat shader applies a node's pose to centres and
    covariances). ``error``: the last frame's fit error per Gaussian as fractions of the scene's
    bounding-box diagonal (median, p99, max); above REKEY_ERROR (at most every REKEY_INTERVAL s)
    the buffers are sent again from the current pose (``rekeys`` counts them)."""

    def __init__(self, viewer, V, F, groups: int):
        from .geometry import motion_groups

        self.viewer = viewer
        g = viewer.gaussians
        face_group = motion_groups(V, F, min(int(groups), g.count))
        self.labels = face_group[g.binding.face.numpy()]
        self.labels = np.unique(self.labels, return_inverse=True)[1]  # groups that hold a Gaussian
        self.K = int(self.labels.max()) + 1
        order = np.argsort(self.labels, kind="stable")
        bounds = np.searchsorted(self.labels[order], np.arange(self.K + 1))
        self.members = [order[bounds[k]:bounds[k + 1]] for k in range(self.K)]
        sc = viewer.server.scene
        self.parent = sc.add_frame("/splats", show_axes=False)
        self.nodes = []
        for k, idx in enumerate(self.members):
            n = len(idx)
            self.nodes.append(sc.add_gaussian_splats(
                f"/splats/g{k}", centers=np.zeros((n, 3), np.float32), covariances=np.zeros((n, 3, 3), np.float32),
                rgbs=np.zeros((n, 3), np.float32), opacities=np.zeros((n, 1), np.float32)))
        self.error = None
        self.rekeys = 0
        self._last_key = -np.inf
        self.key()

    def _centers(self) -> np.ndarray:
        return np.array(self.viewer.gaussians.state.centers.numpy(), dtype=np.float64, copy=True)

    def key(self):
        """Send every group's buffer from the current pose (the new reference)."""
        C = self._centers()
        cnt = np.bincount(self.labels, minlength=self.K).astype(np.float64)
        mean = np.stack([np.bincount(self.labels, C[:, j], self.K) for j in range(3)], 1) / cnt[:, None]
        self.ref_local = C - mean[self.labels]
        buf = self.viewer._splat_buffer()
        buf[:, 0:3] = self.ref_local.astype(np.float32).view(np.uint32)
        self._pose = np.concatenate([np.tile([1.0, 0.0, 0.0, 0.0], (self.K, 1)), mean], 1)  # (K, 7) wxyz, xyz
        for k, node in enumerate(self.nodes):
            node.buffer = np.ascontiguousarray(buf[self.members[k]])
            node.wxyz = (1.0, 0.0, 0.0, 0.0)
            node.position = tuple(float(x) for x in mean[k])
        self._last_key = time.monotonic()
        self.error = {"median": 0.0, "p99": 0.0, "max": 0.0}

    def update(self):
        """Fit each group's pose to the Gaussians' current centres and send the ones that moved;
        key again instead when the fit error is over REKEY_ERROR (at most every REKEY_INTERVAL)."""
        from .geometry import fit_group_motions, rotation_to_wxyz

        scale = self.viewer.scene_scale
        R, t, err = fit_group_motions(self.ref_local, self._centers(), self.labels, self.K)
        err = err / scale
        self.error = {"median": float(np.median(err)), "p99": float(np.percentile(err, 99)), "max": float(err.max())}
        if self.error["max"] > REKEY_ERROR and time.monotonic() - self._last_key >= REKEY_INTERVAL:
            self.rekeys += 1
            self.key()
            return
        pose = np.concatenate([rotation_to_wxyz(R), t], 1)
        d = np.abs(pose - self._pose)
        moved = np.flatnonzero((d[:, :4].max(axis=1) > 1e-7) | (d[:, 4:].max(axis=1) > 1e-7 * scale))
        for k in moved:
            self.nodes[k].wxyz = tuple(float(x) for x in pose[k, :4])
            self.nodes[k].position = tuple(float(x) for x in pose[k, 4:])
        self._pose[moved] = pose[moved]


def _shape_mesh(shape: dict):
    """(V float32, F uint32) of a Newton shape in its own frame, or None (planes, unknown)."""
    import trimesh

    t, sc = shape["type"], shape["scale"]
    if t == "box":
        m = trimesh.creation.box(extents=[2 * sc[0], 2 * sc[1], 2 * sc[2]])
    elif t == "sphere":
        m = trimesh.creation.icosphere(subdivisions=2, radius=sc[0])
    elif t == "capsule":
        m = trimesh.creation.capsule(height=2 * sc[1], radius=sc[0], count=[16, 16])
    elif t == "cylinder":
        m = trimesh.creation.cylinder(radius=sc[0], height=2 * sc[1], sections=24)
    elif "vertices" in shape:
        return (np.asarray(shape["vertices"], np.float32) * np.float32(sc[:3]),
                np.asarray(shape["indices"], np.uint32))
    else:
        return None
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32)


def _xyzw_to_wxyz(q) -> tuple:
    return (float(q[3]), float(q[0]), float(q[1]), float(q[2]))


class NewtonViewer(Viewer):
    """:class:`Viewer` for a ``NewtonWorld``: the deforming surface (and its Gaussians) plus every
    Newton shape (boxes, spheres, capsules, cylinders, meshes of MJCF/URDF/USD bodies) at its
    current pose. Reset, time seeking and sphere dropping are built-in-world features and are
    not offered here."""

    body_color = (240, 170, 60)

    def __init__(self, newton_world, gaussians=None, **kw):
        self.newton_world = newton_world
        self._bodies: list = []
        super().__init__(newton_world, gaussians, **kw)
        sc = self.server.scene
        X = newton_world.shape_transforms()
        for shape in newton_world.shapes():
            mesh = _shape_mesh(shape)
            if mesh is None:
                continue
            s = shape["index"]
            h = sc.add_mesh_simple(f"/bodies/shape_{s}", mesh[0], mesh[1], color=self.body_color,
                                   position=tuple(float(x) for x in X[s, :3]), wxyz=_xyzw_to_wxyz(X[s, 3:]))
            self._bodies.append((s, h))
        self._refresh_gaussians()

    def _send_spheres(self, force: bool = False):
        if not self._bodies:
            return
        X = self.newton_world.shape_transforms()
        for s, h in self._bodies:
            h.position = tuple(float(x) for x in X[s, :3])
            h.wxyz = _xyzw_to_wxyz(X[s, 3:])

    def reset(self):
        self.log("viewer: reset is not available for Newton scenes")

    def seek(self, t: float):
        self.log("viewer: time seeking is not available for Newton scenes")

    def drop_sphere(self, radius: float | None = None):
        self.log("viewer: dropping spheres is not available for Newton scenes")


def recording_html(data: bytes, dark_mode: bool = False) -> str:
    """A self-contained HTML page playing the ``.viser`` recording ``data``: viser's single-file
    client build with the recording embedded as base64 (what ``StateSerializer.as_html`` does)."""
    import base64

    viser = _require_viser()
    client = Path(viser.__file__).parent / "client" / "build" / "index.html"
    page = client.read_text(encoding="utf-8")
    inject = (f'<script>window.__VISER_EMBED_DATA__="{base64.b64encode(data).decode("ascii")}";'
              f"window.__VISER_EMBED_CONFIG__={{darkMode:{'true' if dark_mode else 'false'}}};</script>")
    i = page.index("</head>")
    return page[:i] + inject + page[i:]


# -- decoding what viser sends (tests, inspection) -------------------------------------------------


def _resolve(obj, buffers):
    if isinstance(obj, dict):
        if "__binary_index" in obj and "dtype" in obj:
            return np.frombuffer(buffers[obj["__binary_index"]], dtype=np.dtype(obj["dtype"]))
        return {k: _resolve(v, buffers) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_resolve(v, buffers) for v in obj]
    return obj


def _split_buffers(blob: memoryview, offset: int, lengths) -> list:
    out = []
    for n in lengths:
        offset += (8 - offset % 8) % 8
        out.append(bytes(blob[offset:offset + n]))
        offset += n
    return out


def decode_wire_message(raw: bytes) -> list[dict]:
    """Messages of one viser websocket frame (zstd msgpack + aligned raw buffers), arrays as
    flat NumPy arrays."""
    import msgspec
    import zstandard

    mv = memoryview(raw)
    n_inner = int.from_bytes(mv[0:8], "little")
    n_comp = int.from_bytes(mv[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(bytes(mv[16:16 + n_comp]), max_output_size=n_inner)
    meta = msgspec.msgpack.decode(inner)
    bufs = _split_buffers(mv, 16 + n_comp, meta["binaryBufferLengths"])
    return [_resolve(m, bufs) for m in meta["messages"]]


def decode_viser_recording(data: bytes) -> dict:
    """A ``.viser`` recording: {"duration": s, "version": str, "messages": [(t, message dict)]}."""
    import msgspec
    import zstandard

    size = int.from_bytes(data[:8], "little")
    inner = zstandard.ZstdDecompressor().decompress(data[8:], max_output_size=size)
    mv = memoryview(inner)
    n = int.from_bytes(mv[:8], "little")
    meta = msgspec.msgpack.decode(bytes(mv[8:8 + n]))
    bufs = _split_buffers(mv, 8 + n, meta["binaryBufferLengths"])
    msgs = [(t, _resolve(m, bufs)) for t, m in meta["messages"]]
    return {"duration": meta["durationSeconds"], "version": meta["viserVersion"], "messages": msgs}


class SceneStateTracker:
    """Applies decoded viser messages to a {node name: props} dict (creation, prop updates,
    pose updates as ``position`` / ``wxyz``, removal), i.e. the scene a client would show."""

    def __init__(self):
        self.nodes: dict[str, dict] = {}

    def apply(self, msg: dict):
        t = msg.get("type", "")
        if t == "SceneNodeUpdateMessage":
            if msg["name"] in self.nodes:
                self.nodes[msg["name"]].update(msg["updates"])
        elif t == "RemoveSceneNodeMessage":
            self.nodes.pop(msg["name"], None)
        elif t in ("SetPositionMessage", "SetOrientationMessage"):  # node pose (position, wxyz)
            if msg["name"] in self.nodes:
                key = "position" if t == "SetPositionMessage" else "wxyz"
                self.nodes[msg["name"]][key] = msg[key]
        elif "props" in msg and "name" in msg and isinstance(msg["props"], dict):
            self.nodes[msg["name"]] = dict(msg["props"], _type=t)


def scene_splat_centers(nodes: dict, members=None) -> np.ndarray:
    """(G, 3) float64 world centres of the splats a client shows (``SceneStateTracker.nodes``):
    the one ``/splats`` node's buffer, or the grouped ``/splats/g{k}`` nodes' local centres moved
    by each node's pose (position, wxyz), in group order, or in the Gaussians' order when the
    stream's ``members`` are given."""
    if "/splats" in nodes and "buffer" in nodes["/splats"]:
        return nodes["/splats"]["buffer"].reshape(-1, 8)[:, :3].copy().view(np.float32).astype(np.float64)
    keys = sorted((int(k[len("/splats/g"):]), k) for k in nodes if k.startswith("/splats/g"))
    parts = []
    for _, k in keys:
        nd = nodes[k]
        local = nd["buffer"].reshape(-1, 8)[:, :3].copy().view(np.float32).astype(np.float64)
        w, x, y, z = (float(a) for a in nd.get("wxyz", (1.0, 0.0, 0.0, 0.0)))
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        parts.append(local @ R.T + np.asarray(nd.get("position", (0.0, 0.0, 0.0)), np.float64))
    C = np.concatenate(parts) if parts else np.zeros((0, 3))
    if members is not None:
        out = np.empty_like(C)
        out[np.concatenate(members)] = C
        return out
    return C


def run_viewer(cfg, device=None, viewer: str = "viser", port: int = 8080, host: str = "127.0.0.1",
               record: str | None = None, steps: int | None = None, collider: str | None = None,
               rebuild_every: str | None = None, fps: float = 30.0, log=print, stop=None,
               splat_groups: int | None = None, view_envs=None) -> dict:
    """Build the scene, bind/generate its Gaussians and run the viewer.

    ``viewer="viser"``: interactive until Ctrl-C (or ``steps`` physics steps, if given);
    ``viewer="none"`` with ``record``: headless, frames back to back for ``steps`` (default:
    the scene's run duration), then the recording is written. ``stop``: a callable checked
    between frames (the CLI's SIGINT/SIGTERM); the loop ends there, the recording of the frames
    so far is written and the server stopped; ``"interrupted_by"`` in the result names it.
    ``splat_groups``: :class:`Viewer`'s (None: SPLAT_GROUPS). ``view_envs``: for batched envs,
    the envs shown (one: that env; several: side by side, ``batch.EnvGrid``; None: env 0).
    """
    kw = {"splat_groups": SPLAT_GROUPS if splat_groups is None else int(splat_groups)}
    from .gaussians import can_bind, gaussians_for_surface

    if viewer != "viser":  # headless recording: viser's serializer needs a server object; bind it to an
        host, port = "127.0.0.1", 0  # ephemeral local port (nothing announced, no port clash)
    from .scene import build_world

    if getattr(cfg, "newton", None) is not None:  # bodies simulated by Newton (docs/newton.md)
        from .newton_adapter import build_newton_world

        newton_world = build_newton_world(cfg, device=device)
        g = gaussians_for_surface(newton_world.surface.sequence, cfg, newton_world.device)
        v = NewtonViewer(newton_world, g, port=port, host=host, fps=fps, record=record,
                         realtime=(viewer == "viser"), log=log, **kw)
        world, what = v.world, f"{newton_world.model.body_count} Newton bodies"
    elif cfg.envs.count > 1:  # batched envs: the viewer shows one env or a grid of a few (docs/envs.md)
        from .batch import EnvGrid, EnvView, build_batched_world

        batch = build_batched_world(cfg, device=device)
        shown = [0] if not view_envs else [int(e) for e in view_envs]
        world = EnvView(batch, shown[0]) if len(shown) == 1 else EnvGrid(batch, shown)
        g = gaussians_for_surface(world.surface.sequence, cfg, world.device)
        v = Viewer(world, g, port=port, host=host, fps=fps, record=record, realtime=(viewer == "viser"), log=log,
                   **kw)
        what = (f"env {shown[0]}" if len(shown) == 1 else f"envs {', '.join(map(str, shown))}") + \
            f" of {batch.num_envs} ({batch.model.spheres_per_env} spheres each)"
    else:
        world = build_world(cfg, device=device, collider=collider, rebuild_every=rebuild_every)
        if steps is not None or viewer != "viser":  # a bounded run: the work budget, before the server starts
            from .runtime import check_total_work, run_steps

            check_total_work(cfg, steps if steps is not None else run_steps(cfg), world.substeps)
        # not attached to the step: the viewer updates them once per frame it sends. A varying
        # (e.g. piecewise-fixed) surface has no faces every frame shares to bind them to: the mesh
        # is shown instead, its faces changing per segment
        # (asked, not caught: a bad splat file's SplatPlyError is a ValueError too, and was taken
        # for this case: the note, 0 splats recorded, exit 0)
        seq = world.model.surface.sequence
        if can_bind(seq):
            g = gaussians_for_surface(seq, cfg, world.device)
        else:  # a truly varying surface: no faces to bind them to from frame to frame
            g = None
            log("note: the surface's topology changes every frame: showing the mesh without Gaussians "
                "(convert the sequence to bind them)")
        world.render_state = True  # the vertex buffer current after every step, for the splats and mesh
        v = Viewer(world, g, port=port, host=host, fps=fps, record=record, realtime=(viewer == "viser"), log=log,
                   **kw)
        what = f"{world.model.spheres.count} spheres"
    dt = world.dt
    if steps is None and viewer != "viser":
        from .runtime import run_steps

        steps = run_steps(cfg)
    max_frames = None if steps is None else max(1, int(np.ceil(steps * dt / v.frame_dt)))
    count = g.count if g is not None else 0
    if record and max_frames is not None:  # what a long recording will cost, before it is made
        grouped = v.stream is not None
        # per frame: each group's pose is two viser messages, ~192 B with their headers (measured:
        # 24.6 kB a frame for 128 groups on the default scene; 64 B counted before, so a new user's
        # "up to 0.8 MB" recording held 1.85 MB), or the whole splat buffer
        splats = v.stream.K * GROUP_POSE_BYTES if grouped else count * 32
        mesh = world.surface_points().shape[0] * 12
        per_frame = splats + (mesh if v.mesh.visible else 0) + len(world.sphere_radii()) * 64
        # once: the splats (grouped) and the scene's set-up messages (the surface, the ground,
        # the GUI: ~0.5 MB on the default scene, taken as 4x the surface's vertex bytes + 0.3 MB)
        est = max_frames * per_frame + (count * 32 if grouped else 0) + 4 * mesh + 0.3 * 2**20
        what = (f"the splats once ({count * 32 / 2**20:,.1f} MB) and the poses of {v.stream.K} groups per frame"
                if grouped else f"{count:,} splats x 32 B per frame")
        whole = int(round(max_frames * v.frame_dt / dt))
        log(f"recording {max_frames:,} frames at {v.fps:g} fps: about {est / 2**20:,.1f} MB before compression "
            f"({what}{', the mesh' if v.mesh.visible else ''}, the spheres)"
            + (f"; {whole:,} steps, whole frames of {v.frame_dt:.4g} s ({steps:,} asked)" if whole != steps else ""))
    if viewer == "viser":
        log(f"viewer: http://{'localhost' if host in ('0.0.0.0', '127.0.0.1') else host}:{v.port} "
            f"({count} Gaussians, {what}); Ctrl-C to quit")
    from .cli import checking_stops

    reason = None
    try:
        reason = v.run(max_frames=max_frames, stop=stop)
    finally:
        v.interrupted = reason is not None or sys.exc_info()[0] is not None
        with checking_stops():  # the recording is written whole, the server stopped, even on a signal
            v.close()
    return {"frames": v.frame, "sim_time_s": world.time, "gaussians": count, "port": v.port,
            "record": str(v.record_path) if record else None, "interrupted_by": reason}


if __name__ == "__main__":  # a new user's `python -m dynmesh_warp.viewer scene.yaml` did nothing, exit 0
    from .cli import not_a_command

    not_a_command("viewer", "is the live viewer that run starts (python -m dynmesh_warp.run scene.yaml --viewer viser)")
