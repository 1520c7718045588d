"""Registering an extension's new frames into an existing reconstruction (real pycolmap, procedural world):
old poses stay bit-identical, new frames land on the ground-truth path, bad new frames give problems, and
the `poses` step takes the incremental path only when the old segments are unchanged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from wonderverse.camera import CameraPrior, camera_centers, move_path, umeyama
from wonderverse.features import sequential_pairs
from wonderverse.sfm import SfmParams, SfmWorkspace, reconstruct
from wonderverse.sfm_extend import extend_reconstruction

W, H, T = 128, 96, 8
# One thread and a fixed seed: COLMAP is then reproducible, so the measured bounds below hold run to run.
PARAMS = SfmParams(max_image_size_px=480, num_threads=1, random_seed=0, hold_known_intrinsics=False)


@pytest.fixture(scope="module")
def world() -> dict:
    """Four segments of one procedural world: s000 and s001 (the scene), s002 continuing s001, s003 a left
    extension from s000's first frame (played reversed, before the others)."""
    from wonderverse.video.procedural import ProceduralVideo

    video = ProceduralVideo("a quiet village with houses and trees", 0, W, H, 60.0, {"fault_probability": 0.0})
    paths = {"s000": move_path(video.world.start_pose(), np.radians(-10), 0.0, 1.0, 0.0, T)}
    paths["s001"] = move_path(paths["s000"][-1], np.radians(-20), 0.0, 0.6, -0.6, T)  # bends: not collinear
    paths["s002"] = move_path(paths["s001"][-1], np.radians(-15), 0.0, 1.0, 0.0, T)
    paths["s003"] = move_path(paths["s000"][0], np.radians(25), 0.0, 0.3, 0.8, T)
    frames = {s: video.generate("", p, 0, None).frames for s, p in paths.items()}
    return {"paths": paths, "frames": frames, "K": video.K}


def stitched(world: dict, segs: list[str]) -> tuple[list[str], list[np.ndarray], np.ndarray]:
    """Names, frames and ground-truth W2C poses in stitched order (extensions drop their frame 0, which
    repeats their reference; the left one s003 plays reversed)."""
    names, frames, gt = [], [], []
    for s in segs:
        idx = np.arange(T) if s == "s000" else np.arange(1, T)
        idx = idx[::-1] if s == "s003" else idx
        names += [f"{s}_{i:04d}.png" for i in idx]
        frames += list(world["frames"][s][idx])
        gt.append(world["paths"][s][idx])
    return names, frames, np.concatenate(gt)


@pytest.fixture(scope="module")
def scene(world: dict) -> dict:
    names, frames, gt = stitched(world, ["s000", "s001"])
    prior = CameraPrior(world["K"], "given")  # refined (PARAMS: not held), as the global poses step does
    res = reconstruct(frames, PARAMS, prior, names=names, keep_workspace=True)
    assert res.gates_passed, res.problems
    return {"names": names, "gt": gt, "res": res}


def _new_frames(world: dict, names: list[str], old: list[str]) -> dict[str, np.ndarray]:
    return {n: world["frames"][n[:4]][int(n[5:9])] for n in names if n not in old}


def _new_frame_error(poses: np.ndarray, gt: np.ndarray, old: np.ndarray) -> float:
    """RMS distance of the new frames' centres to ground truth after one Sim(3) fitted on the OLD frames
    only, as a fraction of the path length."""
    sim = umeyama(camera_centers(poses[old]), camera_centers(gt[old]))
    err = np.linalg.norm(sim.apply(camera_centers(poses)) - camera_centers(gt), axis=1)
    length = np.linalg.norm(np.diff(camera_centers(gt), axis=0), axis=1).sum()
    return float(np.sqrt(np.mean(err[~old] ** 2)) / length)


def test_workspace_holds_the_callers_names_and_pairs_follow_colmaps_sequential_matcher(
    scene: dict, tmp_path: Path
) -> None:
    import pycolmap

    ws = scene["res"].workspace
    assert isinstance(ws, SfmWorkspace) and {"cameras.bin", "images.bin", "points3D.bin"} <= set(ws.model)
    db_path, model_dir = ws.restore(tmp_path)
    assert {im.name for im in pycolmap.Reconstruction(model_dir).images.values()} == set(scene["names"])
    db = pycolmap.Database.open(db_path)
    try:
        by_id = {im.image_id: im.name for im in db.read_all_images()}
        ordered = sorted(by_id.values())  # COLMAP's sequential matcher orders by name; ours here agree
        for overlap, quadratic in ((1, False), (3, False), (3, True), (10, True)):
            opts = pycolmap.SequentialPairingOptions()
            opts.overlap, opts.quadratic_overlap, opts.loop_detection = overlap, quadratic, False
            colmap = {
                tuple(sorted((by_id[a], by_id[b]))) for a, b in pycolmap.SequentialPairGenerator(opts, db).all_pairs()
            }
            ours = {(ordered[i], ordered[j]) for i, j in sequential_pairs(len(ordered), overlap, quadratic)}
            assert ours == colmap, (overlap, quadratic)
    finally:
        db.close()


