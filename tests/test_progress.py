"""Progress from inside the steps: a tiny scene run in-process with a recording reporter (iterations with
the loss, views and frames of the outputs, segments as they finish), the plain lines a log shows, the lines
a Prefect task run's log holds, and the check's summary counting only what this run generated."""

from __future__ import annotations

import io
import os
import re
import shutil
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import ROOT, tiny_config
from rich.console import Console

import tasks.progress
from flows.extend import extended_config
from flows.pipeline import execute
from flows.progress import PlainReporter
from tasks.fan_out import fan_out
from wonderverse.config import RunConfig
from wonderverse.store import SceneStore

ITERATIONS = 100
VIDEO_FRAMES = 8


class Recording(PlainReporter):
    """Plain lines into a string, and every `advance` call as (step, done, total, unit, note, eta)."""

    def __init__(self, n_steps: int) -> None:
        super().__init__(Console(file=io.StringIO(), width=200, force_terminal=False), n_steps)
        self.calls: list[tuple[str, int, int, str, str, bool]] = []
        self.caller_threads: set[int] = set()

    def advance(self, done: int, total: int, unit: str, note: str = "", eta: bool = True) -> None:
        self.calls.append((self.step, done, total, unit, note, eta))
        self.caller_threads.add(threading.get_ident())
        super().advance(done, total, unit, note, eta=eta)

    def of(self, unit: str) -> list[tuple[int, int, str]]:
        return [(d, t, n) for _, d, t, u, n, _ in self.calls if u == unit]

    def text(self) -> str:
        return self.console.file.getvalue()  # type: ignore[attr-defined]


def _config(**check: Any) -> RunConfig:
    cfg = tiny_config()
    steps = cfg.steps.model_dump()
    steps["check"] |= check
    steps["splats"]["train"] |= {"iterations": ITERATIONS}
    steps["outputs"] |= {"video_frames": VIDEO_FRAMES}
    execution = {"segment_workers": 1}  # in-process: no Dask cluster to start
    return RunConfig.model_validate({**cfg.model_dump(), "steps": steps, "execution": execution})


def attempts(scene: Path) -> dict[str, int]:
    store = SceneStore.open(scene)
    return {seg: len(store.children(f"segments/{seg}/attempts")) for seg in store.children("segments")}


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> dict[str, Any]:
    scene = tmp_path_factory.mktemp("progress") / "scene"
    rec = Recording(7)
    token = tasks.progress.current.set(rec)
    try:
        results = execute(scene, _config())
    finally:
        tasks.progress.current.reset(token)
    return {"scene": scene, "rec": rec, "results": {r.step: r for r in results}, "thread": threading.get_ident()}


def _counts_up(seq: list[tuple[int, int, str]], total: int) -> None:
    done = [d for d, _, _ in seq]
    assert {t for _, t, _ in seq} == {total}, seq
    assert done == sorted(done) and done[0] == 0 and done[-1] == total, done


@pytest.mark.e2e
def test_splats_reports_iterations_with_the_loss(run) -> None:
    seq = run["rec"].of("iterations")
    _counts_up(seq, ITERATIONS)
    assert len(seq) <= ITERATIONS + 1  # at most one report a step (every 1 % of 100)
    final = seq[-1][2]
    m = re.fullmatch(r"loss (\d+\.\d+), (\d+) Gaussians", final)
    assert m, final
    stored = SceneStore.open(run["scene"]).meta("splats")
    assert float(m[1]) == pytest.approx(stored.curves["total"][-1], abs=1e-4)  # the last loss of the run
    assert int(m[2]) == stored.metrics.n_gaussians
    assert all(step == "splats" for step, *_, unit, _, _ in run["rec"].calls if unit == "iterations")


@pytest.mark.e2e
def test_outputs_report_views_and_frames(run) -> None:
    rec = run["rec"]
    rendered, fused = rec.of("views rendered for the mesh"), rec.of("views fused")
    assert rendered and fused
    n_views = rendered[-1][1]
    assert n_views >= len(SceneStore.open(run["scene"]).meta("splats").frames)  # training cameras and more
    for seq in (rendered, fused):
        _counts_up(seq, n_views)
        assert [d for d, _, _ in seq] == list(range(n_views + 1))  # one report a view
    for unit in ("fly-through frames", "novel-view frames"):
        assert [d for d, _, _ in rec.of(unit)] == list(range(VIDEO_FRAMES + 1)), unit


