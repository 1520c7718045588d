"""The mesh product: TSDF fusion of splat renders from the training cameras, in the output world frame.

A fusion is kept (`wonderverse.tsdf.TsdfFusion.state`) with the cameras it fused, so that an extended scene fuses
only its new cameras into it: the cameras are named by a digest of their pose (`camera_ids`), so a camera whose
pose changed is a new one, and a fused camera that is gone means the fusion starts over (`reusable`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from wonderverse.camera import Sim3
from wonderverse.mesh import MeshParams, TriMesh, clean_mesh, write_mesh
from wonderverse.products import Written
from wonderverse.progress import ProgressFn
from wonderverse.tsdf import TsdfFusion, fuse_tsdf


@dataclass(frozen=True)
class MeshRecord:
    """The mesh's size, the scene extent its lengths followed (input units, fixed when its fusion began), the
    cameras fused (`camera_ids`) with the median rendered depth of each (their median: where the novel-view path
    looks)."""

    triangles: int
    vertices: int
    extent: float
    fused: list[str] = field(default_factory=list)
    view_depths: list[float | None] = field(default_factory=list)

    @property
    def look(self) -> float | None:
        finite = [d for d in self.view_depths if d is not None]
        return float(np.median(finite)) if finite else None


def camera_ids(w2c: np.ndarray) -> list[str]:
    """A name per camera W2C (N,4,4): a digest of its pose, so that the same pose always has the same name."""
    w2c = np.ascontiguousarray(np.asarray(w2c, np.float64).reshape(-1, 4, 4))
    return [hashlib.sha1(c.tobytes()).hexdigest()[:16] for c in w2c]


def reusable(fused: list[str], fused_keys: list[str], cameras: list[str], keys: list[str]) -> bool:
    """Whether a fusion of the cameras `fused` (of which `fused_keys` are frames' poses) can go on with `cameras`
    (of which `keys` are frames' poses): every frame it fused is still there, pose unchanged. A camera interpolated
    between two frames may be gone: a frame registered later between them (an extension poses frames an earlier
    run could not) splits their gap, and what was fused from between two unchanged frames still holds. Without
    `fused_keys` (a fusion recorded before frames were told apart) every camera it fused must still be there."""
    if not fused:
        return False
    if not fused_keys:
        return set(fused) <= set(cameras)
    return set(fused_keys) <= set(keys)


def median_depth(depth: np.ndarray) -> float | None:
    """The median finite positive depth of a view, None when it sees nothing."""
    d = depth[np.isfinite(depth) & (depth > 0)]
    return float(np.median(d)) if d.size else None


def fuse_views(
    fusion: TsdfFusion,
    views: list[tuple[np.ndarray, np.ndarray]],
    w2c: np.ndarray,
    K: np.ndarray,
    progress: ProgressFn | None = None,
) -> TsdfFusion:
    """`views` (rgb uint8 (H,W,3), depth (H,W) camera z, +inf where nothing is) seen from W2C cameras (N,4,4) with
    K (3,3), fused into `fusion`."""
    fused = [(rgb, d, K, c) for (rgb, d), c in zip(views, w2c, strict=True)]
    return fuse_tsdf(fused, fusion.extent, progress=progress, fusion=fusion)


def export_mesh(
    fusion: TsdfFusion, params: MeshParams, to_world: Sim3, world: str, out: Path
) -> tuple[list[Written], TriMesh]:
    """The fused mesh, cleaned (`mesh.clean_mesh`) and mapped by `to_world` into the output frame (described by
    `world`), written as out/mesh.ply and out/mesh.glb."""
    mesh_in = clean_mesh(fusion.extract(), params)
    mesh = TriMesh(to_world.apply(mesh_in.vertices), mesh_in.triangles, mesh_in.colors)
    glb = f"glTF axes: +Y up (the world's +Z), +Z towards the viewer (the world's -Y), +X the world's +X; {world}"
    files = [
        Written(write_mesh(mesh, out / "mesh.ply", world), f"mesh with vertex normals (PLY); {world}"),
        Written(write_mesh(mesh, out / "mesh.glb", glb), "mesh for viewers (glTF binary, +Y up, vertex colours)"),
    ]
    return files, mesh
