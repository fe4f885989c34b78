"""Animated glTF 2.0 (``.glb`` / ``.gltf``): the meshes of a scene posed by one of its animations,
sampled at a fixed frame rate into a fixed-topology sequence (docs/data.md, "Animated glTF").

What is evaluated, as the glTF 2.0 specification defines it:

- node transforms: ``matrix`` (column-major) or translation / rotation (quaternion x, y, z, w) /
  scale, composed down the node hierarchy of the scene;
- animation channels on ``translation``, ``rotation``, ``scale`` and ``weights``, with ``STEP``,
  ``LINEAR`` (rotations by spherical interpolation) and ``CUBICSPLINE`` (Hermite, tangents
  scaled by the keyframe interval) samplers; before the first and after the last keyframe the
  end values hold;
- skins: linear blend skinning with every ``JOINTS_n`` / ``WEIGHTS_n`` set, joint matrix =
  global(joint) x inverse bind matrix; the skinned mesh node's own transform is ignored (the
  specification says so);
- morph targets: ``POSITION`` deltas weighted by the node's (animated) ``weights``, else the
  mesh's;
- primitives in triangle, strip and fan modes (points and lines are skipped); every primitive of
  every mesh node of the scene becomes part of one mesh, in node order.

Not read, with an error saying so: sparse accessors and the compression extensions a file may
require (Draco, meshopt). ``read_gltf_animation(path, fps=None, animation=None) -> (V (T, N, 3)
float32, F (M, 3) int64, fps)``. The frame rate, when not given, is the one the keyframes lie on
(1 / the spacing of uniformly spaced keys, whole or not: exporters bake at 24, 25, 29.97, 30 ...;
for other keys 1 / the median spacing, if whole), else 30.
``write_gltf_animation(path, V, F, fps)`` writes a sequence as an animated GLB (morph targets).
"""

from __future__ import annotations

import base64
import json
import os
import struct
import urllib.parse
from pathlib import Path

import numpy as np

from .mesh_formats import Z_UP_MARK, gltf_json, gltf_marked, linear_to_srgb, srgb_to_linear, y_to_z, z_to_y
from .outputs import atomic_path
from .sequence import MeshDataError

__all__ = ["GLTF_EXTENSIONS", "read_gltf_animation", "gltf_has_animation", "write_gltf_animation"]

GLTF_EXTENSIONS = (".glb", ".gltf")
_DEFAULT_FPS = 30.0
_MAX_KEY_RATE = 1000.0  # keys closer than 1 ms are not taken as frames (the default rate samples them)
_COMPONENT = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_NORM = {"<i1": 127.0, "<u1": 255.0, "<i2": 32767.0, "<u2": 65535.0, "<u4": 4294967295.0}
#: keyframe times are float32 (the accessors' type) and lie up to half a float32 step (6e-8 of
#: the time) from the k / fps they stand for: times within this fraction of the time (of 1 s near
#: 0) count as equal, for the frame count and where a frame time meets a key
_TIME_RTOL = 1e-6
_UNREAD_EXTENSIONS = {"KHR_draco_mesh_compression": "Draco-compressed meshes",
                      "EXT_meshopt_compression": "meshopt-compressed buffers",
                      "KHR_meshopt_compression": "meshopt-compressed buffers"}


