"""`wonderverse studio`: one studio over one folder, one tiny scene, driven as a person would in headless Chromium
(create, watch progress, see it in 3D, extend, download, errors) and through its JSON API as an attacker or a
careless client would (no token, bad names, huge bodies, 100 extends at once, a stream cut mid-way, a job killed
by the OS, Ctrl-C with a job running).

Ground truth: HTTP codes and JSON bodies, the CLI's own error lines (run for the same input), the canvas's pixels,
the scene's store (`inspect --json` through the API, and read directly), the downloaded file parsed with plyfile,
and the OS (which processes are alive).
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import psutil
import pytest
import yaml
from conftest import ROOT, launch_browser, run_cli

from flows.studio_scenes import check_name, scene_entry
from wonderverse.errors import WonderError

READY = "window.wonderverse && (window.wonderverse.ready || window.wonderverse.error || window.wonderverse.empty)"
CANVAS_PNG = "document.getElementById('wv-canvas').toDataURL('image/png')"
SCENE = "winter-house"
PROMPT = "a small house decorated for Christmas"
# The smallest scene the suite makes (tests/conftest.py tiny_config with SHORT_STEPS): one 6-frame 96x64 segment,
# 60 splat iterations; no Dask workers (segment_workers 1), no COLMAP or nerfstudio exports; the global SfM on one
# thread, so every run poses the extension's frames alike (and seeds Gaussians from them alike).
TINY = {
    "preset": "preview",
    "scene": {
        "video": {"width": 96, "height": 64, "frames_per_segment": 6, "options": {"fault_probability": 0.0}},
        "extensions": {"rounds": 0},
    },
    "steps": {
        "check": {"max_attempts": 1},
        "poses": {"sfm": {"num_threads": 1}},  # COLMAP's mapper on one thread repeats itself (test_kill_nine)
        "splats": {"max_side_px": 96, "train": {"iterations": 60, "holdout_every": 0}},
        "outputs": {"video_frames": 4, "quality_frames": 1, "colmap": False, "nerfstudio": False},
    },
    "execution": {"segment_workers": 1},
}


# ------------------------------------------------------------------------------------------- without a server


def test_a_scene_name_is_one_folder_name_inside_the_root(tmp_path: Path):
    for good in ("winter-house", "Scène 2", "a.b"):
        assert check_name(good) == good
    for bad in ("", "..", ".", "../x", "a/b", "a\\b", ".hidden", " x", "x ", "．．", "x\x1b[2J", "a" * 256, "a/../b"):
        with pytest.raises(WonderError):
            check_name(bad)


def test_scene_files_stay_inside_the_scene(tmp_path: Path):
    scene = tmp_path / "s"
    (scene / "colmap").mkdir(parents=True)
    (scene / "colmap" / "a.txt").write_text("a")
    (tmp_path / "secret.txt").write_text("secret")
    (scene / "out").symlink_to(tmp_path / "secret.txt")
    assert scene_entry(scene, "colmap") == (scene / "colmap").resolve()
    assert scene_entry(scene, "colmap/a.txt") == (scene / "colmap" / "a.txt").resolve()
    for bad in ("../secret.txt", "%2e%2e/secret.txt", "out", ".lock", "colmap/..", "a\\..\\b", "x%00", "", "C:/x"):
        assert scene_entry(scene, bad) is None, bad


def test_the_json_reporter_writes_the_terminals_units_as_json_lines(monkeypatch, capsys):
    """PROGRESS_ENV=json: make_reporter gives JSON lines (one per event, progress at most every JSON_EVERY_S per
    unit plus each unit's first and last report) with the line the terminal would show."""
    from rich.console import Console

    from flows.progress import JSON_PREFIX, PROGRESS_ENV, JsonReporter, make_reporter
    from tasks.base import StepResult

    monkeypatch.setenv(PROGRESS_ENV, "json")
    reporter = make_reporter(Console(stderr=True), 7)
    assert isinstance(reporter, JsonReporter)
    reporter.started("splats", "3D Gaussian splatting")
    for i in range(0, 101):
        reporter.advance(i, 100, "iterations", f"loss {1 / (i + 1):.4f}")
    reporter.finished(StepResult(step="splats", status="ran", seconds=1.5, cache_key="k", detail="9 Gaussians"))
    lines = capsys.readouterr().err.splitlines()
    assert all(line.startswith(JSON_PREFIX) for line in lines)
    events = [json.loads(line[len(JSON_PREFIX) :]) for line in lines]
    assert events[0] == {
        "event": "started",
        "step": "splats",
        "description": "3D Gaussian splatting",
        "index": 1,
        "total": 7,
    }
    progress = [e for e in events if e["event"] == "progress"]
    assert progress[0]["done"] == 0 and progress[-1]["done"] == 100 and len(progress) < 10  # throttled
    assert progress[-1]["line"] == "iterations 100/100 (100 %), loss 0.0099"
    assert events[-1] == {
        "event": "finished",
        "step": "splats",
        "status": "ran",
        "seconds": 1.5,
        "detail": "9 Gaussians",
    }


# ------------------------------------------------------------------------------------------- one studio


@dataclass
class Studio:
    proc: subprocess.Popen
    base: str
    token: str
    root: Path
    lines: list[str]

    def api(self, method: str, path: str, token: str | None = "", headers: dict | None = None, **kw) -> httpx.Response:
        auth = {} if token is None else {"Authorization": f"Bearer {token or self.token}"}
        return httpx.request(method, self.base + path, headers={**auth, **(headers or {})}, timeout=30, **kw)

    def wait_job(self, job: str, timeout_s: float = 150) -> dict:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            state = self.api("GET", f"/api/jobs/{job}").json()
            if state["state"] in ("done", "failed"):
                return state
            time.sleep(0.3)
        raise AssertionError(f"job {job} still {state} after {timeout_s} s")


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Studio]:
    """`wonderverse studio ROOT --config tiny.yaml` as a user runs it (supervised), on a free port."""
    folder = tmp_path_factory.mktemp("studio")
    config = folder / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY))
    root = folder / "scenes"
    proc = subprocess.Popen(
        [sys.executable, "-m", "flows", "studio", str(root), "--config", str(config), "--engine", "local"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    line = proc.stdout.readline()
    assert line.startswith("studio of "), (line, proc.stderr.read() if proc.poll() is not None else "")
    url = line.split(" at ", 1)[1].split()[0]
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True).start()
    base, token = url.split("/?token=")
    try:
        yield Studio(proc, base, token, root, lines)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)


