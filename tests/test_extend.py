"""`extend`: one more segment from the user's words; nothing already computed is recomputed, the splats
continue from the existing Gaussians, the history is kept and shown by inspect."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli, tiny_config

from flows.extend import extend, extended_config
from flows.pipeline import execute
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore

VIDEO = {"width": 128, "height": 96, "frames_per_segment": 8}
WORDS = "a frozen lake beyond the trees on the left"


def _config():
    cfg = tiny_config(video=VIDEO, extensions={"rounds": 1, "directions": ["right"]})
    steps = cfg.steps.model_dump()
    steps["splats"] |= {"max_side_px": 96}
    steps["splats"]["train"] |= {"iterations": 60, "holdout_every": 0}
    steps["outputs"] |= {"video_frames": 6}
    execution = {"segment_workers": 1, "renderer": "torch"}
    return cfg.model_validate({**cfg.model_dump(), "steps": steps, "execution": execution})


def _poses_by_frame(store: SceneStore) -> dict[tuple[str, int], object]:
    segs = store.meta("sfm").segments
    return {
        (segs[a], int(i)): pose
        for (a, i), pose in zip(store.array("sfm/frame_index"), store.array("sfm/poses"), strict=True)
    }


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> tuple[Path, dict]:
    scene = tmp_path_factory.mktemp("extend") / "scene"
    execute(scene, _config())
    store = SceneStore.open(scene)
    before = {
        "keys": {
            g: store.cache_key_of(g) for g in ("segments/s000", "segments/s001", "priors_raw/s000", "priors_raw/s001")
        },
        "checks": {s: store.meta(f"segments/{s}/attempts/0/check") for s in ("s000", "s001")},
        "n_gaussians": store.meta("splats").metrics.n_gaussians,
        "frames": store.meta("splats").frames,
        "sfm": _poses_by_frame(store),
    }
    shutil.copytree(scene, scene.parent / "before")  # the scene as the extension found it
    results = extend(scene, WORDS, engine="local")
    return scene, {"before": before, "results": {r.step: r.status for r in results}}


@pytest.mark.e2e
def test_only_the_new_segment_is_generated_and_checked(scenes) -> None:
    scene, info = scenes
    store = SceneStore.open(scene)
    assert store.children("segments") == ["s000", "s001", "s002"]
    new = store.meta("segments/s002")
    assert new.role == "left" and new.intent == WORDS
    for group, key in info["before"]["keys"].items():
        assert store.cache_key_of(group) == key, f"{group} was recomputed"
    for seg, check in info["before"]["checks"].items():
        assert store.meta(f"segments/{seg}/attempts/0/check") == check
    assert store.meta("segments/s002/attempts/0/check").accepted in (True, False)
    assert info["results"]["outputs"] == "ran" and info["results"]["splats"] == "ran"


@pytest.mark.e2e
def test_poses_register_only_the_new_frames_and_old_frames_keep_their_poses(scenes) -> None:
    scene, info = scenes
    store = SceneStore.open(scene)
    a = store.meta("sfm")
    assert a.solve == "incremental", a.incremental_problems
    assert a.new_frames == VIDEO["frames_per_segment"] - 1  # s002 without the frame repeating its reference
    after = _poses_by_frame(store)
    for frame, pose in info["before"]["sfm"].items():
        assert (after[frame] == pose).all() or not np.isfinite(pose).all(), frame  # exactly, where posed before
    assert any(np.isfinite(pose).all() for (seg, _), pose in after.items() if seg == "s002")
    # the new segment's turn is held to its check's reading (only it: the old frames kept their poses)
    from tasks.segments import attempt_path

    check = store.meta(attempt_path(store, "s002").check)
    judged = bool(check and check.accepted and (check.plan_following or {}).get("ok"))
    assert set(a.segment_turn_error_deg) == ({"s002"} if judged else set())
    assert all(e <= 5.0 for e in a.segment_turn_error_deg.values()), a.segment_turn_error_deg


@pytest.mark.e2e
def test_splats_continue_from_the_existing_gaussians(scenes) -> None:
    scene, info = scenes
    a = SceneStore.open(scene).meta("splats")
    assert a.extended_from["frames"] == len(info["before"]["frames"])
    assert a.extended_from["kept_gaussians"] == info["before"]["n_gaussians"]
    assert 0 < a.extended_from["continued_gaussians"] <= a.extended_from["kept_gaussians"]
    assert a.extended_from["views"] <= len(a.frames)
    assert set(info["before"]["frames"]) < set(a.frames) and any(f.startswith("s002_") for f in a.frames)
    splats = _config().steps.splats
    assert len(a.curves["total"]) == round(splats.train.iterations * splats.extend_iterations_frac)


@pytest.mark.e2e
def test_the_splats_record_the_poses_they_were_trained_with_and_train_every_view_once_those_moved(scenes) -> None:
    from tasks.segments import posed_stitched
    from tasks.splats import _previous, _region

    scene, _ = scenes
    store = SceneStore.open(scene)
    poses = _poses_by_frame(store)  # the global poses, read from sfm/ as any reader would
    for folder in (scene, scene.parent / "before"):
        meta = SceneStore.open(folder).meta("splats")
        trained = np.stack([poses[(n.split("_")[0], int(n.split("_")[1]))] for n in meta.frames])
        assert meta.poses_digest == hashlib.sha256(trained.astype(np.float64).tobytes()).hexdigest(), folder
    p = _config().steps.splats.model_copy(update={"extend_old_views_max": 8})  # an extension that trains a region
    before = SceneStore.open(scene.parent / "before")
    _, w2c, names = posed_stitched(store, {})
    previous = _previous(before, p, names)  # the extension's start: the splats as they were
    assert previous is not None and _region(store, p, previous, names, w2c) is not None  # poses kept: a region
    moved = w2c.copy()
    moved[names.index(previous.frames[0]), 0, 3] += 1e-9  # an old frame solved again, ever so slightly elsewhere
    assert _region(store, p, previous, names, moved) is None


@pytest.mark.e2e
def test_the_datasets_keep_the_files_of_the_frames_they_had(scenes) -> None:
    scene, _ = scenes
    for product in ("nerfstudio/images", "nerfstudio/depths", "colmap/images"):
        before = sorted((scene.parent / "before" / product).iterdir())
        assert before and all(f.read_bytes() == (scene / product / f.name).read_bytes() for f in before), product
        assert any(f.name.startswith("s002_") for f in (scene / product).iterdir()), product


@pytest.mark.e2e
def test_history_is_kept_and_inspect_shows_it(scenes) -> None:
    scene, _ = scenes
    r = run_cli("inspect", str(scene), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["extensions"] == [{"words": WORDS, "segment": "s002"}]


def test_bad_requests_are_refused() -> None:
    cfg = _config()
    for words, message in (("   ", "empty"), ("x" * 600, "600 characters")):
        with pytest.raises(WonderError, match=message):
            extended_config(cfg, words)
    assert extended_config(extended_config(cfg, "go up"), "left a bit").scene.extensions.added == (
        "go up",
        "left a bit",
    )


def test_the_extension_settings_do_not_stop_a_continuation() -> None:
    from tasks.splats import _train_digest

    p = _config().steps.splats
    base = _train_digest(p)
    assert _train_digest(p.model_copy(update={"extend_iterations_frac": 0.5, "extend_new_view_share": 0.9})) == base
    # which pixels of older frames count, not what the Gaussians are
    assert _train_digest(p.model_copy(update={"newest_frames_win": False, "superseded_margin": 0.3})) == base
    assert _train_digest(p.model_copy(update={"init_opacity": 0.2})) != base  # the optimisation itself changed
