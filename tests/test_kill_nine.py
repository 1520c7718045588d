"""kill -9, as the issue tried it: nothing of a run outlives the `wonderverse` process, and a run killed at any moment
resumes to the same output files, byte for byte.

Every process of a run is found by a marker in its environment (inherited by the run, its Dask workers and Prefect's
ephemeral server, however they were started, whichever session or parent they end up in), not by ancestry alone: a
process that left the tree is found too."""

from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import psutil
import pytest
import yaml
from conftest import ROOT, SHORT_STEPS, command_of, run_cli, tiny_config

MARKER = "WONDERVERSE_TEST_RUN"
OUTPUTS = ("splats.ply", "mesh.ply", "points.ply")


def tiny_spec(folder: Path) -> Path:
    """tiny_config as a --config file, with SHORT_STEPS (the whole run takes ~20 s on 2 cores) and the global SfM
    on one thread: COLMAP's mapper with two threads is not bit-reproducible (two clean runs of this scene with
    num_threads 2 gave 525 and 507 splats), with one it is."""
    steps = {**SHORT_STEPS, "poses": {"sfm": {"num_threads": 1}}}
    execution = {"cluster_min_pixels": 0}  # Dask workers however small the segments: a kill must take them down too
    scene = tiny_config().scene.model_dump(mode="json")
    f = folder / "tiny.yaml"
    f.write_text(yaml.safe_dump({"preset": "preview", "scene": scene, "steps": steps, "execution": execution}))
    return f


