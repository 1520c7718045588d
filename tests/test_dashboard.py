"""The Prefect UI of a finished run, in headless Chromium, and the server bound to 127.0.0.1 only."""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest
from conftest import ROOT, launch_browser
from test_serve import flow_runs, prefect_env, prefect_server, write_tiny_spec

pytestmark = pytest.mark.e2e  # a Prefect server and a browser


SCENE = "dashboard_scene"  # the spec's name: the scene's subflow run is named after it


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """A Prefect server on 127.0.0.1 and a finished `batch` run on it (one tiny scene, up to `plan`)."""
    tmp = tmp_path_factory.mktemp("dashboard")
    specs = tmp / "specs"
    write_tiny_spec(specs, SCENE, prompt="a lighthouse on a rocky shore")
    with prefect_server(tmp) as (proc, port, api):
        r = subprocess.run(
            [sys.executable, "-m", "flows.serve", "batch", str(specs), "--out", str(tmp / "out"), "--until", "plan"],
            cwd=ROOT,
            env=prefect_env(tmp / "client-home", api),
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert r.returncode == 0, r.stderr[-3000:]
        (run,) = flow_runs(api, flow_runs={"name": {"any_": [SCENE]}})
        assert run["state_type"] == "COMPLETED"
        yield {"proc": proc, "port": port, "api": api, "run": run, "ui": f"http://127.0.0.1:{port}"}


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk."""
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    return struct.unpack(">II", head[16:24])


def test_prefect_ui_lists_the_finished_run_with_its_tasks_and_logs(finished_run: dict[str, Any], tmp_path: Path):
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        if os.environ.get("WONDERVERSE_ALLOW_NO_BROWSER") == "1":
            pytest.skip("playwright is not installed")
        pytest.fail("the playwright package is missing: pip install playwright")
    ui, run = finished_run["ui"], finished_run["run"]
    with sync_playwright() as pw:
        browser = launch_browser(pw)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(f"{ui}/runs")
            page.get_by_text(SCENE, exact=True).first.wait_for(timeout=90_000)  # the run is listed
            page.get_by_text("Completed").first.wait_for(timeout=30_000)
            page.screenshot(path=tmp_path / "runs.png", full_page=True)

            # the run's own page: its task run (the `plan` step) and its logs, as sent by the run
            page.goto(f"{ui}/runs/flow-run/{run['id']}")
            page.get_by_text("Finished in state Completed()").first.wait_for(timeout=90_000)
            page.get_by_text("plan-", exact=False).first.wait_for(timeout=30_000)
            body = page.inner_text("body")
            page.screenshot(path=tmp_path / "run.png", full_page=True)
        finally:
            browser.close()
    assert SCENE in body and "generate" in body  # run name and flow name
    assert not errors, errors
    for shot in ("runs.png", "run.png"):
        width, height = png_size(tmp_path / shot)
        assert width == 1400 and height >= 900, (shot, width, height)
        assert (tmp_path / shot).stat().st_size > 30_000, shot  # a rendered page, not a blank one


def _listening(pid: int, port: int) -> list[str]:
    """The addresses on which `pid` or its children listen on `port`."""
    procs = [psutil.Process(pid), *psutil.Process(pid).children(recursive=True)]
    return [
        c.laddr.ip
        for p in procs
        for c in p.net_connections(kind="inet")
        if c.status == psutil.CONN_LISTEN and c.laddr.port == port
    ]


def test_prefect_server_listens_on_loopback_only(finished_run: dict[str, Any]):
    port = finished_run["port"]
    assert _listening(finished_run["proc"].pid, port) == ["127.0.0.1"]
    others = [
        a.address
        for addrs in psutil.net_if_addrs().values()
        for a in addrs
        if a.family == socket.AF_INET and not a.address.startswith("127.")
    ]
    for ip in others:  # the machine's other addresses refuse the port
        with socket.socket() as s, pytest.raises(OSError):
            s.settimeout(3)
            s.connect((ip, port))
