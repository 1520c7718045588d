"""Web-ready splat files beside the INRIA `splats.ply`: SPZ and a glTF 2.0 GLB with `KHR_gaussian_splatting`.

Both writers take Gaussian arrays in the `GaussianModel.to_numpy()` layout (means, wxyz quats, log_scales,
logit_opacities, sh0 (N,1,3), shN (N,K,3)) in the **world frame** (right-handed, +z up: the frame of the
outputs; `ply.to_world` maps the training frame there). Both formats are +Y up, so the Gaussians are turned by
`Y_UP_FROM_WORLD`, world (x, y, z) -> file (x, z, -y), a rotation of -90° about x: positions, orientations and
the SH bands (`rotate_gaussians`). Lengths stay in world units.

- **SPZ** (Niantic's format, written from its specification in github.com/nianticlabs/spz, README and
  `load-spz.cc`, version 3): a gzip stream of a 16-byte header (magic "NGSP", version, count, SH degree,
  fractional bits, flags) then, attribute by attribute, 24-bit fixed-point positions, uint8 opacities (sigmoid ·
  255, within 1..254 so that the decoder's logit stays finite), uint8 DC colours (dc · 0.15 · 255 + 127.5), uint8
  log-scales ((ln σ + 10) · 16), rotations as the smallest three components of the unit xyzw quaternion (2 + 3 ×
  10 bits) and uint8 SH coefficients (coefficient-major, channel-minor; round(128 x) + 128 snapped to 5 bits for
  degree 1 and 4 bits above, as the library's defaults). SPZ's own axes are RUB (x right, y up, z back:
  OpenGL/three.js), which the turned world frame is. Niantic's library has Python bindings but none installable
  from PyPI (built from its git repository), and the PyPI name `spz` is an unrelated Rust package that needs
  crates.io to build, so the format is written here and checked by independent readers in the tests
  (`@playcanvas/splat-transform`, which decodes SPZ with Adobe's build of Niantic's library, and Spark in
  Chromium).
- **GLB** with the ratified `KHR_gaussian_splatting` extension (Khronos glTF repository,
  extensions/2.0/Khronos/KHR_gaussian_splatting): one POINTS primitive with POSITION, COLOR_0 (the DC colour
  and opacity, the fallback for viewers without the extension), `KHR_gaussian_splatting:ROTATION` (unit xyzw),
  `:SCALE` (linear σ), `:OPACITY` (in [0, 1]) and `:SH_DEGREE_l_COEF_n` (raw coefficients, RGB), all float32;
  kernel `ellipse`, colour space `srgb_rec709_display` (3DGS colours are display-referred sRGB), projection
  `perspective`, sorting `cameraDistance`. No Python library writes this extension (gsplat 1.5.3 exports PLY
  and .splat only; trimesh has no point attributes beyond colour), so it is written here from the
  specification and read back in the tests by three.js's `GLTFGaussianSplatLoaderExtension`.
"""

from __future__ import annotations

import gzip
import json
import math
import struct
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from wonderverse.camera import Sim3

# world (+z up) -> +Y-up file axes: x stays, the file's up (+y) is the world's +z, the file's +z is the world's -y
Y_UP_FROM_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

SPZ_MAGIC = 0x5053474E  # "NGSP", little-endian
SPZ_VERSION = 3
SPZ_COLOR_SCALE = 0.15  # the library's DC scale: leaves room for base colours a little outside [0, 1]
SPZ_MAX_FRACTIONAL_BITS = 12  # the library's choice (~0.24 mm at metre scale)
# Opacity bytes written: the decoder's logit(byte / 255) is -inf at 0 and +inf at 255 (Niantic's library does not
# clamp; splat-transform 3.7 clamps to 1e-6 off the ends), so the ends are never written: opacity 1/255 .. 254/255.
SPZ_MIN_ALPHA, SPZ_MAX_ALPHA = 1, 254
SH_C0 = 0.28209479177387814
GLB_MAGIC = 0x46546C67  # "glTF"
GLB_JSON, GLB_BIN = 0x4E4F534A, 0x004E4942
FLOAT, UNSIGNED_BYTE, ARRAY_BUFFER, POINTS = 5126, 5121, 34962, 0
KHR = "KHR_gaussian_splatting"


