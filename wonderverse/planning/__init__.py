"""Camera planning: the paper's answer format, the rule-based planner (default) and the chat planner.

A planner turns the scene description and the user's words into `PlannedSegment`s: which camera move each
video segment makes, which frame of the stitched video it starts from, and where it goes in playback.
"""

from __future__ import annotations

from typing import Protocol

from wonderverse.planning.chat import PAPER_PROMPT, ChatPlanner
from wonderverse.planning.intents import intent_direction, interpret_intent
from wonderverse.planning.moves import CameraMove, PlanError, PlanParseError, parse_move, parse_moves
from wonderverse.planning.params import Direction, ExtensionSpec, PlannerSpec, PlanParams
from wonderverse.planning.rules import DEFAULT_FOV_DEG, RulePlanner, plan_extension, plan_scene
from wonderverse.planning.segments import Plan, PlannedSegment, stitched_order


class Planner(Protocol):
    name: str

    def plan_scene(
        self, description: str, extensions: ExtensionSpec, params: PlanParams, *, fov_deg: float = ...
    ) -> Plan: ...

    def plan_extension(
        self,
        description: str,
        words: str,
        history: Plan,
        params: PlanParams,
        *,
        fov_deg: float = ...,
        default_direction: Direction | None = ...,
    ) -> PlannedSegment: ...


def make_planner(spec: PlannerSpec) -> Planner:
    """The planner `spec.backend` names: `RulePlanner()` or `ChatPlanner(spec)`."""
    return ChatPlanner(spec) if spec.backend == "chat" else RulePlanner()


__all__ = [
    "DEFAULT_FOV_DEG",
    "PAPER_PROMPT",
    "CameraMove",
    "ChatPlanner",
    "Plan",
    "PlanError",
    "PlanParseError",
    "PlannedSegment",
    "Planner",
    "RulePlanner",
    "intent_direction",
    "interpret_intent",
    "make_planner",
    "parse_move",
    "parse_moves",
    "plan_extension",
    "plan_scene",
    "stitched_order",
]
