"""The chat planner: an OpenAI-compatible chat-completions endpoint asked with the paper's prompt.

Any failure (transport, HTTP status, malformed response, an answer that does not parse strictly or does not
fit the planned roles and view limits) logs one warning and falls back to the rule-based plan. The API key
is read from the environment at request time, sent only in the Authorization header and redacted from every
reason this module writes.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import wonderverse.planning.rules as rules
from wonderverse.planning.intents import intent_direction
from wonderverse.planning.limits import move_problem
from wonderverse.planning.moves import CameraMove, PlanParseError, parse_moves
from wonderverse.planning.params import Direction, ExtensionSpec, PlannerSpec, PlanParams
from wonderverse.planning.segments import Plan, PlannedSegment, Role, next_segment

if TYPE_CHECKING:
    import httpx

logger = logging.getLogger("wonderverse.planning")

CHAT = "chat"
FALLBACK = "rules (fallback from chat)"
# The paper's prompt (Sec. 4.1), verbatim but for its LaTeX: `$X$` is written X.
PAPER_PROMPT = (
    "Provide the direction and angle of camera pose changes based on the given scene description given by "
    "the user. The answer only includes the corresponding angles of up, down, left, right, and the distance "
    "of forward and backward movement of four times extend, and it is required that the perspective "
    "expansion cannot be repeated. Just give the four answers, format of each answer is: up or down X, left "
    "or right X, forward or back X. (X is the angle or distance). If the extension prompt is given, just "
    "give one answer."
)
_SNIPPET_CHARS = 200


class ChatFailure(Exception):
    """Why the chat planner's answer cannot be used (internal: always caught and turned into a fallback)."""


class ChatPlanner:
    """Plans with a chat model; same methods, signatures and results as `rules.RulePlanner`."""

    name = CHAT

    def __init__(self, spec: PlannerSpec) -> None:
        self.spec = spec

    def __repr__(self) -> str:
        return f"ChatPlanner(base_url={self.spec.base_url!r}, model={self.spec.model!r})"

    def plan_scene(
        self,
        description: str,
        extensions: ExtensionSpec,
        params: PlanParams,
        *,
        fov_deg: float = rules.DEFAULT_FOV_DEG,
    ) -> Plan:
        """The chat model's plan (init from `params.initial_move`); the rule plan if anything goes wrong."""
        jobs = rules.extension_jobs(extensions)
        init = rules.initial_segment(params, fov_deg)
        try:
            moves = _parse(self._ask(scene_message(description, jobs)), len(jobs)) if jobs else []
            segments = _checked_segments([init], jobs, moves, params, fov_deg)
        except ChatFailure as e:
            fallback = rules.plan_scene(description, extensions, params, fov_deg=fov_deg)
            return Plan(segments=fallback.segments, planner=FALLBACK, fallback_reason=self._fallback_reason(e))
        return Plan(segments=segments, planner=CHAT)

    def plan_extension(
        self,
        description: str,
        words: str,
        history: Plan,
        params: PlanParams,
        *,
        fov_deg: float = rules.DEFAULT_FOV_DEG,
        default_direction: Direction | None = None,
    ) -> PlannedSegment:
        """The chat model's next segment for `words` (role: the direction the words name, else the move's)."""
        try:
            (move,) = _parse(self._ask(extension_message(description, words)), 1)
            role = intent_direction(words) or move.dominant_direction()
            return _checked_segments(history.segments, [(role, words)], [move], params, fov_deg)[-1]
        except ChatFailure as e:
            self._fallback_reason(e)
            return rules.plan_extension(
                description, words, history, params, fov_deg=fov_deg, default_direction=default_direction
            )

    def _ask(self, user_message: str) -> str:
        """The model's answer text to the paper's prompt and `user_message`."""
        body = {
            "model": self.spec.model,
            "messages": [
                {"role": "system", "content": PAPER_PROMPT},
                {"role": "user", "content": user_message},
            ],
            "temperature": 0,
        }
        key = os.environ.get(self.spec.api_key_env)
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        return _answer_text(self._post(body, headers))

    def _post(self, body: dict[str, Any], headers: dict[str, str]) -> httpx.Response:
        """The endpoint's response, retrying transport errors and 5xx; ChatFailure unless it is 200."""
        import httpx  # here, not at the top: the CLI imports this package and should start fast

        url = f"{self.spec.base_url.rstrip('/')}/chat/completions"
        attempts = self.spec.max_retries + 1
        with httpx.Client(timeout=self.spec.timeout_s) as client:
            for _ in range(attempts):
                try:
                    response = client.post(url, json=body, headers=headers)
                except httpx.TransportError as e:
                    problem = f"cannot reach {url}: {type(e).__name__} {e}".strip()
                    continue
                if response.status_code < 500:
                    break
                problem = f"HTTP {response.status_code} from {url}"
            else:
                raise ChatFailure(f"{problem} (after {attempts} attempt(s))")
        if response.status_code != 200:
            raise ChatFailure(f"HTTP {response.status_code} from {url}: {_snippet(response.text)}")
        return response

    def _fallback_reason(self, failure: ChatFailure) -> str:
        """The failure as one line with the API key redacted; logged as a warning."""
        reason = " ".join(str(failure).split())
        if key := os.environ.get(self.spec.api_key_env):
            reason = reason.replace(key, "***")
        logger.warning("chat planner failed, using the rule-based plan: %s", reason)
        return reason


