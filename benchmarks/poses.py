"""Pose accuracy and speed of the geometric-correction SfM, on procedural scenes and real footage.

- Per-segment ATE (Sim(3)-aligned camera centres vs the procedural ground truth, as a fraction of the
  ground-truth path length) and global ATE (the `poses` step over a whole stitched scene).
- RealEstate10K clips (`../shared/data/cameractrl_re10k`): ATE against their pose files and whether the
  check flags any of these real clips; the AI-generated clips (CameraCtrl gifs, CogVideoX samples):
  which get flagged and why.
- Seconds per 49-frame segment at 480x320, and the speed-up of 4 segments checked in parallel (Dask
  LocalCluster, one worker per core) over serial.

Last-line keys: `ate_segment_frac`, `ate_global_frac`, `re10k_ate_frac` (mean over clips),
`re10k_flagged` (count), `seconds_per_segment`, `parallel_speedup`.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import imageio.v2 as imageio
import numpy as np

from benchmarks.common import parse_args, report
from benchmarks.detection import segment
from flows.pipeline import execute
from tasks.parallel import map_segments
from wonderverse.camera import CameraPrior
from wonderverse.check import CheckParams, check_trajectory
from wonderverse.config import build_config
from wonderverse.metrics import ate
from wonderverse.schema import ATTEMPT, SFM
from wonderverse.sfm import SfmParams, reconstruct
from wonderverse.store import SceneStore

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def read_re10k_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """RealEstate10K pose file -> (W2C (T,4,4), normalised intrinsics (T,4) fx fy cx cy)."""
    rows = [ln.split() for ln in path.read_text().splitlines()[1:] if ln.strip()]
    vals = np.array([[float(x) for x in r] for r in rows])
    w2c = np.tile(np.eye(4), (len(vals), 1, 1))
    w2c[:, :3, :4] = vals[:, 7:19].reshape(-1, 3, 4)
    return w2c, vals[:, 1:5]


def read_clip(path: Path) -> np.ndarray:
    frames = [np.asarray(f)[..., :3] for f in imageio.mimread(path, memtest=False)]
    return np.stack(frames).astype(np.uint8)


def judge_clip(frames: np.ndarray, K: np.ndarray | None, sfm: SfmParams):
    """SfM and the check of a real clip; its K (the pose file's), when given, seeds a focal the mappers refine."""
    prior = None if K is None else CameraPrior(K, "given")
    res = reconstruct(frames, sfm.model_copy(update={"hold_known_intrinsics": False}), prior)
    return res, check_trajectory(res.poses, res.registered, CheckParams(), res.problems, points=res.points)


def _timed_check(i: int, width: int, height: int, frames: int) -> float:
    video = segment(i, "clean", width, height, frames)
    t = time.perf_counter()
    reconstruct(video.frames, SfmParams(max_image_size_px=width, num_threads=1), CameraPrior(video.K, "given"))
    return time.perf_counter() - t


def main() -> None:
    args = parse_args(__doc__ or "")
    rows = []
    # per-segment ATE on clean procedural segments
    n_seg = 3 if args.quick else 10
    w, h, T = (320, 208, 25) if args.quick else (480, 320, 49)
    sfm = SfmParams(max_image_size_px=w, num_threads=2)
    seg_ate, seg_s = [], []
    for i in range(n_seg):
        video = segment(500 + i, "clean", w, h, T)
        t = time.perf_counter()
        res = reconstruct(video.frames, sfm, CameraPrior(video.K, "given"))  # as the check: the renderer's K
        seg_s.append(time.perf_counter() - t)
        ok = res.registered.sum() >= 3
        seg_ate.append(ate(res.poses, video.gt.poses)["rmse_frac"] if ok else float("nan"))
    rows.append(
        {
            "what": f"procedural segment {T} frames {w}x{h}",
            "n": n_seg,
            "ate_frac": float(np.nanmean(seg_ate)),
            "flagged": 0,
            "seconds": float(np.mean(seg_s)),
        }
    )

    # global poses over a whole scene
    with tempfile.TemporaryDirectory() as tmp:
        cfg = build_config(
            "a small house decorated for Christmas",
            preset="preview",
            overrides={
                "scene": {
                    "video": {
                        "width": 320,
                        "height": 208,
                        "frames_per_segment": 17 if args.quick else 25,
                        "options": {"fault_probability": 0.0},
                    }
                }
            },
        )
        t = time.perf_counter()
        execute(Path(tmp) / "g", cfg, until="poses")
        store = SceneStore.open(Path(tmp) / "g")
        segs = store.meta(SFM.path).segments
        gt = np.stack(
            [store.array(ATTEMPT.at(seg=segs[a], attempt=0).gt.poses)[b] for a, b in store.array(SFM.frame_index)]
        )
        g_ate = ate(store.array(SFM.poses), gt)["rmse_frac"]
        rows.append(
            {
                "what": "global poses, stitched scene",
                "n": len(gt),
                "ate_frac": g_ate,
                "flagged": 0,
                "seconds": time.perf_counter() - t,
            }
        )

    # real footage
    re10k = DATA / "cameractrl_re10k"
    re_ate, re_flagged = [], 0
    if re10k.is_dir():
        clip_sfm = SfmParams(max_image_size_px=384, num_threads=2)
        for clip in sorted((re10k / "reference_videos").glob("*.mp4"))[: 2 if args.quick else None]:
            frames = read_clip(clip)
            gt, intr = read_re10k_poses(re10k / "pose_files" / f"{clip.stem}.txt")
            H, W = frames.shape[1:3]
            K = np.array([[intr[0, 0] * W, 0, intr[0, 2] * W], [0, intr[0, 1] * H, intr[0, 3] * H], [0, 0, 1]])
            t = time.perf_counter()
            res, c = judge_clip(frames, K, clip_sfm)
            a = ate(res.poses, gt[: len(frames)])["rmse_frac"] if res.registered.sum() >= 3 else float("nan")
            re_ate.append(a)
            re_flagged += int(not c.accepted)
            rows.append(
                {
                    "what": f"re10k {clip.stem}",
                    "n": len(frames),
                    "ate_frac": a,
                    "flagged": int(not c.accepted),
                    "seconds": time.perf_counter() - t,
                    "why": "; ".join(c.reasons)[:80],
                }
            )
        ai = sorted((re10k / "generated_gifs").glob("*.gif")) + sorted((DATA / "cogvideox_samples").glob("*.mp4"))
        for clip in ai[: 2 if args.quick else None]:
            frames = read_clip(clip)
            if frames.shape[2] > 480:  # CogVideoX 720x480 -> 480x320 like our standard preset
                from PIL import Image

                frames = np.stack([np.asarray(Image.fromarray(f).resize((480, 320))) for f in frames])
            t = time.perf_counter()
            res, c = judge_clip(frames, None, clip_sfm)
            rows.append(
                {
                    "what": f"AI {clip.name[:40]}",
                    "n": len(frames),
                    "ate_frac": float("nan"),
                    "flagged": int(not c.accepted),
                    "seconds": time.perf_counter() - t,
                    "why": "; ".join(c.reasons)[:80] or "-",
                }
            )

    # parallel speed-up: 4 segments, serial vs Dask LocalCluster
    n_par, pw, ph, pT = 4, 320, 208, 17 if args.quick else 25
    t = time.perf_counter()
    [_timed_check(900 + i, pw, ph, pT) for i in range(n_par)]
    serial = time.perf_counter() - t
    t = time.perf_counter()
    map_segments(_timed_check, [900 + i for i in range(n_par)], pw, ph, pT, workers=os.cpu_count() or 2)
    parallel = time.perf_counter() - t  # includes the cluster start-up: the honest figure
    rows.append(
        {
            "what": f"4 segments serial / parallel ({os.cpu_count()} workers)",
            "n": n_par,
            "ate_frac": float("nan"),
            "flagged": 0,
            "seconds": serial / parallel,
        }
    )

    for r in rows:
        r.setdefault("why", "")
    report(
        "poses",
        rows,
        {
            "ate_segment_frac": round(float(np.nanmean(seg_ate)), 5),
            "ate_global_frac": round(float(g_ate), 5),
            "re10k_ate_frac": round(float(np.nanmean(re_ate)), 5) if re_ate else None,
            "re10k_flagged": re_flagged,
            "seconds_per_segment": round(float(np.mean(seg_s)), 2),
            "parallel_speedup": round(serial / parallel, 2),
        },
    )


if __name__ == "__main__":
    main()
