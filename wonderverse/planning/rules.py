"""The rule-based planner (default, deterministic): configured steps, steered by the user's words."""

from __future__ import annotations

from collections.abc import Sequence

from wonderverse.camera import DEFAULT_FOV_DEG
from wonderverse.planning.intents import intent_direction, interpret_intent
from wonderverse.planning.limits import FULL_TURN_DEG, fit_move
from wonderverse.planning.moves import DIRECTION_AXIS, CameraMove, PlanError, PlanParseError, parse_move
from wonderverse.planning.params import Direction, ExtensionSpec, PlanParams
from wonderverse.planning.segments import Plan, PlannedSegment, next_segment

RULES = "rules"


def extension_jobs(extensions: ExtensionSpec) -> list[tuple[Direction, str]]:
    """(direction, user's words) per extension in generation order: each round visits every direction.

    The direction is the one the words name, else the round's. PlanError if there are more intents than
    extensions.
    """
    defaults = [d for _ in range(extensions.rounds) for d in extensions.directions]
    if len(extensions.intents) > len(defaults):
        raise PlanError(
            f"{len(extensions.intents)} intents given for {len(defaults)} extensions "
            f"({extensions.rounds} round(s) of {', '.join(extensions.directions)})"
        )
    intents = [*extensions.intents, *[""] * (len(defaults) - len(extensions.intents))]
    return [(intent_direction(words) or d, words) for d, words in zip(defaults, intents, strict=True)]


def initial_segment(params: PlanParams, fov_deg: float) -> PlannedSegment:
    """The init segment: `params.initial_move`, clamped so it alone keeps within the view limits."""
    try:
        move = parse_move(params.initial_move, any_order=True)
    except PlanParseError as e:
        raise PlanParseError(f"steps.plan.initial_move {params.initial_move!r}: {e}") from None
    max_yaw = FULL_TURN_DEG - fov_deg
    max_pitch = params.max_pitch_deg
    clamped = CameraMove(
        yaw_deg=min(max(move.yaw_deg, -max_yaw), max_yaw),
        pitch_deg=min(max(move.pitch_deg, -max_pitch), max_pitch),
        forward_m=move.forward_m,
    )
    return next_segment((), "init", clamped)


def plan_scene(
    description: str, extensions: ExtensionSpec, params: PlanParams, *, fov_deg: float = DEFAULT_FOV_DEG
) -> Plan:
    """The rule plan: init from `params.initial_move`, then one segment per extension job.

    Steps shrink so that all planned turns fit in 360° and all tilts within the pitch limit; `description`
    is not used by the rules (planners share one signature).
    """
    jobs = extension_jobs(extensions)
    segments = [initial_segment(params, fov_deg)]
    steps = _fitting_steps(params, [d for d, _ in jobs], segments[0].move, fov_deg)
    for direction, words in jobs:
        segments.append(rule_segment(segments, words, direction, steps, fov_deg))
    return Plan(segments=tuple(segments), planner=RULES)


def plan_extension(
    description: str,
    words: str,
    history: Plan,
    params: PlanParams,
    *,
    fov_deg: float = DEFAULT_FOV_DEG,
    default_direction: Direction | None = None,
) -> PlannedSegment:
    """The next segment after `history` for the user's `words`.

    Its role is the direction of the interpreted move; words without a direction go `default_direction`,
    or, if that is None, towards the less explored side (left on a tie).
    """
    default = default_direction or _less_explored_side(history.segments)
    return rule_segment(history.segments, words, default, params, fov_deg)


def rule_segment(
    segments: Sequence[PlannedSegment], words: str, default: Direction, params: PlanParams, fov_deg: float
) -> PlannedSegment:
    """The segment after `segments` that the words ask for, fitted to the view limits (see limits.py)."""
    move = interpret_intent(words, default, params)
    role = move.dominant_direction()
    return next_segment(segments, role, fit_move(segments, role, move, params, fov_deg), words)


class RulePlanner:
    """The rule-based planner behind the common planner interface."""

    name = RULES

    def plan_scene(
        self,
        description: str,
        extensions: ExtensionSpec,
        params: PlanParams,
        *,
        fov_deg: float = DEFAULT_FOV_DEG,
    ) -> Plan:
        return plan_scene(description, extensions, params, fov_deg=fov_deg)

    def plan_extension(
        self,
        description: str,
        words: str,
        history: Plan,
        params: PlanParams,
        *,
        fov_deg: float = DEFAULT_FOV_DEG,
        default_direction: Direction | None = None,
    ) -> PlannedSegment:
        return plan_extension(description, words, history, params, fov_deg=fov_deg, default_direction=default_direction)


def _fitting_steps(params: PlanParams, directions: Sequence[Direction], init: CameraMove, fov_deg: float) -> PlanParams:
    """`params` with the yaw and pitch steps shrunk so that every planned turn and tilt fits the limits."""
    count = {d: directions.count(d) for d in DIRECTION_AXIS}
    yaw_room = FULL_TURN_DEG - fov_deg - abs(init.yaw_deg)
    max_pitch = params.max_pitch_deg
    yaw_step = min([params.yaw_step_deg] + ([yaw_room / n] if (n := count["left"] + count["right"]) else []))
    pitch_step = min(
        [params.pitch_step_deg]
        + ([(max_pitch - init.pitch_deg) / count["up"]] if count["up"] else [])
        + ([(max_pitch + init.pitch_deg) / count["down"]] if count["down"] else [])
    )
    # A zero step is invalid in PlanParams; fit_move reports the exhausted direction instead.
    return params.model_copy(update={"yaw_step_deg": max(yaw_step, 1e-3), "pitch_step_deg": max(pitch_step, 1e-3)})


def _less_explored_side(segments: Sequence[PlannedSegment]) -> Direction:
    left = sum(s.move.yaw_deg for s in segments if s.role == "left")
    right = -sum(s.move.yaw_deg for s in segments if s.role == "right")
    return "right" if right < left else "left"
