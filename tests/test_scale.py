"""What a growing world re-does: a new `video_fps` re-makes the videos and nothing else (the mesh files keep their
bytes), and an extension's continued training spends the same steps on the old frames however large the world."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from conftest import tiny_config
from test_media import ffmpeg_video_stream

from flows.pipeline import execute
from wonderverse.config import RunConfig
from wonderverse.schema import OUTPUTS
from wonderverse.store import SceneStore

MESH_FILES = ("mesh.ply", "mesh.glb")
VIDEOS = ("flythrough.mp4", "novel.mp4")


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _with_fps(cfg: RunConfig, fps: float) -> RunConfig:
    outputs = cfg.steps.outputs.model_copy(update={"video_fps": fps})
    return cfg.model_copy(update={"steps": cfg.steps.model_copy(update={"outputs": outputs})})


@pytest.mark.e2e
def test_a_new_video_fps_re_makes_the_videos_alone(tmp_path: Path) -> None:
    cfg = tiny_config(extensions={"rounds": 0})
    cfg = cfg.model_copy(update={"execution": cfg.execution.model_copy(update={"renderer": "torch"})})
    scene = tmp_path / "scene"
    first = execute(scene, cfg)
    assert first[-1].step == "outputs" and first[-1].status == "ran"
    before = {name: _digest(scene / name) for name in (*MESH_FILES, *VIDEOS)}
    old_fps = cfg.steps.outputs.video_fps
    assert f"{old_fps:g} fps" in ffmpeg_video_stream(scene / "flythrough.mp4")

    again = execute(scene, _with_fps(cfg, old_fps * 2))
    ran = [r.step for r in again if r.status == "ran"]
    assert ran == ["outputs"], ran  # every step before it is cached: only the outputs read video_fps
    made = SceneStore.open(scene).meta(OUTPUTS.path).made
    assert sorted(made) == ["camera_paths", "videos"], made  # the mesh, splat files, datasets: kept as they were
    for name in MESH_FILES:
        assert _digest(scene / name) == before[name], f"{name} changed with video_fps alone"
    for name in VIDEOS:
        assert _digest(scene / name) != before[name], f"{name} was not re-made"
        assert f"{old_fps * 2:g} fps" in ffmpeg_video_stream(scene / name)


@pytest.mark.parametrize("n_old", [40, 130, 600])
def test_an_extension_spends_the_same_steps_on_the_old_frames_however_many_there_are(n_old: int) -> None:
    """The continuation's steps split by `extend_new_view_share` whatever the size of the world: the old frames get
    the same number of steps at 40 frames as at 600, so an extension costs the same and the new frames' share does
    not shrink as the world grows."""
    import torch

    from wonderverse.config import SplatsStepParams
    from wonderverse.splats.trainer import continuation_params, view_order

    p = SplatsStepParams()
    steps = continuation_params(p.train, p.extend_iterations_frac).iterations
    new = list(range(n_old, n_old + 14))  # one segment's training frames
    gen = torch.Generator().manual_seed(0)
    old_steps = []
    for _ in range(200):  # many continuations: the count of one is a random draw
        order: list[int] = []
        taken = []
        for _ in range(steps):
            if not order:
                order = view_order(list(range(n_old + 14)), [(new, p.extend_new_view_share)], gen)
            taken.append(order.pop())
        old_steps.append(sum(i < n_old for i in taken))
    expected = (1 - p.extend_new_view_share) * steps
    assert abs(np.mean(old_steps) - expected) < 0.08 * steps, (np.mean(old_steps), expected)


@pytest.mark.e2e
def test_the_world_as_it_now_is_shows_in_an_older_frame_what_later_words_placed(tmp_path: Path) -> None:
    """`benchmarks.scale.world_now`, the reference of `psnr_now`: words that place a clock tower ahead of a forward
    move put it where the first segment looked. Ground truth: the procedural world's labels and its renders. Where the
    world did not change under a frame, the world's render at the frame's pose is the frame; where it did, it is not."""
    from benchmarks.scale import world_now
    from tasks.segments import attempt_path
    from wonderverse.metrics import psnr

    scene = tmp_path / "scene"
    execute(scene, tiny_config(extensions={"rounds": 0}), until="generate_segments")
    grown = tiny_config(extensions={"rounds": 0, "added": ["further ahead, a clock tower"]})
    results = {r.step: r for r in execute(scene, grown, until="generate_segments")}
    assert "1 rendered, 1 cached" in results["generate_segments"].detail  # the first segment was made before
    store = SceneStore.open(scene)
    frames = store.array(attempt_path(store, "s000").frames)
    now = world_now(store, [f"s000_{i:04d}" for i in range(len(frames))])
    assert any(render is not None for _, render, _ in now.values()), "the tower stands outside the first segment's view"
    for name, (changed, render, _) in now.items():
        frame = frames[int(name.split("_")[1])]
        if render is None:
            assert not changed.any()
            continue
        assert changed.any() and (render != frame).any(axis=-1)[changed].mean() > 0.5
        assert psnr(render[~changed] / 255.0, frame[~changed] / 255.0) > 30, name  # the same world elsewhere


@pytest.mark.e2e
def test_a_later_frame_shows_what_it_saw_of_the_world_now_and_nothing_else(tmp_path: Path) -> None:
    """`benchmarks.scale.shown_later`, what `psnr_seen` leaves in: the pixels of an older frame whose content now some
    later frame shows. The same tiny world as above: the second segment, a forward move, sees much of what the first
    saw (were a convention wrong, its points would land elsewhere and match nothing); of the tower its words placed,
    it shows part, and only changed pixels are counted; the last segment has no later frame to show anything."""
    from benchmarks.scale import shown_later, world_now

    scene = tmp_path / "scene"
    execute(scene, tiny_config(extensions={"rounds": 0}), until="generate_segments")
    execute(
        scene,
        tiny_config(extensions={"rounds": 0, "added": ["further ahead, a clock tower"]}),
        until="generate_segments",
    )
    store = SceneStore.open(scene)
    names = [f"s000_{i:04d}" for i in range(6)]
    everything = shown_later(store, {n: np.ones((64, 96), bool) for n in names})
    share = np.mean([m.mean() for m in everything.values()])
    assert share > 0.3, share
    now = world_now(store, names, render=False)
    tower = shown_later(store, {n: c for n, (c, _, _) in now.items()})
    assert all(not (m & ~now[n][0]).any() for n, m in tower.items())
    assert any(m.any() for m in tower.values()) and not all(m[now[n][0]].all() for n, m in tower.items())
    assert not any(m.any() for m in shown_later(store, {"s001_0003": np.ones((64, 96), bool)}).values())
