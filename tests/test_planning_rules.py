"""The user's words, the segment plan and the rule-based planner."""

from __future__ import annotations

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from wonderverse.config import ExtensionSpec, PlannerSpec, PlanParams, build_config
from wonderverse.errors import ConfigError
from wonderverse.planning import (
    CameraMove,
    ChatPlanner,
    Plan,
    PlanError,
    PlannedSegment,
    RulePlanner,
    interpret_intent,
    make_planner,
    plan_extension,
    plan_scene,
    stitched_order,
)
from wonderverse.planning.params import MAX_SEGMENTS

PARAMS = PlanParams()


def _turn_forward() -> float:
    """The travel the rule planner adds to a turn (a pending PlanParams field, 0.5 m until it exists)."""
    return getattr(PARAMS, "yaw_forward_m", 0.5)


@pytest.mark.parametrize(
    ("words", "default", "yaw", "pitch", "forward"),
    [
        ("go up 20 degrees", "left", 0, 20, 0),
        ("move forward 3 metres", "left", 0, 0, 3),
        ("Move forward 3.5 m please", "left", 0, 0, 3.5),
        ("turn left 45°", "right", 45, 0, None),
        ("turn 45 degrees to the right", "left", -45, 0, None),
        ("turn right by 10", "left", -10, 0, None),
        ("add a frozen lake on the left", "right", 35, 0, None),
        ("add 2 trees on the left", "right", 35, 0, None),  # 2 counts trees, not degrees
        ("add a castle", "right", -35, 0, None),
        ("", "down", 0, -15, 0),
        ("look higher", "left", 0, 15, 0),
        ("show what is below the bridge", "left", 0, -15, 0),
        ("go further down the valley", "left", 0, 0, 2),  # "down the valley" is a way, not a tilt
        ("look further left past the river", "right", 35, 0, None),  # a turning word beats "further"/"past"
        ("a frozen lake beyond the trees on the left", "right", 35, 0, None),  # where the content is
        ("fly past the mountains", "left", 0, 0, 2),
        ("what lies beyond the gate", "right", 0, 0, 2),
        ("show the garden behind the house", "left", 0, 0, -2),
        ("step back 4 units", "left", 0, 0, -4),
        ("the bright sky", "left", 35, 0, None),  # "bright" is not "right"
    ],
)
def test_interpret_intent(words: str, default: str, yaw: float, pitch: float, forward: float | None) -> None:
    move = interpret_intent(words, default, PARAMS)  # type: ignore[arg-type]
    forward = _turn_forward() if forward is None else forward
    assert move == CameraMove(yaw_deg=yaw, pitch_deg=pitch, forward_m=forward)


def test_turns_travel_a_little_forward() -> None:
    move = interpret_intent("turn left", "right", PARAMS)
    assert 0 < move.forward_m < PARAMS.forward_step_m


@pytest.mark.parametrize(
    ("words", "why"),
    [
        ("go up 3 metres", "up takes an angle"),
        ("move forward 20 degrees", "forward takes a distance"),
        ("turn left 0 degrees", "out of range"),
        ("turn left 500°", "out of range"),
        ("tilt up 90 degrees", "out of range"),
    ],
)
def test_interpret_intent_rejects(words: str, why: str) -> None:
    with pytest.raises(PlanError, match=why):
        interpret_intent(words, "left", PARAMS)


def test_default_plan_follows_the_paper() -> None:
    plan = plan_scene("a quiet harbour", ExtensionSpec(rounds=2), PARAMS)
    assert plan.planner == "rules" and plan.fallback_reason is None
    init, *ext = plan.segments
    assert [s.id for s in plan.segments] == ["s000", "s001", "s002", "s003", "s004"]
    assert init.role == "init" and init.reference == "none" and init.reference_segment is None
    assert init.move == CameraMove(yaw_deg=-30, pitch_deg=0, forward_m=2)  # "right 30, up 0, forward 2"
    assert [s.role for s in ext] == ["left", "right", "left", "right"]
    assert [(s.reference, s.reference_segment, s.reversed) for s in ext] == [
        ("first", "s000", True),
        ("last", "s000", False),
        ("first", "s001", True),
        ("last", "s002", False),
    ]
    assert ext[0].move == CameraMove(yaw_deg=35, forward_m=_turn_forward())
    assert ext[1].move == CameraMove(yaw_deg=-35, forward_m=_turn_forward())
    # The second move of a side must differ from the first (the paper: no repeated perspective).
    assert ext[2].move != ext[0].move and 0 < ext[2].move.yaw_deg < 35
    assert ext[3].move != ext[1].move and -35 < ext[3].move.yaw_deg < 0
    assert stitched_order(plan.segments) == ["s003", "s001", "s000", "s002", "s004"]


