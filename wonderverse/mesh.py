"""Meshes and point clouds from a trained scene: clean-up, PLY/GLB/points export (TSDF fusion: `wonderverse.tsdf`).

Inputs are plain arrays in the world frame: rgb (H,W,3) uint8 or float in [0,1]; depth (H,W) camera-space z
in world units, where +inf, NaN or <= 0 means "nothing here" (sky, background) and is never integrated, so
it neither adds surface nor carves free space; K (3,3) pixels with pixel centres at +0.5; W2C (4,4) OpenCV
axes. Outputs are `TriMesh` / `PointCloud` dataclasses of numpy arrays, so callers need not import Open3D.

Every length is a fraction of the scene extent the caller passes (`camera.scene_extent(w2c, depths)` gives
one: the diagonal of the camera centres' bounding box plus twice the median depth, i.e. the path plus the
typical distance to what the cameras look at), so one `MeshParams` serves a room and a valley:
voxel = voxel_frac * extent, truncation = trunc_voxels * voxel; depths up to max_depth_frac * extent are fused
at that voxel, farther ones (up to far_depth_frac * extent, or all) into a second volume with far_voxel_scale
times the voxel, since their depth is coarser anyway.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

if TYPE_CHECKING:
    from wonderverse.camera import Sim3

WORLD_UP = np.array([0.0, 0.0, 1.0])
# DC spherical-harmonic constant (the same as splats.model.SH_C0, repeated so this module does not load torch)
SH_C0 = 0.28209479177387814
# glTF is +Y up, the world is +Z up: (x, y, z) -> (x, z, -y), a proper rotation
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class MeshParams(BaseModel):
    """TSDF fusion, clean-up and point-cloud export. Lengths are fractions of the scene extent.

    max_depth_frac = 0.5 fuses depths up to about half the path plus the median depth at the full voxel size:
    farther surfaces have little parallax, and their depth is too coarse for it. They go to a second, coarser
    volume (`far_voxel_scale`), so the mesh covers everything the cameras see: against every world triangle a
    training camera sees, `benchmarks.enhancement` (outdoor, preview) F@1 % 0.11 near volume only, 0.30 both
    volumes, 0.30 one fine volume for all depths with 2.6x the triangles and 12x the fusion time. Interpolated
    extra views add nothing when every video frame is a training view; they fill gaps when the splats were
    trained on every Nth frame.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    voxel_frac: float = Field(1 / 256, gt=0, le=0.1, description="TSDF voxel edge / scene extent")
    trunc_voxels: float = Field(4.0, ge=1, le=64, description="SDF truncation distance in voxels")
    max_depth_frac: float = Field(0.5, gt=0, description="depths up to this fraction of the extent: the fine volume")
    far_depth_frac: float | None = Field(
        None, description="farther depths up to this fraction go to the coarse volume (None: all; max_depth_frac: off)"
    )
    far_voxel_scale: float = Field(2.0, ge=1, le=64, description="the coarse volume's voxel / the fine one's")
    extra_views_per_gap: int = Field(0, ge=0, le=16, description="views interpolated between consecutive cameras")
    keep_largest: int = Field(0, ge=0, description="keep only this many largest components (0: no limit)")
    min_component_frac: float = Field(
        0.0005, ge=0, lt=1, description="drop connected components with fewer triangles than this share of all"
    )
    target_triangles: int | None = Field(None, ge=4, description="quadric decimation to about this many triangles")
    points_min_opacity: float = Field(0.5, gt=0, lt=1, description="Gaussians at least this opaque go to points.ply")

    @model_validator(mode="after")
    def _far_beyond_near(self) -> MeshParams:
        if self.far_depth_frac is not None and self.far_depth_frac < self.max_depth_frac:
            raise ValueError(f"far_depth_frac {self.far_depth_frac} is below max_depth_frac {self.max_depth_frac}")
        return self

    @property
    def reach_frac(self) -> float:
        """Depth (fraction of the extent) up to which anything is fused: inf when every depth is."""
        return float("inf") if self.far_depth_frac is None else self.far_depth_frac


@dataclass
class TriMesh:
    """A triangle mesh: vertices (V,3) float64 world units, triangles (F,3) int32 (counter-clockwise seen
    from the side the cameras saw, as Open3D's marching cubes winds them), colors (V,3) float64 RGB in [0,1]."""

    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray


@dataclass
class PointCloud:
    """points (N,3) float64 world units, colors (N,3) float64 RGB in [0,1], normals (N,3) unit or None."""

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray | None = None


