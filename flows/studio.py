"""`wonderverse studio [ROOT]`: a local web app to create scenes from prompts, watch every step's progress, see
the splats and cameras in 3D, extend them in words, reconstruct clips and download the exports.

The server is FastAPI on uvicorn in the CLI's supervised child (Ctrl-C kills it and every job with it). Jobs are
the CLI's own commands in child processes (`flows.studio_jobs`), so the scene lock, validation and error lines are
the terminal's; the studio checks a request with the CLI's own validators first, so a bad prompt or word is a 400
with the CLI's message before any process starts. Scenes are the folders of ROOT (`flows.studio_scenes`).

Safe by default: it binds 127.0.0.1 (another address only with --host, with a warning); every /api call needs the
launch token printed in the start-up URL, as `Authorization: Bearer TOKEN` (compared in constant time), else 403.
A page of another origin can neither send that header without the token nor read any answer (no CORS headers are
ever sent). Scene files (the 3D view, downloads) need the token too: as the HttpOnly, SameSite=Strict cookie the
start-up URL sets, or `?token=`. The API is documented in docs/studio.md.
"""

import asyncio
import contextlib
import errno
import json
import secrets
import socket
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from wonderverse.errors import WonderError

# No `from __future__ import annotations`: FastAPI reads the routes' annotations (Request) at definition time.
if TYPE_CHECKING:  # the web stack loads when the command runs: `wonderverse --help` stays fast
    from fastapi import FastAPI, Request

PAGE_DIR = Path(__file__).resolve().parent
PAGE_HTML, PAGE_JS = "studio_page.html", "studio_page.js"
MAX_BODY = 256 * 1024  # bytes of a request body: prompts are at most 2000 characters, words 500
KEEP_ALIVE_S = 15.0  # a comment line on an idle event stream, so proxies and the page see it is alive
LOOPBACK = ("127.0.0.1", "localhost", "::1")


class ApiError(Exception):
    """An answer `{"error": message, **extra}` with a 4xx status."""

    def __init__(self, status: int, message: str, **extra: Any):
        super().__init__(message)
        self.status, self.message, self.extra = status, message, extra


def cookie_name(port: int) -> str:
    """The token's cookie, one per port (cookies are shared by every port of a host)."""
    return f"wonderverse_studio_{port}"