def test_intents_steer_the_extensions() -> None:
    spec = ExtensionSpec(rounds=1, directions=("left", "right"), intents=("add a frozen lake on the right",))
    plan = plan_scene("a valley", spec, PARAMS)
    assert [s.role for s in plan.segments] == ["init", "right", "right"]
    assert plan.segments[1].intent == "add a frozen lake on the right" and plan.segments[2].intent == ""
    assert plan.segments[2].move != plan.segments[1].move
    assert plan.segments[2].reference_segment == "s001"


def test_more_intents_than_extensions_is_an_error() -> None:
    with pytest.raises(PlanError, match="3 intents given for 2 extensions"):
        plan_scene("x", ExtensionSpec(rounds=1, intents=("a", "b", "c")), PARAMS)


def test_bad_initial_move_names_the_setting() -> None:
    """Refused where the params are made (so a config holding it never reaches a store), naming the setting."""
    with pytest.raises(ValidationError, match=r"initial_move\n.*expected 3 clauses .*got 2"):
        PlanParams(initial_move="left 30, forward 2")
    with pytest.raises(ConfigError, match=r"steps\.plan\.initial_move: expected 3 clauses .*got 2"):
        build_config("x", overrides={"steps": {"plan": {"initial_move": "left 30, forward 2"}}})


def test_initial_move_is_clamped_to_the_limits() -> None:
    plan = plan_scene("x", ExtensionSpec(rounds=0), PlanParams(initial_move="up 80, left 180, forward 2"), fov_deg=90)
    assert plan.segments[0].move == CameraMove(yaw_deg=180, pitch_deg=60, forward_m=2)
    plan = plan_scene("x", ExtensionSpec(rounds=0), PlanParams(initial_move="up 0, left 180, forward 2"), fov_deg=200)
    assert plan.segments[0].move.yaw_deg == 160


def _chain_pitches(segments: tuple[PlannedSegment, ...]) -> list[float]:
    """End pitch of every segment: left ones continue from the first frame of init, the rest from the last."""
    first, last, out = 0.0, 0.0, []
    for s in segments:
        if s.role == "left":
            first += s.move.pitch_deg
            out.append(first)
        else:
            last += s.move.pitch_deg
            out.append(last)
    return out


SIGN = {"left": ("yaw_deg", 1), "right": ("yaw_deg", -1), "up": ("pitch_deg", 1), "down": ("pitch_deg", -1)}
SIGN |= {"forward": ("forward_m", 1), "back": ("forward_m", -1)}


@settings(max_examples=150, deadline=None)
@given(
    rounds=st.integers(0, 16),
    directions=st.lists(st.sampled_from(list(SIGN)), min_size=1, max_size=4),
    fov_deg=st.floats(20, 160),
    initial=st.sampled_from(["right 30, up 0, forward 2", "up 45, left 90, forward 0", "down 30, right 0, back 1"]),
)
def test_rule_plans_never_repeat_views(rounds: int, directions: list[str], fov_deg: float, initial: str) -> None:
    assume(1 + rounds * len(directions) <= MAX_SEGMENTS)  # a scene holds at most 64 segments
    spec = ExtensionSpec(rounds=rounds, directions=tuple(directions))
    params = PlanParams(initial_move=initial)
    plan = plan_scene("x", spec, params, fov_deg=fov_deg)
    assert plan == plan_scene("x", spec, params, fov_deg=fov_deg)  # deterministic
    segs = plan.segments
    assert [s.role for s in segs] == ["init", *(directions * rounds)]
    assert fov_deg + sum(abs(s.move.yaw_deg) for s in segs) <= 360 + 1e-3
    assert all(abs(p) <= 60 + 1e-3 for p in _chain_pitches(segs))
    for i, s in enumerate(segs[1:], start=1):
        field, sign = SIGN[s.role]
        assert sign * getattr(s.move, field) > 0, s
        previous = [t for t in segs[:i] if t.role == s.role]
        assert not previous or previous[-1].move != s.move
    order = stitched_order(segs)
    lefts = [s.id for s in segs if s.role == "left"]
    assert sorted(order) == [s.id for s in segs]
    assert order[: len(lefts)] == lefts[::-1] and order[len(lefts)] == "s000"