def _playwright():
    from playwright.sync_api import sync_playwright

    return sync_playwright()


def _canvas(frame) -> np.ndarray:
    from PIL import Image

    data = frame.evaluate(CANVAS_PNG)
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(data.split(",", 1)[1]))).convert("RGB"))


def _view_frame(page, loads: int):
    """The 3D view's frame once its `loads`-th page has drawn a few frames."""
    page.wait_for_function(f"window.studio.viewLoads >= {loads}", timeout=60_000)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        frame = next((f for f in page.frames if "/view?key=" in f.url), None)
        if frame is not None and frame.url.endswith(page.evaluate("window.studio.viewKey")):
            try:
                frame.wait_for_function(READY, timeout=60_000)
            except Exception:  # reloaded meanwhile: the next one
                continue
            state = frame.evaluate("({ready: window.wonderverse.ready, error: window.wonderverse.error})")
            assert state == {"ready": True, "error": None}, state
            return frame
        time.sleep(0.2)
    raise AssertionError("the 3D view never drew")


@pytest.mark.e2e
def test_without_the_token_nothing_is_read_or_started(studio: Studio):
    r = studio.api("GET", "/api/scenes", token=None)
    assert r.status_code == 403 and "token" in r.json()["error"]
    assert "access-control-allow-origin" not in r.headers  # no CORS: another origin's page reads nothing
    for method, path, body in [
        ("GET", "/api/scenes", None),
        ("GET", "/api/events", None),
        ("GET", "/api/jobs/x", None),
        ("POST", "/api/scenes", {"name": "x", "prompt": "a house"}),
        ("POST", "/api/scenes/x/extend", {"words": "left"}),
    ]:
        for token in (None, "wrong", studio.token[:-1]):
            r = studio.api(method, path, token=token, json=body)
            assert r.status_code == 403, (method, path, token, r.text)
    assert studio.api("GET", "/api/scenes", token=None, params={"token": studio.token}).status_code == 403
    assert httpx.get(f"{studio.base}/scenes/x/files/splats.ply").status_code == 403
    # a preflight from another origin gets no CORS approval either
    r = httpx.options(
        f"{studio.base}/api/scenes",
        headers={"Origin": "http://evil.example", "Access-Control-Request-Method": "POST"},
    )
    assert "access-control-allow-origin" not in r.headers
    assert not any(studio.root.iterdir()), "nothing was started"