def fusion_cameras(w2c: np.ndarray, extra_per_gap: int) -> np.ndarray:
    """The cameras to fuse: the finite poses of `w2c` (N,4,4) in order, with `extra_per_gap` poses
    interpolated (slerp + straight centre line) between each consecutive pair; (M,4,4) float64."""
    from wonderverse.camera import interpolate_poses

    w2c = np.asarray(w2c, np.float64).reshape(-1, 4, 4)
    keys = w2c[np.isfinite(w2c).all(axis=(1, 2))]
    if extra_per_gap == 0 or len(keys) < 2:
        return keys
    times = np.linspace(0.0, len(keys) - 1.0, (len(keys) - 1) * (extra_per_gap + 1) + 1)
    cams = interpolate_poses(keys, np.arange(len(keys), dtype=np.float64), times, ease=False)
    # the frames bit for bit (a slerp at its end is not): their pose digests name the frames a fusion holds
    cams[:: extra_per_gap + 1] = keys
    return cams


def _to_o3d(mesh: TriMesh) -> Any:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(mesh.triangles, np.int32)),
    )
    if len(mesh.colors):
        m.vertex_colors = o3d.utility.Vector3dVector(np.asarray(mesh.colors, np.float64))
    return m


def _from_o3d(m: Any) -> TriMesh:
    v = np.asarray(m.vertices, np.float64).reshape(-1, 3)
    c = np.asarray(m.vertex_colors, np.float64).reshape(-1, 3)
    return TriMesh(
        vertices=v.copy(),
        triangles=np.asarray(m.triangles, np.int32).reshape(-1, 3).copy(),
        colors=np.clip(c, 0.0, 1.0) if len(c) == len(v) else np.full((len(v), 3), 0.5),
    )


def clean_mesh(mesh: TriMesh, params: MeshParams | None = None) -> TriMesh:
    """Merge duplicate vertices, drop degenerate triangles, keep the large connected components
    (`min_component_frac` of all triangles, and at most `keep_largest` of them), then decimate to
    `target_triangles` by quadric error (colours are carried along)."""
    p = params or MeshParams()
    if len(mesh.triangles) == 0:
        return mesh
    m = _to_o3d(mesh)
    m.remove_duplicated_vertices()
    m.remove_degenerate_triangles()
    m.remove_unreferenced_vertices()
    labels, counts, _ = m.cluster_connected_triangles()
    labels, counts = np.asarray(labels), np.asarray(counts)
    keep = counts >= p.min_component_frac * counts.sum()
    if p.keep_largest > 0:
        keep &= np.isin(np.arange(len(counts)), np.argsort(-counts, kind="stable")[: p.keep_largest])
    if not keep.all():
        m.remove_triangles_by_mask(~keep[labels])
        m.remove_unreferenced_vertices()
    if p.target_triangles is not None and len(m.triangles) > p.target_triangles:
        m = m.simplify_quadric_decimation(target_number_of_triangles=p.target_triangles)
        m.remove_degenerate_triangles()
        m.remove_unreferenced_vertices()
    return _from_o3d(m)


def gaussian_points(
    arrays: dict[str, np.ndarray], norm: Sim3, min_opacity: float = 0.5, toward: np.ndarray | None = None
) -> PointCloud:
    """Centres of the Gaussians with opacity >= `min_opacity`, mapped from the training frame back to the
    world (`norm.apply_inverse`, `norm` the training normalisation), coloured by their view-independent
    (DC) SH colour clipped to [0,1], with normals: each Gaussian's shortest axis (the direction it is
    flattest along, a surfel's normal) in the world, turned to face the nearest of the points `toward`
    (M,3) (the camera centres) when given. `arrays` is the splats step's layout (means (N,3), quats (N,4)
    wxyz, log_scales (N,3), logit_opacities (N,), sh0 (N,1,3), …)."""
    from wonderverse.camera import matrix_from_quat

    logit = np.asarray(arrays["logit_opacities"], np.float64).reshape(-1)
    keep = 1.0 / (1.0 + np.exp(-logit)) >= min_opacity
    means = np.asarray(arrays["means"], np.float64).reshape(-1, 3)[keep]
    sh0 = np.asarray(arrays["sh0"], np.float64).reshape(len(logit), -1, 3)[keep, 0]
    q = np.asarray(arrays["quats"], np.float64).reshape(-1, 4)[keep]
    qn = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(qn > 1e-12, q / np.maximum(qn, 1e-12), [1.0, 0.0, 0.0, 0.0])  # zero quaternion: identity
    axis = np.argmin(np.asarray(arrays["log_scales"], np.float64).reshape(-1, 3)[keep], axis=1)
    n_train = np.take_along_axis(matrix_from_quat(q), axis[:, None, None].repeat(3, 1), axis=2)[..., 0]
    normals = n_train @ norm.R  # directions back to the world: R^T n (the scale does not turn them)
    points = norm.apply_inverse(means)
    if toward is not None and len(toward) and len(points):
        from scipy.spatial import cKDTree

        nearest = np.asarray(toward, np.float64)[cKDTree(toward).query(points)[1]]
        normals = np.where(np.sum(normals * (nearest - points), axis=1, keepdims=True) < 0, -normals, normals)
    return PointCloud(points=points, colors=np.clip(sh0 * SH_C0 + 0.5, 0.0, 1.0), normals=normals)


