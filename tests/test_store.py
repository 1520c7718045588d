"""Scene store: atomic staged commits, cache keys, refusal of bad folders, SIGKILL mid-write."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from wonderverse import STORE_FORMAT
from wonderverse.errors import StoreError
from wonderverse.store import SceneStore, cache_key, write_array


def test_cache_key_is_a_merkle_hash_of_its_parts():
    base = cache_key("check", 1, {"t1": 5.0}, ["abc"])
    assert base == cache_key("check", 1, {"t1": 5.0}, ["abc"])
    assert (
        len(
            {
                base,
                cache_key("check", 2, {"t1": 5.0}, ["abc"]),
                cache_key("check", 1, {"t1": 5.1}, ["abc"]),
                cache_key("check", 1, {"t1": 5.0}, ["abd"]),
                cache_key("sfm", 1, {"t1": 5.0}, ["abc"]),
            }
        )
        == 5
    )
    # key order of params does not matter; numpy values hash like Python ones
    assert cache_key("s", 1, {"a": 1, "b": 2}) == cache_key("s", 1, {"b": np.int64(2), "a": 1})


def test_staged_commit_is_invisible_until_done_and_rolls_back_on_error(tmp_path: Path):
    store = SceneStore.open_or_create(tmp_path / "scene")
    key = cache_key("x", 1, {})
    with store.staged("a/b", key, note="hi") as g:
        write_array(g, "data", np.arange(12, dtype=np.float32).reshape(3, 4))
        assert not store.exists("a/b")  # nothing visible before the commit
    assert store.is_complete("a/b", key)
    assert store.group("a/b").attrs["note"] == "hi"  # an undeclared group: its raw JSON
    np.testing.assert_array_equal(store.array("a/b/data"), np.arange(12).reshape(3, 4))

    with pytest.raises(RuntimeError), store.staged("a/b", cache_key("x", 2, {})) as g:
        write_array(g, "data", np.zeros((3, 4), np.float32))
        raise RuntimeError("boom")
    # the old complete version survives a failed rewrite, and no staging leftovers remain
    assert store.is_complete("a/b", key)
    np.testing.assert_array_equal(store.array("a/b/data")[0], [0, 1, 2, 3])
    assert not [p for p in (store.path / "_staging").iterdir() if p.is_dir()]


def test_rewrite_replaces_group_and_key(tmp_path: Path):
    store = SceneStore.open_or_create(tmp_path / "scene")
    k1, k2 = cache_key("x", 1, {}), cache_key("x", 2, {})
    with store.staged("g", k1) as g:
        write_array(g, "old", np.ones(3))
    with store.staged("g", k2) as g:
        write_array(g, "new", np.ones(3))
    assert store.is_complete("g", k2) and not store.is_complete("g", k1)
    assert store.children("g") == ["new"]


def test_sibling_groups_staged_at_once_all_land(tmp_path: Path):
    # Per-segment groups are written concurrently (threads here, Dask workers in a run) under a
    # parent none of them has created yet; zarr's open-or-create checks, then creates, so the
    # losers of that race must not fail. Without the guard this failed in ~40 % of rounds.
    store = SceneStore.open_or_create(tmp_path / "scene")
    writers, rounds = 8, 20

    def stage(group: str, start: threading.Barrier) -> None:
        start.wait()
        with store.staged(group, "k") as g:
            g.attrs["group"] = group

    with ThreadPoolExecutor(writers) as pool:
        for r in range(rounds):
            start = threading.Barrier(writers)
            list(pool.map(stage, [f"p{r}/seg_{j}" for j in range(writers)], [start] * writers))
    for r in range(rounds):
        assert store.children(f"p{r}") == [f"seg_{j}" for j in range(writers)]
        assert all(store.is_complete(f"p{r}/seg_{j}", "k") for j in range(writers))


def test_refuses_foreign_folder_newer_format_and_unwritable(tmp_path: Path):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "precious.txt").write_text("keep me")
    with pytest.raises(StoreError, match="not empty"):
        SceneStore.open_or_create(foreign)
    assert (foreign / "precious.txt").read_text() == "keep me"

    store = SceneStore.open_or_create(tmp_path / "scene")
    store.root.attrs["format"] = STORE_FORMAT + 1
    with pytest.raises(StoreError, match="newer"):
        SceneStore.open(tmp_path / "scene")

    with pytest.raises(StoreError, match="no scene store"):
        SceneStore.open(tmp_path / "nothing")

    if os.geteuid() != 0:  # root can write anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(StoreError, match="cannot write"):
            SceneStore.open_or_create(locked / "scene")
    with pytest.raises(StoreError, match=r"cannot write|not a folder"):
        SceneStore.open_or_create(Path("/proc/version/scene"))


_CHILD = """
import sys, time, numpy as np
from pathlib import Path
from wonderverse.store import SceneStore, cache_key
store = SceneStore.open_or_create(sys.argv[1])
with store.staged("big", cache_key("big", 1, {})) as g:
    arr = g.create_array("data", shape=(200, 64, 64), dtype="f4", chunks=(1, 64, 64))
    for i in range(200):
        arr[i] = i
        if i == 20:
            Path(sys.argv[2]).touch()   # tell the parent we are mid-write
        time.sleep(0.02)
"""


def test_sigkill_mid_step_leaves_nothing_visible_and_next_run_redoes_it(tmp_path: Path):
    scene, marker = tmp_path / "scene", tmp_path / "mid-write"
    store = SceneStore.open_or_create(scene)
    done_key = cache_key("done", 1, {})
    with store.staged("done", done_key) as g:
        write_array(g, "x", np.ones(4))

    child = subprocess.Popen([sys.executable, "-c", _CHILD, str(scene), str(marker)])
    deadline = time.monotonic() + 60
    while not marker.exists():
        assert child.poll() is None, "child exited before reaching the middle of its write"
        assert time.monotonic() < deadline
        time.sleep(0.01)
    child.send_signal(signal.SIGKILL)
    child.wait()

    store = SceneStore.open(scene, mode="r+")
    assert not store.exists("big") and store.cache_key_of("big") is None
    assert store.is_complete("done", done_key)  # earlier work untouched
    assert [p for p in (store.path / "_staging").iterdir() if p.is_dir()]  # half-written: only in staging
    store.clean_staging()
    assert not (store.path / "_staging").exists()
    subprocess.run([sys.executable, "-c", _CHILD, str(scene), str(marker)], check=True, timeout=120)
    store = SceneStore.open(scene)
    assert store.is_complete("big", cache_key("big", 1, {}))
    assert store.array("big/data")[199, 0, 0] == 199