async def body_json(request: "Request") -> dict[str, Any]:
    """The request's JSON object, at most MAX_BODY bytes (413 before reading more); 400 when it is not one."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > MAX_BODY:
        raise ApiError(413, f"the request has {int(declared)} bytes; at most {MAX_BODY} are allowed")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > MAX_BODY:
            raise ApiError(413, f"the request has more than {MAX_BODY} bytes; at most {MAX_BODY} are allowed")
        chunks.append(chunk)
    try:
        data = json.loads(b"".join(chunks) or b"null")
    except ValueError:
        raise ApiError(400, "the request body is not JSON") from None
    if not isinstance(data, dict):
        raise ApiError(400, "the request body must be a JSON object")
    return data


def _text(data: dict[str, Any], key: str, required: bool = True) -> str | None:
    value = data.get(key)
    if value is None and not required:
        return None
    if not isinstance(value, str):
        raise ApiError(400, f"{key!r} must be a string" + ("" if value is not None else " (it is missing)"))
    return value


def _one_line(e: Exception) -> str:
    from wonderverse.text import error_line

    return error_line(str(e))


def create_app(root: Path, token: str, port: int, config: Path | None = None, engine: str = "auto") -> "FastAPI":
    """The studio's app over the scenes of `root`; `port` names the token's cookie."""
    from fastapi import FastAPI, Request
    from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response, StreamingResponse
    from starlette.exceptions import HTTPException

    from flows import studio_scenes as scenes
    from flows.studio_jobs import Busy, EventHub, Jobs
    from flows.view import viewer_files

    root = Path(root).resolve()
    hub = EventHub()
    jobs = Jobs(root, hub)
    files = viewer_files()
    cache = Path(tempfile.mkdtemp(prefix="wonderverse-studio-"))
    cookie = cookie_name(port)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> Any:
        try:
            yield
        finally:
            jobs.kill_all()
            for f in cache.glob("*"):
                f.unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                cache.rmdir()

    app = FastAPI(lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)
    app.state.jobs, app.state.hub, app.state.root = jobs, hub, root

    @app.exception_handler(ApiError)
    async def api_error(request: Request, e: ApiError) -> JSONResponse:
        return JSONResponse({"error": e.message, **e.extra}, status_code=e.status)

    @app.exception_handler(HTTPException)
    async def http_error(request: Request, e: HTTPException) -> JSONResponse:
        message = {404: "not found", 405: "method not allowed"}.get(e.status_code, str(e.detail))
        return JSONResponse({"error": message}, status_code=e.status_code)

    @app.exception_handler(Exception)
    async def internal_error(request: Request, e: Exception) -> JSONResponse:
        """A bug, still answered in JSON (the page shows it); the traceback goes to the studio's stderr."""
        return JSONResponse({"error": f"internal error ({type(e).__name__}: {_one_line(e)})"}, status_code=500)

    @app.middleware("http")
    async def guard(request: Request, call_next: Any) -> Response:
        """/api needs the Bearer token; scene files the cookie, ?token= or the header; the page and the viewer's
        library files are public (they hold nothing of any scene)."""
        path = request.url.path
        if path.startswith("/api/") or path.startswith("/scenes/"):
            header = request.headers.get("authorization", "")
            given = header[len("Bearer ") :] if header.startswith("Bearer ") else ""
            if path.startswith("/scenes/") and not given:
                given = request.cookies.get(cookie) or request.query_params.get("token") or ""
            if not secrets.compare_digest(given.encode(), token.encode()):
                why = "a missing or wrong token" if given else "no token"
                message = f"forbidden ({why}): open the studio at the URL it printed when it started (with ?token=)"
                return JSONResponse({"error": message}, status_code=403)
        response = await call_next(request)
        response.headers["X-Content-Type-Options"] = "nosniff"
        response.headers["X-Frame-Options"] = "SAMEORIGIN"
        response.headers["Referrer-Policy"] = "no-referrer"  # the token in the page's URL goes nowhere
        response.headers.setdefault("Cache-Control", "no-store")
        return response

    # ------------------------------------------------------------------------------------------ the page

    @app.get("/")
    async def page(request: Request) -> Response:
        response = HTMLResponse((PAGE_DIR / PAGE_HTML).read_text(encoding="utf-8"))
        given = request.query_params.get("token", "")
        if given and secrets.compare_digest(given.encode(), token.encode()):
            response.set_cookie(cookie, token, httponly=True, samesite="strict", path="/")
        return response

    @app.get("/_studio/" + PAGE_JS)
    async def page_js() -> Response:
        return FileResponse(PAGE_DIR / PAGE_JS, media_type="text/javascript; charset=utf-8")

    @app.get("/_viewer/{name:path}")
    async def viewer_file(name: str) -> Response:
        if name not in files:
            raise ApiError(404, "not found")
        return Response(files[name], media_type="text/javascript; charset=utf-8")

    # ------------------------------------------------------------------------------------------ the API

    def checked(name: str, must_exist: bool = True) -> Path:
        try:
            return scenes.existing_scene(root, name) if must_exist else scenes.scene_dir(root, name)
        except scenes.NotFound as e:
            raise ApiError(404, str(e)) from None
        except WonderError as e:
            raise ApiError(400, _one_line(e)) from None

    def started(scene: str, kind: str, argv: list[str]) -> JSONResponse:
        try:
            job = jobs.start(scene, kind, argv)
        except Busy as e:
            raise ApiError(409, str(e), job=e.job.id) from None
        return JSONResponse({"job": job.id, "scene": scene}, status_code=202)

    def config_args() -> list[str]:
        return ["--config", str(config)] if config is not None else []

    @app.get("/api/scenes")
    async def list_scenes() -> dict[str, Any]:
        names = set(scenes.scene_names(root)) | {j.scene for j in jobs.jobs.values() if j.active}
        listed = []
        for name in sorted(names):
            job = jobs.active(name)
            listed.append({"name": name, "job": job.public() if job else None})
        return {"scenes": listed}

    @app.get("/api/scenes/{name}")
    async def get_scene(name: str) -> dict[str, Any]:
        job = jobs.active(name)
        try:
            info = await asyncio.to_thread(scenes.scene_info, root, name)
        except scenes.NotFound as e:
            if job is None:
                raise ApiError(404, str(e)) from None
            info = {"name": name, "segments": [], "files": [], "view_key": None, "gaussians": None}
        except WonderError as e:
            raise ApiError(400, _one_line(e)) from None
        last = [j for j in jobs.jobs.values() if j.scene == name]
        return {**info, "job": job.public() if job else None, "last_job": last[-1].public() if last else None}

    @app.post("/api/scenes")
    async def create_scene(request: Request) -> JSONResponse:
        data = await body_json(request)
        name, prompt = _text(data, "name"), _text(data, "prompt")
        preset = _text(data, "preset", required=False) or None
        seed = data.get("seed")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
            raise ApiError(400, "'seed' must be a whole number ≥ 0 (or left out)")
        folder = checked(name, must_exist=False)
        try:  # the CLI's own checks (prompt, preset, seed, the config file): the same one-line messages
            await asyncio.to_thread(_check_generate, prompt, preset, config, seed)
        except WonderError as e:
            raise ApiError(400, _one_line(e)) from None
        argv = ["generate", "--out", str(folder), "--engine", engine, *config_args()]
        argv += [*(["--preset", preset] if preset else []), *(["--seed", str(seed)] if seed is not None else [])]
        return started(name, "generate", [*argv, "--", prompt])

    @app.post("/api/scenes/{name}/extend")
    async def extend_scene(name: str, request: Request) -> JSONResponse:
        from flows.extend import checked_words

        data = await body_json(request)
        words = _text(data, "words")
        folder = checked(name)
        try:
            checked_words(words)
        except WonderError as e:
            raise ApiError(400, _one_line(e)) from None
        return started(name, "extend", ["extend", "--engine", engine, "--", str(folder), words])

    @app.post("/api/scenes/{name}/reconstruct")
    async def reconstruct_scene(name: str, request: Request) -> JSONResponse:
        data = await body_json(request)
        clips = data.get("clips")
        if isinstance(clips, str):
            clips = [c for c in clips.splitlines() if c.strip()]
        if not isinstance(clips, list) or not clips or not all(isinstance(c, str) for c in clips):
            raise ApiError(400, "'clips' must list at least one video file or image folder inside the studio's folder")
        preset = _text(data, "preset", required=False) or None
        folder = checked(name, must_exist=False)
        paths = [_clip_inside(root, c) for c in clips]
        argv = ["reconstruct", "--out", str(folder), "--engine", engine, *(["--preset", preset] if preset else [])]
        return started(name, "reconstruct", [*argv, "--", *paths])

    @app.get("/api/status")
    async def status() -> dict[str, Any]:
        """The studio's own state: its folder, open event streams, active jobs (a health check)."""
        active = [j.id for j in jobs.jobs.values() if j.active]
        return {"root": str(root), "streams": len(hub.queues), "active_jobs": active, "events": len(hub.events)}

    @app.get("/api/jobs")
    async def list_jobs() -> dict[str, Any]:
        return {"jobs": [j.public() for j in jobs.jobs.values()]}

    @app.get("/api/jobs/{job_id}")
    async def get_job(job_id: str) -> dict[str, Any]:
        job = jobs.jobs.get(job_id)
        if job is None:
            raise ApiError(404, f"no job {job_id[:40]!r}")
        return job.public()

    @app.get("/api/events")
    async def events(request: Request, since: int = 0) -> StreamingResponse:
        """Server-sent events: every job's state changes, progress and output lines, from id `since` on."""
        queue = hub.subscribe(since)

        async def stream() -> Any:
            try:
                yield "retry: 2000\n\n"
                while True:
                    try:
                        event = await asyncio.wait_for(queue.get(), KEEP_ALIVE_S)
                    except TimeoutError:
                        yield ": keep-alive\n\n"
                        continue
                    if event is None:  # too slow: closed, the page reconnects with `since`
                        return
                    yield f"id: {event['id']}\ndata: {json.dumps(event, separators=(',', ':'))}\n\n"
            finally:
                hub.unsubscribe(queue)

        return StreamingResponse(stream(), media_type="text/event-stream", headers={"X-Accel-Buffering": "no"})

    # ------------------------------------------------------------------------------------------ scene files

    @app.get("/scenes/{name}/view")
    async def view(name: str) -> Response:
        folder = checked(name)
        try:
            page = await asyncio.to_thread(scenes.view_page, folder, cache)
        except WonderError as e:
            return HTMLResponse(_placeholder(_one_line(e)), status_code=200)
        return HTMLResponse(page)

    @app.get("/scenes/{name}/" + scenes.LIVE_SPLATS)
    async def live(name: str) -> Response:
        folder = checked(name)
        try:
            path = await asyncio.to_thread(scenes.live_splats, folder, cache)
        except WonderError as e:
            raise ApiError(404, _one_line(e)) from None
        return FileResponse(path, media_type="application/octet-stream")

    @app.get("/scenes/{name}/files/{rel:path}")
    async def scene_file(name: str, rel: str) -> Response:
        folder = checked(name)
        found = scenes.scene_entry(folder, rel)
        if found is None:
            raise ApiError(404, f"no file {rel[:80]!r} in scene {name!r}")
        if found.is_dir():
            return StreamingResponse(
                _zip_chunks(found),
                media_type="application/zip",
                headers={"Content-Disposition": f'attachment; filename="{found.name}.zip"'},
            )
        from flows.view import CONTENT_TYPES

        ctype = CONTENT_TYPES.get(found.suffix.lower(), "application/octet-stream")
        return FileResponse(found, media_type=ctype)

    return app


