"""Did a segment go where its plan said? The plan-following check.

A segment is generated along a planned camera path (`camera.move_path` of a `CameraMove`); SfM then
estimates the segment's own path, up to a similarity (its world frame and scale are arbitrary). Both
paths are expressed relative to their first judged frame, in that camera's coordinates, which removes the
unknown world frame: the relative rotations are then directly comparable and the relative translations
differ only by SfM's unknown scale. The estimated path is read in the planned start camera's *level*
frame (world up from the plan, since SfM knows no gravity), so that the numbers mean what the plan's
words mean: yaw left (heading of the optical axis about world up), pitch up (its elevation), roll left
(turn about the optical axis, from level), and travel forward / left / up.

Judged: the rotation at the end (all three angles against the plan's, within an absolute plus a relative
tolerance) and along the way (each angle must stay within the range the plan covers, widened by the same
tolerance, so a path that first turns the wrong way or overshoots is caught even if it ends right); the
translation direction at the end and along the way (angle to the plan's); its size only when a scale
(SfM units -> plan units) is given. A planned rotation or translation below a minimum is "none": a
planned no-turn must then not rotate beyond a limit, and its translation direction is not judged.

Which path is judged (`judge_segment`, `choose_path`): SfM's path can be wrong while passing its own gates:
on short small clips over a ground plane it settles in the planar twin of the true motion (`two_view`'s
module doc), turning 13-27° up and travelling downwards where the camera went forward, and the test then
rejects a segment that followed its plan (all 7 false positives of 48 clean segments in the benchmark, FPR
0.146 at recall 0.956 on SfM's path alone). So SfM's path is checked against an independent reading of the
same frames: the two-view geometry of each looked-at frame against the first (`two_view.two_view_path`,
essential matrices fitted to all matches, K known). SfM's path is judged when two-view geometry confirms its
rotations from the first frame (to `sfm_rotation_tol_deg`; over the benchmark's 96 renderings SfM's paths that
fail the test against the path really rendered disagreed by 4-36°, median 18°, the others by 1.4° median,
4.7° at the 90th percentile), or when SfM's model passed its gates and the two share fewer than 2
frames; otherwise (contradicted; not judged; failed its gates and unconfirmed) the two-view path is judged,
and if it registers fewer than 2 frames too, the segment is not judged. The tolerances are the same for both
paths. The two-view path measures the travel only where there is parallax (`compare_to_plan`'s
`travel_known`): elsewhere the rotation is judged and the travel is not (not measured is not "did not move").
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from wonderverse.camera import STILL_REL_TOL, camera_centers
from wonderverse.two_view import TwoViewParams

# Words of the three angles (yaw, pitch, roll) for positive and negative values.
ANGLE_WORDS = (("left", "right"), ("up", "down"), ("left", "right"))
# Words of the three travel components (forward, left, up) for positive and negative values.
TRAVEL_WORDS = (("forward", "backward"), ("left", "right"), ("up", "down"))
# A component is named in words when it is at least this share of the largest one (so "left 30°", not
# "left 30°, up 1°"), and an angle only when it is also at least WORDS_MIN_DEG.
WORDS_MIN_SHARE = 0.35
WORDS_MIN_DEG = 1.5


class PlanFollowingParams(BaseModel):
    """Step `check`: tolerances of the plan-following test (degrees; lengths in the plan's units, metres).

    Defaults: video models follow a camera instruction loosely (they ease in and out, turn along an arc
    instead of the plan's straight line), so the tolerances catch an ignored instruction (no turn, the
    wrong way, a turn up instead of left, backward instead of forward) rather than an imprecise one; a
    half-done turn passes. SfM's own rotation error (< 1°) is far below them where its path is right; where
    it took a wrong solution (the planar twin, 13-36° off), two-view geometry overrules it (`two_view`,
    `sfm_rotation_tol_deg`; module doc) rather than wider tolerances, which cost recall.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    rotation_tol_deg: float = Field(8.0, ge=0, description="allowed rotation error, absolute part ...")
    rotation_tol_share: float = Field(0.6, ge=0, description="... plus this share of the planned rotation")
    min_rotation_deg: float = Field(3.0, ge=0, description="a planned rotation below this is 'no turn'")
    still_rotation_max_deg: float = Field(
        10.0, gt=0, description="a planned no-turn must not rotate more than this anywhere on the path"
    )
    translation_direction_tol_deg: float = Field(
        80.0, gt=0, le=180, description="allowed angle between estimated and planned travel (arcs: ~yaw/2)"
    )
    min_translation_m: float = Field(0.05, ge=0, description="a planned travel below this is 'no travel'")
    size_ratio_min: float = Field(0.5, gt=0, description="travel ÷ planned travel, lower bound (scale known)")
    size_ratio_max: float = Field(2.0, gt=0, description="travel ÷ planned travel, upper bound (scale known)")
    still_translation_max_m: float = Field(
        0.25, gt=0, description="a planned no-travel must not travel more than this (scale known)"
    )
    path_min_share: float = Field(
        0.25, gt=0, le=1, description="frames displaced less than this share of the largest give no direction"
    )
    two_view: TwoViewParams | None = Field(
        TwoViewParams(),
        description="the two-view look that checks SfM's path and replaces it where contradicted (None: SfM only)",
    )
    sfm_rotation_tol_deg: float = Field(
        4.0,
        gt=0,
        description="SfM's path is contradicted where its rotation from the first frame differs from the "
        "two-view geometry's by more than this",
    )

    @model_validator(mode="after")
    def _ratio_bounds_ordered(self) -> PlanFollowingParams:
        if self.size_ratio_min > self.size_ratio_max:
            raise ValueError(f"size_ratio_min {self.size_ratio_min} is above size_ratio_max {self.size_ratio_max}")
        return self


@dataclass(frozen=True)
class Motion:
    """A camera's motion from the first judged frame to the last, in the first camera's level frame.

    Angles in the aircraft sense: yaw_left_deg: change of the optical axis' heading about world up
    (+ left); pitch_up_deg: change of its elevation (+ up); roll_left_deg: change of the camera's turn
    about its optical axis, from level (+ left: the right side of the image rises).
    forward, left, up: travel along the start camera's horizontal viewing direction, its horizontal left
    and world up, in the plan's units for a plan (or an estimate with a known scale), else in SfM units.
    """

    yaw_left_deg: float
    pitch_up_deg: float
    roll_left_deg: float
    forward: float
    left: float
    up: float

    @property
    def rotation_deg(self) -> float:
        """Size of the turn: the norm of (yaw, pitch, roll), degrees."""
        return math.hypot(self.yaw_left_deg, self.pitch_up_deg, self.roll_left_deg)

    @property
    def travel(self) -> float:
        """Length of the net translation (the units of forward/left/up)."""
        return math.hypot(self.forward, self.left, self.up)


@dataclass
class PlanFollowing:
    """Verdict of `compare_to_plan` on one segment.

    ok: True (followed the plan), False (did not: `reasons` says how, in words), None (not judged:
    `reasons` says why). notes: observations that do not reject (frames left out, components not judged).
    frames: the frame indices judged (registered ones). planned / estimated: the net motions (None when
    not judged); rotation_error_deg: norm of the (yaw, pitch, roll) differences at the end, against
    rotation_tol_deg; translation_direction_error_deg: angle between the net travels (NaN when not
    judged); size_ratio: estimated ÷ planned travel (NaN unless a scale was given and travel planned).
    source: the path judged ("sfm", or "two_view": `judge_segment` judged the two-view path instead);
    sfm_disagreement_deg: the largest angle between SfM's and the two-view geometry's rotations from their
    first common frame (NaN: not compared); two_view: the two-view look's summary (`TwoViewPath.to_attrs`).
    """

    ok: bool | None
    reasons: list[str]
    notes: list[str] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)
    planned: Motion | None = None
    estimated: Motion | None = None
    rotation_error_deg: float = float("nan")
    rotation_tol_deg: float = float("nan")
    translation_direction_error_deg: float = float("nan")
    size_ratio: float = float("nan")
    source: str = "sfm"
    sfm_disagreement_deg: float = float("nan")
    two_view: dict[str, Any] | None = None

    def to_attrs(self) -> dict[str, Any]:
        """JSON-ready summary (NaN -> None) for store attributes."""

        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        def motion(m: Motion | None) -> dict[str, float | None] | None:
            return None if m is None else {k: num(v) for k, v in asdict(m).items()}

        return {
            "ok": self.ok,
            "reasons": list(self.reasons),
            "notes": list(self.notes),
            "frames": [int(i) for i in self.frames],
            "planned": motion(self.planned),
            "estimated": motion(self.estimated),
            "rotation_error_deg": num(self.rotation_error_deg),
            "rotation_tol_deg": num(self.rotation_tol_deg),
            "translation_direction_error_deg": num(self.translation_direction_error_deg),
            "size_ratio": num(self.size_ratio),
            "source": self.source,
            "sfm_disagreement_deg": num(self.sfm_disagreement_deg),
            "two_view": self.two_view,
        }