@pytest.mark.e2e
def test_segment_steps_report_each_segment_as_it_finishes(run) -> None:
    rec = run["rec"]
    segs = SceneStore.open(run["scene"]).children("segments")
    for unit in ("segments rendered", "segments checked", "segments with priors"):
        seq = rec.of(unit)
        _counts_up(seq, len(segs))
        assert [d for d, _, _ in seq] == list(range(len(segs) + 1)), (unit, seq)
        assert sorted(n for d, _, n in seq if d) == segs, (unit, seq)  # each segment named once, as it finished
    stages = rec.of("SfM stages")
    assert [d for d, _, _ in stages] == [0, 1, 2, 3, 4] and "mapping" in stages[3][2], stages
    assert not any(eta for *_, unit, _, eta in rec.calls if unit == "SfM stages")  # unequal stages: no time left
    assert rec.caller_threads == {run["thread"]}  # reported from the step's thread, never a worker's


@pytest.mark.e2e
def test_plain_lines_of_the_run(run) -> None:
    text = run["rec"].text()
    assert re.search(rf"\[6/7\] splats: iterations 0/{ITERATIONS} \(0 %\)", text), text
    assert re.search(rf"\[6/7\] splats: iterations {ITERATIONS}/{ITERATIONS} \(100 %\), loss \d", text), text
    assert re.search(r"\[3/7\] check: segments checked 3/3 \(100 %\), s00\d", text), text
    assert "[4/7] poses: SfM stages 0/4 (0 %), writing frames\n" in text, text
    assert "[4/7] poses: SfM stages 3/4 (75 %), mapping (" in text, text  # stages: a line each, unthrottled
    assert not re.search(r"poses: SfM stages.* left", text), text
    # throttled (a unit's first and last report, then one every 10 s): 101 reports, a few lines
    assert len(run["rec"].of("iterations")) == ITERATIONS + 1
    assert 2 <= len([ln for ln in text.splitlines() if "splats: iterations" in ln]) <= 4


def test_plain_reporter_prints_time_left_and_unit(monkeypatch) -> None:
    monkeypatch.setattr(tasks.progress, "PLAIN_EVERY_S", 0.5)  # a line every 0.5 s instead of every 10 s
    out = io.StringIO()
    reporter = PlainReporter(Console(file=out, width=200, force_terminal=False), 7)
    reporter.started("splats", "3D Gaussian splatting")
    reporter.advance(0, 1000, "iterations", "loss 0.2000, 100 Gaussians")
    for k in range(1, 100):  # many quick reports: one line at most
        reporter.advance(k, 1000, "iterations", "loss 0.1000, 120 Gaussians")
    time.sleep(1.1)
    reporter.advance(250, 1000, "iterations", "loss 0.0521, 21468 Gaussians")
    reporter.advance(1000, 1000, "iterations", "loss 0.0400, 21468 Gaussians")
    lines = out.getvalue().splitlines()
    assert lines[0] == "[1/7] splats: 3D Gaussian splatting …"
    assert lines[1] == "[1/7] splats: iterations 0/1000 (0 %), loss 0.2000, 100 Gaussians"
    left = [ln for ln in lines if "left" in ln]
    assert len(left) == 1 and left[0].startswith("[1/7] splats: iterations 250/1000 (25 %), loss 0.0521"), lines
    seconds = int(re.search(r"(\d+) s left", left[0])[1])
    assert 2 <= seconds <= 5  # 250 in ~1.1 s: 750 more in ~3.3 s
    assert lines[-1] == "[1/7] splats: iterations 1000/1000 (100 %), loss 0.0400, 21468 Gaussians"
    assert len(lines) <= 5


def test_fan_out_reports_from_the_calling_thread_in_completion_order() -> None:
    """Item c finishes first, then b, then a: each item waits until the previous one has been reported, so
    this passes only when every item is reported as it finishes, not when all are done."""
    items = ["a", "b", "c"]
    released = {name: threading.Event() for name in items}
    reports: list[tuple[int, int, str, int]] = []

    def work(name: str) -> str:
        assert released[name].wait(20), f"{name} was never released: the report before it did not come"
        return name.upper()

    def progress(done: int, total: int, note: str) -> None:
        reports.append((done, total, note, threading.get_ident()))
        nxt = {"": "c", "c": "b", "b": "a"}.get(note)
        if nxt:
            released[nxt].set()

    assert fan_out("test", items, work, concurrency=3, progress=progress) == ["A", "B", "C"]
    assert [(d, t, n) for d, t, n, _ in reports] == [(0, 3, ""), (1, 3, "c"), (2, 3, "b"), (3, 3, "a")]
    assert {ident for *_, ident in reports} == {threading.get_ident()}


