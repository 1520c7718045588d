"""prune_for_export on constructed scenes: planted floaters and absurd Gaussians go, everything a camera sees or
the SfM points vouch for stays; planted needles are shortened, discs and round Gaussians left as they are. Ground
truth is the construction (where each Gaussian was put, and its axes)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from wonderverse.camera import intrinsics, look_at
from wonderverse.splats.cleanup import ExportPruneParams, axis_ratios, in_any_view, prune_for_export, shorten_needles

W, H = 160, 120
K = intrinsics(W, H, 60.0)
EXTENT = 25.0  # the constructed scene's size
SIDE = EXTENT / math.sqrt(3.0)  # a cube whose diagonal is the scene extent


def _cameras(n: int = 6) -> np.ndarray:
    """Cameras on a ring just inside the cube's top, each looking at the cube's centre."""
    angles = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    eyes = np.stack([4.0 * np.cos(angles), 4.0 * np.sin(angles), np.full(n, 2.0)], axis=1)
    return np.stack([look_at(e, np.zeros(3), np.array([0.0, 0.0, 1.0])) for e in eyes])


def _gaussians(means: np.ndarray, sigma: float = 0.05, opacity: float = 0.8) -> dict[str, np.ndarray]:
    n = len(means)
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1.0
    return {
        "means": np.asarray(means, np.float32),
        "quats": quats,
        "log_scales": np.full((n, 3), math.log(sigma), np.float32),
        "logit_opacities": np.full(n, math.log(opacity / (1 - opacity)), np.float32),
        "sh0": np.zeros((n, 1, 3), np.float32),
        "shN": np.zeros((n, 3, 3), np.float32),
    }


def _cat(*parts: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


@pytest.fixture
def scene() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """SfM points filling the 25-unit cube (its corners included) and Gaussians jittered around them."""
    rng = np.random.default_rng(0)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * SIDE / 2
    points = np.concatenate([rng.uniform(-SIDE / 2, SIDE / 2, size=(600, 3)), corners])
    cloud = points[rng.integers(0, len(points), 3000)] + rng.normal(0, 0.1, size=(3000, 3))
    return _cameras(), points, _gaussians(cloud)


def test_floaters_far_away_and_a_59_unit_splat_are_removed_the_cloud_stays(scene):
    w2c, points, cloud = scene
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(20, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    floaters = _gaussians(20.0 * 25.0 * directions)
    # a floater straight ahead of camera 0, 20 extents away: inside its frustum, far beyond anything seen
    eye = -w2c[0, :3, :3].T @ w2c[0, :3, 3]
    ahead = _gaussians((eye + 500.0 * w2c[0, 2, :3])[None])
    huge = _gaussians(np.zeros((1, 3)), sigma=59.0 / 6.0)  # 59 units wide (6 σ) in the middle of the scene
    faint = _gaussians(np.full((1, 3), 1.0), opacity=0.002)
    nan = _gaussians(np.full((1, 3), np.nan))
    everything = _cat(cloud, floaters, ahead, huge, faint, nan)
    assert in_any_view(ahead["means"], w2c, K, W, H, 0.0, 1e9).all(), "precondition: camera 0 looks at it"

    kept, report = prune_for_export(everything, w2c, K, W, H, points, EXTENT)

    n = len(cloud["means"])
    assert report["before"] == n + 24 and report["after"] == n
    assert report["removed"] == {"non_finite": 1, "transparent": 1, "too_large": 1, "outside_views": 21}
    np.testing.assert_array_equal(kept["means"], cloud["means"])  # the cloud, whole and in order
    assert set(kept) == set(everything) and all(kept[k].dtype == everything[k].dtype for k in kept)
    assert report["extent"] == pytest.approx(25.0, rel=0.1)
    assert max(np.abs(report["bounds_before"]["max"]).max(), np.abs(report["bounds_before"]["min"]).max()) > 400
    assert np.all(np.abs(report["bounds_after"]["min"]) < SIDE) and np.all(np.abs(report["bounds_after"]["max"]) < SIDE)


def _outward_cameras() -> np.ndarray:
    """Three level cameras at the cube's centre looking outwards 120° apart: their views, even grown by the
    default margin (98° wide), do not overlap."""
    yaws = np.radians([0.0, 120.0, 240.0])
    targets = np.stack([np.cos(yaws), np.sin(yaws), np.zeros(3)], axis=1)
    return np.stack([look_at(np.zeros(3), t, np.array([0.0, 0.0, 1.0])) for t in targets])


@pytest.mark.parametrize("margin", [0.0, 0.5])
def test_a_gaussian_one_camera_sees_at_its_edge_stays(scene, margin):
    _, points, cloud = scene
    w2c = _outward_cameras()
    params = ExportPruneParams(view_margin_frac=margin)
    pose, depth = w2c[0], 14.0

    def at_pixel(u: float, v: float) -> np.ndarray:
        ray_cam = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0]) * depth
        return pose[:3, :3].T @ (ray_cam - pose[:3, 3])

    edge = at_pixel(W - 0.6, H / 2)  # in camera 0's last pixel column
    assert in_any_view(edge[None], w2c[:1], K, W, H, 0.0, 1e9).all()
    assert not in_any_view(edge[None], w2c[1:], K, W, H, 0.5, 1e9).any(), "precondition: only camera 0 sees it"
    assert cKDTree(points).query(edge)[0] > 0.1 * 25.0, "precondition: far from every SfM point"
    kept, report = prune_for_export(_cat(cloud, _gaussians(edge[None])), w2c, K, W, H, points, EXTENT, params)
    assert report["after"] == report["before"] and report["removed"]["outside_views"] == 0
    np.testing.assert_allclose(kept["means"][-1], edge.astype(np.float32))
    # the same Gaussian just past the grown edge, still far from the points, goes
    beyond = at_pixel(W * (1.0 + margin) + 4.0, H / 2)
    assert cKDTree(points).query(beyond)[0] > 0.1 * 25.0
    report = prune_for_export(_cat(cloud, _gaussians(beyond[None])), w2c, K, W, H, points, EXTENT, params)[1]
    assert report["removed"]["outside_views"] == 1 and report["after"] == len(cloud["means"])


def test_distant_scenery_near_sfm_points_stays_and_without_points_only_views_count(scene):
    w2c, points, cloud = scene
    far_point = np.array([0.0, 0.0, 400.0])  # straight up: above every camera's view
    assert not in_any_view(far_point[None], w2c, K, W, H, 0.5, 1e9).any(), "precondition: nobody looks up"
    scenery = _gaussians(far_point[None] + np.array([[0.3, 0.0, 0.0]]))
    with_point = np.concatenate([points, far_point[None]])
    report = prune_for_export(_cat(cloud, scenery), w2c, K, W, H, with_point, EXTENT)[1]
    assert report["removed"]["outside_views"] == 0, "an SfM point vouches for it"
    kept = prune_for_export(_cat(cloud, scenery), w2c, K, W, H, None, EXTENT)[0]
    assert not (kept["means"][:, 2] > 100).any(), "with no points, out of every view is out"
    # without points to vouch for them, what stays is what the cameras see: the whole cloud in front of them
    seen = np.zeros(len(cloud["means"]), bool)
    for pose in w2c:
        cam = cloud["means"] @ pose[:3, :3].T + pose[:3, 3]
        u, v = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
        seen |= (cam[:, 2] > 0) & (u >= 0) & (u <= W) & (v >= 0) & (v <= H)
    assert seen.sum() > 1000, "precondition: the cameras see much of the cloud"
    kept_rows = {tuple(r) for r in kept["means"]}
    assert all(tuple(r) in kept_rows for r in cloud["means"][seen])


def test_thresholds_are_settings(scene):
    w2c, points, cloud = scene
    big = _gaussians(np.zeros((1, 3)), sigma=2.0)  # 12 units wide in a 25-unit scene
    assert prune_for_export(_cat(cloud, big), w2c, K, W, H, points, EXTENT)[1]["removed"]["too_large"] == 0
    strict = ExportPruneParams(max_width_extent_frac=0.4)
    assert prune_for_export(_cat(cloud, big), w2c, K, W, H, points, EXTENT, strict)[1]["removed"]["too_large"] == 1
    with pytest.raises(ValueError):
        ExportPruneParams(min_opacity=1.5)
    with pytest.raises(ValueError):
        ExportPruneParams(unknown_setting=1)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(0, 60),
    margin=st.floats(0.0, 1.0),
)
def test_counts_add_up_and_what_stays_is_in_order(seed, n, margin):
    rng = np.random.default_rng(seed)
    w2c = _cameras(3)
    points = rng.uniform(-5, 5, size=(20, 3))
    g = _gaussians(rng.normal(0, 30, size=(n, 3)), sigma=float(rng.uniform(0.01, 5)))
    g["logit_opacities"] = rng.normal(0, 4, size=n).astype(np.float32)
    extent = 10.0 * math.sqrt(3.0)  # the points' box
    kept, report = prune_for_export(g, w2c, K, W, H, points, extent, ExportPruneParams(view_margin_frac=margin))
    assert report["before"] == n and report["after"] == len(kept["means"])
    assert sum(report["removed"].values()) == n - report["after"]
    # what stays is a subsequence of the input: each kept row is found in order
    rows = [tuple(r) for r in g["means"]]
    pos = [rows.index(tuple(r)) for r in kept["means"]]
    assert pos == sorted(pos)
    near = np.linalg.norm(g["means"][:, None] - points[None], axis=2).min(1) <= 0.1 * extent * 0.999
    ok = (1 / (1 + np.exp(-g["logit_opacities"])) >= 1 / 255) & (6 * np.exp(g["log_scales"].max(1)) <= extent)
    # a Gaussian close to an SfM point, opaque enough and not too large, always stays
    kept_rows = {tuple(r) for r in kept["means"]}
    assert all(tuple(r) in kept_rows for r in g["means"][near & ok])


# ---------------------------------------------------------------------------------------------- needles


def _shaped(axes: list[tuple[float, float, float]], means: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Gaussians at `means` (default: on the cube's centre line) with the given σ per axis."""
    means = np.stack([np.array([0.0, 0.0, 0.3 * i]) for i in range(len(axes))]) if means is None else means
    g = _gaussians(means)
    g["log_scales"] = np.log(np.asarray(axes, np.float32))
    return g


