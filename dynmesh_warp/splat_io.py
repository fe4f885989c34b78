"""Read and write 3D Gaussian Splatting ``.ply`` files (binary little-endian).

Layout of the standard 3DGS file (Kerbl et al. 2023, written by ``plyfile``): one ``vertex``
element, one float32 property per column, in this order::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(K-1)  opacity  scale_0..2  rot_0..3

Values are stored *pre-activation*: ``scale_*`` is log(std dev), ``opacity`` is logit(alpha),
``rot_*`` is an unnormalized quaternion (w, x, y, z), ``f_dc``/``f_rest`` are spherical-harmonic
coefficients (``f_rest`` grouped by colour channel: K/3 per channel). The activations are
:func:`activate_scale` (exp), :func:`activate_opacity` (sigmoid), :func:`activate_rotation`
(normalize) and :func:`sh_dc_to_rgb` (0.5 + C0 * f_dc, clamped at 0 only, as 3DGS: a colour may
exceed 1; the image is clipped where it is written).

The reader keeps the property order, types and comments, so ``write_splat_ply(read_splat_ply(p))``
reproduces a file written by this module (or by plyfile) byte for byte.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .mesh_formats import file_problem
from .outputs import atomic_write_bytes

__all__ = [
    "SplatPlyError",
    "SplatCloud",
    "read_splat_ply",
    "write_splat_ply",
    "SH_C0",
    "OPACITY_EPS",
    "F_REST_COUNTS",
    "activate_scale",
    "activate_opacity",
    "activate_rotation",
    "sh_dc_to_rgb",
    "rgb_to_sh_dc",
    "rotate_sh",
    "inverse_sigmoid",
]

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi))
#: SH degrees a 3DGS file holds, and their f_rest counts 3 ((d + 1)^2 - 1) for d = 0..3: any other
#: count fits no degree (30 was read as degree 2 before)
MAX_SH_DEGREE = 3
F_REST_COUNTS = tuple(3 * ((d + 1) ** 2 - 1) for d in range(MAX_SH_DEGREE + 1))
#: activated opacities exactly 0 or 1 (no finite logit) are stored as the nearest float32
#: opacities that are not: 2^-24 and 1 - 2^-24 (logits -16.6 / +16.6); ``from_activated``
OPACITY_EPS = 2.0 ** -24

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}
_NP_TO_PLY = {"i1": "char", "u1": "uchar", "<i2": "short", "<u2": "ushort", "<i4": "int", "<u4": "uint",
              "<f4": "float", "<f8": "double"}
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


class SplatPlyError(ValueError):
    """A 3DGS .ply file is malformed or lacks a required property; the message names the file."""


def activate_scale(log_scale):
    """Std devs [m] from stored log-scales."""
    return np.exp(log_scale)


def inverse_sigmoid(p):
    p = np.asarray(p, np.float64)
    return np.log(p / (1.0 - p))


def activate_opacity(logit):
    """Opacity in (0, 1) from the stored logit."""
    return 1.0 / (1.0 + np.exp(-np.asarray(logit, np.float64)))


def activate_rotation(q_wxyz):
    """Unit quaternions (w, x, y, z) from stored unnormalized ones; a zero quaternion -> identity."""
    q = np.asarray(q_wxyz, np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    ident = np.zeros_like(q)
    ident[..., 0] = 1.0
    return np.where(n > 0, q / np.where(n > 0, n, 1.0), ident)


_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
          1.445305721320277, -0.5900435899266435)


def _sh_rest_basis(d: np.ndarray, degree: int) -> np.ndarray:
    """The 3DGS reference code's SH basis of degrees 1..``degree`` (its order and signs: ``eval_sh``)
    at unit directions d (..., 3): (..., (degree + 1)^2 - 1)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        out += [_SH_C2[0] * x * y, _SH_C2[1] * y * z, _SH_C2[2] * (2 * zz - xx - yy), _SH_C2[3] * x * z,
                _SH_C2[4] * (xx - yy)]
        if degree > 2:
            out += [_SH_C3[0] * y * (3 * xx - yy), _SH_C3[1] * x * y * z, _SH_C3[2] * y * (4 * zz - xx - yy),
                    _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _SH_C3[4] * x * (4 * zz - xx - yy),
                    _SH_C3[5] * z * (xx - yy), _SH_C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, axis=-1)


#: directions the SH rotation samples (a Fibonacci sphere; any set on which each band's basis has
#: full rank gives the same, exact, rotation)
_SH_SAMPLES = 24
#: Gaussians per chunk of :func:`rotate_sh` (its (chunk, samples, coefficients) float64 buffers)
_SH_CHUNK = 16384


