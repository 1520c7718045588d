"""Camera paths for rendering: fly-through along the training cameras, parallel novel-view track, orbit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from wonderverse.camera import camera_centers, intrinsics, look_at, scene_extent
from wonderverse.paths import (
    FlythroughParams,
    NovelViewParams,
    OrbitParams,
    flythrough_path,
    novel_view_path,
    orbit_path,
)


def _track(n: int = 60, jitter: float = 0.0, seed: int = 0) -> np.ndarray:
    """Cameras at 1.5 m height along a quarter-ish arc of radius 4 m, looking along the direction of travel."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.5, n)
    eyes = np.stack([4 * np.sin(t), 4 * (1 - np.cos(t)), np.full(n, 1.5)], -1)
    heading = np.stack([np.cos(t), np.sin(t), np.zeros(n)], -1)
    eyes = eyes + jitter * rng.standard_normal((n, 3))
    return np.stack(
        [look_at(e, e + h + 0.05 * jitter * rng.standard_normal(3)) for e, h in zip(eyes, heading, strict=True)]
    )


def _dense_polyline_distance(points: np.ndarray, line: np.ndarray, per_segment: int = 50) -> np.ndarray:
    """Distance of each point to a polyline (sampled densely)."""
    u = np.linspace(0.0, 1.0, per_segment, endpoint=False)[:, None]
    dense = np.concatenate([(line[:-1, None] * (1 - u) + line[1:, None] * u).reshape(-1, 3), line[-1:]])
    return cKDTree(dense).query(points)[0]