class SpzParams(BaseModel):
    """How SPZ quantises the spherical harmonics (bits kept of 8; the library's defaults)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    sh1_bits: int = Field(5, ge=1, le=8, description="bits per degree-1 SH coefficient")
    sh_rest_bits: int = Field(4, ge=1, le=8, description="bits per degree-2 and degree-3 SH coefficient")


def _degree(shn: np.ndarray) -> int:
    degree = round(math.sqrt(shn.shape[1] + 1)) - 1
    if (degree + 1) ** 2 - 1 != shn.shape[1] or not 0 <= degree <= 3:
        raise ValueError(f"shN has {shn.shape[1]} coefficients per channel, not (d+1)^2 - 1 for d <= 3")
    return degree


def _checked(gaussians: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """float64 copies with the expected shapes; ValueError naming the first non-finite or misshapen array."""
    n = len(gaussians["means"])
    shapes = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "logit_opacities": (n,), "sh0": (n, 1, 3)}
    out = {}
    for name, shape in shapes.items():
        a = np.asarray(gaussians[name], np.float64)
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
        out[name] = a
    shn = np.asarray(gaussians["shN"], np.float64)
    out["shN"] = shn if shn.ndim == 3 and shn.shape[0] == n else shn.reshape(n, -1, 3)
    _degree(out["shN"])
    for name, a in out.items():
        if not np.isfinite(a).all():
            raise ValueError(f"{name} holds non-finite values: remove those Gaussians before export")
    return out


def rotate_gaussians(gaussians: dict[str, np.ndarray], R: np.ndarray) -> dict[str, np.ndarray]:
    """The Gaussians turned by the rotation R (3,3) about the origin: means R x, orientations q(R) q, SH bands
    rotated so that each Gaussian's colour seen from R d equals the old one seen from d; scales, opacities and
    the DC term unchanged. float64 arrays, the input layout."""
    from wonderverse.splats.ply import to_world

    # to_world inverts x_n = s R_n (x - c) + t; with s = 1, R_n = R^T, c = t = 0 that is x -> R x_n
    return to_world(gaussians, Sim3(1.0, np.asarray(R, np.float64).T, np.zeros(3)))


def unit_quats_xyzw(quats_wxyz: np.ndarray) -> np.ndarray:
    """Unit quaternions (N,4) in x, y, z, w order from the model's wxyz (a zero quaternion is the identity)."""
    q = np.asarray(quats_wxyz, np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 1e-12, q / np.maximum(norm, 1e-300), np.array([1.0, 0.0, 0.0, 0.0]))
    return q[:, [1, 2, 3, 0]]


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # no overflow for large |x|


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def spz_fractional_bits(means: np.ndarray) -> int:
    """Fractional bits of SPZ's 24-bit fixed-point positions: the library's 12 when the coordinates fit
    (|x| < 2048 units), fewer for larger scenes (ValueError beyond 2^23 units)."""
    reach = float(np.abs(means).max()) if means.size else 0.0
    for bits in range(SPZ_MAX_FRACTIONAL_BITS, -1, -1):
        if round(reach * (1 << bits)) < (1 << 23):
            return bits
    raise ValueError(f"coordinates up to {reach:g} units do not fit SPZ's 24-bit positions")


