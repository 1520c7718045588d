"""One segment's check, the paper's geometric correction: each attempt's camera path is estimated with SfM and
judged (T1/T2, registration, and whether the camera followed its planned move); a failed segment is regenerated whole
with a new seed (a new attempt, `tasks.attempts.add_attempt`) until one passes or attempts run out.

Writes, per segment: `attempts/<k>/sfm` (poses, registered, points, colors), `attempts/<k>/check` (decision,
reasons, per-frame steps) and `accepted` (the attempt later steps follow). Its declared writer is the check step; a
guided flow's `generate_segments` runs it too (an extension is generated from its checked parent), under the check's
own keys, so the check step later finds it done.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from tasks.attempts import add_attempt, video_model
from tasks.segments import attempt_ids, camera_prior
from wonderverse.config import CheckStepParams, Model, VideoSource
from wonderverse.errors import WonderError
from wonderverse.schema import ATTEMPT, SEGMENT
from wonderverse.schema.attrs import AcceptedAttrs, AttemptCheckAttrs
from wonderverse.store import SceneStore, cache_key, write_array

log = logging.getLogger("wonderverse.check")
VERSION = 4  # 2: keyed by the step's params model; 3: guessed K self-calibrated, parallax looked at first; 4: plan


class CheckParams(Model):
    """The check's settings, and the video source it regenerates failed segments with."""

    check: CheckStepParams
    source: VideoSource


def check_key(p: CheckParams, seg_key: str) -> str:
    """The key of a segment's check (its `accepted`): the check's settings and the segment's key."""
    return cache_key("check_segment", VERSION, p, [seg_key])


def _judge(store: SceneStore, p: CheckStepParams, seg: str, k: int, key: str) -> AttemptCheckAttrs:
    """SfM + check of one attempt (cached in its `sfm` and `check` groups); returns the check's decision."""
    from wonderverse.check import check_trajectory
    from wonderverse.sfm import k_record, reconstruct

    ap = ATTEMPT.at(seg=seg, attempt=k)
    if store.is_complete(ap.check, key):
        return store.meta(ap.check)
    prior = camera_prior(store, seg)
    frames = store.array(ap.frames)
    sfm = reconstruct(frames, p.sfm, prior)
    result = check_trajectory(sfm.poses, sfm.registered, p.rules, sfm.problems, points=sfm.points, stopped=sfm.stopped)
    verdict = _with_plan_verdict(result.to_attrs(), store.array(SEGMENT.at(seg=seg).path), sfm, p, frames, prior.K)
    with store.staged(
        ap.sfm,
        key,
        mapper=sfm.mapper,
        reproj_error_px=sfm.reproj_error_px,
        n_points=sfm.n_points,
        timings=sfm.timings,
        problems=sfm.problems,
        stopped=sfm.stopped,
        parallax=sfm.parallax,
        **k_record(sfm, prior),
    ) as g:
        write_array(g, ap.sfm.poses, sfm.poses)
        write_array(g, ap.sfm.registered, sfm.registered)
        write_array(g, ap.sfm.K, sfm.K)
        write_array(g, ap.sfm.points, sfm.points.reshape(-1, 3))
        write_array(g, ap.sfm.colors, sfm.colors.reshape(-1, 3))
    with store.staged(ap.check, key, **verdict, sfm_seconds=sfm.timings.get("total", 0.0)):
        pass
    return store.meta(ap.check)


