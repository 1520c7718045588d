"""Step `check`: the paper's geometric correction. Each segment's camera path is estimated with
SfM and judged (T1/T2, registration); a failed segment is regenerated whole with a new seed (a new
attempt group) until one passes or attempts run out. Segments are checked in parallel on Dask.

Writes, per segment: `attempts/<k>/sfm` (poses, registered, points, colors), `attempts/<k>/check`
(decision, reasons, per-frame steps) and `accepted` (the attempt later steps follow). The step's own
group `check` holds the summary (extra trials per segment, dropped segments).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from tasks.base import Step, StepContext
from tasks.generate_segments import render_attempt, replay_content, stored_words, write_attempt
from tasks.parallel import map_segments
from tasks.progress import callback
from tasks.segments import attempt_ids, intrinsics, segment_ids
from wonderverse.config import CheckStepParams, Model, RunConfig, VideoSource
from wonderverse.errors import WonderError
from wonderverse.schema import ATTEMPT, CHECK, SEGMENT
from wonderverse.store import SceneStore, cache_key, write_array

log = logging.getLogger("wonderverse.check")
VERSION = 4  # 2: keyed by the step's params model; 3: guessed K self-calibrated, parallax looked at first; 4: plan
THIS_RUN = "this_run"  # the key of what `check_segment` did in this run (returned, never stored)


class Params(Model):
    """The check's settings, and the video source it regenerates failed segments with."""

    check: CheckStepParams
    source: VideoSource


def params(cfg: RunConfig) -> Params:
    return Params(check=cfg.steps.check, source=cfg.scene.video_source)


def segment_key(p: Params, seg_key: str) -> str:
    return cache_key("check_segment", VERSION, p, [seg_key])


def _judge(store: SceneStore, p: CheckStepParams, seg: str, k: int, key: str) -> dict[str, Any]:
    """SfM + check of one attempt (cached in its `sfm` and `check` groups); returns the check attrs."""
    from wonderverse.check import check_trajectory
    from wonderverse.sfm import k_record, reconstruct

    ap = ATTEMPT.at(seg=seg, attempt=k)
    if store.is_complete(ap.check, key):
        return store.attrs(ap.check)
    K, known = intrinsics(store, seg)
    frames = store.array(ap.frames)
    sfm = reconstruct(frames, p.sfm, K_prior=K, K_known=known, K_guessed=not known)
    result = check_trajectory(sfm.poses, sfm.registered, p.rules, sfm.problems, points=sfm.points, stopped=sfm.stopped)
    verdict = _with_plan_verdict(result.to_attrs(), store.array(SEGMENT.at(seg=seg).path), sfm, p, frames, K)
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
        **k_record(sfm, K, known),
    ) as g:
        write_array(g, ap.sfm.poses, sfm.poses)
        write_array(g, ap.sfm.registered, sfm.registered)
        write_array(g, ap.sfm.K, sfm.K)
        write_array(g, ap.sfm.points, sfm.points.reshape(-1, 3))
        write_array(g, ap.sfm.colors, sfm.colors.reshape(-1, 3))
    with store.staged(ap.check, key, **verdict, sfm_seconds=sfm.timings.get("total", 0.0)):
        pass
    return store.attrs(ap.check)


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


