"""Splat training on a CUDA GPU: our step against gsplat's bare rasteriser, speed, memory, quality.

Two stages, because the device machine has neither Open3D nor pycolmap:
  python -m benchmarks.gpu_step --prepare .gpu/scene.npz   # here: render a procedural scene + priors
  python -m benchmarks.gpu_step --data .gpu/scene.npz      # there: train and measure (gsplat backend)

The scene is the procedural "small house decorated for Christmas" (two segments at 480x320); priors are
the oracle at the "realistic" level aligned to sparse ground-truth depths (standing in for SfM points),
normals computed from that depth. Training uses the `standard` preset's TrainParams; every 8th view is
held out.

Last-line keys:
- `step_ratio_vs_gsplat`: our full training step ÷ gsplat's bare `rasterization` forward + backward on
  the same Gaussians and camera, measured in alternation after training: `ROUNDS` rounds, each
  `ROUND_STEPS` more training steps resumed from the trained state (their mean step time without the
  first `ROUND_WARMUP`), then the median of 50 bare passes on the same Gaussians; the median of the
  rounds' ratios. Alternating matters: both sides are host-bound, and the device machine's host speed
  drifted by up to 50 % between measurements minutes apart (2026-11-23, docs/benchmarks.md). Our step is a
  mean because the trainer queues work without waiting for the device (except inside gsplat's tile
  intersection).
- `ours_step_ms`, `gsplat_fwd_bwd_ms`: the rounds' medians; `step_ratio_in_run`: the figure of the runs
  before 2026-11-23 (mean step over the run's last 1000 iterations ÷ one bare measurement after the run).
- `iters_per_s`, `peak_gpu_gb` (standard preset), `psnr_heldout`, `psnr_heldout_no_geo` (without depth
  and normal losses), `depth_absrel`, `depth_absrel_no_geo` (rendered depth on held-out views against
  ground truth).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

HOLDOUT = 8
ROUNDS, ROUND_STEPS, ROUND_WARMUP = 5, 300, 50


def prepare(out: Path) -> None:
    from benchmarks.priors import sparse_reference
    from wonderverse.camera import move_path
    from wonderverse.priors import align_scale_shift
    from wonderverse.priors.oracle import OracleDepth
    from wonderverse.video import initial_pose
    from wonderverse.video.procedural import ProceduralVideo

    model = ProceduralVideo("a small house decorated for Christmas", 0, 480, 320, 60.0, {"fault_probability": 0})
    p0 = move_path(initial_pose(model), np.radians(-30), 0.0, 2.0, -1.2, 25)
    path = np.concatenate([p0, move_path(p0[-1], np.radians(-35), 0.0, 0.5, -1.4, 25)[1:]])
    v = model.generate("bench", path, 0, None)
    rng = np.random.default_rng(0)
    pred = OracleDepth(v.gt.depth, "realistic", "inverse_depth", seed=1).predict(v.frames)
    prior = np.stack(
        [
            align_scale_shift(pred.depth[t], sparse_reference(v.gt.depth[t], rng), space=pred.kind).aligned_depth
            for t in range(len(path))
        ]
    )
    prior[~np.isfinite(v.gt.depth)] = np.inf  # sky stays sky
    held = np.arange(HOLDOUT - 1, len(path), HOLDOUT)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out,
        frames=v.frames,
        w2c=path,
        K=v.K,
        prior_depth=prior.astype(np.float16),
        gt_depth_heldout=v.gt.depth[held].astype(np.float32),
        held=held,
    )


VARIANTS = {  # name: loss overrides (None = the preset's loss)
    "rgb+depth+normal": {},
    "rgb only": {"lambda_depth": 0.0, "lambda_normal": 0.0},
    "rgb+depth": {"lambda_normal": 0.0},
    "rgb+depth (D/alpha)+normal": {"depth_use_expected": True},
    "rgb+depth (D/alpha)": {"depth_use_expected": True, "lambda_normal": 0.0},
}


def _train(data: dict, loss_update: dict, iterations: int | None, backend: str) -> dict:
    import torch

    from wonderverse.config import build_config
    from wonderverse.metrics import depth_errors
    from wonderverse.priors.from_depth import NormalsFromDepth
    from wonderverse.splats.data import backproject_depth
    from wonderverse.splats.model import init_from_points, normalization_from_cameras, voxel_downsample
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.trainer import Views, auto_scene_scale, normalize_views, train

    step = build_config("x", preset="standard").steps.splats
    loss = step.train.loss.model_copy(update=loss_update)
    params = step.train.model_copy(update={"loss": loss, "holdout_every": HOLDOUT})
    if iterations is not None:
        params = params.model_copy(update={"iterations": iterations})
    params = params.model_copy(update={"checkpoint_every_iters": params.iterations})  # one snapshot, at the end
    depth = data["prior_depth"].astype(np.float32)
    normals = NormalsFromDepth().predict(data["frames"], K=data["K"], depth=depth).normals  # as the priors step
    views = Views(frames=data["frames"], w2c=data["w2c"], K=data["K"], prior_depth=depth, prior_normals=normals)
    norm = normalization_from_cameras(views.w2c)
    nv = normalize_views(views, norm)
    pts, cols = backproject_depth(nv, step.init_depth_stride_px, step.init_depth_frame_stride)
    pts, rgb = voxel_downsample(pts, cols / 255.0, step.init_voxel_frac * auto_scene_scale(nv.w2c, pts))
    model = init_from_points(pts, rgb, params.sh_degree, init_opacity=step.init_opacity)
    renderer = make_renderer(backend)
    cuda = torch.cuda.is_available()
    dev = "cuda" if cuda else "cpu"
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    t = time.perf_counter()
    final: dict = {}
    model, curves, metrics = train(model, nv, params, renderer, checkpoint_cb=lambda _s, state: final.update(state))
    if cuda:
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t
    # held-out rendered depth (expected depth = Σwz / alpha) back in metres against ground truth
    errs = []
    m = model.to(dev)
    h, w = nv.frames.shape[1:3]
    for j, i in enumerate(data["held"]):
        with torch.no_grad():
            _, d, a, _, _ = renderer(
                m.means,
                m.quats,
                torch.exp(m.log_scales),
                torch.sigmoid(m.logit_opacities),
                torch.cat([m.sh0, m.shN], 1),
                torch.tensor(nv.w2c[i], dtype=torch.float32, device=dev),
                torch.tensor(nv.K, dtype=torch.float32, device=dev),
                w,
                h,
                sh_degree=params.sh_degree,
            )
        z = (d / a.clamp_min(1e-6)).squeeze(-1).cpu().numpy() / norm.s
        ok = a.squeeze(-1).cpu().numpy() > 0.5
        errs.append(depth_errors(z, data["gt_depth_heldout"][j], mask=ok)["absrel"])
    return {
        "model": model,
        "renderer": renderer,
        "views": nv,
        "params": params,
        "curves": curves,
        "seconds": seconds,
        "psnr": metrics.get("test_psnr"),
        "ssim": metrics.get("test_ssim"),
        "n": model.num_gaussians,
        "peak_gb": torch.cuda.max_memory_allocated() / 1e9 if cuda else float("nan"),
        "depth_absrel": float(np.nanmean(errs)),
        "state": final,
    }


def alternating_ratio(run: dict) -> tuple[float, float, float]:
    """(median ratio, median our step s, median bare s) over `ROUNDS` rounds of resumed training steps
    followed by bare gsplat passes on the same Gaussians (see the module docstring)."""
    from wonderverse.splats.trainer import train

    model, state = run["model"], run["state"]
    ratios, ours, bare = [], [], []
    for _ in range(ROUNDS):
        params = run["params"].model_copy(update={"iterations": state["step"] + ROUND_STEPS})
        model, curves, _ = train(
            model, run["views"], params, run["renderer"], lambda _s, st: state.update(st), resume_state=dict(state)
        )
        ours.append(float(np.mean(curves["step_s"][-(ROUND_STEPS - ROUND_WARMUP) :])))
        bare.append(bare_gsplat_seconds(model, run["views"]))
        ratios.append(ours[-1] / bare[-1])
        print(
            f"round {len(ratios)}: our step {1e3 * ours[-1]:.2f} ms, gsplat {1e3 * bare[-1]:.2f} ms, {ratios[-1]:.3f}"
        )
    return float(np.median(ratios)), float(np.median(ours)), float(np.median(bare))


def bare_gsplat_seconds(model, views, reps: int = 50) -> float:
    """Median seconds of gsplat.rasterization forward + backward (RGB, SH) on one view."""
    import torch
    from gsplat import rasterization

    h, w = views.frames.shape[1:3]
    params = {k: p.detach().clone().requires_grad_(True) for k, p in model.param_dict().items()}
    vm = torch.tensor(views.w2c[0], dtype=torch.float32, device="cuda")[None]
    K = torch.tensor(views.K, dtype=torch.float32, device="cuda")[None]
    times = []
    for _ in range(reps + 5):
        torch.cuda.synchronize()
        t = time.perf_counter()
        colors = torch.cat([params["sh0"], params["shN"]], 1)
        img, _, _ = rasterization(
            params["means"],
            params["quats"],
            torch.exp(params["log_scales"]),
            torch.sigmoid(params["logit_opacities"]),
            colors,
            vm,
            K,
            w,
            h,
            sh_degree=model.sh_degree,
        )
        img.sum().backward()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    return float(np.median(times[5:]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--prepare", type=Path, help="render the scene and write it here (needs Open3D)")
    ap.add_argument("--data", type=Path, help="train on this prepared scene (needs CUDA and gsplat)")
    ap.add_argument("--skip-ablation", action="store_true")
    ap.add_argument("--variants", nargs="*", default=["rgb+depth+normal", "rgb only"], choices=list(VARIANTS))
    ap.add_argument("--iterations", type=int, help="override the standard preset's iteration count")
    ap.add_argument("--renderer", default="gsplat", help="gsplat (default) or torch for a CPU smoke run")
    args = ap.parse_args()
    if args.prepare:
        prepare(args.prepare)
        print(f"wrote {args.prepare} ({args.prepare.stat().st_size / 1e6:.1f} MB)")
        return
    data = dict(np.load(args.data))
    runs = {}
    for name in args.variants[:1] if args.skip_ablation else args.variants:
        runs[name] = _train(data, VARIANTS[name], args.iterations, args.renderer)
    first = runs[args.variants[0]]
    in_run = float(np.mean(first["curves"]["step_s"][-1000:]))
    nan = float("nan")
    bare_after = bare_gsplat_seconds(first["model"], first["views"]) if args.renderer == "gsplat" else nan
    ratio, ours, bare = alternating_ratio(first) if args.renderer == "gsplat" else (nan, in_run, nan)
    for name, r in runs.items():
        row = {
            "run": name,
            "iters": r["params"].iterations,
            "seconds": r["seconds"],
            "gaussians": r["n"],
            "psnr": r["psnr"],
            "ssim": r["ssim"],
            "depth_absrel": r["depth_absrel"],
            "peak_gb": r["peak_gb"],
        }
        print(" | ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()))
    head = {
        "step_ratio_vs_gsplat": round(ratio, 3),
        "ours_step_ms": round(1e3 * ours, 2),
        "gsplat_fwd_bwd_ms": round(1e3 * bare, 2),
        "step_ratio_in_run": round(in_run / bare_after, 3),
        "iters_per_s": round(first["params"].iterations / first["seconds"], 1),
        "peak_gpu_gb": round(first["peak_gb"], 3),
        "psnr_heldout": round(first["psnr"], 2),
        "depth_absrel": round(first["depth_absrel"], 4),
    }
    if "rgb only" in runs:
        r = runs["rgb only"]
        head |= {"psnr_heldout_no_geo": round(r["psnr"], 2), "depth_absrel_no_geo": round(r["depth_absrel"], 4)}
    print(json.dumps(head), flush=True)


if __name__ == "__main__":
    main()