def _with_plan_verdict(
    verdict: dict[str, Any], planned: np.ndarray, sfm: Any, p: CheckStepParams, frames: np.ndarray, K: np.ndarray
) -> dict[str, Any]:
    """The check's `verdict` with the plan-following test of the attempt's path against its planned path
    (`plan_following.judge_segment`: SfM's path, checked against the two-view geometry of the attempt's frames
    with K) added: its figures, and, when the camera ignored its instruction, a rejection with the reasons in
    words. A user's clip has no plan (NaN path) and is not judged."""
    if p.plan_following is None or not np.isfinite(planned).all():
        return verdict
    from wonderverse.plan_following import judge_segment

    pf = judge_segment(
        planned, sfm.poses, sfm.registered, frames, K, p.plan_following, sfm_gates_passed=sfm.gates_passed
    )
    verdict = verdict | {"plan_following": pf.to_attrs()}
    if pf.ok is False:
        reasons = [f"ignored its camera instruction: {r}" for r in pf.reasons]
        verdict |= {"accepted": False, "reasons": [*verdict["reasons"], *reasons]}
    return verdict


@dataclass(frozen=True)
class SegmentChecked:
    """What `check_segment` decided (what `accepted` holds), and what this call did: whether the segment was
    checked already under this key, and how many attempts it rendered."""

    decision: AcceptedAttrs
    cached: bool
    regenerated: int


def check_segment(seg: str, scene_dir: str, p: CheckParams) -> SegmentChecked:
    """Check (and regenerate) one segment until an attempt passes; writes `segments/<seg>/accepted`."""
    store = SceneStore.open(scene_dir, mode="r+")
    seg_key = store.cache_key_of(SEGMENT.at(seg=seg))
    if seg_key is None:
        raise WonderError(f"segment {seg} is not complete; run generate_segments first")
    key = check_key(p, seg_key)
    accepted = SEGMENT.at(seg=seg).accepted
    if store.is_complete(accepted, key):
        return SegmentChecked(store.meta(accepted), cached=True, regenerated=0)
    model = None
    checks: dict[int, AttemptCheckAttrs] = {}
    rendered = 0  # attempts a run before this one left (killed mid-check) are reused, not counted
    clips = p.source.video.backend == "files"  # a user's clip cannot be regenerated
    for k in range(1 if clips else p.check.max_attempts):
        if k not in attempt_ids(store, seg):
            model = model or video_model(store, p.source)
            add_attempt(store, p.source, model, seg, k, seg_key)
            rendered += 1
        checks[k] = _judge(store, p.check, seg, k, cache_key("attempt_check", VERSION, {"k": k}, [key]))
        if checks[k].accepted:
            break
    with store.staged(accepted, key, **_decide(seg, checks, p.check.on_failure)):
        pass
    return SegmentChecked(store.meta(accepted), cached=False, regenerated=rendered)


def _decide(seg: str, checks: dict[int, AttemptCheckAttrs], on_failure: str) -> dict[str, Any]:
    """The segment's decision from its attempts' checks: the first that passed, else (`on_failure`) the least bad
    one kept, the segment dropped, or a WonderError."""
    from wonderverse.check import least_bad

    passed = [k for k, c in checks.items() if c.accepted]
    summary: dict[str, Any] = {"segment": seg, "attempts": len(checks), "extra_trials": len(checks) - 1}
    if passed:
        return summary | {"attempt": passed[0], "dropped": False, "reasons": []}
    best = least_bad({k: c.model_dump() for k, c in checks.items()})
    reasons = checks[best].reasons
    if on_failure == "fail":
        raise WonderError(f"segment {seg} failed all {len(checks)} attempts; last reasons: {'; '.join(reasons)}")
    if on_failure == "drop":
        log.warning("segment %s dropped after %d attempts: %s", seg, len(checks), "; ".join(reasons))
        return summary | {"attempt": None, "dropped": True, "reasons": reasons}
    log.warning("segment %s kept its best failing attempt %d: %s", seg, best, "; ".join(reasons))
    return summary | {"attempt": best, "dropped": False, "reasons": reasons}


def is_checked(store: SceneStore, p: CheckParams, seg: str) -> bool:
    """Whether segment `seg` is checked under these settings (its `accepted` complete under its key)."""
    seg_key = store.cache_key_of(SEGMENT.at(seg=seg))
    return seg_key is not None and store.is_complete(SEGMENT.at(seg=seg).accepted, check_key(p, seg_key))
