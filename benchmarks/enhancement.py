"""The paper's ablation of the geometric enhancement: RGB only, + depth, + normal, + both, on procedural scenes
with and without the defects of real AI video.

- Scenes: two worlds (outdoor "a small house decorated for Christmas", indoor "a cosy reading room with shelves and
  armchairs") × three conditions of the procedural backend: `clean` (defects "none"), `texture_poor` and
  `ai_like` (the named defect levels, `wonderverse.video.procedural_options.DEFECT_LEVELS`). Each is two segments
  (turn left 30° while moving forward, then 35° more), rendered at the preset's video size and downscaled to its
  training size as the splat step does.
- What varies is the reconstruction alone, as in the paper's ablation: true poses; initial points and the prior's
  alignment references are the true depth at the pixels where a feature detector would fire (Shi-Tomasi corner
  response in the top `FEATURE_SHARE` of the frame, every `FEATURE_FRAME_STRIDE`-th frame) — a stand-in for SfM
  points, which are as scarce on texture-poor surfaces. Priors: the oracle at the "realistic" level (the error of
  Depth Anything V2 / Omnidata on real benchmarks) aligned per frame to those references by the priors step's
  method; normals from that depth (`NormalsFromDepth`), as the priors step computes them.
- Training: the preset's `steps.splats`, every 8th view held out. Variants: "rgb" trains as the pipeline does
  with both prior backends set to `none` (Gaussians start from the feature points alone, and the sky, which the
  priors step marks, is modelled like anything else); "rgb_seeded" has the priors but no prior loss (the depth
  prior seeds Gaussians and marks the sky; λ_d = λ_n = 0): the baseline of the loss terms themselves; "depth",
  "normal" and "both" add L_depth, L_normal or both at the preset's weights ("both" is the shipped pipeline).
- Scores, against the procedural truth: `psnr` held-out PSNR (dB); `absrel` the rendered depth (D̂/alpha, where
  alpha > 0.5) of the held-out views vs the true depth; `normal_deg` mean angle between the rendered normals and the
  true normals there; `f1` mesh F-score at 1 % of the scene extent (`camera.scene_extent` of the true cameras and
  depths) and `chamfer_m` (m): the preset's mesh (TSDF of every view's rendered depth, the preset's `MeshParams`,
  clean-up) against points sampled on the world's triangles that a training camera sees at ANY distance (not only
  within the fusion's reach: a mesh that covers only the nearer half loses recall).
- What the images can determine (`determinable`): a world point seen by training cameras whose rays to it span an
  angle θ (widest pair, occlusion ignored, so an upper bound) has a depth uncertainty of about z σ / θ from
  triangulation (z its nearest camera's depth, σ `MATCH_SIGMA_PX` pixels at the training size as an angle).
  `parallax_bound` is the share of the seen world (by area) where that is below the F-score's threshold: no method
  that gets depth from parallax recalls more. `f1_determined` is the F-score there (recall over those world
  points, precision over the mesh points whose nearest world point is one): what the reconstruction makes of what
  the video determines. `input_bound` adds what the aligned depth prior gives: the share of the seen world that
  parallax determines OR that the prior of some view framing it places within the threshold along that view's
  ray (generous: it assumes a method that knows which view's prior to trust where). A recall above it is luck.

Usage: `python -m benchmarks.enhancement [--quick] [--preset preview|standard|high] [--worlds outdoor indoor]
[--conditions clean texture_poor ai_like] [--variants rgb depth normal both] [--loss KEY=VALUE ...] [--mesh
KEY=VALUE ...] [--train KEY=VALUE ...] [--defects KEY=VALUE ...] [--prior KEY=VALUE ...] [--out ROWS.json]`, and
`--merge A.json B.json ...` to report runs made apart (in parallel; a later file's row replaces an earlier one of
the same world, condition, variant, defects and prior, so a re-measured variant goes last); `--quick` shrinks the
video to 160x112 and 9 frames per segment with 120 iterations (a smoke run); `--train` overrides the preset's
`steps.splats.train` (e.g. `iterations=2000` at the preset's video and training sizes); `--defects` changes the
conditions' defects (`DefectParams` fields, e.g. `geometric_drift_m=0` to leave one of `ai_like`'s out; rows then
carry a `defects` column); `--prior` changes the oracle's "realistic" level (`OracleDegradation` fields, e.g.
`world_warp_log_amp=0.05` for an error fixed to the world's surfaces; rows then carry a `prior` column); `--loss`
and `--train` likewise add `loss` and `train` columns (e.g. `--loss prior_parallax_ref=0.05` for the parallax gate
of the prior weights, `wonderverse.splats.parallax`).
Last-line keys (means over the worlds run): `fscore_gain_lowtex`, `fscore_gain_ai` (F@1 % of "both" minus
"rgb_seeded", texture-poor and AI-like conditions: what the loss terms add), `depth_gain_ai` (1 - AbsRel both /
AbsRel rgb_seeded, AI-like), `psnr_cost_clean_db` (PSNR rgb_seeded minus both, clean), the same four against
"rgb" with the suffix `_vs_rgb` (what the priors add as a whole), and with --preset standard/high
`fscore_standard` / `fscore_high` (F@1 % of "both", mean over worlds and conditions), `fscore_standard_determined`
/ `fscore_high_determined` (the same as `f1_determined`), `parallax_bound` and `input_bound` (their means). A
baseline not run: NaN.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads

import numpy as np

from benchmarks.common import machine, report

WORLDS = {
    "outdoor": ("a small house decorated for Christmas", 2.0),  # prompt, forward metres per segment
    "indoor": ("a cosy reading room with shelves and armchairs", 1.0),
}
CONDITIONS = ("clean", "texture_poor", "ai_like")
DEFECTS = {"clean": "none", "texture_poor": "texture_poor", "ai_like": "ai_like"}
# variant: (the priors step ran, λ_d on, λ_n on)
VARIANTS = {
    "rgb": (False, False, False),
    "rgb_seeded": (True, False, False),
    "depth": (True, True, False),
    "normal": (True, False, True),
    "both": (True, True, True),
}
HOLDOUT = 8
FEATURE_SHARE = 0.02  # share of a frame's pixels that count as features (strongest corner response)
FEATURE_FRAME_STRIDE = 2
GT_SAMPLES = 1_000_000
PRED_SAMPLES = 300_000
FULL_REACH = 1e3  # max_depth_frac of the "f1_full_reach" column: every rendered depth is fused at the fine voxel
MATCH_SIGMA_PX = 0.25  # a good sub-pixel match (feature matching, or photometric alignment of sharp texture)
DETERMINABLE_SAMPLES = 50_000


def corner_mask(frame: np.ndarray, share: float) -> np.ndarray:
    """(H,W) bool: the `share` of pixels with the strongest Shi-Tomasi response (minimum eigenvalue of the
    structure tensor of the grey image, 5x5 window), where a feature detector would fire."""
    from scipy import ndimage

    grey = frame.astype(np.float32).mean(-1) / 255.0
    gx, gy = ndimage.sobel(grey, 1), ndimage.sobel(grey, 0)
    a, b, c = (ndimage.uniform_filter(x, 5) for x in (gx * gx, gx * gy, gy * gy))
    response = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    cut = np.quantile(response, 1.0 - share)
    return (response >= cut) & (response > 1e-6)


def prepare(
    world: str,
    condition: str,
    cfg: Any,
    seed: int = 0,
    defect_update: dict[str, Any] | None = None,
    prior_update: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Frames, true poses, K, priors and ground truth of one scene at the preset's training size;
    `defect_update` changes fields of the condition's defects (`DefectParams`), e.g. one defect off;
    `prior_update` fields of the oracle's "realistic" level (`OracleDegradation`)."""
    from wonderverse.camera import move_path
    from wonderverse.priors import align_scale_shift
    from wonderverse.priors.from_depth import NormalsFromDepth
    from wonderverse.priors.oracle import OracleDepth
    from wonderverse.priors.params import ORACLE_LEVELS
    from wonderverse.splats.data import _resize, downscale_views
    from wonderverse.splats.trainer import Views
    from wonderverse.video import initial_pose
    from wonderverse.video.procedural import ProceduralVideo
    from wonderverse.video.procedural_options import DEFECT_LEVELS

    prompt, forward = WORLDS[world]
    v = cfg.scene.video
    options: dict[str, Any] = {"fault_probability": 0.0}
    if condition != "clean" or defect_update:
        options["defects"] = DEFECT_LEVELS[DEFECTS[condition]].model_copy(update=defect_update or {})
    model = ProceduralVideo(prompt, seed, v.width, v.height, v.fov_deg, options)
    n = v.frames_per_segment
    p0 = move_path(initial_pose(model), np.radians(-30), 0.0, forward, -0.6 * forward, n)
    path = np.concatenate([p0, move_path(p0[-1], np.radians(-35), 0.0, 0.25 * forward, -0.7 * forward, n)[1:]])
    video = model.generate(prompt, path, 0, None)
    gt = video.gt
    views = downscale_views(Views(frames=video.frames, w2c=gt.poses, K=video.K), cfg.steps.splats.max_side_px)
    h, w = views.frames.shape[1:3]
    depth = _resize(gt.depth, (w, h), True)
    normals = _resize(gt.normals, (w, h), True)
    level = ORACLE_LEVELS["realistic"].model_copy(update=prior_update or {})
    oracle = OracleDepth(depth, level, "inverse_depth", seed=seed + 1, K=views.K, w2c=gt.poses)
    pred = oracle.predict(views.frames)
    prior = np.empty_like(depth)
    points, colors = [], []
    for t in range(len(depth)):
        feats = corner_mask(views.frames[t], FEATURE_SHARE) & np.isfinite(depth[t])
        ref = np.where(feats, depth[t], np.nan)
        prior[t] = align_scale_shift(pred.depth[t], ref, space=pred.kind).aligned_depth
        if t % FEATURE_FRAME_STRIDE == 0:
            pts, cols = _backproject(depth[t], views.frames[t], views.K, gt.poses[t], feats)
            points.append(pts)
            colors.append(cols)
    prior[~np.isfinite(depth)] = np.inf  # the oracle's sky is far; the priors step marks sky invalid alike
    prior_normals = NormalsFromDepth().predict(views.frames, K=views.K, depth=prior).normals
    return {
        "views": views.replace(prior_depth=prior, prior_normals=prior_normals),
        "points": np.concatenate(points),
        "colors": np.concatenate(colors),
        "gt_depth": depth,
        "gt_normals": normals,
        "world": model.world,
    }


