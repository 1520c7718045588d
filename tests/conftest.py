"""Shared fixtures: tiny configs that keep end-to-end runs fast on a 2-core machine."""

from __future__ import annotations

import contextlib
import hashlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

# Idle OpenMP threads sleep instead of spinning (set before torch loads): on a 2-core machine spinning
# threads made small splat renders 3-10x slower.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest

from wonderverse.config import RunConfig, build_config

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
TINY_VIDEO = {"width": 96, "height": 64, "frames_per_segment": 6}


def tiny_config(prompt: str = "a small house decorated for Christmas", **scene: Any) -> RunConfig:
    """Preview preset shrunk to 96x64, 6 frames per segment, no faults unless asked."""
    video = {**TINY_VIDEO, "options": {"fault_probability": 0.0}, **scene.pop("video", {})}
    return build_config(prompt, preset="preview", overrides={"scene": {"video": video, **scene}})


def run_cli(*args: str, env: dict[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run `wonderverse ARGS` in a fresh interpreter, as a user would."""
    full_env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", "flows.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=full_env,
        cwd=ROOT,
    )


def tree_digest(folder: Path) -> str:
    """One hash of every file's path and bytes under `folder` (to show a refused run changed nothing)."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(folder)).encode() + p.read_bytes())
    return h.hexdigest()


CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def launch_browser(playwright: Any) -> Any:
    """Headless Chromium from the system package; its absence fails the test unless explicitly allowed."""
    if not CHROMIUM.is_file():
        message = f"{CHROMIUM} is missing: install it with `bash scripts/install-browser.sh`"
        if os.environ.get("WONDERVERSE_ALLOW_NO_BROWSER") == "1":
            pytest.skip(message)
        pytest.fail(message + " (or set WONDERVERSE_ALLOW_NO_BROWSER=1 to skip)")
    return playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)


@pytest.fixture
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"shared data folder {DATA} is absent (tests with real footage need it)")
    return DATA


# Step settings for a whole scene in ~15-20 s (with TINY_VIDEO): one attempt per segment, short training, few
# rendered frames. Merged one level deep into the steps of a config.
SHORT_STEPS: dict[str, dict[str, Any]] = {
    "check": {"max_attempts": 1},
    "splats": {"max_side_px": 96, "train": {"iterations": 60, "holdout_every": 0}},
    "outputs": {"video_frames": 4, "quality_frames": 1},
}


def complete_config() -> RunConfig:
    """tiny_config with SHORT_STEPS: a whole scene, every step, in ~15-20 s."""
    cfg = tiny_config()
    dumped = cfg.steps.model_dump()
    steps = cfg.steps.model_validate(dumped | {k: dumped[k] | v for k, v in SHORT_STEPS.items()})
    return cfg.model_copy(update={"steps": steps})


_LOCK_HOLDER = """
import sys
from wonderverse.store import scene_lock
with scene_lock(sys.argv[1]):
    print("locked", flush=True)
    sys.stdin.readline()
"""


@contextlib.contextmanager
def lock_held_elsewhere(scene: Path) -> Iterator[subprocess.Popen]:
    """A separate process holding the scene's lock until its stdin closes or the block ends (then killed)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _LOCK_HOLDER, str(scene)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "locked", "holder did not take the lock"
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