@dataclass(frozen=True)
class Made:
    spec: Path
    scene: Path  # made by one uninterrupted `generate`


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> Made:
    """The tiny scene made once, uninterrupted: the reference of the kills and the base of the extension."""
    folder = tmp_path_factory.mktemp("made")
    spec = tiny_spec(folder)
    r = run_cli("generate", "--config", str(spec), "--out", str(folder / "scene"), "--engine", "local", timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return Made(spec, folder / "scene")


def start(*args: str, env: dict[str, str]) -> tuple[subprocess.Popen, list[str]]:
    """`wonderverse ARGS` in its own session (a shell's job); its stderr lines gathered as they come."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "flows", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **env},
        start_new_session=True,
    )
    lines: list[str] = []

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append(line)

    threading.Thread(target=read, daemon=True).start()
    return proc, lines


def marked(marker: str) -> list[psutil.Process]:
    """Every live process whose environment carries `marker` (zombies are dead already)."""
    found = []
    for p in psutil.process_iter():
        try:
            if p.status() != psutil.STATUS_ZOMBIE and p.environ().get(MARKER) == marker:
                found.append(p)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return found


def described(processes: list[psutil.Process]) -> list[str]:
    out = []
    for p in processes:
        try:
            out.append(f"{p.pid} sid {os.getsid(p.pid)} ppid {p.ppid()}: {' '.join(p.cmdline())[:160]}")
        except (psutil.NoSuchProcess, ProcessLookupError):
            continue
    return out


def wait_until(what: str, condition, timeout: float, proc: subprocess.Popen, lines: list[str]):  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = condition()
        if found:
            return found
        if proc.poll() is not None:
            pytest.fail(f"the run ended (rc {proc.returncode}) before {what}:\n{''.join(lines)}")
        time.sleep(0.2)
    proc.kill()
    pytest.fail(f"no {what} within {timeout} s:\n{''.join(lines)}")


def wait_for_line(proc: subprocess.Popen, lines: list[str], wanted: Callable[[str], bool]) -> None:
    """Until the running command has printed a line that is `wanted` (it must not end first, nor take 10 min)."""
    deadline = time.monotonic() + 600
    while not any(wanted(ln) for ln in lines):
        assert proc.poll() is None and time.monotonic() < deadline, "".join(lines)[-3000:]
        time.sleep(0.005)


@pytest.mark.e2e
def test_kill_9_of_wonderverse_alone_leaves_no_prefect_server_and_no_run(tmp_path: Path):
    marker = uuid.uuid4().hex
    env = {MARKER: marker, "PREFECT_HOME": str(tmp_path / "prefect"), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    args = ("generate", "--config", str(tiny_spec(tmp_path)), "--out", str(tmp_path / "scene"), "--engine", "prefect")
    proc, lines = start(*args, env=env)
    try:

        def server() -> list[psutil.Process]:
            return [p for p in marked(marker) if "uvicorn" in command_of(p)]

        servers = wait_until("Prefect's server (uvicorn)", server, 300, proc, lines)
        wait_until("a step of the flow", lambda: any("] plan:" in ln for ln in lines), 300, proc, lines)
        run = marked(marker)
        assert len(run) >= 3, described(run)  # this command, the run, the reaper, the server
        assert proc.pid in {p.pid for p in run} and servers[0].pid != proc.pid
        proc.kill()  # kill -9 of the `wonderverse` process only
        proc.wait(timeout=10)
        t0 = time.monotonic()
        while marked(marker) and time.monotonic() - t0 < 10:
            time.sleep(0.2)
        left = marked(marker)
        assert not left, f"left running {time.monotonic() - t0:.1f} s after kill -9: {described(left)}"
    finally:
        for p in marked(marker):  # never leave them to the next test
            p.kill()
        if proc.poll() is None:
            proc.kill()


def kill_everything(proc: subprocess.Popen) -> None:
    """SIGKILL the command and every process of its run at once (the run's own process group, the command's group,
    and any descendant), as a power cut or the OOM killer of the whole job would."""
    descendants = psutil.Process(proc.pid).children(recursive=True)
    for group in {os.getpgid(p.pid) for p in descendants if p.is_running()} | {proc.pid}:
        try:
            os.killpg(group, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            continue
    for p in descendants:
        try:
            p.kill()
        except psutil.NoSuchProcess:
            continue
    proc.wait(timeout=10)
    # SIGKILL is delivered at once but a large process takes a moment to be torn down: wait for those killed here, so
    # that what `marked` finds afterwards is what escaped the kill, not what is still dying
    psutil.wait_procs(descendants, timeout=10)


@pytest.mark.e2e
def test_a_run_killed_at_random_moments_resumes_to_byte_identical_outputs(made: Made, tmp_path: Path):
    truth = {name: (made.scene / name).read_bytes() for name in OUTPUTS}
    assert all(truth.values())

    # One moment at random in each part of the run, early, middle and late: a random delay after the step that
    # begins it has said so (by the run's own progress, not the clock: the machine's load changes how long it takes).
    rng = random.Random(21)
    moments = [("generate_segments", 3.0), ("priors", 3.0), ("outputs", 1.0)]
    states = set()
    for i, (step, most) in enumerate(moments):
        marker = uuid.uuid4().hex
        scene = tmp_path / f"killed-{i}"
        args = ("generate", "--config", str(made.spec), "--out", str(scene), "--engine", "local")
        proc, lines = start(*args, env={MARKER: marker})
        wait_for_line(proc, lines, lambda ln, step=step: re.match(rf"\[\d+/\d+\] {step}: ", ln) is not None)
        delay = rng.random() * most
        time.sleep(delay)
        assert proc.poll() is None, f"the run finished {delay:.1f} s after {step} began:\n{''.join(lines)}"
        kill_everything(proc)
        time.sleep(0.5)
        assert not marked(marker), described(marked(marker))
        done = [m.group(1) for ln in lines if (m := re.match(r"\[\d+/\d+\] (\w+): (ran|cached)", ln))]
        states.add(tuple(done))
        r = run_cli(*args, timeout=600)
        when = f"{delay:.1f} s into {step} (after {done})"
        assert r.returncode == 0, f"resume after a kill {when}: {r.stderr[-3000:]}"
        for name in OUTPUTS:
            assert (scene / name).read_bytes() == truth[name], f"{name} differs after a kill {when}"
    assert len(states) == 3, states  # the kills came at three different points of the run


@pytest.mark.e2e
def test_an_extension_killed_while_it_fuses_its_new_views_resumes_to_byte_identical_outputs(made: Made, tmp_path: Path):
    """The mesh of an extended scene goes on from the stored fusion (`tasks.output_mesh`): a kill while the new
    views are fused leaves that fusion as it was, and the re-run gives the files an uninterrupted extension gives."""
    import shutil

    words = "a frozen lake on the left"
    reference, killed = tmp_path / "reference", tmp_path / "killed"
    shutil.copytree(made.scene, reference)
    shutil.copytree(made.scene, killed)
    r = run_cli("extend", str(reference), words, "--engine", "local", timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "views rendered for the mesh (new cameras)" in r.stderr  # the fusion went on from the stored one
    truth = {name: (reference / name).read_bytes() for name in (*OUTPUTS, "mesh.glb")}
    marker = uuid.uuid4().hex
    proc, lines = start("extend", str(killed), words, "--engine", "local", env={MARKER: marker})
    wait_for_line(proc, lines, lambda ln: "views rendered for the mesh (new cameras)" in ln)  # the fusion has begun
    kill_everything(proc)
    assert not marked(marker), described(marked(marker))
    assert not any("] outputs: ran" in ln for ln in lines), "the kill came after the run finished"
    r = run_cli("extend", str(killed), words, "--engine", "local", timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    for name, data in truth.items():
        assert (killed / name).read_bytes() == data, f"{name} differs after a kill during the fusion"