def compare_to_plan(
    estimated_w2c: np.ndarray,
    planned_w2c: np.ndarray,
    params: PlanFollowingParams | None = None,
    scale: float | None = None,
    *,
    registered: np.ndarray | None = None,
    travel_known: np.ndarray | None = None,
) -> PlanFollowing:
    """Judge whether a segment's estimated camera path followed its planned one.

    estimated_w2c: (T,4,4) W2C poses from SfM (any world frame and scale; NaN where unregistered);
    planned_w2c: (T,4,4) W2C poses of the plan, frame for frame, in the project's world (+z up).
    scale: estimated units -> planned units, when known (then the travel's size is judged too);
    registered: optional (T,) bool mask (frames outside it, or with non-finite poses, are left out).
    travel_known: optional (T,) bool mask of the frames whose translation is measured (a two-view path
    measures the rotation of frames whose parallax is too small for a direction of travel): the rotation
    is judged on every registered frame, the translation on these only (none but the first: not judged).
    Judged on the registered frames, relative to the first of them. Returns ok=None (not judged) when
    fewer than 2 frames are registered or the plan has no finite path (a user's clip). Raises
    ValueError for wrong shapes or a scale that is not finite and positive.
    """
    params = params or PlanFollowingParams()
    est = np.asarray(estimated_w2c, dtype=np.float64)
    plan = np.asarray(planned_w2c, dtype=np.float64)
    if est.ndim != 3 or est.shape[1:] != (4, 4) or plan.shape != est.shape:
        raise ValueError(f"estimated and planned poses must both be (T,4,4), got {est.shape} and {plan.shape}")
    if scale is not None and not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be finite and positive, got {scale}")
    n = len(est)
    reg = np.all(np.isfinite(est.reshape(n, -1)), axis=1)
    if registered is not None:
        registered = np.asarray(registered, dtype=bool)
        if registered.shape != (n,):
            raise ValueError(f"registered must be ({n},), got {registered.shape}")
        reg &= registered
    idx = np.flatnonzero(reg)
    if not np.all(np.isfinite(plan)):
        return PlanFollowing(None, ["not judged: the segment has no planned camera path"], frames=idx.tolist())
    if len(idx) < 2:
        return PlanFollowing(
            None, [f"not judged: only {len(idx)} frame(s) registered; at least 2 are needed"], frames=idx.tolist()
        )
    notes: list[str] = []
    if len(idx) < n:
        notes.append(f"judged on the {len(idx)} registered frames of {n} (frames {idx[0]}-{idx[-1]})")

    i0 = idx[0]
    basis = _level_basis(plan[i0, :3, :3])
    # The plan over every frame from the first judged one (so yaw unwraps continuously), then sampled.
    p_ang, p_trav = _curves(plan, np.arange(i0, idx[-1] + 1), basis)
    p_ang, p_trav = p_ang[idx - i0], p_trav[idx - i0]
    e_ang, e_trav = _curves(est, idx, basis)
    if scale is not None:
        e_trav = e_trav * scale
    known = np.ones(len(idx), dtype=bool)
    if travel_known is not None:
        travel_known = np.asarray(travel_known, dtype=bool)
        if travel_known.shape != (n,):
            raise ValueError(f"travel_known must be ({n},), got {travel_known.shape}")
        known = travel_known[idx] & travel_known[i0]  # travel is relative to the first judged frame
    kt = np.flatnonzero(known)
    last = kt[-1] if len(kt) >= 2 else len(idx) - 1
    planned = _motion(p_ang[-1], p_trav[last])
    estimated = _motion(e_ang[-1], e_trav[last] if len(kt) >= 2 else np.full(3, np.nan))
    out = PlanFollowing(True, [], notes, idx.tolist(), planned, estimated)

    _judge_rotation(out, p_ang, e_ang, params)
    if len(kt) < 2:
        if np.linalg.norm(p_trav[-1]) >= params.min_translation_m:
            out.notes.append("the travel was not measured (too little parallax): the translation is not judged")
        else:
            out.notes.append("no travel planned: the direction of travel is not judged")
    else:
        if len(kt) < len(idx):
            frames_with = ", ".join(str(int(idx[k])) for k in kt)
            out.notes.append(f"travel measured at frames {frames_with} only; judged there")
        # "Did not move" is judged against the SfM coordinates' own rounding (SfM units: scale unknown).
        c = camera_centers(est[idx[kt]])
        still_len = STILL_REL_TOL * max(1.0, float(np.abs(c).max())) * (scale or 1.0)
        _judge_translation(out, p_trav[kt], e_trav[kt], params, scale is not None, still_len)
    out.ok = not out.reasons
    return out


