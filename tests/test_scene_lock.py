"""The scene lock is held on the scene folder itself: removing or replacing its lock file while a run holds it
lets no second run in (it did: the second run created a new file and locked that)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from conftest import lock_held_elsewhere

from wonderverse.store import LOCK_NAME, StoreError, scene_lock


@pytest.fixture
def holder(tmp_path: Path):  # type: ignore[no-untyped-def]
    """A separate process holding the lock of `tmp_path/scene` until its stdin closes."""
    scene = tmp_path / "scene"
    with lock_held_elsewhere(scene) as proc:
        yield scene, proc


def test_removing_the_lock_file_lets_no_second_run_in(holder) -> None:  # type: ignore[no-untyped-def]
    scene, proc = holder
    (scene / LOCK_NAME).unlink()
    removed = rf"being written by another run \(holder unknown: {LOCK_NAME} was removed"
    with pytest.raises(StoreError, match=removed), scene_lock(scene):
        pass
    assert not (scene / LOCK_NAME).exists()  # the refused run made no new file either
    (scene / LOCK_NAME).write_text("{}")  # a new, empty lock file: still refused
    with pytest.raises(StoreError, match="being written by another run"), scene_lock(scene):
        pass
    proc.stdin.close()  # the holder finishes: the scene is free again
    proc.wait(timeout=10)
    with scene_lock(scene) as lock_file:
        assert f'"pid": {os.getpid()}' in lock_file.read_text()


def test_a_lock_file_that_is_a_symlink_is_refused_and_its_target_left_alone(tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    scene.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    (scene / LOCK_NAME).symlink_to(victim)
    with pytest.raises(StoreError, match="cannot write to output folder"), scene_lock(scene):
        pass
    assert victim.read_text() == "keep me"
