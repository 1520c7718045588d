"""The quality block of a scene's outputs: the paper's no-reference metrics over rendered novel views."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from wonderverse.quality.niqe_metric import BLOCK_PX, niqe_many
from wonderverse.quality.params import QualityParams


def score_views(frames: Sequence[np.ndarray], prompt: str, params: QualityParams) -> dict[str, float | None]:
    """Mean NIQE (None when frames are under NIQE's minimum size), CLIP-S against `prompt` and Q-Align of
    `frames` ((H,W,3) uint8); a model metric is None when its weights are not configured."""
    small = min(frames[0].shape[:2]) < 2 * BLOCK_PX  # NIQE needs two blocks per side
    out: dict[str, float | None] = {"niqe": None if small else niqe_many(frames), "clip_s": None, "q_align": None}
    if params.clip_model:
        from wonderverse.quality.clip_score import ClipScorer

        clip = ClipScorer(params.clip_model, params.device, params.fp16, params.clip_weight, params.batch_size)
        out["clip_s"] = float(np.mean(clip.score(list(frames), [prompt] * len(frames))))
    if params.qalign_model:
        from wonderverse.quality.qalign import QAlignScorer

        qalign = QAlignScorer(
            params.qalign_model,
            params.device,
            params.fp16,
            params.qalign_trust_remote_code,
            params.qalign_scale,
            params.batch_size,
        )
        out["q_align"] = float(np.mean(qalign.score(list(frames))))
    return out
