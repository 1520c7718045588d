"""No-reference quality metrics of rendered novel views, as the paper evaluates them: NIQE (lower is better),
CLIP-S (text-image alignment, 0..2.5) and Q-Align (1..5 or 0..1). NIQE runs on numpy/scipy with the project's
pristine model (wonderverse/data/niqe_pristine.npz); CLIP-S and Q-Align need local transformers checkpoints.
Importing this package is light: scipy, torch and transformers load when a metric is first used.
"""

from __future__ import annotations

from typing import Any

from wonderverse.quality.params import QualityParams

_LAZY = {
    "niqe": "wonderverse.quality.niqe_metric",
    "niqe_many": "wonderverse.quality.niqe_metric",
    "ClipScorer": "wonderverse.quality.clip_score",
    "QAlignScorer": "wonderverse.quality.qalign",
    "score_views": "wonderverse.quality.views",
}

__all__ = ["ClipScorer", "QAlignScorer", "QualityParams", "niqe", "niqe_many", "score_views"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'wonderverse.quality' has no attribute {name!r}")
