"""Bad input to a guided flow through the command line under the default engine (no --engine: `auto`, which runs
locally when no Prefect server is configured): a guided family whose weights are not a mask-capable pipeline, a
guide of the wrong size, an extension whose parent has no geometry. Each is one `error:` line naming the segment,
exit code 2, and every segment stored before the failure is still there, complete and intact."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import pytest
from conftest import run_cli, tree_digest
from test_guided_flow import GUIDED_VIDEO, PROMPT, one_error_line, spec_file

from wonderverse.store import SceneStore

pytestmark = pytest.mark.e2e  # the CLI in a subprocess


SEGMENTS = ("s000", "s001", "s002")


def default_engine(tmp_path: Path, *args: str, extra_env: dict[str, str] | None = None) -> Any:
    """`wonderverse ARGS` with no --engine, no Prefect server configured (a Prefect home of its own)."""
    env = {"PREFECT_API_URL": "", "PREFECT_HOME": str(tmp_path / "prefect"), **(extra_env or {})}
    r = run_cli(*args, env=env)
    assert "--engine" not in args and ", engine local, " in r.stderr.splitlines()[0], r.stderr[:500]
    return r


def intact(store: SceneStore, seg: str) -> None:
    """Segment `seg` is complete, undamaged, and its first attempt's frames read."""
    assert store.cache_key_of(f"segments/{seg}") is not None, seg
    assert store.damage(f"segments/{seg}") == {}, seg
    assert store.array(f"segments/{seg}/attempts/0/frames").ndim == 4


def test_a_guided_family_without_a_mask_capable_pipeline_keeps_the_scene_made_before(tmp_path: Path) -> None:
    """A procedural scene, then the same scene asked of the wan_vace family whose weights are a plain Wan
    text-to-video folder: the run stops at the first segment, and the segments made before are untouched (each is
    replaced only once its new version is complete)."""
    pytest.importorskip("diffusers")
    if importlib.util.find_spec("ftfy") is None:
        pytest.skip("diffusers' Wan pipelines need ftfy")
    from tiny_diffusers import plain_wan_as_guided

    scene = tmp_path / "scene"
    video = {"width": 96, "height": 64, "frames_per_segment": 6, "options": {"fault_probability": 0.0}}
    before = {"preset": "preview", "scene": {"prompt": PROMPT, "video": video}}
    args = ("generate", "--config", str(spec_file(tmp_path, "procedural", before)), "--out", str(scene))
    r = default_engine(tmp_path, *args, "--until", "generate_segments")
    assert r.returncode == 0, r.stderr[-3000:]
    keys = {seg: SceneStore.open(scene).cache_key_of(f"segments/{seg}") for seg in SEGMENTS}
    digest = tree_digest(scene / "scene.zarr" / "segments")

    guided = plain_wan_as_guided(tmp_path / "wan-t2v", PROMPT)
    args = ("generate", "--config", str(spec_file(tmp_path, "wan", guided)), "--out", str(scene))
    # the user allows the new model to replace the segments: it fails before it has made one, so none is replaced
    line = one_error_line(default_engine(tmp_path, *args, "--until", "check", "--replace-segments"))
    assert "step generate_segments failed" in line and "segment s000: video.options.guided_model: " in line, line
    assert "holds a WanPipeline, not a WanVACEPipeline" in line and "mask-capable" in line
    store = SceneStore.open(scene)
    assert {seg: store.cache_key_of(f"segments/{seg}") for seg in SEGMENTS} == keys
    for seg in SEGMENTS:
        intact(store, seg)
    assert tree_digest(scene / "scene.zarr" / "segments") == digest


# Every guide the parent's geometry renders comes out at half the video's size (as from a renderer or a backend
# that disagrees with the configured size): no setting makes one, so the library function is replaced, in every
# process of the run, before the command starts.
HALF_SIZE_GUIDES = """
import wonderverse.segment_geometry as sg
from wonderverse.video.base import Guide

_render = sg.guide_from_geometry


def _half_size(*args, **kwargs):
    g = _render(*args, **kwargs)
    return Guide(g.frames[:, ::2, ::2], g.mask[:, ::2, ::2], g.depth[:, ::2, ::2])


sg.guide_from_geometry = _half_size
"""


def test_a_guide_of_the_wrong_size_names_the_segment_and_keeps_its_parent(tmp_path: Path) -> None:
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(HALF_SIZE_GUIDES)
    data = {
        "preset": "preview",
        "scene": {"prompt": PROMPT, "video": GUIDED_VIDEO},
        "steps": {"check": {"max_attempts": 1}},
    }
    scene = tmp_path / "scene"
    args = ("generate", "--config", str(spec_file(tmp_path, "guided", data)), "--out", str(scene), "--until", "check")
    line = one_error_line(default_engine(tmp_path, *args, extra_env={"PYTHONPATH": str(hook)}))
    assert "step generate_segments failed" in line, line
    assert "segment s001: guide frames is 80x56, 9 frames but the video is 160x112" in line, line
    store = SceneStore.open(scene)
    intact(store, "s000")  # the parent, made before the failure: generated, checked and placed
    assert store.cache_key_of("segments/s000/accepted") is not None  # complete
    assert store.meta("segments/s000/geometry").placed is True and store.damage("segments/s000/geometry") == {}
    assert store.cache_key_of("segments/s001") is None  # the extension was never committed


def test_an_extension_whose_parent_has_no_geometry_names_both_and_keeps_the_parent(tmp_path: Path) -> None:
    """The check drops the initial segment (every attempt fails), so its extensions have no geometry to be guided
    by. Once the check keeps it instead, the next run generates the extensions and does not render it again."""
    video = {"width": 96, "height": 64, "frames_per_segment": 6, "options": GUIDED_VIDEO["options"]}
    check = {
        "max_attempts": 1,
        "on_failure": "drop",
        "rules": {"translation_mode": "absolute", "abs_trans_thresh": 1e-9},
    }
    data: dict[str, Any] = {"preset": "preview", "scene": {"prompt": PROMPT, "video": video}, "steps": {"check": check}}
    scene = tmp_path / "scene"
    args = ("generate", "--config", str(spec_file(tmp_path, "drop", data)), "--out", str(scene), "--until", "check")
    line = one_error_line(default_engine(tmp_path, *args))
    assert "step generate_segments failed" in line, line
    assert "segment s001: its parent segment s000 was dropped by the check" in line, line
    assert "so there is no geometry to guide it" in line
    store = SceneStore.open(scene)
    intact(store, "s000")
    assert store.meta("segments/s000/accepted").dropped is True
    assert store.cache_key_of("segments/s001") is None and store.cache_key_of("segments/s002") is None
    frames = store.array("segments/s000/attempts/0/frames")

    data["steps"]["check"]["on_failure"] = "keep_best"
    args = ("generate", "--config", str(spec_file(tmp_path, "keep", data)), "--out", str(scene), "--until", "check")
    r = default_engine(tmp_path, *args, "--replace-segments")  # the check's settings change what guides are made of
    assert r.returncode == 0, r.stderr[-3000:]
    assert "2 rendered, 1 cached" in r.stderr, r.stderr[-3000:]  # s000 as it was made before the failure
    store = SceneStore.open(scene)
    assert (store.array("segments/s000/attempts/0/frames") == frames).all()
    for seg in SEGMENTS:
        intact(store, seg)