def test_a_needle_is_shortened_a_disc_and_a_ball_are_kept_as_they_are(scene):
    """Three Gaussians among the cloud: a needle (σ 1.0 × 0.02 × 0.02, ratio 50), a disc (1.0 × 1.0 × 0.02: flat,
    largest / middle 1) and a ball. The needle's long axis is cut to 10 × its middle one (0.2), nothing else of
    any Gaussian changes, and the three stay exported."""
    w2c, points, cloud = scene
    planted = _shaped([(1.0, 0.02, 0.02), (1.0, 1.0, 0.02), (0.1, 0.1, 0.1)])
    ratio, flatness = axis_ratios(planted["log_scales"])
    np.testing.assert_allclose(ratio, [50.0, 1.0, 1.0], rtol=1e-5)
    np.testing.assert_allclose(flatness, [50.0, 50.0, 1.0], rtol=1e-5)  # max/min cannot tell a disc from a needle
    kept, report = prune_for_export(_cat(cloud, planted), w2c, K, W, H, points, EXTENT)
    assert report["after"] == report["before"] == len(cloud["means"]) + 3
    assert report["needles_shortened"] == 1
    got = np.exp(kept["log_scales"][-3:])
    np.testing.assert_allclose(got, [(0.2, 0.02, 0.02), (1.0, 1.0, 0.02), (0.1, 0.1, 0.1)], rtol=1e-5)
    np.testing.assert_array_equal(kept["log_scales"][:-3], cloud["log_scales"])
    for name in ("means", "quats", "logit_opacities", "sh0", "shN"):
        np.testing.assert_array_equal(kept[name], _cat(cloud, planted)[name])


