"""The splat products: the Gaussians for other tools (pruned first), and the point cloud of their centres."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from wonderverse.camera import Sim3
from wonderverse.mesh import PointCloud, gaussian_points, set_ply_comments, write_points_ply
from wonderverse.products import Written
from wonderverse.splats.cleanup import ExportPruneParams, prune_for_export
from wonderverse.splats.ply import write_ply
from wonderverse.splats.web import write_splat_glb, write_spz


def export_splats(
    gaussians: dict[str, np.ndarray],
    w2c: np.ndarray,
    K: np.ndarray,
    size: tuple[int, int],
    sfm_points: np.ndarray | None,
    extent: float,
    prune: ExportPruneParams,
    world: str,
    out: Path,
) -> tuple[list[Written], dict[str, Any]]:
    """Prune `gaussians` (world-frame arrays, `GaussianModel.to_numpy` layout) of floaters, absurd and invisible
    Gaussians against the training cameras w2c (N,4,4) with K at `size` (width, height), the SfM points and the
    scene `extent` (`prune_for_export`), then write out/splats.ply (INRIA 3DGS), .spz (Niantic SPZ v3) and .glb
    (KHR_gaussian_splatting). Returns the files and the pruning report."""
    kept, pruned = prune_for_export(gaussians, w2c, K, size[0], size[1], sfm_points, extent, prune)
    ply = write_ply(out / "splats.ply", kept)
    set_ply_comments(ply, [f"WonderVerse Gaussian splats (INRIA 3DGS layout): {world}"])
    spz_axes = "SPZ's RUB axes: +Y up (the world's +Z), +Z the world's -Y"
    glb_axes = "glTF axes: +Y up (the world's +Z)"
    files = [
        Written(ply, f"Gaussian splats, INRIA 3DGS PLY layout; {world}"),
        Written(write_spz(out / "splats.spz", kept), f"Gaussian splats, Niantic SPZ v3; {spz_axes}; {world}"),
        Written(
            write_splat_glb(out / "splats.glb", kept),
            f"Gaussian splats, glTF with KHR_gaussian_splatting; {glb_axes}; {world}",
        ),
    ]
    return files, pruned


def point_cloud(arrays: dict[str, np.ndarray], norm: Sim3, min_opacity: float, toward: np.ndarray) -> PointCloud:
    """Centres of the Gaussians at least `min_opacity` opaque in the world `norm` maps the training frame from,
    with their colours and normals facing the nearest of `toward` (the cameras' centres)."""
    return gaussian_points(arrays, norm, min_opacity, toward=toward)


def export_points(cloud: PointCloud, world: str, out: Path) -> list[Written]:
    """out/points.ply: the point cloud with normals."""
    return [Written(write_points_ply(out / "points.ply", cloud, world), f"point cloud with normals; {world}")]
