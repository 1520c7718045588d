"""One writer per scene: a second run on a busy scene is refused at once with the holder's pid, or
waits for it; a killed holder frees the scene. The holder is a real second process."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import tree_digest

from wonderverse.errors import WonderError
from wonderverse.store import LOCK_NAME, SceneStore, StoreError, scene_lock, write_array

ROOT = Path(__file__).resolve().parents[1]
HOLDER = """
import sys, time
from wonderverse.store import scene_lock
with scene_lock(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def hold(scene: Path, seconds: float) -> subprocess.Popen:
    """A separate process that holds the scene's lock for `seconds`; returns once it has it."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(scene), str(seconds)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "locked", "holder did not take the lock"
    return proc


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout=10)


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    """A small real store written under the lock, as a run would."""
    d = tmp_path / "scene"
    with scene_lock(d):
        store = SceneStore.open_or_create(d, spec={"prompt": "a lighthouse"})
        with store.staged("segments/s000", "k0") as g:
            write_array(g, "frames", np.arange(4 * 8 * 8 * 3, dtype=np.uint8).reshape(4, 8, 8, 3))
    return d


def test_second_writer_is_refused_at_once_naming_the_holder_and_leaves_the_scene_untouched(scene: Path):
    holder = hold(scene, 60)
    try:
        before = tree_digest(scene)  # the lock file included, with the holder's details
        t0 = time.monotonic()
        with pytest.raises(StoreError) as err, scene_lock(scene):
            # what a second run would do; must never happen while the holder writes
            store = SceneStore.open_or_create(scene, spec={"prompt": "another"})
            store.remove("segments/s000")
        assert time.monotonic() - t0 < 1.0
        msg = str(err.value)
        assert isinstance(err.value, WonderError) and "\n" not in msg
        assert f"pid {holder.pid} on {socket.gethostname()} since " in msg, msg
        assert f"scene {scene} is being written by another run" in msg and "another --out" in msg, msg
        assert "waited" not in msg
        assert tree_digest(scene) == before
        assert SceneStore.open(scene).exists("segments/s000")
    finally:
        stop(holder)


def test_a_waiting_writer_gets_the_scene_once_the_holder_finishes(scene: Path):
    holder = hold(scene, 2.0)
    try:
        t0 = time.monotonic()  # the holder lets go about 2 s from now
        with pytest.raises(StoreError, match=rf"pid {holder.pid} .*\(waited 0.5 s\)"), scene_lock(scene, wait_s=0.5):
            pass
        assert 0.5 <= time.monotonic() - t0 < 1.5
        with scene_lock(scene, wait_s=30) as lock_file:
            assert time.monotonic() - t0 > 1.8  # we got in only once the holder had finished
            assert holder.wait(timeout=10) == 0
            assert json.loads(lock_file.read_text())["pid"] == os.getpid()
        assert lock_file.read_text() == ""  # released: no stale details left to mislead a later reader
    finally:
        stop(holder)


def test_a_killed_holder_frees_the_scene(scene: Path):
    holder = hold(scene, 120)
    try:
        assert json.loads((scene / LOCK_NAME).read_text())["pid"] == holder.pid
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait(timeout=10)
        t0 = time.monotonic()
        with scene_lock(scene):  # no waiting: the kernel released the dead holder's lock
            assert json.loads((scene / LOCK_NAME).read_text())["pid"] == os.getpid()
        assert time.monotonic() - t0 < 1.0
    finally:
        stop(holder)


def test_two_writers_in_one_process_also_exclude_each_other(scene: Path):
    with scene_lock(scene), pytest.raises(StoreError, match=f"pid {os.getpid()} "), scene_lock(scene):
        pass


def test_lock_creates_a_new_scene_folder_and_refuses_a_foreign_one_untouched(tmp_path: Path):
    new = tmp_path / "a" / "new"
    with scene_lock(new):
        SceneStore.open_or_create(new)  # the lock file alone does not make the folder "not empty"
    assert sorted(p.name for p in new.iterdir()) == sorted([LOCK_NAME, "scene.zarr"])

    foreign = tmp_path / "photos"
    foreign.mkdir()
    (foreign / "holiday.jpg").write_bytes(b"\xff\xd8")
    with pytest.raises(StoreError, match="not empty and holds no scene"), scene_lock(foreign):
        pass
    assert [p.name for p in foreign.iterdir()] == ["holiday.jpg"]

    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(StoreError, match="not a folder"), scene_lock(blocker):
        pass
    with pytest.raises(StoreError, match="cannot write to output folder"), scene_lock(blocker / "scene"):
        pass


def test_a_bad_output_folder_is_refused_before_anything_is_made(tmp_path: Path):
    from wonderverse.store import check_scene_dir

    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    cases = [
        (a_file, "is not a folder"),
        (a_file / "deeper" / "scene", "a-file is not a folder"),
        (tmp_path, "not empty and holds no scene"),
    ]
    if os.geteuid() != 0:  # root may write anywhere
        cases.append((locked / "scene", "permission denied"))
    before = sorted(p.name for p in tmp_path.rglob("*"))
    for path, message in cases:
        with pytest.raises(StoreError, match=message):
            check_scene_dir(path)
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing created
    check_scene_dir(tmp_path / "new" / "scene")  # a folder that can be made is fine
    assert not (tmp_path / "new").exists()