def test_the_needle_limit_is_a_setting_and_the_long_axis_is_found_in_any_column(scene):
    """A needle long along its second axis (0.02 × 0.3 × 0.01, ratio 15): shortened to 0.2 at the default limit,
    to 20 × 0.02 = 0.4 (so left as is) at limit 20, to 3 × 0.02 at limit 3."""
    w2c, points, cloud = scene
    needle = _shaped([(0.02, 0.3, 0.01)])
    for limit, want in ((10.0, 0.2), (20.0, 0.3), (3.0, 0.06)):
        p = ExportPruneParams(max_needle_ratio=limit)
        kept, report = prune_for_export(_cat(cloud, needle), w2c, K, W, H, points, EXTENT, p)
        np.testing.assert_allclose(np.exp(kept["log_scales"][-1]), [0.02, want, 0.01], rtol=1e-5)
        assert report["needles_shortened"] == (want != 0.3)
    with pytest.raises(ValueError):
        ExportPruneParams(max_needle_ratio=1.0)  # every Gaussian but a ball would be a needle


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-8.0, 3.0)] * 3), min_size=1, max_size=30), st.floats(1.01, 100.0))
def test_shortened_needles_keep_their_two_short_axes_and_end_at_the_limit(log_axes, limit):
    ls = np.asarray(log_axes, np.float64)
    out, needle = shorten_needles(ls, limit)
    ratio_before, _ = axis_ratios(ls)
    ratio_after, _ = axis_ratios(out)
    np.testing.assert_array_equal(needle, ratio_before > limit)
    np.testing.assert_array_equal(out[~needle], ls[~needle])
    assert np.all(ratio_after <= limit * (1 + 1e-9))
    np.testing.assert_allclose(ratio_after[needle], limit, rtol=1e-9)
    np.testing.assert_array_equal(np.sort(out, 1)[:, :2], np.sort(ls, 1)[:, :2])  # the two shorter axes unchanged
