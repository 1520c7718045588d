"""The quality block of a scene's outputs: the paper's no-reference metrics over rendered novel views."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from wonderverse.progress import ProgressFn, no_progress
from wonderverse.quality.niqe_metric import BLOCK_PX, niqe_many
from wonderverse.quality.params import QualityParams


def score_views(
    frames: Sequence[np.ndarray], prompt: str, params: QualityParams, progress: ProgressFn | None = None
) -> dict[str, float | None]:
    """Mean NIQE (None when frames are under NIQE's minimum size), CLIP-S against `prompt` and Q-Align of
    `frames` ((H,W,3) uint8); a model metric is None when its weights are not configured.
    progress(metrics done, metrics to compute, the one now computed) before each metric and at the end."""
    small = min(frames[0].shape[:2]) < 2 * BLOCK_PX  # NIQE needs two blocks per side
    todo = [m for m, on in (("NIQE", not small), ("CLIP-S", params.clip_model), ("Q-Align", params.qalign_model)) if on]
    report = progress or no_progress
    out: dict[str, float | None] = {"niqe": None, "clip_s": None, "q_align": None}
    if not small:
        report(todo.index("NIQE"), len(todo), "NIQE")
        out["niqe"] = niqe_many(frames)
    if params.clip_model:
        from wonderverse.quality.clip_score import ClipScorer

        report(todo.index("CLIP-S"), len(todo), "CLIP-S")
        clip = ClipScorer(params.clip_model, params.device, params.fp16, params.clip_weight, params.batch_size)
        out["clip_s"] = float(np.mean(clip.score(list(frames), [prompt] * len(frames))))
    if params.qalign_model:
        from wonderverse.quality.qalign import QAlignScorer

        report(todo.index("Q-Align"), len(todo), "Q-Align")
        qalign = QAlignScorer(
            params.qalign_model,
            params.device,
            params.fp16,
            params.qalign_trust_remote_code,
            params.qalign_scale,
            params.batch_size,
        )
        out["q_align"] = float(np.mean(qalign.score(list(frames))))
    if todo:
        report(len(todo), len(todo), "")
    return out
