"""The planner's settings: the scene's extensions, the planner backend, and the sizes of planned moves.

Pydantic only (and the move parser, to check `initial_move` when the config is built): the config composes these,
and the planners read them."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from wonderverse.planning.moves import Direction, PlanParseError, parse_move
from wonderverse.text import url_credentials

MAX_SEGMENTS = 64  # what one scene holds: its store, its poses' solve and its training stay within one machine


class Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ExtensionSpec(Model):
    """How the scene grows beyond the initial video (the paper repeats left+right `rounds` times)."""

    rounds: int = Field(1, ge=0, le=16, description="extension iterations n; each adds one segment per direction")
    directions: tuple[Direction, ...] = Field(
        ("left", "right"),
        min_length=1,
        description="the directions each round extends in, in order (left, right, up, down, forward, back); words "
        "in `intents` that name another direction win",
    )
    intents: tuple[str, ...] = Field((), description="the user's words for each extension, in order")
    added: tuple[str, ...] = Field(
        (), description="extensions added later (`wonderverse extend`), the user's words, oldest first"
    )

    @property
    def segments(self) -> int:
        """Segments the scene has: the initial one, one per direction per round, one per later extension."""
        return 1 + self.rounds * len(self.directions) + len(self.added)

    @model_validator(mode="after")
    def _within_the_cap(self) -> ExtensionSpec:
        if self.segments > MAX_SEGMENTS:
            raise ValueError(
                f"a scene holds at most {MAX_SEGMENTS} segments and this one would have {self.segments}; "
                "start a new scene for more"
            )
        return self


class PlannerSpec(Model):
    """Which planner turns the description and the user's words into camera moves."""

    backend: Literal["rules", "chat"] = Field(
        "rules",
        description="rules: the deterministic planner; chat: an OpenAI-compatible endpoint asked with the paper's "
        "prompt, falling back to the rules on any failure",
    )
    base_url: str = Field("http://127.0.0.1:8000/v1", description="OpenAI-compatible endpoint (chat backend)")
    model: str = Field("gpt-4o-mini", description="model name sent to the chat endpoint")
    api_key_env: str = Field("OPENAI_API_KEY", description="name of the environment variable holding the key")
    timeout_s: float = Field(
        30.0, gt=0, le=600, description="seconds for each attempt as a whole: connect, send, every byte of the answer"
    )
    max_retries: int = Field(
        1, ge=0, le=5, description="requests repeated after a transport error, timeout or HTTP 5xx (not a bad answer)"
    )

    @field_validator("base_url")
    @classmethod
    def _no_credentials(cls, v: str) -> str:
        """A URL's user:password would be printed, logged and stored with the scene (its config is in the store and
        the report): the key belongs in an environment variable (`api_key_env`), read when the request is sent."""
        problem = url_credentials(v)
        if problem is not None:
            raise ValueError(problem)
        return v


class PlanParams(Model):
    """Step `plan`: the initial camera move and the sizes of rule-planned extension moves."""

    initial_move: str = Field(
        "up 0, right 30, forward 2", max_length=200, description="paper format, for the initial video"
    )
    yaw_step_deg: float = Field(
        35.0,
        gt=0,
        le=180,
        description="degrees of a left/right extension whose words give no amount; shrunk so that every planned "
        "turn plus the field of view fits in 360°",
    )
    pitch_step_deg: float = Field(
        15.0,
        gt=0,
        le=89,
        description="degrees of an up/down extension whose words give no amount; shrunk to keep `max_pitch_deg`",
    )
    forward_step_m: float = Field(
        2.0, gt=0, le=100, description="travel (scene units) of a forward/back extension whose words give no amount"
    )

    yaw_forward_m: float = Field(0.5, gt=0, le=100, description="forward travel added to each turn")
    step_variation_ratio: float = Field(0.15, ge=0, lt=1, description="shrink of a repeated move on one side")
    max_pitch_deg: float = Field(60.0, gt=0, le=89, description="pitch limit of each extension chain")
    min_turn_deg: float = Field(1.0, gt=0, description="less room than this: the direction is exhausted")
    strafe_m_per_deg: float = Field(
        0.04, ge=0, le=1, description="sideways travel per degree of yaw, so turns keep parallax for SfM"
    )

    @field_validator("initial_move")
    @classmethod
    def _paper_format(cls, v: str) -> str:
        try:
            parse_move(v, any_order=True)
        except PlanParseError as e:
            raise ValueError(str(e)) from None
        return v