def _backproject(
    z: np.ndarray, frame: np.ndarray, K: np.ndarray, w2c: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    from wonderverse.camera import pixels_to_world

    v, u = np.nonzero(mask)
    return pixels_to_world(u + 0.5, v + 0.5, z[v, u], K, w2c), frame[v, u]


def train_variant(data: dict[str, Any], cfg: Any, variant: str, loss_update: dict[str, Any]) -> dict[str, Any]:
    """Train one loss variant from the scene's start; returns the model arrays, normalisation and metrics."""
    from wonderverse.splats.model import normalization_from_cameras
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.seeding import initial_model
    from wonderverse.splats.trainer import normalize_views, train

    p = cfg.steps.splats
    with_priors, use_depth, use_normal = VARIANTS[variant]
    loss = p.train.loss.model_copy(update=loss_update)
    loss = loss.model_copy(
        update={
            "lambda_depth": loss.lambda_depth if use_depth else 0.0,
            "lambda_normal": loss.lambda_normal if use_normal else 0.0,
        }
    )
    tp = p.train.model_copy(update={"loss": loss, "holdout_every": HOLDOUT, "checkpoint_every_iters": 10**9})
    views = data["views"]
    if not with_priors:  # as the pipeline trains with both prior backends set to none
        views = views.replace(prior_depth=None, prior_normals=None)
    norm = normalization_from_cameras(views.w2c, data["points"])
    nviews = normalize_views(views, norm)
    model = initial_model(nviews, norm.apply(data["points"]), data["colors"], p)
    renderer = make_renderer("auto")
    t0 = time.perf_counter()
    model, _, metrics = train(model, nviews, tp, renderer)
    return {
        "arrays": model.to_numpy(),
        "norm": norm,
        "psnr": metrics.get("test_psnr", float("nan")),
        "seconds": time.perf_counter() - t0,
        "gaussians": model.num_gaussians,
        "renderer": renderer,
    }


def score(data: dict[str, Any], run: dict[str, Any], cfg: Any) -> dict[str, float]:
    """Held-out depth and normal errors, and the mesh against the world (module docstring)."""
    from wonderverse.metrics import depth_errors
    from wonderverse.splats.trainer import split_views
    from wonderverse.splats.views import render_views

    views = data["views"]
    h, w = views.frames.shape[1:3]
    rendered = list(render_views(run["arrays"], run["norm"], views.w2c, views.K, w, h, run["renderer"]))
    _, held = split_views(len(views), HOLDOUT)
    pred = np.stack([rendered[i].depth for i in held])
    absrel = depth_errors(pred, data["gt_depth"][held], mask=np.isfinite(pred))["absrel"]
    angles = []
    for i in held:
        n_hat, n_gt = rendered[i].normals, data["gt_normals"][i]
        ok = np.isfinite(rendered[i].depth) & (np.linalg.norm(n_gt, axis=-1) > 0.5)
        ok &= np.linalg.norm(n_hat, axis=-1) > 1e-6
        cos = np.clip((n_hat[ok] * n_gt[ok]).sum(-1), -1.0, 1.0)
        angles.append(np.degrees(np.arccos(cos)))
    images = [(r.rgb, r.depth) for r in rendered]
    mesh = mesh_scores(data, images, cfg)
    whole = mesh_scores(data, images, cfg, max_depth_frac=FULL_REACH)
    return {
        "absrel": float(absrel),
        "normal_deg": float(np.mean(np.concatenate(angles))) if angles else float("nan"),
        **mesh,
        "f1_full_reach": whole["f1"],
    }


def mesh_scores(
    data: dict[str, Any], images: list[tuple[np.ndarray, np.ndarray]], cfg: Any, max_depth_frac: float | None = None
) -> dict[str, float]:
    """F@1 % and Chamfer (m) of the preset's mesh (its fusion reach, or `max_depth_frac`) fused from (rgb, depth)
    at every view, against the world."""
    from scipy.spatial import cKDTree

    from benchmarks.mesh import visible_gt_points
    from wonderverse.mesh import clean_mesh
    from wonderverse.metrics import chamfer_fscore, sample_mesh_points
    from wonderverse.tsdf import TsdfFusion

    views = data["views"]
    h, w = views.frames.shape[1:3]
    extent = scene_extent_of(data)
    mesh_params = cfg.steps.outputs.mesh
    if max_depth_frac is not None:
        mesh_params = mesh_params.model_copy(update={"max_depth_frac": max_depth_frac})
    fusion = TsdfFusion(extent, mesh_params)
    for (rgb, depth), pose in zip(images, views.w2c, strict=True):
        fusion.integrate(rgb, depth, views.K, pose)
    mesh = clean_mesh(fusion.extract(), mesh_params)
    if "gt_points" not in data:
        data["gt_points"] = visible_gt_points(data["world"], views.K, views.w2c, data["gt_depth"], np.inf)
        data["determinable"] = determinable(data["gt_points"], views.K, views.w2c, 0.01 * extent, h, w)
    pred_pts = sample_mesh_points(mesh.vertices, mesh.triangles, PRED_SAMPLES, seed=1)
    m = chamfer_fscore(pred_pts, data["gt_points"], [0.01 * extent])
    sub, ok = data["determinable"]
    near = ok[cKDTree(sub).query(pred_pts, workers=1)[1]]
    d = chamfer_fscore(pred_pts[near], sub[ok], [0.01 * extent])
    return {"f1": float(m["fscore"][0]), "chamfer_m": float(m["chamfer"]), "f1_determined": float(d["fscore"][0])}


def determinable(
    points: np.ndarray, K: np.ndarray, w2c: np.ndarray, tolerance: float, h: int, w: int
) -> tuple[np.ndarray, np.ndarray]:
    """A sample of `points` (M,3) and, per point, whether triangulation from the cameras that frame it (W2C
    (N,4,4), K at h×w) can give its depth within `tolerance` at `MATCH_SIGMA_PX` (module docstring)."""
    rng = np.random.default_rng(0)
    sub = points[rng.choice(len(points), min(DETERMINABLE_SAMPLES, len(points)), replace=False)]
    centres = np.stack([-c[:3, :3].T @ c[:3, 3] for c in w2c])
    cam = np.einsum("nij,pj->npi", w2c[:, :3, :3], sub) + w2c[:, None, :3, 3]  # (N,P,3)
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = K[0, 0] * cam[..., 0] / z + K[0, 2], K[1, 1] * cam[..., 1] / z + K[1, 2]
    framed = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)  # (N,P)
    rays = sub[None] - centres[:, None]
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    widest = np.zeros(len(sub))
    for start in range(0, len(sub), 2000):
        part = slice(start, start + 2000)
        r, f = rays[:, part].transpose(1, 0, 2), framed[:, part].T  # (p,N,3), (p,N)
        cos = np.einsum("pik,pjk->pij", r, r)
        cos = np.where(f[:, :, None] & f[:, None, :], cos, 1.0)
        widest[part] = np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0))
    nearest = np.where(framed, z, np.inf).min(axis=0)
    sigma = nearest * MATCH_SIGMA_PX / K[0, 0] / np.maximum(widest, 1e-12)
    return sub, sigma < tolerance


