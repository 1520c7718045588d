"""Throughput of normals_from_depth (numpy, single process) on W x H depth maps.

    python -m benchmarks.bench_priors_normals --width 480 --height 320 --batch 25 --repeats 5

The depth maps are a ground plane and a wall with sky above (about a third of the pixels) and 2 %
multiplicative noise, so the edge and sky paths run as they would on a rendered frame. Prints the best
and median frames per second over `--repeats` calls on a batch of `--batch` frames (after one warm-up)
and the process CPU time per frame.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def depth_maps(batch: int, h: int, w: int, K: np.ndarray, seed: int = 0) -> np.ndarray:
    """(batch,h,w) float32 camera z: ground 1.5 m below the camera, a wall 6 m ahead, +inf sky."""
    u = np.arange(w) + 0.5
    v = np.arange(h) + 0.5
    a = (u[None, :] - K[0, 2]) / K[0, 0]
    b = (v[:, None] - K[1, 2]) / K[1, 1]
    with np.errstate(divide="ignore"):
        ground = np.where(b > 0, 1.5 / b, np.inf) + 0 * a
    wall = np.where((np.abs(a) < 0.3) & (b > -0.2), 6.0, np.inf) + 0 * b
    z = np.minimum(ground, wall)
    rng = np.random.default_rng(seed)
    noise = 1.0 + 0.02 * rng.standard_normal((batch, h, w))
    return (z[None] * noise).astype(np.float32)


def main() -> None:
    from wonderverse.camera import intrinsics
    from wonderverse.priors import normals_from_depth

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--height", type=int, default=320)
    ap.add_argument("--batch", type=int, default=25)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    K = intrinsics(args.width, args.height, 60.0)
    z = depth_maps(args.batch, args.height, args.width, K)
    normals_from_depth(z, K)  # warm-up
    walls, cpus = [], []
    for _ in range(args.repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        _, valid = normals_from_depth(z, K)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    fps = [args.batch / t for t in walls]
    print(
        f"normals_from_depth {args.width}x{args.height}, batch {args.batch}: "
        f"best {max(fps):.1f} fps, median {statistics.median(fps):.1f} fps, "
        f"CPU {1e3 * statistics.median(cpus) / args.batch:.2f} ms/frame, valid {valid.mean():.2f}"
    )


if __name__ == "__main__":
    main()
