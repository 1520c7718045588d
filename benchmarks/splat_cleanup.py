"""The exported splats' look: how far they spread, what export pruning removed and cost, and how many needles.

Procedural scenes through `outputs` (preview preset; `--quick`: the default scene alone, "a small house decorated
for Christmas"; else the four scenes of `benchmarks.exports`). For each, the trained Gaussians and those
`outputs` exports (`splats.cleanup.prune_for_export` with the scene's settings, run again here on the same
inputs):

- Bounds: the sides of the box of the exported centres, against the box of the training cameras' centres (the
  camera path) and of the SfM points (what the cameras saw), output world frame. The largest side over the
  largest side of each.
- Pruning: the share of the trained Gaussians removed, and its PSNR cost: training views (every 4th) rendered
  with the trained Gaussians and with the exported ones (needles shortened), each against the frames; the cost
  is the first PSNR minus the second (positive: the export renders the training views worse).
- Needles: Gaussians whose largest axis is over `max_needle_ratio` (10) times the middle one (`axis_ratios`),
  among those trained and those exported; elongated ones (over 3, the streaks of novel views on the default
  scene) and flat or needle ones (largest / smallest axis over 10, the count issue 39 asked for: a disc counts).

Last-line keys, the largest over the scenes: `needle_share` (trained), `needle_share_exported`,
`elongated_share` (exported), `flat_or_needle_share` (exported), `pruned_share`, `prune_psnr_cost_db`,
`bounds_over_path`, `bounds_over_points`; and `scenes`.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads

import numpy as np

from benchmarks.common import parse_args, report
from benchmarks.exports import SCENES

DEFAULT_SCENE = "christmas (outdoor)"
VIEW_STEP = 4  # every 4th training view is rendered for the PSNR cost
ELONGATED_RATIO = 3.0
FLAT_RATIO = 10.0


def _side(points: np.ndarray) -> np.ndarray:
    """The sides (3,) of the axis-aligned box of the finite rows of `points` (N,3)."""
    p = points[np.isfinite(points).all(axis=1)]
    return np.ptp(p, axis=0) if len(p) else np.zeros(3)


def _mean_psnr(arrays: dict[str, np.ndarray], scene: Any, idx: np.ndarray) -> float:
    """Mean PSNR (dB) of the training views `idx` rendered from `arrays` (training frame) against their frames."""
    from wonderverse.metrics import psnr
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.views import render_views

    h, w = scene.frames.shape[1:3]
    views = render_views(
        arrays, scene.norm_sfm, scene.w2c_sfm[idx], scene.K, w, h, make_renderer("torch"), scene.background
    )
    return float(np.mean([psnr(v.rgb, scene.frames[i] / 255.0) for v, i in zip(views, idx, strict=True)]))


def scene_figures(scene_dir: Path, outputs: Any, execution: Any) -> dict[str, Any]:
    """The figures of one finished scene (`outputs` / `execution`: the settings it ran with)."""
    from tasks.output_scene import OutputScene
    from wonderverse.camera import Sim3, camera_centers
    from wonderverse.schema import OUTPUTS, SFM
    from wonderverse.splats.cleanup import axis_ratios, prune_for_export, shorten_needles
    from wonderverse.splats.ply import to_world
    from wonderverse.store import SceneStore

    store = SceneStore.open(scene_dir)
    meta = store.meta(OUTPUTS.path)
    scene = OutputScene.load(store, outputs, execution, "")
    to_out = Sim3.from_dict(meta.frame.world_from_sfm)
    gaussians = to_world(scene.arrays, scene.norm_sfm.compose(to_out.inverse()))
    n = len(gaussians["means"])
    gaussians["row"] = np.arange(n, dtype=np.float64)  # carried along by the pruning: which rows were kept
    w2c = to_out.transform_w2c(scene.w2c_sfm)
    points = to_out.apply(store.array(SFM.points3d))
    kept, pruned = prune_for_export(
        gaussians, w2c, scene.K, *scene.size, points, meta.pruned.extent, outputs.prune
    )  # fmt: skip
    rows = kept["row"].astype(np.int64)
    exported = {k: np.asarray(v)[rows] for k, v in scene.arrays.items()}
    exported["log_scales"] = shorten_needles(exported["log_scales"], outputs.prune.max_needle_ratio)[0]
    idx = np.arange(0, len(scene.frames), VIEW_STEP)
    trained_psnr = _mean_psnr(scene.arrays, scene, idx)
    cost = trained_psnr - _mean_psnr(exported, scene, idx)
    limit = outputs.prune.max_needle_ratio
    trained_ratio, _ = axis_ratios(gaussians["log_scales"])
    ratio, flatness = axis_ratios(kept["log_scales"])
    box, path, seen = _side(kept["means"]), _side(camera_centers(w2c)), _side(points)
    return {
        "trained": n,
        "exported": len(rows),
        "pruned_share": round(1.0 - len(rows) / max(n, 1), 4),
        "needles_shortened": pruned["needles_shortened"],
        "needle_share": round(float(np.mean(trained_ratio > limit)), 5),
        # a shortened needle ends at the limit up to float32 rounding of its log scale
        "needle_share_exported": round(float(np.mean(ratio > limit * (1 + 1e-4))), 5),
        "elongated_share": round(float(np.mean(ratio > ELONGATED_RATIO)), 4),
        "flat_or_needle_share": round(float(np.mean(flatness > FLAT_RATIO)), 4),
        "psnr_trained_db": round(trained_psnr, 2),
        "prune_psnr_cost_db": round(cost, 4),
        "box": " x ".join(f"{v:.0f}" for v in box),
        "path box": " x ".join(f"{v:.1f}" for v in path),
        "points box": " x ".join(f"{v:.0f}" for v in seen),
        "bounds_over_path": round(float(box.max() / max(path.max(), 1e-12)), 2),
        "bounds_over_points": round(float(box.max() / max(seen.max(), 1e-12)), 3),
    }


HEADLINE = (
    "needle_share",
    "needle_share_exported",
    "elongated_share",
    "flat_or_needle_share",
    "pruned_share",
    "prune_psnr_cost_db",
    "bounds_over_path",
    "bounds_over_points",
)


def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    from flows.pipeline import execute
    from wonderverse.config import build_config

    scenes = {DEFAULT_SCENE: SCENES[DEFAULT_SCENE]} if args.quick else SCENES
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, prompt in scenes.items():
            cfg = build_config(prompt, preset="preview")
            scene = Path(tmp) / re.sub(r"\W+", "-", name)
            execute(scene, cfg)
            rows.append({"scene": name, **scene_figures(scene, cfg.steps.outputs, cfg.execution)})
    headline: dict[str, float | int] = {k: max(r[k] for r in rows) for k in HEADLINE}
    report("splat_cleanup", rows, {**headline, "scenes": len(rows)})


if __name__ == "__main__":
    main()
