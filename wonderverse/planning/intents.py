"""The user's words for an extension -> a camera move.

Understood: direction words (left, right, up, down, forward, back and ahead, behind, higher, lower, above,
below, further, farther, past, beyond, ...), explicit amounts ("go up 20 degrees", "move forward 3 metres",
"turn left 45°", "turn 45 degrees to the left") and scene content with a positional word ("add a frozen lake
on the left"). "turn" and "look" add nothing by themselves: "turn left" is left. An amount with a unit wins
over a bare direction word; then a positional phrase ("on the left", "to the right": where the new content
is, so "a frozen lake beyond the trees on the left" is left); then the first turning word (left, right, up,
down and their synonyms, but not "down the valley": "look further left past the river" is left, "further"
and "past" only say how far);
then the first travel word (forward, back, ...); words with no direction keep the default.
"""

from __future__ import annotations

import re

from wonderverse.planning.moves import (
    ANGLE_UNITS,
    AXIS_LIMIT,
    DIRECTION_AXIS,
    DISTANCE_UNITS,
    NUMBER,
    CameraMove,
    PlanError,
)
from wonderverse.planning.params import Direction, PlanParams

DIRECTION_WORDS: dict[str, Direction] = {
    **dict.fromkeys(("left", "leftward", "leftwards"), "left"),
    **dict.fromkeys(("right", "rightward", "rightwards"), "right"),
    **dict.fromkeys(("up", "upward", "upwards", "higher", "above", "skyward", "skywards"), "up"),
    **dict.fromkeys(("down", "downward", "downwards", "lower", "below", "beneath"), "down"),
    **dict.fromkeys(
        ("forward", "forwards", "ahead", "further", "farther", "past", "beyond", "onward", "onwards"),
        "forward",
    ),
    **dict.fromkeys(("back", "backward", "backwards", "behind"), "back"),
}


def _alternation(words: set[str] | frozenset[str]) -> str:
    return "|".join(re.escape(w) for w in sorted(words, key=len, reverse=True))


_DIR = rf"(?<![a-z])(?P<dir>{_alternation(set(DIRECTION_WORDS))})(?![a-z])"
_UNIT = rf"(?P<unit>{_alternation(ANGLE_UNITS | DISTANCE_UNITS)})(?![a-z])"
# "left 45°", "up by 20 degrees", "forward 3" (a bare number only when no other word follows it).
_DIR_AMOUNT = re.compile(rf"{_DIR}(?:\s+by)?\s+(?P<num>{NUMBER})(?:\s*{_UNIT}|(?!\s*[a-z\d]))", re.A)
# "45 degrees to the left", "3 metres forward".
_AMOUNT_DIR = re.compile(rf"(?P<num>{NUMBER})\s*{_UNIT}\s+(?:to\s+(?:the\s+)?)?{_DIR}", re.A)
_DIR_WORD = re.compile(_DIR, re.A)
_TURN_WORDS = {w for w, d in DIRECTION_WORDS.items() if d not in ("forward", "back")}
# "down the valley", "up the road" name a way to travel, not a tilt
_TURN_WORD = re.compile(rf"(?<![a-z])(?P<dir>{_alternation(_TURN_WORDS)})(?![a-z])(?!\s+the\s)", re.A)
# "on the left", "to your right", "towards the left"
_POSITIONAL = re.compile(rf"(?<![a-z])(?:on|to|at|towards?)\s+(?:the\s+|your\s+)?{_DIR}", re.A)
_STEP_FIELD = {"yaw": "yaw_step_deg", "pitch": "pitch_step_deg", "forward": "forward_step_m"}


def intent_direction(words: str) -> Direction | None:
    """The direction the user's words name, or None if they name none."""
    direction, _ = _read_intent(words)
    return direction


def interpret_intent(words: str, default_direction: Direction, params: PlanParams) -> CameraMove:
    """The move the words ask for: their direction (else `default_direction`), amount (else the params' step).

    Turns also travel `yaw_forward_m` forward so the camera explores. PlanError for an amount in the wrong
    unit (degrees for forward/back, metres for turns), of zero, or out of range.
    """
    direction, amount = _read_intent(words)
    direction = direction or default_direction
    magnitude = default_step(direction, params) if amount is None else amount
    axis = DIRECTION_AXIS[direction][0]
    if magnitude <= 0 or magnitude > AXIS_LIMIT[axis]:
        raise PlanError(
            f"{words!r}: {direction} {magnitude:g} is out of range (more than 0, at most {AXIS_LIMIT[axis]:g})"
        )
    forward_m = params.yaw_forward_m if axis == "yaw" else 0.0
    return CameraMove.toward(direction, magnitude, forward_m)


def default_step(direction: Direction, params: PlanParams) -> float:
    """The rule planner's step in `direction`: degrees for turns and tilts, metres for travel."""
    return float(getattr(params, _STEP_FIELD[DIRECTION_AXIS[direction][0]]))


def _read_intent(words: str) -> tuple[Direction | None, float | None]:
    """(direction, amount in the direction's unit) the words name; either may be None."""
    text = words.lower()
    matches = [m for pattern in (_DIR_AMOUNT, _AMOUNT_DIR) if (m := pattern.search(text))]
    if matches:
        m = min(matches, key=lambda m: m.start())
        direction = DIRECTION_WORDS[m["dir"]]
        _check_unit(words, direction, m["unit"])
        return direction, float(m["num"])
    m = _POSITIONAL.search(text) or _TURN_WORD.search(text) or _DIR_WORD.search(text)
    return (DIRECTION_WORDS[m["dir"]] if m else None), None


def _check_unit(words: str, direction: Direction, unit: str | None) -> None:
    is_distance = DIRECTION_AXIS[direction][0] == "forward"
    if unit and (unit in DISTANCE_UNITS) != is_distance:
        kind = "a distance (metres)" if is_distance else "an angle (degrees)"
        raise PlanError(f"{words!r}: {direction} takes {kind}, not {unit!r}")
