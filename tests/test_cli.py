"""The CLI as users meet it: bad input is one line and exit code 2, losing nothing; inspect and
preview read a real scene; the Prefect engine runs the same flow."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import imageio.v2 as imageio
import pytest
import yaml
from conftest import TINY_VIDEO, run_cli, tiny_config, tree_digest
from PIL import Image

from flows.pipeline import execute
from wonderverse import STORE_FORMAT
from wonderverse.store import SceneStore

pytestmark = pytest.mark.e2e  # the CLI in a subprocess, over scenes it generates


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("cli") / "scene"
    execute(d, tiny_config(), until="generate_segments")
    return d


def tiny_file(tmp_path: Path, **scene) -> Path:
    f = tmp_path / "tiny.yaml"
    video = {**TINY_VIDEO, "options": {"fault_probability": 0.0}, **scene.pop("video", {})}
    f.write_text(yaml.safe_dump({"preset": "preview", "scene": {"video": video, **scene}}))
    return f


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["generate", ""], "scene.prompt: prompt is empty"),
        (["generate", "x" * 10_000], "prompt has 10000 characters"),
        (["generate", "a forest", "--preset", "turbo"], "unknown preset 'turbo'"),
        (["generate", "a forest", "--until", "nope"], "unknown step 'nope'"),
        (["generate", "a forest", "--engine", "warp"], "--engine must be auto, prefect or local"),
        (["inspect", "/nonexistent/scene"], "holds no scene store"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, message):
    r = run_cli(*args)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], r.stderr


def test_bad_config_files_and_folders_lose_nothing(tmp_path: Path, scene: Path):
    before = tree_digest(scene)
    malformed = tmp_path / "bad.yaml"
    malformed.write_text("scene: {prompt: [oops\n")
    negative = tiny_file(tmp_path, prompt="ok", video={"frames_per_segment": -5})
    cases = [
        (["generate", "--config", str(malformed), "--out", str(scene)], "malformed YAML"),
        (["generate", "--config", str(negative), "--out", str(scene)], "frames_per_segment"),
        (["generate", "", "--out", str(scene)], "prompt is empty"),
    ]
    for args, message in cases:
        r = run_cli(*args)
        assert r.returncode == 2 and message in r.stderr, r.stderr
    assert tree_digest(scene) == before

    blocker = tmp_path / "file"
    blocker.write_text("x")
    r = run_cli("generate", "a forest", "--out", str(blocker / "scene"), "--config", str(tiny_file(tmp_path)))
    assert r.returncode == 2 and "cannot write to output folder" in r.stderr, r.stderr


def test_store_from_a_newer_version_is_refused_untouched(tmp_path: Path):
    d = tmp_path / "future"
    execute(d, tiny_config(), until="generate_segments")
    SceneStore.open(d, mode="r+").root.attrs["format"] = STORE_FORMAT + 1
    before = tree_digest(d)
    for args in (
        ["inspect", str(d)],
        ["generate", "--config", str(tiny_file(tmp_path, prompt="p")), "--out", str(d), "--engine", "local"],
    ):
        r = run_cli(*args)
        assert r.returncode == 2 and "newer WonderVerse" in r.stderr, r.stderr
    assert tree_digest(d) == before


def test_inspect_json_and_preview(scene: Path):
    r = run_cli("inspect", str(scene), "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    status = {s["name"]: s["status"] for s in info["steps"]}
    assert status == {
        "plan": "complete",
        "generate_segments": "complete",
        "check": "missing",
        "poses": "missing",
        "priors": "missing",
        "splats": "missing",
        "outputs": "missing",
    }
    assert all(len(s["cache_key"]) == 64 for s in info["steps"] if s["status"] == "complete")
    assert len(info["segments"]) == 3 and info["spec"]["prompt"].startswith("a small house")
    seg = info["segments"][0]
    assert seg["attempts"][0]["arrays"]["frames"]["shape"] == [6, 64, 96, 3]
    assert seg["attempts"][0]["arrays"]["gt/depth"]["dtype"] == "float32"
    assert info["size_bytes"] > 0

    r = run_cli("inspect", str(scene))
    assert r.returncode == 0 and "generate_segments" in r.stdout and "s000" in r.stdout

    r = run_cli("preview", str(scene))
    assert r.returncode == 0, r.stderr
    with imageio.get_reader(scene / "preview.mp4") as reader:
        frames = list(reader.iter_data())
    assert len(frames) == 16 and frames[0].shape == (64, 96, 3)
    assert Image.open(scene / "contact_sheet.png").size[0] > 100


def prefect_task_runs(home: Path) -> dict[str, str]:
    """{task run name: state name} from the Prefect database that an ephemeral-API run left in `home`."""
    with sqlite3.connect(home / "prefect.db") as db:
        return dict(db.execute("SELECT name, state_name FROM task_run").fetchall())


def test_generate_through_prefect_engine(tmp_path: Path):
    """`--engine prefect`: a real Prefect flow (ephemeral local API, no server to start) whose task runs are the
    steps and, nested in them, one per segment; a re-run records the steps as cached."""
    home = tmp_path / "prefect"
    env = {"PREFECT_HOME": str(home), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    cfg = tiny_file(tmp_path, prompt="a cosy reading room with shelves", extensions={"directions": ["left"]})
    args = ("generate", "--config", str(cfg), "--out", str(tmp_path / "s"), "--until", "check", "--engine", "prefect")
    r = run_cli(*args, env=env, timeout=400)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "generate_segments" in r.stderr and "ran" in r.stderr
    store = SceneStore.open(tmp_path / "s")
    assert store.children("segments") == ["s000", "s001"]
    runs = prefect_task_runs(home)
    per_segment = {f"{step} {seg}" for step in ("generate_segments", "check") for seg in ("s000", "s001")}
    assert per_segment <= set(runs), sorted(runs)
    assert {runs[name] for name in per_segment} == {"Completed"}
    steps = {name.rsplit("-", 1)[0] for name in set(runs) - per_segment}  # step task runs: '<step>-<3 hex>'
    assert steps == {"plan", "generate_segments", "check"}, sorted(runs)

    r = run_cli(*args, env=env, timeout=400)
    assert r.returncode == 0 and r.stderr.count("cached") >= 3, r.stderr[-3000:]
    cached = {name for name, state in prefect_task_runs(home).items() if state == "Cached"}
    assert cached == {"plan", "generate_segments", "check"}  # recorded as cached, nothing per segment re-ran


def test_generate_ends_with_the_outputs_and_the_report(tmp_path: Path):
    d = tmp_path / "full"
    cfg = tiny_file(tmp_path, prompt="a snowy mountain cabin", extensions={"rounds": 0})
    r = run_cli("generate", "--config", str(cfg), "--out", str(d), "--engine", "local", timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    for name in ("mesh.ply", "mesh.glb", "points.ply", "flythrough.mp4", "novel.mp4", "report.html"):
        assert str(d / name) in r.stdout and (d / name).stat().st_size > 0, name


def test_report_command(scene: Path, tmp_path: Path):
    r = run_cli("report", str(scene))
    assert r.returncode == 0 and (scene / "report.html").stat().st_size > 1000, r.stderr
    r = run_cli("report", str(tmp_path / "nothing-here"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and r.stderr.startswith("error:"), r.stderr
