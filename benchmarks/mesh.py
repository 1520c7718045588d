"""Mesh from trained splats: Chamfer distance and F-score against the procedural world's mesh, per preset.

- Scene: "a small house decorated for Christmas" through the real pipeline up to `splats` (rule planner,
  procedural video without faults, per-segment checks, global SfM poses — the default `poses.source: sfm`
  —, oracle priors aligned to SfM, CPU splat training). Training runs once, with the preview preset's
  training settings (--quick: frames shrunk to 128x80, 9 per segment); the presets are then compared on
  their mesh parameters (TSDF resolution, truncation, clean-up) over the same splats — training at the
  standard/high sizes takes hours on a CPU.
- Views: the training cameras plus `extra_views_per_gap` interpolated ones, rendered by `splats.views`
  (the torch rasteriser on a CPU, training resolution) with alpha < 0.5 as background (+inf depth, never
  fused); fused with `wonderverse.mesh` in the SfM frame, then mapped into the world by the Sim(3)
  (Umeyama) that takes the SfM camera centres onto the true ones — so pose errors count against the mesh.
- Ground truth: points sampled by area on the world mesh near the cameras, kept where a training camera
  sees them (in frame, |z - true depth| < 1 % of z) no farther than the fusion's max depth; the
  prediction is sampled by area on the cleaned mesh. Thresholds are 1 % and 2 % of the scene extent
  (`camera.scene_extent` of the true cameras and depths); distances in metres.
- Row "true depth": the standard preset's fusion of the true depth at the true poses of the training frames
  (video resolution, no extra views): the ceiling of the fusion itself, so the gap to it is the splats' depth.
- Seconds: fusion (integrating every view) and extraction (marching cubes + clean-up), per preset.

Last-line keys (standard preset's mesh parameters): `fscore_1pct`, `fscore_2pct`, `chamfer` (m), `fusion_s`;
plus `extraction_s`, `extent_m`, `pipeline_s` (plan to trained splats).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads

import numpy as np

from benchmarks.common import parse_args, report
from wonderverse.mesh import MeshParams
from wonderverse.schema import SFM, SPLATS

PROMPT = "a small house decorated for Christmas"
# The presets' mesh parameters (what the benchmark compares; configs/presets/*.yaml set the same voxels)
PRESET_MESH = {
    "preview": MeshParams(voxel_frac=1 / 128),
    "standard": MeshParams(voxel_frac=1 / 256),
    "high": MeshParams(voxel_frac=1 / 512, extra_views_per_gap=1),
}
GT_SAMPLES = 1_000_000  # on the triangles near the cameras; those seen are kept (a few hundred thousand)
PRED_SAMPLES = 300_000
VISIBLE_REL_TOL = 0.01  # a GT point is seen when its projected depth is within 1 % of the true depth


def build_scene(scene_dir: Path, quick: bool) -> tuple[Any, float]:
    """Run the pipeline up to `splats`; returns the config and the seconds it took."""
    from flows.pipeline import execute
    from wonderverse.config import build_config

    video: dict[str, Any] = {"options": {"fault_probability": 0.0}}
    splats: dict[str, Any] = {}
    if quick:
        video |= {"width": 128, "height": 80, "frames_per_segment": 9}
        splats = {"max_side_px": 128}
    overrides = {
        "scene": {"video": video},
        "steps": {"check": {"max_attempts": 1}, "splats": splats},
        "execution": {"segment_workers": 1},
    }
    cfg = build_config(PROMPT, preset="preview", overrides=overrides)
    t0 = time.perf_counter()
    execute(scene_dir, cfg, until="splats")
    return cfg, time.perf_counter() - t0


def load_trained(scene_dir: Path) -> dict[str, Any]:
    """Splat arrays, normalisation, SfM poses/K of the posed frames, and the true poses, depths (+inf: sky)
    and video frames of the same frames."""
    from tasks.segments import attempt_path
    from wonderverse.splats.model import normalization_from_dict
    from wonderverse.store import SceneStore

    store = SceneStore.open(scene_dir)
    names = ("means", "quats", "log_scales", "logit_opacities", "sh0", "shN")
    arrays = {n: store.array(getattr(SPLATS, n)) for n in names}
    norm = normalization_from_dict(store.meta(SPLATS.path).normalization)
    poses, K = store.array(SFM.poses), store.array(SFM.K)
    segs, index = store.meta(SFM.path).segments, store.array(SFM.frame_index)
    attempts = {a: attempt_path(store, segs[a]) for a in np.unique(index[:, 0])}
    arrays_of = {"poses": lambda ap: ap.gt.poses, "depth": lambda ap: ap.gt.depth, "frames": lambda ap: ap.frames}
    per_seg = {name: {a: store.array(get(ap)) for a, ap in attempts.items()} for name, get in arrays_of.items()}
    gt, depth, frames = (np.stack([per_seg[n][a][i] for a, i in index]) for n in ("poses", "depth", "frames"))
    ok = np.isfinite(poses).all(axis=(1, 2))
    return {
        "arrays": arrays,
        "norm": norm,
        "w2c": poses[ok],
        "K": K,
        "gt_w2c": gt[ok],
        "gt_depth": depth[ok],
        "frames": frames[ok],
    }


def visible_gt_points(world: Any, K: np.ndarray, w2c: np.ndarray, depth: np.ndarray, max_depth: float) -> np.ndarray:
    """Points sampled by area on the world triangles near the cameras that some camera sees (see module doc)."""
    from wonderverse.camera import camera_centers, world_to_pixels
    from wonderverse.metrics import sample_mesh_points

    v, f = np.asarray(world.vertices, np.float64), np.asarray(world.triangles, np.int64)
    centers = camera_centers(w2c)
    near = np.zeros(len(f), bool)
    for c in centers:  # triangles with a vertex within the fusion's reach of some camera
        near |= (np.linalg.norm(v - c, axis=1) <= max_depth)[f].any(axis=1)
    pts = sample_mesh_points(v, f[near], GT_SAMPLES, seed=0)
    h, w = depth.shape[1:]
    seen = np.zeros(len(pts), bool)
    for pose, d in zip(w2c, depth, strict=True):
        u, r, z, framed = world_to_pixels(pts, K, pose, h, w)
        inside = framed & (z <= max_depth)
        ui, ri = u[inside].astype(int), r[inside].astype(int)
        seen[np.flatnonzero(inside)[np.abs(d[ri, ui] - z[inside]) < VISIBLE_REL_TOL * z[inside]]] = True
    return pts[seen]


def render(scene: dict[str, Any], extra: int, width: int, height: int, K: np.ndarray) -> tuple[list, float]:
    """Rendered (rgb, depth, K, w2c) views of the training cameras + `extra` per gap; and the seconds."""
    from wonderverse.mesh import fusion_cameras
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.views import render_views

    cams = fusion_cameras(scene["w2c"], extra)
    t0 = time.perf_counter()
    out = [
        (v.rgb, v.depth, K, c)
        for v, c in zip(
            render_views(scene["arrays"], scene["norm"], cams, K, width, height, make_renderer("auto")),
            cams,
            strict=True,
        )
    ]
    return out, time.perf_counter() - t0


def evaluate(name: str, params: MeshParams, views: list, extent: float, to_world: Any, gt: Any) -> dict[str, Any]:
    """Fuse + clean with `params`; metrics against the GT points (thresholds in `gt`)."""
    from wonderverse.mesh import clean_mesh
    from wonderverse.metrics import chamfer_fscore, sample_mesh_points
    from wonderverse.tsdf import TsdfFusion

    t0 = time.perf_counter()
    fusion = TsdfFusion(extent, params)
    for v in views:
        fusion.integrate(*v)
    t1 = time.perf_counter()
    mesh = clean_mesh(fusion.extract(), params)
    t2 = time.perf_counter()
    pred = to_world.apply(sample_mesh_points(mesh.vertices, mesh.triangles, PRED_SAMPLES, seed=1))
    m = chamfer_fscore(pred, gt["points"], gt["thresholds"])
    return {
        "preset": name,
        "voxel_m": fusion.voxel * to_world.s,
        "views": fusion.views,
        "tris": len(mesh.triangles),
        "chamfer_m": m["chamfer"],
        "acc_m": m["accuracy"],
        "comp_m": m["completeness"],
        "P@1%": m["precision"][0],
        "R@1%": m["recall"][0],
        "F@1%": m["fscore"][0],
        "F@2%": m["fscore"][1],
        "fuse_s": t1 - t0,
        "mc_s": t2 - t1,
        "gt_pts": len(gt["points"]),
    }


def main() -> None:
    args = parse_args(__doc__ or "")
    import torch

    torch.set_num_threads(2)
    with tempfile.TemporaryDirectory(prefix="wv_mesh_") as tmp:
        cfg, pipeline_s = build_scene(Path(tmp), args.quick)
        scene = load_trained(Path(tmp))
    rows, (w, h), extent_m = measure(cfg, scene)
    std = next(r for r in rows if r["preset"] == "standard")
    report(
        f"mesh from splats ({'quick, ' if args.quick else ''}{w}x{h} training views, {len(scene['w2c'])} frames)",
        rows,
        {
            "fscore_1pct": round(std["F@1%"], 4),
            "fscore_2pct": round(std["F@2%"], 4),
            "chamfer": round(std["chamfer_m"], 4),
            "fusion_s": round(std["fuse_s"], 3),
            "extraction_s": round(std["mc_s"], 3),
            "extent_m": round(extent_m, 3),
            "pipeline_s": round(pipeline_s, 1),
        },
    )


def measure(cfg: Any, scene: dict[str, Any]) -> tuple[list[dict[str, Any]], tuple[int, int], float]:
    """One row per preset's MeshParams on the trained splats, and one fusing the true depth; also the
    render size (w, h) and the true scene extent (m)."""
    from wonderverse.camera import Sim3, camera_centers, fit_intrinsics, scene_extent, umeyama
    from wonderverse.video import make_video_model

    video = make_video_model(cfg.scene.video_source)
    world, true_K = video.world, video.K
    vw, vh = cfg.scene.video.width, cfg.scene.video.height
    # render at the training resolution (frames were downscaled to max_side_px on the longer side)
    rw, rh, K = fit_intrinsics(vw, vh, scene["K"], cfg.steps.splats.max_side_px)
    to_world = umeyama(camera_centers(scene["w2c"]), camera_centers(scene["gt_w2c"]), with_scale=True)

    depth, gt_w2c = scene["gt_depth"], scene["gt_w2c"]
    extent_gt = scene_extent(gt_w2c, depth)
    thresholds = [0.01 * extent_gt, 0.02 * extent_gt]
    rendered = {0: render(scene, 0, rw, rh, K)}
    extent = scene_extent(scene["w2c"], [v[1] for v in rendered[0][0]])  # as the pipeline sees it: SfM units
    gt_cache: dict[float, np.ndarray] = {}

    def gt_points(reach_frac: float, ext_m: float) -> dict[str, Any]:
        reach = reach_frac * ext_m  # the fusion's max depth, in metres (inf: every depth)
        if reach not in gt_cache:
            gt_cache[reach] = visible_gt_points(world, true_K, gt_w2c, depth, reach)
        return {"points": gt_cache[reach], "thresholds": thresholds}

    rows = []
    for name, params in PRESET_MESH.items():
        extra = params.extra_views_per_gap
        if extra not in rendered:
            rendered[extra] = render(scene, extra, rw, rh, K)
        views, render_s = rendered[extra]
        gt = gt_points(params.reach_frac, extent * to_world.s)
        rows.append(evaluate(name, params, views, extent, to_world, gt) | {"render_s": render_s})
    # the same fusion on the true depth and poses of the training frames: what the splats' depth costs
    oracle_views = [(c, d, true_K, p) for c, d, p in zip(scene["frames"], depth, gt_w2c, strict=True)]
    params = PRESET_MESH["standard"].model_copy(update={"extra_views_per_gap": 0})
    gt = gt_points(params.reach_frac, extent_gt)
    rows.append(evaluate("true depth", params, oracle_views, extent_gt, Sim3.identity(), gt))
    rows[-1]["render_s"] = 0.0
    return rows, (rw, rh), extent_gt


if __name__ == "__main__":
    main()
