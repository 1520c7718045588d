"""Tests of wonderverse.metrics against hand-derived values and an independent scipy.ndimage SSIM."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage
from scipy.spatial.transform import Rotation

from wonderverse.camera import Sim3, look_at
from wonderverse.metrics import ate as ate_metric
from wonderverse.metrics import depth_errors, normal_errors, psnr, ssim

SLOW = settings(max_examples=60, deadline=None)
seeds = st.integers(0, 2**32 - 1)


def trajectory(rng: np.random.Generator, n: int = 12) -> np.ndarray:
    """W2C poses along a curved, non-planar path."""
    s = np.linspace(0.0, 1.0, n)
    centres = np.stack([3 * np.cos(2 * s), 3 * np.sin(2 * s), 0.5 * s**2], axis=1) + rng.normal(size=3)
    return np.stack([look_at(c, c + rng.normal(size=3) + [0, 0, 0.1]) for c in centres])


def poses_at(centres: np.ndarray) -> np.ndarray:
    return np.stack([look_at(c, c + np.array([1.0, 0.3, 0.1])) for c in centres])


# -------------------------------------------------------------------------------------------------- ATE


@SLOW
@given(seeds, st.floats(-4.0, 4.0))
def test_ate_is_zero_for_a_similarity_copy(seed: int, log10_scale: float) -> None:
    rng = np.random.default_rng(seed)
    gt = trajectory(rng)
    T = Sim3(10.0**log10_scale, Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 100)
    est = T.transform_w2c(gt)  # what an SfM run in another frame and scale would return
    r = ate_metric(est, gt, align="sim3")
    # est's numbers carry float64 rounding of their own size; seen in gt's units that rounding grows by 1 / scale
    rounding = np.finfo(float).eps * np.abs(est).max() / T.s
    assert r["n"] == 12
    assert r["rmse"] < 1e-9 + 1e5 * rounding
    assert r["rmse_frac"] < 1e-9 + 1e5 * rounding
    if abs(log10_scale) > 0.1:  # a rigid fit cannot undo a scale change
        assert ate_metric(est, gt, align="se3")["rmse"] > 1e-3
    rigid = Sim3(1.0, T.R, T.t).transform_w2c(gt)
    assert ate_metric(rigid, gt, align="se3")["rmse"] < 1e-9


@pytest.mark.parametrize("delta", [0.01, 0.1, 0.5])
def test_ate_for_a_known_perturbation(delta: float) -> None:
    # Unit square in the plane z = 0; the estimate lifts the corners alternately by ±delta (a saddle).
    # That perturbation is orthogonal to every rigid motion, so the best rigid fit is the identity and
    # the error is delta. With scale, Umeyama shrinks the estimate by s = 1 / (1 + 2 delta²):
    # residual per corner r = (1 - s) x - s e, |x|² = 1/2, |e|² = delta².
    square = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 1.0, 0], [0.0, 1.0, 0]])
    e = np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0], [0, 0, -1.0]]) * delta
    gt, est = poses_at(square), poses_at(square + e)
    r = ate_metric(est, gt, align="se3")
    np.testing.assert_allclose(r["rmse"], delta, rtol=1e-12)
    np.testing.assert_allclose(r["rmse_frac"], delta / 3.0, rtol=1e-12)  # GT path: three unit edges
    s = 1.0 / (1.0 + 2.0 * delta**2)
    expected = np.sqrt(0.5 * (1 - s) ** 2 + s**2 * delta**2)
    np.testing.assert_allclose(ate_metric(est, gt, align="sim3")["rmse"], expected, rtol=1e-10)
    # Without alignment: a constant offset counts in full.
    shifted = poses_at(square + np.array([0.3, -0.4, 0.0]))
    np.testing.assert_allclose(ate_metric(shifted, gt, align="none")["rmse"], 0.5, rtol=1e-12)
    assert ate_metric(shifted, gt, align="se3")["rmse"] < 1e-12


def test_ate_ignores_nan_frames_and_accepts_a_straight_path() -> None:
    rng = np.random.default_rng(1)
    gt = trajectory(rng)
    noise = rng.normal(size=(12, 3)) * 0.05
    est = Sim3(2.0, np.eye(3), [1.0, 2, 3]).transform_w2c(gt)
    est[:, :3, 3] += noise  # perturbs the centres by an unknown but fixed amount
    full = ate_metric(est, gt)
    est_nan, gt_nan = est.copy(), gt.copy()
    est_nan[3] = np.nan
    gt_nan[7, 0, 0] = np.nan
    keep = np.ones(12, bool)
    keep[[3, 7]] = False
    r = ate_metric(est_nan, gt_nan)
    assert r["n"] == 10
    np.testing.assert_allclose(r["rmse"], ate_metric(est[keep], gt[keep])["rmse"], rtol=1e-12)
    assert r["rmse"] != full["rmse"]
    # Forward-only motion: collinear centres still have a well-defined error (here exactly 0).
    line = np.outer(np.arange(6.0), [1.0, 0.5, 0.0])
    gt_line = poses_at(line)
    assert ate_metric(Sim3(0.3, np.eye(3), [5.0, 0, 0]).transform_w2c(gt_line), gt_line)["rmse"] < 1e-12


def test_ate_rejects_too_few_frames() -> None:
    gt = trajectory(np.random.default_rng(2), n=5)
    est = gt.copy()
    est[:3] = np.nan
    with pytest.raises(ValueError, match="at least 3"):
        ate_metric(est, gt)
    with pytest.raises(ValueError, match="align"):
        ate_metric(gt, gt, align="sim2")  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------------ depth


def test_depth_errors_for_a_known_scale_error() -> None:
    rng = np.random.default_rng(3)
    gt = rng.uniform(0.5, 20.0, size=(2, 16, 24))
    r = depth_errors(1.1 * gt, gt)
    np.testing.assert_allclose(r["absrel"], 0.1, rtol=1e-12)
    assert r["delta1"] == 1.0
    np.testing.assert_allclose(r["rmse"], 0.1 * np.sqrt(np.mean(gt**2)), rtol=1e-12)
    assert r["n"] == gt.size
    assert depth_errors(1.3 * gt, gt)["delta1"] == 0.0
    assert depth_errors(gt / 1.3, gt)["delta1"] == 0.0


def test_depth_errors_ignore_invalid_pixels_and_respect_the_mask() -> None:
    gt = np.array([[1.0, 2.0, 0.0, np.nan], [4.0, np.inf, 5.0, 2.0]])
    pred = np.array([[1.5, 2.0, 3.0, 1.0], [np.nan, 1.0, -5.0, 2.0]])
    r = depth_errors(pred, gt)
    # Valid: (0,0) 1.5 vs 1, (0,1) 2 vs 2, (1,2) -5 vs 5, (1,3) 2 vs 2.
    assert r["n"] == 4
    np.testing.assert_allclose(r["absrel"], (0.5 + 0 + 2.0 + 0) / 4, rtol=1e-12)
    assert r["delta1"] == 0.5  # 1.5/1 fails, a negative prediction fails
    np.testing.assert_allclose(r["rmse"], np.sqrt((0.25 + 100.0) / 4), rtol=1e-12)
    mask = np.array([[False, True, True, True], [True, True, False, True]])
    m = depth_errors(pred, gt, mask)
    assert m["n"] == 2 and m["absrel"] == 0.0 and m["delta1"] == 1.0
    empty = depth_errors(pred, gt, np.zeros_like(mask))
    assert empty["n"] == 0 and np.isnan(empty["absrel"])


# ---------------------------------------------------------------------------------------------- normals


@SLOW
@given(seeds, st.floats(0.0, 179.0))
def test_normal_errors_for_a_known_rotation(seed: int, angle_deg: float) -> None:
    rng = np.random.default_rng(seed)
    gt = rng.normal(size=(8, 10, 3))
    gt /= np.linalg.norm(gt, axis=-1, keepdims=True)
    # Rotate each normal by angle_deg about an axis perpendicular to it (Rodrigues with axis ⟂ n).
    perp = np.cross(gt, rng.normal(size=3))
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    a = np.radians(angle_deg)
    pred = np.cos(a) * gt + np.sin(a) * np.cross(perp, gt)
    r = normal_errors(2.5 * pred, gt)  # length does not matter
    np.testing.assert_allclose(r["mean_deg"], angle_deg, atol=1e-9)
    np.testing.assert_allclose(r["median_deg"], angle_deg, atol=1e-9)
    if abs(angle_deg - 11.25) > 1e-6:  # exactly at the threshold rounding decides
        assert r["pct_11_25"] == (100.0 if angle_deg < 11.25 else 0.0)
    assert r["n"] == 80


def test_normal_errors_ignore_zero_and_nan_normals() -> None:
    gt = np.array([[0.0, 0, 1], [0.0, 0, 1], [0.0, 0, 1], [0.0, 0, 0], [1.0, 0, 0]])
    pred = np.array([[0.0, 0, 1], [0.0, 1, 1], [np.nan, 0, 1], [0.0, 0, 1], [0.0, 0, 0]])
    r = normal_errors(pred, gt)
    assert r["n"] == 2  # only the first two rows are usable: 0° and 45°
    np.testing.assert_allclose([r["mean_deg"], r["median_deg"], r["pct_11_25"]], [22.5, 22.5, 50.0], atol=1e-12)
    r = normal_errors(pred, gt, mask=np.array([False, True, True, True, True]))
    np.testing.assert_allclose(r["mean_deg"], 45.0, atol=1e-12)
    # float16 storage: a tiny but nonzero angle is measured, not rounded to 0 by arccos.
    tiny = normal_errors(np.array([[0.0, 1e-7, 1.0]]), np.array([[0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(tiny["mean_deg"], np.degrees(1e-7), rtol=1e-6)


# ------------------------------------------------------------------------------------------ PSNR, SSIM


def test_psnr_known_values() -> None:
    ref = np.random.default_rng(4).uniform(0.2, 0.8, size=(12, 14, 3))
    assert psnr(ref, ref) == float("inf")
    np.testing.assert_allclose(psnr(ref + 0.1, ref), 20.0, rtol=1e-12)  # MSE 0.01
    np.testing.assert_allclose(psnr(ref + 10.0, ref, max_val=255.0), 20 * np.log10(25.5), rtol=1e-12)


def ssim_reference(x: np.ndarray, y: np.ndarray, L: float = 1.0) -> float:
    """Wang et al. (2004) with scipy's Gaussian filter (σ 1.5, radius 5 = 11 taps), cropped to 'valid'."""
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    vals = []
    for ch in range(x.shape[2]):
        a, b = x[..., ch], y[..., ch]

        def f(z: np.ndarray) -> np.ndarray:
            return ndimage.gaussian_filter(z, sigma=1.5, truncate=5.0 / 1.5, mode="constant")[5:-5, 5:-5]

        ma, mb = f(a), f(b)
        va, vb, cov = f(a * a) - ma**2, f(b * b) - mb**2, f(a * b) - ma * mb
        vals.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