def _level_basis(R0: np.ndarray) -> np.ndarray:
    """Rows (forward, left, up), unit vectors in the start camera's coordinates: world up from the plan's
    start rotation R0 (W2C), forward = its horizontal viewing direction, left = up × forward."""
    up = R0 @ np.array([0.0, 0.0, 1.0])
    right = np.array([1.0, 0.0, 0.0]) - up[0] * up  # the camera's x axis made horizontal
    if np.linalg.norm(right) < 1e-6:  # a camera rolled on its side: fall back to its own axes
        up, right = np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    forward = np.cross(up, right)
    return np.stack([forward, -right, up])


def _elevation(v: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Angle (radians) of vectors (k,3) above the plane normal to `up`; atan2, so exact near ±90°."""
    h = v @ up
    return np.arctan2(h, np.linalg.norm(v - h[:, None] * up, axis=1))


def _curves(w2c: np.ndarray, frames: np.ndarray, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(angles (k,3) degrees [yaw left, pitch up, roll left], travel (k,3) [forward, left, up]) of
    `frames` relative to the first of them, in the level basis (rows forward, left, up) of its camera."""
    R = w2c[frames, :3, :3]
    M = R[0] @ np.swapaxes(R, 1, 2)  # columns: each camera's axes in the first camera's coordinates
    fwd, left, up = basis
    x, z = M[:, :, 0], M[:, :, 2]
    # Yaw: heading of the optical axis (+ toward left); of the right axis (which a left turn swings
    # toward forward) where the optical axis points straight up or down and has no heading.
    vertical = np.linalg.norm(np.cross(z, up), axis=1) < 1e-6
    yaw = np.where(vertical, np.arctan2(x @ fwd, -(x @ left)), np.arctan2(z @ left, z @ fwd))
    pitch = _elevation(z, up) - _elevation(z[:1], up)
    # Roll: the right axis' angle from the level right axis (z × up), + when the right side rises.
    level_right = np.cross(z, up)
    level_right /= np.maximum(np.linalg.norm(level_right, axis=1, keepdims=True), 1e-300)
    roll_abs = np.arctan2(np.sum(x * np.cross(level_right, z), axis=1), np.sum(x * level_right, axis=1))
    roll = np.where(vertical, 0.0, roll_abs - roll_abs[0])
    yaw = np.unwrap(yaw)
    c = camera_centers(w2c[frames])
    d = (c - c[0]) @ R[0].T  # centre displacements in the first camera's coordinates
    return np.degrees(np.stack([yaw, pitch, roll], 1)), d @ basis.T


def _motion(angles: np.ndarray, travel: np.ndarray) -> Motion:
    return Motion(*(float(a) for a in angles), *(float(t) for t in travel))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) between vectors (..., 3); atan2 form, accurate near 0 and 180."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))


