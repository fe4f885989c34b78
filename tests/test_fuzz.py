"""Property-based fuzzing of every reader (Hypothesis).

Readers: ``io.read_mesh`` (OBJ, OFF, PLY ascii / binary little- and big-endian),
``io.load_sequence`` (npz fixed / aliases / single frame / quads / packed varying layouts, folders
of frames, DG-Mesh folders), ``splat_io.read_splat_ply`` (3DGS .ply, plus the gate
``gaussians._check_splats`` that stands between it and the binding kernels) and
``config.load_scene_config`` (YAML scenes).

Inputs: valid files written from generated meshes / clouds / scenes, then mutated (bit flips,
truncation, deleted / duplicated / inserted bytes, tokens replaced by hostile values such as
``nan``, ``1e39``, ``-1``, ``99999999999999999999``), npz members mutated inside a well-formed zip,
arrays of every dtype and shape, and plain garbage.

Property, for every input: the reader returns a valid result (finite float32 vertices, int32
faces in range, positive finite fps; a cloud whose kernel inputs are finite; a scene whose numbers
are finite) or raises a ``ValueError`` (``MeshDataError``, ``SceneError``, ``SplatPlyError`` are
subclasses) whose message names the file or folder. Any other exception type fails, and so does a
reader that runs over ``HANG_S`` seconds (a SIGALRM raises a ``BaseException`` the readers cannot
swallow) or over the Hypothesis deadline.

Profiles (env ``DYNMESH_FUZZ``): ``ci`` (default; derandomized, so CI is reproducible, about
half a minute on 2 cores) and ``long`` (random, ``DYNMESH_FUZZ_EXAMPLES`` (3000) examples per unit,
failures kept in ``.hypothesis/`` and replayed first next time; ``python bench/fuzz_long.py``).
Crashes found and fixed: docs/testing.md.
"""

from __future__ import annotations

import io as _io
import math
import os
import shutil
import signal
import tempfile
import warnings
import zipfile
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path

try:
    import resource
except ImportError:  # not on Windows
    resource = None

import numpy as np
import pytest
import yaml

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, Phase, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

from dynmesh_warp.config import DEFAULT_SCENE, SceneConfig, load_scene_config  # noqa: E402
from dynmesh_warp.io import load_sequence, read_mesh  # noqa: E402
from dynmesh_warp.sequence import FixedTopologySequence, VaryingTopologySequence  # noqa: E402
from dynmesh_warp.splat_io import SplatCloud, read_splat_ply  # noqa: E402

# ------------------------------------------------------------------------------------ profiles

PROFILE = os.environ.get("DYNMESH_FUZZ", "ci")
_COMMON = dict(
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                           HealthCheck.filter_too_much],
    print_blob=True,
    # no "explain" phase: its line tracing slows a reader tenfold and would trip the hang guard
    phases=[Phase.explicit, Phase.reuse, Phase.generate, Phase.target, Phase.shrink],
)
# no deadline in CI: under two workers on two busy cores a deeply nested YAML took 4.35 s against
# 3 s (the hang guard, time_limit, still fails a reader that runs on)
settings.register_profile("fuzz_ci", max_examples=400, deadline=None,
                          derandomize=True, database=None, **_COMMON)
settings.register_profile("fuzz_long", max_examples=int(os.environ.get("DYNMESH_FUZZ_EXAMPLES", 3000)),
                          deadline=timedelta(seconds=5), **_COMMON)
if PROFILE not in ("ci", "long"):
    raise ValueError(f"DYNMESH_FUZZ must be 'ci' or 'long', got {PROFILE!r}")
BASE = settings.get_profile(f"fuzz_{PROFILE}")
HANG_S = 30.0  # one reader call longer than this is a hang (10 s was reached once under two workers on two busy cores)


def fuzz(scale: float = 1.0):
    """The profile's settings, with ``scale`` times its example count."""
    return settings(BASE, max_examples=max(1, int(BASE.max_examples * scale)))


# ------------------------------------------------------------------------------------ property


class ReaderHang(BaseException):
    """Raised by SIGALRM inside a reader; a BaseException so ``except Exception`` cannot hide it."""


MEMORY_B = 2 << 30  # a reader may map at most this much more address space (else MemoryError)


def _address_space() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


@contextmanager
def time_limit(seconds: float = HANG_S):
    """Fail a reader that runs over ``seconds`` (ReaderHang) or asks for more than MEMORY_B
    (MemoryError instead of the machine's OOM killer)."""
    def on_alarm(signum, frame):
        raise ReaderHang(f"reader still running after {seconds} s")

    if not hasattr(signal, "SIGALRM"):  # Windows: the Hypothesis deadline only
        yield
        return
    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    limits = None
    if resource is not None and os.path.exists("/proc/self/statm"):
        limits = resource.getrlimit(resource.RLIMIT_AS)
        cap = _address_space() + MEMORY_B
        if limits[1] == resource.RLIM_INFINITY or cap < limits[1]:
            resource.setrlimit(resource.RLIMIT_AS, (cap, limits[1]))
        else:
            limits = None
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        if limits is not None:
            resource.setrlimit(resource.RLIMIT_AS, limits)