def _pack_smallest_three(q_xyzw: np.ndarray) -> np.ndarray:
    """SPZ v3 rotations (N,4) uint8: index of the largest |component| in the top 2 bits, then the other three
    (in order) as sign bit + 9-bit magnitude / (1/√2), the largest made positive (q and -q are one rotation)."""
    largest = np.argmax(np.abs(q_xyzw), axis=1)
    q = np.where(np.take_along_axis(q_xyzw, largest[:, None], 1) < 0, -q_xyzw, q_xyzw)
    comp = largest.astype(np.uint32)
    for i in range(4):
        others = largest != i
        neg = (q[:, i] < 0).astype(np.uint32)
        mag = np.minimum(np.floor(511.0 * np.abs(q[:, i]) / math.sqrt(0.5) + 0.5), 511).astype(np.uint32)
        comp = np.where(others, (comp << np.uint32(10)) | (neg << np.uint32(9)) | mag, comp)
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def _quantize_sh(x: np.ndarray, bits: int) -> np.ndarray:
    bucket = 1 << (8 - bits)
    q = np.round(x * 128.0) + 128.0
    q = np.floor((q + bucket // 2) / bucket) * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def write_spz(path: str | Path, gaussians: dict[str, np.ndarray], params: SpzParams | None = None) -> Path:
    """Write world-frame Gaussians (GaussianModel.to_numpy layout, +z up) as an SPZ v3 file in SPZ's RUB axes
    (+Y up: `Y_UP_FROM_WORLD`). Lossy as the format is: positions to 2^-12 units (fewer fractional bits past
    2048 units), log-scales to 1/16 within [-10, 5.94] (σ from 4.5e-5 to 380 units: clamped outside), opacity
    to 8 bits within 1..254 (finite when decoded: `SPZ_MAX_ALPHA`), DC colour to 8 bits, SH to `params`' bits.
    Returns the path."""
    params = params or SpzParams()
    g = rotate_gaussians(_checked(gaussians), Y_UP_FROM_WORLD)
    n, shn = len(g["means"]), g["shN"]
    degree = _degree(shn)
    bits = spz_fractional_bits(g["means"])
    fixed = np.round(g["means"] * (1 << bits)).astype(np.int64).reshape(-1)
    positions = np.stack([(fixed >> s) & 0xFF for s in (0, 8, 16)], axis=1).astype(np.uint8)  # two's complement
    # 1..254: the spec's decoder takes the logit of byte/255, infinite at 0 and 255 (Niantic's `invSigmoid`)
    alphas = np.clip(_u8(_sigmoid(g["logit_opacities"]) * 255.0), SPZ_MIN_ALPHA, SPZ_MAX_ALPHA)
    colors = _u8(g["sh0"].reshape(n, 3) * (SPZ_COLOR_SCALE * 255.0) + 0.5 * 255.0)
    scales = _u8((g["log_scales"] + 10.0) * 16.0)
    rotations = _pack_smallest_three(unit_quats_xyzw(g["quats"]))
    sh = np.zeros((n, shn.shape[1], 3), np.uint8)  # coefficient-major, channel-minor, as shN already is
    if degree:
        sh[:, :3] = _quantize_sh(shn[:, :3], params.sh1_bits)
        sh[:, 3:] = _quantize_sh(shn[:, 3:], params.sh_rest_bits)
    header = struct.pack("<IIIBBBB", SPZ_MAGIC, SPZ_VERSION, n, degree, bits, 0, 0)  # flags: not antialiased
    body = b"".join(a.tobytes() for a in (positions, alphas, colors, scales, rotations, sh))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(gzip.compress(header + body, compresslevel=9, mtime=0))
    return path


def read_spz(path: str | Path) -> dict[str, np.ndarray]:
    """Read an SPZ file (versions 2 and 3, gzip) back into GaussianModel.from_numpy arrays (float32) in the
    world frame (+z up): the inverse of `write_spz` up to its quantisation."""
    data = gzip.decompress(Path(path).read_bytes())
    magic, version, n, degree, bits, flags, _ = struct.unpack_from("<IIIBBBB", data)
    if magic != SPZ_MAGIC or version not in (2, 3) or flags & 0x2:
        raise ValueError(f"{path}: not an SPZ v2/v3 file without extensions (magic {magic:#x}, version {version})")
    k = (degree + 1) ** 2 - 1
    sizes = [n * 9, n, n * 3, n * 3, n * (4 if version == 3 else 3), n * k * 3]
    parts, offset = [], 16
    for size in sizes:
        parts.append(np.frombuffer(data, np.uint8, size, offset))
        offset += size
    pos, alpha, color, scale, rot, sh = parts
    b = pos.reshape(n * 3, 3).astype(np.int64)
    fixed = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = (fixed / float(1 << bits)).reshape(n, 3)
    if version == 3:
        comp = rot.reshape(n, 4).copy().view("<u4")[:, 0].astype(np.int64)
        largest = comp >> 30
        q = np.zeros((n, 4))
        for i in range(3, -1, -1):
            mag, neg = comp & 511, (comp >> 9) & 1
            value = math.sqrt(0.5) * mag / 511.0 * np.where(neg == 1, -1.0, 1.0)
            q[:, i] = np.where(largest != i, value, 0.0)
            comp = np.where(largest != i, comp >> 10, comp)
        rows = np.arange(n)
        q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(q * q, axis=1)))
    else:
        xyz = rot.reshape(n, 3) / 127.5 - 1.0
        q = np.concatenate([xyz, np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, axis=1)))[:, None]], axis=1)
    a = np.clip(alpha / 255.0, 1e-7, 1 - 1e-7)
    g = {
        "means": means,
        "quats": q[:, [3, 0, 1, 2]],
        "log_scales": scale.reshape(n, 3) / 16.0 - 10.0,
        "logit_opacities": np.log(a / (1.0 - a)),
        "sh0": ((color.reshape(n, 1, 3) / 255.0) - 0.5) / SPZ_COLOR_SCALE,
        "shN": (sh.reshape(n, k, 3).astype(np.float64) - 128.0) / 128.0,
    }
    g = rotate_gaussians(g, Y_UP_FROM_WORLD.T)
    return {name: np.ascontiguousarray(v, np.float32) for name, v in g.items()}


