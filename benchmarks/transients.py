"""Moving people and vehicles: does the robust photometric loss keep them out of the static scene, and what does it
cost on footage without them?

Procedural clips (`ProceduralVideo` with `movers`: boxes shaped like people and cars crossing the view, composited by
depth, with exact per-frame masks) and the same clips without movers, which are also the static truth of every frame.
Each clip trains twice on the CPU from the same Gaussians (seeded from the static depth, coloured by the frames):
plain (`loss.robust.enabled: false`, the default) and robust (`enabled: true` with its defaults: the cross-view test,
`losses.cross_view_residual`). Poses are the true ones and no priors are used, so the photometric term alone differs.
Held-out views (every 4th) are scored against the static frame on static pixels only: the pixels no mover covers in
that held-out view. Held-out views never train (nor does the cross-view test look at them), so a mover there costs
nothing by itself; what costs is the ghost the training views' movers left in the scene.

The masks the robust loss gave up on are those of `trainer.outlier_masks` on the final model (the weights the last
steps trained with); recall and precision are against the true mover masks of the training views. With `--out DIR`,
PNGs per clip: frame | true mover mask | learned outlier mask, one row per training view shown.

Last-line keys:
- `transient_psnr_gain_db`: robust - plain held-out static-pixel PSNR on the clips with movers (mean over clips; target
  >= 1.0).
- `clean_psnr_cost_db`: plain - robust held-out PSNR on the same clips without movers (target <= 0.1).
- `psnr_plain_movers_db`, `psnr_robust_movers_db`, `psnr_plain_clean_db`, `psnr_robust_clean_db`: the four means.
- `mask_recall`, `mask_precision`: learned outlier masks against the true mover masks (pixels pooled over the
  training views of the mover clips).
- `mover_share`: share of training pixels covered by movers.
- `clean_outlier_share`: share of training pixels the robust loss dropped on the clips without movers.
- `seconds`: wall time of the whole benchmark.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads

import numpy as np

from benchmarks.common import table

SCENES = (("a small house decorated for Christmas", 0), ("a quiet village with houses and trees", 3))
HOLDOUT_EVERY = 4
MOVERS = 5
ROBUST: dict[str, Any] = {}  # robust settings other than the defaults (none: the defaults are measured)


@dataclass
class Clip:
    """One procedural clip with movers, its static twin, the true mover masks and the poses."""

    name: str
    frames: np.ndarray
    static: np.ndarray
    masks: np.ndarray
    depth: np.ndarray
    poses: np.ndarray
    K: np.ndarray


def make_clip(prompt: str, seed: int, width: int, height: int, n_frames: int) -> Clip:
    from wonderverse.video.procedural import ProceduralVideo, demo_path

    out = {}
    for movers in (MOVERS, 0):
        video = ProceduralVideo(prompt, seed, width, height, 60.0, {"fault_probability": 0.0, "movers": movers})
        path = demo_path(video.world.start_pose(), n_frames, yaw_deg=15.0, forward_m=1.2)
        out[movers] = video.generate("", path, 0, None)
    v, s = out[MOVERS], out[0]
    assert v.gt.movers is not None
    return Clip(f"{prompt} #{seed}", v.frames, s.frames, v.gt.movers, s.gt.depth, s.gt.poses, v.K)


def _views(clip: Clip, frames: np.ndarray):
    from wonderverse.splats.model import normalization_from_cameras
    from wonderverse.splats.trainer import Views, normalize_views

    norm = normalization_from_cameras(clip.poses)
    return normalize_views(Views(frames=frames, w2c=clip.poses, K=clip.K, prior_depth=clip.depth), norm)


def _render(model, views, i: int, renderer, bg) -> np.ndarray:
    import torch

    h, w = views.frames.shape[1:3]
    with torch.no_grad():
        rgb, *_ = renderer(
            model.means,
            model.quats,
            torch.exp(model.log_scales),
            torch.sigmoid(model.logit_opacities),
            torch.cat([model.sh0, model.shN], 1),
            torch.tensor(views.w2c[i], dtype=torch.float32),
            torch.tensor(views.K_of(i), dtype=torch.float32),
            w,
            h,
            background=torch.tensor(bg, dtype=torch.float32),
            sh_degree=model.sh_degree,
        )
    return rgb.clamp(0, 1).numpy()


def static_psnr(render: np.ndarray, static: np.ndarray, mover: np.ndarray) -> float:
    """PSNR (dB) of a render (H,W,3) in [0,1] against the static frame (H,W,3) uint8 on pixels no mover covers."""
    keep = ~mover
    err = (render[keep] - static[keep].astype(np.float64) / 255.0) ** 2
    return float(10 * np.log10(1.0 / max(err.mean(), 1e-12)))


def train_one(clip: Clip, frames: np.ndarray, robust: bool, iterations: int) -> dict[str, Any]:
    """Train on `frames` (the clip's with or without movers); held-out static PSNR and the learned masks."""
    import torch

    from wonderverse.splats.data import backproject_depth
    from wonderverse.splats.model import init_from_points
    from wonderverse.splats.params import LossParams, RobustLossParams, TrainParams
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.trainer import outlier_masks, train

    views = _views(clip, frames)
    loss = LossParams(lambda_depth=0.0, lambda_normal=0.0, robust=RobustLossParams(enabled=robust, **ROBUST))
    params = TrainParams(iterations=iterations, sh_degree=1, holdout_every=HOLDOUT_EVERY, loss=loss)
    pts, cols = backproject_depth(views, 2, 2)
    model = init_from_points(pts, cols / 255.0, 1, init_opacity=0.1)
    renderer = make_renderer("torch")
    model, _, m = train(model, views.replace(prior_depth=None), params, renderer)
    bg = np.asarray(m["background_rgb"], np.float32)
    psnrs = [
        static_psnr(_render(model, views, i, renderer, bg), clip.static[i], clip.masks[i]) for i in m["test_views"]
    ]
    ids = m["train_views"]
    learned = outlier_masks(model, views.replace(prior_depth=None), ids, ids, renderer, params, torch.tensor(bg))
    return {"psnr": float(np.mean(psnrs)), "learned": learned}


def mask_scores(learned: dict[int, np.ndarray], truth: np.ndarray) -> tuple[int, int, int]:
    """(true positives, learned pixels, true pixels) pooled over the views in `learned`."""
    tp = sum(int((m & truth[i]).sum()) for i, m in learned.items())
    return tp, sum(int(m.sum()) for m in learned.values()), sum(int(truth[i].sum()) for i in learned)


def save_masks(out: Path, clip: Clip, learned: dict[int, np.ndarray], tag: str) -> Path:
    """frame | true mover mask | learned outlier mask for up to four training views, one row each."""
    from PIL import Image

    rows = []
    for i in list(learned)[:: max(1, len(learned) // 4)][:4]:
        grey = [np.repeat((m[..., None] * 255).astype(np.uint8), 3, -1) for m in (clip.masks[i], learned[i])]
        rows.append(np.concatenate([clip.frames[i], *grey], 1))
    path = out / f"transients_{tag}.png"
    Image.fromarray(np.concatenate(rows, 0)).resize((rows[0].shape[1] * 2, len(rows) * rows[0].shape[0] * 2),
                                                    Image.NEAREST).save(path)  # fmt: skip
    return path


def run_clip(clip: Clip, iterations: int, out: Path | None, tag: str) -> dict[str, Any]:
    res = {(movers, robust): train_one(clip, clip.frames if movers else clip.static, robust, iterations)
           for movers in (True, False) for robust in (False, True)}  # fmt: skip
    learned = res[(True, True)]["learned"]
    if out is not None:
        save_masks(out, clip, learned, tag)
    clean_learned = res[(False, True)]["learned"]
    return {
        "clip": clip.name,
        "plain_movers": res[(True, False)]["psnr"],
        "robust_movers": res[(True, True)]["psnr"],
        "plain_clean": res[(False, False)]["psnr"],
        "robust_clean": res[(False, True)]["psnr"],
        "scores": mask_scores(learned, clip.masks),
        "mover_px": sum(int(clip.masks[i].sum()) for i in learned),
        "px": len(learned) * clip.masks[0].size,
        "clean_dropped": sum(int(m.sum()) for m in clean_learned.values()),
    }


def headline(rows: list[dict[str, Any]], seconds: float) -> dict[str, float]:
    def mean(k: str) -> float:
        return float(np.mean([r[k] for r in rows]))

    tp, learned, truth = (sum(r["scores"][j] for r in rows) for j in range(3))
    px = sum(r["px"] for r in rows)
    return {
        "transient_psnr_gain_db": round(mean("robust_movers") - mean("plain_movers"), 2),
        "clean_psnr_cost_db": round(mean("plain_clean") - mean("robust_clean"), 3),
        "psnr_plain_movers_db": round(mean("plain_movers"), 2),
        "psnr_robust_movers_db": round(mean("robust_movers"), 2),
        "psnr_plain_clean_db": round(mean("plain_clean"), 2),
        "psnr_robust_clean_db": round(mean("robust_clean"), 2),
        "mask_recall": round(tp / max(truth, 1), 3),
        "mask_precision": round(tp / max(learned, 1), 3),
        "mover_share": round(sum(r["mover_px"] for r in rows) / px, 4),
        "clean_outlier_share": round(sum(r["clean_dropped"] for r in rows) / px, 5),
        "seconds": round(seconds, 1),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--quick", action="store_true", help="one clip, fewer iterations (a few minutes on 2 cores)")
    p.add_argument("--out", type=Path, default=None, help="folder for the mask PNGs")
    args = p.parse_args()
    import torch

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    width, height, n_frames, iterations = (96, 64, 16, 400) if args.quick else (96, 64, 16, 600)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for k, (prompt, seed) in enumerate(SCENES[:1] if args.quick else SCENES):
        clip = make_clip(prompt, seed, width, height, n_frames)
        rows.append(run_clip(clip, iterations, args.out, f"clip{k}"))
    shown = [{k: v for k, v in r.items() if k not in ("scores", "px", "mover_px", "clean_dropped")} for r in rows]
    table(shown, "transients: held-out static-pixel PSNR (dB), plain vs robust loss")
    print(json.dumps(headline(rows, time.perf_counter() - t0)), flush=True)


if __name__ == "__main__":
    main()
