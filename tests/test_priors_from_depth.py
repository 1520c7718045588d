"""normals_from_depth against analytic surfaces (planes, a sphere, step edges). Extremes (sky, NaN, float16,
depths from 1e-3 to 1e4) are in test_extremes.py, which imports the helpers here."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_isolated_pixel_is_invalid() -> None:
    z = np.full((H, W), np.inf)
    z[10, 10] = 2.0
    z[20, 20:22] = 3.0  # a horizontal pair: x has a neighbour, y has none
    normals, valid = normals_from_depth(z, K)
    assert not valid.any() and (normals == 0).all()


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
