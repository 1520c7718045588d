"""The files a scene is exported as, one entry point per product, over plain arrays:

  mesh            mesh.ply, mesh.glb: TSDF fusion of splat renders (`mesh.export_mesh`)
  splat files     splats.ply, splats.spz, splats.glb: the pruned Gaussians (`splat_files.export_splats`)
  point cloud     points.ply: the opaque Gaussians' centres (`splat_files.export_points`)
  datasets        colmap/ and nerfstudio/: training datasets (`datasets.export_colmap`, `datasets.export_nerfstudio`)
  camera paths    camera_path.json, novel_path.json and nerfstudio's (`camera_paths.export_camera_paths`)
  videos          flythrough.mp4, novel.mp4 (`videos.export_video`), and the novel views' quality scores

Every product states its world frame (`world_statement`) and returns the files it wrote as `Written` records. Which
product is remade when is the outputs step's business (`tasks.outputs`: one cache key per product).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from wonderverse.gravity import GravityFrame


@dataclass(frozen=True)
class Written:
    """A file or folder a product wrote, and what it holds in words (the conventions it follows)."""

    path: Path
    description: str

    @property
    def size(self) -> int:
        """Bytes on disk (a folder's files summed)."""
        p = self.path
        return sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) if p.is_dir() else p.stat().st_size


def world_statement(gravity: GravityFrame, source: str | None) -> str:
    """The output world frame in words, as every file states it; `source`: where the poses came from (sfm or the
    conditioning path)."""
    units = (
        "SfM units (the reconstruction's own arbitrary scale, not metres)"
        if source == "sfm"
        else "the units of the conditioning camera path (the procedural world's: metres times its scene_scale)"
    )
    how = gravity.evidence["source"]
    up = f"gravity estimated from {how}" if source == "sfm" else how
    return f"world frame: right-handed, +Z up ({up}), origin {gravity.evidence['origin']}; units: {units}"
