"""`wonderverse reconstruct` as users run it: real footage from ../shared/data reconstructs to outputs with no model
weights, a real capture's skipped frames are flagged and kept, and every bad clip is one `error:` line naming it,
exit 2, with no scene folder made. A step that fails is one `error:` line under either engine."""

from __future__ import annotations

import html
import json
import os
import re
import subprocess
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
import yaml
from conftest import TINY_VIDEO, run_cli
from plyfile import PlyData

from flows.pipeline import stored_config
from flows.progress import JSON_PREFIX

pytestmark = pytest.mark.e2e  # the CLI in a subprocess


RE10K_CLIP = "cameractrl_re10k/reference_videos/0bf152ef84195293.mp4"


def error_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.startswith("error:")]


@pytest.fixture(scope="module")
def bad_clips(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bad")
    (d / "notvideo.mp4").write_text("hello")
    (d / "empty.mp4").write_bytes(b"")
    with imageio.get_writer(d / "one.mp4", fps=8) as w:
        w.append_data(np.zeros((64, 96, 3), np.uint8))
    os.symlink(d / "loop2", d / "loop1")
    os.symlink(d / "loop1", d / "loop2")
    mixed = d / "mixed"
    mixed.mkdir()
    for i, (w, h) in enumerate([(96, 64), (96, 64), (128, 64)]):
        imageio.imwrite(mixed / f"f{i}.png", np.full((h, w, 3), 40 * i, np.uint8))
    return {p.name: p for p in d.iterdir()} | {"/dev/zero": Path("/dev/zero")}


@pytest.mark.parametrize(
    ("clip", "extra", "message"),
    [
        ("notvideo.mp4", [], "notvideo.mp4: cannot read video"),
        ("empty.mp4", [], "empty.mp4: cannot read video"),
        ("one.mp4", [], "one.mp4: only 1 frame"),
        ("loop1", [], "loop1: cannot be read (Symlink loop"),
        ("/dev/zero", [], "/dev/zero: not a video file"),
        ("mixed", [], "f2.png: image is 128x64 but the clip's first frame f0.png is 96x64"),  # refused, not resized
        ("one.mp4", ["--fov-deg", "nan"], "scene.video.options.fov_deg"),
        ("one.mp4", ["--fov-deg", "-5"], "scene.video.options.fov_deg"),
        ("one.mp4", ["--shutter", "2"], "steps.splats.train.motion_blur_shutter"),
        ("one.mp4", ["--depth-model", "/nonexistent/da"], "--depth-model /nonexistent/da: no such folder"),
    ],
)
def test_a_bad_clip_is_one_line_naming_it_and_makes_no_scene(bad_clips, tmp_path, clip, extra, message):
    out = tmp_path / "scene"
    r = run_cli("reconstruct", str(bad_clips[clip]), *extra, "--out", str(out))
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert message in lines[0], lines[0]
    assert not out.exists()


CLASS_NAME = re.compile(r"\b[A-Z]\w*(Error|Exception|Failed)\b")  # a Python class name in a line for the user


def assert_failure_reported(scene: Path, r: subprocess.CompletedProcess, step: str, completed: list[str]) -> None:
    """A run that stopped at `step` wrote report.html saying where and why, and `inspect` (text and JSON) says which
    steps that run completed (`ran_then_failed`), which failed and which it never ran."""
    report = scene / "report.html"
    assert f"report: {report}" in r.stdout.splitlines(), r.stdout
    why = error_lines(r.stderr)[0].removeprefix(f"error: step {step} failed: ")
    text = html.unescape(report.read_text())
    assert f"The last run failed at step {step}" in text and why in text, why
    assert f"It completed {', '.join(completed)} first" in text
    info = json.loads(run_cli("inspect", str(scene), "--json").stdout)
    status = {s["name"]: s["status"] for s in info["steps"]}
    assert [n for n, v in status.items() if v == "ran_then_failed"] == completed, status
    assert status[step] == "failed" and status["outputs"] == "missing", status
    shown = run_cli("inspect", str(scene)).stdout
    assert "ran, then the run failed" in shown and "not run" in shown
    assert f"last run failed at step {step}" in " ".join(shown.split()), shown


def test_a_failed_step_is_one_error_line_under_either_engine(tmp_path):
    """A segment failing its check with on_failure=fail: the step raises a WonderError; the user sees the step
    lines and exactly one `error:` line, no traceback, no class name, exit 2 (Prefect's own logs stay in its UI);
    report.html says where and why, and `inspect` tells the steps that run completed from those it never ran."""
    spec = tmp_path / "fail.yaml"
    video = {**TINY_VIDEO, "options": {"fault_probability": 1.0}}
    steps = {"check": {"max_attempts": 1, "on_failure": "fail"}}
    spec.write_text(yaml.safe_dump({"preset": "preview", "scene": {"prompt": "a quiet forest lake", "video": video},
                                    "steps": steps}))  # fmt: skip
    env = {"PREFECT_HOME": str(tmp_path / "prefect"), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    for engine in ("local", "prefect"):
        args = ("generate", "--config", str(spec), "--out", str(tmp_path / f"scene-{engine}"), "--until", "check")
        r = run_cli(*args, "--engine", engine, env=env, timeout=400)
        errors = error_lines(r.stderr)
        assert r.returncode == 2 and len(errors) == 1, r.stderr[-3000:]
        assert "step check failed" in errors[0] and "failed all 1 attempts" in errors[0]
        assert "Traceback" not in r.stderr and r.stderr.rstrip().endswith(errors[0])
        assert not CLASS_NAME.search(errors[0]), errors[0]
        assert_failure_reported(tmp_path / f"scene-{engine}", r, "check", ["plan", "generate_segments"])


def test_a_real_estate_clip_reconstructs_to_outputs_with_no_weights(data_dir: Path, tmp_path: Path):
    out = tmp_path / "scene"
    # a phone-like walkthrough, its motion blur modelled (a 180° shutter)
    r = run_cli(
        "reconstruct", str(data_dir / RE10K_CLIP), "--out", str(out), "--preset", "preview", "--shutter", "0.5",
        timeout=900,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert stored_config(out).steps.splats.train.motion_blur_shutter == 0.5
    assert "priors: none (no depth model named)" in r.stderr
    for name in ("splats.ply", "mesh.ply", "mesh.glb", "points.ply", "novel.mp4", "report.html"):
        assert (out / name).stat().st_size > 0, name
    assert PlyData.read(str(out / "splats.ply"))["vertex"].count > 500
    info = json.loads(run_cli("inspect", str(out), "--json").stdout)
    assert {s["name"]: s["status"] for s in info["steps"]}["outputs"] == "complete"
    assert info["segments"][0]["attempts"][0]["check"]["accepted"] is True  # a real walkthrough passes its check


def test_the_fox_captures_real_jump_is_flagged_and_kept(data_dir: Path, tmp_path: Path):
    """The fox images skip frames 0055-0071 (a 44° jump): the check flags it and, a clip not being regenerable,
    keeps the clip with the reasons (keep_best)."""
    out = tmp_path / "fox"
    r = run_cli("reconstruct", str(data_dir / "instant_ngp_fox/images"), "--out", str(out), "--until", "check",
                timeout=900)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    seg = json.loads(run_cli("inspect", str(out), "--json").stdout)["segments"][0]
    check = seg["attempts"][0]["check"]
    assert seg["accepted_attempt"] == 0 and check["accepted"] is False
    assert any("jump" in reason for reason in check["reasons"]), check["reasons"]


def test_a_near_static_ai_clip_stops_in_one_line_for_too_little_parallax(data_dir: Path, tmp_path: Path):
    """A CogVideoX clip whose camera barely turns (SOURCE.md: near-static): the check keeps it with a parallax
    reason (not a jump), and the global solve stops in one line saying why, before any mapper runs twice."""
    clip = data_dir / "cogvideox_samples" / "cogvideox2b_gallery_4.mp4"
    if not clip.is_file():
        pytest.skip(f"{clip} is absent")
    out = tmp_path / "static"
    r = run_cli("reconstruct", str(clip), "--out", str(out), "--engine", "local", timeout=600)
    errors = error_lines(r.stderr)
    assert r.returncode == 2 and len(errors) == 1, r.stderr[-3000:]
    assert "step poses failed" in errors[0] and "too little parallax" in errors[0], errors[0]
    info = json.loads(run_cli("inspect", str(out), "--json").stdout)
    clip_row = info["clips"][0]
    assert clip_row["verdict"] == "kept_failing" and clip_row["k_source"] == "guessed", clip_row
    assert len(clip_row["reasons"]) == 1 and clip_row["reasons"][0].startswith("too little parallax")
    assert "jump" not in clip_row["reasons"][0]


def test_a_failed_reconstruction_speaks_of_clips_and_reports_where_it_stopped(tmp_path: Path):
    """A clip no SfM can register (flat grey), with --on-failure fail: the step lines (here the studio's progress
    JSON) speak of reading and checking clips, not of planning or regenerating; the run stops at the check with one
    `error:` line and report.html; a later run that completes clears the failure."""
    flat = tmp_path / "flat"
    flat.mkdir()
    for i in range(6):
        imageio.imwrite(flat / f"{i:03d}.png", np.full((64, 96, 3), 128, np.uint8))
    out = tmp_path / "scene"
    args = ("reconstruct", str(flat), "--out", str(out), "--until", "check", "--engine", "local")
    r = run_cli(*args, "--on-failure", "fail", env={"WONDERVERSE_PROGRESS": "json"})
    assert r.returncode == 2 and len(error_lines(r.stderr)) == 1, r.stderr[-3000:]
    events = [json.loads(ln.removeprefix(JSON_PREFIX)) for ln in r.stderr.splitlines() if ln.startswith(JSON_PREFIX)]
    started = {e["step"]: e["description"] for e in events if e["event"] == "started"}
    assert started == {
        "plan": "one segment per clip, in the order given (nothing planned)",
        "generate_segments": "read every clip (nothing generated)",
        "check": "SfM check of each clip; a clip that fails it stops the run",
    }
    units = {e["unit"] for e in events if e["event"] == "progress"}
    assert units == {"clips read", "clips checked"}, units
    finished = {e["step"]: e for e in events if e["event"] == "finished"}
    assert finished["plan"]["detail"] == "1 clip, one segment each, in the order given"
    assert finished["check"]["status"] == "failed" and not CLASS_NAME.search(finished["check"]["detail"])
    assert_failure_reported(out, r, "check", ["plan", "generate_segments"])

    r = run_cli(*args)  # keep_best: the same clip is kept, warned, and the run completes
    assert r.returncode == 0, r.stderr[-3000:]
    assert "check: ran" in r.stderr and "1 clip checked: 0 passed, kept failing s000 (warned)" in r.stderr
    status = {s["name"]: s["status"] for s in json.loads(run_cli("inspect", str(out), "--json").stdout)["steps"]}
    assert status == {**dict.fromkeys(("plan", "generate_segments", "check"), "complete"),
                      **dict.fromkeys(("poses", "priors", "splats", "outputs"), "missing")}  # fmt: skip
    assert "The last run failed" not in html.unescape((out / "report.html").read_text())
