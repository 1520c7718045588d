"""CPU speed of the torch rasteriser: forward + backward of one view, N Gaussians at W x H.

    python -m benchmarks.bench_splats_render --n 20000 --width 256 --height 144 --threads 2

The scene is random but image-filling: means uniform in the view frustum at depth 2..8, per-axis sigmas
log-normal around `--sigma-px` pixels, random rotations, opacities uniform in [0.1, 0.9]. Prints the
best and median wall time and process CPU time over `--repeats` runs (after one warm-up), with the
number of tile intersections and drawn (Gaussian, pixel) pairs, which set the cost.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

# Idle OpenMP threads sleep instead of spinning: on a shared machine a spinning thread waiting for a
# descheduled partner makes two threads several times slower than one. Must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main() -> None:
    import torch

    from wonderverse.camera import intrinsics
    from wonderverse.splats.render_torch import render

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=144)
    ap.add_argument("--sigma-px", type=float, default=1.5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tile-size", type=int, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    n, w, h = args.n, args.width, args.height
    K = torch.tensor(intrinsics(w, h, 60.0), dtype=torch.float32)
    fx = float(K[0, 0])
    z = torch.rand(n) * 6 + 2
    x = (torch.rand(n) * 2 - 1) * z * (w / 2) / fx
    y = (torch.rand(n) * 2 - 1) * z * (h / 2) / fx
    means = torch.stack([x, y, z], 1).requires_grad_()
    log_scales = (torch.log(z[:, None] * args.sigma_px / fx) + 0.5 * torch.randn(n, 3)).requires_grad_()
    quats = torch.randn(n, 4).requires_grad_()
    logit_op = torch.logit(torch.rand(n) * 0.8 + 0.1).requires_grad_()
    colors = torch.rand(n, 3).requires_grad_()
    kw = {} if args.tile_size is None else {"tile_size": args.tile_size}
    walls, cpus = [], []
    info = {}
    for i in range(args.repeats + 1):
        t0, c0 = time.perf_counter(), time.process_time()
        rgb, depth, alpha, normals, info = render(
            means, quats, log_scales.exp(), logit_op.sigmoid(), colors, torch.eye(4), K, w, h, **kw
        )
        (rgb.mean() + depth.mean() + normals.abs().mean() + alpha.mean()).backward()
        if i:
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
    print("| N | W x H | threads | isects | pairs/pixel | wall best/median s | CPU best/median s |")
    print(
        f"| {n} | {w}x{h} | {args.threads} | {info['n_isects']} | {info['n_pairs'] / (w * h):.1f} | "
        f"{min(walls):.3f} / {statistics.median(walls):.3f} | {min(cpus):.3f} / {statistics.median(cpus):.3f} |"
    )


if __name__ == "__main__":
    main()