@pytest.mark.e2e
def test_bad_requests_are_one_json_error_with_a_4xx(studio: Studio, tmp_path: Path):
    cli = run_cli("generate", "", "--out", str(tmp_path / "cli"), "--config", str(studio.root.parent / "tiny.yaml"))
    assert cli.returncode == 2
    r = studio.api("POST", "/api/scenes", json={"name": "e", "prompt": ""})
    assert r.status_code == 400 and "error: " + r.json()["error"] == cli.stderr.strip()  # the CLI's own line
    r = studio.api("POST", "/api/scenes", json={"name": "e", "prompt": "a house", "preset": "nope"})
    assert r.status_code == 400 and r.json()["error"].startswith("unknown preset 'nope'")
    for name in ("../x", "..", "a/b", ".x"):
        r = studio.api("POST", "/api/scenes", json={"name": name, "prompt": "a house"})
        assert r.status_code == 400 and "scene name" in r.json()["error"], (name, r.text)
    for path in ("/api/scenes/..%2Fx", "/api/scenes/%2E%2E", "/api/scenes/nosuch", "/api/jobs/nosuch"):
        r = studio.api("GET", path)
        assert r.status_code in (400, 404) and r.json()["error"], (path, r.text)
    r = studio.api("POST", "/api/scenes/nosuch/extend", json={"words": "left"})
    assert r.status_code == 404 and "no scene 'nosuch'" in r.json()["error"]
    huge = json.dumps({"name": "big", "prompt": "x" * 10_000_000})
    r = studio.api("POST", "/api/scenes", content=huge, headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and "bytes" in r.json()["error"]
    for body in (b"not json", b"[1]", b'{"name": 3, "prompt": "x"}'):
        r = studio.api("POST", "/api/scenes", content=body)
        assert r.status_code == 400 and r.json()["error"], body
    r = studio.api("POST", "/api/scenes/rec/reconstruct", json={"clips": ["/etc"]})
    assert r.status_code == 400 and "not inside the studio's folder" in r.json()["error"]
    assert studio.api("GET", "/api/status").json()["active_jobs"] == []
    assert not any(studio.root.iterdir()), "no request made a folder"


@pytest.mark.e2e
def test_create_watch_view_extend_and_download_in_the_browser(studio: Studio, tmp_path: Path):
    """The page creates the scene, shows progress as it comes and the splats in 3D, refuses an empty prompt with
    the CLI's words, extends the scene in words (segments and Gaussians change, the view reloads) and downloads
    splats.ply."""
    from plyfile import PlyData

    log: list[str] = []
    with _playwright() as pw:
        browser = launch_browser(pw)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 900}, accept_downloads=True)
            page.on("pageerror", lambda e: log.append(f"page error: {e}"))
            page.goto(f"{studio.base}/?token={studio.token}")
            assert "token" not in page.url  # taken out of the address bar
            page.wait_for_function("window.studio.connected", timeout=20_000)
            page.fill("#new-name", SCENE)
            page.fill("#new-prompt", PROMPT)
            page.click("#create")
            page.wait_for_function("window.studio.job && window.studio.job.state === 'running'", timeout=30_000)
            # progress arrives while the job runs, in the terminal's units
            page.wait_for_function("window.studio.progress >= 3", timeout=60_000)
            assert page.evaluate("window.studio.job.state") == "running"
            # an empty prompt: refused in the page with the CLI's line, while the job goes on
            page.fill("#new-name", "empty")
            page.fill("#new-prompt", "   ")
            page.click("#create")
            page.wait_for_function("window.studio.error.length > 0", timeout=10_000)
            assert "prompt is empty" in page.inner_text("#error")
            page.wait_for_function("window.studio.job && window.studio.job.state === 'done'", timeout=150_000)
            units = {e["unit"] for e in _progress_events(studio) if e.get("event") == "progress"}
            assert {"segments rendered", "iterations"} <= units, units
            frame = _view_frame(page, 1)
            first = _canvas(frame)
            page.wait_for_function("document.getElementById('segments-count').textContent !== '-'")
            segments, gaussians = _counts(page)
            assert segments == 1 and gaussians > 0
            assert (first.std(axis=(0, 1)) > 3).any(), "the 3D view is blank"
            background = first[0, 0].astype(int)
            assert (np.abs(first.astype(int) - background).max(axis=2) > 10).mean() > 0.05, "only the background"

            loads = page.evaluate("window.studio.viewLoads")
            page.fill("#words", "a red barn straight ahead")
            page.click("#extend")
            page.wait_for_function("window.studio.job && window.studio.job.kind === 'extend'", timeout=20_000)
            page.wait_for_function("window.studio.job.state === 'done'", timeout=150_000)
            page.wait_for_function(f"Number(document.getElementById('segments-count').textContent) === {segments + 1}")
            second = _canvas(_view_frame(page, loads + 1))
            assert second.shape == first.shape and (second.std(axis=(0, 1)) > 3).any()
            new_segments, new_gaussians = _counts(page)
            print(f"segments {segments} -> {new_segments}, Gaussians {gaussians} -> {new_gaussians}")
            assert new_segments == segments + 1 and new_gaussians != gaussians
            row = page.inner_text("#segments tr:last-child")
            assert "a red barn straight ahead" in row and any(v in row for v in ("ok", "rejected", "-"))

            with page.expect_download() as download:
                page.click("#files a:text-is('splats.ply')")
            saved = tmp_path / "splats.ply"
            download.value.save_as(saved)
        finally:
            browser.close()
    vertex = PlyData.read(str(saved))["vertex"]
    assert 0 < vertex.count <= new_gaussians and {"x", "f_dc_0", "opacity", "rot_0"} <= set(vertex.data.dtype.names)
    assert log == []


