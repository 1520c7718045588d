"""The splats step end to end on a tiny procedural scene: trains from the global poses and aligned
priors, writes the Gaussians into the store (the exported splats.ply is the outputs step's: tests/test_outputs.py),
checkpoints into the store and resumes after a kill."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import tiny_config

from flows.pipeline import execute
from wonderverse.store import SceneStore

pytestmark = pytest.mark.e2e  # the pipeline up to the splats step


VIDEO = {"width": 200, "height": 136, "frames_per_segment": 12}


def splat_config(iterations: int = 40):
    cfg = tiny_config(video=VIDEO, extensions={"rounds": 0})
    train = cfg.steps.splats.train.model_copy(
        update={"iterations": iterations, "checkpoint_every_iters": 20, "holdout_every": 4}
    )
    splats = cfg.steps.splats.model_copy(update={"train": train, "max_side_px": 96})
    execution = cfg.execution.model_copy(update={"renderer": "torch"})
    return cfg.model_copy(update={"steps": cfg.steps.model_copy(update={"splats": splats}), "execution": execution})


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    scene = tmp_path_factory.mktemp("splats") / "scene"
    results = execute(scene, splat_config(), until="splats")
    assert results[-1].step == "splats" and results[-1].status == "ran"
    return scene


def test_splats_are_stored_with_the_normalisation_to_the_world(trained: Path):
    store = SceneStore.open(trained)
    a = store.meta("splats")
    n = a.metrics.n_gaussians
    assert n > 100 and store.array("splats/means").shape == (n, 3)
    assert np.isfinite(store.array("splats/means")).all()
    assert a.metrics.test_views and np.isfinite(a.metrics.test_psnr)
    assert len(a.curves["total"]) == 40 and a.curves["total"][-1] < a.curves["total"][0]
    # the normalisation takes the Gaussians back to the world: they sit where the SfM points are
    from wonderverse.splats.model import normalization_from_dict

    xyz = normalization_from_dict(a.normalization).apply_inverse(store.array("splats/means"))
    pts = store.array("sfm/points3d")
    assert np.linalg.norm(np.median(xyz, 0) - np.median(pts, 0)) < 0.5 * np.ptp(pts, 0).max()
    assert not (trained / "splats.ply").exists()  # exported by the outputs step, in the outputs' frame
    assert not store.exists("splats_checkpoint")  # removed once the result is committed


def test_the_step_trains_on_each_frame_s_prior_with_the_priors_step_s_alignment_flag(trained: Path):
    """Frames the priors step aligned are compared as they are, the others are fitted (`LossParams.depth_fit`):
    the step hands each frame's flag to the trainer, in the order of its frames."""
    from tasks.splats import load_views

    store = SceneStore.open(trained)
    views, names = load_views(store)
    flags = {seg: store.array(f"priors/{seg}/aligned") for seg in store.meta("sfm").segments}
    expect = [bool(flags[name.rsplit("_", 1)[0]][int(name.rsplit("_", 1)[1])]) for name in names]
    assert views.prior_aligned is not None and views.prior_aligned.tolist() == expect
    assert any(expect)  # the tiny scene's priors do align to its SfM points


def test_sigkill_during_training_resumes_from_its_checkpoint(tmp_path: Path, trained: Path, caplog):
    import shutil
    import signal
    import subprocess
    import sys
    import time

    import psutil
    import yaml
    from conftest import ROOT

    scene = tmp_path / "scene"
    shutil.copytree(trained, scene)
    SceneStore.open(scene, mode="r+").remove("splats")
    cfg = splat_config(iterations=200)
    cfg_file = tmp_path / "scene.yaml"
    cfg_file.write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    child = subprocess.Popen(
        [
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
        ],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 300
    while SceneStore.open(scene).cache_key_of("splats_checkpoint") is None:  # not complete yet
        assert child.poll() is None and time.monotonic() < deadline, "training ended before a checkpoint"
        time.sleep(0.1)
    run = psutil.Process(child.pid).children(recursive=True)  # the command's worker process
    child.send_signal(signal.SIGKILL)  # kill -9 of the command: its reaper takes the run down with it
    child.wait()
    _, alive = psutil.wait_procs(run, timeout=10)
    assert not alive, [p.cmdline() for p in alive]
    step = SceneStore.open(scene).meta("splats_checkpoint").step
    assert 20 <= step < 200 and not SceneStore.open(scene).exists("splats")
    with caplog.at_level("WARNING", logger="wonderverse.splats"):
        results = execute(scene, cfg, until="splats")
    assert [r.status for r in results][-1] == "ran" and [r.status for r in results][:-1] == ["cached"] * 5
    assert any(f"checkpoint at step {step}" in r.message for r in caplog.records)
    assert len(SceneStore.open(scene).meta("splats").curves["total"]) == 200  # history carried over