def _assert_rotations(w2c: np.ndarray) -> None:
    R = w2c[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_array_equal(w2c[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (len(w2c), 4)))


# ------------------------------------------------------------------------------------------- fly-through


def test_flythrough_starts_and_ends_at_the_training_cameras() -> None:
    w2c = _track(jitter=0.02)
    path = flythrough_path(w2c, 240)
    assert path.shape == (240, 4, 4)
    np.testing.assert_allclose(camera_centers(path[[0, -1]]), camera_centers(w2c[[0, -1]]), atol=1e-9)
    np.testing.assert_allclose(path[[0, -1], :3, :3], w2c[[0, -1], :3, :3], atol=1e-9)
    _assert_rotations(path)


def test_flythrough_is_smooth_even_when_the_training_cameras_jitter() -> None:
    w2c = _track(n=80, jitter=0.03)
    c_train = camera_centers(w2c)
    c = camera_centers(flythrough_path(w2c, 300))
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert steps.max() < 1.5 * np.median(steps)  # near-constant speed, no jumps
    assert steps.min() > 0.5 * np.median(steps)
    # Second differences relative to the step: the input's are of the order of the jitter, the path's tiny.
    rough_train = np.linalg.norm(np.diff(c_train, 2, axis=0), axis=1).max() / np.median(
        np.linalg.norm(np.diff(c_train, axis=0), axis=1)
    )
    rough_path = np.linalg.norm(np.diff(c, 2, axis=0), axis=1).max() / np.median(steps)
    assert rough_train > 0.5
    assert rough_path < 0.05
    # Rotations turn smoothly too: no step much larger than the typical one.
    R = flythrough_path(w2c, 300)[:, :3, :3]
    ang = np.arccos(np.clip((np.trace(np.swapaxes(R[:-1], 1, 2) @ R[1:], axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert ang.max() < np.radians(1.0)


def test_flythrough_covers_the_whole_training_trajectory() -> None:
    w2c = _track(jitter=0.01)
    extent = scene_extent(w2c)
    c_train = camera_centers(w2c)
    c = camera_centers(flythrough_path(w2c, 200))
    # Every path camera stays near the training trajectory and every training camera is passed by.
    assert _dense_polyline_distance(c, c_train).max() < 0.02 * extent
    assert cKDTree(c).query(c_train)[0].max() < 0.03 * extent
    # Viewing directions follow the training ones (the tangent of the arc).
    R_path = flythrough_path(w2c, len(w2c), FlythroughParams(smooth_sigma_poses=0.0))
    cosines = np.sum(R_path[:, 2, :3] * w2c[:, 2, :3], axis=1)
    assert cosines.min() > np.cos(np.radians(3.0))


def test_flythrough_skips_nan_poses() -> None:
    w2c = _track()
    bad = w2c.copy()
    bad[[0, 7, 8, 30]] = np.nan
    path = flythrough_path(bad, 100)
    assert np.all(np.isfinite(path))
    np.testing.assert_allclose(path, flythrough_path(np.delete(w2c, [0, 7, 8, 30], axis=0), 100), atol=1e-12)
    np.testing.assert_allclose(camera_centers(path[0]), camera_centers(w2c[1]), atol=1e-9)


def test_flythrough_of_a_camera_turning_on_the_spot_still_turns() -> None:
    yaw = np.radians(np.linspace(0.0, 90.0, 30))
    w2c = np.stack([look_at([1.0, 2.0, 1.5], [1.0 + np.cos(a), 2.0 + np.sin(a), 1.5]) for a in yaw])
    path = flythrough_path(w2c, 50)
    np.testing.assert_allclose(camera_centers(path), np.broadcast_to([1.0, 2.0, 1.5], (50, 3)), atol=1e-12)
    np.testing.assert_allclose(path[-1, :3, :3], w2c[-1, :3, :3], atol=1e-9)
    headings = np.degrees(np.arctan2(path[:, 2, 1], path[:, 2, 0]))
    assert np.all(np.diff(headings) > 0.0)  # it advances at every frame


def test_flythrough_edge_cases() -> None:
    one = _track(n=1)
    np.testing.assert_allclose(flythrough_path(one, 5), np.repeat(one, 5, axis=0), atol=1e-12)
    still = np.repeat(_track(n=1), 4, axis=0)
    np.testing.assert_allclose(flythrough_path(still, 3), np.repeat(still[:1], 3, axis=0), atol=1e-12)
    assert flythrough_path(_track(), 1).shape == (1, 4, 4)
    with pytest.raises(ValueError, match="no finite camera pose"):
        flythrough_path(np.full((3, 4, 4), np.nan), 10)
    with pytest.raises(ValueError, match="n_frames"):
        flythrough_path(_track(), 0)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(2, 40),
    n_frames=st.integers(2, 120),
    sigma=st.floats(0.0, 6.0),
)
def test_flythrough_properties_on_random_walks(seed: int, n: int, n_frames: int, sigma: float) -> None:
    rng = np.random.default_rng(seed)
    eyes = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    targets = eyes + rng.normal(size=(n, 3)) + np.array([3.0, 0.0, 0.0])
    w2c = np.stack([look_at(e, t) for e, t in zip(eyes, targets, strict=True)])
    path = flythrough_path(w2c, n_frames, FlythroughParams(smooth_sigma_poses=sigma))
    assert path.shape == (n_frames, 4, 4)
    assert np.all(np.isfinite(path))
    _assert_rotations(path)
    # The ends are the training ends exactly when smoothing cannot reach past them (odd padding).
    if n > 4 * sigma + 1:
        np.testing.assert_allclose(camera_centers(path[[0, -1]]), eyes[[0, -1]], atol=1e-8)
    # The path stays within the (slightly grown) bounding box of the training cameras.
    lo, hi = eyes.min(0), eyes.max(0)
    pad = 0.25 * np.linalg.norm(hi - lo) + 1e-9
    c = camera_centers(path)
    assert np.all(c > lo - pad) and np.all(c < hi + pad)


# ---------------------------------------------------------------------------------------- novel views


def test_novel_view_path_leaves_the_trajectory_by_the_requested_amount() -> None:
    w2c = _track(n=60)
    extent = scene_extent(w2c)
    frac = 0.1
    look = 0.5 * extent  # the default look distance
    expected = frac * max(extent, look)
    path = novel_view_path(w2c, 150, offset_frac=frac)
    _assert_rotations(path)
    c = camera_centers(path)
    dist = _dense_polyline_distance(c, camera_centers(w2c))
    # Beside/above a curved track the distance to its nearest point is about the shift (exact for a straight one).
    np.testing.assert_allclose(dist, expected, rtol=0.05)
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert steps.max() < 1.5 * np.median(steps)


def test_novel_view_offset_direction_left_and_up() -> None:
    # Straight track along +x looking along +x: left is +y, up is +z.
    xs = np.linspace(0.0, 10.0, 20)
    w2c = np.stack([look_at([x, 0.0, 1.5], [x + 1.0, 0.0, 1.5]) for x in xs])
    shift = 0.2 * 10.0  # extent 10 > default look distance 5
    left = camera_centers(novel_view_path(w2c, 30, 0.2, params=NovelViewParams(offset_direction_deg=0.0)))
    np.testing.assert_allclose(left[:, 1], shift, atol=1e-9)
    np.testing.assert_allclose(left[:, 2], 1.5, atol=1e-9)
    up = camera_centers(novel_view_path(w2c, 30, 0.2, params=NovelViewParams(offset_direction_deg=90.0)))
    np.testing.assert_allclose(up[:, 1], 0.0, atol=1e-9)
    np.testing.assert_allclose(up[:, 2], 1.5 + shift, atol=1e-9)
    np.testing.assert_allclose(up[:, 0], np.linspace(0.0, 10.0, 30), atol=1e-9)


def test_novel_views_look_at_what_the_training_cameras_looked_at() -> None:
    # Training cameras on an arc around a statue at P, 5 m away, all looking at it.
    P = np.array([2.0, -1.0, 1.0])
    az = np.radians(np.linspace(-40.0, 40.0, 50))
    eyes = P + np.stack([5 * np.cos(az), 5 * np.sin(az), np.full_like(az, 0.5)], -1)
    w2c = np.stack([look_at(e, P) for e in eyes])
    K, W, H = intrinsics(640, 480, 60.0), 640, 480
    path = novel_view_path(w2c, 80, offset_frac=0.15, look_distance=float(np.linalg.norm(eyes[0] - P)))
    c = camera_centers(path)
    assert _dense_polyline_distance(c, eyes).min() > 0.1 * scene_extent(w2c)  # truly off the trajectory
    cam = np.einsum("nij,j->ni", path[:, :3, :3], P) + path[:, :3, 3]
    assert np.all(cam[:, 2] > 0.0)  # in front of every camera
    uv = (cam @ K.T)[:, :2] / cam[:, 2:]
    assert np.all(np.abs(uv[:, 0] - W / 2) < 0.1 * W) and np.all(np.abs(uv[:, 1] - H / 2) < 0.1 * H)
    np.testing.assert_allclose(path[:, 0, 2], 0.0, atol=1e-12)  # no roll: camera x stays horizontal


def test_novel_view_needs_a_look_distance_for_cameras_that_do_not_move() -> None:
    yaw = np.radians(np.linspace(0.0, 60.0, 10))
    w2c = np.stack([look_at([0.0, 0.0, 1.0], [np.cos(a), np.sin(a), 1.0]) for a in yaw])
    with pytest.raises(ValueError, match="look_distance"):
        novel_view_path(w2c, 10)
    path = novel_view_path(w2c, 10, offset_frac=0.5, look_distance=4.0)
    np.testing.assert_allclose(np.linalg.norm(camera_centers(path) - [0.0, 0.0, 1.0], axis=1), 2.0, atol=1e-9)


# --------------------------------------------------------------------------------------------- orbit


def test_orbit_circles_the_look_at_centre() -> None:
    P = np.array([1.0, 1.0, 0.5])
    az = np.radians(np.linspace(10.0, 50.0, 20))
    eyes = P + np.stack([3 * np.cos(az), 3 * np.sin(az), np.full_like(az, 1.0)], -1)
    w2c = np.stack([look_at(e, P) for e in eyes])
    d_look = float(np.linalg.norm(eyes[0] - P))
    path = orbit_path(w2c, 36, look_distance=d_look, params=OrbitParams(height_frac=0.0))
    _assert_rotations(path)
    c = camera_centers(path)
    np.testing.assert_allclose(np.linalg.norm(c[:, :2] - P[:2], axis=1), 3.0, atol=1e-9)
    np.testing.assert_allclose(c[:, 2], P[2] + 1.0, atol=1e-9)
    np.testing.assert_allclose(c[0], eyes[0], atol=1e-9)  # starts at the first training camera
    angles = np.degrees(np.unwrap(np.arctan2(c[:, 1] - P[1], c[:, 0] - P[0])))
    np.testing.assert_allclose(np.diff(angles), 10.0, atol=1e-9)  # full circle, counter-clockwise, no repeat
    cam = np.einsum("nij,j->ni", path[:, :3, :3], P) + path[:, :3, 3]
    np.testing.assert_allclose(cam[:, :2], 0.0, atol=1e-9)  # the centre is on every optical axis
    assert np.all(cam[:, 2] > 0.0)
