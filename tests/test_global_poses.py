"""wonderverse.global_poses on constructed arrays: a Sim(3) applied and recovered, the merge of an
extension, the re-solve loop, the segments' disagreement, interpolation and COLMAP image names."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from wonderverse.camera import Sim3, camera_centers, look_at, move_path
from wonderverse.global_poses import (
    PreviousSolve,
    can_extend,
    fill_poses,
    image_names,
    map_into_previous,
    merge_incremental,
    segment_disagreement,
    segment_turn_error,
    solve_consistent,
)
from wonderverse.sfm import SfmResult


def _path(n: int, seed: int = 0) -> np.ndarray:
    """W2C poses (n,4,4) along a gently curving track at 1.5 m height, looking ahead."""
    rng = np.random.default_rng(seed)
    a = np.linspace(0, 0.8, n)
    eyes = np.stack([4 * np.sin(a), 4 * (1 - np.cos(a)), 1.5 + 0.1 * rng.normal(size=n)], -1)
    ahead = eyes + np.stack([np.cos(a), np.sin(a), np.zeros(n)], -1)
    return np.stack([look_at(e, t) for e, t in zip(eyes, ahead, strict=True)])


def _keys(seg: str, n: int) -> list[tuple[str, int]]:
    return [(seg, i) for i in range(n)]


def _result(poses: np.ndarray, registered: np.ndarray, points: np.ndarray | None = None) -> SfmResult:
    pts = np.zeros((0, 3)) if points is None else points
    return SfmResult(poses, registered, pts, np.zeros((len(pts), 3), np.uint8), np.eye(3), 0.5, len(pts), "global")


TRUE = Sim3(2.5, Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix(), np.array([3.0, -1.0, 0.5]))


def test_a_resolve_is_mapped_back_into_the_previous_world_frame() -> None:
    world = _path(12)
    index = _keys("s000", 12)
    points_world = np.random.default_rng(1).normal(size=(30, 3)) * 3
    # the new solve sees the same scene in SfM's own frame: the world moved by TRUE
    new, points_new = TRUE.transform_w2c(world), TRUE.apply(points_world)
    new[5] = np.nan  # a frame the new solve did not pose
    previous = dict(zip(index, world, strict=True))
    out, points, info, sim = map_into_previous(index, new, points_new, previous)
    fin = np.isfinite(new).all(axis=(1, 2))
    np.testing.assert_allclose(out[fin], world[fin], atol=1e-9)
    assert np.isnan(out[5]).all()
    np.testing.assert_allclose(points, points_world, atol=1e-9)
    assert info == {"shared_frames": 11, "scale": pytest.approx(1 / TRUE.s)}
    np.testing.assert_allclose(sim.matrix(), TRUE.inverse().matrix(), atol=1e-9)


def test_without_a_previous_solve_or_three_shared_frames_nothing_moves() -> None:
    world, index = _path(6), _keys("s000", 6)
    pts = np.ones((2, 3))
    for previous in (None, {index[0]: world[0], index[1]: world[1], ("s009", 0): world[2]}):
        out, points, info, sim = map_into_previous(index, TRUE.transform_w2c(world), pts, previous)
        np.testing.assert_array_equal(out, TRUE.transform_w2c(world))
        assert points is pts and info is None and np.array_equal(sim.matrix(), np.eye(4))


def test_an_extension_keeps_the_old_poses_and_maps_the_new_frames() -> None:
    world = _path(14)
    index = [("s001", i) for i in range(6, 0, -1)] + _keys("s000", 8)  # a left extension prepended
    old_keys = index[6:]
    old = {k: p for k, p in zip(old_keys, world[6:], strict=True)}
    old[("s000", 3)] = old[("s000", 3)] + 1e-3  # interpolated before: kept exactly, not re-interpolated
    registered_before = set(old_keys) - {("s000", 3)}
    previous = PreviousSolve(poses=old, registered=registered_before, names=[], sources={})
    sel = np.arange(0, 14, 1)
    model = TRUE.transform_w2c(world)  # what the COLMAP model holds: the world in its own frame
    reg = np.ones(14, bool)
    reg[[2, 3]] = False  # two new frames did not register: interpolated between their neighbours
    poses, registered, points = merge_incremental(
        index, sel, _result(model, reg, np.ones((4, 3))), TRUE.inverse(), previous
    )
    for k, key in enumerate(old_keys, start=6):
        np.testing.assert_array_equal(poses[k], old[key])  # old frames: exactly their stored poses
    for k in (0, 1, 4, 5):
        np.testing.assert_allclose(poses[k], world[k], atol=1e-9)  # new registered frames, in the world
    assert not registered[2] and not registered[3] and registered[[0, 1, 4, 5]].all()
    centres = camera_centers(poses[[1, 2, 3, 4]])
    np.testing.assert_allclose(centres[1], centres[0] + (centres[3] - centres[0]) / 3, atol=1e-9)  # linear centre
    np.testing.assert_allclose(points, TRUE.inverse().apply(np.ones((4, 3))), atol=1e-12)


def test_fill_poses_interpolates_inside_only() -> None:
    world = _path(5)
    known = np.array([False, True, False, True, False])
    poses = np.where(known[:, None, None], world, np.nan)
    out = fill_poses(poses, known)
    c = camera_centers(out)
    np.testing.assert_allclose(c[2], (c[1] + c[3]) / 2, atol=1e-12)
    assert np.isnan(out[0]).all() and np.isnan(out[4]).all()  # outside the known ones: nothing to go by
    np.testing.assert_array_equal(fill_poses(poses, known & (np.arange(5) == 1)), poses)  # one known: unchanged


def test_segment_disagreement_is_zero_up_to_a_similarity_and_grows_when_bent() -> None:
    world = _path(10)
    keys = _keys("s000", 5) + _keys("s001", 5)
    own = {"s000": TRUE.transform_w2c(world[:5]), "s001": world[5:].copy()}
    assert segment_disagreement(world, keys, own) == {"s000": pytest.approx(0, abs=1e-9), "s001": pytest.approx(0)}
    bent = world.copy()
    bent[7:, :3, 3] += [0.0, 0.0, 0.5]  # s001's last three frames dragged sideways in camera space
    d = segment_disagreement(bent, keys, own)
    assert d["s000"] == pytest.approx(0, abs=1e-9) and d["s001"] > 0.02
    assert set(segment_disagreement(world, keys, {"s000": own["s000"]})) == {"s000"}  # no own path: left out
    few = world.copy()
    few[:3] = np.nan  # s000: only 2 frames posed by both
    assert set(segment_disagreement(few, keys, own)) == {"s001"}


def test_solve_consistent_retries_while_a_segment_disagrees_and_keeps_the_best() -> None:
    poses = _path(4)
    solves = {0: 0.12, 1: 0.08, 2: 0.09, 3: 0.01}  # disagreement of each seed offset's solve

    def run(retries: int, limit: float, unposed: set[int] = frozenset()) -> tuple[list[tuple[int, str]], dict]:
        calls: list[tuple[int, str]] = []

        def solve(offset: int, note: str) -> SfmResult:
            calls.append((offset, note))
            reg = np.zeros(4, bool) if offset in unposed else np.ones(4, bool)
            return _result(poses + offset, reg)  # the offset marks which solve came back

        measure = (lambda p: {"s000": solves[int(p[0, 3, 3]) - 1]}, limit)
        res, attrs = solve_consistent(solve, {"segment_disagreement": measure}, retries)
        assert attrs["seed_offset"] == int(res.poses[0, 3, 3]) - 1
        return calls, attrs

    calls, attrs = run(2, 0.05)
    assert calls == [(0, ""), (1, "solve 2 of up to 3: "), (2, "solve 3 of up to 3: ")]
    assert attrs == {"segment_disagreement": {"s000": 0.08}, "solves": 3, "seed_offset": 1}  # least disagreeing
    calls, attrs = run(3, 0.05)
    assert len(calls) == 4 and attrs["seed_offset"] == 3  # stops at the first that agrees
    calls, attrs = run(5, 0.1)
    assert len(calls) == 2 and attrs["seed_offset"] == 1
    calls, attrs = run(1, 0.05, unposed={1})
    assert attrs["seed_offset"] == 0  # a solve that posed nothing never wins over one that did


def test_solve_consistent_holds_every_measure_to_its_own_limit() -> None:
    """A solve within one limit but past the other is solved again; the kept one went least past its limits,
    each figure taken over its own limit."""
    poses = _path(4)
    ate = {0: 0.01, 1: 0.06, 2: 0.02}  # limit 0.05
    turn = {0: 20.0, 1: 1.0, 2: 7.0}  # limit 5°: solve 0 goes 4x past a limit, solve 1 1.2x, solve 2 1.4x

    def solve(offset: int, note: str) -> SfmResult:
        return _result(poses + offset, np.ones(4, bool))

    def seed(p: np.ndarray) -> int:
        return int(p[0, 3, 3]) - 1

    measures = {
        "segment_disagreement": (lambda p: {"s000": ate[seed(p)]}, 0.05),
        "segment_turn_error_deg": (lambda p: {"s000": turn[seed(p)]}, 5.0),
    }
    _, attrs = solve_consistent(solve, measures, 2)
    assert attrs == {
        "segment_disagreement": {"s000": 0.06},
        "segment_turn_error_deg": {"s000": 1.0},
        "solves": 3,
        "seed_offset": 1,
    }
    turn[1] = 5.0  # at its limit, and the ATE then decides: solve 1 is consistent
    ate[1] = 0.05
    assert solve_consistent(solve, measures, 2)[1]["solves"] == 2


def _turn(start: np.ndarray, yaw_deg: float) -> np.ndarray:
    """A planner's turn (+ left) of 17 frames: 0.5 m forward and 0.04 m sideways per degree."""
    return move_path(start, np.radians(yaw_deg), 0.0, 0.5, 0.04 * yaw_deg, 17)


