"""The case behind SfM's last-resort mapper, at any size: the outdoor scene's first segment (a 30° turn
with 2 m of travel, rendered fault-free) through a preset's check SfM, with and without the fallback.

    python scripts/sfm_fallback_case.py [--preset high] [--frames 49] [--size 720 480]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from wonderverse.camera import CameraPrior, move_path
from wonderverse.check import check_trajectory
from wonderverse.config import build_config
from wonderverse.sfm import reconstruct
from wonderverse.video import initial_pose
from wonderverse.video.procedural import ProceduralVideo

PROMPT = "a small house decorated for Christmas"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="high")
    ap.add_argument("--frames", type=int, default=49)
    ap.add_argument("--size", type=int, nargs=2, default=(720, 480), metavar=("W", "H"))
    args = ap.parse_args()
    model = ProceduralVideo(PROMPT, 0, *args.size, 60.0, {"fault_probability": 0})
    path = move_path(initial_pose(model), np.radians(-30), 0.0, 2.0, -1.2, args.frames)
    video = model.generate("case", path, 0, None)
    cfg = build_config(PROMPT, preset=args.preset)
    for fallback in (False, True):
        t = time.perf_counter()
        update = {"prior_focal_fallback": fallback, "hold_known_intrinsics": False}  # the focal refined from K
        res = reconstruct(video.frames, cfg.steps.check.sfm.model_copy(update=update), CameraPrior(video.K, "given"))
        verdict = check_trajectory(res.poses, res.registered, cfg.steps.check.rules, res.problems, points=res.points)
        print(
            f"fallback={fallback}: mapper {res.mapper or '-'}, gates {res.gates_passed} {res.problems}; "
            f"check accepted {verdict.accepted} {verdict.reasons[:2]}; {time.perf_counter() - t:.1f} s"
        )


if __name__ == "__main__":
    main()