def rotate_sh(f_rest, rotations) -> np.ndarray:
    """3DGS ``f_rest`` (G, 3K) (channel-major, K = (d + 1)^2 - 1 a channel, degrees 1..3) of
    Gaussians turned by ``rotations`` (G, 3, 3) or (3, 3), world: the coefficients whose colour seen
    from direction v is the original's seen from R^T v, so the view-dependent colour turns with the
    Gaussian. Each band l is one (2l + 1)-square matrix a Gaussian: with Y(R^T v) = D Y(v) for the
    band's basis Y, the new coefficients are D^T f. D^T is solved exactly from the basis at fixed
    sample directions (least squares on a full-rank system, no approximation)."""
    f = np.asarray(f_rest, np.float64)
    G, n = f.shape
    if n == 0 or G == 0:
        return np.asarray(f_rest, np.float32).copy()
    if n not in F_REST_COUNTS:
        raise ValueError(f"rotate_sh: {n} f_rest coefficients fit no SH degree (one of {F_REST_COUNTS[1:]})")
    degree = F_REST_COUNTS.index(n)
    K = n // 3
    R = np.broadcast_to(np.asarray(rotations, np.float64), (G, 3, 3))
    i = np.arange(_SH_SAMPLES) + 0.5
    z = 1.0 - 2.0 * i / _SH_SAMPLES
    phi = np.pi * (1.0 + 5.0 ** 0.5) * i
    S = np.stack([np.sqrt(1.0 - z * z) * np.cos(phi), np.sqrt(1.0 - z * z) * np.sin(phi), z], axis=1)
    YS = _sh_rest_basis(S, degree)
    bands = [np.arange(b * b - 1, (b + 1) ** 2 - 1) for b in range(1, degree + 1)]
    pinv = [np.linalg.pinv(YS[:, b]) for b in bands]
    coef = f.reshape(G, 3, K)
    out = np.empty_like(coef)
    for lo in range(0, G, _SH_CHUNK):
        r = R[lo:lo + _SH_CHUNK]
        Yr = _sh_rest_basis(np.einsum("gji,nj->gni", r, S), degree)  # Y(R^T s) (chunk, samples, K)
        for b, P in zip(bands, pinv):
            Dt = np.einsum("in,gnj->gij", P, Yr[:, :, b])  # D^T a Gaussian
            out[lo:lo + _SH_CHUNK][:, :, b] = np.einsum("gij,gcj->gci", Dt, coef[lo:lo + _SH_CHUNK][:, :, b])
    return out.reshape(G, n).astype(np.float32)


def sh_dc_to_rgb(f_dc, clamp: bool = True):
    """Base colour from the degree-0 SH coefficient: 0.5 + C0 f_dc, clamped at 0 only (as 3DGS's
    ``clamp_min(..., 0)``: a bright splat's colour exceeds 1; the composited image is clipped to
    [0, 1] where it is written). ``clamp=False``: the linear value, which keeps f_dc (a binding
    holds it, so an export writes back what was read)."""
    rgb = 0.5 + SH_C0 * np.asarray(f_dc, np.float64)
    return np.maximum(rgb, 0.0) if clamp else rgb


def rgb_to_sh_dc(rgb):
    return (np.asarray(rgb, np.float64) - 0.5) / SH_C0