def _counts(page) -> tuple[int, int]:
    return int(page.inner_text("#segments-count")), int(page.inner_text("#gaussians-count"))


def _progress_events(studio: Studio) -> list[dict]:
    """Every event so far, read from the stream (replayed from id 0) until a keep-alive would come."""
    events = []
    with httpx.stream(
        "GET", f"{studio.base}/api/events", headers={"Authorization": f"Bearer {studio.token}"}, timeout=5
    ) as r:
        last = studio.api("GET", "/api/status").json()["events"]
        for line in r.iter_lines():
            if line.startswith("data: "):
                events.append(json.loads(line[6:]))
                if events[-1]["id"] >= last:
                    break
    return [e for e in events if e["type"] == "progress"]


@pytest.mark.e2e
def test_a_stream_cut_mid_way_and_100_extends_at_once_leave_the_studio_serving(studio: Studio):
    """A client that drops its event stream is forgotten; of 100 extends at once one runs and 99 get 409 with its
    id; that job killed by the OS fails with the CLI's line, and the scene keeps every segment it had."""
    before = studio.api("GET", f"/api/scenes/{SCENE}").json()
    with httpx.stream("GET", f"{studio.base}/api/events", headers={"Authorization": f"Bearer {studio.token}"}) as r:
        next(r.iter_lines())
        assert studio.api("GET", "/api/status").json()["streams"] >= 1
    results: list[httpx.Response] = []
    barrier = threading.Barrier(100)

    def extend() -> None:
        barrier.wait()
        results.append(studio.api("POST", f"/api/scenes/{SCENE}/extend", json={"words": "a pine forest ahead"}))

    threads = [threading.Thread(target=extend) for _ in range(100)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    codes = sorted(r.status_code for r in results)
    assert codes == [202] + [409] * 99, codes
    job = next(r.json()["job"] for r in results if r.status_code == 202)
    assert all(r.json()["job"] == job and "busy" in r.json()["error"] for r in results if r.status_code == 409)
    # the OS kills the run (the supervised child's own child) mid-way
    deadline = time.monotonic() + 30
    while len(runs := _extend_processes(studio)) < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1.0)
    run = next(p for p in runs if p.ppid() in {q.pid for q in runs})  # the supervisor's child: the run itself
    run.send_signal(signal.SIGKILL)
    state = studio.wait_job(job, 60)
    assert state["state"] == "failed" and state["error"].startswith("the run was killed by signal 9"), state
    assert studio.api("GET", "/api/status").json()["streams"] == 0
    after = studio.api("GET", f"/api/scenes/{SCENE}").json()
    assert {s["id"] for s in before["segments"]} <= {s["id"] for s in after["segments"] if s["complete"]}
    assert after["gaussians"] == before["gaussians"] and after["damaged"] == []
    assert httpx.get(f"{studio.base}/scenes/{SCENE}/files/splats.ply", params={"token": studio.token}).is_success
    report = httpx.get(f"{studio.base}/scenes/{SCENE}/files/report.html", params={"token": studio.token})
    assert (
        report.status_code == 200 and report.headers["content-type"].startswith("text/html") and PROMPT in report.text
    )
    assert "report.html" in after["files"]


def _extend_processes(studio: Studio) -> list[psutil.Process]:
    """The running job's processes: its supervisor (the studio's child) and the run (the supervisor's child)."""
    found = []
    for p in psutil.Process(studio.proc.pid).children(recursive=True):
        with contextlib.suppress(psutil.Error):
            if "extend" in p.cmdline():
                found.append(p)
    return found


@pytest.mark.e2e
def test_ctrl_c_stops_the_studio_and_its_running_job(studio: Studio):
    r = studio.api("POST", f"/api/scenes/{SCENE}/extend", json={"words": "a pine forest ahead"})
    assert r.status_code == 202, r.text
    deadline = time.monotonic() + 30
    while len(_extend_processes(studio)) < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(0.5)  # the run has started its reaper
    tree = psutil.Process(studio.proc.pid).children(recursive=True)
    assert len(_extend_processes(studio)) >= 2, "the job's supervisor and its run"
    studio.proc.send_signal(signal.SIGINT)
    assert studio.proc.wait(timeout=20) == 130
    time.sleep(0.5)
    alive = [p for p in tree if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert alive == [], alive
    with pytest.raises(httpx.TransportError):
        httpx.get(f"{studio.base}/", timeout=2)