class _File:
    """A glTF document and its buffers; accessors read as float64 / int64 arrays (count, width)."""

    def __init__(self, path: Path):
        self.path = path
        data = path.read_bytes()
        self.bin = None
        try:
            if data[:4] == b"glTF":
                doc = self._chunks(data)
            else:
                doc = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError, struct.error) as e:
            raise self.error(f"not a readable glTF file ({type(e).__name__}: {e})") from None
        if not isinstance(doc, dict):
            raise self.error("not a glTF document (its JSON is not an object)")
        self.doc = doc
        self._buffers = {}

    def check_extensions(self) -> None:
        for ext in self.doc.get("extensionsRequired", []):
            if ext in _UNREAD_EXTENSIONS:
                raise self.error(f"requires {ext} ({_UNREAD_EXTENSIONS[ext]}), which is not read; export it "
                                 "without compression")

    def error(self, msg: str) -> MeshDataError:
        return MeshDataError(f"{self.path}: {msg}")

    def ref(self, value, where: str, what: str, items=None, owner: str = "the file") -> int:
        """``value``, found at the JSON path ``where``, checked as an index into the document's list
        ``what`` (or ``items``, a list of ``owner``'s): an index out of range is an error naming the
        file, the path and the list (``nodes[3].mesh: 7, but the file has 2 meshes``), as a glTF
        validator reports it, never an IndexError or KeyError."""
        items = (self.doc.get(what) or []) if items is None else items
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < len(items):
            raise self.error(f"{where}: {value!r}, but {owner} has {len(items)} {what}")
        return value

    def _chunks(self, data: bytes) -> dict:
        _, length = struct.unpack_from("<II", data, 4)
        if length > len(data):
            raise self.error(f"GLB header says {length:,} bytes, but the file has {len(data):,} (truncated)")
        off, doc = 12, None
        while off + 8 <= length:
            size, kind = struct.unpack_from("<II", data, off)
            chunk = data[off + 8:off + 8 + size]
            if len(chunk) < size:
                raise self.error(f"GLB chunk at byte {off} says {size:,} bytes, but the file ends first (truncated)")
            if kind == 0x4E4F534A:  # JSON
                doc = json.loads(chunk.decode("utf-8"))
            elif kind == 0x004E4942 and self.bin is None:  # BIN
                self.bin = chunk
            off += 8 + size
        if doc is None:
            raise self.error("GLB file without a JSON chunk")
        return doc

    def _buffer(self, i: int) -> bytes:
        if i not in self._buffers:
            try:
                b = self.doc["buffers"][i]
            except (KeyError, IndexError, TypeError):
                raise self.error(f"buffer {i} does not exist") from None
            uri = b.get("uri")
            if uri is None:
                if self.bin is None:
                    raise self.error(f"buffer {i} has no uri and the file no binary chunk")
                data = self.bin
            elif uri.startswith("data:"):
                data = base64.b64decode(uri.split(",", 1)[1])
            else:
                f = self.path.parent / urllib.parse.unquote(uri)
                if not f.is_file():
                    raise self.error(f"buffer {i}: file {f} not found")
                data = f.read_bytes()
            if len(data) < int(b.get("byteLength", 0)):
                raise self.error(f"buffer {i} holds {len(data):,} bytes, less than its byteLength "
                                 f"{int(b['byteLength']):,} (truncated)")
            self._buffers[i] = data
        return self._buffers[i]

    def accessor(self, i: int) -> np.ndarray:
        try:
            a = self.doc["accessors"][int(i)]
            dtype, width, count = _COMPONENT[a["componentType"]], _WIDTH[a["type"]], int(a["count"])
        except (KeyError, IndexError, TypeError, ValueError):
            raise self.error(f"accessor {i} is missing or malformed") from None
        if "sparse" in a:
            raise self.error(f"accessor {i} is sparse, which is not read; export without sparse accessors")
        if "bufferView" not in a:
            return np.zeros((count, width))
        try:
            view = self.doc["bufferViews"][a["bufferView"]]
        except (KeyError, IndexError, TypeError):
            raise self.error(f"accessor {i}: buffer view {a['bufferView']} does not exist") from None
        buf = self._buffer(view["buffer"])
        item = np.dtype(dtype).itemsize
        stride = int(view.get("byteStride") or width * item)
        start = int(view.get("byteOffset", 0)) + int(a.get("byteOffset", 0))
        end = start + stride * (count - 1) + width * item if count else start
        limit = min(len(buf), int(view.get("byteOffset", 0)) + int(view["byteLength"]))
        if end > limit:
            raise self.error(f"accessor {i} ({count} x {a['type']}) reaches byte {end:,} of a buffer view that "
                             f"ends at {limit:,} (truncated or corrupt)")
        arr = np.ndarray((count, width), dtype, buffer=buf, offset=start, strides=(stride, item))
        if dtype == "<f4":
            return arr.astype(np.float64)
        if a.get("normalized"):
            return np.maximum(arr / _NORM[dtype], -1.0)
        return arr.astype(np.int64)


# --------------------------------------------------------------------------- transforms


