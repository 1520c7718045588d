"""Step `priors`: per segment, a depth and a normal prior for every accepted frame, the depth aligned
per image (scale and shift) to the global SfM points seen in that frame. Segments run in parallel.

Writes `priors/<seg>/`: depth (T,H,W) f32 (aligned depth in SfM units where the alignment held, else
the prior turned into depth; +inf for sky), normals (T,H,W,3) f16 camera space, scale/shift/aligned (T,) and attrs
with the prior kind and the alignment reasons."""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from tasks.base import Step, StepContext
from tasks.parallel import map_segments
from tasks.progress import callback
from tasks.raw_depth import ground_truth, raw_depth
from tasks.segments import accepted_attempt, attempt_path, pixels, segment_ids
from wonderverse.config import PriorsStepParams, RunConfig
from wonderverse.errors import WonderError
from wonderverse.schema import PRIORS, PRIORS_RAW, PRIORS_RAW_SEGMENT, PRIORS_SEGMENT, SEGMENT, SFM
from wonderverse.schema.attrs import PriorsSegmentAttrs
from wonderverse.store import SceneStore, cache_key, write_array

VERSION = 2  # 2: keyed by the segment's own poses, not the step's key (extensions leave old segments alone)
NO_PRIORS = "no depth or normal prior (no depth model named): the splats train on colours alone"
Params = PriorsStepParams  # the step reads its own settings only


def params(cfg: RunConfig) -> PriorsStepParams:
    return cfg.steps.priors


def segment_poses(store: SceneStore, seg: str, n_frames: int) -> np.ndarray:
    """Global W2C poses (from `sfm/`) of a segment's frames in generation order; NaN where unknown."""
    out = np.full((n_frames, 4, 4), np.nan)
    meta = store.meta(SFM.path, complete=False)
    segs = meta.segments if meta is not None else []
    if seg in segs:
        fi = store.array(SFM.frame_index)
        rows = np.flatnonzero(fi[:, 0] == segs.index(seg))
        out[fi[rows, 1]] = store.array(SFM.poses)[rows]
    return out


def segment_key(store: SceneStore, seg: str, settings: PriorsStepParams, poses: np.ndarray, K: np.ndarray) -> str:
    """A segment's priors are keyed by its accepted attempt (its segment's and check's keys), the settings, and its
    frames' global poses and K: an extension that keeps them (the poses step registers new frames only) leaves the
    segment's priors as they are, though the SfM points the alignment used may have grown since."""
    accepted = store.cache_key_of(SEGMENT.at(seg=seg).accepted) or store.cache_key_of(SEGMENT.at(seg=seg)) or ""
    where = hashlib.sha256(np.ascontiguousarray(poses).tobytes() + np.ascontiguousarray(K).tobytes()).hexdigest()
    return cache_key("priors_segment", VERSION, {"seg": seg, "settings": settings, "poses_sha256": where}, [accepted])


def _stored(store: SceneStore, seg: str, settings: PriorsStepParams) -> PriorsSegmentAttrs | None:
    """A segment's priors when they are stored under the key they would have now, else None."""
    ap = attempt_path(store, seg)
    n = store.shape(ap.frames)[0]
    K = store.array(SFM.K) if store.exists(SFM.path) else store.array(SEGMENT.at(seg=seg).K)
    key = segment_key(store, seg, settings, segment_poses(store, seg, n), K)
    return store.meta(PRIORS_SEGMENT.at(seg=seg)) if store.is_complete(PRIORS_SEGMENT.at(seg=seg), key) else None


