"""Camera moves and the paper's answer format `up|down X, left|right X, forward|back X`.

A move is relative to the camera's current pose: yaw turns about the camera's vertical axis (+ = left),
pitch tilts about its horizontal axis (+ = up), forward travels along its viewing direction (+ = forward).
Angles are degrees and distances metres (scene units), as the user and the language model write them.
"""

from __future__ import annotations

import math
import re
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from wonderverse.errors import WonderError

Direction = Literal["left", "right", "up", "down", "forward", "back"]
Axis = Literal["pitch", "yaw", "forward"]

# Direction -> (axis, sign of that axis's value).
DIRECTION_AXIS: dict[Direction, tuple[Axis, int]] = {
    "left": ("yaw", 1),
    "right": ("yaw", -1),
    "up": ("pitch", 1),
    "down": ("pitch", -1),
    "forward": ("forward", 1),
    "back": ("forward", -1),
}
AXIS_LIMIT = {"yaw": 180.0, "pitch": 89.0, "forward": 1000.0}
# The paper's clause order, with the words that name each sign.
PAPER_AXES: tuple[tuple[Axis, str, str], ...] = (
    ("pitch", "up", "down"),
    ("yaw", "left", "right"),
    ("forward", "forward", "back"),
)
ANGLE_UNITS = frozenset({"degrees", "degree", "deg", "°"})
DISTANCE_UNITS = frozenset({"m", "meters", "metres", "meter", "metre", "units", "unit"})
AXIS_UNITS = {"pitch": ANGLE_UNITS, "yaw": ANGLE_UNITS, "forward": DISTANCE_UNITS}
# Moves are kept to 0.001° / 1 mm so that the paper text of a move parses back to the same move.
DECIMALS = 3

NUMBER = r"\d+(?:\.\d*)?|\.\d+"
_CLAUSE = re.compile(rf"(?P<word>[a-z]+)\s+(?P<sign>[-+])?(?P<value>{NUMBER})\s*(?P<unit>[a-z]+|°)?", re.I | re.A)
# List numbering, bullets and "Answer 1:" labels a model may put before an answer.
_PREFIX = re.compile(r"(?:[-*•]\s*|\(?\d{1,3}[.):]\s+|answer\s*\d{0,3}\s*[:.)-]\s*)+", re.I | re.A)


class PlanError(WonderError):
    """A plan that cannot be made as asked (no unexplored view left, an unusable intent)."""


class PlanParseError(PlanError):
    """Text that is not in the paper's answer format."""