def check_segment(seg: str, scene_dir: str, p: Params) -> dict[str, Any]:
    """Check (and regenerate) one segment until an attempt passes; writes `segments/<seg>/accepted`.

    Returns that summary plus THIS_RUN: {"cached": the segment was already checked under this key,
    "regenerated": attempts rendered by this call} (what this run did, not stored)."""
    from wonderverse.check import least_bad

    store = SceneStore.open(scene_dir, mode="r+")
    seg_key = store.cache_key_of(SEGMENT.at(seg=seg))
    if seg_key is None:
        raise WonderError(f"segment {seg} is not complete; run generate_segments first")
    key = segment_key(p, seg_key)
    accepted = SEGMENT.at(seg=seg).accepted
    if store.is_complete(accepted, key):
        return store.attrs(accepted) | {THIS_RUN: {"cached": True, "regenerated": 0}}
    model = None
    checks: dict[int, dict[str, Any]] = {}
    rendered = 0  # attempts a run before this one left (killed mid-check) are reused, not counted
    clips = p.source.video.backend == "files"  # a user's clip cannot be regenerated
    for k in range(1 if clips else p.check.max_attempts):
        if k not in attempt_ids(store, seg):
            if model is None:
                from wonderverse.video import make_video_model

                model = make_video_model(p.source)
                replay_content(model, p.source, stored_words(store))
            video, seed, guide = render_attempt(store, p.source, model, seg, k)
            at = ATTEMPT.at(seg=seg, attempt=k)
            with store.staged(at, cache_key("attempt", VERSION, {"seed": seed}, [seg_key])) as g:
                write_attempt(g, at, video, seed, p.source.video.backend, guide)
            rendered += 1
        checks[k] = _judge(store, p.check, seg, k, cache_key("attempt_check", VERSION, {"k": k}, [key]))
        if checks[k]["accepted"]:
            break
    passed = [k for k, c in checks.items() if c["accepted"]]
    summary: dict[str, Any] = {"segment": seg, "attempts": len(checks), "extra_trials": len(checks) - 1}
    if passed:
        summary |= {"attempt": passed[0], "dropped": False, "reasons": []}
    else:
        best = least_bad(checks)
        reasons = checks[best]["reasons"]
        if p.check.on_failure == "fail":
            raise WonderError(f"segment {seg} failed all {len(checks)} attempts; last reasons: {'; '.join(reasons)}")
        if p.check.on_failure == "drop":
            summary |= {"attempt": None, "dropped": True, "reasons": reasons}
            log.warning("segment %s dropped after %d attempts: %s", seg, len(checks), "; ".join(reasons))
        else:
            summary |= {"attempt": best, "dropped": False, "reasons": reasons}
            log.warning("segment %s kept its best failing attempt %d: %s", seg, best, "; ".join(reasons))
    with store.staged(accepted, key, **summary):
        pass
    return summary | {THIS_RUN: {"cached": False, "regenerated": rendered}}


def is_checked(store: SceneStore, p: Params, seg: str) -> bool:
    """Whether segment `seg` is checked under these settings (its `accepted` complete under its key)."""
    seg_key = store.cache_key_of(SEGMENT.at(seg=seg))
    return seg_key is not None and store.is_complete(SEGMENT.at(seg=seg).accepted, segment_key(p, seg_key))


def run(store: SceneStore, p: Params, ctx: StepContext) -> str:
    segs = segment_ids(store)
    # segments checked already (a guided flow checks them while generating) are read here; no workers start for them
    todo = [s for s in segs if not is_checked(store, p, s)]
    done = {s: check_segment(s, str(store.scene_dir), p) for s in segs if s not in todo}
    fresh = map_segments(
        check_segment,
        todo,
        str(store.scene_dir),
        p,
        workers=ctx.execution.segment_workers,
        address=ctx.execution.dask_address,
        step="check",
        progress=callback("segments checked"),
    )
    results = [done[s] if s in done else fresh[todo.index(s)] for s in segs]
    this_run = [s[THIS_RUN] for s in results]
    summaries = [{k: v for k, v in s.items() if k != THIS_RUN} for s in results]
    extra = [s["extra_trials"] for s in summaries]
    dropped = [s["segment"] for s in summaries if s["dropped"]]
    failing = [s["segment"] for s in summaries if s["reasons"] and not s["dropped"]]
    summary = {"segments": summaries, "mean_extra_trials": float(np.mean(extra)), "dropped": dropped}
    with store.staged(CHECK.path, ctx.key, **summary, kept_failing=failing):
        pass
    cached = sum(r["cached"] for r in this_run)
    msg = f"{len(segs)} segments" + (f" ({cached} cached)" if cached else "")
    msg += f", {sum(r['regenerated'] for r in this_run)} regenerated this run"
    return (
        msg
        + (f", dropped {', '.join(dropped)}" if dropped else "")
        + (f", kept failing {', '.join(failing)}" if failing else "")
    )


# 3: a guessed K is self-calibrated with its pixel aspect held; too little parallax stops SfM before mapping
STEP = Step(
    "check", 3, ("generate_segments",), params, run, "SfM pose check, regenerate abnormal segments", group=CHECK.path
)
