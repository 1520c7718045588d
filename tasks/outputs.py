"""Step `outputs`: the files users open elsewhere, written beside the store from the trained splats.

  points.ply              Gaussian centres at least `mesh.points_min_opacity` opaque, with their base colour
  mesh.ply, mesh.glb      TSDF fusion of splat renders from the training cameras (sky/background excluded)
  colmap/                 COLMAP text model of the global poses and sparse points (W2C, as COLMAP stores it)
  nerfstudio/             transforms.json (OpenGL camera-to-world) + images/ of the stitched frames
  camera_path.json        the fly-through path (W2C, OpenCV axes, world units; stated in the file)
  flythrough.mp4          splat renders along a smooth path through the whole scene
  novel.mp4               splat renders along a parallel path off the training trajectory

Everything is in the world frame of the global poses (`sfm/`). The `outputs` group lists the files and
their sizes; it is committed last, so a killed run rewrites them all on the next run.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from tasks.base import Step, StepContext
from tasks.progress import callback
from wonderverse.config import Model, OutputsParams, RunConfig
from wonderverse.schema import OUTPUTS, SFM, SPLATS
from wonderverse.store import SceneStore

log = logging.getLogger("wonderverse.outputs")


class Params(Model):
    """The outputs' settings, and the prompt the novel views are scored against (CLIP-S)."""

    outputs: OutputsParams
    prompt: str


def params(cfg: RunConfig) -> Params:
    return Params(outputs=cfg.steps.outputs, prompt=cfg.scene.prompt)


def posed_frames(store: SceneStore) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Stitched frames that have a global pose: frames (N,H,W,3) uint8, W2C (N,4,4), names `s000_0007`."""
    from tasks.segments import attempt_path, posed_stitched

    rows, w2c, names = posed_stitched(store, {"frames": lambda seg: attempt_path(store, seg).frames})
    return rows["frames"], w2c, names


def run(store: SceneStore, params: Params, ctx: StepContext) -> str:
    from wonderverse.camera import fit_intrinsics
    from wonderverse.exports import write_camera_path, write_colmap_text, write_nerfstudio
    from wonderverse.media import write_mp4
    from wonderverse.mesh import fusion_cameras, gaussian_points, mesh_from_views, write_mesh, write_points_ply
    from wonderverse.paths import flythrough_path, novel_view_path
    from wonderverse.quality import score_views
    from wonderverse.splats.model import GaussianModel, normalization_from_dict
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.views import render_views

    p = params.outputs
    out = Path(store.scene_dir)
    splats = store.attrs(SPLATS.path)
    norm = normalization_from_dict(splats["normalization"])
    arrays = {name: store.array(getattr(SPLATS, name)) for name in GaussianModel.PARAM_NAMES}
    background = splats.get("metrics", {}).get("background_rgb")
    frames, w2c, names = posed_frames(store)
    K = store.array(SFM.K)
    height, width = frames.shape[1:3]
    w, h, Kr = fit_intrinsics(width, height, K, p.render_max_side_px)
    renderer = make_renderer(ctx.execution.renderer)
    workers = ctx.execution.render_workers or _usable_cores()
    files: list[Path] = []

    def render(poses: np.ndarray, unit: str) -> list[Any]:
        views = render_views(
            arrays, norm, poses, Kr, w, h, renderer, background=background, workers=workers, progress=callback(unit)
        )
        return list(views)

    cloud = gaussian_points(arrays, norm, p.mesh.points_min_opacity)
    files.append(write_points_ply(out / "points.ply", cloud))

    cams = fusion_cameras(w2c, p.mesh.extra_views_per_gap)
    # colour as uint8 and depth only: the fusion needs nothing else, and every view is held until the extent is known
    views = [(np.round(v.rgb * 255).astype(np.uint8), v.depth) for v in render(cams, "views rendered for the mesh")]
    mesh, extent = mesh_from_views(views, cams, Kr, p.mesh, progress=callback("views fused"))
    files += [write_mesh(mesh, out / "mesh.ply"), write_mesh(mesh, out / "mesh.glb")]

    if p.colmap:
        points, colors = store.array(SFM.points3d), store.array(SFM.colors)
        files.append(write_colmap_text(out / "colmap", K, w2c, width, height, names, points, colors))
    if p.nerfstudio:
        files.append(write_nerfstudio(out / "nerfstudio", frames, K, w2c, names).parent)

    finite = np.concatenate([d[np.isfinite(d)] for _, d in views]) if views else np.zeros(0)
    look = float(np.median(finite)) if finite.size else None
    fly = flythrough_path(w2c, p.video_frames)
    files.append(write_camera_path(out / "camera_path.json", fly, Kr, w, h, p.video_fps))

    def video(poses: np.ndarray, name: str, unit: str) -> np.ndarray:
        rgb = np.stack([np.round(v.rgb * 255).astype(np.uint8) for v in render(poses, unit)])
        files.append(write_mp4(rgb, out / name, p.video_fps))
        return rgb

    video(fly, "flythrough.mp4", "fly-through frames")
    novel = video(novel_view_path(w2c, p.video_frames, p.novel_offset_frac, look), "novel.mp4", "novel-view frames")
    picks = np.linspace(0, len(novel) - 1, min(p.quality_frames, len(novel))).round().astype(int)
    metrics = callback("quality metrics", eta=False)  # unequal: NIQE is quick, a CLIP model loads first
    quality = score_views(list(novel[picks]), params.prompt, p.quality, metrics)  # of the novel views, as the paper

    listed = [{"path": f.name, "bytes": _size(f)} for f in files]
    stats = {"triangles": len(mesh.triangles), "vertices": len(mesh.vertices), "points": len(cloud.points)}
    with store.staged(
        OUTPUTS.path, ctx.key, files=listed, mesh=stats | {"extent": extent}, render_size=[w, h], quality=quality
    ):
        pass
    return f"{len(files)} files: mesh {stats['triangles']} triangles, {stats['points']} points, 2 videos"


def _usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one), not the host's count."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else path.stat().st_size


# 3: the step contract
STEP = Step(
    "outputs", 3, ("splats",), params, run, "mesh, point cloud, COLMAP/nerfstudio exports, videos", group=OUTPUTS.path
)