def test_segment_turn_error_finds_the_pitch_drift_that_camera_centres_miss() -> None:
    """The planar-twin failure measured on a 15-segment world: the global solve turned a 30° left turn with a pitch
    drift growing to 27°, its camera centres where they belong. The centres' ATE sees nothing; the turn against what
    the check read sees all of it. A generator that turned 40° where 30° were planned is no error when its check
    read the 10° extra."""
    start = look_at(np.array([0.0, 0.0, 3.5]), np.array([10.0, 0.0, 1.5]))
    plan = _turn(start, 30.0)
    keys = _keys("s001", 17)[1:]  # the frame it repeats from its parent is not in the stitched video
    solved = TRUE.transform_w2c(plan)[1:]  # the solve's own world frame and scale
    turns = {"s001": (plan, np.zeros(3))}
    assert segment_turn_error(solved, keys, turns)["s001"] == pytest.approx(0.0, abs=1e-6)
    bent = solved.copy()
    for k in range(len(bent)):  # tilt each camera up about its own x axis, keeping its centre
        tilt = Rotation.from_rotvec([np.radians(27.0) * (k + 1) / len(bent), 0.0, 0.0]).as_matrix()
        centre = camera_centers(bent[k : k + 1])[0]
        bent[k, :3, :3] = tilt @ bent[k, :3, :3]
        bent[k, :3, 3] = -bent[k, :3, :3] @ centre
    own = {"s001": TRUE.transform_w2c(plan)}  # its own SfM, generation order
    assert segment_disagreement(bent, keys, own)["s001"] == pytest.approx(0.0, abs=1e-9)
    assert segment_turn_error(bent, keys, turns)["s001"] == pytest.approx(27.0, abs=1.5)
    wider = TRUE.transform_w2c(_turn(start, 40.0))[1:]
    read = {"s001": (plan, np.array([10.0, 0.0, 0.0]))}  # read from frame 0, the solve's turn from frame 1:
    assert segment_turn_error(wider, keys, read)["s001"] == pytest.approx(10.0 / 16, abs=0.05)  # 1/16 of the 10°
    assert segment_turn_error(wider, keys, turns)["s001"] == pytest.approx(10.0 * 15 / 16)  # read as planned
    assert segment_turn_error(solved, keys, {}) == {}  # nothing read: left out
    few = solved.copy()
    few[1:] = np.nan
    assert segment_turn_error(few, keys, turns) == {}  # one frame posed: no turn