def vertex_normals(mesh: TriMesh, fallback: np.ndarray = WORLD_UP) -> np.ndarray:
    """Unit vertex normals (V,3): the area-weighted sum of the normals of the triangles around each vertex,
    on the side the triangles' winding faces (for fused meshes: towards the cameras that saw them).
    A vertex with no triangle of non-zero area gets `fallback`."""
    v = np.asarray(mesh.vertices, np.float64).reshape(-1, 3)
    f = np.asarray(mesh.triangles, np.int64).reshape(-1, 3)
    acc = np.zeros_like(v)
    if len(f):
        face = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = twice the area
        for k in range(3):
            np.add.at(acc, f[:, k], face)
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.where(length > 0, acc / np.where(length > 0, length, 1.0), fallback)


def _ply_comments(convention: str | None) -> list[str]:
    """PLY comment lines (one line each, ASCII) stating the file's convention."""
    text = "WonderVerse" + (f": {convention}" if convention else "")
    return [ln for ln in text.encode("ascii", "replace").decode("ascii").splitlines() if ln.strip()]


def write_mesh(mesh: TriMesh, path: Path | str, convention: str | None = None) -> Path:
    """Write `mesh` with vertex normals (`vertex_normals`), by suffix. Returns the path.

    .ply: binary little-endian; vertex x, y, z, nx, ny, nz float32 (world frame), red, green, blue uchar
    (sRGB, as the images); face vertex_indices (uchar count, int indices); `convention` in comment lines.
    .glb: glTF 2.0 binary (`glb_bytes`): rotated from the world's +Z up to glTF's +Y up.
    """
    from plyfile import PlyData, PlyElement

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".glb"):
        raise ValueError(f"write_mesh: unsupported format {path.suffix!r}; use .ply or .glb")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".glb":
        path.write_bytes(glb_bytes(mesh, convention))
        return path
    v = np.asarray(mesh.vertices, np.float64).reshape(-1, 3)
    vert = np.empty(len(v), dtype=[(c, "<f4") for c in ("x", "y", "z", "nx", "ny", "nz")] + _RGB)
    vert["x"], vert["y"], vert["z"] = v.T
    vert["nx"], vert["ny"], vert["nz"] = vertex_normals(mesh).T
    _set_rgb(vert, mesh.colors)
    faces = np.empty(len(mesh.triangles), dtype=[("vertex_indices", "<i4", (3,))])
    faces["vertex_indices"] = np.asarray(mesh.triangles, np.int32).reshape(-1, 3)
    elements = [
        PlyElement.describe(vert, "vertex"),
        PlyElement.describe(faces, "face", len_types={"vertex_indices": "u1"}),
    ]
    PlyData(elements, text=False, byte_order="<", comments=_ply_comments(convention)).write(str(path))
    return path


_RGB = [("red", "u1"), ("green", "u1"), ("blue", "u1")]


def _set_rgb(rec: np.ndarray, colors: np.ndarray) -> None:
    c = np.round(np.clip(np.asarray(colors, np.float64).reshape(-1, 3), 0.0, 1.0) * 255.0).astype(np.uint8)
    rec["red"], rec["green"], rec["blue"] = c.T