def _num(x: float) -> str:
    return f"{x:.2g}" if abs(x) < 1 else f"{x:.3g}"


def _turn_words(angles: np.ndarray, also: np.ndarray | None = None) -> str:
    """'left 30°', 'left 30°, up 10°', 'left 28° and rolled right 12°'; '' when nothing is named.
    Named: the large components, and those in `also` (3 bools) that are at least WORDS_MIN_DEG."""
    a = np.asarray(angles, dtype=np.float64)
    big = np.abs(a) >= max(WORDS_MIN_DEG, WORDS_MIN_SHARE * float(np.abs(a).max()))
    if also is not None:
        big |= also & (np.abs(a) >= WORDS_MIN_DEG)
    named = [bool(b) for b in big]
    words = [f"{ANGLE_WORDS[i][v < 0]} {abs(v):.0f}°" for i, v in enumerate(a.tolist()) if named[i]]
    turn, roll = ", ".join(words[: len(words) - named[2]]), words[-1] if named[2] else ""
    if roll:
        return f"{turn} and rolled {roll}" if turn else f"rolled {roll}"
    return turn


def _turned(angles: np.ndarray, also: np.ndarray | None = None) -> str:
    """What a camera did, in words: 'turned right 28°', 'rolled left 15°', 'did not turn (2°)'."""
    words = _turn_words(angles, also)
    if not words:
        return f"did not turn ({float(np.linalg.norm(angles)):.0f}°)"
    return words if words.startswith("rolled") else f"turned {words}"


