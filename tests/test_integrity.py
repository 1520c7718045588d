"""Integrity of the scene store: digests recorded at commit, verified on read and before a step is skipped.

Each kind of damage (a chunk deleted, truncated, emptied or with one byte altered; an array's metadata damaged)
is done to a copy of one tiny scene, on a segment's frames (written by generate_segments) and on the global SfM
points (written by poses): `inspect` lists the group, a read raises DamagedData naming it (never zeros), and the
same run again rebuilds it with the step that wrote it, leaving the outputs byte-identical."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import complete_config, run_cli, tree_digest

from flows.inspect import damaged_lines, scene_summary
from flows.pipeline import StepFailed, _direct, execute
from wonderverse.config import RunConfig
from wonderverse.errors import WonderError
from wonderverse.schema import ATTEMPT, SEGMENT, SFM
from wonderverse.store import DIGESTS, DamagedData, SceneStore, cache_key, write_array

FRAMES = ATTEMPT.at(seg="s000", attempt=0).frames
FRAMES_GROUP = SEGMENT.at(seg="s000")  # generate_segments commits a segment with its first attempt's frames
TARGETS = {  # array -> (the committed group it belongs to, the step that wrote it, a chunk of it)
    "frames": (FRAMES, FRAMES_GROUP, "generate_segments", "c/2/0/0/0"),
    "points3d": (SFM.points3d, SFM.path, "poses", "c/0/0"),
}


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, RunConfig]:
    cfg = complete_config()
    scene = tmp_path_factory.mktemp("integrity") / "scene"
    assert [r.status for r in execute(scene, cfg)] == ["ran"] * 7
    return scene, cfg


def _outputs(scene: Path) -> dict[str, bytes]:
    """The files beside the store (what users open), by path."""
    return {
        str(p.relative_to(scene)): p.read_bytes()
        for p in sorted(scene.rglob("*"))
        if p.is_file() and "scene.zarr" not in p.parts and p.name != ".wonderverse.lock"
    }


def _delete(f: Path) -> None:
    f.unlink()


def _truncate(f: Path) -> None:
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])


def _empty(f: Path) -> None:
    f.write_bytes(b"")


def _alter(f: Path) -> None:
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0x40
    f.write_bytes(bytes(data))


DAMAGE: dict[str, Callable[[Path], None]] = {
    "deleted": _delete,
    "truncated": _truncate,
    "zero-byte": _empty,
    "altered": _alter,
}


def _damage(scene: Path, array: str, chunk: str, kind: str) -> None:
    folder = scene / "scene.zarr" / array
    if kind == "metadata":
        meta = json.loads((folder / "zarr.json").read_text())
        del meta["data_type"]
        (folder / "zarr.json").write_text(json.dumps(meta))
    else:
        DAMAGE[kind](folder / chunk)


@pytest.mark.e2e
@pytest.mark.parametrize("target", sorted(TARGETS))
@pytest.mark.parametrize("kind", [*DAMAGE, "metadata"])
def test_damaged_data_is_listed_refused_on_read_and_rebuilt_by_its_step(
    made: tuple[Path, RunConfig], tmp_path: Path, target: str, kind: str
):
    original, cfg = made
    array, group, step, chunk = TARGETS[target]
    truth = SceneStore.open(original).array(array)
    scene = tmp_path / "scene"
    shutil.copytree(original, scene)
    _damage(scene, array, chunk, kind)

    store = SceneStore.open(scene)  # read-only, as inspect opens it: it reports and changes nothing
    info = scene_summary(store)
    assert [d.group for d in info.damaged] == [group]
    assert damaged_lines(info)[0].startswith(f"damaged: {group}: ")
    with pytest.raises(DamagedData) as err:
        store.array(array)  # never the fill value in place of a missing chunk
    assert err.value.group == group and group in str(err.value) and "\n" not in str(err.value)
    assert isinstance(err.value, WonderError)  # the CLI prints it as one `error:` line
    assert not store.is_complete(group, store.group(group).attrs["cache_key"])  # kept, though now incomplete

    results = {r.step: r.status for r in execute(scene, cfg)}
    assert results == {s: ("ran" if s == step else "cached") for s in results}
    repaired = SceneStore.open(scene)
    assert repaired.damaged_groups() == {}
    assert _outputs(scene) == _outputs(original)
    rebuilt = repaired.array(array)
    if target == "frames":  # rendering is deterministic: the frames come back as they were
        np.testing.assert_array_equal(rebuilt, truth)
        # the units the check committed inside the segment were kept through the rewrite
        for unit in (SEGMENT.at(seg="s000").accepted, ATTEMPT.at(seg="s000", attempt=0).sfm):
            assert repaired.cache_key_of(unit) is not None  # complete
    else:  # the global SfM (two threads) is not bit-reproducible: a full solve of the same frames again
        assert rebuilt.shape[1] == 3 and np.isfinite(rebuilt).all() and len(rebuilt) > 0.8 * len(truth)


@pytest.mark.e2e
def test_inspect_json_lists_the_damaged_group(made: tuple[Path, RunConfig], tmp_path: Path):
    original, _ = made
    scene = tmp_path / "scene"
    shutil.copytree(original, scene)
    _damage(scene, SFM.points3d, "c/0/0", "deleted")
    before = tree_digest(scene)
    out = run_cli("inspect", str(scene), "--json")
    assert out.returncode == 0, out.stderr
    damaged = json.loads(out.stdout)["damaged"]
    assert damaged == [{"group": SFM.path, "problems": ["chunk c/0/0 of array points3d is missing"]}]
    text = run_cli("inspect", str(scene))
    assert text.returncode == 0 and f"damaged: {SFM.path}: chunk c/0/0 of array points3d is missing" in text.stdout
    assert tree_digest(scene) == before  # inspect changes nothing


@pytest.mark.e2e
def test_damaged_input_read_by_a_step_fails_in_one_line_naming_the_group_then_the_next_run_rebuilds_it(
    made: tuple[Path, RunConfig], tmp_path: Path
):
    """Damage done after the upstream step was judged complete (here: just before priors runs, which reads the
    SfM points) fails that step in one line naming the group; the next run re-runs poses, then priors."""
    original, cfg = made
    scene = tmp_path / "scene"
    shutil.copytree(original, scene)
    SceneStore.open(scene, mode="r+").remove("priors")  # so that priors runs and reads sfm/points3d

    def damaging_call(step, scene_dir, params, ctx):  # type: ignore[no-untyped-def]
        if step.name == "priors":
            _damage(Path(scene_dir), SFM.points3d, "c/0/0", "altered")
        return _direct(step, scene_dir, params, ctx)

    with pytest.raises(StepFailed) as err:
        execute(scene, cfg, call=damaging_call)
    message = str(err.value)
    assert "\n" not in message and f"damaged scene data in {SFM.path}: " in message
    assert "differs from what was written" in message
    assert isinstance(err.value.cause, DamagedData) and err.value.cause.group == SFM.path
    results = {r.step: r.status for r in execute(scene, cfg)}
    assert results["poses"] == "ran" and results["priors"] == "ran" and results["splats"] == "cached"
    assert SceneStore.open(scene).damaged_groups() == {}


def test_groups_committed_before_digests_are_read_unverified_without_alarm(tmp_path: Path):
    store = SceneStore.open_or_create(tmp_path / "scene")
    key = cache_key("x", 1, {})
    data = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    with store.staged("a", key) as g:
        write_array(g, "data", data)
    assert DIGESTS in store.group("a").attrs  # recorded beside the attributes, never read as one of them
    del store.group("a").attrs[DIGESTS]  # as a store written before digests existed
    assert store.is_complete("a", key) and store.damaged_groups() == {}
    np.testing.assert_array_equal(store.array("a/data"), data)
    # their damaged metadata still ends in one DamagedData line, never a KeyError from zarr
    meta_file = store.path / "a" / "data" / "zarr.json"
    meta = json.loads(meta_file.read_text())
    del meta["data_type"]
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(DamagedData, match=r"in a: array data: its data type .None. is not a number.s"):
        store.array("a/data")


def test_a_rewrite_under_another_key_drops_what_other_steps_kept_inside(tmp_path: Path):
    """Only a repair (the same key) keeps the units committed inside the old version; new settings do not."""
    store = SceneStore.open_or_create(tmp_path / "scene")
    old, new = cache_key("seg", 1, {}), cache_key("seg", 2, {})
    with store.staged("s", old) as g:
        write_array(g, "frames", np.ones((2, 4, 4, 3), np.uint8))
    with store.staged("s/unit", cache_key("unit", 1, {})) as g:  # committed inside "s" by another step
        write_array(g, "x", np.arange(3.0))
    _damage(tmp_path / "scene", "s/frames", "c/1/0/0/0", "altered")
    assert not store.is_complete("s", old)
    with store.staged("s", old) as g:  # the repair
        write_array(g, "frames", np.ones((2, 4, 4, 3), np.uint8))
    assert store.is_complete("s", old) and store.cache_key_of("s/unit") is not None
    np.testing.assert_array_equal(store.array("s/unit/x"), np.arange(3.0))
    with store.staged("s", new) as g:
        write_array(g, "frames", np.zeros((2, 4, 4, 3), np.uint8))
    assert store.is_complete("s", new) and not store.exists("s/unit")
