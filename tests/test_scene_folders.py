"""Default scene folders (no --out): many prompts share a folder name, and a run never silently replaces a scene
made from another prompt; it takes the next free name and says so on its first line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT

from flows.cli import _default_out, _default_scene_folder
from wonderverse.store import SceneStore


def make_scene(folder: Path, prompt: str) -> None:
    SceneStore.open_or_create(folder, spec={"prompt": prompt})


@pytest.mark.parametrize(
    ("first", "second", "folder"),
    [("a house, decorated!", "A HOUSE -- decorated", "a-house-decorated"), ("🎄🎄", "🔥", "scene")],
)
def test_prompts_sharing_a_folder_name_get_their_own_folders(tmp_path, monkeypatch, first, second, folder):
    monkeypatch.chdir(tmp_path)
    assert _default_out(first) == _default_out(second) == Path("scenes") / folder  # the collision
    assert _default_scene_folder(first) == (Path("scenes") / folder, "")
    make_scene(Path("scenes") / folder, first)
    assert _default_scene_folder(first) == (Path("scenes") / folder, "")  # its own scene: the same folder
    taken = f"scenes/{folder} holds another scene"
    assert _default_scene_folder(second) == (Path("scenes") / f"{folder}-2", taken)
    make_scene(Path("scenes") / f"{folder}-2", second)
    assert _default_scene_folder(second) == (Path("scenes") / f"{folder}-2", taken)  # found again
    assert _default_scene_folder(f"{first} at night")[0] != Path("scenes") / folder


def test_a_folder_holding_other_files_or_an_unreadable_store_is_skipped(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scenes" / "a-forest").mkdir(parents=True)
    (tmp_path / "scenes" / "a-forest" / "notes.txt").write_text("mine")
    (tmp_path / "scenes" / "a-forest-2" / "scene.zarr").mkdir(parents=True)  # no zarr.json: not a readable store
    (tmp_path / "scenes" / "a-forest-3").write_text("a file, not a folder")
    (tmp_path / "scenes" / "a-forest-4").mkdir()  # empty: free
    assert _default_scene_folder("a forest")[0] == Path("scenes") / "a-forest-4"


def cli_in(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [sys.executable, "-m", "flows", *args], capture_output=True, text=True, timeout=300, env=env, cwd=cwd
    )


@pytest.mark.e2e
def test_generate_without_out_keeps_another_prompts_scene_and_says_where_it_went(tmp_path):
    r = cli_in(tmp_path, "generate", "a house, decorated!", "--until", "plan", "--engine", "local")
    assert r.returncode == 0, r.stderr
    assert r.stderr.splitlines()[0].endswith("scene scenes/a-house-decorated"), r.stderr
    first = (tmp_path / "scenes" / "a-house-decorated" / "scene.zarr" / "zarr.json").read_bytes()

    r = cli_in(tmp_path, "generate", "A HOUSE -- decorated", "--until", "plan", "--engine", "local")
    assert r.returncode == 0, r.stderr
    line = r.stderr.splitlines()[0]
    assert line.endswith("scene scenes/a-house-decorated-2 (scenes/a-house-decorated holds another scene)"), line
    assert (tmp_path / "scenes" / "a-house-decorated" / "scene.zarr" / "zarr.json").read_bytes() == first
    assert SceneStore.open(tmp_path / "scenes" / "a-house-decorated-2").root.attrs["spec"]["prompt"] == (
        "A HOUSE -- decorated"
    )

    r = cli_in(tmp_path, "generate", "a house, decorated!", "--until", "plan", "--engine", "local")
    assert r.returncode == 0 and r.stderr.splitlines()[0].endswith("scene scenes/a-house-decorated"), r.stderr
    assert "] plan: cached" in r.stderr, r.stderr