def placed_by_prior(
    points: np.ndarray, K: np.ndarray, w2c: np.ndarray, prior: np.ndarray, tolerance: float
) -> np.ndarray:
    """(M,) bool: whether some view that frames the point (W2C (N,4,4), K, aligned prior depth (N,H,W)) has a
    prior that puts it within `tolerance` along its ray (an occluded point meets the occluder's depth and fails)."""
    from wonderverse.camera import world_to_pixels

    h, w = prior.shape[1:]
    placed = np.zeros(len(points), bool)
    for pose, depth in zip(w2c, prior, strict=True):
        u, v, z, framed = world_to_pixels(points, K, pose, h, w)
        zp = np.full(len(points), np.nan)
        zp[framed] = depth[v[framed].astype(int), u[framed].astype(int)]
        with np.errstate(invalid="ignore"):  # along the ray, in metres
            off = np.abs(zp - z) * np.hypot(np.hypot((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]), 1.0)
        placed |= framed & (off < tolerance)
    return placed


def ceiling(data: dict[str, Any], cfg: Any) -> dict[str, float]:
    """The fusion's ceiling: the same mesh from the true depth at every view; and what the inputs determine."""
    views = data["views"]
    frames = views.frames
    images = [(f, d) for f, d in zip(frames, data["gt_depth"], strict=True)]
    top = mesh_scores(data, images, cfg) | {"f1_full_reach": mesh_scores(data, images, cfg, FULL_REACH)["f1"]}
    sub, parallax = data["determinable"]
    tolerance = 0.01 * scene_extent_of(data)
    prior = placed_by_prior(sub, views.K, views.w2c, views.prior_depth, tolerance)
    return top | {"parallax_bound": float(np.mean(parallax)), "input_bound": float(np.mean(parallax | prior))}


