"""The chat planner: an OpenAI-compatible chat-completions endpoint asked with the paper's prompt.

Any failure (transport, HTTP status, malformed response, an answer that does not parse strictly or does not
fit the planned roles and view limits) logs one warning and falls back to the rule-based plan. The API key
is read from the environment at request time, sent only in the Authorization header, and masked (whole and
any 8-character part, `secrets.mask_secret`) in the server's text as it arrives, before anything shortens it,
and in httpx's and httpcore's log records. Each attempt is bounded as a whole by `timeout_s` (connect, send and
every byte of the answer: a server that drips its answer is cut off) and the answer by MAX_ANSWER_BYTES.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from collections.abc import Sequence
from contextlib import suppress
from typing import TYPE_CHECKING, Any

import wonderverse.planning.rules as rules
from wonderverse.planning.intents import intent_direction
from wonderverse.planning.limits import move_problem
from wonderverse.planning.moves import CameraMove, PlanParseError, parse_moves
from wonderverse.planning.params import Direction, ExtensionSpec, PlannerSpec, PlanParams
from wonderverse.planning.secrets import mask_secret, masked_logs
from wonderverse.planning.segments import Plan, PlannedSegment, Role, next_segment

if TYPE_CHECKING:
    from collections.abc import Callable

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
# A plan's answer is a few hundred bytes; a megabyte is a misconfigured or hostile server. A constant rather than
# a setting: every planner setting is hashed into the plan's key, and this limit changes no plan.
MAX_ANSWER_BYTES = 1 << 20


class ChatFailure(Exception):
    """Why the chat planner's answer cannot be used (internal: always caught and turned into a fallback)."""


class _Expired(Exception):
    """An attempt ran past its deadline (turned into a ChatFailure that says so)."""


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
        """The model's answer text to the paper's prompt and `user_message`, the API key masked."""
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
        with masked_logs(key):
            text = self._post(body, headers, lambda t: mask_secret(t, key))
        return mask_secret(_answer_text(text), key)

    def _post(self, body: dict[str, Any], headers: dict[str, str], mask: Callable[[str], str]) -> str:
        """The endpoint's answer text (`mask`ed), retrying transport errors, timeouts and 5xx; ChatFailure unless
        it is HTTP 200."""
        import httpx  # here, not at the top: the CLI imports this package and should start fast

        url = f"{self.spec.base_url.rstrip('/')}/chat/completions"
        attempts = self.spec.max_retries + 1
        for _ in range(attempts):
            try:
                status, text = _request(url, body, headers, self.spec.timeout_s, mask)
            except _Expired:
                problem = f"chat server {url} did not answer within {self.spec.timeout_s:g} s"
                continue
            except httpx.HTTPError as e:
                problem = mask(f"cannot reach {url}: {type(e).__name__} {e}".strip())
                continue
            if status < 500:
                break
            problem = f"HTTP {status} from {url}"
        else:
            raise ChatFailure(f"{problem} (after {attempts} attempt(s))")
        if status != 200:
            raise ChatFailure(f"HTTP {status} from {url}: {_snippet(text)}")
        return text

    def _fallback_reason(self, failure: ChatFailure) -> str:
        """The failure as one line with the API key masked; logged as a warning."""
        key = os.environ.get(self.spec.api_key_env)
        reason = mask_secret(" ".join(mask_secret(str(failure), key).split()), key)
        logger.warning("chat planner failed, using the rule-based plan: %s", reason)
        return reason


def _request(
    url: str, body: dict[str, Any], headers: dict[str, str], timeout_s: float, mask: Callable[[str], str]
) -> tuple[int, str]:
    """One POST: (HTTP status, answer text passed through `mask`). _Expired when it takes more than `timeout_s`
    in all (httpx's own timeouts bound each operation only: at the deadline a timer shuts the socket, which ends
    a blocked read at once); ChatFailure for an answer over MAX_ANSWER_BYTES or a compressed one; httpx errors."""
    import httpx

    deadline = time.monotonic() + timeout_s
    lock = threading.Lock()
    expired = threading.Event()
    sockets: list[socket.socket] = []

    def cut(sock: socket.socket) -> None:
        with suppress(OSError):  # already closed
            sock.shutdown(socket.SHUT_RDWR)

    def trace(event: str, info: dict[str, Any]) -> None:  # httpcore's documented `trace` request extension
        if event.endswith((".connect_tcp.complete", ".start_tls.complete")):  # direct, through a proxy, TLS
            sock = info["return_value"].get_extra_info("socket")
            if sock is None:
                return
            with lock:
                sockets.append(sock)
            if expired.is_set():  # connected just as the deadline passed
                cut(sock)

    def expire() -> None:
        with lock:
            expired.set()
            for sock in sockets:
                cut(sock)

    def too_big(size: str) -> ChatFailure:
        return ChatFailure(f"the answer of {url} is {size}, over the limit of {MAX_ANSWER_BYTES} bytes")

    timer = threading.Timer(timeout_s, expire)
    timer.daemon = True
    timer.start()
    try:
        with (
            httpx.Client(timeout=timeout_s) as client,
            client.stream(
                "POST",
                url,
                json=body,
                headers={**headers, "Accept-Encoding": "identity"},  # compressed: no bound on the unpacked size
                extensions={"trace": trace},
            ) as response,
        ):
            encoding = response.headers.get("Content-Encoding", "identity").strip().lower()
            if encoding not in ("", "identity"):
                raise ChatFailure(f"{url} answered compressed ({_snippet(mask(encoding))}), which is not read")
            declared = response.headers.get("Content-Length", "").strip()
            if declared.isdigit() and int(declared) > MAX_ANSWER_BYTES:
                raise too_big(f"{int(declared)} bytes")
            data = bytearray()
            for chunk in response.iter_raw():
                data += chunk
                if len(data) > MAX_ANSWER_BYTES:
                    raise too_big(f"more than {MAX_ANSWER_BYTES} bytes")
                if time.monotonic() > deadline:
                    raise _Expired
            status, charset = response.status_code, response.charset_encoding
    except httpx.HTTPError:
        if expired.is_set() or time.monotonic() >= deadline:
            raise _Expired from None
        raise
    finally:
        timer.cancel()
    try:
        text = data.decode(charset or "utf-8", errors="replace")
    except LookupError:  # a charset Python does not know
        text = data.decode("utf-8", errors="replace")
    return status, mask(text)


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


def _answer_text(text: str) -> str:
    """`choices[0].message.content` of a chat-completions response's text."""
    try:
        data = json.loads(text)
    except (ValueError, RecursionError):
        raise ChatFailure(f"the response is not JSON: {_snippet(text)}") from None
    try:
        content = data["choices"][0]["message"]["content"]
    except (KeyError, IndexError, TypeError):
        content = None
    if not isinstance(content, str):
        raise ChatFailure(f"the response has no choices[0].message.content: {_snippet(text)}")
    return content


def _snippet(text: str) -> str:
    text = " ".join(text.split())
    return repr(text if len(text) <= _SNIPPET_CHARS else text[:_SNIPPET_CHARS] + "...")
