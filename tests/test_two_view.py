"""Two-view geometry of a segment against its first frame (`wonderverse.two_view`). Ground truth: procedural
videos rendered along paths built here (their gt.poses are the cameras really rendered), and rays, descriptors
and depths constructed with known geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from wonderverse.camera import camera_centers, geodesic_angle, move_path, so3_exp
from wonderverse.two_view import (
    TwoViewParams,
    _baselines,
    match_descriptors,
    rays,
    rotation_only,
    triangulated_depths,
    two_view_path,
)

FOREST = "a quiet forest lake in autumn"
W, H, T = 320, 208, 17  # the preview preset's frames


def _render(yaw_deg: float, pitch_deg: float, forward_m: float, opts: dict | None = None, seed: int = 1013):
    """A procedural segment from the world's start pose along move_path (the planner's 0.04 m of strafe per
    degree of yaw), no faults: (video, planned path)."""
    from wonderverse.video import initial_pose
    from wonderverse.video.procedural import ProceduralVideo

    model = ProceduralVideo(FOREST, 13, W, H, 60.0, {"fault_probability": 0.0, **(opts or {})})
    path = move_path(initial_pose(model), math.radians(yaw_deg), math.radians(pitch_deg), forward_m, 0.04 * yaw_deg, T)
    return model.generate(FOREST, path, seed=seed, reference=None), path


def _relative(w2c: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, centre) of frame j in frame 0's camera coordinates."""
    R = w2c[j, :3, :3] @ w2c[0, :3, :3].T
    c = camera_centers(w2c)
    return R, w2c[0, :3, :3] @ (c[j] - c[0])


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0)))


@pytest.fixture(scope="module")
def turn_and_travel():
    """Right 24° with 1.8 m forward over the forest lake's ground: the clip on which SfM's path took the planar
    twin (26° of pitch invented, travel mostly downwards; benchmarks.plan_following case 13)."""
    video, path = _render(-24.0, 0.0, 1.8)
    return video, path, two_view_path(video.frames, video.K)


def test_turn_and_travel_over_the_ground_is_read_right(turn_and_travel) -> None:
    video, _, tv = turn_and_travel
    truth = video.gt.poses
    assert tv.registered[0] and tv.travel_known[0]
    np.testing.assert_allclose(tv.poses[0], np.eye(4))
    looked = [p.j for p in tv.pairs if p.used]
    assert len(looked) >= 6 and max(looked) >= 12  # most of the segment, the far end included
    last = max(looked)
    assert tv.travel_known[last]
    _, c_last = _relative(truth, last)
    # measured on 2026-12-04 (commit 088e394): rotation 0.26° (0.44° without travel), direction 2.8°, length 0.055;
    # the bounds leave a margin of 2x
    for j in looked:
        R_true, c_true = _relative(truth, j)
        R_est, c_est = _relative(tv.poses, j)
        # short pairs without measured travel: E's rotation soaks up some of the travel
        assert math.degrees(float(geodesic_angle(R_est, R_true))) < (0.5 if tv.travel_known[j] else 0.9), j
        if tv.travel_known[j]:  # the direction of travel, and its length as a share of the longest
            assert _angle(c_est, c_true) < 6.0, j
            assert np.linalg.norm(c_est) == pytest.approx(np.linalg.norm(c_true) / np.linalg.norm(c_last), abs=0.11)
    attrs = tv.to_attrs()
    assert attrs["frames"] == [int(i) for i in np.flatnonzero(tv.registered)]
    assert all(v is None or not (isinstance(v, float) and math.isnan(v)) for p in attrs["pairs"] for v in p.values())


def test_pure_rotation_has_no_travel_and_the_right_turn() -> None:
    """An up turn with no travel at all: every pair a rotation, the travel never measured."""
    video, _ = _render(0.0, 25.0, 0.0)
    tv = two_view_path(video.frames, video.K)
    used = [p for p in tv.pairs if p.used]
    assert len(used) >= 6
    assert not tv.travel_known[1:].any()
    for p in used:
        R_true, _ = _relative(video.gt.poses, p.j)
        # measured 0.012° on 2026-12-04 (commit 088e394); margin 4x
        assert math.degrees(float(geodesic_angle(_relative(tv.poses, p.j)[0], R_true))) < 0.05
        assert not p.travel and math.isnan(p.baseline)
    last = used[-1].j
    assert used[-1].rotation_deg == pytest.approx(25.0 * last / (T - 1), abs=0.05)  # measured 0.004° off


def test_textureless_frames_register_only_the_first() -> None:
    frames = np.full((5, 64, 96, 3), 128, dtype=np.uint8)
    K = np.array([[80.0, 0.0, 48.0], [0.0, 80.0, 32.0], [0.0, 0.0, 1.0]])
    tv = two_view_path(frames, K)
    assert tv.registered.tolist() == [True, False, False, False, False]
    assert all(not p.used and "matches" in p.why for p in tv.pairs)
    assert len(tv.notes) == len(tv.pairs)


