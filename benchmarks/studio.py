"""How live is `wonderverse studio`? One studio, one scene, headless Chromium driving the page as a person would.

- Extend to drawn: a scene made in the studio (preview preset: its initial segment and one extension each side, 3
  segments; `--quick`: the tests' tiny settings, 1 segment), then the page's "extend" pressed with words; the time
  until the view shows the new splats (the iframe reloaded with the new splats' key and drawn 3 frames) and until
  the job is done (the outputs step and the report after the splats).
- Frame rate: the 3D view of that (largest) scene in headless Chromium, software WebGL (SwiftShader, no GPU), while
  the mouse orbits (the view draws every animation frame then) and while idle (the studio's view then draws a frame
  every 2 s); the view's canvas size is stated.
- Memory: the resident memory of the idle studio (the server process and its supervisor) before any scene is opened,
  and after the 3D view was served (the live splats read the store: torch is loaded then).

Command: `python -m benchmarks.studio [--quick]`. Needs Chromium (`bash scripts/install-browser.sh`) and Playwright.
Last-line keys: `extend_to_drawn_s`, `extend_job_s`, `generate_s`, `segments_before`, `segments_after`,
`gaussians_before`, `gaussians_after`, `fps_orbit`, `fps_idle`, `canvas` ("WxH"), `idle_rss_mb`,
`rss_after_view_mb`, `preset`.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import psutil
import yaml

from benchmarks.common import parse_args, report

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking"]
READY = "window.wonderverse && (window.wonderverse.ready || window.wonderverse.error)"
PROMPT = "a small house decorated for Christmas"
QUICK = {  # tests/test_studio.py's tiny scene
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
FULL = {"preset": "preview", "scene": {"video": {"options": {"fault_probability": 0.0}}}}


def _rss_mb(pid: int) -> float:
    """Resident memory of the studio: its supervisor and the server (not the jobs: none runs when measured)."""
    p = psutil.Process(pid)
    procs = [p, *(c for c in p.children() if "studio" in c.cmdline())]
    return sum(q.memory_info().rss for q in procs) / 1e6


def _view(page: Any, loads: int) -> Any:
    """The 3D view's frame once the page's `loads`-th view has drawn."""
    waited = time.monotonic()
    while True:
        try:
            page.wait_for_function(f"window.studio.viewLoads >= {loads}", timeout=20_000)
            break
        except Exception:
            state = page.evaluate("JSON.stringify({...window.studio, lastEvent: window.studio.lastEvent})")
            print(f"waiting for view {loads} ({time.monotonic() - waited:.0f} s): {state[:600]}", file=sys.stderr)
            if time.monotonic() - waited > 900:
                raise
    key = page.evaluate("window.studio.viewKey")
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        frame = next((f for f in page.frames if f.url.endswith(f"key={key}")), None)
        if frame is not None:
            try:
                frame.wait_for_function(READY, timeout=20_000)
            except Exception as e:  # still loading, or reloaded meanwhile
                print(f"view {key}: {type(e).__name__}: {str(e)[:200]}", file=sys.stderr)
                continue
            error = frame.evaluate("window.wonderverse.error")
            if error:
                raise RuntimeError(f"the view failed: {error}")
            return frame
        if int(time.monotonic() * 20) % 100 == 0:
            state = page.evaluate("[window.studio.viewKey, window.studio.viewLoads, window.studio.error]")
            print(f"view {key}: frames {[f.url for f in page.frames]}, page {state}", file=sys.stderr)
        time.sleep(0.05)
    raise RuntimeError(f"the view never drew; frames: {[f.url for f in page.frames]}")


def _fps(page: Any, frame: Any, orbit: bool, seconds: float = 5.0) -> float:
    """Frames the view drew per second over `seconds`, the mouse orbiting (drags across the canvas) or not."""
    box = page.locator("#view").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    frame.evaluate("0")  # settle
    n0, t0 = frame.evaluate("window.wonderverse.frames"), time.monotonic()
    if orbit:
        page.mouse.move(x, y)
        page.mouse.down()
        step = 0
        while time.monotonic() - t0 < seconds:
            step += 1
            page.mouse.move(x + 60 * ((step % 20) / 10 - 1), y, steps=2)
        page.mouse.up()
    else:
        time.sleep(seconds)
    return (frame.evaluate("window.wonderverse.frames") - n0) / (time.monotonic() - t0)


def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    from playwright.sync_api import sync_playwright

    settings = QUICK if args.quick else FULL
    with tempfile.TemporaryDirectory(prefix="studio-bench-") as tmp:
        config = Path(tmp) / "settings.yaml"
        config.write_text(yaml.safe_dump(settings))
        proc = subprocess.Popen(
            [sys.executable, "-m", "flows", "studio", str(Path(tmp) / "scenes"), "--config", str(config)],
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        try:
            url = proc.stdout.readline().split(" at ", 1)[1].split()[0]
            base, token = url.split("/?token=")
            time.sleep(3.0)
            idle_rss = _rss_mb(proc.pid)
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
                page = browser.new_page(viewport={"width": 1280, "height": 900})
                page.goto(url)
                page.wait_for_function("window.studio.connected")
                page.fill("#new-name", "bench")
                page.fill("#new-prompt", PROMPT)
                t0 = time.monotonic()
                page.click("#create")
                page.wait_for_function("window.studio.job && window.studio.job.kind === 'generate'")
                page.wait_for_function("window.studio.job.state === 'done'", timeout=1_800_000)
                generate_s = time.monotonic() - t0
                print(f"generated in {generate_s:.1f} s", file=sys.stderr, flush=True)
                _view(page, 1)
                auth = {"Authorization": f"Bearer {token}"}
                before = httpx.get(f"{base}/api/scenes/bench", headers=auth, timeout=60).json()
                assert before["job"] is None and before["last_job"]["state"] == "done", before["last_job"]
                loads = page.evaluate("window.studio.viewLoads")
                page.fill("#words", "a red barn straight ahead")
                t0 = time.monotonic()
                page.click("#extend")
                page.wait_for_function(
                    "window.studio.error || (window.studio.job && window.studio.job.kind === 'extend')"
                )
                if page.evaluate("window.studio.error"):
                    raise RuntimeError(f"extend refused: {page.evaluate('window.studio.error')}")
                print(f"extend started; view loads {loads}", file=sys.stderr, flush=True)
                frame = _view(page, loads + 1)
                drawn_s = time.monotonic() - t0
                page.wait_for_function(
                    "window.studio.job && window.studio.job.kind === 'extend' && window.studio.job.state === 'done'",
                    timeout=1_800_000,
                )
                job_s = time.monotonic() - t0
                after = httpx.get(f"{base}/api/scenes/bench", headers=auth, timeout=60).json()
                frame = _view(page, page.evaluate("window.studio.viewLoads"))
                time.sleep(2.5)  # idle from here on
                fps_idle = _fps(page, frame, orbit=False, seconds=10.0)
                fps_orbit = _fps(page, frame, orbit=True)
                size = frame.evaluate(
                    "[document.getElementById('wv-canvas').width, document.getElementById('wv-canvas').height]"
                )
                browser.close()
            time.sleep(2.0)
            view_rss = _rss_mb(proc.pid)
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=30)
    rows = [
        {"measure": "generate (page: create → job done)", "value": round(generate_s, 1), "unit": "s"},
        {"measure": "extend → new splats drawn", "value": round(drawn_s, 1), "unit": "s"},
        {"measure": "extend → job done", "value": round(job_s, 1), "unit": "s"},
        {
            "measure": "segments before → after",
            "value": f"{len(before['segments'])} → {len(after['segments'])}",
            "unit": "",
        },
        {"measure": "Gaussians before → after", "value": f"{before['gaussians']} → {after['gaussians']}", "unit": ""},
        {"measure": f"frame rate, orbiting ({size[0]}×{size[1]} canvas)", "value": round(fps_orbit, 1), "unit": "fps"},
        {"measure": "frame rate, idle", "value": round(fps_idle, 1), "unit": "fps"},
        {"measure": "idle studio, fresh", "value": round(idle_rss), "unit": "MB RSS"},
        {"measure": "idle studio, after the 3D view", "value": round(view_rss), "unit": "MB RSS"},
    ]
    headline = {
        "extend_to_drawn_s": round(drawn_s, 2),
        "extend_job_s": round(job_s, 2),
        "generate_s": round(generate_s, 2),
        "segments_before": len(before["segments"]),
        "segments_after": len(after["segments"]),
        "gaussians_before": before["gaussians"],
        "gaussians_after": after["gaussians"],
        "fps_orbit": round(fps_orbit, 2),
        "fps_idle": round(fps_idle, 2),
        "canvas": f"{size[0]}x{size[1]}",
        "idle_rss_mb": round(idle_rss, 1),
        "rss_after_view_mb": round(view_rss, 1),
        "preset": "preview (tiny)" if args.quick else "preview",
    }
    report("wonderverse studio", rows, headline)


if __name__ == "__main__":
    main()