def test_image_names_sort_in_stitched_order() -> None:
    order = ["s002", "s000", "s001"]  # s002 a left extension, prepended and played reversed
    keys = [("s002", i) for i in (5, 3, 1)] + [("s000", i) for i in (0, 2)] + [("s001", i) for i in (1, 4)]
    names = image_names(keys, order, left={"s002"}, reversed_={"s002"})
    assert names == sorted(names) and len(set(names)) == len(names)
    assert names[0] == "49999994_s002_0005.png" and names[3] == "50000000_s000_0000.png"
    assert image_names([("s000", 0)], ["s000"], set(), set()) == ["50000000_s000_0000.png"]


def test_can_extend_only_when_segments_are_added() -> None:
    names = ["50000000_s000_0000.png", "50010001_s001_0001.png"]
    sources = {"s000": {"key": "a", "attempt": 0}}
    prev = PreviousSolve(
        poses={},
        registered=set(),
        names=names[:1],
        sources=sources,
        workspace_key="w",
        model_to_world=Sim3.identity(),
        load_workspace=lambda: None,  # type: ignore[arg-type,return-value]
    )
    seg = {n: n.split("_")[1] for n in names}
    more = sources | {"s001": {"key": "b", "attempt": 0}}
    assert can_extend(prev, "w", names, seg, more)
    assert not can_extend(prev, "other settings", names, seg, more)
    assert not can_extend(prev, "w", names[:1], seg, sources)  # nothing new
    assert not can_extend(prev, "w", names, seg, more | {"s000": {"key": "a", "attempt": 1}})  # s000 regenerated
    assert not can_extend(prev, "w", names[1:], seg, more)  # an old frame gone
    assert not can_extend(None, "w", names, seg, more)
    no_workspace = PreviousSolve(poses={}, registered=set(), names=names[:1], sources=sources, workspace_key="w")
    assert not can_extend(no_workspace, "w", names, seg, more)


def test_one_segment_global_solve_starts_with_its_checks_mapper() -> None:
    """The same frames never go through the whole mapper chain twice: the check's mapper first, alone when it
    passed no gates (the prior-focal run is an incremental one); several segments keep the configured order."""
    from wonderverse.global_poses import mappers_after_check
    from wonderverse.sfm import SfmParams

    assert mappers_after_check(None) == {}
    assert mappers_after_check(("", False)) == {}
    assert mappers_after_check(("global", True)) == {"auto_order": ("global", "incremental")}
    assert mappers_after_check(("incremental", True)) == {"auto_order": ("incremental", "global")}
    assert mappers_after_check(("incremental_prior_focal", False)) == {"mapper": "incremental"}
    for update in (mappers_after_check(("global", False)), mappers_after_check(("incremental", True))):
        assert SfmParams.model_validate({**SfmParams().model_dump(), **update}).model_dump().items() >= update.items()