def read_or_clear_error(call, *names):
    """``call()``'s result, or None when it raised a ValueError naming one of ``names``.

    Any other exception (and a hang) propagates and fails the test."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with time_limit():
            try:
                return call()
            except ValueError as e:
                msg = str(e)
                assert any(str(n) in msg for n in names), (
                    f"{type(e).__name__} does not name the file ({names}): {msg}")
                return None


def assert_valid_mesh(V, F):
    assert isinstance(V, np.ndarray) and V.dtype == np.float32, V.dtype
    assert V.ndim == 2 and V.shape[1] == 3 and V.shape[0] > 0, V.shape
    assert np.isfinite(V).all()
    assert isinstance(F, np.ndarray) and F.dtype == np.int32, F.dtype
    assert F.ndim == 2 and F.shape[1] == 3 and F.shape[0] > 0, F.shape
    assert F.min() >= 0 and F.max() < V.shape[0]


def assert_valid_sequence(seq):
    assert isinstance(seq, (FixedTopologySequence, VaryingTopologySequence)), type(seq)
    assert math.isfinite(seq.fps) and seq.fps > 0
    assert seq.num_frames >= 1
    if isinstance(seq, FixedTopologySequence):
        assert seq.V.dtype == np.float32 and seq.V.ndim == 3 and seq.V.shape[2] == 3
        assert np.isfinite(seq.V).all()
        assert_valid_mesh(seq.V[0], seq.F)
    else:
        for V, F in seq.frames:
            assert_valid_mesh(V, F)


@contextmanager
def scratch():
    d = Path(tempfile.mkdtemp(prefix="dynmesh-fuzz-"))
    try:
        yield d
    finally:
        shutil.rmtree(d, ignore_errors=True)


# ------------------------------------------------------------------------------------ mutations

HOSTILE = [b"nan", b"-nan", b"inf", b"-inf", b"1e39", b"-1e39", b"1e400", b"1e-400", b"-1", b"0",
           b"-0", b"1", b"2", b"3", b"4", b"255", b"65536", b"2147483648", b"4294967296",
           b"99999999999999999999", b"-2147483649", b"1.5", b"0x10", b"1_0", b"", b" ", b"\n",
           b"\x00", b"\xff\xfe", b"//", b"/", b"#", b"x", b"end_header", b"ply", b"OFF",
           b"element vertex 1000000000", b"property list uchar int vertex_indices",
           b"format ascii 1.0", b"f", b"v", b"\xc3\xa9"]

mutation = st.tuples(
    st.sampled_from(["flip", "truncate", "delete", "insert", "token", "dup_line", "swap_lines"]),
    st.integers(0, 1 << 20), st.integers(0, 1 << 20),
    st.one_of(st.sampled_from(HOSTILE), st.binary(max_size=6)),
)


def mutate(data: bytes, muts) -> bytes:
    """Apply mutations (kind, a, b, payload) deterministically to ``data``."""
    for kind, a, b, payload in muts:
        n = len(data)
        if kind == "flip" and n:
            i = a % n
            data = data[:i] + bytes([data[i] ^ (1 << (b % 8))]) + data[i + 1:]
        elif kind == "truncate":
            data = data[:a % (n + 1)]
        elif kind == "delete" and n:
            i = a % n
            data = data[:i] + data[i + 1 + b % 16:]
        elif kind == "insert":
            i = a % (n + 1)
            data = data[:i] + payload + data[i:]
        elif kind == "token":
            toks = data.split(b" ")
            if len(toks) > 1:
                toks[a % len(toks)] = payload
                data = b" ".join(toks)
            else:
                lines = data.split(b"\n")
                lines[a % len(lines)] = payload
                data = b"\n".join(lines)
        elif kind in ("dup_line", "swap_lines"):
            lines = data.split(b"\n")
            i, j = a % len(lines), b % len(lines)
            if kind == "dup_line":
                lines.insert(j, lines[i])
            else:
                lines[i], lines[j] = lines[j], lines[i]
            data = b"\n".join(lines)
    return data


mutations = st.lists(mutation, min_size=0, max_size=4)

# ------------------------------------------------------------------------------------ meshes

coord = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False, width=32)


@st.composite
def meshes(draw, max_n: int = 10):
    """A small valid triangle mesh (V float64 (N,3), F int64 (M,3)); some faces degenerate."""
    n = draw(st.integers(3, max_n))
    V = draw(hnp.arrays(np.float32, (n, 3), elements=coord)).astype(np.float64)
    m = draw(st.integers(1, 8))
    F = draw(hnp.arrays(np.int64, (m, 3), elements=st.integers(0, n - 1)))
    return V, F


def obj_bytes(V, F, style) -> bytes:
    out = ["# fuzz\n", "o thing\n"]
    for i, v in enumerate(V):
        out.append("v %r %r %r%s\n" % (*map(float, v), " 1.0" if style == "w" else ""))
        if style == "extras":
            out.append("vt 0.5 0.5\nvn 0 0 1\n")
    n = len(V)
    for f in F:
        if style == "slash":
            out.append("f " + " ".join(f"{i + 1}/{i + 1}/{i + 1}" for i in f) + "\n")
        elif style == "negative":
            out.append("f " + " ".join(str(i - n) for i in f) + "\n")
        elif style == "quad":
            out.append("f " + " ".join(str(i + 1) for i in (*f, f[0])) + "\n")
        else:
            out.append("f " + " ".join(str(i + 1) for i in f) + "\n")
    return "".join(out).encode()


def off_bytes(V, F, style) -> bytes:
    head = f"OFF {len(V)} {len(F)} 0\n" if style == "oneline" else f"OFF\n# c\n{len(V)} {len(F)} 0\n"
    if style == "noheader":
        head = f"{len(V)} {len(F)} 0\n"
    extra = " 0.1 0.2 0.3" if style == "extra" else ""
    body = "".join("%r %r %r%s\n" % (*map(float, v), extra) for v in V)
    body += "".join("3 %d %d %d\n" % tuple(f) for f in F)
    return (head + body).encode()


_PLY_NP = {"float": "f4", "double": "f8", "int": "i4", "uint": "u4", "uchar": "u1", "ushort": "u2",
           "short": "i2", "char": "i1"}


def ply_bytes(V, F, fmt, vtype, ltype, itype, color) -> bytes:
    head = ["ply", f"format {fmt} 1.0", "comment fuzz", f"element vertex {len(V)}"]
    head += [f"property {vtype} {a}" for a in "xyz"]
    if color:
        head += ["property uchar red", "property uchar green", "property uchar blue"]
    head += [f"element face {len(F)}", f"property list {ltype} {itype} vertex_indices", "end_header"]
    text = ("\n".join(head) + "\n").encode()
    if fmt == "ascii":
        rows = ["%r %r %r%s" % (*map(float, v), " 1 2 3" if color else "") for v in V]
        rows += ["3 %d %d %d" % tuple(f) for f in F]
        return text + ("\n".join(rows) + "\n").encode()
    end = "<" if fmt == "binary_little_endian" else ">"
    vfields = [(a, end + _PLY_NP[vtype]) for a in "xyz"]
    if color:
        vfields += [(c, "u1") for c in ("r", "g", "b")]
    vert = np.zeros(len(V), vfields)
    for k, a in enumerate("xyz"):
        vert[a] = V[:, k]
    face = np.zeros(len(F), [("n", end + _PLY_NP[ltype]), ("i", end + _PLY_NP[itype], (3,))])
    face["n"] = 3
    face["i"] = F
    return text + vert.tobytes() + face.tobytes()


@st.composite
def mesh_files(draw):
    """(file name, bytes) of a valid OBJ / OFF / PLY file, possibly mutated, or garbage."""
    ext = draw(st.sampled_from([".obj", ".off", ".ply"]))
    if draw(st.integers(0, 9)) == 0:  # garbage, sometimes behind a plausible magic
        magic = {".obj": b"v ", ".off": b"OFF\n", ".ply": b"ply\n"}[ext]
        return "g" + ext, draw(st.sampled_from([b"", magic])) + draw(st.binary(max_size=300))
    V, F = draw(meshes())
    if ext == ".obj":
        data = obj_bytes(V, F, draw(st.sampled_from(["plain", "w", "extras", "slash", "negative", "quad"])))
    elif ext == ".off":
        data = off_bytes(V, F, draw(st.sampled_from(["plain", "oneline", "noheader", "extra"])))
    else:
        data = ply_bytes(V, F, draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"])),
                         draw(st.sampled_from(["float", "double"])),
                         draw(st.sampled_from(["uchar", "int", "ushort"])),
                         draw(st.sampled_from(["int", "uint", "short"])), draw(st.booleans()))
    return "mesh" + ext, mutate(data, draw(mutations))


@fuzz(3.0)
@given(mesh_files())
def test_fuzz_read_mesh(case):
    """OBJ / OFF / PLY (ascii, binary LE/BE): read_mesh and a one-file load_sequence."""
    name, data = case
    with scratch() as d:
        p = d / name
        p.write_bytes(data)
        out = read_or_clear_error(lambda: read_mesh(p), p)
        if out is not None:
            assert_valid_mesh(*out)
        seq = read_or_clear_error(lambda: load_sequence(p, kind="varying"), p)
        if seq is not None:
            assert_valid_sequence(seq)


# ------------------------------------------------------------------------------------ npz

HOSTILE_VALUES = [np.nan, np.inf, -np.inf, 1e39, -1e300, -1, 0, 2**31, 2**63 - 1, 1.5, 1e-45]
DTYPES = ["f2", "f4", "f8", "i1", "u1", "i2", "i4", "u4", "i8", "u8", "?", "c8", "U3", "S2"]


def _array_mutation(draw, a: np.ndarray) -> np.ndarray:
    """One semantic mutation of an array: dtype, shape, a hostile element, or emptiness."""
    kind = draw(st.sampled_from(["none", "dtype", "value", "reshape", "slice", "empty", "scalar",
                                 "transpose"]))
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        if kind == "dtype":
            try:
                return a.astype(draw(st.sampled_from(DTYPES)))
            except (ValueError, OverflowError, TypeError):
                return a
        if kind == "value" and a.size:
            b = a.copy()
            if draw(st.booleans()) and np.issubdtype(a.dtype, np.number):
                b = a.astype(np.float64)
            try:
                b.flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from(HOSTILE_VALUES))
            except (ValueError, OverflowError, TypeError):
                pass
            return b
        if kind == "reshape" and a.size:
            return a.reshape(draw(st.sampled_from([(-1,), (1, -1), (-1, 1), (1, 1, -1), (a.size, 1, 1)])))
        if kind == "slice" and a.ndim:
            return a[..., : draw(st.integers(0, 4))]
        if kind == "empty":
            return np.zeros((0,) + a.shape[1:], a.dtype)
        if kind == "scalar":
            return np.asarray(draw(st.sampled_from(HOSTILE_VALUES + ["abc", b"\xff"])))
        if kind == "transpose":
            return a.T
    return a


@st.composite
def npz_files(draw):
    """Bytes of an .npz: one of the layouts, arrays mutated, members' .npy bytes mutated inside a
    well-formed zip (correct CRCs), or the whole file mutated."""
    layout = draw(st.sampled_from(["fixed", "alias", "single", "quads", "packed", "empty", "bogus"]))
    V, F = draw(meshes())
    T = draw(st.integers(1, 3))
    Vs = np.stack([V + k for k in range(T)]).astype(np.float32)
    arrays = {}
    if layout in ("fixed", "alias", "single", "quads"):
        vk, fk = ("V", "F") if layout != "alias" else (draw(st.sampled_from(["vertices", "verts", "points"])),
                                                       draw(st.sampled_from(["faces", "triangles"])))
        arrays[vk] = Vs[0] if layout == "single" else Vs
        arrays[fk] = np.concatenate([F, F[:, :1]], axis=1) if layout == "quads" else F.astype(np.int32)
    elif layout == "packed":
        frames = [draw(meshes()) for _ in range(T)]
        arrays["V_packed"] = np.concatenate([v for v, _ in frames]).astype(np.float32)
        arrays["F_packed"] = np.concatenate([f for _, f in frames]).astype(np.int32)
        arrays["V_offsets"] = np.concatenate([[0], np.cumsum([len(v) for v, _ in frames])]).astype(np.int64)
        arrays["F_offsets"] = np.concatenate([[0], np.cumsum([len(f) for _, f in frames])]).astype(np.int64)
    elif layout == "bogus":
        arrays["x"] = Vs
    if draw(st.booleans()):
        fps = draw(st.sampled_from([24.0, 30, 0.0, -1.0, np.nan, np.inf, 1e39]))
        with np.errstate(over="ignore"):
            arrays["fps"] = np.asarray(fps, dtype=draw(st.sampled_from(["f4", "f8", "f2"])))
    if draw(st.booleans()):
        arrays["name"] = np.asarray(draw(st.sampled_from(["seq", "", "a/b", "é"])))
    for key in draw(st.lists(st.sampled_from(sorted(arrays) or ["V"]), max_size=2, unique=True)):
        if key in arrays:
            arrays[key] = _array_mutation(draw, np.asarray(arrays[key]))
    members = {}
    for key, a in arrays.items():
        buf = _io.BytesIO()
        np.lib.format.write_array(buf, np.asarray(a), allow_pickle=False)
        members[key + ".npy"] = buf.getvalue()
    if members and draw(st.booleans()):  # mutate one member's .npy bytes (header or data)
        key = draw(st.sampled_from(sorted(members)))
        members[key] = mutate(members[key], draw(st.lists(mutation, min_size=1, max_size=3)))
    zbuf = _io.BytesIO()
    comp = draw(st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]))
    with zipfile.ZipFile(zbuf, "w", compression=comp) as z:
        for key, b in members.items():
            z.writestr(key, b)
    data = zbuf.getvalue()
    if draw(st.integers(0, 4)) == 0:  # the zip itself: truncated, flipped ...
        data = mutate(data, draw(st.lists(mutation, min_size=1, max_size=2)))
    if draw(st.integers(0, 19)) == 0:
        data = draw(st.binary(max_size=200))
    return data


@fuzz(2.0)
@given(npz_files(), st.sampled_from(["auto", "fixed", "varying"]),
       st.sampled_from(["stored", "auto"]))
def test_fuzz_npz(data, kind, frame_order):
    """npz layouts (fixed, aliases, one frame, quads, packed varying) and broken ones."""
    with scratch() as d:
        p = d / "seq.npz"
        p.write_bytes(data)
        seq = read_or_clear_error(lambda: load_sequence(p, kind=kind, frame_order=frame_order), p)
        if seq is not None:
            assert_valid_sequence(seq)


# ------------------------------------------------------------------------------------ folders

frame_name = st.one_of(
    st.from_regex(r"[a-z_]{0,4}[0-9]{0,3}[a-z_]{0,2}", fullmatch=True),
    st.sampled_from(["frame_0", "frame_1", "frame_2", "frame_10", "frame_01", "horse9",
                     "frame_99999999999999999999", "frame_-1", "frame_1e3", ".hidden_3", "a 4"]),
)


@st.composite
def frame_folders(draw):
    """{relative path: bytes}: per-frame meshes (same topology, moved, or mutated), odd names,
    non-mesh files, DG-Mesh subfolders."""
    V, F = draw(meshes(max_n=6))
    ext = draw(st.sampled_from([".obj", ".off", ".ply"]))
    sub = draw(st.sampled_from(["", "", "dynamic_mesh/", "mesh_gt/"]))
    names = draw(st.lists(frame_name, min_size=0, max_size=5, unique=True))
    files = {}
    for k, stem in enumerate(names):
        e = ext if draw(st.integers(0, 5)) else draw(st.sampled_from([".obj", ".off", ".ply", ".txt", ".json", ""]))
        W = V + k * 0.1
        if e == ".obj":
            data = obj_bytes(W, F, "plain")
        elif e == ".off":
            data = off_bytes(W, F, "plain")
        elif e == ".ply":
            data = ply_bytes(W, F, "binary_little_endian", "float", "uchar", "int", False)
        else:
            data = b"{}"
        if draw(st.integers(0, 3)) == 0:
            if draw(st.booleans()):  # another topology
                W2, F2 = draw(meshes(max_n=6))
                data = {".obj": obj_bytes, ".off": off_bytes}.get(e, lambda a, b, s: data)(W2, F2, "plain")
            data = mutate(data, draw(mutations))
        if stem + e:
            files[sub + stem + e] = data
    return files


@fuzz(1.0)
@given(frame_folders(), st.sampled_from(["auto", "fixed", "varying"]))
def test_fuzz_folder(files, kind):
    """Folders of frames: names (no integer, duplicates, huge or far-apart indices), mixed
    extensions, hidden and non-mesh files, DG-Mesh subfolders, broken frames."""
    with scratch() as d:
        root = d / "scene"
        root.mkdir()
        for rel, data in files.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_bytes(data)
        seq = read_or_clear_error(lambda: load_sequence(root, kind=kind), root)
        if seq is not None:
            assert_valid_sequence(seq)


# ------------------------------------------------------------------------------------ 3DGS .ply

SPLAT_ORDER = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
SPLAT_TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
ODD_NAMES = ["f_rest_x", "f_rest_", "f_rest_-1", "f_rest_99999999999999999999", "x", "rot_0", "é"]


@st.composite
def splat_files(draw):
    """Bytes of a 3DGS .ply: the plyfile layout with random SH degree, property types, values
    (NaN, inf, beyond float32, log-scales whose exp overflows), renamed / retyped / dropped
    properties, mutated header lines and body bytes, or garbage."""
    if draw(st.integers(0, 14)) == 0:
        return draw(st.sampled_from([b"", b"ply\n", b"ply\nformat binary_little_endian 1.0\n"])) + draw(
            st.binary(max_size=200))
    G = draw(st.integers(0, 4))
    K = draw(st.sampled_from([0, 0, 3, 9, 45]))
    names = SPLAT_ORDER + [f"f_rest_{i}" for i in range(K)] + SPLAT_TAIL
    types = [draw(st.sampled_from(["float", "float", "float", "double"]))] * len(names)
    for _ in range(draw(st.integers(0, 2))):
        i = draw(st.integers(0, len(names) - 1))
        kind = draw(st.sampled_from(["type", "rename", "drop"]))
        if kind == "type":
            types[i] = draw(st.sampled_from(["double", "uchar", "char", "short", "int", "uint", "float64"]))
        elif kind == "rename":
            names[i] = draw(st.sampled_from(ODD_NAMES))
        elif len(names) > 1:
            del names[i], types[i]
    seen = set()
    if any(n in seen or seen.add(n) for n in names):  # duplicates: the header says so, no body
        body = b""
    else:
        data = np.zeros(G, [(n, _PLY_TYPES_NP[t]) for n, t in zip(names, types)])
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            for n in names:
                vals = draw(st.lists(st.floats(-5, 5, width=32), min_size=G, max_size=G))
                data[n] = np.round(vals) if data.dtype[n].kind in "iu" else vals
            if "rot_0" in data.dtype.names and G and draw(st.booleans()):
                data["rot_0"] = 1.0
            for _ in range(draw(st.integers(0, 2)) if G else 0):  # a hostile value here and there
                n = draw(st.sampled_from([n for n in names if n in SPLAT_TAIL + ["x"]] or names))
                v = draw(st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 89.0, 1e39, -1e39, 1e300]))
                data[n][draw(st.integers(0, G - 1))] = np.asarray(v).astype(data.dtype[n])  # ints: wrapped
        body = data.tobytes()
    head = (f"ply\nformat {draw(st.sampled_from(['binary_little_endian'] * 5 + ['ascii', 'binary_big_endian']))}"
            f" 1.0\ncomment fuzz\nelement vertex {G}\n"
            + "".join(f"property {t} {n}\n" for n, t in zip(names, types)) + "end_header\n").encode()
    head = mutate(head, draw(st.lists(mutation, max_size=1)))
    return head + mutate(body, draw(st.lists(mutation, max_size=2)))


_PLY_TYPES_NP = {"float": "<f4", "float64": "<f8", "double": "<f8", "uchar": "u1", "char": "i1",
                 "short": "<i2", "int": "<i4", "uint": "<u4"}


def assert_kernel_inputs_finite(cloud: SplatCloud):
    """What bind_splats hands to its kernels (float32 centres, unit quaternions, exp'd scales)
    and to the renderer (colour, opacity) is finite once _check_splats has passed."""
    with np.errstate(all="ignore"):
        assert np.isfinite(cloud.positions.astype(np.float32)).all()
        assert np.isfinite(cloud.rotations_wxyz().astype(np.float32)).all()
        assert np.isfinite(cloud.scales().astype(np.float32)).all()
        assert np.isfinite(cloud.rgb()).all() and np.isfinite(cloud.opacities()).all()


@fuzz(2.0)
@given(splat_files())
def test_fuzz_splat_ply(data):
    """read_splat_ply, every accessor, and the check that gates the binding kernels."""
    from dynmesh_warp.gaussians import _check_splats

    with scratch() as d:
        p = d / "point_cloud.ply"
        p.write_bytes(data)
        cloud = read_or_clear_error(lambda: read_splat_ply(p), p)
        if cloud is None:
            return
        assert isinstance(cloud, SplatCloud)
        with np.errstate(all="ignore"):  # accessors of the raw columns never raise
            cloud.positions, cloud.f_dc, cloud.f_rest, cloud.sh_degree, cloud.log_scales
            cloud.opacity_logits, cloud.rotations_raw, cloud.rgb(), cloud.opacities()
        checked = read_or_clear_error(lambda: (_check_splats(cloud), True)[1], p)
        if checked and len(cloud):
            assert_kernel_inputs_finite(cloud)


# ------------------------------------------------------------------------------------ YAML scenes

yaml_leaf = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20),
                      st.floats(allow_nan=True, allow_infinity=True),
                      st.sampled_from(["", "auto", "builtin:wave_bowl", "builtin:nope", "loop", "~nobody_x/y",
                                       "x" * 300, "a\x00b", "é", "1e400", ".nan", "missing.npz"]),
                      st.text(max_size=8))
yaml_value = st.recursive(yaml_leaf, lambda c: st.one_of(st.lists(c, max_size=4),
                                                         st.dictionaries(st.text(max_size=6), c, max_size=3)),
                          max_leaves=8)
path_value = st.sampled_from(["~nobody_x/y.npz", "x" * 300, "/" + "y" * 5000, "a\x00b", "missing.npz", ".",
                              "..", "/", "/dev/null", "scene.yaml", "builtin:", "" ])
SCENE_KEYS = [("name",), ("device",), ("surface",), ("surface", "source"), ("surface", "fps"),
              ("surface", "scale"), ("surface", "translate"), ("surface", "params"), ("surface", "conversion"),
              ("surface", "conversion", "template"), ("spheres",), ("spheres", 0), ("spheres", 0, "position"),
              ("spheres", 0, "radius"), ("spheres", "count"), ("physics",), ("physics", "dt"),
              ("physics", "gravity"), ("physics", "ground"), ("physics", "substeps"), ("physics", "friction"),
              ("run",), ("run", "duration"), ("run", "steps"), ("gaussians",), ("gaussians", "splats"),
              ("gaussians", "count"), ("newton",), ("newton", "bodies"), ("newton", "bodies", 0, "half_extents"),
              ("newton", "bodies", 0, "file"), ("bogus",)]


def _scene_seed():
    return [
        dict(DEFAULT_SCENE),
        {"name": "list", "surface": {"source": "builtin:wave_bowl", "fps": 24, "scale": 1.0,
                                     "translate": [0, 0, 0]},
         "spheres": [{"position": [0.1, 0.0, 0.6], "radius": 0.05}],
         "physics": {"gravity": [0, 0, -9.81], "ground": "auto"}, "run": {"steps": 10}},
        {"name": "newton", "surface": {"source": "builtin:wave_bowl"}, "spheres": [],
         "newton": {"bodies": [{"type": "box", "position": [0, 0, 1], "half_extents": [0.1, 0.1, 0.1]}]}},
    ]


def _set_path(doc, path, value):
    cur = doc
    for k in path[:-1]:
        nxt = cur[k] if isinstance(cur, dict) and k in cur else (
            cur[k] if isinstance(cur, list) and isinstance(k, int) and k < len(cur) else None)
        if not isinstance(nxt, (dict, list)):
            nxt = [{}] if isinstance(k, str) and isinstance(path[path.index(k) + 1], int) else {}
            if isinstance(cur, dict):
                cur[k] = nxt
            elif isinstance(cur, list) and isinstance(k, int) and k < len(cur):
                cur[k] = nxt
            else:
                return
        cur = nxt
    last = path[-1]
    if isinstance(cur, dict):
        cur[last] = value
    elif isinstance(cur, list) and isinstance(last, int) and last < len(cur):
        cur[last] = value


@st.composite
def scene_texts(draw):
    """YAML text: a valid scene with fields replaced by hostile values (NaN, inf, huge ints,
    NUL bytes, overlong or ~user paths, wrong types), then text mutations; or garbage YAML
    (deep nesting, anchors, tags, tabs, non-UTF-8)."""
    choice = draw(st.integers(0, 9))
    if choice == 0:
        return draw(st.sampled_from([
            b"[" * 5000 + b"]" * 5000, b"a: " + b"{b: " * 3000 + b"1" + b"}" * 3000,
            b"a: &a [1, 2]\nb: &b [*a, *a, *a, *a]\nc: [*b, *b, *b, *b]\nspheres: *c\n",
            b"!!python/object:os.system {}", b"name: !!binary aGVsbG8=", b"? [a, b]\n: 1\n",
            b"\tname: x", b"\xff\xfe\x00", b"--- 1\n--- 2\n", b"name: [", b"%YAML 9.9\n---\n{}",
            b"spheres: !!set {a, b}", b"physics: {dt: !!timestamp 2001-12-14}", b"",
        ]))
    if choice == 1:
        return draw(st.binary(max_size=200))
    doc = draw(st.sampled_from(_scene_seed()))
    doc = yaml.safe_load(yaml.safe_dump(doc))  # a deep copy
    for path in draw(st.lists(st.sampled_from(SCENE_KEYS), max_size=3)):
        hostile_path = path[-1] in ("source", "template", "splats", "file") and draw(st.booleans())
        _set_path(doc, path, draw(path_value if hostile_path else yaml_value))
    text = yaml.safe_dump(doc, allow_unicode=draw(st.booleans())).encode()
    return mutate(text, draw(st.lists(mutation, max_size=2)))


def _finite_numbers(obj, path=()):
    """Paths of non-finite floats in a dumped scene, outside the free-form keyword dicts."""
    if isinstance(obj, dict):
        return [p for k, v in obj.items() if k not in ("params", "options", "solver_options")
                for p in _finite_numbers(v, path + (k,))]
    if isinstance(obj, (list, tuple)):
        return [p for i, v in enumerate(obj) for p in _finite_numbers(v, path + (i,))]
    if isinstance(obj, float) and not math.isfinite(obj):
        return [path]
    return []


@fuzz(3.0)
@given(scene_texts())
def test_fuzz_scene_yaml(text):
    """load_scene_config: a SceneConfig whose numbers are finite, or a SceneError naming the file."""
    with scratch() as d:
        p = d / "scene.yaml"
        p.write_bytes(text)
        cfg = read_or_clear_error(lambda: load_scene_config(p), p)
        if cfg is not None:
            assert isinstance(cfg, SceneConfig)
            assert _finite_numbers(cfg.model_dump()) == []


@fuzz(1.0)
@given(st.integers(1, 4).flatmap(lambda G: st.tuples(
    st.sampled_from(["<f4", "<f8"]),
    st.lists(st.lists(st.floats(width=64), min_size=G, max_size=G), min_size=len(SPLAT_ORDER + SPLAT_TAIL),
             max_size=len(SPLAT_ORDER + SPLAT_TAIL)))))
def test_fuzz_splat_values(case):
    """Any float in any column of a well-formed float / double 3DGS file: the cloud either fails
    _check_splats naming the file, or every kernel input is finite."""
    from dynmesh_warp.gaussians import _check_splats

    dtype, cols = case
    names = SPLAT_ORDER + SPLAT_TAIL
    data = np.zeros(len(cols[0]), [(n, dtype) for n in names])
    with np.errstate(all="ignore"):
        for n, c in zip(names, cols):
            data[n] = c
    with scratch() as d:
        p = d / "point_cloud.ply"
        from dynmesh_warp.splat_io import write_splat_ply

        write_splat_ply(p, SplatCloud(data))
        cloud = read_or_clear_error(lambda: read_splat_ply(p), p)
        assert cloud is not None
        if read_or_clear_error(lambda: (_check_splats(cloud), True)[1], p):
            assert_kernel_inputs_finite(cloud)


# ------------------------------------------------------------------------------------ found by fuzzing
# Each input below crashed a reader (or let a non-finite value through) before its fix; the table
# in docs/testing.md lists them.


@pytest.mark.parametrize("name, text", [
    ("big.obj", "v 1e39 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n"),
    ("big.off", "OFF\n3 1 0\n0 0 -1e39\n0 1 0\n0 0 1\n3 0 1 2\n"),
    ("big.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\nproperty double y\n"
                "property double z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                "0 0 0\n1e300 0 0\n0 1 0\n3 0 1 2\n"),
])
def test_found_coordinates_beyond_float32_are_refused(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(ValueError, match=f"{name}: 1 vertices have NaN/inf coordinates or ones beyond 1e\\+09"):
        read_mesh(p)


def test_npz_vertex_array_of_a_wrong_shape_is_named_as_stored(tmp_path):
    """A (T, N*3) vertex array: the message gives the file's own shape, not a reshaped one."""
    np.savez(tmp_path / "flat.npz", V=np.zeros((4, 486), np.float32), F=np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match=r"flat\.npz: array 'V' has shape \(4, 486\); expected \(T, N, 3\)"):
        load_sequence(tmp_path / "flat.npz")


@pytest.mark.parametrize("scale", [1e30, 1e10])
def test_huge_finite_coordinates_are_refused_at_load(tmp_path, scale):
    """Finite float32 coordinates far beyond any unit a mesh is in (1e30 crashed the step with an
    OverflowError; squared lengths overflow float32) are refused where the data enters, naming
    the file and the frame; 1e9 and below load."""
    V = np.zeros((2, 3, 3), np.float32)
    V[:, 1, 0], V[:, 2, 1] = 1, 1
    np.savez(tmp_path / "ok.npz", V=V * np.float32(1e9), F=np.array([[0, 1, 2]]))
    assert load_sequence(tmp_path / "ok.npz").num_frames == 2
    W = V.copy()
    W[1] *= np.float32(scale)
    np.savez(tmp_path / "s.npz", V=W, F=np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match=r"s\.npz, frame 1: 2 vertices have NaN/inf coordinates or ones beyond 1e\+09"):
        load_sequence(tmp_path / "s.npz")
    with pytest.raises(ValueError, match=r"frame 1: 2 vertices .* wrong units or garbage data"):
        FixedTopologySequence(W, np.array([[0, 1, 2]]))


def test_found_npz_beyond_float32_names_the_frame(tmp_path):
    V = np.zeros((2, 3, 3))
    V[:, 1, 0], V[:, 2, 1] = 1, 1
    V[1, 2, 2] = 1e39
    np.savez(tmp_path / "s.npz", V=V, F=np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match=r"s\.npz, frame 1: 1 vertices have NaN/inf"):
        load_sequence(tmp_path / "s.npz")


def test_found_far_apart_frame_indices_do_not_exhaust_memory(tmp_path):
    for stem in ("frame_0", "frame_99999999999999999999"):
        (tmp_path / f"{stem}.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with time_limit(5.0), pytest.warns(UserWarning, match=r"missing 1, 2, .*, 10 \.\.\."):
        seq = load_sequence(tmp_path)
    assert seq.num_frames == 2


def test_found_odd_f_rest_name_is_another_property(tmp_path):
    names = SPLAT_ORDER + ["f_rest_x"] + [f"f_rest_{i}" for i in range(9)] + SPLAT_TAIL
    data = np.zeros(2, [(n, "<f4") for n in names])
    data["rot_0"] = 1
    from dynmesh_warp.splat_io import write_splat_ply

    write_splat_ply(tmp_path / "s.ply", SplatCloud(data))
    cloud = read_splat_ply(tmp_path / "s.ply")
    assert cloud.f_rest.shape == (2, 9) and cloud.sh_degree == 1  # a count that fits no degree is refused


@pytest.mark.parametrize("column, value, dtype, match", [
    ("x", 1e39, "<f8", "property 'x' is beyond float32's range"),
    ("scale_1", 89.0, "<f4", "log-scale .* overflows float32"),
    ("scale_1", 45.0, "<f4", "log-scale .* squared \\(the covariance\\) overflows float32"),  # exp fits, its square not
])
def test_found_splats_overflowing_float32_are_refused(column, value, dtype, match):
    from dynmesh_warp.gaussians import _check_splats
    from dynmesh_warp.splat_io import SplatPlyError

    data = np.zeros(3, [(n, dtype) for n in SPLAT_ORDER + SPLAT_TAIL])
    data["rot_0"] = 1
    data[column][1] = value
    with pytest.raises(SplatPlyError, match=f"s.ply: .*{match}"):
        _check_splats(SplatCloud(data, source="s.ply"))


@pytest.mark.parametrize("text, match", [
    (b"[" * 5000 + b"]" * 5000, "nested too deeply"),
    (b"a: " + b"{b: " * 3000 + b"1" + b"}" * 3000, "nested too deeply"),
    (b"surface: {source: ~nobody_x/seq.npz}", "cannot expand '~'"),
    (b"gaussians: {splats: ~nobody_x/s.ply}", "cannot expand '~'"),
    (b"surface: {source: " + b"x" * 300 + b".npz}", "File name too long"),
    (b"newton: {bodies: [{type: mjcf, file: " + b"y" * 300 + b"}]}", "File name too long"),
], ids=["deep-list", "deep-map", "tilde-source", "tilde-splats", "long-source", "long-body-file"])
def test_found_scene_yaml_crashes_are_scene_errors(tmp_path, text, match):
    from dynmesh_warp.config import SceneError

    p = tmp_path / "scene.yaml"
    p.write_bytes(text)
    with time_limit(), pytest.raises(SceneError, match=f"scene.yaml.*{match}"):
        load_scene_config(p)
