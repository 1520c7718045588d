"""The gravity-aligned frame (wonderverse.gravity) on constructed scenes whose up is known: level and rolled
cameras, tilted ground planes, noisy points, degenerate inputs, and the procedural worlds' own surfaces (indoor
and outdoor) seen from a random SfM-like frame."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from wonderverse.camera import Sim3, camera_centers, move_path
from wonderverse.gravity import GravityParams, angle_deg, estimate_gravity, given_frame, rotation_to_z

UP = np.array([0.0, 0.0, 1.0])


def _cameras(n: int, heading_deg: np.ndarray, pitch_deg: np.ndarray, roll_deg: np.ndarray, seed: int = 0):
    """W2C (n,4,4) in a +z-up world: cameras 1.6 above the ground z = 0, scattered over a few metres, each
    with its heading (about +z), pitch (+ up) and roll (about its optical axis)."""
    rng = np.random.default_rng(seed)
    out = []
    for h, p, r in zip(heading_deg, pitch_deg, roll_deg, strict=True):
        eye = np.array([*rng.uniform(-3, 3, 2), 1.6])
        h, p = np.radians(h), np.radians(p)
        fwd = np.array([np.cos(p) * np.cos(h), np.cos(p) * np.sin(h), np.sin(p)])
        right = np.array([np.sin(h), -np.cos(h), 0.0])
        R = np.stack([right, np.cross(fwd, right), fwd])  # rows: camera x, y (down), z in the world
        R = Rotation.from_euler("z", r, degrees=True).as_matrix() @ R  # roll about the optical axis
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        out.append(w2c)
    return np.stack(out)


def _ground(n: int, seed: int = 0, size: float = 10.0, noise: float = 0.01) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-size, size, (n, 2)), rng.normal(0.0, noise, n)])


def _frame(seed: int) -> Sim3:
    """An arbitrary similarity, like SfM's frame: random rotation, scale and offset."""
    rng = np.random.default_rng(seed)
    return Sim3(rng.uniform(0.1, 10.0), Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 20, 3))


def _estimate(w2c, points, sim: Sim3, params: GravityParams | None = None):
    """Estimate in the SfM-like frame; returns (the frame, error of its up against the truth in degrees)."""
    g = estimate_gravity(sim.transform_w2c(w2c), None if points is None else sim.apply(points), params)
    return g, angle_deg(g.up, sim.R @ UP)


@given(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1))
def test_rotation_to_z_is_the_smallest_rotation_onto_z(a: float, b: float, c: float) -> None:
    u = np.array([a, b, c])
    if np.linalg.norm(u) < 1e-3:
        return
    R = rotation_to_z(u)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ (u / np.linalg.norm(u)), UP, atol=1e-12)
    # the smallest: its angle is the angle between u and z, and the axis is horizontal
    rotvec = Rotation.from_matrix(R).as_rotvec(degrees=True)
    assert np.linalg.norm(rotvec) == pytest.approx(angle_deg(u, UP), abs=1e-5)
    assert abs(rotvec[2]) < 1e-6
    np.testing.assert_allclose(rotation_to_z(-UP) @ -UP, UP, atol=1e-15)


def test_level_cameras_with_spread_headings_give_up_exactly_whatever_their_pitch() -> None:
    n = 12
    w2c = _cameras(n, np.linspace(0, 120, n), np.full(n, -25.0), np.zeros(n))  # all pitched well down
    for seed in range(3):
        g, err = _estimate(w2c, None, _frame(seed))
        assert err < 1e-6, err
        assert g.evidence["source"] == "cameras" and g.evidence["camera"]["mode"] == "x axes"
    # each camera's image up is off by the pitch, and their mean by 20° over these 120° of headings
    assert all(angle_deg(-r[1, :3], UP) == pytest.approx(25.0, abs=1e-6) for r in w2c)
    assert angle_deg(-w2c[:, 1, :3].mean(0), UP) > 15.0


def test_noisy_camera_rolls_average_out() -> None:
    rng = np.random.default_rng(4)
    n = 60
    w2c = _cameras(n, rng.uniform(-90, 90, n), rng.normal(-10, 5, n), rng.normal(0, 1.5, n))
    for seed in range(3):
        _, err = _estimate(w2c, _ground(3000, seed), _frame(seed))
        assert err < 0.65, err  # 1.5° of roll per camera, 60 cameras: measured 0.32° (2026-12-04); margin 2x


def test_one_heading_takes_the_ground_plane_under_the_cameras_pitch() -> None:
    # one heading (a walk forward), every camera pitched 20° down: the cameras only know up to that pitch
    n = 10
    w2c = _cameras(n, np.full(n, 30.0), np.full(n, -20.0), np.zeros(n))
    ground = _ground(4000)
    wall = np.column_stack([np.full(1500, 9.0), np.random.default_rng(1).uniform(-9, 9, 1500), np.linspace(0, 5, 1500)])
    sim = _frame(7)
    cams, _ = _estimate(w2c, None, sim)
    assert cams.evidence["camera"]["mode"] == "image up, one heading"
    assert angle_deg(cams.up, sim.R @ UP) == pytest.approx(20.0, abs=1e-6)
    g, err = _estimate(w2c, np.concatenate([ground, wall]), sim)
    assert err < 0.02, err  # measured 0.005° on 2026-12-04 (commit 088e394); margin 4x
    assert g.evidence["source"].startswith("ground plane")
    assert 0.6 < g.evidence["plane"]["support_frac"] < 0.8  # the ground, not the wall
    # the frame: +z up, origin on the ground below the cameras' centroid
    world = g.world_from_input.apply(sim.apply(ground)) / sim.s  # metres again
    assert np.median(np.abs(world[:, 2])) < 0.02 and np.abs(world[:, 2]).max() < 0.15
    centres = camera_centers(g.world_from_input.transform_w2c(sim.transform_w2c(w2c)))
    np.testing.assert_allclose(centres[:, :2].mean(0), 0.0, atol=1e-9)
    assert centres[:, 2].mean() == pytest.approx(1.6 * sim.s, rel=0.02)