def _travel_words(travel: np.ndarray, sized: bool) -> str:
    """'forward 2', 'backward and left' (sized=False): the components of a travel vector, in words."""
    t = np.asarray(travel, dtype=np.float64)
    top = float(np.abs(t).max())
    parts = [
        (TRAVEL_WORDS[i][v < 0], abs(v))
        for i, v in enumerate(t.tolist())
        if top > 0 and abs(v) >= WORDS_MIN_SHARE * top
    ]
    if sized:
        return ", ".join(f"{w} {_num(v)}" for w, v in parts)
    return " and ".join(w for w, _ in parts)


def _judge_rotation(out: PlanFollowing, p_ang: np.ndarray, e_ang: np.ndarray, params: PlanFollowingParams) -> None:
    planned = float(np.linalg.norm(p_ang[-1]))
    if planned < params.min_rotation_deg:
        # No turn planned: the camera must stay within the still limit everywhere on the path.
        out.rotation_tol_deg = params.still_rotation_max_deg
        out.rotation_error_deg = float(np.linalg.norm(e_ang[-1] - p_ang[-1]))
        size = np.linalg.norm(e_ang - p_ang, axis=1)
        k = int(np.argmax(size))
        if size[k] > params.still_rotation_max_deg:
            where = "" if k == len(size) - 1 else " on the way"
            out.reasons.append(f"{_turned(e_ang[k])}{where} where the plan said no turn")
        return
    tol = params.rotation_tol_deg + params.rotation_tol_share * planned
    out.rotation_tol_deg = tol
    out.rotation_error_deg = float(np.linalg.norm(e_ang[-1] - p_ang[-1]))
    if out.rotation_error_deg > tol:
        # Name the angles that are wrong too, even where they are small beside the others.
        diff = np.abs(e_ang[-1] - p_ang[-1])
        wrong = diff >= WORDS_MIN_SHARE * diff.max()
        out.reasons.append(f"{_turned(e_ang[-1], wrong)} where the plan said {_turn_words(p_ang[-1], wrong)}")
        return
    said = f"where the plan said {_turn_words(p_ang[-1])}"
    # Along the way: each angle within the range the plan covers (timing free), widened by the tolerance.
    below = p_ang.min(axis=0) - e_ang.min(axis=0)
    above = e_ang.max(axis=0) - p_ang.max(axis=0)
    excess = np.maximum(below, above)
    j = int(np.argmax(excess))
    if excess[j] > tol:
        value = float(e_ang[:, j].min() if below[j] >= above[j] else e_ang[:, j].max())
        verb = "rolled" if j == 2 else "turned"
        out.reasons.append(f"{verb} {ANGLE_WORDS[j][value < 0]} {abs(value):.0f}° on the way {said}")


