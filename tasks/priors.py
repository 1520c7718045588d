"""Step `priors`: per segment, a depth and a normal prior for every accepted frame, the depth aligned
per image (scale and shift) to the global SfM points seen in that frame. Segments run in parallel.

Writes `priors/<seg>/`: depth (T,H,W) f32 (aligned depth in SfM units where the alignment held, else
the prior turned into depth; +inf for sky), normals (T,H,W,3) f16 camera space, scale/shift/aligned (T,) and attrs
with the prior kind and the alignment reasons."""

from __future__ import annotations

from typing import Any

import numpy as np

from tasks.base import Step
from tasks.parallel import map_segments
from tasks.progress import callback
from tasks.segments import accepted_attempt, attempt_path, segment_ids
from wonderverse.config import RunConfig
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore, cache_key, write_array

VERSION = 1


def _params(cfg: RunConfig) -> dict[str, Any]:
    return {"priors": cfg.steps.priors.model_dump(exclude={"workers", "dask_address"})}


def _ground_truth(store: SceneStore, ap: str) -> Any:
    from wonderverse.video import GroundTruth

    if not store.exists(f"{ap}/gt"):
        return None
    return GroundTruth(
        poses=store.array(f"{ap}/gt/poses"),
        depth=store.array(f"{ap}/gt/depth"),
        normals=store.array(f"{ap}/gt/normals"),
    )


def segment_poses(store: SceneStore, seg: str, n_frames: int) -> np.ndarray:
    """Global W2C poses (from `sfm/`) of a segment's frames in generation order; NaN where unknown."""
    out = np.full((n_frames, 4, 4), np.nan)
    segs = store.attrs("sfm").get("segments", [])
    if seg in segs:
        fi = store.array("sfm/frame_index")
        rows = np.flatnonzero(fi[:, 0] == segs.index(seg))
        out[fi[rows, 1]] = store.array("sfm/poses")[rows]
    return out


def _raw_depth(store: SceneStore, seg: str, ap: str, p: Any, frames: np.ndarray, gt: Any) -> Any:
    """The depth network's output for a segment, computed once per attempt and model settings and kept in
    `priors_raw/<seg>`: poses change whenever the scene is extended, this does not (it is the costly part)."""
    from wonderverse.priors import make_depth_model
    from wonderverse.priors.base import DepthPrediction

    key = cache_key("priors_raw", VERSION, {"attempt": ap, "models": p}, [store.cache_key_of(f"segments/{seg}") or ""])
    group = f"priors_raw/{seg}"
    if store.is_complete(group, key):
        conf = store.array(f"{group}/confidence").astype(np.float32) if store.exists(f"{group}/confidence") else None
        return DepthPrediction(store.array(f"{group}/depth"), store.attrs(group)["kind"], conf)
    pred = make_depth_model(p, gt).predict(frames)
    with store.staged(group, key, kind=pred.kind) as g:
        write_array(g, "depth", np.asarray(pred.depth, np.float32))
        if pred.confidence is not None:
            write_array(g, "confidence", np.asarray(pred.confidence, np.float16))
    return pred


def priors_segment(seg: str, scene_dir: str, cfg: RunConfig, step_key: str) -> dict[str, Any]:
    from wonderverse.priors import align_frames, make_normal_model

    store = SceneStore.open(scene_dir, mode="r+")
    ap = attempt_path(store, seg)
    key = cache_key("priors_segment", VERSION, {"seg": seg, "attempt": ap}, [step_key])
    if store.is_complete(f"priors/{seg}", key):
        return store.attrs(f"priors/{seg}")
    p = cfg.steps.priors.models
    frames = store.array(f"{ap}/frames")
    K = store.array("sfm/K") if store.exists("sfm") else store.array(f"segments/{seg}/K")
    gt = _ground_truth(store, ap)
    if "oracle" in (p.depth_backend, p.normal_backend) and gt is None:
        raise WonderError(f"segment {seg}: the oracle prior needs procedural ground truth; use depth_anything")
    pred = _raw_depth(store, seg, ap, p, frames, gt)
    points = store.array("sfm/points3d") if store.exists("sfm/points3d") else np.zeros((0, 3))
    poses = segment_poses(store, seg, len(frames))
    sky_beyond_ref = cfg.steps.priors.sky_beyond_ref
    aligned = align_frames(pred.depth, pred.kind, poses, points, K, p.align, sky_beyond_ref)
    normals = make_normal_model(p, gt).predict(frames, K=K, depth=aligned.depth).normals
    summary = {
        "segment": seg,
        "kind": pred.kind,
        "aligned_frames": int(aligned.ok.sum()),
        "frames": len(frames),
        "reasons": aligned.reasons[:20],
    }
    with store.staged(f"priors/{seg}", key, **summary) as g:
        write_array(g, "depth", aligned.depth)
        write_array(g, "normals", normals.astype(np.float16))
        for name, arr in (("scale", aligned.scale), ("shift", aligned.shift), ("aligned", aligned.ok)):
            write_array(g, name, arr, chunks=arr.shape)
        if pred.confidence is not None:
            write_array(g, "confidence", pred.confidence.astype(np.float16))
    return summary


def run(store: SceneStore, cfg: RunConfig, key: str) -> str:
    segs = [s for s in segment_ids(store) if accepted_attempt(store, s) is not None]
    out = map_segments(
        priors_segment,
        segs,
        str(store.scene_dir),
        cfg,
        key,
        workers=cfg.steps.priors.workers,
        address=cfg.steps.priors.dask_address,
        step="priors",
        progress=callback("segments with priors"),
    )
    for group in ("priors", "priors_raw"):
        for stale in set(store.children(group)) - set(segs):
            store.remove(f"{group}/{stale}")
    store.mark_complete("priors", key)
    aligned = sum(s["aligned_frames"] for s in out)
    total = sum(s["frames"] for s in out)
    return f"{len(segs)} segments, {aligned}/{total} frames aligned to SfM ({out[0]['kind'] if out else '-'})"


STEP = Step("priors", 3, ("poses",), _params, run, "depth and normal priors, aligned to SfM")
