"""Shared fixtures: tiny configs that keep end-to-end runs fast on a 2-core machine."""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import re
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

# Idle OpenMP threads sleep instead of spinning (set before torch loads): on a 2-core machine spinning
# threads made small splat renders 3-10x slower.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import psutil
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
        [sys.executable, "-m", "flows", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=full_env,
        cwd=ROOT,
    )


def command_of(process: psutil.Process) -> str:
    """The process's command line, or "" once it has ended (a process listed a moment ago may be gone)."""
    try:
        return " ".join(process.cmdline())
    except psutil.Error:
        return ""


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
    refuse_unless_e2e("a browser (launch_browser)")
    if not CHROMIUM.is_file():
        message = f"{CHROMIUM} is missing: install it with `bash scripts/install-browser.sh`"
        if os.environ.get("WONDERVERSE_ALLOW_NO_BROWSER") == "1":
            pytest.skip(message)
        pytest.fail(message + " (or set WONDERVERSE_ALLOW_NO_BROWSER=1 to skip)")
    return playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared folder of real footage and model files (../shared/data next to the repository); tests that need it
    are skipped, saying why, where it is absent."""
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


# --- Two tiers ---------------------------------------------------------------------------------------------------
# `pytest -m "not e2e"` is the fast tier. A test that runs a pipeline, the CLI, a server or a browser belongs to the
# e2e tier and says so (@pytest.mark.e2e, or `pytestmark = pytest.mark.e2e` for a module). While a test without the
# marker runs, its fixtures included (a module-scoped fixture that builds a scene is set up inside the first test
# that uses it), those entry points fail it, so the fast tier cannot grow slow unnoticed. E2e tests run untouched.
# SfM over a whole real or rendered clip (tens of seconds each) is marked e2e too, by hand: no entry point shows it.

E2E = "e2e"

# Command lines of the CLI, a benchmark, or a server (Prefect's API runs under uvicorn, ephemeral or `prefect server`).
_E2E_COMMAND = re.compile(
    r"(^|[\s/])wonderverse(\s|$)|-m\s+flows(\s|$)|\bflows\.(cli|serve|view)\b|-m\s+benchmarks\.|\buvicorn\b"
    r"|\bprefect\s+server\b"
)

_unmarked_test: str | None = None  # node id of the test running now when it lacks the e2e marker


def refuse_unless_e2e(what: str) -> None:
    """Fail the running test when it is not marked e2e (a no-op in e2e tests and outside tests)."""
    if _unmarked_test is not None:
        pytest.fail(
            f"{_unmarked_test} runs {what} but is not marked e2e: "
            f"add @pytest.mark.{E2E} (or `pytestmark = pytest.mark.{E2E}` for the whole module)"
        )


def _command_line(args: Any) -> str:
    if isinstance(args, (str, bytes, os.PathLike)):
        return os.fsdecode(args)
    return " ".join(os.fsdecode(a) for a in args)


def _guards() -> list[tuple[Any, str, str]]:
    """(owner, attribute, what it runs) of every entry point an unmarked test may not call (besides commands, see
    `_guarded_popen_init`, and `launch_browser`, which checks itself: tests import it by name). The modules load once
    per process; those a test file did not import cost ~0.3 s then."""
    import click.testing
    import typer.main
    import typer.testing

    import flows.pipeline
    import flows.serve
    import flows.view
    import tasks
    import tasks.parallel
    from tasks.base import Step

    found = [
        (flows.pipeline, "_execute", "a pipeline (flows.pipeline)"),
        (Step, "run_in", "a pipeline step (Step.run_in)"),
        (click.testing.CliRunner, "invoke", "the CLI (CliRunner)"),
        (typer.testing.CliRunner, "invoke", "the CLI (CliRunner)"),  # its own invoke, not click's
        (typer.main.Typer, "__call__", "the CLI (the typer app)"),
        (flows.serve, "serve", "a server (flows.serve.serve)"),
        (flows.serve, "run_batch", "a batch of scenes (flows.serve.run_batch)"),
        (flows.view, "make_server", "a server (flows.view.make_server)"),
        (flows.view, "serve_scene", "a server (flows.view.serve_scene)"),
        (tasks.parallel, "_open_client", "a Dask cluster (tasks.parallel)"),
    ]
    for step in tasks.STEPS:  # each step's `run`, which a test may call on a store directly
        module = sys.modules.get(step.run.__module__)
        if module is not None and getattr(module, step.run.__name__, None) is step.run:
            found.append((module, step.run.__name__, f"the {step.name} step ({module.__name__}.{step.run.__name__})"))
    # Names a refactor removed are simply not guarded; a class's own attribute only (restoring puts back exactly that).
    return [g for g in found if (g[1] in vars(g[0]) if isinstance(g[0], type) else hasattr(g[0], g[1]))]


def _guarded(original: Callable[..., Any], what: str) -> Callable[..., Any]:
    @functools.wraps(original)
    def guarded(*args: Any, **kwargs: Any) -> Any:
        refuse_unless_e2e(what)
        return original(*args, **kwargs)

    return guarded


def _guarded_popen_init(original: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(original)
    def init(self: subprocess.Popen, args: Any, *rest: Any, **kwargs: Any) -> None:
        line = _command_line(args)
        if _E2E_COMMAND.search(line):
            refuse_unless_e2e(f"the command `{line[:200]}`")
        original(self, args, *rest, **kwargs)

    return init


@contextlib.contextmanager
def _entry_points_refused(nodeid: str) -> Iterator[None]:
    """Every guarded entry point wrapped (and the steps' `run` fields, which a frozen dataclass holds) while `nodeid`
    runs; all restored afterwards."""
    global _unmarked_test
    import tasks

    patched: list[tuple[Any, str, Any]] = []
    step_runs = [(step, step.run) for step in tasks.STEPS]
    try:
        for owner, name, what in _guards():
            original = vars(owner)[name] if isinstance(owner, type) else getattr(owner, name)
            patched.append((owner, name, original))
            setattr(owner, name, _guarded(original, what))
        popen_init = vars(subprocess.Popen)["__init__"]
        patched.append((subprocess.Popen, "__init__", popen_init))
        subprocess.Popen.__init__ = _guarded_popen_init(popen_init)  # type: ignore[method-assign]
        for step, run in step_runs:
            object.__setattr__(step, "run", _guarded(run, f"the {step.name} step"))
        _unmarked_test = nodeid
        yield
    finally:
        _unmarked_test = None
        for step, run in step_runs:
            object.__setattr__(step, "run", run)
        for owner, name, original in reversed(patched):
            setattr(owner, name, original)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Any:
    if item.get_closest_marker(E2E) is not None:
        return (yield)
    with _entry_points_refused(item.nodeid):
        return (yield)


# --- Order -------------------------------------------------------------------------------------------------------
# With `-n 2 --dist loadfile` each file goes whole to the next free worker in collection order, so a long file
# collected late runs alone at the end while the other worker idles. The longest files (by `--durations`) go first,
# then the other e2e files, then the fast tier, which fills in the gaps at the end.
LONGEST_FIRST = ("test_quickstart", "test_adversarial", "test_kill_nine", "test_reconstruct_cli", "test_run_control")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> tuple[int, int]:
        module = item.path.stem
        if module in LONGEST_FIRST:
            return (0, LONGEST_FIRST.index(module))
        return (1, 0) if item.get_closest_marker(E2E) is not None else (2, 0)

    firsts: dict[Path, tuple[int, int]] = {}
    for item in items:  # a file's rank is its best test's: a file stays together
        firsts[item.path] = min(firsts.get(item.path, (9, 0)), rank(item))
    items.sort(key=lambda item: firsts[item.path])  # stable: collection order within a rank


# --- Bytecode ------------------------------------------------------------------------------------------------------
# The suite starts the CLI in hundreds of fresh interpreters. Where the environment sets PYTHONDONTWRITEBYTECODE
# (as some CI images do), each of them would compile the project's ~70 modules again (~0.2 s a start); compiled
# once here, before the workers start, they are read (Python reads .pyc files even when told not to write them).
def pytest_sessionstart(session: pytest.Session) -> None:
    import compileall

    if not hasattr(session.config, "workerinput"):  # the controller, or a run without xdist
        for package in ("wonderverse", "tasks", "flows", "benchmarks"):
            compileall.compile_dir(ROOT / package, quiet=1)