def test_bad_input_raises() -> None:
    K = np.eye(3)
    with pytest.raises(ValueError, match="uint8"):
        two_view_path(np.zeros((3, 8, 8, 3), dtype=np.float32), K)
    with pytest.raises(ValueError, match="K must be"):
        two_view_path(np.zeros((3, 8, 8, 3), dtype=np.uint8), np.full((3, 3), np.nan))
    with pytest.raises(ValidationError):
        TwoViewParams(frames=1)
    with pytest.raises(ValidationError):
        TwoViewParams(unknown=1)


# ---------------------------------------------------------------- the pieces, on constructed data


def test_match_descriptors_keeps_mutual_unambiguous_matches() -> None:
    rng = np.random.default_rng(0)
    d1 = rng.normal(size=(50, 128))
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    perm = rng.permutation(50)
    d2 = d1[perm] + 0.01 * rng.normal(size=(50, 128))
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    m = match_descriptors(d1, d2, 0.8, 0.7)
    assert len(m) == 50
    assert np.all(perm[m[:, 1]] == m[:, 0])
    # a twin of descriptor 0 in the second set makes its match ambiguous: the ratio test drops it
    d2b = np.vstack([d2, d2[np.flatnonzero(perm == 0)]])
    m2 = match_descriptors(d1, d2b, 0.8, 0.7)
    assert 0 not in m2[:, 0] and len(m2) == 49
    assert len(match_descriptors(d1[:1], d2, 0.8, 0.7)) == 0


def test_rotation_only_recovers_a_rotation_among_outliers() -> None:
    rng = np.random.default_rng(1)
    R = so3_exp(np.radians([3.0, -20.0, 1.0]))
    r1 = rng.normal(size=(200, 3)) * [0.5, 0.4, 0.0] + [0.0, 0.0, 1.0]
    r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
    r2 = r1 @ R.T
    r2[:40] = rng.normal(size=(40, 3))  # outliers
    r2 /= np.linalg.norm(r2, axis=1, keepdims=True)
    R_est, n = rotation_only(r1, r2, math.radians(0.2), 300, 0)
    assert n == 160
    assert math.degrees(float(geodesic_angle(R_est, R))) < 1e-6


def test_triangulated_depths_of_a_known_scene() -> None:
    rng = np.random.default_rng(2)
    X = rng.uniform([-2, -1, 4], [2, 1, 9], size=(30, 3))  # points in camera 1
    R, t = so3_exp(np.radians([0.0, 10.0, 0.0])), np.array([-0.5, 0.0, 0.1])
    X2 = X @ R.T + t
    r1 = X / np.linalg.norm(X, axis=1, keepdims=True)
    r2 = X2 / np.linalg.norm(X2, axis=1, keepdims=True)
    depth, angle = triangulated_depths(r1, r2, R, t)
    np.testing.assert_allclose(depth, X[:, 2], rtol=1e-9)
    c2 = -R.T @ t
    expect = [_angle(x, x - c2) for x in X]
    np.testing.assert_allclose(angle, expect, atol=1e-9)
    # with the travel reversed every point lies behind a camera
    assert np.isnan(triangulated_depths(r1, r2, R, -t)[0]).all()


def test_rays_invert_the_projection() -> None:
    K = np.array([[200.0, 0.0, 160.0], [0.0, 210.0, 104.0], [0.0, 0.0, 1.0]])
    X = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 4.0]])
    p = (X @ K.T)[:, :2] / X[:, 2:]
    np.testing.assert_allclose(rays(p, K), X / np.linalg.norm(X, axis=1, keepdims=True), atol=1e-12)


def test_baselines_from_shared_depths() -> None:
    """Three pairs seeing the same 20 points (true depths z) with baselines 0.2, 0.5, 1: each pair's depths at
    unit baseline are z / b. A fourth pair shares nothing and is left out."""
    rng = np.random.default_rng(3)
    z = rng.uniform(3.0, 10.0, 20)
    ids = np.arange(20)
    depth_of = {2: (ids, z / 0.2), 4: (ids[5:], z[5:] / 0.5), 8: (ids[:15], z[:15] / 1.0), 9: (ids + 100, z)}
    tri = {2: 0.5, 4: 1.0, 8: 2.0, 9: 0.1}
    b = _baselines(depth_of, tri)
    assert set(b) == {2, 4, 8}
    assert b[8] == pytest.approx(1.0)
    assert b[4] == pytest.approx(0.5)
    assert b[2] == pytest.approx(0.2)
    assert _baselines({}, {}) == {}
