"""`wonderverse serve` and `wonderverse batch` against real Prefect: a server on 127.0.0.1, a served cron
deployment, runs through the REST API, and a local batch on Prefect's ephemeral API."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from conftest import ROOT, TINY_VIDEO

from tasks import STEPS, step_keys
from wonderverse.config import build_config
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore

SERVER_START_S = 240  # a fresh Prefect home migrates its database first: ~20 s idle, far more on a busy 2-core box


def write_tiny_spec(folder: Path, name: str, prompt: str = "a cosy reading room with shelves", **scene: Any) -> Path:
    """A scene spec file with the tiny settings of conftest.tiny_config and no extensions (one segment)."""
    folder.mkdir(parents=True, exist_ok=True)
    video = {**TINY_VIDEO, "options": {"fault_probability": 0.0}, **scene.pop("video", {})}
    spec = {"preset": "preview", "scene": {"prompt": prompt, "extensions": {"rounds": 0}, "video": video, **scene}}
    f = folder / f"{name}.yaml"
    f.write_text(yaml.safe_dump(spec))
    return f


def step_status(scene_dir: Path, cfg: Any) -> dict[str, bool]:
    """{step: complete under the key the config gives} for a scene store (keys computed here, from the config)."""
    store, keys = SceneStore.open(scene_dir), step_keys(STEPS, cfg)
    return {s.name: store.is_complete(s.group, keys[s.name]) for s in STEPS}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def prefect_env(home: Path, api_url: str | None = None, **extra: str) -> dict[str, str]:
    """The environment of a child process with its own Prefect home (never the user's ~/.prefect)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env |= {"PREFECT_HOME": str(home), "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "PYTHONUNBUFFERED": "1"}
    # a fresh home migrates its database at the first start: on 2 busy cores that outlasts the 20 s default
    env["PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS"] = "180"
    if api_url:
        env["PREFECT_API_URL"] = api_url
    return env | extra


def stop(proc: subprocess.Popen, first: int = signal.SIGTERM, wait_s: float = 20) -> None:
    """Stop a child we started (its own process group: runners spawn flow-run processes)."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, first)
        proc.wait(wait_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    except ProcessLookupError:
        pass


def wait_for(what: str, probe, timeout_s: float, poll_s: float = 1.0, proc: subprocess.Popen | None = None) -> Any:
    """probe() until it returns something truthy; fail naming `what` on timeout or when `proc` dies."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = probe()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            pytest.fail(f"process died (rc {proc.returncode}) while waiting for {what}")
        time.sleep(poll_s)
    pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}")