def _judge_translation(
    out: PlanFollowing,
    p_trav: np.ndarray,
    e_trav: np.ndarray,
    params: PlanFollowingParams,
    sized: bool,
    still_len: float,
) -> None:
    planned, moved = float(np.linalg.norm(p_trav[-1])), float(np.linalg.norm(e_trav[-1]))
    if planned < params.min_translation_m:
        out.notes.append("no travel planned: the direction of travel is not judged")
        if sized and moved > params.still_translation_max_m:
            out.reasons.append(f"moved {_travel_words(e_trav[-1], True)} where the plan said no travel")
        return
    said = f"where the plan said {_travel_words(p_trav[-1], True)}"
    if moved <= still_len:
        out.reasons.append(f"did not move {said}")
        return
    out.translation_direction_error_deg = float(_angle_deg(e_trav[-1], p_trav[-1]))
    if sized:
        out.size_ratio = moved / planned
    if out.translation_direction_error_deg > params.translation_direction_tol_deg:
        out.reasons.append(f"moved {_travel_words(e_trav[-1], sized)} {said}")
        return
    # Along the way: every frame displaced enough to have a direction goes the plan's way at that frame
    # (or its final way where the plan has hardly moved yet).
    e_len = np.linalg.norm(e_trav, axis=1)
    p_len = np.linalg.norm(p_trav, axis=1)
    ref = np.where((p_len >= params.path_min_share * planned)[:, None], p_trav, p_trav[-1])
    err = np.where(e_len >= params.path_min_share * e_len.max(), _angle_deg(e_trav, ref), 0.0)
    k = int(np.argmax(err))
    if err[k] > params.translation_direction_tol_deg:
        out.reasons.append(f"moved {_travel_words(e_trav[k], sized)} on the way {said}")
    if sized and not params.size_ratio_min <= out.size_ratio <= params.size_ratio_max:
        out.reasons.append(f"moved {_travel_words(e_trav[-1], True)} {said}")


# ---------------------------------------------------------------- SfM's path checked against two-view geometry


def rotation_disagreement(
    a_w2c: np.ndarray, a_registered: np.ndarray, b_w2c: np.ndarray, b_registered: np.ndarray
) -> tuple[float, int]:
    """The largest angle (degrees) between two paths' rotations from their first common frame, over the frames
    both have (registered and finite), and the frame where it is largest: (NaN, -1) when fewer than 2 frames
    are common. Each path in its own world frame (only rotations relative to the first common frame count)."""
    n = len(a_w2c)

    def usable(w2c: np.ndarray, reg: np.ndarray) -> np.ndarray:
        return np.asarray(reg, dtype=bool) & np.all(np.isfinite(np.asarray(w2c).reshape(n, -1)), axis=1)

    common = np.flatnonzero(usable(a_w2c, a_registered) & usable(b_w2c, b_registered))
    if len(common) < 2:
        return float("nan"), -1
    Ra, Rb = a_w2c[common, :3, :3], b_w2c[common, :3, :3]
    rel_a = Ra @ Ra[0].T
    rel_b = Rb @ Rb[0].T
    cos = (np.trace(rel_a @ np.swapaxes(rel_b, 1, 2), axis1=1, axis2=2) - 1.0) / 2.0
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    k = int(np.argmax(ang))
    return float(ang[k]), int(common[k])


