"""The mesh product: TSDF fusion of splat renders from the training cameras, in the output world frame."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wonderverse.camera import Sim3
from wonderverse.mesh import MeshParams, TriMesh, mesh_from_views, write_mesh
from wonderverse.products import Written
from wonderverse.progress import ProgressFn


@dataclass(frozen=True)
class MeshRecord:
    """The mesh's size, the scene extent its lengths followed (input units) and the median rendered depth of the
    fused views (where the novel-view path looks)."""

    triangles: int
    vertices: int
    extent: float
    look: float | None


def export_mesh(
    views: list[tuple[np.ndarray, np.ndarray]],
    w2c: np.ndarray,
    K: np.ndarray,
    params: MeshParams,
    to_world: Sim3,
    world: str,
    out: Path,
    progress: ProgressFn | None = None,
) -> tuple[list[Written], MeshRecord]:
    """Fuse `views` (rgb uint8 (H,W,3), depth (H,W) camera z, +inf where nothing is) seen from W2C cameras (N,4,4)
    with K (3,3), map the mesh by `to_world` into the output frame (described by `world`) and write out/mesh.ply and
    out/mesh.glb."""
    mesh_in, extent = mesh_from_views(views, w2c, K, params, progress=progress)
    mesh = TriMesh(to_world.apply(mesh_in.vertices), mesh_in.triangles, mesh_in.colors)
    glb = f"glTF axes: +Y up (the world's +Z), +Z towards the viewer (the world's -Y), +X the world's +X; {world}"
    files = [
        Written(write_mesh(mesh, out / "mesh.ply", world), f"mesh with vertex normals (PLY); {world}"),
        Written(write_mesh(mesh, out / "mesh.glb", glb), "mesh for viewers (glTF binary, +Y up, vertex colours)"),
    ]
    finite = np.concatenate([d[np.isfinite(d)] for _, d in views]) if views else np.zeros(0)
    look = float(np.median(finite)) if finite.size else None
    return files, MeshRecord(len(mesh.triangles), len(mesh.vertices), float(extent), look)
