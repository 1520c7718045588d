"""How a run behaves for the person at the terminal: Ctrl-C and SIGTERM stop it at once with one line and
exit 130 / 143, leaving no process behind and everything complete in the store (the same command resumes);
a re-run keeps the scene's extensions, and a run that would regenerate the scene's segments is refused
unless asked; the first line says which preset and engine run. Both engines."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest
import yaml
from conftest import ROOT, SHORT_STEPS, TINY_VIDEO, command_of, run_cli, tree_digest

from flows.pipeline import execute
from tasks.segments import segment_ids
from wonderverse.config import build_config
from wonderverse.store import SceneStore

pytestmark = pytest.mark.e2e  # the CLI in a subprocess, signalled


def tiny_spec(
    tmp_path: Path, prompt: str = "a small house decorated for Christmas", execution: dict | None = None, **scene
) -> Path:
    """A --config file of the tiny video with SHORT_STEPS (a whole run in ~20 s on 2 cores)."""
    f = tmp_path / f"spec-{abs(hash((prompt, str(scene), str(execution))))}.yaml"
    video = {**TINY_VIDEO, "options": {"fault_probability": 0.0}}
    spec = {"preset": "preview", "scene": {"prompt": prompt, "video": video, **scene}, "steps": SHORT_STEPS}
    spec |= {"execution": execution} if execution else {}
    f.write_text(yaml.safe_dump(spec))
    return f


def prefect_env(tmp_path: Path) -> dict[str, str]:
    return {"PREFECT_HOME": str(tmp_path / "prefect"), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}


def start_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    """`wonderverse ARGS` in its own process group, as a shell starts a foreground job."""
    return subprocess.Popen(
        [sys.executable, "-m", "flows", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        start_new_session=True,
    )


def wait_for_line(proc: subprocess.Popen, needle: str, timeout: float = 600) -> list[str]:
    """stderr lines up to and including the first that contains `needle`."""
    assert proc.stderr is not None
    lines: list[str] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            pytest.fail(f"the run ended before {needle!r}: rc {proc.wait()}, stderr:\n{''.join(lines)}")
        lines.append(line)
        if needle in line:
            return lines
    proc.kill()
    pytest.fail(f"no {needle!r} within {timeout} s")


@pytest.mark.parametrize(
    ("engine", "signum", "during", "code"),
    [
        ("local", signal.SIGINT, "splats:", 130),  # the terminal's Ctrl-C reaches the whole foreground job
        ("prefect", signal.SIGINT, "splats:", 130),
        ("local", signal.SIGTERM, "check:", 143),  # `kill PID` while pycolmap (with its glog handler) is loaded
    ],
)
def test_a_signal_stops_the_run_at_once_and_the_same_command_resumes(tmp_path, engine, signum, during, code):
    scene = tmp_path / "scene"
    # stopped during the check, the run has Dask workers, however small its segments: they must stop too
    spec = tiny_spec(tmp_path, execution={"cluster_min_pixels": 0} if during == "check:" else None)
    args = ("generate", "--config", str(spec), "--out", str(scene), "--engine", engine)
    env = prefect_env(tmp_path)
    proc = start_cli(*args, env=env)
    before = wait_for_line(proc, f"] {during}")
    if during == "check:":
        time.sleep(1.0)  # into the SfM of the first segments
    processes = psutil.Process(proc.pid).children(recursive=True)
    t0 = time.monotonic()
    if signum == signal.SIGINT:
        os.killpg(proc.pid, signum)
    else:
        proc.send_signal(signum)
    _, err = proc.communicate(timeout=30)
    seconds = time.monotonic() - t0
    assert proc.returncode == code, err
    assert seconds < 2.0, f"took {seconds:.2f} s to stop"
    after = [ln for ln in err.splitlines() if ln.strip()]  # progress lines written before the signal, then ours
    assert after[-1].startswith("stopped by ") and "resume" in after[-1], err
    assert all(ln.startswith("[") for ln in after[:-1]), err  # nothing else: one line from the stop
    assert not any("Traceback" in ln or "***" in ln for ln in before + after), "".join(before) + err
    time.sleep(0.5)
    alive = [p for p in processes if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert not alive, f"left running: {[command_of(p) for p in alive]}"

    r = run_cli(*args, env=env, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "] plan: cached" in r.stderr and "] generate_segments: cached" in r.stderr, r.stderr[-3000:]
    assert (scene / "splats.ply").stat().st_size > 0 and (scene / "report.html").is_file()


def test_the_first_line_names_the_preset_and_the_engine(tmp_path):
    scene = tmp_path / "s"
    r = run_cli("generate", "a quiet harbour at dawn", "--out", str(scene), "--until", "plan")
    assert r.returncode == 0, r.stderr
    first = r.stderr.splitlines()[0]
    import torch

    expected = "preset standard (a CUDA GPU" if torch.cuda.is_available() else "preset preview (no CUDA GPU"
    assert expected in first and "engine local" in first and str(scene) in first, first
    assert "mesh.ply" not in r.stdout  # only the files this run wrote (none) are listed

    r = run_cli("generate", "a quiet harbour at dawn", "--out", str(scene), "--until", "plan", "--preset", "high")
    assert r.returncode == 0 and "preset high (--preset)" in r.stderr.splitlines()[0], r.stderr
    r = run_cli("generate", "a quiet harbour at dawn", "--out", str(scene), "--until", "plan")
    assert r.returncode == 0 and "preset high (the scene's)" in r.stderr.splitlines()[0], r.stderr


def test_a_rerun_keeps_the_extensions_and_a_changed_prompt_is_refused_unless_asked(tmp_path):
    scene = tmp_path / "scene"
    spec = tiny_spec(tmp_path, extensions={"rounds": 0})
    extended = build_config(
        config_file=spec, overrides={"scene": {"extensions": {"added": ["go left past the trees"]}}}
    )
    execute(scene, extended, until="generate_segments")  # as `extend` leaves a scene: s000 + the added s001
    assert segment_ids(SceneStore.open(scene)) == ["s000", "s001"]

    r = run_cli("generate", "--config", str(spec), "--out", str(scene), "--until", "generate_segments")
    assert r.returncode == 0, r.stderr
    store = SceneStore.open(scene)
    assert segment_ids(store) == ["s000", "s001"]  # the extension is part of the scene
    assert store.root.attrs["config"]["scene"]["extensions"]["added"] == ["go left past the trees"]
    assert "cached" in next(ln for ln in r.stderr.splitlines() if "] generate_segments:" in ln)

    assert run_cli("preview", str(scene)).returncode == 0
    preview = (scene / "preview.mp4").read_bytes()
    before = tree_digest(scene)
    other = tiny_spec(tmp_path, prompt="a desert canyon at noon", extensions={"rounds": 0})
    for engine in ("local", "prefect"):
        r = run_cli(
            "generate", "--config", str(other), "--out", str(scene), "--engine", engine, env=prefect_env(tmp_path)
        )
        lines = [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith("wonderverse: ")]
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), r.stderr
        assert "2 segment(s)" in lines[0] and "prompt" in lines[0] and "--replace-segments" in lines[0]
        assert tree_digest(scene) == before
    assert not (tmp_path / "prefect" / "prefect.db").exists()  # refused before Prefect started

    r = run_cli(
        "generate", "--config", str(other), "--out", str(scene), "--until", "generate_segments", "--replace-segments"
    )
    assert r.returncode == 0, r.stderr
    store = SceneStore.open(scene)
    assert segment_ids(store) == ["s000"] and store.root.attrs["config"]["scene"]["prompt"] == "a desert canyon at noon"
    assert (scene / "preview.mp4").read_bytes() != preview  # derived files follow the scene they show


def test_kill_9_of_the_command_takes_its_run_and_prefects_server_down(tmp_path):
    scene = tmp_path / "scene"
    args = ("generate", "--config", str(tiny_spec(tmp_path)), "--out", str(scene), "--engine", "prefect")
    proc = start_cli(*args, env=prefect_env(tmp_path))
    wait_for_line(proc, "] generate_segments:")  # Prefect's ephemeral server is up by now
    run = psutil.Process(proc.pid).children(recursive=True)
    assert any("uvicorn" in command_of(p) for p in run), [command_of(p) for p in run]
    proc.kill()
    proc.wait()
    _, alive = psutil.wait_procs(run, timeout=5)
    assert not alive, [command_of(p) for p in alive]
