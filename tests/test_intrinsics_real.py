"""Intrinsics nobody gave, on real footage: RealEstate10K clips (16:9 footage resized to 384x256, so their
pixels are not square) reconstruct within 1 % of their reference path with the 60° guess, as `reconstruct`
reads them; the pose files are the ground truth (SOURCE.md in ../shared/data/cameractrl_re10k)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from wonderverse.camera import CameraPrior
from wonderverse.config import CheckStepParams
from wonderverse.metrics import ate
from wonderverse.sfm import k_record, reconstruct
from wonderverse.video.files import RESIZED_16_9_TO_3_2, read_clip

pytestmark = pytest.mark.e2e  # whole real clips through SfM (~20 s each on 2 cores)

# 3c35: 2.55 % off with the guess as a refined square-pixel prior; 0f47: the worst over seeds (0.70-1.04 %)
CLIPS = ["3c35b868a8ec3433", "0f47577ab3441480"]


def reference(data_dir: Path, stem: str) -> tuple[np.ndarray, np.ndarray]:
    """(W2C (T,4,4), normalised [fx, fy]) from a RealEstate10K pose file: per line a timestamp, fx fy cx cy
    (fractions of width and height), two zeros and the 3x4 W2C matrix."""
    rows = (data_dir / "cameractrl_re10k/pose_files" / f"{stem}.txt").read_text().splitlines()[1:]
    vals = np.array([[float(x) for x in r.split()] for r in rows if r.strip()])
    w2c = np.tile(np.eye(4), (len(vals), 1, 1))
    w2c[:, :3, :4] = vals[:, 7:19].reshape(-1, 3, 4)
    return w2c, vals[0, 1:3]


@pytest.mark.parametrize("stem", CLIPS)
def test_a_guessed_k_on_resized_footage_ends_within_one_percent_of_the_path(data_dir: Path, stem: str) -> None:
    clip_path = data_dir / "cameractrl_re10k/reference_videos" / f"{stem}.mp4"
    if not clip_path.is_file():
        pytest.skip(f"{clip_path} is absent")
    clip = read_clip(clip_path)
    ref, (fx_frac, fy_frac) = reference(data_dir, stem)
    height, width = clip.frames.shape[1:3]
    # the clip's 3:2 frames are read as resized 16:9 footage: the pose file's fy/fx, not square pixels
    true_aspect = (fy_frac * height) / (fx_frac * width)
    assert clip.k_is_guess and clip.K[1, 1] / clip.K[0, 0] == pytest.approx(RESIZED_16_9_TO_3_2, rel=1e-3)
    assert true_aspect == pytest.approx(RESIZED_16_9_TO_3_2, rel=0.02)

    guess = CameraPrior(clip.K, "guessed")
    res = reconstruct(clip.frames, CheckStepParams().sfm, guess)
    assert res.gates_passed and res.registered.sum() >= len(res.registered) - 1, res.problems  # 0f47: 15 of 16
    error = ate(res.poses, ref[: len(res.poses)])["rmse_frac"]
    assert error < 0.01, f"{stem}: {100 * error:.2f} % of the path"
    record = k_record(res, guess)
    assert record["k_source"] == "estimated"
    fx_true = fx_frac * width
    assert abs(record["K"][0][0] - fx_true) / fx_true < 0.1, (record["K"][0][0], fx_true)  # the focal, found