def scene_extent_of(data: dict[str, Any]) -> float:
    from wonderverse.camera import scene_extent

    return float(scene_extent(data["views"].w2c, data["gt_depth"]))


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """KEY=VALUE overrides (values parsed as JSON, else kept as strings)."""
    out: dict[str, Any] = {}
    for item in items:
        key, _, value = item.partition("=")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def headline(rows: list[dict[str, Any]], preset: str) -> dict[str, float]:
    def mean(cond: str, variant: str, key: str) -> float:
        vals = [r[key] for r in rows if r["condition"] == cond and r["variant"] == variant]
        return float(np.mean(vals)) if vals else float("nan")

    head: dict[str, float] = {}
    for base, suffix in (("rgb_seeded", ""), ("rgb", "_vs_rgb")):
        head |= {
            f"fscore_gain_lowtex{suffix}": mean("texture_poor", "both", "f1") - mean("texture_poor", base, "f1"),
            f"fscore_gain_ai{suffix}": mean("ai_like", "both", "f1") - mean("ai_like", base, "f1"),
            f"depth_gain_ai{suffix}": 1.0 - mean("ai_like", "both", "absrel") / mean("ai_like", base, "absrel"),
            f"psnr_cost_clean_db{suffix}": mean("clean", base, "psnr") - mean("clean", "both", "psnr"),
        }
    if preset in ("standard", "high"):
        both = [r for r in rows if r["variant"] == "both"]
        head[f"fscore_{preset}"] = float(np.mean([r["f1"] for r in both]))
        head[f"fscore_{preset}_determined"] = float(np.mean([r.get("f1_determined", np.nan) for r in both]))
        head["parallax_bound"] = float(np.mean([r.get("parallax_bound", np.nan) for r in both]))
        head["input_bound"] = float(np.mean([r.get("input_bound", np.nan) for r in both]))
    return {k: round(v, 4) for k, v in head.items()}


