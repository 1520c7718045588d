"""CameraMove and the strict parser of the paper's answer format."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from wonderverse.errors import WonderError
from wonderverse.planning import CameraMove, PlanParseError, parse_move, parse_moves


@pytest.mark.parametrize(
    ("move", "text"),
    [
        (CameraMove(yaw_deg=30, pitch_deg=10, forward_m=2), "up 10, left 30, forward 2"),
        (CameraMove(), "up 0, left 0, forward 0"),
        (CameraMove(yaw_deg=-3.5, pitch_deg=-5, forward_m=-1.25), "down 5, right 3.5, back 1.25"),
        (CameraMove(yaw_deg=-0.0001, pitch_deg=89, forward_m=1000), "up 89, left 0, forward 1000"),
    ],
)
def test_to_paper(move: CameraMove, text: str) -> None:
    assert move.to_paper() == text


@pytest.mark.parametrize(
    "fields",
    [
        {"yaw_deg": 180.5},
        {"yaw_deg": -181},
        {"pitch_deg": 89.01},
        {"pitch_deg": -90},
        {"forward_m": 1000.1},
        {"forward_m": math.inf},
        {"yaw_deg": math.nan},
        {"roll_deg": 3},
    ],
)
def test_camera_move_rejects_out_of_range(fields: dict[str, float]) -> None:
    with pytest.raises(ValidationError):
        CameraMove(**fields)


def test_camera_move_is_frozen() -> None:
    move = CameraMove(yaw_deg=1)
    with pytest.raises(ValidationError):
        move.yaw_deg = 2  # type: ignore[misc]


@pytest.mark.parametrize(
    ("fields", "direction"),
    [
        ({"yaw_deg": 30, "pitch_deg": 10, "forward_m": 2}, "left"),
        ({"yaw_deg": -30, "forward_m": 50}, "right"),
        ({"yaw_deg": 5, "pitch_deg": -20}, "down"),
        ({"pitch_deg": 1}, "up"),
        ({"yaw_deg": -10, "pitch_deg": 10}, "right"),  # tie: yaw wins
        ({"forward_m": 3}, "forward"),
        ({"forward_m": -3}, "back"),
        ({}, "forward"),
    ],
)
def test_dominant_direction(fields: dict[str, float], direction: str) -> None:
    assert CameraMove(**fields).dominant_direction() == direction


@pytest.mark.parametrize(
    ("line", "yaw", "pitch", "forward"),
    [
        ("up 10, left 30, forward 2", 30, 10, 2),
        ("  DOWN 5 Degrees, Right 12.5 deg, BACK 3 metres.  ", -12.5, -5, -3),
        ("1. up 0°, left 45°, forward 1m", 45, 0, 1),
        ("2) down 1 degree, right .5, forward 2 meters", -0.5, -1, 2),
        ("(3) up 7, left 8 degrees, back 9 units", 8, 7, -9),
        ("- up 1, right 2, forward 3", -2, 1, 3),
        ("* up 1, right 2, forward 3", -2, 1, 3),
        ("• up 1, right 2, forward 3", -2, 1, 3),
        ("Answer 1: up 1, right 2, forward 3", -2, 1, 3),
        ("answer: up 1, right 2, forward 3.", -2, 1, 3),
        ("4. Answer 4: up 89, left 180, forward 1000", 180, 89, 1000),
    ],
)
def test_parse_accepts(line: str, yaw: float, pitch: float, forward: float) -> None:
    assert parse_move(line) == CameraMove(yaw_deg=yaw, pitch_deg=pitch, forward_m=forward)


@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("up 10, left 30", "expected 3 clauses"),
        ("up 10, left 30, forward 2, down 3", "expected 3 clauses"),
        ("left 30, up 10, forward 2", "expected 'up|down X' here"),
        ("up 10, forward 2, left 30", "expected 'left|right X' here"),
        ("up -10, left 30, forward 2", "must not be negative"),
        ("up 10, left 30, forward -2", "must not be negative"),
        ("up 90, left 30, forward 2", "out of range (at most 89)"),
        ("up 10, left 181, forward 2", "out of range (at most 180)"),
        ("up 10, left 30, forward 1001", "out of range (at most 1000)"),
        ("up 10, left 30, forward " + "9" * 400, "out of range"),
        ("up inf, left 30, forward 2", "is not 'DIRECTION NUMBER [UNIT]'"),
        ("up nan, left 30, forward 2", "is not 'DIRECTION NUMBER [UNIT]'"),
        ("up 10 m, left 30, forward 2", "unit 'm' does not fit"),
        ("up 10, left 30, forward 2 degrees", "unit 'degrees' does not fit"),
        ("up 10, left 30, forward 2 km", "unknown unit 'km'"),
        ("go up 10, left 30, forward 2", "is not 'DIRECTION NUMBER [UNIT]'"),
        ("up 10, left 30, forward 2 please", "unknown unit 'please'"),
        ("up 10, left 30, forward 2 m m", "is not 'DIRECTION NUMBER [UNIT]'"),
        ("sideways 10, left 30, forward 2", "unknown direction 'sideways'"),
        ("up 10; left 30; forward 2", "expected 3 clauses"),
        ("Here are the answers:", "expected 3 clauses"),
    ],
)
def test_parse_rejects_with_reason(line: str, why: str) -> None:
    with pytest.raises(PlanParseError) as info:
        parse_moves(f"up 1, left 2, forward 3\n\n{line}")
    assert why in str(info.value)
    assert str(info.value).startswith("line 3 ")


def test_parse_moves_counts_and_skips_blank_lines() -> None:
    text = "\n1. up 0, left 30, forward 2\n\n2. up 0, right 30, forward 2\n   \n"
    assert parse_moves(text, expected=2) == [
        CameraMove(yaw_deg=30, forward_m=2),
        CameraMove(yaw_deg=-30, forward_m=2),
    ]
    with pytest.raises(PlanParseError, match=r"expected 3 answer\(s\), got 2"):
        parse_moves(text, expected=3)
    assert parse_moves("", expected=0) == []


def test_any_order_is_only_for_config_strings() -> None:
    assert parse_move("right 30, up 0, forward 2", any_order=True) == CameraMove(yaw_deg=-30, forward_m=2)
    with pytest.raises(PlanParseError, match="repeats the yaw axis"):
        parse_move("right 30, left 3, forward 2", any_order=True)
    with pytest.raises(PlanParseError):
        parse_move("right 30, up 0, forward 2")


def test_parse_error_is_a_wonder_error() -> None:
    assert issubclass(PlanParseError, WonderError)


moves = st.builds(
    CameraMove,
    yaw_deg=st.floats(-180, 180),
    pitch_deg=st.floats(-89, 89),
    forward_m=st.floats(-1000, 1000),
)


@given(st.lists(moves, max_size=6))
def test_moves_round_trip_through_paper_text(ms: list[CameraMove]) -> None:
    text = "\n".join(m.to_paper() for m in ms)
    assert parse_moves(text, expected=len(ms)) == ms


def _number(limit: int) -> st.SearchStrategy[tuple[str, float]]:
    """(text, value) of a non-negative number as a model might write it, with at most 3 decimals."""
    return st.integers(0, limit * 1000).flatmap(
        lambda milli: st.sampled_from(
            [f"{milli / 1000:.3f}", f"{milli / 1000:g}"] + ([str(milli // 1000)] if milli % 1000 == 0 else [])
        ).map(lambda s: (s, milli / 1000))
    )


def _clause(plus: str, minus: str, limit: int, units: list[str]) -> st.SearchStrategy[tuple[str, float]]:
    return st.tuples(st.booleans(), _number(limit), st.sampled_from(["", *units]), st.sampled_from(["", " "])).map(
        lambda t: (
            f"{plus if t[0] else minus} {t[1][0]}{t[3] if t[2] else ''}{t[2]}",
            t[1][1] if t[0] else -t[1][1],
        )
    )


_ANGLE_UNITS = ["degrees", "degree", "deg", "°"]
answers = st.tuples(
    st.sampled_from(["", "1. ", "2) ", "(3) ", "- ", "* ", "Answer 1: ", "answer: "]),
    _clause("up", "down", 89, _ANGLE_UNITS),
    _clause("left", "right", 180, _ANGLE_UNITS),
    _clause("forward", "back", 1000, ["m", "meters", "metres", "units"]),
    st.sampled_from(["", ".", " ", " . "]),
    st.booleans(),
)


@given(st.lists(answers, max_size=5))
def test_generated_answers_parse_to_their_values(items: list[tuple]) -> None:
    lines, expected = [], []
    for prefix, (p_text, pitch), (y_text, yaw), (f_text, forward), suffix, upper in items:
        line = f"{prefix}{p_text}, {y_text}, {f_text}{suffix}"
        lines.append(line.upper() if upper else line)
        expected.append((yaw, pitch, forward))
    parsed = parse_moves("\n".join(lines), expected=len(items))
    assert [(m.yaw_deg, m.pitch_deg, m.forward_m) for m in parsed] == expected
    assert parse_moves("\n".join(m.to_paper() for m in parsed)) == parsed


_ALPHABET = "updownleftrightforwardbackmdegrs°0123456789.,:;-+*•() \n\tAnswerUPLEFT€\x00"


@settings(max_examples=300)
@given(st.one_of(st.text(), st.text(alphabet=_ALPHABET)), st.one_of(st.none(), st.integers(0, 5)))
def test_arbitrary_text_raises_only_plan_parse_errors(text: str, expected: int | None) -> None:
    try:
        moves = parse_moves(text, expected)
    except PlanParseError as e:
        assert str(e)
    else:
        assert all(isinstance(m, CameraMove) for m in moves)
        assert expected is None or len(moves) == expected
