"""Non-repeating views (the paper: "the perspective expansion cannot be repeated").

Horizontal coverage: every turn widens the swept view, so the planned views span `fov + sum(|yaw|)` degrees
and must stay within 360 (beyond that, left and right extensions would wrap round onto covered views).
Pitch: each chain of the stitched video (the left chain starts at the first frame of `init`, every other
extension continues from its last frame) may tilt at most `max_pitch_deg` up or down.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from wonderverse.planning.moves import DECIMALS, DIRECTION_AXIS, CameraMove, PlanError, format_number
from wonderverse.planning.params import PlanParams
from wonderverse.planning.segments import PlannedSegment, Role, reference_kind

FULL_TURN_DEG = 360.0
# Moves are rounded to DECIMALS, so a fitted move may overshoot a limit by half a quantum.
_TOLERANCE = 10.0**-DECIMALS


def yaw_span_deg(segments: Sequence[PlannedSegment], fov_deg: float) -> float:
    """Degrees of horizontal view the segments sweep: the field of view plus every turn."""
    return fov_deg + sum(abs(s.move.yaw_deg) for s in segments)


def chain_pitch_deg(segments: Sequence[PlannedSegment], role: Role) -> float:
    """Pitch (+ up, degrees, from the first frame of init) of the frame a `role` segment starts from."""
    first = reference_kind(role) == "first"
    return sum(s.move.pitch_deg for s in segments if (s.role == "left") == first)


def headroom(segments: Sequence[PlannedSegment], role: Role, params: PlanParams, fov_deg: float) -> float:
    """How far a new `role` segment may still go in its direction (degrees; metres are unlimited)."""
    axis, sign = DIRECTION_AXIS[role]
    if axis == "yaw":
        return max(0.0, FULL_TURN_DEG - yaw_span_deg(segments, fov_deg))
    if axis == "pitch":
        return max(0.0, params.max_pitch_deg - sign * chain_pitch_deg(segments, role))
    return math.inf


def move_problem(
    segments: Sequence[PlannedSegment], role: Role, move: CameraMove, params: PlanParams, fov_deg: float
) -> str | None:
    """Why `move` cannot be the next `role` segment (wrong direction, repeated views), or None if it can."""
    if move.component(role) <= 0:
        axis, sign = DIRECTION_AXIS[role]
        return f"a {role} segment needs {axis} {'>' if sign > 0 else '<'} 0"
    span = yaw_span_deg(segments, fov_deg) + abs(move.yaw_deg)
    if span > FULL_TURN_DEG + _TOLERANCE:
        return f"the views would span {format_number(span)}° (more than 360°, so they would repeat)"
    pitch = chain_pitch_deg(segments, role) + move.pitch_deg
    limit = params.max_pitch_deg
    if abs(pitch) > limit + _TOLERANCE:
        way = "up" if pitch > 0 else "down"
        return f"the camera would tilt {format_number(abs(pitch))}° {way} (limit {limit:g}°)"
    return None


def fit_move(
    segments: Sequence[PlannedSegment], role: Role, move: CameraMove, params: PlanParams, fov_deg: float
) -> CameraMove:
    """`move` shortened to the view left in its direction, and shrunk if it would repeat its side's last move.

    PlanError if that direction is exhausted: less view is left than both `min_turn_deg` and the move asks.
    """
    room = headroom(segments, role, params, fov_deg)
    if room + _TOLERANCE < min(params.min_turn_deg, move.component(role)):
        raise PlanError(_exhausted(segments, role, params, fov_deg))
    magnitude = min(move.component(role), room)
    fitted = move.with_component(role, magnitude)
    previous = next((s.move for s in reversed(segments) if s.role == role), None)
    if fitted == previous:
        fitted = move.with_component(role, magnitude * (1.0 - params.step_variation_ratio))
    return fitted


def _exhausted(segments: Sequence[PlannedSegment], role: Role, params: PlanParams, fov_deg: float) -> str:
    if DIRECTION_AXIS[role][0] == "yaw":
        span = format_number(yaw_span_deg(segments, fov_deg))
        return f"cannot extend {role}: the planned views already span {span}° of 360° (try up, down or forward)"
    pitch = chain_pitch_deg(segments, role)
    return (
        f"cannot extend {role}: the camera already tilts {format_number(abs(pitch))}° "
        f"{'up' if pitch > 0 else 'down'} (limit {params.max_pitch_deg:g}°)"
    )
