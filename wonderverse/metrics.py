"""Ground-truth metrics: camera trajectory (ATE), depth, normals, image fidelity (PSNR, SSIM), surfaces (Chamfer).

Arrays in, plain Python floats/ints (in dicts) out. Poses are W2C 4x4 float64 (OpenCV camera axes); depth is
camera-space z; normals are 3-vectors in any one frame shared by `pred` and `gt`. The constants below are
part of each metric's standard definition, not tunables.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from wonderverse.camera import Sim3, camera_centers, umeyama

DELTA1_RATIO = 1.25  # δ1: share of pixels with max(pred/gt, gt/pred) below this
NORMAL_GOOD_DEG = 11.25  # share of normals within this angle (the usual "11.25°" column)
NORMAL_MIN_NORM = 1e-6  # shorter normals count as missing (stored as zeros, possibly in float16)
SSIM_WIN = 11  # Gaussian window size (Wang et al. 2004)
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03


def ate(
    est_w2c: np.ndarray, gt_w2c: np.ndarray, align: Literal["sim3", "se3", "none"] = "sim3"
) -> dict[str, float | int]:
    """Absolute trajectory error of camera centres, after aligning the estimate to the ground truth.

    est_w2c, gt_w2c: (N, 4, 4) W2C poses of the same frames. Frames with a non-finite value in either pose
    are ignored. The estimated centres are mapped onto the GT centres by umeyama (with scale for "sim3",
    rigid for "se3", not at all for "none"); a collinear path (pure forward motion) is accepted, as the
    residual is then still well defined.
    Returns {"rmse": RMS centre distance (GT units), "rmse_frac": rmse / length of the GT centre path (over
    consecutive frames with finite GT; NaN if that length is 0), "n": frames used}.
    Raises ValueError for fewer than 3 usable frames, mismatched shapes or an unknown `align`.
    """
    est = np.asarray(est_w2c, dtype=np.float64)
    gt = np.asarray(gt_w2c, dtype=np.float64)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"ate: est and gt must both be (N,4,4), got {est.shape} and {gt.shape}")
    if align not in ("sim3", "se3", "none"):
        raise ValueError(f"ate: align must be 'sim3', 'se3' or 'none', got {align!r}")
    gt_ok = np.all(np.isfinite(gt), axis=(1, 2))
    valid = gt_ok & np.all(np.isfinite(est), axis=(1, 2))
    n = int(valid.sum())
    if n < 3:
        raise ValueError(f"ate: need at least 3 frames with finite est and gt poses, got {n}")
    c_est = camera_centers(est[valid])
    c_gt = camera_centers(gt[valid])
    T = Sim3.identity() if align == "none" else umeyama(c_est, c_gt, with_scale=align == "sim3", allow_degenerate=True)
    rmse = float(np.sqrt(np.mean(np.sum((c_gt - T.apply(c_est)) ** 2, axis=-1))))
    path = float(np.sum(np.linalg.norm(np.diff(camera_centers(gt[gt_ok]), axis=0), axis=-1)))
    return {"rmse": rmse, "rmse_frac": rmse / path if path > 0.0 else float("nan"), "n": n}


def depth_errors(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float | int]:
    """Depth errors over pixels with finite gt > 0, finite pred and (if given) mask true.

    pred, gt, mask: same shape (any, e.g. (H,W) or (T,H,W)), depths in the same units.
    Returns {"absrel": mean |pred - gt| / gt, "delta1": share (0..1) of pixels with pred > 0 and
    max(pred/gt, gt/pred) < 1.25, "rmse": sqrt(mean (pred - gt)²), "n": pixels used}; NaNs when n == 0.
    """
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"depth_errors: pred {pred.shape} and gt {gt.shape} differ in shape")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(gt) & (gt > 0.0) & np.isfinite(pred)
    if mask is not None:
        valid &= np.asarray(mask, dtype=bool)
    p, g = pred[valid], gt[valid]
    n = int(p.size)
    if n == 0:
        return {"absrel": float("nan"), "delta1": float("nan"), "rmse": float("nan"), "n": 0}
    pos = p > 0.0  # a non-positive prediction is never within a ratio of the truth
    ratio = np.maximum(p[pos] / g[pos], g[pos] / p[pos])
    return {
        "absrel": float(np.mean(np.abs(p - g) / g)),
        "delta1": float(np.sum(ratio < DELTA1_RATIO) / n),
        "rmse": float(np.sqrt(np.mean((p - g) ** 2))),
        "n": n,
    }


def normal_errors(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float | int]:
    """Angular error between normal fields (..., 3), ignoring pixels where either normal is zero or NaN.

    Vectors need not be unit length (they are normalised). The angle is atan2(|a×b|, a·b), accurate at 0°.
    Returns {"mean_deg", "median_deg", "pct_11_25": percentage (0..100) of pixels within 11.25°,
    "n": pixels used}; NaNs when n == 0.
    """
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise ValueError(f"normal_errors: pred {pred.shape} and gt {gt.shape} must be equal and (..., 3)")
    npred = np.linalg.norm(pred, axis=-1)
    ngt = np.linalg.norm(gt, axis=-1)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(npred) & np.isfinite(ngt) & (npred > NORMAL_MIN_NORM) & (ngt > NORMAL_MIN_NORM)
    if mask is not None:
        valid &= np.asarray(mask, dtype=bool)
    a = pred[valid] / npred[valid][:, None]
    b = gt[valid] / ngt[valid][:, None]
    n = int(a.shape[0])
    if n == 0:
        return {"mean_deg": float("nan"), "median_deg": float("nan"), "pct_11_25": float("nan"), "n": 0}
    ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))
    return {
        "mean_deg": float(np.mean(ang)),
        "median_deg": float(np.median(ang)),
        "pct_11_25": float(100.0 * np.mean(ang < NORMAL_GOOD_DEG)),
        "n": n,
    }


def psnr(img: np.ndarray, ref: np.ndarray, max_val: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, 10 log10(max_val² / MSE) over all values; inf if identical."""
    img = np.asarray(img, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if img.shape != ref.shape:
        raise ValueError(f"psnr: img {img.shape} and ref {ref.shape} differ in shape")
    mse = float(np.mean((img - ref) ** 2))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(max_val**2 / mse))