@SLOW
@given(seeds, st.floats(0.0, 0.5))
def test_ssim_matches_an_independent_implementation(seed: int, noise: float) -> None:
    rng = np.random.default_rng(seed)
    ref = ndimage.gaussian_filter(rng.uniform(0, 1, size=(24, 31, 3)), sigma=(2, 2, 0))
    img = np.clip(ref + noise * rng.normal(size=ref.shape), 0.0, 1.0)
    s = ssim(img, ref)
    np.testing.assert_allclose(s, ssim_reference(img, ref), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(s, ssim(ref, img), rtol=1e-12)  # symmetric
    assert s <= 1.0 + 1e-12


def test_ssim_known_cases() -> None:
    rng = np.random.default_rng(5)
    ref = rng.uniform(0, 1, size=(20, 20, 3))
    np.testing.assert_allclose(ssim(ref, ref), 1.0, rtol=1e-12)
    # Constant images a and b: no structure, only luminance: (2ab + C1) / (a² + b² + C1).
    a, b, c1 = 0.3, 0.5, 0.01**2
    got = ssim(np.full((16, 16, 3), a), np.full((16, 16, 3), b))
    np.testing.assert_allclose(got, (2 * a * b + c1) / (a * a + b * b + c1), rtol=1e-12)
    # Inverting the contrast of a zero-mean-ish pattern makes the structure term negative.
    assert ssim(1.0 - ref, ref) < 0.0
    with pytest.raises(ValueError, match="at least 11"):
        ssim(np.zeros((10, 30, 3)), np.zeros((10, 30, 3)))
