"""The scene's stored config is the last completed run's: a run that fails never replaces it, while what the
segments were made with is recorded when they are generated, so the guard against replacing them, `inspect` and
a re-run stay right after a failure."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import tiny_config

from flows.inspect import summarize
from flows.pipeline import StepFailed, execute, run_pipeline, segments_config, stored_config
from tasks import Step
from wonderverse.config import RunConfig
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore

pytestmark = pytest.mark.e2e  # the pipeline


def failing_at(name: str):
    """Run each step as the local engine does, except that step `name` raises (a crash, Ctrl-C, a full disk)."""

    def call(step: Step, scene_dir: str, cfg: RunConfig, key: str) -> str:
        if step.name == name:
            raise RuntimeError("injected failure")
        return step.run_in(scene_dir, cfg, key)

    return call


def with_check_rule(cfg: RunConfig, **rules: float) -> RunConfig:
    check = cfg.steps.check.model_copy(update={"rules": cfg.steps.check.rules.model_copy(update=rules)})
    return cfg.model_copy(update={"steps": cfg.steps.model_copy(update={"check": check})})


def test_a_failed_run_never_replaces_the_stored_config(tmp_path: Path) -> None:
    d = tmp_path / "scene"
    first = tiny_config(extensions={"rounds": 0})
    with pytest.raises(StepFailed, match="injected failure"):
        execute(d, first, until="check", call=failing_at("check"))
    assert "config" not in SceneStore.open(d).root.attrs and stored_config(d) is None  # no run completed
    assert segments_config(d) == first  # but the segments are known to be its

    # so a run of another prompt is still refused, before it touches anything
    other = tiny_config("a desert canyon at noon", extensions={"rounds": 0})
    with pytest.raises(WonderError, match=r"1 segment\(s\) made with other settings \(prompt"):
        run_pipeline(d, other, until="plan", engine="local")

    # the same config resumes from the store and, completed, becomes the scene's
    assert [r.status for r in run_pipeline(d, first, until="generate_segments", engine="local")] == ["cached"] * 2
    assert stored_config(d) == first

    # a later run with other check settings fails: the scene keeps the completed run's config
    changed = with_check_rule(first, rot_thresh_rad=0.45)
    with pytest.raises(StepFailed):
        execute(d, changed, until="check", call=failing_at("check"))
    assert stored_config(d) == first and segments_config(d) == first  # its segments were cached, not regenerated
    status = {s["name"]: s["status"] for s in summarize(SceneStore.open(d))["steps"]}
    assert status["plan"] == status["generate_segments"] == "complete"  # judged against the stored config

    # and a completed run of the changed settings replaces it
    execute(d, changed, until="generate_segments")
    assert stored_config(d) == changed