def test_extension_of_an_existing_plan() -> None:
    history = plan_scene("x", ExtensionSpec(rounds=1), PARAMS)
    seg = plan_extension("x", "add a frozen lake on the left", history, PARAMS)
    assert (seg.id, seg.role, seg.reference, seg.reference_segment, seg.reversed) == (
        "s003",
        "left",
        "first",
        "s001",
        True,
    )
    assert seg.move.yaw_deg > 0 and seg.move != history.segments[1].move
    up = plan_extension("x", "go up 20 degrees", history.extended(seg), PARAMS)
    assert (up.id, up.role, up.reference_segment, up.move.pitch_deg) == ("s004", "up", "s002", 20)
    plan = history.extended(seg).extended(up)
    assert stitched_order(plan.segments) == ["s003", "s001", "s000", "s002", "s004"]


def test_extension_without_direction_goes_to_the_less_explored_side() -> None:
    history = plan_scene("x", ExtensionSpec(rounds=1, directions=("left",)), PARAMS)
    assert plan_extension("x", "add a castle", history, PARAMS).role == "right"
    assert plan_extension("x", "add a castle", history, PARAMS, default_direction="up").role == "up"


def test_exhausted_directions_are_errors() -> None:
    history = plan_scene("x", ExtensionSpec(rounds=0), PARAMS)  # init turns 30° with a 60° view: 90° covered
    seg = plan_extension("x", "turn left 180 degrees", history, PARAMS)
    history = history.extended(seg)
    seg = plan_extension("x", "turn right 180 degrees", history, PARAMS)
    assert seg.move.yaw_deg == pytest.approx(-90)  # clamped: 90 + 180 + 90 = 360
    history = history.extended(seg)
    with pytest.raises(PlanError, match="span 360° of 360°"):
        plan_extension("x", "add a tower on the left", history, PARAMS)
    history = history.extended(plan_extension("x", "look up 50 degrees", history, PARAMS))
    seg = plan_extension("x", "look up 50 degrees", history, PARAMS)
    assert seg.move.pitch_deg == pytest.approx(10)
    with pytest.raises(PlanError, match="already tilts 60° up"):
        plan_extension("x", "look higher", history.extended(seg), PARAMS)
    assert plan_extension("x", "look down", history.extended(seg), PARAMS).move.pitch_deg == -15


def test_plan_models_refuse_inconsistent_segments() -> None:
    plan = plan_scene("x", ExtensionSpec(rounds=1), PARAMS)
    left = plan.segments[1]
    with pytest.raises(ValidationError, match="reversed"):
        PlannedSegment.model_validate(left.model_dump() | {"reversed": False})
    with pytest.raises(ValidationError, match="reference"):
        PlannedSegment.model_validate(left.model_dump() | {"reference": "last"})
    wrong_ref = PlannedSegment.model_validate(plan.segments[2].model_dump() | {"reference_segment": "s001"})
    with pytest.raises(ValidationError, match="should be"):
        Plan(segments=(*plan.segments[:2], wrong_ref), planner="rules")
    with pytest.raises(ValidationError):
        Plan(segments=plan.segments[1:], planner="rules")  # no init
    assert Plan.model_validate_json(plan.model_dump_json()) == plan


def test_make_planner() -> None:
    assert isinstance(make_planner(PlannerSpec()), RulePlanner)
    assert isinstance(make_planner(PlannerSpec(backend="chat")), ChatPlanner)
    planner = make_planner(PlannerSpec())
    assert planner.plan_scene("x", ExtensionSpec(), PARAMS) == plan_scene("x", ExtensionSpec(), PARAMS)