class CameraMove(BaseModel):
    """One segment's camera change: degrees of yaw (+ left) and pitch (+ up), metres forward (+ forward)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    yaw_deg: float = Field(0.0, ge=-AXIS_LIMIT["yaw"], le=AXIS_LIMIT["yaw"], allow_inf_nan=False)
    pitch_deg: float = Field(0.0, ge=-AXIS_LIMIT["pitch"], le=AXIS_LIMIT["pitch"], allow_inf_nan=False)
    forward_m: float = Field(0.0, ge=-AXIS_LIMIT["forward"], le=AXIS_LIMIT["forward"], allow_inf_nan=False)

    @field_validator("yaw_deg", "pitch_deg", "forward_m")
    @classmethod
    def _quantised(cls, v: float) -> float:
        return round(v, DECIMALS) + 0.0  # + 0.0 turns -0.0 into 0.0

    @classmethod
    def toward(cls, direction: Direction, magnitude: float, forward_m: float = 0.0) -> CameraMove:
        """A move of `magnitude` (degrees or metres) in `direction`, plus `forward_m` on a turn or tilt."""
        axis, sign = DIRECTION_AXIS[direction]
        values = {"pitch": 0.0, "yaw": 0.0, "forward": forward_m}
        values[axis] = sign * magnitude
        return cls(yaw_deg=values["yaw"], pitch_deg=values["pitch"], forward_m=values["forward"])

    def axis_value(self, axis: Axis) -> float:
        return {"yaw": self.yaw_deg, "pitch": self.pitch_deg, "forward": self.forward_m}[axis]

    def component(self, direction: Direction) -> float:
        """How far the move goes in `direction` (negative when it goes the opposite way)."""
        axis, sign = DIRECTION_AXIS[direction]
        return sign * self.axis_value(axis)

    def with_component(self, direction: Direction, magnitude: float) -> CameraMove:
        """This move with its `direction` axis replaced by `magnitude` in `direction`."""
        axis, sign = DIRECTION_AXIS[direction]
        field = {"yaw": "yaw_deg", "pitch": "pitch_deg", "forward": "forward_m"}[axis]
        return CameraMove.model_validate(self.model_dump() | {field: sign * magnitude})

    def to_paper(self) -> str:
        """The move as the paper writes it, e.g. `up 10, left 30, forward 2` (zeros as `up 0`)."""
        clauses = []
        for axis, plus, minus in PAPER_AXES:
            v = self.axis_value(axis)
            clauses.append(f"{plus if v >= 0 else minus} {format_number(abs(v))}")
        return ", ".join(clauses)

    def dominant_direction(self) -> Direction:
        """The main direction: the larger turn (yaw wins ties), else the travel (a null move: forward).

        Rotations win over travel because they change what comes into view.
        """
        if self.yaw_deg or self.pitch_deg:
            if abs(self.yaw_deg) >= abs(self.pitch_deg):
                return "left" if self.yaw_deg > 0 else "right"
            return "up" if self.pitch_deg > 0 else "down"
        return "back" if self.forward_m < 0 else "forward"


def format_number(x: float) -> str:
    """`x` with at most DECIMALS decimals and no trailing zeros: 2 -> "2", 29.75 -> "29.75"."""
    return f"{x:.{DECIMALS}f}".rstrip("0").rstrip(".")


def parse_move(text: str, *, any_order: bool = False) -> CameraMove:
    """One answer `up|down X, left|right X, forward|back X` as a CameraMove; PlanParseError (why) if not.

    With `any_order` the three clauses may come in any order (each axis exactly once), for moves that
    people write in config files; answers from a model must keep the paper's order.
    """
    text = text.strip()
    prefix = _PREFIX.match(text)
    body = text[prefix.end() if prefix else 0 :].strip().removesuffix(".")
    clauses = [c.strip() for c in body.split(",")]
    if len(clauses) != 3:
        raise PlanParseError(f"expected 3 clauses 'up|down X, left|right X, forward|back X', got {len(clauses)}")
    values: dict[Axis, float] = {}
    for i, clause in enumerate(clauses):
        axis, value = _parse_clause(clause, None if any_order else PAPER_AXES[i][0])
        if axis in values:
            raise PlanParseError(f"clause {_quote(clause)} repeats the {axis} axis")
        values[axis] = value
    try:
        return CameraMove(yaw_deg=values["yaw"], pitch_deg=values["pitch"], forward_m=values["forward"])
    except ValidationError as e:  # unreachable after the range checks; kept so no pydantic error escapes
        raise PlanParseError(f"invalid move: {e.errors()[0]['msg']}") from None


def parse_moves(text: str, expected: int | None = None) -> list[CameraMove]:
    """Every answer in `text`, one per non-blank line, in order; PlanParseError naming the line and why.

    If `expected` is given the number of answers must equal it.
    """
    moves = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            moves.append(parse_move(line))
        except PlanParseError as e:
            raise PlanParseError(f"line {number} ({_quote(line)}): {e}") from None
    if expected is not None and len(moves) != expected:
        raise PlanParseError(f"expected {expected} answer(s), got {len(moves)}")
    return moves


def _parse_clause(clause: str, axis_wanted: Axis | None) -> tuple[Axis, float]:
    """(axis, signed value) of one clause such as `left 30 degrees`."""
    m = _CLAUSE.fullmatch(clause)
    if m is None:
        raise PlanParseError(f"clause {_quote(clause)} is not 'DIRECTION NUMBER [UNIT]'")
    word, unit = m["word"].lower(), (m["unit"] or "").lower()
    found = next(((a, p, n) for a, p, n in PAPER_AXES if word in (p, n)), None)
    if found is None:
        raise PlanParseError(f"unknown direction {m['word']!r}")
    axis, plus, minus = found
    if axis_wanted is not None and axis != axis_wanted:
        wanted = next(f"{p}|{n}" for a, p, n in PAPER_AXES if a == axis_wanted)
        raise PlanParseError(
            f"expected '{wanted} X' here, got {_quote(clause)} (order is up|down, left|right, forward|back)"
        )
    if m["sign"] == "-":
        raise PlanParseError(f"{_quote(clause)}: the number must not be negative (the word gives the sign)")
    if unit and unit not in ANGLE_UNITS | DISTANCE_UNITS:
        raise PlanParseError(f"{_quote(clause)}: unknown unit {m['unit']!r}")
    if unit and unit not in AXIS_UNITS[axis]:
        raise PlanParseError(f"{_quote(clause)}: unit {unit!r} does not fit {plus}|{minus}")
    value = float(m["value"])
    if not math.isfinite(value) or value > AXIS_LIMIT[axis]:
        raise PlanParseError(f"{_quote(clause)}: {m['value'][:20]} is out of range (at most {AXIS_LIMIT[axis]:g})")
    return axis, value if word == plus else -value


def _quote(text: str, limit: int = 60) -> str:
    text = text.strip()
    return repr(text if len(text) <= limit else text[: limit - 3] + "...")