def test_extension_appended_then_prepended_keeps_old_poses_and_follows_the_path(world: dict, scene: dict) -> None:
    old_names, old_res = scene["names"], scene["res"]
    names, _, gt = stitched(world, ["s000", "s001", "s002"])
    res, ws = extend_reconstruction(old_res.workspace, names, _new_frames(world, names, old_names), PARAMS)
    old = np.isin(names, old_names)
    assert res.gates_passed, res.problems
    assert res.registered.all() and res.mapper == "incremental"
    np.testing.assert_array_equal(res.poses[old], old_res.poses)  # bit-identical
    np.testing.assert_array_equal(res.K, old_res.K)  # intrinsics held fixed
    assert res.n_points > old_res.n_points and res.colors.any(axis=1).all()  # new points got colours
    assert {"write", "extract", "match", "map_incremental", "total"} <= set(res.timings)
    # measured 0.042 (one thread, seed 0); for scale: a full global re-solve of these 22 + 7 frames is 8 % off
    assert _new_frame_error(res.poses, gt, old) < 0.08

    # a left extension is prepended: its frames come first in the order, and the workspace returned chains
    names2, _, gt2 = stitched(world, ["s003", "s000", "s001", "s002"])
    res2, _ = extend_reconstruction(ws, names2, _new_frames(world, names2, names), PARAMS)
    old2 = np.isin(names2, names)
    assert res2.gates_passed and res2.registered.all(), res2.problems
    np.testing.assert_array_equal(res2.poses[old2], res.poses)
    np.testing.assert_array_equal(res2.poses[np.isin(names2, old_names)], old_res.poses)
    assert _new_frame_error(res2.poses, gt2, old2) < 0.08  # measured 0.036


