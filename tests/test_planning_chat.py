"""The chat planner against a real local HTTP server speaking the chat-completions protocol."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from wonderverse.config import ExtensionSpec, PlannerSpec, PlanParams
from wonderverse.planning import (
    PAPER_PROMPT,
    CameraMove,
    ChatPlanner,
    Plan,
    PlanError,
    plan_extension,
    plan_scene,
)

KEY = "sk-test-S3CRET-do-not-leak-42"
KEY_ENV = "WV_TEST_CHAT_KEY"
DESCRIPTION = "a lighthouse on a rocky coast at dusk"
PARAMS = PlanParams()
EXTENSIONS = ExtensionSpec(rounds=1, directions=("left", "right"))
FALLBACK = "rules (fallback from chat)"


@dataclass
class Reply:
    status: int = 200
    body: bytes = b""
    delay_s: float = 0.0
    echo: Callable[[str], bytes] | None = None  # the body made from the request's Authorization header
    reason: str | None = None  # the status line's reason phrase
    headers: dict[str, str] = field(default_factory=dict)
    raw: Callable[[BaseHTTPRequestHandler], None] | None = None  # writes the whole response itself


def completion(content: str) -> Reply:
    return Reply(
        body=json.dumps({"choices": [{"index": 0, "message": {"role": "assistant", "content": content}}]}).encode()
    )


@dataclass
class ChatServer:
    """Replies from a queue (the last one repeats) and records every request it receives."""

    replies: deque[Reply] = field(default_factory=deque)
    requests: list[dict] = field(default_factory=list)
    url: str = ""

    def reply(self) -> Reply:
        return self.replies.popleft() if len(self.replies) > 1 else self.replies[0]


@pytest.fixture
def server(monkeypatch: pytest.MonkeyPatch) -> Iterator[ChatServer]:
    for name in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
        monkeypatch.delenv(name, raising=False)
    state = ChatServer()

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
            state.requests.append({"path": self.path, "headers": dict(self.headers), "json": json.loads(body)})
            reply = state.reply()
            time.sleep(reply.delay_s)
            body = reply.echo(self.headers.get("Authorization", "")) if reply.echo else reply.body
            try:
                if reply.raw is not None:
                    reply.raw(self)
                    return
                self.send_response(reply.status, reply.reason)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                for name, value in reply.headers.items():
                    self.send_header(name, value)
                self.end_headers()
                self.wfile.write(body)
            except OSError:  # the client gave up (timeout test)
                pass

        def log_message(self, *args: object) -> None:
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    httpd.daemon_threads = True
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    state.url = f"http://127.0.0.1:{httpd.server_address[1]}/v1"
    yield state
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture
def key(monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setenv(KEY_ENV, KEY)
    return KEY


def planner(url: str, **spec: object) -> ChatPlanner:
    return ChatPlanner(PlannerSpec(backend="chat", base_url=url, model="test-model", api_key_env=KEY_ENV, **spec))


def assert_fallback(plan: Plan, caplog: pytest.LogCaptureFixture, *reason_parts: str) -> None:
    assert plan.planner == FALLBACK
    assert plan.segments == plan_scene(DESCRIPTION, EXTENSIONS, PARAMS).segments
    for part in reason_parts:
        assert part in plan.fallback_reason
    warnings = [r for r in caplog.records if r.name == "wonderverse.planning" and r.levelno == logging.WARNING]
    assert len(warnings) == 1 and plan.fallback_reason in warnings[0].getMessage()
    assert "\n" not in warnings[0].getMessage()
    assert_no_key(plan.model_dump_json(), caplog.text, plan.fallback_reason)


def assert_no_key(*texts: str) -> None:
    for text in texts:
        assert KEY not in text


def test_good_answer_is_used(server: ChatServer, key: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)  # httpx/httpcore debug logs must not leak the key either
    server.replies.append(completion("1. up 0, left 30, forward 1\n2. up 5, right 25 degrees, forward 1.5 m"))
    chat = planner(server.url)
    plan = chat.plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert plan.planner == "chat" and plan.fallback_reason is None
    assert [s.role for s in plan.segments] == ["init", "left", "right"]
    assert [s.move for s in plan.segments] == [
        CameraMove(yaw_deg=-30, forward_m=2),  # PlanParams.initial_move
        CameraMove(yaw_deg=30, forward_m=1),
        CameraMove(yaw_deg=-25, pitch_deg=5, forward_m=1.5),
    ]
    (request,) = server.requests
    assert request["path"] == "/v1/chat/completions"
    assert request["headers"]["Authorization"] == f"Bearer {key}"
    body = request["json"]
    assert body["model"] == "test-model" and body["temperature"] == 0
    system, user = body["messages"]
    assert system == {"role": "system", "content": PAPER_PROMPT}
    assert "Provide the direction and angle of camera pose changes" in system["content"]
    assert user["role"] == "user" and DESCRIPTION in user["content"] and "Give 2 answers" in user["content"]
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert_no_key(plan.model_dump_json(), caplog.text, repr(chat), repr(plan))


def test_no_key_sends_no_authorization(server: ChatServer, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(KEY_ENV, raising=False)
    server.replies.append(completion("up 0, left 30, forward 1\nup 0, right 30, forward 1"))
    assert planner(server.url).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS).planner == "chat"
    assert "Authorization" not in server.requests[0]["headers"]


def test_intents_reach_the_model_and_steer_roles(server: ChatServer, key: str) -> None:
    spec = ExtensionSpec(rounds=1, intents=("add a frozen lake on the right",))
    server.replies.append(completion("up 0, right 20, forward 1\nup 0, right 40, forward 1"))
    plan = planner(server.url).plan_scene(DESCRIPTION, spec, PARAMS)
    assert [s.role for s in plan.segments] == ["init", "right", "right"]
    assert "add a frozen lake on the right" in server.requests[0]["json"]["messages"][1]["content"]


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        ("Sure! Here is the plan: go left, then right.", "unusable answer: line 1"),
        ("up 0, left 30, forward 1", "expected 2 answer(s), got 1"),
        (
            "up 0, right 30, forward 1\nup 0, right 30, forward 1",
            "for the left extension: a left segment needs yaw > 0",
        ),
        ("up 0, left 180, forward 1\nup 0, right 180, forward 1", "more than 360°"),
        ("up 0, left 30, forward 1\nup 80, right 30, forward 1", "tilt 80° up (limit 60°)"),
        (f"up 0, left 30, forward 1\nup 0, right 30, forward {KEY}", "unusable answer: line 2"),
    ],
)
def test_unusable_answers_fall_back(
    server: ChatServer, key: str, caplog: pytest.LogCaptureFixture, content: str, reason: str
) -> None:
    server.replies.append(completion(content))
    assert_fallback(planner(server.url).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS), caplog, reason)


@pytest.mark.parametrize(
    ("body", "reason"),
    [
        (b"<html>gateway</html>", "the response is not JSON"),
        (b'{"object": "chat.completion"}', "no choices[0].message.content"),
        (b'{"choices": []}', "no choices[0].message.content"),
        (b'{"choices": [{"message": {"content": null}}]}', "no choices[0].message.content"),
        (b"\xff\xfe\x00", "the response is not JSON"),
    ],
)
def test_malformed_responses_fall_back(
    server: ChatServer, key: str, caplog: pytest.LogCaptureFixture, body: bytes, reason: str
) -> None:
    server.replies.append(Reply(body=body))
    assert_fallback(planner(server.url).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS), caplog, reason)


def test_server_error_is_retried(server: ChatServer, key: str) -> None:
    server.replies.extend(
        [Reply(status=500, body=b"oops"), completion("up 0, left 30, forward 1\nup 0, right 30, forward 1")]
    )
    plan = planner(server.url, max_retries=1).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert plan.planner == "chat" and len(server.requests) == 2


def test_persistent_server_error_falls_back(server: ChatServer, key: str, caplog: pytest.LogCaptureFixture) -> None:
    server.replies.append(Reply(status=503, body=b"busy"))
    plan = planner(server.url, max_retries=2).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert_fallback(plan, caplog, "HTTP 503", "after 3 attempt(s)")
    assert len(server.requests) == 3


def test_unauthorized_is_not_retried_and_never_leaks_the_key(
    server: ChatServer, key: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    server.replies.append(Reply(status=401, body=json.dumps({"error": f"invalid key {key}"}).encode()))
    plan = planner(server.url, max_retries=3).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert_fallback(plan, caplog, "HTTP 401", "invalid key ***")
    assert len(server.requests) == 1


def test_slow_server_times_out(server: ChatServer, key: str, caplog: pytest.LogCaptureFixture) -> None:
    server.replies.append(Reply(body=completion("up 0, left 30, forward 1\nup 0, right 30, forward 1").body, delay_s=3))
    start = time.monotonic()
    plan = planner(server.url, timeout_s=0.5, max_retries=1).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert time.monotonic() - start < 2.5
    assert_fallback(plan, caplog, f"chat server {server.url}/chat/completions did not answer within 0.5 s")
    assert "after 2 attempt(s)" in plan.fallback_reason and len(server.requests) == 2


def test_connection_refused(key: str, caplog: pytest.LogCaptureFixture) -> None:
    with socket.socket() as s:  # a port that nothing listens on once the socket is closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    plan = planner(f"http://127.0.0.1:{port}/v1", max_retries=1).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert_fallback(plan, caplog, "cannot reach", "ConnectError", "after 2 attempt(s)")


def test_no_extensions_needs_no_request(server: ChatServer, key: str) -> None:
    server.replies.append(Reply(status=500))
    plan = planner(server.url).plan_scene(DESCRIPTION, ExtensionSpec(rounds=0), PARAMS)
    assert plan.planner == "chat" and len(plan.segments) == 1 and not server.requests


def test_input_errors_are_raised_not_swallowed(server: ChatServer, key: str) -> None:
    server.replies.append(completion("up 0, left 30, forward 1"))
    with pytest.raises(PlanError, match="3 intents given for 2 extensions") as info:
        planner(server.url).plan_scene(DESCRIPTION, ExtensionSpec(intents=("a", "b", "c")), PARAMS)
    assert_no_key(str(info.value))


def test_extension_uses_one_answer(server: ChatServer, key: str, caplog: pytest.LogCaptureFixture) -> None:
    history = plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    server.replies.append(completion("Answer 1: up 10, left 40, forward 1"))
    seg = planner(server.url).plan_extension(DESCRIPTION, "add a frozen lake on the left", history, PARAMS)
    assert (seg.id, seg.role, seg.reference_segment, seg.move) == (
        "s003",
        "left",
        "s001",
        CameraMove(yaw_deg=40, pitch_deg=10, forward_m=1),
    )
    user = server.requests[0]["json"]["messages"][1]["content"]
    assert DESCRIPTION in user and "add a frozen lake on the left" in user
    assert not caplog.records


def test_extension_role_from_the_move_when_words_name_none(server: ChatServer, key: str) -> None:
    history = plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    server.replies.append(completion("up 20, left 5, forward 0"))
    seg = planner(server.url).plan_extension(DESCRIPTION, "show the stars", history, PARAMS)
    assert (seg.role, seg.reference, seg.reference_segment) == ("up", "last", "s002")


def test_extension_disagreeing_with_the_words_falls_back(
    server: ChatServer, key: str, caplog: pytest.LogCaptureFixture
) -> None:
    history = plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    server.replies.append(completion("up 0, right 40, forward 1"))
    words = "add a frozen lake on the left"
    seg = planner(server.url).plan_extension(DESCRIPTION, words, history, PARAMS)
    assert seg == plan_extension(DESCRIPTION, words, history, PARAMS)
    (warning,) = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "a left segment needs yaw > 0" in warning.getMessage()


# -- the key never leaks, whole or in part ------------------------------------------------------------------

LONG_KEY = "sk-ADVSECRET-" + "Zq7Lm2Vx9Rt4Kp8Wn3Hj6Bc1Yf5Gd0Se7Ua2Io4Pl9Mk3Nb8Vc"  # 63 characters, as long as real keys


def parts_of(secret: str, n: int = 8) -> set[str]:
    return {secret[i : i + n] for i in range(len(secret) - n + 1)}


def assert_no_part_of_key(*texts: str) -> None:
    """Neither the key nor any 8 characters of it (every prefix, suffix and inner part of 8 or more contains one)."""
    parts = parts_of(LONG_KEY)
    for text in texts:
        found = sorted(p for p in parts if p in text)
        assert not found, f"key parts {found[:3]} in {text[:300]!r}"


def _two_answers_then(tail: str) -> Reply:
    return completion(f"up 0, left 30, forward 1\nup 0, right 30, forward {tail}")


LEAKS = {
    # a server that echoes the Authorization header it received
    "401 echoing the header": Reply(status=401, echo=lambda auth: json.dumps({"error": f"bad header {auth}"}).encode()),
    "non-JSON echoing the header": Reply(echo=lambda auth: f"<html><pre>Authorization: {auth}</pre></html>".encode()),
    # the key inside a long text: a reason cut at 200 characters splits it
    "400 key across the cut": Reply(status=400, body=("x" * 186 + " " + LONG_KEY + " y").encode()),
    "no content, key across the cut": Reply(body=json.dumps({"note": "n" * 150, "k": LONG_KEY}).encode()),
    # the key's first 20 characters
    "answer with a key prefix": _two_answers_then(LONG_KEY[:20]),
    "answer of a key prefix": completion(f"{LONG_KEY[:20]}\n{LONG_KEY[:20]}"),
    "JSON-escaped key in the answer": Reply(
        body=json.dumps({"choices": [{"message": {"content": f"up 0, left 30, {LONG_KEY}"}}]}, ensure_ascii=True)
        .replace("sk-", "\\u0073k-")
        .encode()
    ),
    # where httpx and httpcore log what the server said: the status line and the response headers
    "status line": Reply(status=502, reason=f"Bad {LONG_KEY}", body=b"{}"),
    "response header": Reply(status=418, headers={"X-Echo": f"Bearer {LONG_KEY}"}, body=b"{}"),
}


@pytest.fixture
def long_key(monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setenv(KEY_ENV, LONG_KEY)
    return LONG_KEY


@pytest.mark.parametrize("leak", sorted(LEAKS))
def test_a_server_echoing_the_key_gets_no_part_of_it_into_reasons_or_logs(
    server: ChatServer, long_key: str, caplog: pytest.LogCaptureFixture, leak: str
) -> None:
    caplog.set_level(logging.DEBUG)  # httpx's status lines and httpcore's response headers included
    server.replies.append(LEAKS[leak])
    chat = planner(server.url, max_retries=0)
    plan = chat.plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert plan.planner == FALLBACK and plan.fallback_reason
    assert server.requests[0]["headers"]["Authorization"] == f"Bearer {long_key}"  # the key was sent
    history = plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    segment = chat.plan_extension(DESCRIPTION, "add a frozen lake on the left", history, PARAMS)
    messages = [r.getMessage() for r in caplog.records]
    assert any("HTTP Request: POST" in m for m in messages)  # httpx's log line was made (and masked)
    assert_no_part_of_key(
        plan.model_dump_json(), plan.fallback_reason, segment.model_dump_json(), caplog.text, *messages
    )


def test_mask_secret_masks_every_run_of_eight_or_more() -> None:
    from wonderverse.planning.secrets import mask_secret

    key = LONG_KEY
    assert mask_secret(f"Bearer {key}.", key) == "Bearer ***."
    assert mask_secret(f"a {key[:8]} b {key[-8:]} c {key[10:31]}", key) == "a *** b *** c ***"
    assert mask_secret(f"a {key[:7]} b", key) == f"a {key[:7]} b"  # 7 characters: ordinary text
    assert mask_secret(key[20:40] + key[:20], key) == "***"  # adjacent runs: one mask
    assert mask_secret("text", None) == mask_secret("text", "") == "text"
    assert mask_secret("id=abc!", "abc") == "id=***!"  # a short key is masked whole
    for i in range(len(key)):  # every cut of every echo
        for j in range(i + 8, len(key) + 1):
            assert_no_part_of_key(mask_secret(f"x{key[i:j]}y{key}", key))


@pytest.mark.e2e
def test_the_plan_step_stores_no_part_of_an_echoed_key(
    server: ChatServer, long_key: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from conftest import tiny_config

    from flows.pipeline import execute

    server.replies.append(LEAKS["400 key across the cut"])
    spec = {"backend": "chat", "base_url": server.url, "api_key_env": KEY_ENV, "max_retries": 0}
    cfg = tiny_config(planner=spec, extensions={"rounds": 1})
    scene = tmp_path / "scene"
    with caplog.at_level(logging.DEBUG):
        (result,) = execute(scene, cfg, until="plan")
    assert result.status == "ran" and "fallback" in result.detail and "HTTP 400" in result.detail
    files = [p for p in scene.rglob("*") if p.is_file()]
    assert files
    assert_no_part_of_key(result.detail, caplog.text, *(p.read_bytes().decode("latin-1") for p in files))


# -- each attempt bounded as a whole, the answer bounded in size --------------------------------------------


def _drip(data: bytes, every_s: float = 0.2) -> Callable[[BaseHTTPRequestHandler], None]:
    def write(handler: BaseHTTPRequestHandler) -> None:
        for i in range(len(data)):
            handler.wfile.write(data[i : i + 1])
            handler.wfile.flush()
            time.sleep(every_s)

    return write


def _head(length: int) -> bytes:
    return f"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {length}\r\n\r\n".encode()


ANSWER = completion("up 0, left 30, forward 1\nup 0, right 30, forward 1").body


@pytest.mark.parametrize(
    "raw",
    [
        pytest.param(lambda h: (h.wfile.write(_head(len(ANSWER))), _drip(ANSWER)(h)), id="body one byte at a time"),
        pytest.param(_drip(_head(len(ANSWER)) + ANSWER), id="status line and headers one byte at a time"),
    ],
)
def test_a_dripping_server_is_cut_off_at_timeout_s(
    server: ChatServer, key: str, caplog: pytest.LogCaptureFixture, raw: Callable[[BaseHTTPRequestHandler], None]
) -> None:
    server.replies.append(Reply(raw=raw))
    start = time.monotonic()
    plan = planner(server.url, timeout_s=1, max_retries=0).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert time.monotonic() - start < 1.5  # each read gets a byte within 0.2 s: httpx's own timeout never fires
    assert_fallback(plan, caplog, "did not answer within 1 s (after 1 attempt(s))")


def test_a_dripping_server_is_cut_off_on_every_attempt(server: ChatServer, key: str) -> None:
    server.replies.append(Reply(raw=lambda h: (h.wfile.write(_head(len(ANSWER))), _drip(ANSWER)(h))))
    start = time.monotonic()
    plan = planner(server.url, timeout_s=0.6, max_retries=1).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert time.monotonic() - start < 1.8 and len(server.requests) == 2
    assert "did not answer within 0.6 s (after 2 attempt(s))" in plan.fallback_reason


def _unsized(size: int) -> Callable[[BaseHTTPRequestHandler], None]:
    """An answer of `size` bytes without a Content-Length (it ends when the server closes the connection)."""

    def write(handler: BaseHTTPRequestHandler) -> None:
        handler.wfile.write(b"HTTP/1.0 200 OK\r\nContent-Type: application/json\r\nConnection: close\r\n\r\n")
        block = b" " * 65536
        for _ in range(size // len(block)):
            handler.wfile.write(block)

    return write


@pytest.mark.parametrize(
    ("reply", "reason"),
    [
        (Reply(body=ANSWER + b" " * (1 << 20)), f"is {len(ANSWER) + (1 << 20)} bytes, over the limit of 1048576"),
        (Reply(raw=_unsized(2 << 20)), "is more than 1048576 bytes, over the limit of 1048576 bytes"),
        (Reply(body=ANSWER, headers={"Content-Encoding": "gzip"}), "answered compressed ('gzip')"),
    ],
)
def test_an_answer_over_the_size_limit_or_compressed_is_refused(
    server: ChatServer, key: str, caplog: pytest.LogCaptureFixture, reply: Reply, reason: str
) -> None:
    from wonderverse.planning.chat import MAX_ANSWER_BYTES

    assert MAX_ANSWER_BYTES == 1 << 20
    server.replies.append(reply)
    plan = planner(server.url, max_retries=2).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS)
    assert_fallback(plan, caplog, reason)
    assert len(server.requests) == 1  # not retried: the same server would send the same


def test_an_answer_just_under_the_limit_is_read(server: ChatServer, key: str) -> None:
    from wonderverse.planning.chat import MAX_ANSWER_BYTES

    server.replies.append(Reply(body=ANSWER + b" " * (MAX_ANSWER_BYTES - len(ANSWER))))
    assert planner(server.url).plan_scene(DESCRIPTION, EXTENSIONS, PARAMS).planner == "chat"
