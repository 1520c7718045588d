"""normals_from_depth against analytic surfaces (planes, a sphere, step edges), with sky, NaN, float16
and depth ranges from 1e-3 to 1e4."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from wonderverse.camera import intrinsics
from wonderverse.errors import WonderError
from wonderverse.priors import NormalsFromDepth, normals_from_depth

H, W = 48, 64
K = intrinsics(W, H, 60.0)


def rays(K: np.ndarray = K, h: int = H, w: int = W) -> np.ndarray:
    """(h,w,3) rays (a, b, 1) through pixel centres (+0.5)."""
    u = np.arange(w) + 0.5
    v = np.arange(h) + 0.5
    a = (u[None, :] - K[0, 2]) / K[0, 0]
    b = (v[:, None] - K[1, 2]) / K[1, 1]
    return np.stack(np.broadcast_arrays(a, b, np.ones_like(a)), axis=-1)


def plane_depth(n: np.ndarray, d: float, K: np.ndarray = K, h: int = H, w: int = W) -> np.ndarray:
    """Camera z of the plane {X : n.X = d} along each pixel ray (n facing the camera, d < 0)."""
    return d / (rays(K, h, w) @ n)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def unit(v: tuple[float, float, float]) -> np.ndarray:
    n = np.asarray(v, dtype=np.float64)
    return n / np.linalg.norm(n)


@pytest.mark.parametrize("n", [unit((0, 0, -1)), unit((0.3, -0.5, -0.8)), unit((-0.6, 0.1, -0.4)), unit((0, -1, -0.8))])
def test_planes_are_exact(n: np.ndarray) -> None:
    z = plane_depth(n, -4.0)
    assert (z > 0).all()
    normals, valid = normals_from_depth(z, K)
    assert normals.shape == (H, W, 3) and normals.dtype == np.float32
    assert valid.all()
    assert angle_deg(normals, n).max() < 0.05


def test_sphere_normals_match_analytic() -> None:
    # One-sided differences are first order: the error is about half the angle the surface turns per
    # pixel, so use a sphere ~70 px in radius.
    h, w = 192, 256
    k = intrinsics(w, h, 60.0)
    c, r = np.array([0.2, -0.1, 5.0]), 1.5
    ray = rays(k, h, w)
    # |t ray - c| = r  ->  t^2 |ray|^2 - 2 t ray.c + |c|^2 - r^2 = 0, nearest root; t is the camera z.
    aa = (ray * ray).sum(-1)
    bb = -2.0 * (ray @ c)
    cc = c @ c - r * r
    disc = bb * bb - 4 * aa * cc
    hit = disc > 0
    z = np.where(hit, (-bb - np.sqrt(np.where(hit, disc, 0))) / (2 * aa), np.inf)
    truth = (ray * z[..., None] - c) / r
    normals, valid = normals_from_depth(z, k)
    assert not valid[~hit].any()
    assert (normals[~hit] == 0).all()
    # Interior of the disc (away from the silhouette, where the surface is at grazing angles).
    inner = hit & (truth[..., 2] < -0.5)
    assert valid[inner].all()
    assert np.median(angle_deg(normals[inner], truth[inner])) < 1.0
    assert angle_deg(normals[inner], truth[inner]).max() < 3.0


def test_step_edges_keep_each_pixel_on_its_own_surface() -> None:
    # Left half: a tilted plane near the camera; right half: a wall far behind with another normal.
    n_near, n_far = unit((0.4, -0.2, -0.9)), unit((-0.2, 0.3, -1.0))
    z = plane_depth(n_near, -2.0)
    z_far = plane_depth(n_far, -20.0)
    z[:, W // 2 :] = z_far[:, W // 2 :]
    # and a horizontal edge too: the bottom rows are the far wall as well
    z[-10:] = z_far[-10:]
    normals, valid = normals_from_depth(z, K)
    assert valid.all()
    near = np.zeros((H, W), dtype=bool)
    near[:-10, : W // 2] = True
    assert angle_deg(normals[near], n_near).max() < 0.05  # the columns/rows next to the edges included
    assert angle_deg(normals[~near], n_far).max() < 0.05


def test_sky_nan_zero_and_all_sky_give_zero_invalid_finite() -> None:
    n = unit((0.1, -0.3, -1.0))
    z = plane_depth(n, -3.0)
    z[:5] = np.inf
    z[10:14, 20:30] = np.nan
    z[30, 40] = 0.0
    z[31, 41] = -2.0
    normals, valid = normals_from_depth(z, K)
    bad = ~np.isfinite(z) | (z <= 0)
    assert np.isfinite(normals).all()
    assert not valid[bad].any()
    assert (normals[bad] == 0).all()
    # pixels next to holes still have a neighbour on each axis and are exact
    assert angle_deg(normals[valid], n).max() < 0.05
    assert valid.sum() == (~bad).sum()

    for fill in (np.inf, np.nan, 0.0):
        sky = np.full((2, H, W), fill, dtype=np.float32)
        ns, vs = normals_from_depth(sky, K)
        assert ns.shape == (2, H, W, 3) and np.isfinite(ns).all() and not vs.any() and (ns == 0).all()


def test_isolated_pixel_is_invalid() -> None:
    z = np.full((H, W), np.inf)
    z[10, 10] = 2.0
    z[20, 20:22] = 3.0  # a horizontal pair: x has a neighbour, y has none
    normals, valid = normals_from_depth(z, K)
    assert not valid.any() and (normals == 0).all()


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e4])
def test_depth_scale_does_not_matter(scale: float) -> None:
    n = unit((0.2, -0.6, -0.7))
    z = plane_depth(n, -5.0) * scale
    assert z.min() >= 0.9e-3 and z.max() <= 1e4 * 20
    normals, valid = normals_from_depth(z, K)
    assert valid.all()
    assert angle_deg(normals, n).max() < 0.05


def test_float16_input() -> None:
    # A steep ground plane: float16 rounds depth to ~5e-4 relative, far below its per-pixel change.
    n = unit((0.0, -1.0, -0.15))
    z = plane_depth(n, -1.5)
    z[z <= 0] = np.inf
    z16 = z.astype(np.float16)
    normals, valid = normals_from_depth(z16, K)
    assert normals.dtype == np.float32 and np.isfinite(normals).all()
    fin = np.isfinite(z16.astype(np.float32))
    assert valid.sum() >= 0.9 * fin.sum()
    assert np.median(angle_deg(normals[valid], n)) < 3.0
    # depths near float16's top (6.5e4) and bottom stay finite too
    big = np.full((H, W), 6.0e4, dtype=np.float16)
    tiny = np.full((H, W), 1e-3, dtype=np.float16)
    for arr in (big, tiny):
        nn_, vv = normals_from_depth(arr, K)
        assert vv.all() and np.abs(angle_deg(nn_, np.array([0.0, 0.0, -1.0]))).max() < 0.05


def test_batch_matches_singles_and_per_frame_K() -> None:
    n1, n2 = unit((0.3, -0.5, -0.8)), unit((0.0, 0.0, -1.0))
    K2 = intrinsics(W, H, 90.0)
    z = np.stack([plane_depth(n1, -4.0), plane_depth(n2, -4.0, K2)])
    Ks = np.stack([K, K2])
    batch, vb = normals_from_depth(z, Ks)
    for i, k in enumerate(Ks):
        single, vs = normals_from_depth(z[i], k)
        np.testing.assert_array_equal(batch[i], single)
        np.testing.assert_array_equal(vb[i], vs)
    assert angle_deg(batch[0], n1).max() < 0.05 and angle_deg(batch[1], n2).max() < 0.05
    with pytest.raises(ValueError):
        normals_from_depth(z, np.stack([K, K, K]))


def test_max_rel_step_marks_grazing_surfaces_invalid() -> None:
    # Nearly edge-on plane: neighbouring depths differ by far more than 10 %.
    n = unit((0.0, -1.0, -0.01))
    z = plane_depth(n, -1.0)
    z[z <= 0] = np.inf
    _, v_all = normals_from_depth(z, K)
    _, v_cut = normals_from_depth(z, K, max_rel_step=0.1)
    assert v_cut.sum() < v_all.sum()
    assert not (v_cut & ~v_all).any()


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    log_scale=st.floats(-3.0, 4.0),
    holes=st.floats(0.0, 0.5),
)
def test_random_depth_maps_give_finite_unit_camera_facing_normals(seed: int, log_scale: float, holes: float) -> None:
    rng = np.random.default_rng(seed)
    z = (10**log_scale) * rng.uniform(0.5, 2.0, (2, 12, 16))
    z[rng.random(z.shape) < holes] = rng.choice([np.inf, np.nan, 0.0, -1.0])
    k = intrinsics(16, 12, 70.0)
    normals, valid = normals_from_depth(z, k)
    assert np.isfinite(normals).all()
    norms = np.linalg.norm(normals, axis=-1)
    np.testing.assert_allclose(norms[valid], 1.0, atol=1e-5)
    assert (normals[~valid] == 0).all()
    facing = (normals * rays(k, 12, 16)).sum(-1)
    assert (facing[valid] < 0).all()


def test_model_wrapper_needs_K_and_depth() -> None:
    frames = np.zeros((2, H, W, 3), dtype=np.uint8)
    z = np.stack([plane_depth(unit((0, 0, -1)), -2.0)] * 2)
    pred = NormalsFromDepth().predict(frames, K=K, depth=z)
    assert pred.normals.shape == (2, H, W, 3) and pred.confidence is not None
    assert pred.confidence.dtype == np.float32 and (pred.confidence == 1).all()
    with pytest.raises(WonderError):
        NormalsFromDepth().predict(frames, K=None, depth=z)
    with pytest.raises(WonderError):
        NormalsFromDepth().predict(frames, K=K, depth=None)


def test_smoothing_tames_per_pixel_noise_and_keeps_sky() -> None:
    from wonderverse.camera import intrinsics
    from wonderverse.priors.from_depth import NormalsFromDepth, smooth_depth
    from wonderverse.priors.params import FromDepthParams

    K = intrinsics(96, 64, 60.0)
    v = np.arange(64)[:, None] + 0.5
    b = (v - K[1, 2]) / K[1, 1] + 0 * np.arange(96)[None, :]
    ground = np.where(b > 0.02, 1.5 / np.maximum(b, 1e-6), np.inf).astype(np.float32)  # floor 1.5 m below
    noisy = ground * (1 + 0.02 * np.random.default_rng(0).standard_normal(ground.shape)).astype(np.float32)
    frames = np.zeros((1, 64, 96, 3), np.uint8)
    truth = np.array([0.0, -1.0, 0.0])  # floor normal points up: -y in OpenCV camera axes

    def mean_err(smooth: float) -> float:
        n = NormalsFromDepth(FromDepthParams(smooth_px=smooth)).predict(frames, K=K, depth=noisy[None]).normals[0]
        ok = np.isfinite(ground)
        return float(np.degrees(np.arccos(np.clip(n[ok] @ truth, -1, 1))).mean())

    assert mean_err(1.5) < 0.5 * mean_err(0.0)
    sm = smooth_depth(noisy, 1.5)
    assert np.array_equal(np.isinf(sm), np.isinf(noisy)) and np.isfinite(sm[np.isfinite(noisy)]).all()
