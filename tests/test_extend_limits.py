"""`extend` refused in one line, the scene untouched: a scene at the segment cap (64, `planning.params.MAX_SEGMENTS`),
a store whose metadata is damaged, a scene another run is writing."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import lock_held_elsewhere, run_cli, tiny_config, tree_digest

from flows.extend import with_extensions
from wonderverse.config import ConfigError, validate_config
from wonderverse.planning.params import MAX_SEGMENTS, ExtensionSpec
from wonderverse.schema import ROOT
from wonderverse.store import SceneStore

pytestmark = pytest.mark.e2e  # the CLI


def scene_with_config(folder: Path, added: int) -> Path:
    """A scene store whose last completed run had `added` extensions (no step has run: extend refuses first)."""
    cfg = with_extensions(tiny_config(), tuple(f"further on the left {i}" for i in range(added)))
    store = SceneStore.open_or_create(folder, spec=cfg.scene.model_dump(mode="json"))
    store.update_attrs(ROOT.path, config=cfg.model_dump(mode="json"), segments_config=cfg.model_dump(mode="json"))
    return folder


def one_error_line(r) -> str:  # type: ignore[no-untyped-def]
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert r.returncode == 2 and len(errors) == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    return errors[0]


def test_the_cap_counts_every_segment_and_holds_in_the_config() -> None:
    assert ExtensionSpec(rounds=1, added=("x",) * (MAX_SEGMENTS - 3)).segments == MAX_SEGMENTS
    with pytest.raises(ValueError, match=f"at most {MAX_SEGMENTS} segments"):
        ExtensionSpec(rounds=16, directions=("left", "right", "up", "down"))
    data = tiny_config().model_dump(mode="json")
    data["scene"]["extensions"]["added"] = ["x"] * MAX_SEGMENTS
    with pytest.raises(ConfigError, match="at most 64 segments and this one would have 67"):
        validate_config(data)


def test_extend_at_the_segment_cap_is_one_line_and_changes_nothing(tmp_path: Path) -> None:
    scene = scene_with_config(tmp_path / "full", MAX_SEGMENTS - 3)  # 1 + 2 + 61 = 64 segments
    before = tree_digest(scene)
    line = one_error_line(run_cli("extend", str(scene), "a frozen lake on the left"))
    assert f"at most {MAX_SEGMENTS} segments" in line and "start a new scene" in line
    assert tree_digest(scene) == before


def test_extend_of_a_store_with_damaged_metadata_is_one_line_and_changes_nothing(tmp_path: Path) -> None:
    scene = scene_with_config(tmp_path / "damaged", 0)
    (scene / "scene.zarr" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "gr')  # cut short
    before = tree_digest(scene)
    line = one_error_line(run_cli("extend", str(scene), "a frozen lake on the left"))
    assert "scene.zarr" in line or "no completed run" in line, line
    assert tree_digest(scene) == before


def test_extend_of_a_scene_another_run_writes_is_one_line_and_changes_nothing(tmp_path: Path) -> None:
    scene = scene_with_config(tmp_path / "busy", 0)
    with lock_held_elsewhere(scene):
        before = tree_digest(scene)
        line = one_error_line(run_cli("extend", str(scene), "a frozen lake on the left", "--engine", "local"))
        assert "being written by another run" in line
        assert tree_digest(scene) == before
