"""`wonderverse reconstruct` as users run it: real footage from ../shared/data reconstructs to outputs with no model
weights, a real capture's skipped frames are flagged and kept, and every bad clip is one `error:` line naming it,
exit 2, with no scene folder made. A step that fails is one `error:` line under either engine. A field of view given
is the K of every output (RealEstate10K's own poses and intrinsics as ground truth); a clip its check failed but the
global solve registered is `recovered`; a scene the global solve barely poses ends with a warning (--strict: exit 2)."""

from __future__ import annotations

import html
import json
import os
import re
import shutil
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
from wonderverse.store import SceneStore

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
    for i, (w, h) in enumerate([(96, 64), (128, 64)]):  # two shapes, neither the main one: refused
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
        ("mixed", [], "f1.png: image is 128x64 but the clip's first frame f0.png is 96x64"),  # refused, not resized
        ("one.mp4", ["--fov-deg", "nan"], "scene.video.options.fov_deg"),
        ("one.mp4", ["--fov-deg", "-5"], "scene.video.options.fov_deg"),
        ("one.mp4", ["--shutter", "2"], "steps.splats.train.motion_blur_shutter"),
        ("one.mp4", ["--depth-model", "/nonexistent/da"], "--depth-model /nonexistent/da: no such folder"),
        ("one.mp4", ["--intrinsics", "180,180,96"], "--intrinsics 180,180,96: four numbers FX,FY,CX,CY"),
        ("one.mp4", ["--intrinsics", "180,-1,96,64"], "scene.video.options.intrinsics"),
        ("one.mp4", ["--fov-deg", "60", "--intrinsics", "180,180,96,64"], "intrinsics or fov_deg, not both"),
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
    # inspect --json's quality: the clip's 16 frames (SOURCE.md) all posed; no ground-truth path here, and it says so
    poses, splats = info["quality"]["poses"], info["quality"]["splats"]
    assert (poses["registered"], poses["frames_used"], poses["passed"]) == (16, 16, True), poses
    assert poses["ate_frac"] is None and poses["ate_note"].startswith("not available")
    every = stored_config(out).steps.splats.train.holdout_every  # held out: views k-1, 2k-1, ... of the 16
    assert splats["held_out_views"] == (16 // every if every > 1 else 0) and splats["training_views"] > 0
    if splats["held_out_views"]:
        assert (
            splats["psnr_label"] == "held-out" and splats["held_out_psnr_db"] > 10 and 0 < splats["held_out_ssim"] < 1
        )
    assert info["global_k"]["k_source"] == "estimated" and info["global_k"]["held"] is False
    transforms = json.loads((out / "nerfstudio" / "transforms.json").read_text())  # the K inspect reports is exported
    K = np.array(info["global_k"]["K"])
    assert transforms["fl_x"] / transforms["w"] == pytest.approx(K[0, 0] / (2 * K[0, 2]), rel=1e-9)


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
    assert not CLASS_NAME.search(errors[0]), errors[0]  # was `step poses failed: WonderError: …`
    assert_failure_reported(out, r, "poses", ["plan", "generate_segments", "check"])
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
    steps = html.unescape((out / "report.html").read_text()).split('id="steps"')[1].split("</section>")[0]
    assert "no priors (no depth model named)" in steps and "on colours alone (no priors)" in steps  # as configured

    r = run_cli(*args)  # keep_best: the same clip is kept, warned, and the run completes
    assert r.returncode == 0, r.stderr[-3000:]
    assert "check: ran" in r.stderr and "1 clip checked: 0 passed, kept failing s000 (warned)" in r.stderr
    status = {s["name"]: s["status"] for s in json.loads(run_cli("inspect", str(out), "--json").stdout)["steps"]}
    assert status == {**dict.fromkeys(("plan", "generate_segments", "check"), "complete"),
                      **dict.fromkeys(("poses", "priors", "splats", "outputs"), "missing")}  # fmt: skip
    assert "The last run failed" not in html.unescape((out / "report.html").read_text())


FOV_0BF1 = 92.98  # RealEstate10K's own intrinsics for this clip (pose file: fx = 0.4748 of the width)


def _re10k_ate(scene: Path, pose_file: Path) -> float:
    """ATE (share of the path, Sim(3)-aligned) of a scene's global poses against RealEstate10K's poses of the clip."""
    from wonderverse.metrics import ate

    rows = [ln.split() for ln in pose_file.read_text().splitlines()[1:] if ln.strip()]
    gt = np.stack([np.vstack([np.array(r[7:19], float).reshape(3, 4), [0, 0, 0, 1]]) for r in rows])
    return float(ate(SceneStore.open(scene).array("sfm/poses"), gt)["rmse_frac"])


@pytest.fixture(scope="module")
def held(data_dir: Path, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """The RealEstate10K clip with its field of view given, to the poses (~16 s)."""
    out = tmp_path_factory.mktemp("fov") / "scene"
    r = run_cli("reconstruct", str(data_dir / RE10K_CLIP), "--fov-deg", str(FOV_0BF1), "--out", str(out), "--until",
                "poses", "--engine", "local", timeout=600)  # fmt: skip
    return out, r


def test_a_given_field_of_view_is_held_through_the_global_solve(held, data_dir: Path):
    """The K the user gave is the K of the global poses, exactly (refined before: 4-5 % off the FOV given), the
    poses are right against RealEstate10K's own, and `inspect` says which K the outputs use and why."""
    out, r = held
    assert r.returncode == 0, r.stderr[-3000:]
    fx = 0.5 * 384 / np.tan(np.radians(FOV_0BF1 / 2))  # 384x256 frames; 16:9 footage resized to 3:2: fy = 32/27 fx
    info = json.loads(run_cli("inspect", str(out), "--json").stdout)
    g = info["global_k"]
    np.testing.assert_allclose(g["K"], [[fx, 0, 192], [0, fx * 32 / 27, 128], [0, 0, 1]], rtol=1e-12)
    assert (g["k_source"], g["held"], g["fov_deg"]) == ("given", True, round(FOV_0BF1, 2))
    assert info["clips"][0]["fov_deg"] == g["fov_deg"]  # one field of view: the check's and the outputs'
    assert _re10k_ate(out, data_dir / "cameractrl_re10k/pose_files/0bf152ef84195293.txt") < 0.015
    text = run_cli("inspect", str(out)).stdout
    words = "the camera you gave (--fov-deg or --intrinsics), held fixed through the global solve"
    assert words in " ".join(text.split())


def test_a_full_k_given_is_held_through_the_global_solve(data_dir: Path, tmp_path: Path):
    """RealEstate10K's own K of the clip (its pose file: fx, fy, cx, cy as shares of the 384x256 frames, non-square
    pixels) given with --intrinsics: the global poses use exactly that K, and are right against its poses."""
    pose_file = data_dir / "cameractrl_re10k/pose_files/0bf152ef84195293.txt"
    row = pose_file.read_text().splitlines()[1].split()
    fx, fy, cx, cy = (float(v) * size for v, size in zip(row[1:5], (384, 256, 384, 256), strict=True))
    out = tmp_path / "scene"
    r = run_cli("reconstruct", str(data_dir / RE10K_CLIP), "--intrinsics", f"{fx},{fy},{cx},{cy}", "--out", str(out),
                "--until", "poses", "--engine", "local", timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    g = json.loads(run_cli("inspect", str(out), "--json").stdout)["global_k"]
    np.testing.assert_allclose(g["K"], [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], rtol=1e-12)
    assert (g["k_source"], g["held"]) == ("given", True)
    assert _re10k_ate(out, pose_file) < 0.015


def test_refine_intrinsics_refines_the_given_field_of_view(held, data_dir: Path, tmp_path: Path):
    """--refine-intrinsics: the global solve starts from the K given and refines it (a changed setting: the poses
    run again, the clip's check is reused)."""
    scene, _ = held
    out = tmp_path / "refined"
    shutil.copytree(scene, out)
    r = run_cli("reconstruct", str(data_dir / RE10K_CLIP), "--fov-deg", str(FOV_0BF1), "--refine-intrinsics",
                "--out", str(out), "--until", "poses", "--engine", "local", timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert re.search(r"check: cached|check.*cached", r.stderr), r.stderr[-2000:]
    g = json.loads(run_cli("inspect", str(out), "--json").stdout)["global_k"]
    assert (g["k_source"], g["held"]) == ("estimated", False) and "--refine-intrinsics" in g["reason"]
    fx = 0.5 * 384 / np.tan(np.radians(FOV_0BF1 / 2))
    assert g["K"][0][0] != pytest.approx(fx, rel=1e-6) and g["K"][0][0] == pytest.approx(fx, rel=0.1)
    assert _re10k_ate(out, data_dir / "cameractrl_re10k/pose_files/0bf152ef84195293.txt") < 0.015


def test_a_clip_its_check_failed_but_the_global_solve_registered_is_recovered(data_dir: Path, tmp_path: Path):
    """The check's SfM made too weak to register the clip (64 px, 64 features): it fails its check; the global
    solve (480 px) registers all 16 frames. The verdict is `recovered` with both figures, in inspect and the
    report."""
    spec = tmp_path / "weak.yaml"
    spec.write_text(yaml.safe_dump({"steps": {"check": {"sfm": {"max_image_size_px": 64, "max_num_features": 64}}}}))
    out = tmp_path / "scene"
    r = run_cli("reconstruct", str(data_dir / RE10K_CLIP), "--config", str(spec), "--out", str(out), "--until",
                "poses", "--engine", "local", timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    clip = json.loads(run_cli("inspect", str(out), "--json").stdout)["clips"][0]
    check_registered = int(SceneStore.open(out).array("segments/s000/attempts/0/sfm/registered").sum())
    assert check_registered < 13 and clip["check_registered"] == [check_registered, 16]  # under 80 %: failed
    assert clip["poses_registered"] == [16, 16] and clip["verdict"] == "recovered" and clip["reasons"], clip
    text = " ".join(run_cli("inspect", str(out)).stdout.split())
    assert f"recovered: its check registered {check_registered} of 16 frames, the global solve 16 of 16" in text
    report = " ".join(re.sub(r"<[^>]+>", " ", html.unescape((out / "report.html").read_text())).split())
    assert "recovered by the global solve (its check failed)" in report
    assert f"(check {check_registered} of 16 frames registered, global solve 16 of 16)" in report


def test_a_scene_the_global_solve_barely_poses_ends_with_a_warning_and_strict_refuses_it(data_dir, tmp_path):
    """Six photos (every third frame of the clip): at most 6 views can register, under the gates' 8. The run ends
    with one closing `warning:` line naming the figures, exit 0; with --strict, one `error:` line instead, exit 2."""
    frames = imageio.mimread(data_dir / RE10K_CLIP)
    photos = tmp_path / "six"
    photos.mkdir()
    for j, i in enumerate(range(0, 16, 3)):
        imageio.imwrite(photos / f"p{j}.png", frames[i])
    out = tmp_path / "scene"
    args = ("reconstruct", str(photos), "--out", str(out), "--until", "poses", "--engine", "local")
    r = run_cli(*args, timeout=600)
    last = r.stderr.rstrip().splitlines()[-1]
    assert r.returncode == 0 and last.startswith("warning: the final camera poses fail the quality gates"), r.stderr
    n = int(SceneStore.open(out).array("sfm/registered").sum())
    assert n <= 6 and f"{n} of 6 views registered (at least 8" in last
    assert len([ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]) == 1 and not error_lines(r.stderr)
    report = " ".join(re.sub(r"<[^>]+>", " ", html.unescape((out / "report.html").read_text())).split())
    assert f"fail the quality gates: {n} of 6 views registered" in report
    assert f"FAILS the quality gates: {n} of 6 views registered" in run_cli("inspect", str(out)).stdout
    r = run_cli(*args, "--strict", timeout=600)  # every step cached: the same poses judged again
    errors = error_lines(r.stderr)
    assert r.returncode == 2 and len(errors) == 1 and r.stderr.rstrip().endswith(errors[0]), r.stderr[-2000:]
    assert f"{n} of 6 views registered" in errors[0] and "(--strict)" in errors[0]
    assert not any(ln.startswith("warning:") for ln in r.stderr.splitlines())