@pytest.mark.e2e
def test_check_counts_only_attempts_generated_in_this_run(run, tmp_path: Path) -> None:
    """An extension re-runs the check: the old segments are cached and their earlier regenerations are
    not this run's; only the new segment's attempts count."""
    before = attempts(run["scene"])
    assert sum(before.values()) > len(before), before  # the first run regenerated (tiny frames fail the check)
    first = run["results"]["check"].detail
    assert first.startswith(f"{len(before)} segments, {sum(before.values()) - len(before)} regenerated this run")
    assert "cached" not in first

    scene = tmp_path / "scene"
    shutil.copytree(run["scene"], scene)
    cfg = extended_config(_config(), "a frozen lake beyond the trees on the left")
    detail = {r.step: r for r in execute(scene, cfg, until="check")}["check"].detail
    after = attempts(scene)
    new = set(after) - set(before)
    assert len(new) == 1 and {s: after[s] for s in before} == before
    regenerated = after[new.pop()] - 1
    assert detail.startswith(f"{len(after)} segments ({len(before)} cached), {regenerated} regenerated this run")


PREFECT_RUN = """
import sys
from pathlib import Path
from flows.pipeline import run_pipeline
from wonderverse.config import RunConfig

cfg = RunConfig.model_validate_json(Path(sys.argv[2]).read_text())
for r in run_pipeline(sys.argv[1], cfg, until="splats", engine="prefect"):
    print(f"{r.step}|{r.status}|{r.detail}")
"""


@pytest.mark.e2e
def test_prefect_task_runs_log_the_progress(run, tmp_path: Path) -> None:
    """Under the Prefect engine the step task runs' logs hold the same progress lines: a re-run whose
    check settings changed re-checks every segment (as Prefect sub-task runs) and re-trains the splats."""
    scene, home = tmp_path / "scene", tmp_path / "prefect"
    shutil.copytree(run["scene"], scene)
    before = attempts(scene)
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(_config(max_attempts=3).model_dump_json())
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env |= {"PREFECT_HOME": str(home), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    env["PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS"] = "180"  # a fresh home migrates its database first
    r = subprocess.run(
        [sys.executable, "-c", PREFECT_RUN, str(scene), str(cfg_file)],
        capture_output=True,
        text=True,
        timeout=400,
        cwd=ROOT,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    status = {line.split("|")[0]: line.split("|", 2)[1:] for line in r.stdout.splitlines() if "|" in line}
    assert status["plan"][0] == "cached" and status["splats"][0] == "ran", r.stdout
    # attempts the first run made are re-checked, not regenerated (all of them, when it made >= 3 a segment)
    regenerated = sum(attempts(scene).values()) - sum(before.values())
    assert status["check"][1].startswith(f"3 segments, {regenerated} regenerated this run"), status["check"]
    with sqlite3.connect(home / "prefect.db") as db:
        rows = db.execute(
            "SELECT task_run.name, log.message FROM log JOIN task_run ON log.task_run_id = task_run.id"
        ).fetchall()
        names = {name for (name,) in db.execute("SELECT name FROM task_run")}
    assert {"check s000", "check s001", "check s002"} <= names, names  # segments checked as sub-task runs
    logs: dict[str, list[str]] = {}
    for name, message in rows:
        logs.setdefault(name.rsplit("-", 1)[0], []).append(message)  # step task runs: '<step>-<3 hex>'
    splats = logs.get("splats", [])
    assert any(re.match(rf"iterations 0/{ITERATIONS} \(0 %\), \d+ Gaussians$", m) for m in splats), logs
    assert any(re.match(rf"iterations {ITERATIONS}/{ITERATIONS} \(100 %\), loss \d", m) for m in splats), logs
    assert any(re.match(r"segments checked 3/3 \(100 %\), s00\d$", m) for m in logs.get("check", [])), logs
    assert any(m.startswith("SfM stages 3/4 (75 %), mapping (") for m in logs.get("poses", [])), logs