def scene_message(description: str, jobs: Sequence[tuple[Direction, str]]) -> str:
    """The user message for a whole scene: the description and one line per extension, in order."""
    lines = [f"{i}. {direction}" + (f": {words}" if words else "") for i, (direction, words) in enumerate(jobs, 1)]
    return (
        f"Scene description: {description}\n"
        f"Give {len(jobs)} answers, one per line, for these extensions in order:\n" + "\n".join(lines)
    )


def extension_message(description: str, words: str) -> str:
    """The user message for one interactive extension."""
    return f"Scene description: {description}\nExtension prompt: {words or '(none)'}\nGive 1 answer."


def _checked_segments(
    segments: Sequence[PlannedSegment],
    jobs: Sequence[tuple[Role, str]],
    moves: Sequence[CameraMove],
    params: PlanParams,
    fov_deg: float,
) -> tuple[PlannedSegment, ...]:
    """`segments` and then one per (role, words) job with the model's move for it.

    ChatFailure if a move goes the wrong way for its role or repeats views (see limits.py).
    """
    out = list(segments)
    for i, ((role, words), move) in enumerate(zip(jobs, moves, strict=True), start=1):
        if problem := move_problem(out, role, move, params, fov_deg):
            raise ChatFailure(f"answer {i} ({move.to_paper()}) for the {role} extension: {problem}")
        out.append(next_segment(out, role, move, words))
    return tuple(out)


def _parse(answer: str, expected: int) -> list[CameraMove]:
    try:
        return parse_moves(answer, expected)
    except PlanParseError as e:
        raise ChatFailure(f"unusable answer: {e}") from None


def _answer_text(response: httpx.Response) -> str:
    """`choices[0].message.content` of a chat-completions response."""
    try:
        data = response.json()
    except ValueError:
        raise ChatFailure(f"the response is not JSON: {_snippet(response.text)}") from None
    try:
        content = data["choices"][0]["message"]["content"]
    except (KeyError, IndexError, TypeError):
        content = None
    if not isinstance(content, str):
        raise ChatFailure(f"the response has no choices[0].message.content: {_snippet(response.text)}")
    return content


def _snippet(text: str) -> str:
    text = " ".join(text.split())
    return repr(text if len(text) <= _SNIPPET_CHARS else text[:_SNIPPET_CHARS] + "...")