@dataclass
class SplatCloud:
    """A 3DGS point cloud: the raw vertex table (a NumPy structured array, file order) + comments.

    Accessors return the stored (pre-activation) columns; the ``*_activated`` ones apply the
    activations. G = number of Gaussians.
    """

    data: np.ndarray
    comments: list = field(default_factory=list)
    source: str = "<memory>"
    type_names: list | None = None  # PLY type word per property as read ("float" / "float32" ...)

    def __post_init__(self):
        names = self.data.dtype.names or ()
        missing = [n for n in _REQUIRED if n not in names]
        if missing:
            raise SplatPlyError(f"{self.source}: not a 3D Gaussian Splatting file, missing properties {missing}")
        k = len(self._f_rest_names())
        if k not in F_REST_COUNTS:
            raise SplatPlyError(f"{self.source}: {k} f_rest properties fit no SH degree (degree d has "
                                f"3 ((d + 1)^2 - 1): {', '.join(map(str, F_REST_COUNTS))} for degrees 0..{MAX_SH_DEGREE})")

    def __len__(self):
        return int(self.data.shape[0])

    def _cols(self, names) -> np.ndarray:
        return np.stack([self.data[n] for n in names], axis=-1) if names else np.zeros((len(self), 0), np.float32)

    @property
    def positions(self) -> np.ndarray:
        """(G, 3) centres [m]."""
        return self._cols(["x", "y", "z"])

    @property
    def f_dc(self) -> np.ndarray:
        return self._cols(["f_dc_0", "f_dc_1", "f_dc_2"])

    def _f_rest_names(self) -> list:
        return sorted((n for n in self.data.dtype.names if n.startswith("f_rest_") and n[7:].isdecimal()),
                      key=lambda n: int(n[7:]))  # "f_rest_x" is some other property

    @property
    def f_rest(self) -> np.ndarray:
        """(G, K) higher-order SH coefficients (channel-major: K/3 for R, then G, then B)."""
        return self._cols(self._f_rest_names())

    @property
    def sh_degree(self) -> int:
        """The SH degree the f_rest count holds (K = 3 ((d + 1)^2 - 1); checked when made)."""
        return F_REST_COUNTS.index(len(self._f_rest_names()))

    @property
    def log_scales(self) -> np.ndarray:
        return self._cols(["scale_0", "scale_1", "scale_2"])

    @property
    def opacity_logits(self) -> np.ndarray:
        return np.asarray(self.data["opacity"])

    @property
    def rotations_raw(self) -> np.ndarray:
        """(G, 4) stored quaternions (w, x, y, z), unnormalized."""
        return self._cols(["rot_0", "rot_1", "rot_2", "rot_3"])

    # activated
    def scales(self) -> np.ndarray:
        """(G, 3) std devs [m]."""
        return activate_scale(self.log_scales.astype(np.float64))

    def opacities(self) -> np.ndarray:
        """(G,) opacity in (0, 1)."""
        return activate_opacity(self.opacity_logits)

    def rotations_wxyz(self) -> np.ndarray:
        """(G, 4) unit quaternions (w, x, y, z)."""
        return activate_rotation(self.rotations_raw)

    def rgb(self) -> np.ndarray:
        """(G, 3) view-independent base colour, >= 0 (above 1 for a bright splat)."""
        return sh_dc_to_rgb(self.f_dc)

    @classmethod
    def from_activated(cls, centers, scales, rotations_wxyz, rgb, opacities, f_rest=None, normals=None,
                       comments=None, opacity_logits=None) -> "SplatCloud":
        """Build a cloud in the standard property order from activated values (inverse
        activations applied: log of scales, logit of opacities, SH DC from rgb, which may exceed
        1). ``opacity_logits`` (G,): the stored logits to write as they are (a binding read from
        a file keeps them: sigmoid(20) is 1.0 in float32, whose logit is inf); else the logit of
        ``opacities``, those at exactly 0 or 1 taken as ``OPACITY_EPS`` / 1 - ``OPACITY_EPS``."""
        centers = np.asarray(centers, np.float32).reshape(-1, 3)
        G = centers.shape[0]
        scales = np.asarray(scales, np.float64).reshape(G, 3)
        if (scales <= 0).any():
            raise SplatPlyError("scales must be > 0 (they are stored as logarithms)")
        op = np.clip(np.asarray(opacities, np.float64).reshape(G), OPACITY_EPS, 1 - OPACITY_EPS)
        f_rest = np.zeros((G, 0), np.float32) if f_rest is None else np.asarray(f_rest, np.float32).reshape(G, -1)
        normals = np.zeros((G, 3), np.float32) if normals is None else np.asarray(normals, np.float32).reshape(G, 3)
        cols = {"x": centers[:, 0], "y": centers[:, 1], "z": centers[:, 2],
                "nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2]}
        dc = rgb_to_sh_dc(np.asarray(rgb, np.float64).reshape(G, 3))
        for i in range(3):
            cols[f"f_dc_{i}"] = dc[:, i]
        for i in range(f_rest.shape[1]):
            cols[f"f_rest_{i}"] = f_rest[:, i]
        cols["opacity"] = inverse_sigmoid(op) if opacity_logits is None else np.asarray(opacity_logits).reshape(G)
        ls = np.log(scales)
        for i in range(3):
            cols[f"scale_{i}"] = ls[:, i]
        q = np.asarray(rotations_wxyz, np.float64).reshape(G, 4)
        for i in range(4):
            cols[f"rot_{i}"] = q[:, i]
        data = np.empty(G, dtype=[(k, "<f4") for k in cols])
        for k, v in cols.items():
            data[k] = v
        return cls(data, list(comments or []))


def _header_error(path, msg):
    return SplatPlyError(f"{path}: {msg}")


def read_splat_ply(path) -> SplatCloud:
    """Read a binary little-endian 3DGS ``.ply``. Raises :class:`SplatPlyError` (naming the file)
    for ASCII/big-endian files, list properties, extra elements, truncated data or missing
    3DGS properties; FileNotFoundError when absent or not a file (a folder, a broken link)."""
    path = Path(path)
    problem = file_problem(path)
    if problem is not None:  # "file not found", "a folder, not a file", a broken link
        raise FileNotFoundError(f"{path}: splat file: {problem}")
    raw = path.read_bytes()
    eol = b"\r\n" if raw.startswith(b"ply\r\n") else b"\n"  # a header written with Windows line
    # endings (a valid file, read as "not a PLY file" before: a new user's)
    end = raw.find(b"end_header" + eol)
    if not raw.startswith(b"ply" + eol) or end < 0:
        raise _header_error(path, "not a PLY file (no 'ply' magic or no 'end_header')")
    body = raw[end + len(b"end_header" + eol):]
    try:
        lines = raw[:end].decode("ascii").replace("\r\n", "\n").split("\n")[1:]
    except UnicodeDecodeError:
        raise _header_error(path, "PLY header is not ASCII") from None
    fmt, count, props, comments, element = None, None, [], [], None
    for ln in lines:
        parts = ln.split()
        if not parts:
            continue
        key = parts[0]
        if key == "format":
            fmt = parts[1] if len(parts) > 1 else ""
        elif key in ("comment", "obj_info"):
            comments.append(ln)
        elif key == "element":
            if element is not None:
                raise _header_error(path, f"unexpected second element {parts[1:]!r}: a 3DGS file has only 'vertex'")
            if len(parts) != 3 or parts[1] != "vertex":
                raise _header_error(path, f"expected 'element vertex N', got {ln!r}")
            element = "vertex"
            try:
                count = int(parts[2])
            except ValueError:
                raise _header_error(path, f"bad vertex count in {ln!r}") from None
            if count < 0:
                raise _header_error(path, f"negative vertex count in {ln!r}")
        elif key == "property":
            if element is None:
                raise _header_error(path, f"property before any element: {ln!r}")
            if len(parts) != 3 or parts[1] == "list":
                raise _header_error(path, f"unsupported property {ln!r} (only scalar properties)")
            if parts[1] not in _PLY_TYPES:
                raise _header_error(path, f"unknown property type {parts[1]!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]], parts[1]))
        else:
            raise _header_error(path, f"unexpected header line {ln!r}")
    if fmt != "binary_little_endian":
        raise _header_error(path, f"format {fmt!r} not supported: only binary_little_endian (3DGS standard)")
    if count is None:
        raise _header_error(path, "no 'element vertex' in header")
    names = [p[0] for p in props]
    if len(set(names)) != len(names):
        raise _header_error(path, "duplicate property names")
    dtype = np.dtype([(n, t) for n, t, _ in props])
    need = count * dtype.itemsize
    if len(body) != need:
        raise _header_error(path, f"data has {len(body)} bytes, header says {count} x {dtype.itemsize} = {need}")
    data = np.frombuffer(body, dtype=dtype, count=count).copy()
    return SplatCloud(data, comments, source=str(path), type_names=[p[2] for p in props])


def splat_ply_bytes(cloud: SplatCloud) -> bytes:
    """The file contents of ``cloud`` as binary little-endian PLY."""
    data = cloud.data
    le = np.dtype([(n, data.dtype[n].newbyteorder("<") if data.dtype[n].itemsize > 1 else data.dtype[n])
                   for n in data.dtype.names])
    type_names = cloud.type_names
    hdr = ["ply", "format binary_little_endian 1.0", *cloud.comments, f"element vertex {len(data)}"]
    for i, n in enumerate(le.names):
        t = type_names[i] if type_names and len(type_names) == len(le.names) else _NP_TO_PLY.get(le[n].str)
        if t is None:
            raise SplatPlyError(f"property {n!r}: dtype {le[n]} has no PLY type")
        hdr.append(f"property {t} {n}")
    hdr.append("end_header")
    return ("\n".join(hdr) + "\n").encode("ascii") + np.ascontiguousarray(data.astype(le, copy=False)).tobytes()


def write_splat_ply(path, cloud: SplatCloud) -> None:
    """Write ``cloud`` to ``path`` atomically (binary little-endian, property order kept)."""
    atomic_write_bytes(path, splat_ply_bytes(cloud))
