"""Abnormal-segment detection (the paper's geometric correction, Sec. 3.2): is a segment's SfM camera
trajectory continuous?

The paper marks a frame as discontinuous when its translation jump exceeds T1 or its rotation change
exceeds T2 relative to the previous frame, and rejects the whole segment if any frame is. SfM units are
arbitrary (each reconstruction has its own scale), so by default the translation test is scale free: a
step is abnormal when it is `max_step_ratio` times the median of the segment's *other* steps (leave-one-out,
so that a single jump in a short segment cannot raise its own reference). `translation_mode="absolute"`
applies the paper's T1 in SfM units instead. Rotation uses the paper's T2 (radians) as is.

Also rejected: too few frames registered, unregistered frames inside the segment (unless `allow_gaps`),
fewer than 3 registered frames, a camera that does not move, every SfM quality-gate problem passed in, and
a clip SfM did not map because it saw too little parallax (`stopped`, `wonderverse.parallax`).

Pure rotation (translation steps ~0 while the camera turns): the segment is judged on rotation alone and
accepted if that is smooth, with a note. Translation ratios of pure noise say nothing, so the reference step
is floored at `min_step_depth_frac` × scene depth (from the SfM points when given, else at ~0, so that
any real translation jump in an otherwise still camera is still flagged). A pan without parallax gives SfM
little to triangulate, but the video is not inconsistent; SfM's own gates reject it if it is unusable.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from wonderverse.camera import camera_centers, geodesic_angle

MAX_LISTED = 5  # flagged steps listed one by one in the reasons; the rest are counted


class CheckParams(BaseModel):
    """Step `check`: thresholds of the trajectory-continuity test.

    max_step_ratio 3.5: smooth real and generated trajectories measured here stay below ~2.5× the median
    step (RealEstate10K pose files ≤ 1.6×, their SfM poses ≤ 2.2×); real jumps are far above (the fox
    capture's 0054→0072 jump is 9.85×). Evenly sampled frames are assumed: dropping every other frame of
    a smooth clip doubles a step, which stays below 3.5.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    translation_mode: Literal["scale_free", "absolute"] = Field(
        "scale_free",
        description="scale_free: a step is judged against the median of the others (`max_step_ratio`); absolute: "
        "the paper's T1 (`abs_trans_thresh`) in SfM's arbitrary units",
    )
    abs_trans_thresh: float = Field(5.0, gt=0, description="T1 in SfM units (absolute mode, the paper's)")
    max_step_ratio: float = Field(3.5, gt=1, description="step ÷ median of the other steps (scale-free mode)")
    rot_thresh_rad: float = Field(0.5, gt=0, le=math.pi, description="T2: rotation between consecutive frames")
    max_rot_ratio: float | None = Field(
        3.0, gt=1, description="also abnormal: a rotation step this many times the median one (None: off) ..."
    )
    min_rot_jump_rad: float = Field(0.1, ge=0, description="... and above this, so jitter of a still camera is not")
    min_registered_frac: float = Field(
        0.8, ge=0, le=1, description="a segment with a smaller share of its frames registered by SfM is abnormal"
    )
    allow_gaps: bool = Field(False, description="judge steps across unregistered frames instead of rejecting")
    min_step_depth_frac: float = Field(
        1e-3, ge=0, description="translation below this × scene depth counts as none (pure rotation / static)"
    )
    static_rot_rad: float = Field(1e-3, ge=0, description="median rotation step below this: camera static")


@dataclass
class CheckResult:
    """Verdict on one segment.

    trans_steps, step_ratio, rot_steps: (T-1,) float64; entry i describes the step from frame i to i+1 (or,
    with allow_gaps, from i across unregistered frames to the next registered one); NaN where undefined.
    trans_steps are camera-centre distances in SfM units; rot_steps are geodesic angles in radians.
    flagged_frames: indices i whose step i -> next is abnormal. reasons: why it is rejected (empty if
    accepted). notes: observations that do not reject (pure rotation, unregistered ends).
    """

    accepted: bool
    reasons: list[str]
    trans_steps: np.ndarray
    step_ratio: np.ndarray
    rot_steps: np.ndarray
    flagged_frames: list[int]
    notes: list[str] = field(default_factory=list)
    median_step: float = float("nan")
    registered_frac: float = 0.0

    def to_attrs(self) -> dict[str, Any]:
        """JSON-ready summary (NaN -> None) for store attributes."""

        def clean(a: np.ndarray) -> list[float | None]:
            return [None if not np.isfinite(v) else float(v) for v in a]

        return {
            "accepted": self.accepted,
            "reasons": list(self.reasons),
            "notes": list(self.notes),
            "flagged_frames": [int(i) for i in self.flagged_frames],
            "trans_steps": clean(self.trans_steps),
            "step_ratio": clean(self.step_ratio),
            "rot_steps": clean(self.rot_steps),
            "median_step": None if not np.isfinite(self.median_step) else float(self.median_step),
            "registered_frac": float(self.registered_frac),
        }


def _runs(indices: Sequence[int]) -> list[tuple[int, int]]:
    """Consecutive runs in a sorted index list, as (first, last)."""
    out: list[tuple[int, int]] = []
    for i in indices:
        if out and i == out[-1][1] + 1:
            out[-1] = (out[-1][0], i)
        else:
            out.append((i, i))
    return out


def _frames_words(a: int, b: int) -> str:
    return f"frame {a}" if a == b else f"frames {a}-{b}"


def _limited(items: list[str], what: str) -> list[str]:
    if len(items) <= MAX_LISTED:
        return items
    return [*items[:MAX_LISTED], f"and {len(items) - MAX_LISTED} more {what}"]


def check_trajectory(
    poses: np.ndarray,
    registered: np.ndarray,
    params: CheckParams | None = None,
    sfm_problems: Sequence[str] = (),
    points: np.ndarray | None = None,
    stopped: str = "",
) -> CheckResult:
    """Judge the continuity of one segment's camera trajectory.

    poses: (T,4,4) world-to-camera (NaN rows allowed where unregistered); registered: (T,) bool.
    sfm_problems: the SfM quality-gate problems (each one rejects, quoted as "SfM: ...").
    points: (P,3) SfM points, optional; they give the scene depth that tells a still camera or a pure
    rotation from a moving one.
    stopped: why SfM stopped before mapping (`SfmResult.stopped`: too little parallax); it is then the one
    reason, in SfM's words (a clip never mapped has no trajectory to judge, and "0 frames registered"
    would only hide the cause). Returns a CheckResult; raises ValueError only for wrong shapes.
    """
    params = params or CheckParams()
    poses = np.asarray(poses, dtype=np.float64)
    registered = np.asarray(registered)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (T,4,4), got {poses.shape}")
    if registered.shape != (len(poses),) or registered.dtype != bool:
        raise ValueError(f"registered must be a ({len(poses)},) bool array, got {registered.dtype} {registered.shape}")
    n = len(poses)
    # A "registered" frame with a non-finite pose is as good as unregistered.
    reg = registered & np.all(np.isfinite(poses.reshape(n, -1)), axis=1)
    idx = np.flatnonzero(reg)
    frac = len(idx) / n if n else 0.0
    reasons = [f"SfM: {p}" for p in sfm_problems]
    notes: list[str] = []
    trans = np.full(max(n - 1, 0), np.nan)
    rot = np.full(max(n - 1, 0), np.nan)
    ratio = np.full(max(n - 1, 0), np.nan)
    if stopped:
        return CheckResult(False, [stopped], trans, ratio, rot, [], notes, float("nan"), frac)

    if frac < params.min_registered_frac:
        reasons.append(f"only {100 * frac:.0f}% of frames registered ({len(idx)} of {n})")
    if len(idx) < 3:
        reasons.append(f"only {len(idx)} registered frames; at least 3 are needed to judge the trajectory")
        return CheckResult(False, reasons, trans, ratio, rot, [], notes, float("nan"), frac)

    # Unregistered frames inside the segment break the trajectory; at the ends they only shorten it.
    missing = [i for i in range(idx[0], idx[-1] + 1) if not reg[i]]
    for a, b in _runs(missing):
        if params.allow_gaps:
            notes.append(f"unregistered {_frames_words(a, b)} bridged")
        else:
            verb = "splits" if a == b else "split"
            reasons.append(f"unregistered {_frames_words(a, b)} {verb} the segment")
    if idx[0] > 0 or idx[-1] < n - 1:
        ends = [_frames_words(0, idx[0] - 1)] if idx[0] > 0 else []
        ends += [_frames_words(idx[-1] + 1, n - 1)] if idx[-1] < n - 1 else []
        notes.append(f"unregistered {' and '.join(ends)} at the ends")

    centres = camera_centers(poses)
    # Steps between consecutive registered frames; `span` = how many frame steps each covers.
    starts: list[int] = []
    ends_: list[int] = []
    spans: list[int] = []
    for a, b in pairwise(idx):
        if b - a == 1 or params.allow_gaps:
            starts.append(a)
            ends_.append(b)
            spans.append(b - a)
    starts_a = np.array(starts, dtype=int)
    spans_a = np.array(spans, dtype=float)
    d = np.array([np.linalg.norm(centres[b] - centres[a]) for a, b in zip(starts, ends_, strict=True)])
    r = np.array(
        [float(geodesic_angle(poses[a, :3, :3], poses[b, :3, :3])) for a, b in zip(starts, ends_, strict=True)]
    )
    if len(d) == 0:
        reasons.append("no two consecutive frames are registered")
        return CheckResult(False, reasons, trans, ratio, rot, [], notes, float("nan"), frac)
    trans[starts_a] = d
    rot[starts_a] = r

    # Reference pool: the single-frame steps (steps across gaps, per frame, only if there are none).
    single = spans_a == 1
    pool_idx = np.flatnonzero(single) if single.any() else np.arange(len(d))
    pool = d[pool_idx] / spans_a[pool_idx]
    rot_pool = r[pool_idx] / spans_a[pool_idx]
    median_step = float(np.median(pool))
    median_rot = float(np.median(rot_pool))
    if points is not None and len(points):
        depth = float(np.median(np.linalg.norm(np.asarray(points, float) - centres[idx].mean(axis=0), axis=1)))
        floor = params.min_step_depth_frac * depth
    else:
        depth = float("nan")
        # Without points there is no scale: only a numerically zero step counts as none.
        floor = 1e-9 * max(1.0, float(np.max(np.abs(centres[idx]))))
    still = median_step <= floor
    static = still and median_rot <= params.static_rot_rad
    if static:
        moved = "0" if median_step == 0 else f"{median_step:.3g}"
        reasons.append(f"camera does not move (median step {moved}, median rotation {median_rot:.2g} rad)")
    elif still:
        of_depth = f" = {median_step / depth:.1e} of scene depth" if np.isfinite(depth) else ""
        notes.append(
            f"camera only rotates (median step {median_step:.3g}{of_depth}, median rotation "
            f"{median_rot:.3f} rad); judged on rotation and on translation jumps above the noise floor"
        )

    # Scale-free reference: for each step, the median of the *other* pool steps, floored at the noise level.
    ref = np.full(len(d), median_step)
    if len(pool) > 1:
        for j, k in enumerate(pool_idx):
            ref[k] = np.median(np.delete(pool, j))
    ref = np.maximum(ref, floor)
    # A step across a gap of k frames may hold k-1 ordinary steps; the excess is what could be a jump.
    excess = d - (spans_a - 1) * max(median_step, floor)
    step_ratio = np.maximum(excess, 0.0) / ref
    rot_excess = r - (spans_a - 1) * median_rot
    ratio[starts_a] = step_ratio

    flagged: set[int] = set()
    jump_words, rot_words = [], []
    for k, a in enumerate(starts):
        b = ends_[k]
        if static:
            bad_t = False  # already rejected as still; ratios of noise would only add noise to the reasons
        elif params.translation_mode == "scale_free":
            bad_t = step_ratio[k] > params.max_step_ratio
            t_text = f"translation jump {step_ratio[k]:.1f}x the median step between frames {a} and {b}"
        else:
            bad_t = d[k] - (spans_a[k] - 1) * median_step > params.abs_trans_thresh
            t_text = f"translation step {d[k]:.3g} > {params.abs_trans_thresh:g} between frames {a} and {b}"
        if bad_t:
            flagged.add(a)
            jump_words.append(t_text)
        if rot_excess[k] > params.rot_thresh_rad:
            flagged.add(a)
            rot_words.append(f"rotation step {r[k]:.2f} rad > {params.rot_thresh_rad:g} between frames {a} and {b}")
        elif (
            params.max_rot_ratio is not None
            and rot_excess[k] > params.min_rot_jump_rad
            and rot_excess[k] > params.max_rot_ratio * max(median_rot, 1e-9)
        ):
            flagged.add(a)
            rot_words.append(
                f"rotation step {r[k]:.2f} rad is {rot_excess[k] / max(median_rot, 1e-9):.1f}x the median "
                f"between frames {a} and {b}"
            )
    reasons += _limited(jump_words, "translation jumps") + _limited(rot_words, "rotation jumps")
    return CheckResult(
        accepted=not reasons,
        reasons=reasons,
        trans_steps=trans,
        step_ratio=ratio,
        rot_steps=rot,
        flagged_frames=sorted(int(i) for i in flagged),
        notes=notes,
        median_step=median_step,
        registered_frac=frac,
    )


def least_bad(checks: Mapping[int, Mapping[str, Any]]) -> int:
    """The attempt to keep when none passed (`on_failure: keep_best`), of `checks` (attempt -> its
    `CheckResult.to_attrs()`): the fewest reasons, then the most frames registered, then the earliest."""
    return min(checks, key=lambda k: (len(checks[k].get("reasons", [])), -float(checks[k].get("registered_frac", 0.0))))
