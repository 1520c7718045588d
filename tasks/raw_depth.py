"""The depth network's raw output per segment (`priors_raw/<seg>`), shared by the priors step and guided flows.

It is the costly part of the priors and does not change when the scene is extended (poses do), so it is computed
once per accepted attempt and model settings. Its declared writer is the priors step; a guided flow's
`generate_segments` writes it too (a segment's geometry needs it before the priors step runs), under the same key,
so the priors step later finds it done."""

from __future__ import annotations

from typing import Any

import numpy as np

from wonderverse.schema import PRIORS_RAW_SEGMENT, SEGMENT, GroupPath
from wonderverse.store import SceneStore, cache_key, write_array

VERSION = 1


def ground_truth(store: SceneStore, ap: GroupPath) -> Any:
    """The procedural ground truth of attempt `ap` (what the oracle priors read), None for other backends."""
    from wonderverse.video import GroundTruth

    if not store.exists(ap.gt):
        return None
    return GroundTruth(
        poses=store.array(ap.gt.poses),
        depth=store.array(ap.gt.depth),
        normals=store.array(ap.gt.normals),
    )


def raw_depth(store: SceneStore, seg: str, ap: GroupPath, models: Any, frames: np.ndarray, gt: Any) -> Any:
    """The depth network's `DepthPrediction` for the frames of attempt `ap` of segment `seg` with the priors' model
    settings `models`: read from `priors_raw/<seg>` when it holds this attempt and these settings, else computed
    and stored there."""
    from wonderverse.priors import make_depth_model
    from wonderverse.priors.base import DepthPrediction

    seg_key = store.cache_key_of(SEGMENT.at(seg=seg)) or ""
    key = cache_key("priors_raw", VERSION, {"attempt": ap, "models": models}, [seg_key])
    group = PRIORS_RAW_SEGMENT.at(seg=seg)
    if store.is_complete(group, key):
        conf = store.array(group.confidence).astype(np.float32) if store.exists(group.confidence) else None
        return DepthPrediction(store.array(group.depth), store.meta(group).kind, conf)
    pred = make_depth_model(models, gt).predict(frames)
    with store.staged(group, key, kind=pred.kind) as g:
        write_array(g, group.depth, pred.depth)
        if pred.confidence is not None:
            write_array(g, group.confidence, pred.confidence)
    return pred