def _check_generate(prompt: str, preset: str | None, config: Path | None, seed: int | None) -> None:
    """WonderError (the CLI's message) when `generate` would refuse these inputs before starting."""
    from wonderverse.config import build_config

    build_config(
        prompt=prompt,
        preset=preset,
        config_file=config,
        overrides={"scene": {"seed": seed}} if seed is not None else None,
    )


def _clip_inside(root: Path, clip: str) -> str:
    """The absolute path of a clip (a video file or an image folder) given relative to the studio's folder or
    absolute; ApiError 400 when it is missing or resolves outside the studio's folder (symlinks followed)."""
    if "\0" in clip or not clip.strip():
        raise ApiError(400, "a clip path is empty or holds a NUL character")
    path = Path(clip.strip())
    path = path if path.is_absolute() else root / path
    try:
        resolved = path.resolve(strict=True)
    except (OSError, RuntimeError):
        raise ApiError(400, f"{clip[:200]}: no such file or folder in the studio's folder") from None
    if not resolved.is_relative_to(root):
        raise ApiError(400, f"{clip[:200]}: not inside the studio's folder {root} (put clips there)")
    return str(resolved)


async def _zip_chunks(folder: Path) -> Any:
    """A zip of `folder` (files staying inside it), made in a temporary file and sent in chunks."""
    import zipfile

    from flows.studio_scenes import folder_files

    def build() -> Any:
        tmp = tempfile.TemporaryFile()  # noqa: SIM115 (read by the caller, which closes it)
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
            for path, arcname in folder_files(folder):
                z.write(path, arcname)
        tmp.seek(0)
        return tmp

    tmp = await asyncio.to_thread(build)
    try:
        while chunk := await asyncio.to_thread(tmp.read, 1 << 20):
            yield chunk
    finally:
        tmp.close()