def _time_tol(t: float) -> float:
    """How far two times near ``t`` may lie apart and still be one (float32 keyframe times)."""
    return _TIME_RTOL * max(abs(float(t)), 1.0)


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, np.float64) / max(np.linalg.norm(q), 1e-300)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _slerp(a, b, u: float) -> np.ndarray:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d = float(a @ b)
    if d < 0.0:  # the shorter way round
        b, d = -b, -d
    if d > 0.9995:
        q = a + u * (b - a)
    else:
        th = np.arccos(min(d, 1.0))
        q = (np.sin((1 - u) * th) * a + np.sin(u * th) * b) / np.sin(th)
    return q / np.linalg.norm(q)


def _trs(t, r, s) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = _quat_matrix(r) * np.asarray(s, np.float64)[None, :]
    M[:3, 3] = t
    return M


def _sample(times: np.ndarray, values: np.ndarray, interp: str, t: float, rotation: bool) -> np.ndarray:
    """The value of one sampler at time ``t`` (values (K, n), or (3K, n) for CUBICSPLINE)."""
    cubic = interp == "CUBICSPLINE"
    K = len(times)

    def key(k):
        return values[3 * k + 1] if cubic else values[k]

    tol = _time_tol(t)  # a frame time (float64) within float32 rounding of a key is at that key
    if t <= times[0] + tol or K == 1:
        return key(0)
    if t >= times[-1] - tol:
        return key(K - 1)
    i = int(np.searchsorted(times, t + tol, side="right")) - 1
    td = float(times[i + 1] - times[i])
    u = min(max((t - times[i]) / td, 0.0), 1.0) if td > 0 else 0.0
    if interp == "STEP":
        return key(i)
    if cubic:
        p0, m0 = values[3 * i + 1], td * values[3 * i + 2]
        p1, m1 = values[3 * (i + 1) + 1], td * values[3 * (i + 1)]
        u2, u3 = u * u, u * u * u
        v = (2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + u) * m0 + (-2 * u3 + 3 * u2) * p1 + (u3 - u2) * m1
        return v / np.linalg.norm(v) if rotation else v
    if rotation:
        return _slerp(values[i], values[i + 1], u)
    return (1 - u) * values[i] + u * values[i + 1]


# --------------------------------------------------------------------------- the scene


