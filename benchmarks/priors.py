"""Depth and normal priors against procedural ground truth, per backend and degradation level.

For each procedural scene the oracle depth prior (ground truth degraded like a monocular network:
unknown per-frame scale/shift, low-frequency warp, noise, edge blur) is aligned per image to ~500
sparse ground-truth depths (standing in for SfM points) and scored; normals are scored for the oracle
normal prior and for normals computed from the aligned depth (the embedded default). Depth Anything V2
and the DPT normal model need weights, which these machines do not have: they are not scored here.

Last-line keys: `depth_absrel`, `depth_delta1` (aligned oracle depth at the default "realistic"
level), `normal_mean_deg` (normals from that aligned depth, the default normal backend),
`normals_fps` (normals_from_depth frames/s at 480x320 on real rendered depth).
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks.common import parse_args, report
from benchmarks.detection import PROMPTS
from wonderverse.camera import move_path
from wonderverse.metrics import depth_errors, normal_errors
from wonderverse.priors import align_scale_shift, normals_from_depth
from wonderverse.priors.from_depth import NormalsFromDepth
from wonderverse.priors.oracle import OracleDepth, OracleNormals
from wonderverse.video import initial_pose
from wonderverse.video.procedural import ProceduralVideo

LEVELS = ("none", "mild", "realistic", "harsh")


def render(prompt: str, seed: int, w: int, h: int, n: int):
    model = ProceduralVideo(prompt, seed, w, h, 60.0, {"fault_probability": 0.0})
    path = move_path(initial_pose(model), np.radians(25), 0.0, 1.5, 1.0, n)
    return model.generate("bench", path, seed, None)


def sparse_reference(gt: np.ndarray, rng: np.random.Generator, n: int = 500) -> np.ndarray:
    """(n,3) (u, v, z) samples of finite ground-truth depth at random pixels (pixel centres +0.5)."""
    rows, cols = np.nonzero(np.isfinite(gt) & (gt > 0))
    pick = rng.choice(len(rows), size=min(n, len(rows)), replace=False)
    return np.column_stack([cols[pick] + 0.5, rows[pick] + 0.5, gt[rows[pick], cols[pick]]])


def main() -> None:
    args = parse_args(__doc__ or "")
    w, h, n = (160, 112, 4) if args.quick else (320, 208, 10)
    scenes = [render(p, i, w, h, n) for i, p in enumerate(PROMPTS[: 2 if args.quick else 4])]
    rng = np.random.default_rng(0)
    rows, head = [], {}
    for level in LEVELS:
        d_err, n_or, n_fd = [], [], []
        for v in scenes:
            gt_d, gt_n, K = v.gt.depth, v.gt.normals.astype(np.float32), v.K
            pred = OracleDepth(gt_d, level, "inverse_depth", seed=1).predict(v.frames)
            aligned = np.stack(
                [
                    align_scale_shift(pred.depth[t], sparse_reference(gt_d[t], rng), space=pred.kind).aligned_depth
                    for t in range(len(gt_d))
                ]
            )
            sky = ~np.isfinite(gt_d)
            d_err.append(depth_errors(aligned, gt_d, mask=~sky))
            n_or.append(normal_errors(OracleNormals(gt_n, level, seed=1).predict(v.frames).normals, gt_n))
            n_fd.append(normal_errors(NormalsFromDepth().predict(v.frames, K=K, depth=aligned).normals, gt_n))
        mean = lambda es, k: float(np.mean([e[k] for e in es]))  # noqa: E731
        rows.append(
            {
                "prior": f"oracle depth ({level})",
                "absrel": mean(d_err, "absrel"),
                "delta1": mean(d_err, "delta1"),
                "normal_mean_deg": float("nan"),
                "normal_median_deg": float("nan"),
                "pct_11_25": float("nan"),
            }
        )
        for name, es in ((f"oracle normals ({level})", n_or), (f"normals from aligned depth ({level})", n_fd)):
            rows.append(
                {
                    "prior": name,
                    "absrel": float("nan"),
                    "delta1": float("nan"),
                    "normal_mean_deg": mean(es, "mean_deg"),
                    "normal_median_deg": mean(es, "median_deg"),
                    "pct_11_25": mean(es, "pct_11_25"),
                }
            )
        if level == "realistic":
            head = {
                "depth_absrel": round(mean(d_err, "absrel"), 4),
                "depth_delta1": round(mean(d_err, "delta1"), 4),
                "normal_mean_deg": round(mean(n_fd, "mean_deg"), 2),
            }
    big = render(PROMPTS[0], 0, 480, 320, 4 if args.quick else 12)
    normals_from_depth(big.gt.depth, big.K)  # warm-up
    reps = 2 if args.quick else 5
    t = time.perf_counter()
    for _ in range(reps):
        normals_from_depth(big.gt.depth, big.K)
    fps = reps * len(big.gt.depth) / (time.perf_counter() - t)
    rows.append(
        {
            "prior": "normals_from_depth 480x320 (frames/s)",
            "absrel": float("nan"),
            "delta1": float("nan"),
            "normal_mean_deg": fps,
            "normal_median_deg": float("nan"),
            "pct_11_25": float("nan"),
        }
    )
    report("priors", rows, {**head, "normals_fps": round(fps, 1)})


if __name__ == "__main__":
    main()
