"""Abnormal-sequence detection on procedural segments with known faults.

Every segment is rendered by the procedural world with a forced fault type (or none), posed with
`wonderverse.sfm.reconstruct` and judged by `wonderverse.check.check_trajectory` in both translation
modes (the same SfM result for both). Ground truth is the injected fault, never the code under test.
Then the real `check` step runs on whole scenes with the default fault probability to measure the
mean number of extra trials (the paper reports 0.25).

Last-line keys: `recall_teleport`, `recall_rotation`, `recall_morph`, `recall_freeze` (scale-free
mode, the default), `false_positive_rate` (clean segments rejected, scale-free mode),
`mean_extra_trials` (check step over whole scenes).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import parse_args, report
from wonderverse.camera import CameraPrior, move_path
from wonderverse.check import CheckParams, check_trajectory
from wonderverse.config import build_config
from wonderverse.schema import CHECK
from wonderverse.sfm import SfmParams, reconstruct
from wonderverse.video import Video, initial_pose
from wonderverse.video.procedural import ProceduralVideo

KINDS = ("clean", "teleport", "rotation", "morph", "freeze")
PROMPTS = (
    "a small house decorated for Christmas",
    "a quiet forest lake in autumn",
    "a desert village at noon",
    "a cosy living room with bookshelves",
    "a snowy mountain cabin",
    "a modern office with desks",
)


def segment(i: int, kind: str, width: int, height: int, frames: int) -> Video:
    """Benchmark segment i with fault `kind` (frames, K, ground truth); varied world, seed and move."""
    rng = np.random.default_rng(i)
    opts = {"fault_probability": 0.0 if kind == "clean" else 1.0}
    if kind != "clean":
        opts["force_fault"] = kind
    model = ProceduralVideo(PROMPTS[i % len(PROMPTS)], i, width, height, 60.0, opts)
    yaw = float(rng.choice([-1, 1]) * rng.uniform(20, 40))
    path = move_path(initial_pose(model), np.radians(yaw), 0.0, float(rng.uniform(0.5, 2.0)), 0.04 * yaw, frames)
    return model.generate("benchmark", path, seed=1000 + i, reference=None)


def mean_extra_trials(n_scenes: int, width: int, height: int, frames: int) -> float:
    """The real check step (default fault probability) over whole scenes: mean extra attempts per segment."""
    from flows.pipeline import execute
    from wonderverse.store import SceneStore

    extra = []
    with tempfile.TemporaryDirectory() as tmp:
        for s in range(n_scenes):
            cfg = build_config(
                PROMPTS[s % len(PROMPTS)],
                preset="preview",
                overrides={
                    "scene": {
                        "seed": 100 + s,
                        "video": {"width": width, "height": height, "frames_per_segment": frames},
                    }
                },
            )
            execute(Path(tmp) / f"s{s}", cfg, until="check")
            extra += [x.extra_trials for x in SceneStore.open(Path(tmp) / f"s{s}").meta(CHECK.path).segments]
    return float(np.mean(extra))


def main() -> None:
    args = parse_args(__doc__ or "")
    per_kind = 3 if args.quick else 12
    width, height, frames = 240, 160, 16  # the quick run only checks fewer segments
    sfm = SfmParams(max_image_size_px=width, num_threads=2)
    modes = {"scale_free": CheckParams(), "absolute": CheckParams(translation_mode="absolute")}
    outcomes: dict[tuple[str, str], list[bool]] = {}
    seconds = []
    for j in range(per_kind):
        for kind in KINDS:
            i = j * len(KINDS) + KINDS.index(kind)
            video = segment(i, kind, width, height, frames)
            t = time.perf_counter()
            prior = CameraPrior(video.K, "guessed" if video.k_is_guess else "given")
            res = reconstruct(video.frames, sfm, prior)  # as the check
            seconds.append(time.perf_counter() - t)
            for mode, cp in modes.items():
                c = check_trajectory(res.poses, res.registered, cp, res.problems, points=res.points)
                outcomes.setdefault((mode, kind), []).append(not c.accepted)
            flagged = outcomes[("scale_free", kind)][-1]
            print(f"segment {i} ({kind}): {'flagged' if flagged else 'accepted'}", file=sys.stderr, flush=True)
    rows = []
    for mode in modes:
        for kind in KINDS:
            flagged = outcomes[(mode, kind)]
            rows.append(
                {
                    "mode": mode,
                    "segments": kind,
                    "n": len(flagged),
                    "flagged": sum(flagged),
                    "rate": float(np.mean(flagged)),
                }
            )
    extra = mean_extra_trials(1 if args.quick else 4, width, height, frames)
    rows.append({"mode": "check step", "segments": "fault p=0.2", "n": 0, "flagged": 0, "rate": extra})
    rate = {(r["mode"], r["segments"]): r["rate"] for r in rows}
    headline = {f"recall_{k}": round(rate[("scale_free", k)], 3) for k in KINDS[1:]}
    headline |= {
        "false_positive_rate": round(rate[("scale_free", "clean")], 3),
        "mean_extra_trials": round(extra, 3),
        "sfm_s_per_segment": round(float(np.mean(seconds)), 2),
    }
    report("detection (rate = recall for faults, false-positive rate for clean)", rows, headline)


if __name__ == "__main__":
    main()
