"""Tests of wonderverse.camera. References are scipy's Rotation, look_at-built cameras and hand-made paths."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from wonderverse.camera import (
    Sim3,
    camera_centers,
    geodesic_angle,
    heading_pitch,
    interpolate_poses,
    look_at,
    matrix_from_quat,
    move_path,
    pixels_to_world,
    quat_from_matrix,
    quat_slerp,
    relative_motion_steps,
    skew,
    so3_exp,
    so3_log,
    umeyama,
)

PI = np.pi
FAST = settings(max_examples=200, deadline=None)
SLOW = settings(max_examples=80, deadline=None)

coords = st.floats(-1.0, 1.0, allow_nan=False)
unit_vectors = (
    st.tuples(coords, coords, coords)
    .map(np.array)
    .filter(lambda v: np.linalg.norm(v) > 0.1)
    .map(lambda v: v / np.linalg.norm(v))
)
seeds = st.integers(0, 2**32 - 1)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    return Rotation.random(random_state=rng).as_matrix()


def random_sim3(rng: np.random.Generator, log10_scale: tuple[float, float] = (-1.0, 1.0)) -> Sim3:
    return Sim3(10.0 ** rng.uniform(*log10_scale), random_rotation(rng), rng.normal(size=3) * 10.0)


def dir_from(yaw: float, pitch: float) -> np.ndarray:
    """World direction with heading `yaw` (from +x, counter-clockwise) and elevation `pitch`."""
    return np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])


def wrap(a: float) -> float:
    return (a + PI) % (2 * PI) - PI


def assert_rotation(R: np.ndarray, atol: float = 1e-12) -> None:
    eye = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, eye, atol=atol)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=atol)


# ------------------------------------------------------------------------------------------------- SO(3)


@FAST
@given(unit_vectors, unit_vectors, st.floats(0.01, 10.0))
def test_skew_is_cross_product(a: np.ndarray, b: np.ndarray, k: float) -> None:
    np.testing.assert_allclose(skew(k * a) @ b, np.cross(k * a, b), atol=1e-12)
    np.testing.assert_allclose(skew(a), -skew(a).T, atol=0)


@FAST
@given(unit_vectors, st.floats(0.0, PI))
def test_exp_matches_scipy_and_log_inverts(axis: np.ndarray, theta: float) -> None:
    omega = axis * theta
    R = so3_exp(omega)
    np.testing.assert_allclose(R, Rotation.from_rotvec(omega).as_matrix(), atol=1e-13)
    assert_rotation(R)
    np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-13)
    if theta < PI - 1e-6:  # away from π the vector (not only the rotation) is unique
        np.testing.assert_allclose(so3_log(R), omega, atol=1e-12)


@FAST
@given(unit_vectors, st.floats(PI - 1e-9, PI))
def test_exp_log_near_pi(axis: np.ndarray, theta: float) -> None:
    omega = axis * theta
    R = so3_exp(omega)
    w = so3_log(R)
    assert np.all(np.isfinite(w))
    np.testing.assert_allclose(np.linalg.norm(w), theta, atol=1e-12)
    np.testing.assert_allclose(so3_exp(w), R, atol=1e-12)
    # The direction comes from the symmetric part; the sign is only defined while sinθ >> rounding.
    if PI - theta > 1e-12:
        np.testing.assert_allclose(w, omega, atol=1e-12)
    else:
        assert min(np.abs(w - omega).max(), np.abs(w + omega).max()) < 1e-12
    assert abs(geodesic_angle(np.eye(3), R) - theta) < 1e-12


@FAST
@given(unit_vectors)
def test_log_of_exact_half_turn(axis: np.ndarray) -> None:
    R = 2.0 * np.outer(axis, axis) - np.eye(3)  # 180° about axis, built without any trigonometry
    w = so3_log(R)
    np.testing.assert_allclose(np.linalg.norm(w), PI, atol=1e-13)
    np.testing.assert_allclose(np.abs(w @ axis), PI, atol=1e-12)
    np.testing.assert_allclose(so3_exp(w), R, atol=1e-13)
    np.testing.assert_allclose(geodesic_angle(np.eye(3), R), PI, atol=1e-15)


@SLOW
@given(seeds)
def test_so3_vectorised_over_leading_axes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    omega = rng.normal(size=(2, 5, 3))
    omega *= (rng.uniform(0, PI, size=(2, 5)) / np.linalg.norm(omega, axis=-1))[..., None]
    R = so3_exp(omega)
    assert R.shape == (2, 5, 3, 3)
    np.testing.assert_allclose(R[1, 3], so3_exp(omega[1, 3]), atol=0)
    np.testing.assert_allclose(so3_log(R), omega, atol=1e-11)
    np.testing.assert_allclose(geodesic_angle(np.eye(3), R), np.linalg.norm(omega, axis=-1), atol=1e-12)


# ------------------------------------------------------------------------------------------- quaternions


def quat_scipy(R: np.ndarray) -> np.ndarray:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


@FAST
@given(unit_vectors, st.floats(0.0, PI))
def test_quat_matrix_round_trip_and_scipy(axis: np.ndarray, theta: float) -> None:
    R = so3_exp(axis * theta)
    q = quat_from_matrix(R)
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-15)
    assert q[0] >= 0.0
    expected = np.concatenate([[np.cos(theta / 2)], np.sin(theta / 2) * axis])  # from the definition
    if theta < PI - 1e-7:
        np.testing.assert_allclose(q, expected, atol=1e-13)
    else:  # w ~ 0: q and -q both have w >= 0 up to rounding
        assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-13
    np.testing.assert_allclose(matrix_from_quat(q), R, atol=1e-13)


@FAST
@given(st.tuples(coords, coords, coords, coords).map(np.array).filter(lambda q: np.linalg.norm(q) > 0.05))
def test_q_and_minus_q_are_the_same_rotation(q: np.ndarray) -> None:
    R = matrix_from_quat(q)
    assert_rotation(R)
    np.testing.assert_allclose(matrix_from_quat(-q), R, atol=0)
    np.testing.assert_allclose(matrix_from_quat(3.7 * q), R, atol=1e-14)  # normalises
    x, y, z, w = q[1], q[2], q[3], q[0]
    np.testing.assert_allclose(R, Rotation.from_quat([x, y, z, w]).as_matrix(), atol=1e-13)
    qn = q / np.linalg.norm(q)
    back = quat_from_matrix(R)
    assert min(np.abs(back - qn).max(), np.abs(back + qn).max()) < 1e-13


@SLOW
@given(seeds)
def test_quat_from_matrix_stack_matches_scipy(seed: int) -> None:
    R = Rotation.random(50, random_state=np.random.default_rng(seed)).as_matrix()
    q = quat_from_matrix(R)
    assert q.shape == (50, 4)
    for Ri, qi in zip(R, q, strict=True):
        ref = quat_scipy(Ri)
        assert min(np.abs(qi - ref).max(), np.abs(qi + ref).max()) < 1e-13


@pytest.mark.parametrize("bad", [[0, 0, 0, 0], [np.nan, 0, 0, 1], [np.inf, 0, 0, 0]])
def test_matrix_from_quat_rejects_zero_and_non_finite(bad: list[float]) -> None:
    with pytest.raises(ValueError, match="zero or not finite"):
        matrix_from_quat(np.array(bad, dtype=float))
    with pytest.raises(ValueError):
        matrix_from_quat(np.stack([[1.0, 0, 0, 0], np.array(bad, dtype=float)]))


@FAST
@given(unit_vectors, st.floats(0.0, PI), unit_vectors, st.floats(1e-6, 3.1), st.integers(2, 12))
def test_slerp_endpoints_and_constant_angular_velocity(
    a0: np.ndarray, th0: float, axis: np.ndarray, angle: float, n: int
) -> None:
    R0 = so3_exp(a0 * th0)
    R1 = R0 @ so3_exp(axis * angle)  # shortest arc from R0 to R1 has length `angle` (< π)
    q0, q1 = quat_from_matrix(R0), quat_from_matrix(R1)
    t = np.linspace(0.0, 1.0, n + 1)
    for sign in (1.0, -1.0):  # -q1 is the same rotation: same path
        q = quat_slerp(q0, sign * q1, t)
        np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-14)
        R = matrix_from_quat(q)
        np.testing.assert_allclose(R[0], R0, atol=1e-13)
        np.testing.assert_allclose(R[-1], R1, atol=1e-13)
        steps = geodesic_angle(R[:-1], R[1:])
        np.testing.assert_allclose(steps, angle / n, atol=1e-11)
        # On the geodesic: every sample lies at angle t * angle from R0, about the same axis.
        np.testing.assert_allclose(geodesic_angle(R0, R), t * angle, atol=1e-11)
        np.testing.assert_allclose(R, R0 @ so3_exp(np.outer(t, axis * angle)), atol=1e-12)


@FAST
@given(unit_vectors, unit_vectors, st.floats(0.0, 1e-9), st.floats(0.0, 1.0))
def test_slerp_of_nearly_identical_quats(a0: np.ndarray, axis: np.ndarray, eps: float, t: float) -> None:
    q0 = quat_from_matrix(so3_exp(a0 * 1.0))
    q1 = quat_from_matrix(so3_exp(a0 * 1.0) @ so3_exp(axis * eps))
    q = quat_slerp(q0, q1, t)
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(q, (1 - t) * q0 + t * q1, atol=1e-15)
    np.testing.assert_allclose(quat_slerp(q0, q0, t), q0, atol=1e-15)


@FAST
@given(seeds, unit_vectors, st.floats(0.0, PI))
def test_geodesic_angle_symmetric_and_equals_generating_angle(seed: int, axis: np.ndarray, theta: float) -> None:
    R0 = random_rotation(np.random.default_rng(seed))
    R1 = R0 @ so3_exp(axis * theta)
    g01 = geodesic_angle(R0, R1)
    assert 0.0 <= g01 <= PI
    np.testing.assert_allclose(g01, geodesic_angle(R1, R0), atol=1e-15)
    np.testing.assert_allclose(g01, theta, atol=2e-13)
    # Left-multiplying both by a rotation changes nothing (it is a distance on SO(3)).
    Q = so3_exp(axis[::-1] * 0.7)
    np.testing.assert_allclose(geodesic_angle(Q @ R0, Q @ R1), theta, atol=2e-13)
    assert geodesic_angle(R0, R0) < 1e-15


# ------------------------------------------------------------------------------------------------ Sim(3)


@SLOW
@given(seeds)
def test_sim3_compose_inverse_identities(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a, b = random_sim3(rng), random_sim3(rng)
    p = rng.normal(size=(20, 3)) * 5
    np.testing.assert_allclose(a.compose(b).apply(p), a.apply(b.apply(p)), rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(a.compose(b).matrix(), a.matrix() @ b.matrix(), rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(a.inverse().apply(a.apply(p)), p, atol=1e-10)
    np.testing.assert_allclose(a.compose(a.inverse()).matrix(), np.eye(4), atol=1e-11)
    np.testing.assert_allclose(a.inverse().matrix(), np.linalg.inv(a.matrix()), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(a.compose(Sim3.identity()).matrix(), a.matrix(), atol=0)
    h = np.concatenate([p, np.ones((20, 1))], axis=1)
    np.testing.assert_allclose((h @ a.matrix().T)[:, :3], a.apply(p), rtol=1e-12, atol=1e-10)


def test_sim3_is_frozen_and_validated() -> None:
    T = Sim3.identity()
    with pytest.raises(AttributeError):
        T.s = 2.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        T.R[0, 0] = 2.0
    with pytest.raises(ValueError, match="scale"):
        Sim3(0.0, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="R must be"):
        Sim3(1.0, np.eye(4), np.zeros(3))


def random_points(rng: np.random.Generator, n: int, offset: float, spread: float) -> np.ndarray:
    return offset * rng.normal(size=3) + spread * rng.normal(size=(n, 3))


@SLOW
@given(seeds)
def test_umeyama_never_returns_a_reflection(seed: int) -> None:
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(10, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: the best rotation is not the reflection
    est = umeyama(src, dst)
    assert_rotation(est.R, atol=1e-12)
    # Planar points mirrored through their own plane are matched exactly by a rotation.
    flat = np.concatenate([rng.normal(size=(10, 2)), np.zeros((10, 1))], axis=1)
    est = umeyama(flat, flat * np.array([1.0, 1.0, -1.0]))
    assert_rotation(est.R, atol=1e-12)
    np.testing.assert_allclose(est.apply(flat), flat, atol=1e-12)


def test_umeyama_rejects_bad_input() -> None:
    rng = np.random.default_rng(0)
    p = rng.normal(size=(10, 3))
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(p[:2], p[:2])
    line = np.outer(np.linspace(0, 1, 10), [1.0, 2.0, 3.0]) + 5.0
    with pytest.raises(ValueError, match="collinear or coincident"):
        umeyama(line, p)
    with pytest.raises(ValueError, match="collinear or coincident"):
        umeyama(p, line)
    with pytest.raises(ValueError, match="collinear or coincident"):
        umeyama(np.ones((5, 3)), p[:5])
    with pytest.raises(ValueError, match="finite"):
        umeyama(np.where(np.arange(30).reshape(10, 3) == 4, np.nan, p), p)
    with pytest.raises(ValueError, match=r"\(N,3\)"):
        umeyama(p, p[:5])
    # A collinear set is accepted on request, and then still gives the best possible residual.
    T = umeyama(line, 2.0 * line + 1.0, allow_degenerate=True)
    np.testing.assert_allclose(T.apply(line), 2.0 * line + 1.0, atol=1e-12)


@SLOW
@given(seeds)
def test_transform_w2c_moves_centres_and_scales_camera_space(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = random_sim3(rng, (-3.0, 3.0))
    eyes = rng.normal(size=(6, 3)) * 3
    w2c = np.stack([look_at(e, e + rng.normal(size=3)) for e in eyes])
    new = T.transform_w2c(w2c)
    np.testing.assert_allclose(camera_centers(new), T.apply(camera_centers(w2c)), rtol=1e-11, atol=1e-9 * T.s)
    assert_rotation(new[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(new[:, 3], np.tile([0.0, 0, 0, 1], (6, 1)), atol=0)
    # Seen from each camera, the moved scene is the old one scaled by s (depths scale by s).
    X = rng.normal(size=(8, 3)) * 4
    cam_old = np.einsum("nij,pj->npi", w2c[:, :3, :3], X) + w2c[:, None, :3, 3]
    cam_new = np.einsum("nij,pj->npi", new[:, :3, :3], T.apply(X)) + new[:, None, :3, 3]
    np.testing.assert_allclose(cam_new, T.s * cam_old, rtol=1e-10, atol=1e-9 * T.s)
    # Composition: transforming twice equals transforming by the composite.
    U = random_sim3(rng)
    np.testing.assert_allclose(U.transform_w2c(new), U.compose(T).transform_w2c(w2c), rtol=1e-9, atol=1e-8)
    nan_pose = np.full((4, 4), np.nan)
    assert np.all(np.isnan(T.transform_w2c(nan_pose)[:3]))


# ------------------------------------------------------------------------------------------ trajectories


@SLOW
@given(seeds, st.integers(2, 6), st.booleans())
def test_interpolate_poses_hits_keys_and_interpolates(seed: int, k: int, ease: bool) -> None:
    rng = np.random.default_rng(seed)
    eyes = rng.normal(size=(k, 3)) * 3
    keys = np.stack([look_at(e, e + rng.normal(size=3)) for e in eyes])
    key_times = np.cumsum(rng.uniform(0.2, 2.0, size=k))
    out = interpolate_poses(keys, key_times, key_times, ease=ease)
    np.testing.assert_allclose(out, keys, atol=1e-12)
    # Midpoint between the first two keys: centre halfway, rotation halfway along the geodesic.
    mid = interpolate_poses(keys, key_times, [0.5 * (key_times[0] + key_times[1])], ease=ease)[0]
    np.testing.assert_allclose(camera_centers(mid), 0.5 * (eyes[0] + eyes[1]), atol=1e-12)
    total = geodesic_angle(keys[0, :3, :3], keys[1, :3, :3])
    np.testing.assert_allclose(geodesic_angle(keys[0, :3, :3], mid[:3, :3]), total / 2, atol=1e-10)
    np.testing.assert_allclose(geodesic_angle(mid[:3, :3], keys[1, :3, :3]), total / 2, atol=1e-10)
    # A quarter of the way: u = 1/4 (linear) or smoothstep(1/4) = 5/32 (eased).
    t = key_times[0] + 0.25 * (key_times[1] - key_times[0])
    u = 5.0 / 32.0 if ease else 0.25
    q = interpolate_poses(keys, key_times, [t], ease=ease)[0]
    np.testing.assert_allclose(camera_centers(q), (1 - u) * eyes[0] + u * eyes[1], atol=1e-12)
    np.testing.assert_allclose(geodesic_angle(keys[0, :3, :3], q[:3, :3]), u * total, atol=1e-10)
    # Outside the keys: clamped.
    ends = interpolate_poses(keys, key_times, [key_times[0] - 5.0, key_times[-1] + 5.0], ease=ease)
    np.testing.assert_allclose(ends, keys[[0, -1]], atol=1e-12)


def test_interpolate_poses_rejects_unsorted_times() -> None:
    keys = np.stack([look_at([0, 0, 0], [1, 0, 0]), look_at([1, 0, 0], [2, 0, 0])])
    with pytest.raises(ValueError, match="strictly increasing"):
        interpolate_poses(keys, [1.0, 1.0], [1.0])


headings = st.floats(-PI, PI)
pitches = st.floats(-1.2, 1.2)


@FAST
@given(seeds, headings, pitches, st.floats(-PI + 1e-3, PI - 1e-3), st.floats(-0.3, 0.3))
def test_heading_pitch_of_look_at(seed: int, yaw0: float, pitch0: float, dyaw: float, dpitch: float) -> None:
    eye = np.random.default_rng(seed).normal(size=3)
    yaw, pitch = heading_pitch(look_at(eye, eye + 2.5 * dir_from(yaw0, pitch0)))
    assert abs(wrap(yaw - yaw0)) < 1e-12
    assert abs(pitch - pitch0) < 1e-12
    stack = np.stack([look_at(eye, eye + dir_from(yaw0, pitch0)), look_at(eye, eye + dir_from(dyaw, dpitch))])
    ys, ps = heading_pitch(stack)
    np.testing.assert_allclose(ps, [pitch0, dpitch], atol=1e-12)
    assert abs(wrap(ys[1] - dyaw)) < 1e-12


@FAST
@given(
    seeds,
    headings,
    st.floats(-1.0, 1.0),
    st.floats(-PI + 0.01, PI - 0.01),
    st.floats(-0.5, 0.5),
    st.floats(-5.0, 5.0),
    st.floats(-5.0, 5.0),
    st.integers(2, 30),
)
def test_move_path_against_look_at(
    seed: int, yaw0: float, pitch0: float, yaw: float, pitch: float, fwd: float, strafe: float, n: int
) -> None:
    eye = np.random.default_rng(seed).normal(size=3) * 3
    start = look_at(eye, eye + dir_from(yaw0, pitch0))
    path = move_path(start, yaw, pitch, fwd, strafe, n)
    assert path.shape == (n, 4, 4)
    np.testing.assert_array_equal(path[0], start)
    h = np.array([np.cos(yaw0), np.sin(yaw0), 0.0])  # start heading on the ground plane
    left = np.array([-np.sin(yaw0), np.cos(yaw0), 0.0])  # 90° counter-clockwise from h, seen from above
    for k in range(n):
        u = k / (n - 1)
        c = eye + u * fwd * h + u * strafe * left
        expected = look_at(c, c + dir_from(yaw0 + u * yaw, pitch0 + u * pitch))
        np.testing.assert_allclose(path[k], expected, atol=1e-10)
    ys, ps = heading_pitch(path)
    assert abs(wrap(ys[-1] - (yaw0 + yaw))) < 1e-10
    np.testing.assert_allclose(ps[-1], pitch0 + pitch, atol=1e-10)
    np.testing.assert_allclose(path[:, 0, 2], 0.0, atol=1e-12)  # camera x stays horizontal: no roll


def test_move_path_directions_in_the_image() -> None:
    start = look_at([0.0, 0.0, 1.0], [1.0, 0.0, 1.0])  # at 1 m height, looking along +x

    def pixel_x_sign(w2c: np.ndarray, X: list[float]) -> float:
        p = w2c[:3, :3] @ np.asarray(X) + w2c[:3, 3]
        return p[0] / p[2]

    def pixel_y_sign(w2c: np.ndarray, X: list[float]) -> float:
        p = w2c[:3, :3] @ np.asarray(X) + w2c[:3, 3]
        return p[1] / p[2]

    # A tree at world +y is on the left of the image (x < 0); turning left by 45° centres it.
    tree = [5.0, 5.0, 1.0]
    assert pixel_x_sign(start, tree) < 0
    turned = move_path(start, np.radians(45), 0.0, 0.0, 0.0, 5)[-1]
    assert abs(pixel_x_sign(turned, tree)) < 1e-12
    # A bird above the horizon is in the upper half (y < 0); pitching up by 45° centres it.
    bird = [5.0, 0.0, 6.0]
    assert pixel_y_sign(start, bird) < 0
    up = move_path(start, 0.0, np.radians(45), 0.0, 0.0, 5)[-1]
    assert abs(pixel_y_sign(up, bird)) < 1e-12
    # Forward moves along +x, a positive strafe to the left (+y), keeping the height.
    np.testing.assert_allclose(camera_centers(move_path(start, 0.0, 0.3, 2.0, 0.0, 3)[-1]), [2.0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(camera_centers(move_path(start, 0.5, 0.0, 0.0, 1.5, 3)[-1]), [0, 1.5, 1], atol=1e-12)
    # Ease: smoothstep progress, halfway at the middle frame, slow at the ends.
    eased = camera_centers(move_path(start, 0.0, 0.0, 4.0, 0.0, 5, ease=True))
    np.testing.assert_allclose(eased[:, 0], 4.0 * np.array([0.0, 5 / 32, 0.5, 27 / 32, 1.0]), atol=1e-12)
    # Looking straight down still has a heading (from the camera x axis): forward = image-up direction.
    down = look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], up=[1.0, 0.0, 0.0])
    np.testing.assert_allclose(camera_centers(move_path(down, 0, 0, 1.0, 0, 2)[-1]), [1.0, 0, 5], atol=1e-12)


def test_relative_motion_steps_on_a_hand_built_path() -> None:
    centres = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 2.0, 0], [1.0, 2.0, 0.5], [1.0, 2.0, 0.5]])
    yaws = np.array([0.0, 0.1, 0.3, 0.3, -0.2])
    w2c = np.stack([look_at(c, c + dir_from(y, 0.0)) for c, y in zip(centres, yaws, strict=True)])
    trans, rot = relative_motion_steps(w2c)
    np.testing.assert_allclose(trans, [1.0, 2.0, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(rot, [0.1, 0.2, 0.0, 0.5], atol=1e-12)
    w2c[2] = np.nan
    trans, rot = relative_motion_steps(w2c)
    np.testing.assert_array_equal(np.isnan(trans), [False, True, True, False])
    np.testing.assert_array_equal(np.isnan(rot), [False, True, True, False])
    np.testing.assert_allclose(trans[[0, 3]], [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rot[[0, 3]], [0.1, 0.5], atol=1e-12)


# ------------------------------------------------- the one Sim(3), quaternion, rot_z/rot_x, scene extent


def test_quaternion_edges_identity_pi_and_negative_w() -> None:
    from wonderverse.camera import quat_multiply

    np.testing.assert_array_equal(quat_from_matrix(np.eye(3)), [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(matrix_from_quat(np.array([1.0, 0, 0, 0])), np.eye(3))
    # rotations by π: w = 0, the axis up to sign, and back to the same matrix
    axes = [np.array(a, float) for a in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [-1, 2, -2], [0.3, -0.1, 0.9])]
    for axis in axes:
        axis /= np.linalg.norm(axis)
        R = Rotation.from_rotvec(PI * axis).as_matrix()
        q = quat_from_matrix(R)
        assert abs(q[0]) < 1e-15
        np.testing.assert_allclose(q[1:] * np.sign(q[1:] @ axis), axis, atol=1e-15)
        np.testing.assert_allclose(matrix_from_quat(q), R, atol=1e-15)
    # a quaternion and its negative (w < 0) are one rotation; the canonical one has w >= 0
    rng = np.random.default_rng(4)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        neg = -q if q[0] > 0 else q  # w < 0
        np.testing.assert_allclose(matrix_from_quat(neg), matrix_from_quat(-neg), atol=1e-15)
        np.testing.assert_allclose(quat_from_matrix(matrix_from_quat(neg)), -neg, atol=1e-14)
    # the Hamilton product composes the rotations: q(a) * q(b) is a after b
    a, b = (Rotation.random(random_state=s) for s in (1, 2))
    qa, qb = (r.as_quat()[[3, 0, 1, 2]] for r in (a, b))
    np.testing.assert_allclose(matrix_from_quat(quat_multiply(qa, qb)), (a * b).as_matrix(), atol=1e-14)


def test_torch_and_numpy_rotation_from_quaternion_agree_except_at_zero() -> None:
    import torch

    from wonderverse.splats.model import quat_to_rotmat

    rng = np.random.default_rng(5)
    q = rng.normal(size=(64, 4)) * 3
    q[:16, 0] = -np.abs(q[:16, 0])  # negative w
    q[16] = [0.0, 1.0, 0.0, 0.0]  # rotation by π about x
    np.testing.assert_allclose(quat_to_rotmat(torch.from_numpy(q)).numpy(), matrix_from_quat(q), atol=1e-14)
    # a zero quaternion: the identity for a Gaussian (gsplat's convention), an error for a camera
    np.testing.assert_array_equal(quat_to_rotmat(torch.zeros(1, 4, dtype=torch.float64)).numpy()[0], np.eye(3))
    with pytest.raises(ValueError):
        matrix_from_quat(np.zeros(4))


def test_rot_z_and_rot_x() -> None:
    from wonderverse.camera import rot_x, rot_z

    np.testing.assert_allclose(rot_z(PI / 2) @ [1.0, 0, 0], [0, 1, 0], atol=1e-15)  # counter-clockwise from above
    np.testing.assert_allclose(rot_x(PI / 2) @ [0, 1.0, 0], [0, 0, 1], atol=1e-15)  # y towards z
    a = np.linspace(-3, 3, 7)
    assert rot_z(a).shape == (7, 3, 3) and rot_x(a.reshape(7, 1)).shape == (7, 1, 3, 3)
    np.testing.assert_allclose(rot_z(a), so3_exp(a[:, None] * [0, 0, 1.0]), atol=1e-15)
    np.testing.assert_allclose(rot_x(a), so3_exp(a[:, None] * [1.0, 0, 0]), atol=1e-15)


def test_sim3_about_a_centre_is_the_same_map_in_matrix_form() -> None:
    rng = np.random.default_rng(6)
    for _ in range(10):
        s, R = 10.0 ** rng.uniform(-2, 2), random_rotation(rng)
        t, c = rng.normal(size=3) * 10, rng.normal(size=3) * 1e3
        a = Sim3(s, R, t, center=c)
        p = rng.normal(size=(20, 3)) * 1e3
        np.testing.assert_allclose(a.apply(p), s * (p - c) @ R.T + t, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(a.apply(p), Sim3(s, R, a.translation).apply(p), rtol=1e-12, atol=1e-8)
        h = np.concatenate([p, np.ones((20, 1))], 1)
        np.testing.assert_allclose((h @ a.matrix().T)[:, :3], a.apply(p), rtol=1e-12, atol=1e-8)
        np.testing.assert_allclose(a.apply_inverse(a.apply(p)), p, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(a.inverse().apply(a.apply(p)), p, rtol=1e-12, atol=1e-9)
        b = Sim3(2.0, random_rotation(rng), rng.normal(size=3), center=rng.normal(size=3))
        np.testing.assert_allclose(a.compose(b).apply(p), a.apply(b.apply(p)), rtol=1e-12, atol=1e-8)
        # cameras move with the scene: what a camera sees (pixels) stays, depth scales by s
        w2c = np.stack([look_at(x, x + np.array([1.0, 0.2, 0.1])) for x in p[:3]])
        moved = a.transform_w2c(w2c)
        cam, cam_moved = p @ w2c[0, :3, :3].T + w2c[0, :3, 3], a.apply(p) @ moved[0, :3, :3].T + moved[0, :3, 3]
        np.testing.assert_allclose(cam_moved, s * cam, rtol=1e-9, atol=1e-6 * s * np.abs(cam).max())
        np.testing.assert_allclose(a.inverse_transform_w2c(moved), w2c, atol=1e-9)
        again = Sim3.from_dict(a.to_dict())
        np.testing.assert_array_equal(again.apply(p), a.apply(p))


def test_sim3_without_a_centre_computes_exactly_as_before() -> None:
    rng = np.random.default_rng(7)
    a, p = random_sim3(rng), rng.normal(size=(30, 3)) * 5
    np.testing.assert_array_equal(a.apply(p), a.s * (p @ a.R.T) + a.t)  # the plain form, bit for bit
    w2c = np.stack([look_at(x, x + np.array([1.0, 0.0, 0.3])) for x in p[:4]])
    Rc = w2c[:, :3, :3] @ a.R.T
    np.testing.assert_array_equal(a.transform_w2c(w2c)[:, :3, 3], a.s * w2c[:, :3, 3] - np.einsum("nij,j->ni", Rc, a.t))
    assert set(a.to_dict()) == {"s", "R", "t"}  # the stored model_to_world layout


def test_scene_extent_span_and_camera_radius() -> None:
    from wonderverse.camera import camera_radius, scene_extent, span

    cams = np.stack([look_at(np.array([x, 0.0, 1.0]), np.array([x, 5.0, 1.0])) for x in (0.0, 3.0, 6.0)])
    assert scene_extent(cams) == pytest.approx(6.0)
    with_nan = np.concatenate([cams, np.full((1, 4, 4), np.nan)])
    assert scene_extent(with_nan) == pytest.approx(6.0)  # unregistered frames are skipped
    assert scene_extent(with_nan, [np.full((2, 2), 2.0), np.array([[4.0, np.inf], [0.0, np.nan]])]) == pytest.approx(
        6.0 + 2 * 2.0  # median of the valid depths (2, 2, 2, 2, 4) is 2
    )
    turning = np.stack([look_at(np.array([1e3, 0, 1]), np.array([1e3 + np.cos(a), np.sin(a), 1])) for a in (0, 1, 2)])
    assert scene_extent(turning) == 0.0  # a camera that only turns: centres equal up to rounding
    assert scene_extent(turning, [np.full((2, 2), np.inf)]) == 1.0  # with depths always positive
    assert span(np.zeros((0, 3))) == 0.0 and span(np.array([[0, 0, 0], [3.0, 4, 0]])) == pytest.approx(5.0)
    assert camera_radius(cams) == pytest.approx(3.0) and camera_radius(np.zeros((0, 4, 4))) == 0.0


def test_fit_intrinsics_scales_rows_and_never_enlarges() -> None:
    from wonderverse.camera import fit_intrinsics, intrinsics

    K = intrinsics(640, 480, 60.0)
    w, h, Ks = fit_intrinsics(640, 480, K, 320)
    assert (w, h) == (320, 240)
    np.testing.assert_allclose(Ks, np.diag([0.5, 0.5, 1.0]) @ K, atol=1e-12)
    np.testing.assert_allclose(Ks[:2, 2], [160.0, 120.0])  # still centred: pixel centres at +0.5
    w, h, same = fit_intrinsics(640, 480, K, 1000)
    assert (w, h) == (640, 480) and np.array_equal(same, K) and same is not K
    w, h, per_frame = fit_intrinsics(100, 3, np.stack([K, 2 * K]), 10)
    assert (w, h) == (10, 1) and per_frame.shape == (2, 3, 3)
    np.testing.assert_allclose(per_frame[1, 1], 2 * K[1] / 3)  # each side's own ratio, at least one pixel


def test_pixels_to_world_land_where_the_camera_projects_them_back():
    K = np.array([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])
    w2c = look_at(np.array([1.0, 2.0, 3.0]), np.array([5.0, 5.0, 3.0]))
    u, v, z = np.array([10.5, 40.25]), np.array([3.5, 30.0]), np.array([2.0, 7.5])
    cam = pixels_to_world(u, v, z, K, w2c) @ w2c[:3, :3].T + w2c[:3, 3]
    np.testing.assert_allclose(cam[:, 2], z)
    np.testing.assert_allclose(K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], u)
    np.testing.assert_allclose(K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2], v)


def test_world_to_pixels_inverts_pixels_to_world_and_frames_only_what_is_in_front() -> None:
    from wonderverse.camera import intrinsics, world_to_pixels

    K = intrinsics(64, 48, 70.0)
    w2c = look_at(np.array([3.0, -2.0, 1.5]), np.array([0.0, 0.0, 1.0]))
    u, v, z = np.array([0.5, 31.7, 63.9]), np.array([0.5, 20.2, 47.9]), np.array([0.1, 5.0, 1e4])
    pts = pixels_to_world(u, v, z, K, w2c)
    u2, v2, z2, framed = world_to_pixels(pts, K, w2c, 48, 64)
    np.testing.assert_allclose(np.stack([u2, v2, z2]), np.stack([u, v, z]), rtol=1e-9, atol=1e-7)
    assert framed.all()
    centre = pixels_to_world(np.array([32.0]), np.array([24.0]), np.array([2.0]), K, w2c)[0]
    eye = np.array([3.0, -2.0, 1.5])
    behind = 2 * eye - centre  # the mirror image through the camera centre: projects inside, but z < 0
    outside = pixels_to_world(np.array([80.0]), np.array([24.0]), np.array([2.0]), K, w2c)[0]
    _, _, zb, framed = world_to_pixels(np.stack([behind, outside, eye]), K, w2c, 48, 64)
    assert zb[0] < 0 and not framed.any()  # behind, beside the image, at the centre (z = 0)