def _triangles(mode: int, idx: np.ndarray) -> np.ndarray:
    if mode == 4:
        return idx[: len(idx) // 3 * 3].reshape(-1, 3)
    if mode == 5:  # strip: every other triangle flipped to keep the winding
        tri = np.stack([idx[:-2], idx[1:-1], idx[2:]], axis=1)
        tri[1::2] = tri[1::2][:, [1, 0, 2]]
        return tri
    if mode == 6:  # fan
        return np.stack([np.full(len(idx) - 2, idx[0]), idx[1:-1], idx[2:]], axis=1)
    return np.zeros((0, 3), np.int64)  # points, lines


def _key_rate(allt: np.ndarray) -> float:
    """The frame rate the keyframe times ``allt`` (sorted, distinct) lie on. Uniformly spaced keys
    (within float32 rounding: a baked animation, the library's own .glb) give 1 / their spacing,
    whole or not, as the shortest decimal (up to 6 places) that puts every key within two float32
    steps of its k / fps (23.976, 29.97, 12.5, 0.5; else the spacing's own rate), so that each key
    is one frame. Others: 1 / the median spacing if it is a whole rate in [1, 1000], else 30."""
    K = len(allt)
    if K < 2:
        return _DEFAULT_FPS
    t0, t1 = float(allt[0]), float(allt[-1])
    k = np.arange(K)
    step = (t1 - t0) / (K - 1)
    if np.all(np.abs(allt - (t0 + k * step)) <= _time_tol(t1)) and 1.0 / step <= _MAX_KEY_RATE:
        r = 1.0 / step
        ulps = 2.0 * (np.spacing(np.abs(allt).astype(np.float32)).astype(np.float64)
                      + float(np.spacing(np.float32(abs(t0)))))
        for places in range(7):
            short = round(r, places)
            if short > 0 and np.all(np.abs(allt - t0 - k / short) <= ulps):
                return float(short)
        return r
    r = 1.0 / float(np.median(np.diff(allt)))
    if 1.0 <= r <= _MAX_KEY_RATE and abs(r - round(r)) < 1e-3 * r:
        return float(round(r))
    return _DEFAULT_FPS


def gltf_document(path) -> dict:
    """The JSON document of a .glb / .gltf file, reading only a .glb's header and its JSON chunk
    (:func:`~dynmesh_warp.mesh_formats.gltf_json`), not its binary buffer; a file that is not laid
    out so is read whole by :class:`_File`, which names what is wrong with it."""
    doc = gltf_json(path)
    return doc if isinstance(doc, dict) else _File(Path(path)).doc


def gltf_has_animation(path) -> bool:
    """Whether a .glb / .gltf file holds at least one animation with channels (its JSON only: a
    static file goes on to the mesh reader whatever extensions it requires)."""
    doc = gltf_document(path)
    return any(a.get("channels") for a in doc.get("animations", []) or [])


#: ``asset.generator`` of the files :func:`write_gltf_animation` wrote before it turned z-up data
#: to glTF's +Y up: they hold z-up coordinates as they were, which ``up_axis: auto`` reads unturned
GENERATOR = "dynmesh_warp"
#: ... and of the files it writes now: +Y up, as the specification says (a glTF input's coordinates
#: as they were; z-up data turned, with :data:`Z_UP_MARK`)
GENERATOR_Y_UP = "dynmesh_warp (+Y up)"
def gltf_turned_from_z(path) -> bool:
    """Whether a .glb / .gltf file holds z-up coordinates turned to +Y up by this project (its
    ``asset.extras`` carry :data:`Z_UP_MARK`; its JSON only, False when unreadable)."""
    try:
        return gltf_marked(gltf_document(path))
    except (MeshDataError, OSError, AttributeError):
        return False


def gltf_generator(path) -> str:
    """The ``asset.generator`` of a .glb / .gltf file ("" when absent or unreadable: its JSON only)."""
    try:
        g = gltf_document(path).get("asset", {}).get("generator", "")
    except (MeshDataError, OSError, AttributeError):
        return ""
    return g if isinstance(g, str) else ""


def read_gltf_animation(path, fps: float | None = None, animation=None, rest: bool = False, colors: bool = False):
    """Sample an animated glTF scene: ``(V (T, N, 3) float32, F (M, 3) int64, fps)``.

    ``animation``: the index or name of the animation (default: the first); ``fps``: the frame
    rate to sample at (default: the keyframes', else 30). ``rest``: a file without animations is
    one frame, its scene as its nodes, skins and morph weights stand (by the same rules: a skinned
    mesh's own node transform is not applied, as the specification says). ``colors``: also return
    the primitives' ``COLOR_0`` as sRGB, (N, 3) float32 in [0, 1], or None when a primitive has none:
    ``(V, F, fps, colors)``. Raises :class:`MeshDataError` naming the file for what cannot be read
    (module docstring)."""
    g = _File(Path(path))
    g.check_extensions()
    doc = g.doc
    nodes = doc.get("nodes", [])
    anims = [a for a in doc.get("animations", []) or []]
    if not anims and not (rest and animation is None):
        raise g.error("has no animation")
    if not anims:
        anims = [{"channels": []}]  # the scene as it stands: one frame
    if animation is None:
        ai = 0
    elif isinstance(animation, str):
        named = [k for k, a in enumerate(anims) if a.get("name") == animation]
        if not named:
            raise g.error(f"no animation named {animation!r}; it has {[a.get('name') for a in anims]}")
        ai = named[0]
    else:
        if not 0 <= int(animation) < len(anims):
            raise g.error(f"animation {animation} does not exist; it has {len(anims)}")
        ai = int(animation)
    anim = anims[ai]
    # channels: node -> path -> (times, values, interpolation)
    chans: dict[int, dict[str, tuple]] = {}
    key_times = []
    for ci, c in enumerate(anim.get("channels", [])):
        tgt = c.get("target", {})
        if "node" not in tgt:  # allowed (an extension may name the target)
            continue
        where = f"animations[{ai}].channels[{ci}]"
        node_i = g.ref(tgt["node"], f"{where}.target.node", "nodes")
        if tgt.get("path") not in ("translation", "rotation", "scale", "weights"):
            continue
        s = anim.get("samplers") or []
        s = s[g.ref(c.get("sampler"), f"{where}.sampler", "samplers", s, f"animations[{ai}]")]
        if "input" not in s or "output" not in s:
            raise g.error(f"animations[{ai}].samplers[{c['sampler']}] has no {'input' if 'input' not in s else 'output'}")
        times = g.accessor(s["input"])[:, 0].astype(np.float64)
        vals = g.accessor(s["output"])
        interp = s.get("interpolation", "LINEAR")
        if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
            raise g.error(f"animation sampler interpolation {interp!r} is not glTF 2.0")
        if len(times) == 0 or np.any(np.diff(times) < 0) or not np.all(np.isfinite(times)):
            raise g.error(f"animation sampler {c['sampler']}: keyframe times must be finite and increasing")
        if tgt["path"] == "weights":  # K x targets, flattened
            per = len(vals) // (len(times) * (3 if interp == "CUBICSPLINE" else 1))
            vals = vals.reshape(-1, max(per, 1))
        need = len(times) * (3 if interp == "CUBICSPLINE" else 1)
        if len(vals) != need:
            raise g.error(f"animation sampler {c['sampler']}: {len(vals)} output values for {len(times)} keyframes")
        chans.setdefault(node_i, {})[tgt["path"]] = (times, vals, interp)
        key_times.append(times)
    if not key_times and not (rest and not anim["channels"]):
        raise g.error("its animation has no channel on a node's translation, rotation, scale or weights")
    allt = np.unique(np.concatenate(key_times)) if key_times else np.zeros(1)
    t0, t1 = float(allt[0]), float(allt[-1])
    if fps is None:
        fps = _key_rate(allt)
    # the last key counts when it lies within float32 rounding of a frame time (k / fps stored as
    # float32 may round down: 60 frames at 24 fps read back as 59)
    n_frames = int(np.floor((t1 - t0 + _time_tol(t1)) * fps)) + 1
    # the node tree: transforms for every node (joints may lie outside the scene's roots), meshes
    # from the scene's nodes only
    children = [g.ref(c, f"nodes[{i}].children[{j}]", "nodes") for i, n in enumerate(nodes)
                for j, c in enumerate(n.get("children", []))]
    if len(set(children)) != len(children):
        raise g.error("its node tree is malformed (a node with two parents)")
    order, parent = [], {}
    stack = [(r, None) for r in reversed([i for i in range(len(nodes)) if i not in set(children)])]
    while stack:
        i, p = stack.pop()
        parent[i] = p
        order.append(i)
        stack.extend((c, i) for c in reversed(nodes[i].get("children", [])))
    if len(order) != len(nodes):
        raise g.error("its node tree has a cycle")
    scenes = doc.get("scenes") or []
    shown = set(order)
    if scenes or "scene" in doc:
        si = g.ref(doc.get("scene", 0), "scene", "scenes")
        stack = [g.ref(r, f"scenes[{si}].nodes[{j}]", "nodes") for j, r in enumerate(scenes[si].get("nodes", []))]
        shown = set()
        while stack:
            i = stack.pop()
            shown.add(i)
            stack.extend(nodes[i].get("children", []))
    # the static parts of every primitive
    prims = []
    for i in order:
        node = nodes[i]
        if "mesh" not in node or i not in shown:
            continue
        mesh_i = g.ref(node["mesh"], f"nodes[{i}].mesh", "meshes")  # checked before the list is indexed
        skin_i = g.ref(node["skin"], f"nodes[{i}].skin", "skins") if "skin" in node else None
        mesh = doc["meshes"][mesh_i]
        skin = None if skin_i is None else doc["skins"][skin_i]
        ibm = None
        if skin is not None:
            if not isinstance(skin.get("joints"), list) or not skin["joints"]:
                raise g.error(f"skins[{skin_i}].joints: {skin.get('joints')!r}, but a skin needs a list of "
                              "joint nodes")
            for j, jn in enumerate(skin["joints"]):
                g.ref(jn, f"skins[{skin_i}].joints[{j}]", "nodes")
            J = len(skin["joints"])
            ibm = (g.accessor(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
                   if "inverseBindMatrices" in skin else np.tile(np.eye(4), (J, 1, 1)))
            if len(ibm) != J:
                raise g.error(f"skin {skin_i}: {len(ibm)} inverse bind matrices for {J} joints")
        for k, pr in enumerate(mesh.get("primitives", [])):
            attrs = pr.get("attributes", {})
            if "POSITION" not in attrs:
                continue
            P = g.accessor(attrs["POSITION"])
            idx = g.accessor(pr["indices"])[:, 0] if "indices" in pr else np.arange(len(P))
            tri = _triangles(int(pr.get("mode", 4)), idx)
            if len(tri) == 0:
                continue
            if tri.min() < 0 or tri.max() >= len(P):
                raise g.error(f"mesh {mesh_i} primitive {k}: indices out of range [0, {len(P)})")
            targets = [g.accessor(t["POSITION"]) if "POSITION" in t else np.zeros_like(P)
                       for t in pr.get("targets", [])]
            joints, weights = [], []
            s = 0
            while skin is not None and f"JOINTS_{s}" in attrs and f"WEIGHTS_{s}" in attrs:
                joints.append(g.accessor(attrs[f"JOINTS_{s}"]).astype(np.int64))
                weights.append(g.accessor(attrs[f"WEIGHTS_{s}"]))
                s += 1
            if joints:
                joints, weights = np.concatenate(joints, axis=1), np.concatenate(weights, axis=1)
                if joints.max() >= len(skin["joints"]) or joints.min() < 0:
                    raise g.error(f"mesh {mesh_i} primitive {k}: joint index out of range of skin "
                                  f"{skin_i} ({len(skin['joints'])} joints)")
                tot = weights.sum(axis=1, keepdims=True)
                weights = np.where(tot > 0, weights / np.where(tot > 0, tot, 1.0), 0.0)
            C = g.accessor(attrs["COLOR_0"])[:, :3] if "COLOR_0" in attrs else None
            if C is not None and len(C) != len(P):
                raise g.error(f"mesh {mesh_i} primitive {k}: {len(C)} COLOR_0 values for {len(P)} positions")
            prims.append({"node": i, "P": P, "tri": tri, "targets": targets, "C": C,
                          "weights0": node.get("weights", mesh.get("weights", [0.0] * len(targets))),
                          "skin": skin if len(joints) else None, "ibm": ibm, "joints": joints, "w": weights})
    if not prims:
        raise g.error("its scene has no triangle mesh")
    F = np.concatenate([p["tri"] + off for p, off in
                        zip(prims, np.cumsum([0] + [len(p["P"]) for p in prims[:-1]]))]).astype(np.int64)
    N = sum(len(p["P"]) for p in prims)
    V = np.empty((n_frames, N, 3), np.float32)
    for f in range(n_frames):
        t = t0 + f / fps
        G, W = {}, {}
        for i in order:  # parents before children
            node, ch = nodes[i], chans.get(i, {})
            if "matrix" in node and not ch:
                L = np.asarray(node["matrix"], np.float64).reshape(4, 4).T
            else:
                tr = _sample(*ch["translation"], t, False) if "translation" in ch else node.get("translation", [0, 0, 0])
                ro = _sample(*ch["rotation"], t, True) if "rotation" in ch else node.get("rotation", [0, 0, 0, 1])
                sc = _sample(*ch["scale"], t, False) if "scale" in ch else node.get("scale", [1, 1, 1])
                L = _trs(tr, ro, sc)
            G[i] = L if parent[i] is None else G[parent[i]] @ L
            if "weights" in ch:
                W[i] = _sample(*ch["weights"], t, False)
        out, off = V[f], 0
        for p in prims:
            P = p["P"]
            w = np.asarray(W.get(p["node"], p["weights0"]), np.float64)
            for k, d in enumerate(p["targets"]):
                if k < len(w) and w[k] != 0.0:
                    P = P + w[k] * d
            Ph = np.c_[P, np.ones(len(P))]
            if p["skin"] is not None:
                Jm = np.stack([G[j] for j in p["skin"]["joints"]]) @ p["ibm"]  # (J, 4, 4)
                M = np.einsum("nk,nkij->nij", p["w"], Jm[p["joints"]])  # blended per vertex
                X = np.einsum("nij,nj->ni", M, Ph)[:, :3]
            else:
                X = Ph @ G[p["node"]].T[:, :3]
            out[off:off + len(P)] = X
            off += len(P)
    if gltf_marked(doc):
        V = y_to_z(V)  # this project's z-up data, turned to +Y up on writing: as it was saved
    if not colors:
        return V, F, float(fps)
    C = None if any(p["C"] is None for p in prims) else \
        linear_to_srgb(np.concatenate([p["C"] for p in prims])).astype(np.float32)
    return V, F, float(fps), C


def write_gltf_animation(path, V, F, fps: float, y_up: bool = False, colors=None) -> None:
    """Write a fixed-topology sequence ``V`` (T, N, 3) on faces ``F`` (M, 3) as one animated GLB
    (``path``, atomically): frame 0 is the mesh, frames 1 .. T - 1 are morph targets (position
    offsets from frame 0), and one animation sets target t - 1's weight to 1 at time t / fps, 0
    elsewhere, with LINEAR interpolation, so a viewer plays the frames and blends between them
    as the physics does. Reads back with :func:`read_gltf_animation`; Blender imports the targets
    as shape keys. float32 positions, uint32 indices, +Y up as the specification says (``asset.generator``
    ``GENERATOR_Y_UP``): ``y_up`` coordinates as they are, else z-up ones turned, (x, y, z) -> (x, z, -y),
    and marked (:data:`Z_UP_MARK`: read back as they were given). ``colors``: (N, 3) sRGB in [0, 1], written as linear
    float ``COLOR_0`` (the specification's space)."""
    V = np.asarray(V, np.float32)
    if not y_up:
        V = z_to_y(V)  # glTF is +Y up: viewers show it upright (read back turned again: Z_UP_MARK)
    F = np.asarray(F, np.uint32)
    T, n = V.shape[:2]
    blob = bytearray()
    views, accessors = [], []

    def add(arr, kind: str, ctype: int, minmax: bool = False) -> int:
        data = np.ascontiguousarray(arr).tobytes()
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        blob.extend(data)
        a = np.asarray(arr)
        acc = {"bufferView": len(views) - 1, "componentType": ctype, "count": int(len(a)), "type": kind}
        if minmax:  # required for POSITION accessors and animation inputs
            flat = a.reshape(len(a), -1)
            acc["min"], acc["max"] = flat.min(axis=0).tolist(), flat.max(axis=0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    prim = {"attributes": {"POSITION": add(V[0], "VEC3", 5126, True)}, "indices": add(F.reshape(-1), "SCALAR", 5125),
            "mode": 4}
    if colors is not None:
        prim["attributes"]["COLOR_0"] = add(srgb_to_linear(colors).astype(np.float32), "VEC3", 5126)
    asset = {"version": "2.0", "generator": GENERATOR_Y_UP, **({} if y_up else {"extras": Z_UP_MARK})}
    doc = {"asset": asset, "scene": 0,
           "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "surface"}],
           "meshes": [{"primitives": [prim], "name": "surface"}]}
    if T > 1:
        prim["targets"] = [{"POSITION": add(V[t] - V[0], "VEC3", 5126, True)} for t in range(1, T)]
        doc["meshes"][0]["weights"] = [0.0] * (T - 1)
        times = add((np.arange(T) / float(fps)).astype(np.float32), "SCALAR", 5126, True)
        W = np.zeros((T, T - 1), np.float32)
        W[np.arange(1, T), np.arange(T - 1)] = 1.0
        weights = add(W.reshape(-1), "SCALAR", 5126)
        doc["animations"] = [{"name": "frames", "samplers": [{"input": times, "output": weights,
                                                                "interpolation": "LINEAR"}],
                              "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}]
    blob.extend(b"\0" * (-len(blob) % 4))
    doc["buffers"] = [{"byteLength": len(blob)}]
    doc["bufferViews"], doc["accessors"] = views, accessors
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(blob), 0x004E4942) + bytes(blob)
    path = Path(path)
    with atomic_path(path, suffix=path.suffix) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
            fh.flush()
            os.fsync(fh.fileno())