def _placeholder(message: str) -> str:
    import html

    return (
        '<!doctype html><meta charset="utf-8"><body style="background:#111;color:#fc6;font:14px system-ui">'
        f'<p id="wv-status">{html.escape(message)}</p><script>window.wonderverse={{ready:false,'
        f"error:{json.dumps(message)},empty:true}}</script>"
    )


def listen(host: str, port: int) -> socket.socket:
    """A listening socket on host:port (port 0: a free one); WonderError, as `view` words it, when it cannot."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.bind((host, port))
        sock.listen(128)
    except OSError as e:
        sock.close()
        if e.errno == errno.EADDRINUSE:
            raise WonderError(f"port {port} on {host} is in use: choose another with --port, or leave it out") from None
        raise WonderError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    return sock


def serve_studio(
    root: Path, host: str = "127.0.0.1", port: int = 0, config: Path | None = None, engine: str = "auto"
) -> None:
    """Serve the studio over the scenes of `root` (made when absent) until the process is stopped; prints one line
    with the URL holding the launch token."""
    import uvicorn

    from flows.engine import check_engine
    from wonderverse.config import read_yaml

    check_engine(engine)
    if config is not None:
        read_yaml(config)  # a bad settings file is refused now, not at the first scene
        config = config.resolve()
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise WonderError(f"{root} is not a folder (the studio's scenes are its folders)")
    root.mkdir(parents=True, exist_ok=True)
    if host not in LOOPBACK:
        print(
            f"wonderverse: studio on {host}: other machines on that network can reach it (with its token)",
            file=sys.stderr,
        )
    sock = listen(host, port)
    bound_host, bound_port = sock.getsockname()[:2]
    token = secrets.token_urlsafe(24)
    app = create_app(root, token, bound_port, config, engine)
    shown = f"[{bound_host}]" if ":" in str(bound_host) else bound_host
    print(f"studio of {root} at http://{shown}:{bound_port}/?token={token} — Ctrl-C stops it and its jobs", flush=True)
    server = uvicorn.Server(
        uvicorn.Config(app, log_level="warning", timeout_graceful_shutdown=2, access_log=False, lifespan="on")
    )
    server.run(sockets=[sock])