def priors_segment(seg: str, scene_dir: str, settings: PriorsStepParams) -> PriorsSegmentAttrs:
    from wonderverse.priors import align_frames, make_normal_model

    store = SceneStore.open(scene_dir, mode="r+")
    ap = attempt_path(store, seg)
    frames = store.array(ap.frames)
    K = store.array(SFM.K) if store.exists(SFM.path) else store.array(SEGMENT.at(seg=seg).K)
    poses = segment_poses(store, seg, len(frames))
    key = segment_key(store, seg, settings, poses, K)
    group = PRIORS_SEGMENT.at(seg=seg)
    if store.is_complete(group, key):
        return store.meta(group)
    p = settings.models
    gt = ground_truth(store, ap)
    if "oracle" in (p.depth_backend, p.normal_backend) and gt is None:
        raise WonderError(f"segment {seg}: the oracle prior needs procedural ground truth; use depth_anything")
    summary: dict[str, Any] = {"segment": seg, "kind": "none", "aligned_frames": 0, "frames": len(frames)}
    arrays: dict[str, np.ndarray] = {}
    depth = None
    if p.depth_backend != "none":
        pred = raw_depth(store, seg, ap, p, frames, gt)
        points = store.array(SFM.points3d) if store.exists(SFM.points3d) else np.zeros((0, 3))
        aligned = align_frames(pred.depth, pred.kind, poses, points, K, p.align, settings.sky_beyond_ref)
        depth = aligned.depth
        summary |= {"kind": pred.kind, "aligned_frames": int(aligned.ok.sum()), "reasons": aligned.reasons[:20]}
        summary["sky_share"] = round(float(np.isinf(depth).mean()), 4)
        arrays |= {"depth": depth, "scale": aligned.scale, "shift": aligned.shift, "aligned": aligned.ok}
        if pred.confidence is not None:
            arrays["confidence"] = pred.confidence
    if p.normal_backend != "none":
        arrays["normals"] = make_normal_model(p, gt).predict(frames, K=K, depth=depth).normals
    with store.staged(group, key, **summary) as g:
        for name, data in arrays.items():
            write_array(g, getattr(group, name), data)
    return store.meta(group)


def run(store: SceneStore, p: PriorsStepParams, ctx: StepContext) -> str:
    segs = [s for s in segment_ids(store) if accepted_attempt(store, s) is not None]
    if not p.models.any:  # no prior to compute: the splats train on colours alone
        segs = []
    done = {s: m for s in segs if (m := _stored(store, s, p)) is not None}  # read here: no worker starts for them
    todo = [s for s in segs if s not in done]
    fresh = map_segments(
        priors_segment,
        todo,
        str(store.scene_dir),
        p,
        workers=ctx.execution.segment_workers,
        address=ctx.execution.dask_address,
        step="priors",
        pixels=pixels(store, todo),
        min_pixels=ctx.execution.cluster_min_pixels,
        progress=callback("segments with priors"),
    )
    out = [done[s] if s in done else fresh[todo.index(s)] for s in segs]
    for parent, child in ((PRIORS, PRIORS_SEGMENT), (PRIORS_RAW, PRIORS_RAW_SEGMENT)):
        for stale in set(store.children(parent.path)) - set(segs):
            store.remove(child.at(seg=stale))
    backends = [p.models.depth_backend, p.models.normal_backend]
    if not p.models.any:
        with store.staged(PRIORS.path, ctx.key, backends=backends):  # an empty group: no segment has priors
            pass
        return NO_PRIORS
    store.mark_complete(PRIORS.path, ctx.key, backends=backends)
    note = f" ({len(done)} unchanged)" if done else ""
    aligned = sum(s.aligned_frames for s in out)
    total = sum(s.frames for s in out)
    # the share the sky rule took is worth seeing: far terrain no SfM point reaches can be taken too
    sky = sum((s.sky_share or 0.0) * s.frames for s in out) / max(total, 1)
    kind = out[0].kind if out else "-"
    return (
        f"{len(segs)} segments{note}, {aligned}/{total} frames aligned to SfM ({kind}), {100 * sky:.1f} % of pixels sky"
    )


# 4: the step contract
STEP = Step("priors", 4, ("poses",), params, run, "depth and normal priors, aligned to SfM", group=PRIORS.path)