def choose_path(
    sfm: PlanFollowing,
    sfm_w2c: np.ndarray,
    sfm_registered: np.ndarray,
    sfm_gates_passed: bool,
    two_view: Any,
    planned_w2c: np.ndarray,
    params: PlanFollowingParams,
) -> PlanFollowing:
    """The verdict on the path the images support: `sfm` (compare_to_plan of SfM's path) when two-view geometry
    (`two_view`, a `TwoViewPath`) confirms SfM's rotations (`rotation_disagreement` <= sfm_rotation_tol_deg),
    or when SfM's model passed its quality gates and the two share too few frames to compare; otherwise (SfM's
    path contradicted, not judged, or failed its gates and unconfirmed) the verdict on the two-view path, or,
    when that path judges nothing either, not judged. The verdict's `source`, `sfm_disagreement_deg`,
    `two_view` and notes say which and why."""
    dis, frame = rotation_disagreement(sfm_w2c, sfm_registered, two_view.poses, two_view.registered)
    summary = two_view.to_attrs()
    why = ""
    if sfm.ok is None:
        why = "SfM's path could not be judged"
    elif not sfm_gates_passed and not math.isfinite(dis):
        why = "SfM's model failed its quality gates and shares fewer than 2 frames with two-view geometry"
    elif dis > params.sfm_rotation_tol_deg:
        why = (
            f"SfM's path is contradicted by two-view geometry: its rotation from the first frame differs by "
            f"{dis:.0f}° at frame {frame} (a wrong solution such as the planar twin)"
        )
    if not why:
        sfm.sfm_disagreement_deg, sfm.two_view = dis, summary
        if math.isfinite(dis):
            sfm.notes.append(f"two-view geometry agrees with SfM's rotations to {dis:.1f}°")
        else:
            sfm.notes.append("two-view geometry shares fewer than 2 frames with SfM's path: not compared")
        return sfm
    tv = compare_to_plan(
        two_view.poses, planned_w2c, params, registered=two_view.registered, travel_known=two_view.travel_known
    )
    tv.source, tv.sfm_disagreement_deg, tv.two_view = "two_view", dis, summary
    if tv.ok is None:
        tv.reasons = [f"not judged: {why}; two-view geometry: {tv.reasons[0].removeprefix('not judged: ')}"]
        return tv
    tv.notes.insert(0, f"judged on two-view geometry: {why}")
    return tv


def judge_segment(
    planned_w2c: np.ndarray,
    sfm_w2c: np.ndarray,
    sfm_registered: np.ndarray,
    frames: np.ndarray | None = None,
    K: np.ndarray | None = None,
    params: PlanFollowingParams | None = None,
    *,
    sfm_gates_passed: bool = True,
) -> PlanFollowing:
    """The plan-following verdict of one attempt: SfM's path (W2C (T,4,4), registered (T,) bool) against the
    planned path, checked against the two-view geometry of the attempt's frames ((T,H,W,3) uint8, K (3,3)
    pixels) when `params.two_view` is set and frames and K are given (`choose_path`); else SfM's path alone.
    A plan that is not finite (a user's clip) is not judged, and no two-view look is taken."""
    params = params or PlanFollowingParams()
    sfm = compare_to_plan(sfm_w2c, planned_w2c, params, registered=sfm_registered)
    if params.two_view is None or frames is None or K is None or not np.all(np.isfinite(planned_w2c)):
        return sfm
    from wonderverse.two_view import two_view_path

    path = two_view_path(np.asarray(frames), np.asarray(K), params.two_view)
    return choose_path(sfm, sfm_w2c, sfm_registered, sfm_gates_passed, path, planned_w2c, params)