@contextmanager
def prefect_server(tmp: Path) -> Iterator[tuple[subprocess.Popen, int, str]]:
    """`prefect server start --host 127.0.0.1` on a free port with its own home; yields (process, port, API URL).

    PREFECT_API_URL is set for the server too: the UI it serves reads the API address from it."""
    port = free_port()
    api = f"http://127.0.0.1:{port}/api"
    log = open(tmp / "server.log", "w")  # noqa: SIM115 (closed in finally)
    proc = subprocess.Popen(
        [sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port", str(port)],
        env=prefect_env(tmp / "server-home", api),
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:

        def healthy() -> bool:
            try:
                return httpx.get(f"{api}/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for("the Prefect server's /api/health", healthy, SERVER_START_S, proc=proc)
        yield proc, port, api
    finally:
        stop(proc)
        log.close()


def api_call(method: str, url: str, json: Any = None, tries: int = 10) -> Any:
    """One REST call to the Prefect server, its JSON answer. A 503 (the server's SQLite database busy, seen
    on 2 loaded cores) is retried after a pause, as Prefect's own client does; any other error fails."""
    for attempt in range(tries):
        r = httpx.request(method, url, json=json, timeout=10)
        if r.status_code != 503 or attempt == tries - 1:
            break
        time.sleep(2)
    r.raise_for_status()
    return r.json()


def flow_runs(api: str, **filters: Any) -> list[dict[str, Any]]:
    return api_call("POST", f"{api}/flow_runs/filter", {"limit": 200, **filters})


def run_state(api: str, run_id: str) -> str:
    return api_call("GET", f"{api}/flow_runs/{run_id}")["state"]["type"]


def task_runs(api: str, flow_run_id: str) -> dict[str, str]:
    """{task name: state name} of a flow run's task runs."""
    runs = api_call("POST", f"{api}/task_runs/filter", {"flow_runs": {"id": {"any_": [flow_run_id]}}})
    # task run names are '<task name>-<3 hex>' unless named explicitly
    return {t["name"].rsplit("-", 1)[0]: t["state"]["name"] for t in runs}


def _at(ts: str) -> datetime:
    return datetime.fromisoformat(ts.replace("Z", "+00:00"))


@pytest.mark.e2e
def test_serve_registers_a_cron_deployment_whose_runs_complete(tmp_path: Path):
    """serve over a folder with one spec: the cron schedule creates runs on the minute, a run triggered through
    the API and a cron run both complete, each scene is a subflow whose task runs are the steps (and one per
    segment), logs reach the server, and the scene store holds the completed step."""
    specs = tmp_path / "specs"
    spec = write_tiny_spec(specs, "reading_room")
    out = tmp_path / "scenes"
    with prefect_server(tmp_path) as (_, _, api):
        serve_log = open(tmp_path / "serve.log", "w")  # noqa: SIM115
        cmd = [sys.executable, "-m", "flows.serve", "serve", str(specs), "--out", str(out), "--cron", "* * * * *"]
        serve = subprocess.Popen(
            [*cmd, "--until", "generate_segments", "--name", "tiny"],
            cwd=ROOT,
            env=prefect_env(tmp_path / "serve-home", api, PREFECT_RUNNER_POLL_FREQUENCY="2"),
            stdout=serve_log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:

            def deployment() -> dict[str, Any] | None:
                r = httpx.get(f"{api}/deployments/name/batch/tiny", timeout=10)
                return r.json() if r.status_code == 200 else None

            dep = wait_for("deployment batch/tiny", deployment, 120, proc=serve)
            assert dep["parameters"]["until"] == "generate_segments"
            assert dep["schedules"][0]["schedule"]["cron"] == "* * * * *"
            by_dep = {"deployments": {"id": {"any_": [dep["id"]]}}}

            # the server's scheduler fills in cron runs, each due on a whole minute
            cron_runs = wait_for(
                "runs scheduled by cron", lambda: [r for r in flow_runs(api, **by_dep) if r["auto_scheduled"]], 60
            )
            starts = sorted(_at(r["expected_start_time"]) for r in cron_runs)
            assert all(t.second == 0 and t.microsecond == 0 for t in starts)
            assert len(starts) >= 2 and (starts[1] - starts[0]).total_seconds() == 60

            # a run triggered through the API (what `prefect deployment run batch/tiny` does)
            manual = api_call("POST", f"{api}/deployments/{dep['id']}/create_flow_run", {})["id"]

            def finished() -> list[dict[str, Any]] | None:
                runs = flow_runs(api, **by_dep)
                done = {r["id"]: r for r in runs if r["state_type"] == "COMPLETED"}
                bad = [r for r in runs if r["state_type"] in ("FAILED", "CRASHED")]
                assert not bad, f"{bad[0]['state']['message']}\n{(tmp_path / 'serve.log').read_text()[-3000:]}"
                cron_done = [r for r in done.values() if r["auto_scheduled"]]
                return [done[manual], cron_done[0]] if manual in done and cron_done else None

            # the next whole minute is at most 60 s away; then one run of a cached scene
            runs = wait_for("the triggered run and a cron run to complete", finished, 150, poll_s=2, proc=serve)

            # the later run found the scene complete: its log says so. Logs reach the server in batches from the
            # run's process, so they are awaited before Ctrl-C stops that process (under load, a batch came late).
            later = max(runs, key=lambda r: _at(r["end_time"]))

            def later_logs() -> list[str]:
                logs = api_call("POST", f"{api}/logs/filter", {"logs": {"flow_run_id": {"any_": [later["id"]]}}})
                return [x["message"] for x in logs]

            logs = wait_for("the batch run's logs", lambda: [m for m in later_logs() if "reading_room" in m], 60)
            assert "reading_room: completed (plan cached, generate_segments cached)" in logs
        finally:
            stop(serve, signal.SIGINT)  # what Ctrl-C does: the runner pauses the schedule and exits
            serve_log.close()

        # each batch run ran the scene as a subflow named after its spec; the first one's task runs are the steps
        # (the first two: a later cron run may have started while the logs were awaited)
        subflows = flow_runs(api, flow_runs={"name": {"any_": ["reading_room"]}}, sort="START_TIME_ASC")[:2]
        assert len(subflows) == 2 and {s["state_type"] for s in subflows} == {"COMPLETED"}
        first, second = (task_runs(api, s["id"]) for s in subflows)
        assert first == {"plan": "Completed", "generate_segments": "Completed", "generate_segments s000": "Completed"}
        assert second == {"plan": "Cached", "generate_segments": "Cached"}  # complete: shown as cached, not re-run

    status = step_status(out / "reading_room", build_config(config_file=spec))
    assert status["plan"] and status["generate_segments"]
    assert not status["check"]  # --until generate_segments stopped there
    store = SceneStore.open(out / "reading_room")
    assert store.children("segments") == ["s000"]


@pytest.mark.e2e
def test_batch_runs_every_spec_and_survives_an_invalid_one(tmp_path: Path):
    """`batch` on Prefect's ephemeral API (no server): the valid scene completes, the invalid spec is named as a
    failure with its reason, exit code 2."""
    specs = tmp_path / "specs"
    good = write_tiny_spec(specs, "good", prompt="a small harbour at dawn")
    write_tiny_spec(specs, "bad", video={"frames_per_segment": -5})
    (specs / "notes.txt").write_text("not a spec")  # ignored: only *.yaml / *.yml are specs
    out = tmp_path / "scenes"
    r = subprocess.run(
        [sys.executable, "-m", "flows.serve", "batch", str(specs), "--out", str(out), "--until", "plan"],
        cwd=ROOT,
        env=prefect_env(tmp_path / "home", PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="240"),
        capture_output=True,
        text=True,
        timeout=400,
    )
    assert r.returncode == 2, r.stderr[-3000:]
    assert r.stderr.strip().splitlines()[-1] == "error: 1 of 2 scenes failed: bad"
    rows = {line.split("│")[1].strip(): line for line in r.stdout.splitlines() if line.count("│") >= 4}
    assert "failed" in rows["bad"] and "frames_per_segment" in rows["bad"]
    assert "completed" in rows["good"] and "plan ran" in rows["good"]
    assert not (out / "bad").exists()  # an invalid spec never touches its output folder
    status = step_status(out / "good", build_config(config_file=good))
    assert status["plan"] and not status["generate_segments"]


@pytest.mark.e2e
def test_serve_refuses_without_a_server(tmp_path: Path):
    specs = tmp_path / "specs"
    write_tiny_spec(specs, "one")
    cmd = [sys.executable, "-m", "flows.serve", "serve", str(specs), "--out", str(tmp_path / "o")]
    r = subprocess.run(cmd, cwd=ROOT, env=prefect_env(tmp_path / "h"), capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "set PREFECT_API_URL" in r.stderr, r.stderr[-2000:]
    dead = f"http://127.0.0.1:{free_port()}/api"  # nothing listens there
    r = subprocess.run(
        cmd, cwd=ROOT, env=prefect_env(tmp_path / "h", dead), capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 2 and f"no Prefect server answers at PREFECT_API_URL={dead}" in r.stderr, r.stderr[-2000:]


def test_deployment_is_loadable_by_the_runner(tmp_path: Path):
    """What a served run does first: import the deployment's entrypoint and find the `batch` flow there."""
    from prefect.flows import load_flow_from_entrypoint

    from flows.serve import build_deployment

    specs = tmp_path / "specs"
    write_tiny_spec(specs, "one")
    dep = build_deployment(specs, tmp_path / "out", cron="*/5 * * * *", until="plan")
    assert dep.name == "specs" and dep.entrypoint == "flows.serve.batch"
    assert dep.parameters["specs_dir"] == str(specs.resolve()) and dep.parameters["until"] == "plan"
    assert dep.schedules[0].schedule.cron == "*/5 * * * *"
    assert load_flow_from_entrypoint(dep.entrypoint).name == "batch"
    with pytest.raises(WonderError, match="not a valid cron expression"):
        build_deployment(specs, tmp_path / "out", cron="every minute")
    with pytest.raises(WonderError, match="unknown step 'splat'"):
        build_deployment(specs, tmp_path / "out", until="splat")
    (tmp_path / "empty").mkdir()
    with pytest.raises(WonderError, match="no scene specs"):
        build_deployment(tmp_path / "empty", tmp_path / "out")


RETRY_SCRIPT = """
import json, sys
from prefect import flow
from tasks.base import Step, is_transient
from wonderverse.store import SceneStore

SceneStore.open_or_create(sys.argv[1])
calls = {"flaky": 0, "buggy": 0}

def flaky(store, params, ctx):
    calls["flaky"] += 1
    if calls["flaky"] < 3:
        raise ConnectionError("scheduler connection lost")
    return "ok"

def buggy(store, params, ctx):
    calls["buggy"] += 1
    raise ValueError("a bug")

def task_of(name, fn):
    return Step(name, 1, (), lambda cfg: None, fn, f"test step {name}", name).task.with_options(retry_delay_seconds=0)

@flow
def f():
    try:
        task_of("buggy", buggy)(sys.argv[1], None, "k")
    except ValueError:
        pass
    return task_of("flaky", flaky)(sys.argv[1], None, "k")

kinds = [is_transient(e) for e in (TimeoutError(), ConnectionResetError(), OSError(), ValueError())]
print(json.dumps({"result": f(), **calls, "transient": kinds}))
"""


@pytest.mark.e2e
def test_step_tasks_retry_transient_failures_only(tmp_path: Path):
    """A step that loses its connection twice succeeds on its third try; a bug fails at once."""
    r = subprocess.run(
        [sys.executable, "-c", RETRY_SCRIPT, str(tmp_path / "scene")],
        cwd=ROOT,
        env=prefect_env(tmp_path / "home", PREFECT_LOGGING_LEVEL="CRITICAL"),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out == {"result": "ok", "flaky": 3, "buggy": 1, "transient": [True, True, False, False]}