def write_splat_glb(path: str | Path, gaussians: dict[str, np.ndarray], name: str = "splats") -> Path:
    """Write world-frame Gaussians (GaussianModel.to_numpy layout, +z up) as a binary glTF 2.0 file with the
    `KHR_gaussian_splatting` extension, in glTF's +Y-up axes (`Y_UP_FROM_WORLD`), float32 throughout (no loss
    but float32 rounding). Returns the path."""
    g = rotate_gaussians(_checked(gaussians), Y_UP_FROM_WORLD)
    n, shn = len(g["means"]), g["shN"]
    degree = _degree(shn)
    dc_rgb = np.clip(g["sh0"].reshape(n, 3) * SH_C0 + 0.5, 0.0, 1.0)
    opacity = _sigmoid(g["logit_opacities"])
    columns: list[tuple[str, np.ndarray, str, dict]] = [
        ("POSITION", g["means"].astype(np.float32), "VEC3", {}),
        ("COLOR_0", _u8(np.concatenate([dc_rgb, opacity[:, None]], axis=1) * 255.0), "VEC4", {"normalized": True}),
        (f"{KHR}:ROTATION", unit_quats_xyzw(g["quats"]).astype(np.float32), "VEC4", {}),
        (f"{KHR}:SCALE", np.exp(g["log_scales"]).astype(np.float32), "VEC3", {}),
        (f"{KHR}:OPACITY", opacity.astype(np.float32), "SCALAR", {}),
        (f"{KHR}:SH_DEGREE_0_COEF_0", g["sh0"].reshape(n, 3).astype(np.float32), "VEC3", {}),
    ]
    for band in range(1, degree + 1):
        for coef in range(2 * band + 1):
            data = shn[:, band * band - 1 + coef, :].astype(np.float32)
            columns.append((f"{KHR}:SH_DEGREE_{band}_COEF_{coef}", data, "VEC3", {}))
    views, accessors, attributes, blobs, offset = [], [], {}, [], 0
    for i, (semantic, data, kind, extra) in enumerate(columns):
        raw = np.ascontiguousarray(data).tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(raw), "target": ARRAY_BUFFER})
        accessor = {"bufferView": i, "componentType": UNSIGNED_BYTE if data.dtype == np.uint8 else FLOAT}
        accessor |= {"count": n, "type": kind, **extra}
        if semantic == "POSITION" and n:  # required by the core specification
            accessor |= {"min": data.min(0).tolist(), "max": data.max(0).tolist()}
        accessors.append(accessor)
        attributes[semantic] = i
        blobs.append(raw + b"\0" * (-len(raw) % 4))
        offset += len(blobs[-1])
    binary = b"".join(blobs)
    extension = {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}
    extension |= {"projection": "perspective", "sortingMethod": "cameraDistance"}
    gltf = {
        "asset": {"version": "2.0", "generator": "WonderVerse (wonderverse.splats.web)"},
        "extensionsUsed": [KHR],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [
            {"name": name, "primitives": [{"attributes": attributes, "mode": POINTS, "extensions": {KHR: extension}}]}
        ],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": accessors,
    }
    if not n:  # glTF has no empty accessors: no Gaussians is a scene with nothing in it
        gltf = {"asset": gltf["asset"], "scene": 0, "scenes": [{"nodes": []}]}
        binary = b""
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + (8 + len(binary) if binary else 0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        f.write(struct.pack("<III", GLB_MAGIC, 2, total))
        f.write(struct.pack("<II", len(text), GLB_JSON) + text)
        if binary:
            f.write(struct.pack("<II", len(binary), GLB_BIN) + binary)
    return path


def read_splat_glb(path: str | Path) -> dict[str, np.ndarray]:
    """Read a `write_splat_glb` file (one KHR_gaussian_splatting primitive, float attributes) back into
    GaussianModel.from_numpy arrays (float32) in the world frame (+z up)."""
    data = Path(path).read_bytes()
    magic, _, _ = struct.unpack_from("<III", data)
    if magic != GLB_MAGIC:
        raise ValueError(f"{path}: not a GLB file")
    json_len, _ = struct.unpack_from("<II", data, 12)
    gltf = json.loads(data[20 : 20 + json_len])
    bin_start = 20 + json_len + 8
    if not gltf.get("meshes"):  # written from no Gaussians

        def z(shape: tuple[int, ...] | int) -> np.ndarray:
            return np.zeros(shape, np.float32)

        return {"means": z((0, 3)), "quats": z((0, 4)), "log_scales": z((0, 3)), "logit_opacities": z(0),
                "sh0": z((0, 1, 3)), "shN": z((0, 0, 3))}  # fmt: skip
    attributes = gltf["meshes"][0]["primitives"][0]["attributes"]

    def column(semantic: str) -> np.ndarray:
        acc = gltf["accessors"][attributes[semantic]]
        view = gltf["bufferViews"][acc["bufferView"]]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
        start = bin_start + view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        return np.frombuffer(data, np.float32, acc["count"] * width, start).reshape(acc["count"], width)

    n = gltf["accessors"][attributes["POSITION"]]["count"]
    degree = max((b for b in range(1, 4) if f"{KHR}:SH_DEGREE_{b}_COEF_0" in attributes), default=0)
    shn = [column(f"{KHR}:SH_DEGREE_{b}_COEF_{c}") for b in range(1, degree + 1) for c in range(2 * b + 1)]
    opacity = np.clip(column(f"{KHR}:OPACITY")[:, 0].astype(np.float64), 1e-12, 1 - 1e-12)
    g = {
        "means": column("POSITION"),
        "quats": column(f"{KHR}:ROTATION")[:, [3, 0, 1, 2]],
        "log_scales": np.log(column(f"{KHR}:SCALE").astype(np.float64)),
        "logit_opacities": np.log(opacity / (1.0 - opacity)),
        "sh0": column(f"{KHR}:SH_DEGREE_0_COEF_0").reshape(n, 1, 3),
        "shN": np.stack(shn, axis=1) if shn else np.zeros((n, 0, 3)),
    }
    g = rotate_gaussians(g, Y_UP_FROM_WORLD.T)
    return {name: np.ascontiguousarray(v, np.float32) for name, v in g.items()}