def merge_rows(runs: list[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """The rows of several runs, a later run's row replacing an earlier one of the same world, condition,
    variant, defect, prior, loss and train changes (a re-measured variant in place of the old one)."""
    merged = {
        (r["world"], r["condition"], r["variant"], *(r.get(k, "") for k in ("defects", "prior", "loss", "train"))): r
        for rows in runs
        for r in rows
    }
    return list(merged.values())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="160x112 frames, 9 per segment, 120 iterations")
    ap.add_argument("--preset", default="preview", choices=["preview", "standard", "high"])
    ap.add_argument("--worlds", nargs="*", default=list(WORLDS), choices=list(WORLDS))
    ap.add_argument("--conditions", nargs="*", default=list(CONDITIONS), choices=list(CONDITIONS))
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--loss", nargs="*", default=[], help="LossParams overrides KEY=VALUE for every variant")
    ap.add_argument("--mesh", nargs="*", default=[], help="MeshParams overrides KEY=VALUE (steps.outputs.mesh)")
    ap.add_argument("--train", nargs="*", default=[], help="steps.splats.train overrides KEY=VALUE (not loss)")
    ap.add_argument("--defects", nargs="*", default=[], help="DefectParams overrides KEY=VALUE of each condition")
    ap.add_argument("--prior", nargs="*", default=[], help="OracleDegradation overrides KEY=VALUE of the prior")
    ap.add_argument("--out", type=Path, help="also write the rows here (JSON), to merge runs made apart")
    ap.add_argument("--merge", nargs="*", type=Path, help="only merge rows written by --out runs and report them")
    args = ap.parse_args()
    if args.merge:
        rows = merge_rows([json.loads(f.read_text()) for f in args.merge])
        report(f"Enhancement ablation, {args.preset}, merged {len(args.merge)} runs", rows, headline(rows, args.preset))
        return
    from wonderverse.config import build_config

    overrides: dict[str, Any] = {}
    if args.mesh:
        overrides["steps"] = {"outputs": {"mesh": parse_overrides(args.mesh)}}
    if args.quick:
        overrides |= {
            "scene": {"video": {"width": 160, "height": 112, "frames_per_segment": 9}},
            "steps": {**overrides.get("steps", {}), "splats": {"max_side_px": 160, "train": {"iterations": 120}}},
        }
    if args.train:
        splats = overrides.setdefault("steps", {}).setdefault("splats", {})
        splats["train"] = {**splats.get("train", {}), **parse_overrides(args.train)}
    cfg = build_config("benchmark", preset=args.preset, overrides=overrides)
    loss_update = parse_overrides(args.loss)
    defect_update = parse_overrides(args.defects)
    prior_update = parse_overrides(args.prior)
    rows = []
    for world in args.worlds:
        for condition in args.conditions:
            t0 = time.perf_counter()
            data = prepare(world, condition, cfg, defect_update=defect_update, prior_update=prior_update)
            prep_s = time.perf_counter() - t0
            top = ceiling(data, cfg)
            print(json.dumps({"world": world, "condition": condition, "ceiling": top}), flush=True)
            for variant in args.variants:
                run = train_variant(data, cfg, variant, loss_update)
                row = {"world": world, "condition": condition, "variant": variant}
                row |= {"defects": " ".join(args.defects)} if args.defects else {}
                row |= {"prior": " ".join(args.prior)} if args.prior else {}
                row |= {"loss": " ".join(args.loss)} if args.loss else {}
                row |= {"train": " ".join(args.train)} if args.train else {}
                row |= {"psnr": run["psnr"], **score(data, run, cfg), "gaussians": run["gaussians"]}
                row |= {"ceiling_f1": top["f1"], "ceiling_f1_full_reach": top["f1_full_reach"]}
                row |= {"parallax_bound": top["parallax_bound"], "input_bound": top["input_bound"]}
                row |= {"train_s": run["seconds"], "prepare_s": prep_s}
                rows.append(row)
                print(json.dumps({k: round(x, 4) if isinstance(x, float) else x for k, x in row.items()}), flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))
    iterations = cfg.steps.splats.train.iterations
    title = (
        f"Enhancement ablation, {args.preset}, {iterations} iterations, {machine()}, "
        f"loss {loss_update or '-'}, mesh {args.mesh or '-'}, train {args.train or '-'}, "
        f"defects {args.defects or '-'}, prior {args.prior or '-'}"
    )
    report(title, rows, headline(rows, args.preset))


if __name__ == "__main__":
    main()