def _gaussian_valid(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Separable correlation of (H, W, C) with the 1-D window w along H and W, 'valid' part only."""
    from numpy.lib.stride_tricks import sliding_window_view

    x = sliding_window_view(x, w.size, axis=0) @ w  # (H-k+1, W, C)
    return sliding_window_view(x, w.size, axis=1) @ w  # (H-k+1, W-k+1, C)


def ssim(img: np.ndarray, ref: np.ndarray, max_val: float = 1.0) -> float:
    """Mean structural similarity (Wang et al. 2004) of (H, W, C) or (H, W) images in [0, max_val].

    11x11 Gaussian window (σ = 1.5), C1 = (0.01 L)², C2 = (0.03 L)², L = max_val, population (weighted)
    statistics; the SSIM map is computed where the window fits inside the image ('valid', as in the
    reference MATLAB code), averaged over positions and channels. 1.0 for identical images.
    """
    x = np.asarray(img, dtype=np.float64)
    y = np.asarray(ref, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"ssim: img {x.shape} and ref {y.shape} differ in shape")
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    if x.ndim != 3 or min(x.shape[:2]) < SSIM_WIN:
        raise ValueError(f"ssim: need (H,W) or (H,W,C) images at least {SSIM_WIN} px on a side, got {x.shape}")
    r = np.arange(SSIM_WIN) - (SSIM_WIN - 1) / 2.0
    w = np.exp(-(r**2) / (2.0 * SSIM_SIGMA**2))
    w /= w.sum()
    c1 = (SSIM_K1 * max_val) ** 2
    c2 = (SSIM_K2 * max_val) ** 2
    mx, my = _gaussian_valid(x, w), _gaussian_valid(y, w)
    sxx = _gaussian_valid(x * x, w) - mx * mx
    syy = _gaussian_valid(y * y, w) - my * my
    sxy = _gaussian_valid(x * y, w) - mx * my
    s = ((2.0 * mx * my + c1) * (2.0 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(np.mean(s))


def sample_mesh_points(vertices: np.ndarray, triangles: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """`n` points (n,3) float64 drawn uniformly by area on a triangle mesh (vertices (V,3), triangles (F,3)):
    a triangle with probability proportional to its area, then a uniform point in it (the square-root
    barycentric trick). Degenerate triangles are never drawn; an empty or zero-area mesh gives (0,3)."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0 or n <= 0:
        return np.zeros((0, 3))
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = float(area.sum())
    if not total > 0.0:
        return np.zeros((0, 3))
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(f), size=n, p=area / total)
    r1, r2 = np.sqrt(rng.random(n))[:, None], rng.random(n)[:, None]
    return (1.0 - r1) * a[idx] + r1 * (1.0 - r2) * b[idx] + r1 * r2 * c[idx]


def chamfer_fscore(
    pred_points: np.ndarray, gt_points: np.ndarray, thresholds: tuple[float, ...] | list[float]
) -> dict[str, float | int | list[float]]:
    """Point-set distances between a reconstruction and the ground truth (both (N,3), same units).

    accuracy = mean distance from each predicted point to its nearest GT point; completeness = mean distance
    from each GT point to its nearest prediction; chamfer = (accuracy + completeness) / 2. For each threshold
    t: precision = share of predicted points within t of the GT, recall = share of GT points within t of the
    prediction, fscore = 2 P R / (P + R) (0 when both are 0). Returns {"chamfer", "accuracy", "completeness"
    (floats), "precision", "recall", "fscore" (lists of floats in the order of `thresholds`, shares in 0..1),
    "n_pred", "n_gt"}; distances are NaN and shares 0 when either set is empty.
    """
    from scipy.spatial import cKDTree

    pred = np.asarray(pred_points, dtype=np.float64).reshape(-1, 3)
    gt = np.asarray(gt_points, dtype=np.float64).reshape(-1, 3)
    ts = [float(t) for t in thresholds]
    if len(pred) == 0 or len(gt) == 0:
        nan = float("nan")
        shares = {"precision": [0.0] * len(ts), "recall": [0.0] * len(ts), "fscore": [0.0] * len(ts)}
        return {"chamfer": nan, "accuracy": nan, "completeness": nan, **shares, "n_pred": len(pred), "n_gt": len(gt)}
    d_pred, _ = cKDTree(gt).query(pred, workers=1)
    d_gt, _ = cKDTree(pred).query(gt, workers=1)
    precision = [float(np.mean(d_pred < t)) for t in ts]
    recall = [float(np.mean(d_gt < t)) for t in ts]
    fscore = [2 * p * r / (p + r) if p + r > 0 else 0.0 for p, r in zip(precision, recall, strict=True)]
    acc, comp = float(np.mean(d_pred)), float(np.mean(d_gt))
    return {
        "chamfer": (acc + comp) / 2.0,
        "accuracy": acc,
        "completeness": comp,
        "precision": precision,
        "recall": recall,
        "fscore": fscore,
        "n_pred": len(pred),
        "n_gt": len(gt),
    }
