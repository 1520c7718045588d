"""Guided flows: with a video model that takes guides, each extension is generated from what its
parent already shows (its checked frames placed in the plan's world), so branches run generate -> check ->
geometry -> children inside generate_segments. Checked against the procedural ground truth: the guides' coverage
and error, the geometry's poses and depth; keys chain so that nothing runs twice and a changed parent regenerates
its extensions; unguided flows keep their keys and do not check early; bad input is one line, exit 2."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from conftest import run_cli, tiny_config

from flows.extend import extension_config
from flows.pipeline import execute, run_pipeline
from tasks import STEPS, attempts, step_keys
from tasks import generate_segments as gs
from tasks.plan import load_plan
from wonderverse.camera import camera_centers
from wonderverse.config import RunConfig, build_config, deep_merge
from wonderverse.errors import ConfigError, WonderError
from wonderverse.planning.paths import stitched_frame_index
from wonderverse.store import SceneStore, cache_key
from wonderverse.video import make_video_model
from wonderverse.video.base import Guide

PROMPT = "a small house decorated for Christmas"
# 160x112, 9 frames: the smallest size at which the check's SfM of these moves passes and places every segment
GUIDED_VIDEO = {
    "width": 160,
    "height": 112,
    "frames_per_segment": 9,
    "options": {"fault_probability": 0.0, "accept_guide": True},
}
# Settings of steps.generate_segments other than the defaults, which must reach the flow: guides for splats only
# (so the frames' guides are as with the defaults) and a placement tolerance every segment here is well within.
GUIDE_SETTINGS = {"splat_min_alpha": 0.4}
GEOMETRY_SETTINGS = {"max_fit_rms_rel": 0.25}
GUIDED: dict[str, Any] = {
    "preset": "preview",
    "scene": {"prompt": PROMPT, "video": GUIDED_VIDEO},
    "steps": {
        "plan": {"yaw_step_deg": 30.0},
        "check": {"max_attempts": 1},
        "generate_segments": {"guide": GUIDE_SETTINGS, "geometry": GEOMETRY_SETTINGS},
    },
    "execution": {"segment_workers": 2},  # the wave of two extensions is checked on a Dask LocalCluster
}


def spec_file(folder: Path, name: str, data: dict[str, Any]) -> Path:
    f = folder / f"{name}.yaml"
    f.write_text(yaml.safe_dump(data))
    return f


def one_error_line(r: Any) -> str:
    """The one `error:` line of a run that failed in a step (after the step lines), exit 2, no traceback."""
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error")]
    assert r.returncode == 2 and len(errors) == 1, r.stderr[-3000:]
    assert "Traceback" not in r.stderr and r.stderr.rstrip().endswith(errors[0]), r.stderr[-3000:]
    return errors[0]


@pytest.fixture(scope="module")
def guided(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """A guided 3-segment scene (initial, left, right) made through the command line up to the check."""
    folder = tmp_path_factory.mktemp("guided")
    config = spec_file(folder, "guided", GUIDED)
    scene = folder / "scene"
    r = run_cli("generate", "--config", str(config), "--out", str(scene), "--until", "check", "--engine", "local")
    assert r.returncode == 0, r.stderr[-3000:]
    return scene, config, r.stderr


def config_of(config: Path) -> RunConfig:
    return build_config(config_file=config)


@pytest.mark.e2e
def test_each_extension_is_generated_from_its_parents_guide(guided: tuple[Path, Path, str]) -> None:
    scene, _, _ = guided
    store = SceneStore.open(scene)
    assert store.children("segments") == ["s000", "s001", "s002"]
    # the initial segment continues from nothing
    assert store.meta("segments/s000/attempts/0", complete=False).guide is None
    parent_geometry = store.cache_key_of("segments/s000/geometry")
    for seg in ("s001", "s002"):
        a = store.meta(f"segments/{seg}")
        assert a.reference_segment == "s000" and a.guide_geometry_key == parent_geometry
        record = store.meta(f"segments/{seg}/attempts/0", complete=False).guide
        assert record.source == "segment s000, attempt 0" and record.geometry_key == parent_geometry
        truth = store.meta(f"segments/{seg}/attempts/0/gt", complete=False).guide  # measured by the procedural backend
        assert truth.coverage == pytest.approx(record.coverage)
        assert truth.coverage > 0.3, (seg, truth)  # a 30 deg turn keeps most of what the parent shows
        assert truth.psnr_db > 20.0, (seg, truth)  # measured 22.1 (left) and 21.0 (right)
        assert truth.depth_absrel < 0.3, (seg, truth)
        # the guided model kept the known pixels: frame 0 is (nearly) the parent's reference frame again
        ref = store.array("segments/s000/attempts/0/frames")[a.reference_frame].astype(int)
        first = store.array(f"segments/{seg}/attempts/0/frames")[0].astype(int)
        assert np.abs(first - ref).mean() < 8.0


@pytest.mark.e2e
def test_the_guide_and_geometry_settings_come_from_the_config(guided: tuple[Path, Path, str]) -> None:
    from tasks.segment_geometry import depth_settings, geometry_key
    from wonderverse.guide import GuideParams
    from wonderverse.segment_geometry import GeometryParams

    scene, config, _ = guided
    cfg = config_of(config)
    store = SceneStore.open(scene)
    guide = GuideParams(depth_tol_rel=0.15, **GUIDE_SETTINGS)  # the flow's default depth tolerance, kept
    for seg in ("s001", "s002"):
        assert store.meta(f"segments/{seg}").guide_params == guide.model_dump(mode="json")
    accepted = store.cache_key_of("segments/s000/accepted")
    frames = store.array("segments/s000/attempts/0/frames")
    placed_by = GeometryParams(**GEOMETRY_SETTINGS)
    key = geometry_key(accepted, 0, frames, depth_settings(cfg.steps.priors), placed_by)
    assert store.cache_key_of("segments/s000/geometry") == key


def test_a_default_config_keeps_the_keys_made_before_the_settings_existed() -> None:
    """The guided flow's key as it was computed with the guide and geometry settings fixed in code."""
    from tasks.segment_geometry import depth_settings
    from wonderverse.guide import GuideParams
    from wonderverse.segment_geometry import GeometryParams

    cfg = build_config(PROMPT, preset="preview", overrides={"scene": {"video": GUIDED_VIDEO}})
    p = gs.params(cfg)
    assert isinstance(p, gs.GuidedParams)
    old = {
        "source": cfg.scene.video_source,
        "strafe_m_per_deg": cfg.steps.plan.strafe_m_per_deg,
        "check": cfg.steps.check,
        "depth": depth_settings(cfg.steps.priors),
        "geometry": GeometryParams(),
        "guide": GuideParams(depth_tol_rel=0.15),
    }
    keys = step_keys(STEPS, cfg)
    assert keys["generate_segments"] == cache_key("generate_segments", 2, old, [keys["plan"]])
    # a setting of steps.generate_segments changes a guided flow's key and no unguided one's
    over = {"steps": {"generate_segments": {"guide": {"frame_stride": 2}}}}
    changed = build_config(PROMPT, preset="preview", overrides=deep_merge(over, {"scene": {"video": GUIDED_VIDEO}}))
    assert gs.params(changed).guide.frame_stride == 2  # type: ignore[attr-defined]
    assert step_keys(STEPS, changed)["generate_segments"] != keys["generate_segments"]
    unguided = tiny_config()
    assert step_keys(STEPS, unguided) == step_keys(STEPS, unguided.model_copy(update={"steps": changed.steps}))


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ({"guide": {"depth_tol": 0.1}}, r"steps\.generate_segments\.guide\.depth_tol: unknown setting"),
        (
            {"geometry": {"max_fit_rms_rel": 0}},
            r"generate_segments\.geometry\.max_fit_rms_rel: .*greater than 0",
        ),
        (
            {"guide": {"frame_stride": 0}},
            r"generate_segments\.guide\.frame_stride: .*greater than or equal to 1",
        ),
        ({"mask": True}, r"steps\.generate_segments\.mask: unknown setting"),
    ],
)
def test_bad_guide_settings_are_refused_naming_the_setting(setting: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        build_config(PROMPT, preset="preview", overrides={"steps": {"generate_segments": setting}})


@pytest.mark.e2e
def test_segments_are_checked_and_placed_inside_generate_segments(guided: tuple[Path, Path, str]) -> None:
    scene, _, stderr = guided
    assert "checked and placed" in stderr and "3 segments (3 cached)" in stderr, stderr[-3000:]
    store = SceneStore.open(scene)
    for seg in ("s000", "s001", "s002"):
        assert store.meta(f"segments/{seg}/accepted").attempt == 0
        g = store.meta(f"segments/{seg}/geometry")
        assert g.placed and g.registered_frames == 9, (seg, g)
        # the plan is the truth for a fault-free procedural segment: the placed poses and depth are the world's
        gt = f"segments/{seg}/attempts/0/gt"
        poses, true_poses = store.array(f"segments/{seg}/geometry/poses"), store.array(f"{gt}/poses")
        length = np.linalg.norm(np.diff(camera_centers(true_poses), axis=0), axis=1).sum()
        off = np.linalg.norm(camera_centers(poses) - camera_centers(true_poses), axis=1)
        assert off.max() < 0.1 * length, (seg, off, length)
        depth, true_depth = store.array(f"segments/{seg}/geometry/depth"), store.array(f"{gt}/depth")
        both = np.isfinite(depth) & np.isfinite(true_depth)
        # median AbsRel measured 0.06-0.18: the "realistic" oracle's own error and the bias of a short clip's SfM
        assert np.median(np.abs(depth[both] - true_depth[both]) / true_depth[both]) < 0.25, seg


@pytest.mark.e2e
def test_inspect_and_the_report_show_the_guide_of_each_extension(guided: tuple[Path, Path, str]) -> None:
    """Per attempt: where its guide came from, its share of known pixels, and (procedural) its error against the
    truth; in `inspect --json`, inspect's table and the HTML report."""
    import json
    import re

    from flows.inspect import summarize
    from flows.report import gather
    from wonderverse.report import render_html

    scene, _, _ = guided
    store = SceneStore.open(scene)
    info = json.loads(json.dumps(summarize(store)))  # JSON as `inspect --json` prints it
    attempts = {s["id"]: s["attempts"] for s in info["segments"]}
    assert attempts["s000"][0]["guide"] is None  # the initial segment looks for no guide
    coverage = {}
    for seg in ("s001", "s002"):
        shown = attempts[seg][0]["guide"]
        truth = store.meta(f"segments/{seg}/attempts/0/gt", complete=False).guide
        assert shown["source"] == "segment s000, attempt 0" and shown["reason"] == ""
        assert shown["coverage"] == pytest.approx(truth.coverage) and 0.3 < shown["coverage"] < 1.0
        assert shown["truth"]["psnr_db"] == pytest.approx(truth.psnr_db)
        assert shown["truth"]["depth_absrel"] == pytest.approx(truth.depth_absrel)
        coverage[seg] = shown["coverage"]

    r = run_cli("inspect", str(scene))
    assert r.returncode == 0, r.stderr
    assert "guide known" in r.stdout
    rows = {ln.split()[1]: ln for ln in r.stdout.splitlines() if re.match(r"^\W+s00\d\b", ln)}  # table rows
    for seg, c in coverage.items():
        assert f"{100 * c:.0f} %" in rows[seg], rows[seg]
    assert " - " in rows["s000"].split(" ok ", 1)[1], rows["s000"]  # no guide for the initial segment

    html = render_html(gather(store))
    for seg, c in coverage.items():
        row = re.search(rf'<tr id="{seg}-a0">(.*?)</tr>', html, re.S)
        assert row and f"{100 * c:.0f} % of pixels known, from segment s000, attempt 0" in row.group(1), seg
    mean = 100 * (coverage["s001"] + coverage["s002"]) / 2
    summary = re.search(r"Guided extensions</h3>(.*?)</table>", html, re.S)
    assert summary and "2 of 2" in summary.group(1) and f"{mean:.0f} %" in summary.group(1)


def test_an_attempt_generated_without_its_guide_says_why() -> None:
    from flows.inspect import GuideInfo, guide_words

    assert guide_words(None) == "-"
    assert guide_words(GuideInfo(source=None, coverage=0.0, reason="its parent could not be placed")) == "none"
    assert guide_words(GuideInfo(source="segment s000, attempt 1", coverage=0.694)) == "69 %"
    # the report's summary over the extensions: the attempt each follows (the chosen one)
    from flows.report import _guided_extensions
    from wonderverse.report import AttemptInfo, SegmentInfo

    unguided = AttemptInfo(0, chosen=True, guide="none: its parent segment s000 could not be placed")
    guided = [AttemptInfo(0, guide="80 % of pixels known", guide_coverage=0.8)]
    guided.append(AttemptInfo(1, chosen=True, guide="60 % of pixels known", guide_coverage=0.6))
    segments = [SegmentInfo("s000", attempts=[AttemptInfo(0, chosen=True)]), SegmentInfo("s001", attempts=[unguided])]
    segments.append(SegmentInfo("s002", attempts=guided))
    assert _guided_extensions(segments) == {
        "generated from a guide": "1 of 2",
        "known pixels of their guides (mean)": "60 %",
    }
    assert _guided_extensions(segments[:1]) == {}  # an unguided scene has no such section


@pytest.mark.e2e
def test_a_rerun_renders_nothing_and_a_new_depth_setting_regenerates_the_extensions_only(
    guided: tuple[Path, Path, str], tmp_path: Path
) -> None:
    scene = tmp_path / "scene"
    shutil.copytree(guided[0], scene)
    cfg = config_of(guided[1])
    again = execute(scene, cfg, until="check")
    assert [r.status for r in again] == ["cached", "cached", "cached"]

    store = SceneStore.open(scene)
    before = {g: store.cache_key_of(g) for g in ("segments/s000", "segments/s001", "segments/s002")}
    checked = store.cache_key_of("segments/s000/accepted")
    data = {**GUIDED, "steps": {**GUIDED["steps"], "priors": {"models": {"oracle_level": "mild"}}}}
    results = execute(scene, config_of(spec_file(tmp_path, "mild", data)), until="generate_segments")
    assert results[1].status == "ran" and results[1].detail.startswith("2 rendered, 1 cached"), results[1]
    store = SceneStore.open(scene)
    assert store.cache_key_of("segments/s000") == before["segments/s000"]  # the parent is kept, checked once
    assert store.cache_key_of("segments/s000/accepted") == checked
    for seg in ("s001", "s002"):  # its geometry changed, so did what its extensions were generated from
        assert store.cache_key_of(f"segments/{seg}") not in (None, before[f"segments/{seg}"])
        assert store.meta(f"segments/{seg}").guide_geometry_key == store.cache_key_of("segments/s000/geometry")

    # a normal-prior setting places nothing differently: every segment stays as it is
    data = {**GUIDED, "steps": {**GUIDED["steps"], "priors": {"models": {"oracle_level": "mild", "oracle_seed": 0}}}}
    data["steps"]["priors"]["models"]["normal_backend"] = "oracle"
    keys = {g: SceneStore.open(scene).cache_key_of(g) for g in before}
    results = execute(scene, config_of(spec_file(tmp_path, "normals", data)), until="generate_segments")
    assert results[1].status == "cached" and keys == {g: SceneStore.open(scene).cache_key_of(g) for g in before}


@pytest.mark.e2e
def test_an_extension_gets_its_guide_from_the_parents_geometry_made_on_demand(
    guided: tuple[Path, Path, str], tmp_path: Path
) -> None:
    """`extend` goes the same way; a parent without geometry (made before guided flows) gets it when needed."""
    scene = tmp_path / "scene"
    shutil.copytree(guided[0], scene)
    store = SceneStore.open(scene, mode="r+")
    parent_key = store.cache_key_of("segments/s001/geometry")
    store.remove("segments/s001/geometry")
    kept = {s: store.cache_key_of(f"segments/{s}") for s in ("s000", "s001", "s002")}
    cfg = extension_config(scene, "look further to the left")
    results = run_pipeline(scene, cfg, until="check", engine="local", flow_name="extend")
    gen = next(r for r in results if r.step == "generate_segments")
    assert gen.detail.startswith("1 rendered, 3 cached"), gen
    store = SceneStore.open(scene)
    assert {s: store.cache_key_of(f"segments/{s}") for s in kept} == kept
    assert store.cache_key_of("segments/s001/geometry") == parent_key  # made again, the same
    a = store.meta("segments/s003")
    assert a.reference_segment == "s001" and a.guide_geometry_key == parent_key
    truth = store.meta("segments/s003/attempts/0/gt", complete=False).guide
    assert truth.coverage > 0.3 and truth.psnr_db > 18.0, truth
    assert store.cache_key_of("segments/s003/geometry") is not None  # complete: ready for the next extension


@pytest.mark.e2e
def test_an_unguided_flow_is_as_before(tmp_path: Path) -> None:
    cfg = tiny_config()
    assert "accept_guide" not in cfg.scene.video.options.model_dump()  # keys made before the option stay valid
    p = gs.params(cfg)
    assert type(p) is gs.Params
    results = execute(tmp_path / "s", cfg, until="generate_segments")
    assert results[1].detail == "3 rendered, 0 cached"
    store = SceneStore.open(tmp_path / "s")
    # the keys as they were computed before guided flows existed
    old = gs.Params(source=cfg.scene.video_source, strafe_m_per_deg=cfg.steps.plan.strafe_m_per_deg)
    keys = step_keys(STEPS, cfg)
    assert keys["generate_segments"] == cache_key("generate_segments", 2, old, [keys["plan"]])
    made: dict[str, str] = {}
    for s in load_plan(store).segments:
        parent = [made[s.reference_segment]] if s.reference_segment else []
        made[s.id] = cache_key("segment", 2, {"params": old, "segment": s}, parent)
        assert store.cache_key_of(f"segments/{s.id}") == made[s.id]
        assert not store.exists(f"segments/{s.id}/accepted") and not store.exists(f"segments/{s.id}/geometry")
        assert store.meta(f"segments/{s.id}/attempts/0", complete=False).guide is None


@pytest.mark.e2e
def test_an_extension_whose_parent_was_dropped_is_one_error_line(tmp_path: Path) -> None:
    """Under the Prefect engine (the guided scene above ran with the local one): the check runs as task runs nested
    in generate_segments', and the failure still reaches the user as one line."""
    engine = "prefect"
    video = {"width": 96, "height": 64, "frames_per_segment": 6, "options": GUIDED_VIDEO["options"]}
    # every attempt fails (any camera step exceeds 1e-9 SfM units) and a failing segment is dropped
    check = {
        "max_attempts": 1,
        "on_failure": "drop",
        "rules": {"translation_mode": "absolute", "abs_trans_thresh": 1e-9},
    }
    data = {"preset": "preview", "scene": {"prompt": PROMPT, "video": video}, "steps": {"check": check}}
    scene = tmp_path / "scene"
    env = {"PREFECT_HOME": str(tmp_path / "prefect"), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    args = ("generate", "--config", str(spec_file(tmp_path, "drop", data)), "--out", str(scene))
    r = run_cli(*args, "--until", "generate_segments", "--engine", engine, env=env)
    line = one_error_line(r)
    assert "step generate_segments failed" in line and "its parent segment s000 was dropped by the check" in line
    assert "segment s001:" in line or "segment s002:" in line, line
    store = SceneStore.open(scene)  # what was made is kept: the initial segment, its check
    assert store.meta("segments/s000/accepted").dropped is True
    assert store.array("segments/s000/attempts/0/frames").shape == (6, 64, 96, 3)


def test_a_guide_of_the_wrong_size_names_the_segment(tmp_path: Path) -> None:
    cfg = build_config(PROMPT, preset="preview", overrides={"scene": {"video": GUIDED_VIDEO}})
    source = cfg.scene.video_source
    model = make_video_model(source)
    path = np.tile(model.world.start_pose(), (9, 1, 1))  # type: ignore[attr-defined]
    small = Guide(np.zeros((9, 56, 80, 3), np.uint8), np.ones((9, 56, 80), bool), np.full((9, 56, 80), np.inf))
    with pytest.raises(
        WonderError, match=r"^segment s001: guide frames is 80x56, 9 frames but the video is 160x112"
    ) as e:
        attempts._render(source, model, "s001", 0, "left", "", path, None, small)
    assert "\n" not in str(e.value)
    with pytest.raises(WonderError, match=r"guide frames is 80x56"):  # the backend refuses it on its own too
        model.generate("", path, 0, None, guide=small)


@pytest.mark.e2e
def test_a_guided_family_without_a_mask_capable_pipeline_is_one_error_line(tmp_path: Path) -> None:
    """The guided family's weights are a pipeline that takes no mask (a plain Wan text-to-video folder)."""
    pytest.importorskip("diffusers")
    import importlib.util

    if importlib.util.find_spec("ftfy") is None:
        pytest.skip("diffusers' Wan pipelines need ftfy")
    from tiny_diffusers import plain_wan_as_guided

    data = plain_wan_as_guided(tmp_path / "wan-t2v", PROMPT)
    scene = tmp_path / "scene"
    args = ("generate", "--config", str(spec_file(tmp_path, "wan", data)), "--out", str(scene))
    line = one_error_line(run_cli(*args, "--until", "check", "--engine", "local"))
    assert "segment s000: video.options.guided_model: " in line and "holds a WanPipeline, not a WanVACEPipeline" in line
    assert "mask-capable" in line
    assert SceneStore.open(scene).cache_key_of("plan") is not None  # the plan made before stays


def test_the_reference_frame_is_lifted_last() -> None:
    from wonderverse.segment_geometry import lift_order

    registered = np.array([True, True, False, True, True])
    assert lift_order(registered, 4).tolist() == [0, 1, 3, 4]
    assert lift_order(registered, 0).tolist() == [4, 3, 1, 0]
    assert lift_order(registered, stitched_frame_index(True, 5, "last"))[-1] == 0


def test_sfm_to_plan_recovers_a_similarity_even_on_a_straight_path() -> None:
    """Collinear camera centres (a straight move) leave Umeyama's rotation undetermined; the orientations fix it."""
    from wonderverse.camera import Sim3, look_at, so3_exp
    from wonderverse.segment_geometry import sfm_to_plan

    yaw = np.radians(np.linspace(0.0, 30.0, 9))
    eyes = np.stack([np.zeros(9), np.linspace(0.0, 2.0, 9), np.full(9, 3.0)], axis=1)
    plan = np.stack([look_at(e, e + np.array([np.sin(a), np.cos(a), -0.1])) for e, a in zip(eyes, yaw, strict=True)])
    plan_to_sfm = Sim3(0.25, so3_exp(np.array([0.3, -0.2, 1.0])), np.array([5.0, -2.0, 1.0]))
    sfm = plan_to_sfm.transform_w2c(plan)
    registered = np.ones(9, bool)
    sfm[3], registered[3] = np.nan, False  # an unregistered frame is left out
    sim, rms = sfm_to_plan(sfm, plan, registered)
    assert sim.s == pytest.approx(4.0) and rms < 1e-9
    np.testing.assert_allclose(sim.transform_w2c(sfm[registered]), plan[registered], atol=1e-9)
    with pytest.raises(ValueError, match="does not move"):
        sfm_to_plan(np.tile(sfm[0], (9, 1, 1)), plan, np.ones(9, bool))
    with pytest.raises(ValueError, match="at least 2"):
        sfm_to_plan(sfm, plan, np.eye(1, 9, 0, dtype=bool)[0])


def test_fusing_neighbouring_frames_removes_independent_depth_noise() -> None:
    from wonderverse.camera import intrinsics, look_at
    from wonderverse.segment_geometry import fuse_depth

    T, H, W = 7, 48, 64
    pose = look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]))
    w2c = np.tile(pose, (T, 1, 1))  # one viewpoint: every frame sees the same wall at 10 units
    noisy = (10.0 * np.exp(np.random.default_rng(0).normal(0.0, 0.1, (T, H, W)))).astype(np.float32)
    noisy[:, :5] = np.inf  # a band of sky stays sky
    fused = fuse_depth(noisy, w2c, intrinsics(W, H, 60.0), np.ones(T, bool), neighbours=3)
    solid = np.isfinite(noisy)
    assert np.isposinf(fused[~solid]).all()
    before, after = np.abs(noisy[solid] - 10.0).mean(), np.abs(fused[solid] - 10.0).mean()
    assert after < 0.7 * before, (before, after)
    np.testing.assert_array_equal(fuse_depth(noisy, w2c, intrinsics(W, H, 60.0), np.ones(T, bool), 0), noisy)


@pytest.mark.e2e
def test_a_guided_flow_without_a_depth_model_is_refused_before_any_segment(tmp_path: Path) -> None:
    overrides = {
        "scene": {"video": GUIDED_VIDEO},
        "steps": {"priors": {"models": {"depth_backend": "none", "normal_backend": "none"}}},
    }
    cfg = build_config(PROMPT, preset="preview", overrides=overrides)
    with pytest.raises(WonderError, match=r"set steps\.priors\.models\.depth_backend"):
        execute(tmp_path / "s", cfg, until="generate_segments")
    assert SceneStore.open(tmp_path / "s").children("segments") == []
