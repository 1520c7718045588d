"""Splats on the CPU: rasteriser speed, and quality with and without the depth and normal losses.

- Speed: seconds per forward + backward of the CPU rasteriser, 20k image-filling Gaussians at 256x144
  (depth 2-8, on-screen sigma log-normal about 1.5 px, one thread), with its C++ kernels (`native_raster`) and
  with the vectorised torch code alone, measured in alternation.
- Quality (the paper's ablation, small scale for a CPU): a procedural scene (12 views at 96x64, every 4th
  held out) trained 300 iterations from back-projected prior depth, with priors at the oracle's
  "realistic" level aligned to sparse ground-truth depths: held-out PSNR/SSIM and rendered-depth AbsRel
  against ground truth, for RGB only and RGB + depth + normal.
- Real capture: the fox (`../shared/data/instant_ngp_fox`, 50 frames): our SfM at 320 px gives poses and
  points, then 300 iterations at 160 px; held-out PSNR (every 8th frame).
GPU figures come from `benchmarks.gpu_step` on the device machine.

Last-line keys: `cpu_s_per_iter` (with the kernels), `cpu_s_per_iter_torch` (without), `kernel_speedup` (their
ratio), `psnr_heldout`, `depth_absrel`, `psnr_heldout_no_geo`, `psnr_fox`.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads

import numpy as np

from benchmarks.common import parse_args, report

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def cpu_seconds_per_iter(
    n: int = 20_000, width: int = 256, height: int = 144, reps: int = 3, kernels: bool = True
) -> float:
    """Median seconds of one forward + backward of the CPU rasteriser on an image-filling random scene, with its
    C++ kernels or (`kernels` False) with the torch code alone."""
    import torch

    from wonderverse.camera import intrinsics
    from wonderverse.splats import native_raster
    from wonderverse.splats.render_torch import render

    usable = native_raster.usable
    if not kernels:
        native_raster.usable = lambda values: False  # type: ignore[assignment]

    g = torch.Generator().manual_seed(0)
    K = torch.tensor(intrinsics(width, height, 60.0), dtype=torch.float32)
    z = torch.rand(n, generator=g) * 6 + 2
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([width / K[0, 0], height / K[1, 1]]) * z[:, None]
    means = torch.cat([xy, z[:, None]], 1).requires_grad_()
    quats = torch.randn(n, 4, generator=g).requires_grad_()
    # per-axis sigma log-normal about 1.5 px on screen: the size of Gaussians in a trained scene
    scales = (z[:, None] * 1.5 / K[0, 0] * torch.exp(0.5 * torch.randn(n, 3, generator=g))).requires_grad_()
    opac = (torch.rand(n, generator=g) * 0.8 + 0.1).requires_grad_()
    colors = torch.rand(n, 3, generator=g).requires_grad_()
    times = []
    for _ in range(reps + 1):
        t = time.perf_counter()
        rgb, depth, _, normals, _ = render(means, quats, scales, opac, colors, torch.eye(4), K, width, height)
        (rgb.sum() + depth.sum() + normals.sum()).backward()
        times.append(time.perf_counter() - t)
    native_raster.usable = usable  # type: ignore[assignment]
    return float(np.median(times[1:]))


def _heldout_depth_absrel(model, views, test_ids, renderer, norm, gt_depth) -> float:
    import torch

    from wonderverse.metrics import depth_errors

    h, w = views.frames.shape[1:3]
    errs = []
    for i in test_ids:
        with torch.no_grad():
            _, d, a, _, _ = renderer(
                model.means,
                model.quats,
                torch.exp(model.log_scales),
                torch.sigmoid(model.logit_opacities),
                torch.cat([model.sh0, model.shN], 1),
                torch.tensor(views.w2c[i], dtype=torch.float32),
                torch.tensor(views.K, dtype=torch.float32),
                w,
                h,
                sh_degree=model.sh_degree,
            )
        z = (d / a.clamp_min(1e-6))[..., 0].numpy() / norm.s
        errs.append(depth_errors(z, gt_depth[i], mask=a[..., 0].numpy() > 0.5)["absrel"])
    return float(np.mean(errs))


def ablation(iterations: int) -> list[dict]:
    from benchmarks.priors import sparse_reference
    from wonderverse.priors import align_scale_shift
    from wonderverse.priors.from_depth import NormalsFromDepth
    from wonderverse.priors.oracle import OracleDepth
    from wonderverse.splats.data import backproject_depth
    from wonderverse.splats.model import init_from_points, normalization_from_cameras
    from wonderverse.splats.params import LossParams, TrainParams
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.trainer import Views, normalize_views, train
    from wonderverse.video.procedural import ProceduralVideo, demo_path

    w, h, t = 96, 64, 12
    video = ProceduralVideo("a small house decorated for Christmas", 0, w, h, 60.0, {"fault_probability": 0.0})
    path = demo_path(video.world.start_pose(), t, yaw_deg=15.0, forward_m=0.8)
    v = video.generate("", path, 0, None)
    rng = np.random.default_rng(0)
    pred = OracleDepth(v.gt.depth, "realistic", "inverse_depth", seed=1).predict(v.frames)
    prior = np.stack(
        [
            align_scale_shift(pred.depth[i], sparse_reference(v.gt.depth[i], rng), space=pred.kind).aligned_depth
            for i in range(t)
        ]
    )
    prior[~np.isfinite(v.gt.depth)] = np.inf
    normals = NormalsFromDepth().predict(v.frames, K=v.K, depth=prior).normals
    norm = normalization_from_cameras(path)
    views = Views(frames=v.frames, w2c=path, K=v.K, prior_depth=prior, prior_normals=normals)
    views = normalize_views(views, norm)
    pts, cols = backproject_depth(views, 3, 3)
    renderer = make_renderer("torch")
    rows = []
    for name, loss in (
        ("RGB only", LossParams(lambda_depth=0.0, lambda_normal=0.0)),
        ("RGB + depth + normal", LossParams()),
    ):
        model = init_from_points(pts, cols / 255.0, 1, init_opacity=0.1)
        params = TrainParams(iterations=iterations, sh_degree=1, holdout_every=4, loss=loss)
        t0 = time.perf_counter()
        model, _, m = train(model, views, params, renderer)
        rows.append(
            {
                "what": f"procedural ablation: {name}",
                "psnr": m["test_psnr"],
                "ssim": m["test_ssim"],
                "depth_absrel": _heldout_depth_absrel(model, views, m["test_views"], renderer, norm, v.gt.depth),
                "seconds": time.perf_counter() - t0,
            }
        )
    return rows


def fox(iterations: int) -> dict | None:
    fox_dir = DATA / "instant_ngp_fox" / "images"
    if not fox_dir.is_dir():
        return None
    from PIL import Image

    from wonderverse.sfm import SfmParams, reconstruct
    from wonderverse.splats.data import downscale_views
    from wonderverse.splats.model import init_from_points, normalization_from_cameras
    from wonderverse.splats.params import TrainParams
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.trainer import Views, normalize_views, train

    paths = sorted(fox_dir.glob("*.jpg"))
    t0 = time.perf_counter()
    res = reconstruct(paths, SfmParams(max_image_size_px=320, num_threads=2))  # the files, read by COLMAP
    ok = res.registered
    frames = np.stack([np.asarray(Image.open(p).convert("RGB").resize((320, 569))) for p in paths])[ok]
    K = res.K.copy()
    K[:2] *= 320 / 1080  # full-size pixels -> 320 px wide frames
    views = downscale_views(Views(frames=frames, w2c=res.poses[ok], K=K), 160)
    norm = normalization_from_cameras(views.w2c, res.points)
    nv = normalize_views(views, norm)
    model = init_from_points(norm.apply(res.points), res.colors / 255.0, 1, init_opacity=0.1)
    _, _, m = train(model, nv, TrainParams(iterations=iterations, sh_degree=1, holdout_every=8), make_renderer("torch"))
    return {
        "what": f"fox: {int(ok.sum())}/{len(paths)} frames posed by our SfM",
        "psnr": m["test_psnr"],
        "ssim": m["test_ssim"],
        "depth_absrel": float("nan"),
        "seconds": time.perf_counter() - t0,
    }


def main() -> None:
    args = parse_args(__doc__ or "")
    import torch

    torch.set_num_threads(1)
    iters = 100 if args.quick else 300
    # in alternation, so that the machine's other load falls on both alike
    reps = 1 if args.quick else 3
    both = [(cpu_seconds_per_iter(reps=reps), cpu_seconds_per_iter(reps=reps, kernels=False)) for _ in range(reps)]
    s_per_iter, s_torch = (float(np.median(v)) for v in zip(*both, strict=True))
    rows = [
        {
            "what": f"rasteriser fwd+bwd, 20k Gaussians 256x144 (s){label}",
            "psnr": float("nan"),
            "ssim": float("nan"),
            "depth_absrel": float("nan"),
            "seconds": seconds,
        }
        for label, seconds in (("", s_per_iter), (", torch alone", s_torch))
    ]
    rows += ablation(iters)
    f = fox(iters)
    if f:
        rows.append(f)
    rgb, geo = rows[2], rows[3]
    report(
        "splats (CPU)",
        rows,
        {
            "cpu_s_per_iter": round(s_per_iter, 3),
            "cpu_s_per_iter_torch": round(s_torch, 3),
            "kernel_speedup": round(s_torch / s_per_iter, 2),
            "psnr_heldout": round(geo["psnr"], 2),
            "depth_absrel": round(geo["depth_absrel"], 4),
            "psnr_heldout_no_geo": round(rgb["psnr"], 2),
            "psnr_fox": round(f["psnr"], 2) if f else None,
        },
    )


if __name__ == "__main__":
    main()