def write_points_ply(path: Path | str, cloud: PointCloud, convention: str | None = None) -> Path:
    """Binary little-endian PLY: x, y, z float32 (world frame), nx, ny, nz float32 (when the cloud has
    normals), red, green, blue uchar; `convention` in comment lines. Returns the path."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    pts = np.asarray(cloud.points, np.float64).reshape(-1, 3)
    fields = ["x", "y", "z"] + (["nx", "ny", "nz"] if cloud.normals is not None else [])
    rec = np.empty(len(pts), dtype=[(c, "<f4") for c in fields] + _RGB)
    rec["x"], rec["y"], rec["z"] = pts.T
    if cloud.normals is not None:
        rec["nx"], rec["ny"], rec["nz"] = np.asarray(cloud.normals, np.float64).reshape(-1, 3).T
    _set_rgb(rec, cloud.colors)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<", comments=_ply_comments(convention)).write(
        str(path)
    )
    return path


# glTF constants: component types and buffer-view targets
_FLOAT, _UINT16, _UINT32 = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0,1] to linear light (the IEC 61966-2-1 curve)."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def glb_bytes(mesh: TriMesh, convention: str | None = None) -> bytes:
    """glTF 2.0 binary of `mesh`, for viewers: vertices rotated from the world's +Z up to glTF's +Y up
    (`Z_UP_TO_Y_UP`: (x, y, z) -> (x, z, -y)); POSITION and NORMAL float32, COLOR_0 the vertex colours in
    linear light (glTF's vertex colours are linear; ours are sRGB) as normalised uint16 RGBA (alpha 1), uint32
    indices, every buffer view with its target. One material shows the vertex colours as they are: KHR_materials_unlit
    (the colours already hold the scene's light), with a PBR fallback for viewers without it (base colour
    factor 1, metallic 0, roughness 1, so lit viewers shade the colours instead of showing black); double
    sided, since a fused surface is seen from both sides. `convention` goes to asset.extras. A mesh
    with no triangle gives a valid file with an empty scene."""
    import json

    v = np.asarray(mesh.vertices, np.float64).reshape(-1, 3) @ Z_UP_TO_Y_UP.T
    f = np.asarray(mesh.triangles, np.uint32).reshape(-1, 3)
    asset: dict[str, Any] = {"version": "2.0", "generator": "WonderVerse"}
    if convention:
        asset["extras"] = {"convention": convention}
    doc: dict[str, Any] = {"asset": asset, "scene": 0, "scenes": [{}]}
    blob = b""
    if len(f):
        n = vertex_normals(mesh) @ Z_UP_TO_Y_UP.T
        rgba = np.column_stack([srgb_to_linear(np.reshape(mesh.colors, (-1, 3))), np.ones(len(v))])
        rgba = np.round(rgba * 65535.0).astype("<u2")  # RGBA: vertex attributes align to 4 bytes
        parts = [
            (v.astype("<f4"), _FLOAT, "VEC3", _ARRAY_BUFFER),
            (n.astype("<f4"), _FLOAT, "VEC3", _ARRAY_BUFFER),
            (rgba, _UINT16, "VEC4", _ARRAY_BUFFER),
            (f.astype("<u4").reshape(-1), _UINT32, "SCALAR", _ELEMENT_ARRAY_BUFFER),
        ]
        views, accessors = [], []
        for i, (data, ctype, kind, target) in enumerate(parts):
            raw = np.ascontiguousarray(data).tobytes()
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(raw), "target": target})
            acc: dict[str, Any] = {"bufferView": i, "componentType": ctype, "count": len(data), "type": kind}
            if i == 0:  # POSITION needs its bounds
                acc |= {"min": data.min(axis=0).tolist(), "max": data.max(axis=0).tolist()}
            if ctype == _UINT16:
                acc["normalized"] = True
            accessors.append(acc)
            blob += raw + b"\0" * (-len(raw) % 4)
        doc |= {
            "scenes": [{"nodes": [0]}],
            "nodes": [{"name": "mesh", "mesh": 0}],
            "meshes": [
                {
                    "name": "mesh",
                    "primitives": [
                        {"attributes": {"POSITION": 0, "NORMAL": 1, "COLOR_0": 2}, "indices": 3, "material": 0}
                    ],
                }
            ],
            "materials": [
                {
                    "name": "vertex colours",
                    "pbrMetallicRoughness": {
                        "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                        "metallicFactor": 0.0,
                        "roughnessFactor": 1.0,
                    },
                    "doubleSided": True,
                    "extensions": {"KHR_materials_unlit": {}},
                }
            ],
            "extensionsUsed": ["KHR_materials_unlit"],
            "accessors": accessors,
            "bufferViews": views,
            "buffers": [{"byteLength": len(blob)}],
        }
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = len(text).to_bytes(4, "little") + b"JSON" + text
    if blob:
        chunks += len(blob).to_bytes(4, "little") + b"BIN\0" + blob
    return b"glTF" + (2).to_bytes(4, "little") + (12 + len(chunks)).to_bytes(4, "little") + chunks


def set_ply_comments(path: Path | str, comments: list[str]) -> Path:
    """Replace a PLY file's header comments with `comments` (ASCII, one line each), its data unchanged: the
    header is rewritten and the body copied after it into a new file that replaces the old. Returns the path."""
    import os
    import shutil

    path = Path(path)
    lines = [ln for c in comments for ln in c.encode("ascii", "replace").decode("ascii").splitlines() if ln.strip()]
    tmp = path.with_name(path.name + ".tmp")
    with path.open("rb") as src:
        header = []
        while not header or header[-1] != b"end_header":
            line = src.readline()
            if not line:
                raise ValueError(f"{path}: no end_header in the PLY header")
            header.append(line.rstrip(b"\r\n"))
        kept = [ln for ln in header if not ln.startswith(b"comment ")]
        new = kept[:2] + [f"comment {ln}".encode() for ln in lines] + kept[2:]  # after `ply` and `format`
        with tmp.open("wb") as dst:
            dst.write(b"\n".join(new) + b"\n")
            shutil.copyfileobj(src, dst, 1 << 22)
    os.replace(tmp, path)
    return path
