"""End to end through the real store: steps run in order, cache, resume after SIGKILL, re-run
only what a changed parameter touches."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import yaml
from conftest import ROOT, tiny_config

from flows.pipeline import execute
from tasks.segments import stitched
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore


def statuses(results) -> dict[str, str]:
    return {r.step: r.status for r in results}


@pytest.mark.e2e
def test_generate_stores_every_segment_and_reruns_cached(tmp_path: Path):
    cfg = tiny_config()
    first = execute(tmp_path / "s", cfg, until="generate_segments")
    assert statuses(first) == {"plan": "ran", "generate_segments": "ran"}
    store = SceneStore.open(tmp_path / "s")
    order = store.meta("segments").order
    assert len(order) == 3 and store.meta(f"segments/{order[1]}").role == "init"
    for seg in order:
        a = f"segments/{seg}/attempts/0"
        f = store.array(f"{a}/frames")
        assert f.shape == (6, 64, 96, 3) and f.dtype == np.uint8 and f.std() > 5  # real images, not blank
        assert store.array(f"{a}/gt/poses").dtype == np.float64
        assert store.array(f"{a}/gt/depth").shape == (6, 64, 96)
    # extensions continue from their reference frame: a left segment starts at init's first pose
    left = next(s for s in order if store.meta(f"segments/{s}").role == "left")
    init = order[1]
    np.testing.assert_allclose(store.array(f"segments/{left}/path")[0], store.array(f"segments/{init}/path")[0])
    np.testing.assert_array_equal(
        store.array(f"segments/{left}/attempts/0/frames")[0],
        store.array(f"segments/{init}/attempts/0/frames")[0],
    )
    frames, index = stitched(store)
    assert len(frames) == 6 + 2 * 5 and index[0][0] == left and index[5][0] == init

    again = execute(tmp_path / "s", cfg, until="generate_segments")
    assert statuses(again) == {"plan": "cached", "generate_segments": "cached"}
    assert [r.cache_key for r in again] == [r.cache_key for r in first]


@pytest.mark.e2e
def test_changed_parameter_reruns_that_step_and_dependants_only(tmp_path: Path):
    cfg = tiny_config()
    execute(tmp_path / "s", cfg, until="generate_segments")
    store = SceneStore.open(tmp_path / "s")
    init_key = store.cache_key_of("segments/s000")

    # a video setting: the plan is upstream and stays cached; segments re-render
    wider = tiny_config(video={"width": 112})
    assert statuses(execute(tmp_path / "s", wider, until="generate_segments")) == {
        "plan": "cached",
        "generate_segments": "ran",
    }
    assert SceneStore.open(tmp_path / "s").array("segments/s000/attempts/0/frames").shape[2] == 112

    # a planner setting that only changes the extensions: plan re-runs, init segment stays cached
    execute(tmp_path / "s", cfg, until="generate_segments")
    assert SceneStore.open(tmp_path / "s").cache_key_of("segments/s000") == init_key
    steeper = cfg.model_copy(
        update={
            "steps": cfg.steps.model_copy(update={"plan": cfg.steps.plan.model_copy(update={"yaw_step_deg": 20.0})})
        }
    )
    results = execute(tmp_path / "s", steeper, until="generate_segments")
    assert statuses(results) == {"plan": "ran", "generate_segments": "ran"}
    assert results[1].detail == "2 rendered, 1 cached"


@pytest.mark.e2e
def test_sigkill_during_generation_resumes_from_last_complete_segment(tmp_path: Path):
    scene = tmp_path / "s"
    spec = {
        "preset": "preview",
        "scene": {
            "prompt": "a quiet forest lake",
            "video": {
                "width": 160,
                "height": 112,
                "frames_per_segment": 30,
                "options": {"fault_probability": 0.0},
            },
            "extensions": {"rounds": 2},
        },
    }
    cfg_file = tmp_path / "scene.yaml"
    cfg_file.write_text(yaml.safe_dump(spec))
    cmd = [
        sys.executable,
        "-m",
        "flows",
        "generate",
        "--config",
        str(cfg_file),
        "--out",
        str(scene),
        "--engine",
        "local",
        "--until",
        "generate_segments",
    ]
    child = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    segs = scene / "scene.zarr" / "segments"
    # wait until one segment is committed and another is being written in staging
    while True:
        assert child.poll() is None, "generation finished before it could be killed"
        assert time.monotonic() < deadline
        done = [p for p in segs.glob("s*") if p.is_dir()] if segs.exists() else []
        staging = scene / "scene.zarr" / "_staging"
        if done and staging.exists() and any(p.is_dir() for p in staging.iterdir()):
            break
        time.sleep(0.05)
    run = psutil.Process(child.pid).children(recursive=True)  # the command's worker process and its own
    child.send_signal(signal.SIGKILL)  # kill -9 of the command: its reaper takes the run down with it
    child.wait()
    _, alive = psutil.wait_procs(run, timeout=10)
    assert not alive, [p.cmdline() for p in alive]

    store = SceneStore.open(scene)
    committed = store.children("segments")
    assert committed and all(store.cache_key_of(f"segments/{s}") is not None for s in committed)
    assert store.cache_key_of("segments") is None  # the step itself is not complete

    from wonderverse.config import build_config

    results = execute(scene, build_config(config_file=cfg_file), until="generate_segments")
    assert statuses(results) == {"plan": "cached", "generate_segments": "ran"}
    rendered, cached = (int(x.split()[0]) for x in results[1].detail.split(", "))
    assert cached == len(committed) and rendered == 5 - len(committed)


@pytest.mark.e2e
def test_a_second_writer_is_refused_and_changes_nothing(tmp_path: Path):
    from wonderverse.store import scene_lock

    scene = tmp_path / "s"
    execute(scene, tiny_config(), until="plan")
    before = dict(SceneStore.open(scene).group("plan").attrs)  # the raw JSON, bookkeeping included
    with scene_lock(scene), pytest.raises(WonderError, match="being written by another run"):
        execute(scene, tiny_config(seed=7), until="plan")
    assert dict(SceneStore.open(scene).group("plan").attrs) == before
    assert [r.status for r in execute(scene, tiny_config(), until="plan")] == ["cached"]


def test_each_entry_point_is_its_own_prefect_flow():
    from flows.pipeline import generate_flow

    names = {n: generate_flow(n).name for n in ("generate", "extend", "reconstruct")}
    assert names == {"generate": "generate", "extend": "extend", "reconstruct": "reconstruct"}
    assert generate_flow("extend") is generate_flow("extend")