def test_a_tilted_floor_decides_when_the_cameras_are_rolled() -> None:
    # handheld cameras rolled by up to ±15°: their x axes are not level; a floor tilted 30° from the input
    # frame's z is the evidence (the true up is its normal)
    rng = np.random.default_rng(2)
    n = 25
    w2c = _cameras(n, rng.uniform(-60, 60, n), rng.uniform(-20, 0, n), rng.uniform(-15, 15, n))
    tilt = Sim3(1.0, Rotation.from_euler("x", 30, degrees=True).as_matrix(), np.zeros(3))
    g = estimate_gravity(tilt.transform_w2c(w2c), tilt.apply(_ground(3000, noise=0.005)))
    assert g.evidence["camera"]["x_axis_tilt_rms_deg"] > 3.0
    assert g.evidence["source"] == "ground plane"
    assert angle_deg(g.up, tilt.R @ UP) < 0.3
    cams = estimate_gravity(tilt.transform_w2c(w2c), None)
    assert angle_deg(cams.up, tilt.R @ UP) > angle_deg(g.up, tilt.R @ UP)


def test_degenerate_inputs() -> None:
    n = 8
    level = _cameras(n, np.linspace(0, 90, n), np.zeros(n), np.zeros(n))
    # no points, empty points, NaN points: the cameras alone, and the origin at their centroid
    for pts in (None, np.zeros((0, 3)), np.full((50, 3), np.nan)):
        g = estimate_gravity(level, pts)
        assert g.evidence["plane"] is None and angle_deg(g.up, UP) < 1e-9
        np.testing.assert_allclose(g.world_from_input.apply(camera_centers(level).mean(0)), 0.0, atol=1e-12)
    # a pose that is not finite is skipped; none at all is an error
    with_nan = level.copy()
    with_nan[3] = np.nan
    assert angle_deg(estimate_gravity(with_nan).up, UP) < 1e-9
    with pytest.raises(ValueError, match="no finite camera pose"):
        estimate_gravity(np.full((3, 4, 4), np.nan))
    # every camera looking straight down (a drone's nadir camera), headings spread: up is against the view
    down = _cameras(n, np.linspace(0, 180, n), np.full(n, -90.0), np.zeros(n))
    for seed in range(3):
        g, err = _estimate(down, _ground(2000, seed), _frame(seed))
        assert err < 1e-6, err
        assert g.evidence["camera"]["sign_from"] == "view axes (looking down)"
    # points with no plane under the cameras (a cloud around them): no plane, the cameras decide
    blob = np.random.default_rng(0).normal(0, 3, (3000, 3))
    g = estimate_gravity(level, blob)
    assert g.evidence["plane"] is None and angle_deg(g.up, UP) < 1e-9


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(-40, 40), st.integers(2, 30))
def test_any_frame_any_pitch(seed: int, pitch: float, n: int) -> None:
    w2c = _cameras(n, np.linspace(-60, 60, n), np.full(n, pitch), np.zeros(n), seed)
    _, err = _estimate(w2c, _ground(500, seed), _frame(seed))
    assert err < 1e-6


def _backproject(depth: np.ndarray, K: np.ndarray, w2c: np.ndarray, step: int = 4) -> np.ndarray:
    v, u = np.mgrid[step // 2 : depth.shape[0] : step, step // 2 : depth.shape[1] : step]
    z = depth[v, u]
    ok = np.isfinite(z)
    cam = np.stack([(u[ok] + 0.5 - K[0, 2]) / K[0, 0] * z[ok], (v[ok] + 0.5 - K[1, 2]) / K[1, 1] * z[ok], z[ok]], -1)
    return (cam - w2c[:3, 3]) @ w2c[:3, :3]


@pytest.mark.parametrize(
    "prompt", ["a small house decorated for Christmas", "a cosy reading room with shelves and armchairs"]
)
def test_procedural_worlds_up_within_two_degrees(prompt: str) -> None:
    """The procedural world's surfaces (its exact depth, back-projected, with 1 % noise) and cameras in a
    random similarity frame: a three-segment path (headings spread) and a walk forward (one heading, the
    start pose pitched 8–10° down), each within 2° of the world's +z."""
    from wonderverse.video.procedural import ProceduralVideo

    video = ProceduralVideo(prompt, 0, 96, 64, 60.0, {"fault_probability": 0.0})
    start = video.world.start_pose()
    forward = move_path(start, 0.0, 0.0, 2.0, 0.0, 6)
    right = move_path(forward[-1], np.radians(-35), 0.0, 0.5, 0.0, 6)
    left = move_path(start, np.radians(35), np.radians(-10), 0.5, 0.0, 6)
    rng = np.random.default_rng(0)
    for name, path in (("three segments", np.concatenate([forward, right, left])), ("forward", forward)):
        pts = np.concatenate([_backproject(video.render(w)[1], video.K, w) for w in path[::2]])
        for seed in range(2):
            sim = _frame(seed)
            noisy = pts + rng.normal(0.0, 0.01 * np.ptp(pts, axis=0).max() / 100, pts.shape)
            g, err = _estimate(path, noisy, sim)
            assert err < 2.0, (name, seed, err, g.evidence)


def test_a_given_frame_is_kept_as_it_is() -> None:
    g = given_frame("the conditioning path's world")
    pts = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_array_equal(g.world_from_input.apply(pts), pts)
    assert g.evidence["source"] == "the conditioning path's world" and g.up.tolist() == [0.0, 0.0, 1.0]
