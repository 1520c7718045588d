"""The segment plan: which video segments to generate, from which frame, and how they are stitched.

The stitched video is continuous: a `left` segment starts from the FIRST frame of the current stitched video,
turns left, and is played reversed in front of it; every other extension starts from the LAST frame and is
appended. So playback order is: newest left (reversed), ..., oldest left (reversed), init, appended ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from wonderverse.planning.moves import CameraMove

Role = Literal["init", "left", "right", "up", "down", "forward", "back"]
Reference = Literal["none", "first", "last"]


class PlannedSegment(BaseModel):
    """One segment to generate; `reference_segment` holds the frame it starts from."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    id: str = Field(pattern=r"^s\d{3,}$", description="s000, s001, ... in generation order")
    role: Role
    move: CameraMove
    intent: str = Field("", description="the user's words for this segment, or empty")
    reference: Reference
    reference_segment: str | None
    reversed: bool = Field(description="played reversed in the stitched video (left segments)")

    @model_validator(mode="after")
    def _consistent(self) -> PlannedSegment:
        if self.reference != reference_kind(self.role):
            raise ValueError(f"a {self.role} segment starts from reference {reference_kind(self.role)!r}")
        if (self.reference_segment is None) != (self.role == "init"):
            raise ValueError("only the init segment has no reference segment")
        if self.reversed != (self.role == "left"):
            raise ValueError("exactly the left segments play reversed")
        return self


class Plan(BaseModel):
    """Segments in generation order, the planner that made them and, after a fallback, why."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    segments: tuple[PlannedSegment, ...] = Field(min_length=1)
    planner: str
    fallback_reason: str | None = None

    @model_validator(mode="after")
    def _consistent(self) -> Plan:
        for i, seg in enumerate(self.segments):
            expected = next_segment(self.segments[:i], seg.role, seg.move, seg.intent)
            if seg != expected:
                raise ValueError(f"segment {i} should be {expected!r}, got {seg!r}")
        return self

    def extended(self, segment: PlannedSegment) -> Plan:
        """This plan with `segment` (made by a planner's `plan_extension`) added at the end."""
        return Plan(segments=(*self.segments, segment), planner=self.planner, fallback_reason=self.fallback_reason)


def reference_kind(role: Role) -> Reference:
    """Which frame of the stitched video a segment of `role` starts from."""
    return "none" if role == "init" else "first" if role == "left" else "last"


def reference_segment(segments: Sequence[PlannedSegment], role: Role) -> str | None:
    """Id of the segment that holds the frame a new `role` segment starts from (None for init)."""
    kind = reference_kind(role)
    if kind == "none":
        return None
    end = [s for s in segments if (s.role == "left") == (kind == "first") and s.role != "init"]
    return end[-1].id if end else segments[0].id


def next_segment(segments: Sequence[PlannedSegment], role: Role, move: CameraMove, intent: str = "") -> PlannedSegment:
    """The segment that follows `segments` in generation order (the first one must be `init`)."""
    if (role == "init") != (not segments):
        raise ValueError("the init segment comes first, and only once")
    return PlannedSegment(
        id=f"s{len(segments):03d}",
        role=role,
        move=move,
        intent=intent,
        reference=reference_kind(role),
        reference_segment=reference_segment(segments, role),
        reversed=role == "left",
    )


def stitched_order(segments: Sequence[PlannedSegment]) -> list[str]:
    """Segment ids in playback order: left segments newest first (each reversed), then the rest in order."""
    lefts = [s.id for s in segments if s.role == "left"]
    return lefts[::-1] + [s.id for s in segments if s.role != "left"]


def clip_plan(clips: Sequence[str]) -> Plan:
    """The user's clips as segments in the given order: the first as `init`, the rest as `right` ones (played
    forward, after the previous); no camera moves are planned, none are generated."""
    segments: list[PlannedSegment] = []
    for i, clip in enumerate(clips):
        segments.append(next_segment(tuple(segments), "init" if i == 0 else "right", CameraMove(), clip))
    return Plan(segments=tuple(segments), planner="clips")