def test_new_frames_that_do_not_register_give_problems_not_errors(world: dict, scene: dict) -> None:
    from wonderverse.video.procedural import ProceduralVideo

    old_names, ws = scene["names"], scene["res"].workspace
    names, _, _ = stitched(world, ["s000", "s001", "s002"])
    new = [n for n in names if n not in old_names]
    flat = {n: np.full((H, W, 3), 128, np.uint8) for n in new}
    indoor = ProceduralVideo("a living room", 5, W, H, 60.0, {"fault_probability": 0.0, "world": "indoor"})
    other = indoor.generate("", move_path(indoor.world.start_pose(), 0.3, 0.0, 0.5, 0.0, len(new)), 0, None)
    for frames in (flat, dict(zip(new, other.frames, strict=True))):
        res, _ = extend_reconstruction(ws, names, frames, PARAMS)
        assert not res.gates_passed and f"only 0 of {len(new)} new frames registered" in res.problems
        assert res.registered.sum() == len(old_names) and np.isnan(res.poses[~np.isin(names, old_names)]).all()
        np.testing.assert_array_equal(res.poses[np.isin(names, old_names)], scene["res"].poses)
    small = {n: np.zeros((H // 2, W // 2, 3), np.uint8) for n in new}
    res, same = extend_reconstruction(ws, names, small, PARAMS)
    assert same is ws and not res.gates_passed
    assert res.problems[0] == f"frames have 2 different sizes ({W // 2}x{H // 2}, {W}x{H}); one camera needs one size"


def test_invalid_arguments_raise_value_error(scene: dict) -> None:
    ws, names = scene["res"].workspace, scene["names"]
    frame = np.zeros((H, W, 3), np.uint8)
    with pytest.raises(ValueError, match="order misses"):
        extend_reconstruction(ws, names[1:], {}, PARAMS)
    with pytest.raises(ValueError, match="exactly the 1 names"):
        extend_reconstruction(ws, [*names, "s009_0001.png"], {"s009_0002.png": frame}, PARAMS)
    with pytest.raises(ValueError, match="unique"):
        extend_reconstruction(ws, [*names, names[0]], {}, PARAMS)
    with pytest.raises(ValueError, match="uint8"):
        extend_reconstruction(ws, [*names, "s009_0001.png"], {"s009_0001.png": frame.astype(float)}, PARAMS)
    with pytest.raises(ValueError, match="one per frame"):
        reconstruct(np.zeros((3, H, W, 3), np.uint8), names=["a.png"])
    with pytest.raises(ValueError, match="plain file names"):
        reconstruct(np.zeros((1, H, W, 3), np.uint8), names=["../a.png"])


# ---------------------------------------------------------------------------------------- the poses step


def _put_segment(store, world: dict, seg: str, role: str, frames: np.ndarray | None = None) -> None:
    """A procedural segment as `generate_segments` writes it (attempt 0, no check yet: attempt 0 counts; the
    renderer's K is known, so no parallax look decides the outcome on these 128-px frames)."""
    from wonderverse.store import cache_key, write_array

    frames = world["frames"][seg] if frames is None else frames
    attrs = {"role": role, "reversed": role == "left", "repeats_reference": role != "init", "k_is_guess": False}
    with store.staged(f"segments/{seg}", cache_key("segment", 1, {"segment": seg}), **attrs) as g:
        write_array(g, "path", np.full((len(frames), 4, 4), np.nan), chunks=(len(frames), 4, 4))
        write_array(g, "K", np.asarray(world["K"], np.float64), chunks=(3, 3))
        write_array(g.create_group("attempts/0"), "frames", frames)


@pytest.mark.e2e
def test_poses_step_registers_an_extension_into_the_stored_reconstruction(world: dict, tmp_path: Path) -> None:
    from conftest import tiny_config

    from tasks import poses
    from tasks.base import StepContext
    from wonderverse.global_poses import can_extend
    from wonderverse.store import SceneStore

    store = SceneStore.open_or_create(tmp_path / "scene")
    cfg = tiny_config()
    _put_segment(store, world, "s000", "init")
    _put_segment(store, world, "s001", "right")
    store.mark_complete("segments", "k1", order=["s000", "s001"])
    p = poses.params(cfg)
    poses.run(store, p, StepContext("key1"))
    first = store.meta("sfm")
    assert first.solve == "full" and first.sfm_names[0] == "50000000_s000_0000.png"
    assert first.sfm_names == sorted(first.sfm_names)  # COLMAP numbers images in this order
    assert store.exists("sfm/colmap_database") and "images.bin" in store.children("sfm/colmap_model")
    before = {k: store.array(f"sfm/{k}") for k in ("poses", "registered", "frame_index", "K")}

    _put_segment(store, world, "s003", "left")  # prepended, reversed: every old stitched position shifts
    store.mark_complete("segments", "k2", order=["s003", "s000", "s001"])
    summary = poses.run(store, p, StepContext("key2"))
    a = store.meta("sfm")
    assert a.solve == "incremental" and "incremental solve" in summary, a.incremental_problems
    assert a.segments == ["s000", "s001", "s003"] and a.new_frames == T - 1 and not a.problems
    assert a.model_to_world == first.model_to_world
    after = {k: store.array(f"sfm/{k}") for k in ("poses", "registered", "frame_index", "K")}
    np.testing.assert_array_equal(after["K"], before["K"])
    old_rows = {tuple(fi): k for k, fi in enumerate(after["frame_index"])}  # segment numbers are unchanged
    rows = [old_rows[tuple(fi)] for fi in before["frame_index"]]
    np.testing.assert_array_equal(after["poses"][rows], before["poses"])  # old frames: exactly as before
    assert after["registered"].all() and np.isfinite(after["poses"]).all()
    assert set(first.sfm_names) < set(a.sfm_names) and a.sfm_names == sorted(a.sfm_names)
    assert a.sfm_names[0] == f"4999{9999 - (T - 1)}_s003_{T - 1:04d}.png"  # prepended, reversed, yet in order

    # new frames that do not register: the step says why and re-solves every frame
    _put_segment(store, world, "s004", "right", np.full((T, H, W, 3), 128, np.uint8))
    store.mark_complete("segments", "k3", order=["s003", "s000", "s001", "s004"])
    poses.run(store, p, StepContext("key3"))
    a3 = store.meta("sfm")
    assert a3.solve == "full" and f"only 0 of {T - 1} new frames registered" in a3.incremental_problems
    assert a3.kept_frame["shared_frames"] >= 3 * (T - 1)  # mapped into the previous world frame

    # a further extension qualifies; anything else (another accepted attempt of s001, other SfM settings)
    # means a full solve
    p = cfg.steps.poses
    names = [*a3.sfm_names, "50020001_s005_0001.png"]
    name_seg = {n: n.split("_")[1] for n in names}
    sources = poses._sources(store, a3.segments) | {"s005": {"key": "x", "attempt": 0}}
    previous, key = poses._previous(store), poses._workspace_key(p)
    assert can_extend(previous, key, names, name_seg, sources)
    changed = sources | {"s001": {**sources["s001"], "attempt": 1}}
    assert not can_extend(previous, key, names, name_seg, changed)
    other = p.model_copy(update={"sfm": p.sfm.model_copy(update={"matcher_overlap": 3})})
    assert not can_extend(previous, poses._workspace_key(other), names, name_seg, sources)


def test_frame_selection_per_segment_is_stable_when_a_segment_is_prepended() -> None:
    from wonderverse.global_poses import select_frames

    a = [("s000", i) for i in range(9)] + [("s001", i) for i in range(1, 9)]
    b = [("s002", i) for i in range(8, 0, -1)] + a
    pick = lambda index, stride: {index[k] for k in select_frames(index, stride)}  # noqa: E731
    assert pick(a, 1) == set(a)
    assert pick(a, 3) == {("s000", i) for i in (0, 3, 6, 8)} | {("s001", i) for i in (1, 3, 6, 8)}
    assert pick(a, 3) <= pick(b, 3) and pick(b, 3) - pick(a, 3) == {("s002", i) for i in (8, 6, 3, 1)}
