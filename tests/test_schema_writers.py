"""One declared writer per store group (`wonderverse.schema`): a step's commit of a group the schema gives to
another step is refused before anything is written, attributes that do not fit a group's model are refused too,
and whole runs (unguided, extended, guided) commit only groups their steps may write."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tasks import STEP_NAMES
from wonderverse.errors import StoreError
from wonderverse.schema import ACCEPTED, GROUPS, PRIORS_RAW_SEGMENT, SFM, group_of
from wonderverse.store import SceneStore, current_writer, writing


def test_every_group_names_a_step_as_its_writer() -> None:
    for group in GROUPS:
        if group.template == "":  # the root: the store and the flow write it, never a step's commit
            continue
        assert group.writer in STEP_NAMES, group.template
        assert set(group.shared) <= set(STEP_NAMES) - {group.writer}, group.template


def test_a_commit_by_a_step_that_is_not_the_writer_is_refused_and_writes_nothing(tmp_path: Path) -> None:
    store = SceneStore.open_or_create(tmp_path / "scene")
    refused = pytest.raises(StoreError, match="step priors may not write sfm")
    with writing("priors"), refused, store.staged(SFM.path, "k", source="sfm", segments=["s000"]):
        raise AssertionError("the block must not run")
    assert not store.exists(SFM.path)
    with writing("poses"), store.staged(SFM.path, "k", source="sfm", segments=["s000"]):
        pass
    assert store.meta(SFM.path).segments == ["s000"]


def test_groups_shared_with_the_guided_flow_take_its_commits_only() -> None:
    accepted = ACCEPTED.at(seg="s001")
    assert group_of(accepted).may_write("check") and group_of(accepted).may_write("generate_segments")
    assert not group_of(accepted).may_write("priors")
    raw = PRIORS_RAW_SEGMENT.at(seg="s000")
    assert group_of(raw).may_write("priors") and group_of(raw).may_write("generate_segments")
    assert not group_of(raw).may_write("check")


def test_attributes_that_do_not_fit_the_groups_model_are_refused_before_anything_is_written(tmp_path: Path) -> None:
    store = SceneStore.open_or_create(tmp_path / "scene")
    refused = pytest.raises(ValueError, match="attributes of sfm do not fit its schema")
    with refused, store.staged(SFM.path, "k", source="the moon"):
        raise AssertionError("the block must not run")
    with pytest.raises(ValueError, match="do not fit its schema"), store.staged(SFM.path, "k", undeclared_key=1):
        raise AssertionError("the block must not run")
    assert not store.exists(SFM.path)


@pytest.mark.e2e
def test_every_commit_of_whole_runs_is_made_by_a_declared_writer(tmp_path: Path, monkeypatch: Any) -> None:
    from conftest import complete_config

    from flows.extend import extended_config
    from flows.pipeline import execute

    made: list[tuple[str, str | None]] = []
    staged, mark_complete = SceneStore.staged, SceneStore.mark_complete

    def recording_staged(self: SceneStore, group_path: str, key: str, **attrs: Any) -> Any:
        made.append((group_path, current_writer()))
        return staged(self, group_path, key, **attrs)

    def recording_mark(self: SceneStore, group_path: str, key: str, **attrs: Any) -> None:
        made.append((group_path, current_writer()))
        mark_complete(self, group_path, key, **attrs)

    monkeypatch.setattr(SceneStore, "staged", recording_staged)
    monkeypatch.setattr(SceneStore, "mark_complete", recording_mark)
    cfg = complete_config()
    in_process = cfg.execution.model_copy(update={"segment_workers": 1})  # Dask workers are other processes
    cfg = cfg.model_copy(update={"execution": in_process})
    execute(tmp_path / "plain", cfg)
    execute(tmp_path / "plain", extended_config(cfg, "a frozen lake on the left"))
    guided = cfg.scene.video.options.model_copy(update={"accept_guide": True})
    guided_cfg = cfg.model_copy(
        update={"scene": cfg.scene.model_copy(update={"video": cfg.scene.video.model_copy(update={"options": guided})})}
    )
    execute(tmp_path / "guided", guided_cfg)
    templates = set()
    for path, writer in made:
        group = group_of(path)
        assert group is not None, f"{path} is no group of the schema"
        assert writer is not None, f"{path} was committed outside any step"
        assert group.may_write(writer), f"{writer} committed {path}"
        templates.add(group.template)
    # every kind of committed group was seen, among them the ones a guided flow shares
    assert {
        "plan",
        "segments/{seg}",
        "segments/{seg}/accepted",
        "segments/{seg}/geometry",
        "sfm",
        "priors/{seg}",
    } <= templates
    assert {"priors_raw/{seg}", "splats", "outputs/{product}", "outputs"} <= templates
    assert any(w == "generate_segments" and group_of(p).writer == "check" for p, w in made)  # a shared commit
