"""Per-image scale/shift alignment of a monocular depth prior to reference depths (sparse SfM points).

Solves a*prior + b ~= target in the prior's own space (camera z for "depth", 1/z for "inverse_depth"),
robustly, and returns the aligned prior as camera-space depth. Degenerate inputs never raise and never
produce NaN: they return ok=False, a reason in words, and a sane depth map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wonderverse.priors.base import DepthKind
from wonderverse.priors.params import AlignMethod, AlignParams

# Relative spread below which the prior counts as constant (float64 fits; float16 priors quantise at ~1e-3).
_CONST_REL_STD = 1e-9


@dataclass
class AlignResult:
    """scale, shift: the fitted a, b of a*prior + b in `space`. aligned_depth: (H,W) float32 camera z,
    finite and > 0 everywhere, clamped to [min_ref/clamp_ratio, max_ref*clamp_ratio]. n_used: reference
    points the final fit used. residual: median |aligned - z_ref| / z_ref over those points (0 for a
    perfect fit; NaN-free, inf only if no point was usable). ok: False when a fallback was taken, and
    `reason` says why ("" when ok). n_clamped: pixels the depth clamp or the positivity guard touched.
    """

    scale: float
    shift: float
    aligned_depth: np.ndarray
    n_used: int
    residual: float
    ok: bool
    reason: str
    space: DepthKind
    n_clamped: int = 0


def reference_samples(reference: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, cols, z) of the usable reference depths for an image of `shape` (H,W).

    reference: a dense (H,W) depth map with NaN / inf / <= 0 where unknown, or (N,3) samples (u, v, z) in
    pixel coordinates with pixel centres at +0.5 (pixel (row, col) covers u in [col, col+1)); samples that
    fall outside the image or have no positive finite z are dropped.
    """
    ref = np.asarray(reference)
    h, w = shape
    if ref.shape == (h, w):
        z = ref.astype(np.float64)
        ok = np.isfinite(z) & (z > 0)
        rows, cols = np.nonzero(ok)
        return rows, cols, z[rows, cols]
    if ref.ndim == 2 and ref.shape[1] == 3:
        uvz = ref.astype(np.float64)
        with np.errstate(invalid="ignore"):
            cols = np.floor(uvz[:, 0])
            rows = np.floor(uvz[:, 1])
            z = uvz[:, 2]
            ok = (
                np.isfinite(cols) & np.isfinite(rows) & np.isfinite(z) & (z > 0)
                & (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
            )  # fmt: skip
        return rows[ok].astype(np.int64), cols[ok].astype(np.int64), z[ok]
    raise ValueError(f"reference must be a ({h},{w}) depth map or (N,3) (u,v,z) samples, got {ref.shape}")


def _lstsq(p: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    """Closed-form least squares of a*p + b = t, centred for conditioning (float64)."""
    pm, tm = p.mean(), t.mean()
    dp = p - pm
    var = float(np.dot(dp, dp))
    if var <= 0:
        return float("nan"), float("nan")
    a = float(np.dot(dp, t - tm) / var)
    return a, float(tm - a * pm)


def _trimmed(p: np.ndarray, t: np.ndarray, prm: AlignParams) -> tuple[float, float, np.ndarray]:
    """Trimmed LS: refit on the (1 - trim_fraction) share of points with the smallest residuals."""
    keep = np.arange(p.size)
    n_keep = max(2, int(np.ceil((1.0 - prm.trim_fraction) * p.size)))
    a, b = _lstsq(p, t)
    for _ in range(prm.max_iters):
        if not np.isfinite(a):
            break
        r = np.abs(a * p + b - t)
        new_keep = np.sort(np.argpartition(r, n_keep - 1)[:n_keep]) if n_keep < p.size else keep
        a, b = _lstsq(p[new_keep], t[new_keep])
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return a, b, keep


def _ransac(p: np.ndarray, t: np.ndarray, prm: AlignParams) -> tuple[float, float, np.ndarray]:
    """RANSAC over point pairs (positive scales only), scored on a subsample, refit on all inliers."""
    rng = np.random.default_rng(prm.seed)
    n = p.size
    score_idx = rng.choice(n, prm.ransac_max_score_points, replace=False) if n > prm.ransac_max_score_points else None
    ps, ts = (p, t) if score_idx is None else (p[score_idx], t[score_idx])
    i = rng.integers(0, n, prm.ransac_iters)
    j = rng.integers(0, n, prm.ransac_iters)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (t[i] - t[j]) / (p[i] - p[j])
        b = t[i] - a * p[i]
    good = np.isfinite(a) & np.isfinite(b) & (a > 0)
    if not good.any():
        return float("nan"), float("nan"), np.zeros(0, dtype=np.int64)
    a, b = a[good], b[good]
    thresh = prm.ransac_rel_thresh * np.abs(ts)
    counts = np.zeros(a.size, dtype=np.int64)
    for k in range(0, a.size, 64):  # chunks keep memory at 64 x n_score
        res = np.abs(a[k : k + 64, None] * ps[None] + b[k : k + 64, None] - ts[None])
        counts[k : k + 64] = (res <= thresh[None]).sum(axis=1)
    best = int(np.argmax(counts))
    a_best, b_best = float(a[best]), float(b[best])
    thresh_all = prm.ransac_rel_thresh * np.abs(t)
    inl = np.nonzero(np.abs(a_best * p + b_best - t) <= thresh_all)[0]
    for _ in range(2):  # refit on inliers, then re-select them once with the better model
        if inl.size < 2:
            break
        a_fit, b_fit = _lstsq(p[inl], t[inl])
        if not (np.isfinite(a_fit) and a_fit > 0):
            break
        a_best, b_best = a_fit, b_fit
        inl = np.nonzero(np.abs(a_best * p + b_best - t) <= thresh_all)[0]
    return a_best, b_best, inl


def _to_depth(
    prior: np.ndarray, a: float, b: float, space: DepthKind, z_lo: float, z_hi: float
) -> tuple[np.ndarray, int]:
    """a*prior + b in `space` as camera z, clamped to [z_lo, z_hi]; (depth float32, pixels clamped)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        v = a * prior.astype(np.float64) + b
        # Non-positive inverse depth is "beyond infinity" (typically sky): far clamp. A non-positive
        # depth cannot be seen at all: nearest plausible value.
        z = np.where(v > 0, 1.0 / v, np.inf) if space == "inverse_depth" else np.where(v > 0, v, z_lo)
        z = np.where(np.isnan(z), z_hi, z)
        n_clamped = int(np.count_nonzero((z < z_lo) | (z > z_hi) | ~(v > 0)))
    return np.clip(z, z_lo, z_hi).astype(np.float32), n_clamped


def align_scale_shift(
    prior: np.ndarray,
    reference: np.ndarray,
    mask: np.ndarray | None = None,
    space: DepthKind = "depth",
    method: AlignMethod | None = None,
    params: AlignParams | None = None,
) -> AlignResult:
    """Fit a*prior + b to the reference depths of one image and return the aligned prior as depth.

    prior: (H,W) prediction, any float dtype, in `space` ("depth": camera z up to scale/shift;
    "inverse_depth": disparity up to scale/shift, fitted against 1/z_ref, then inverted with a guard for
    non-positive values). reference: dense (H,W) depth with NaN where unknown, or (N,3) (u,v,z) samples
    (see reference_samples). mask: (H,W) bool, True where the prior may be used (e.g. not sky).
    method: "lstsq", "trimmed" (drop the worst trim_fraction and refit, up to max_iters) or "ransac";
    None takes params.method. Fallbacks (ok=False): fewer than min_points usable points, a constant prior,
    a non-positive or non-finite scale -> median-ratio scale with zero shift when that is positive and
    finite, else the prior unchanged (a=1, b=0).
    """
    prm = params or AlignParams()
    method = method or prm.method
    if space not in ("depth", "inverse_depth"):
        raise ValueError(f"space must be 'depth' or 'inverse_depth', got {space!r}")
    prior = np.asarray(prior)
    if prior.ndim != 2:
        raise ValueError(f"prior must be (H,W), got {prior.shape}")
    h, w = prior.shape
    rows, cols, z_ref = reference_samples(reference, (h, w))
    p_all = prior.astype(np.float64)
    usable = np.isfinite(p_all[rows, cols])
    if mask is not None:
        if mask.shape != (h, w):
            raise ValueError(f"mask must be ({h},{w}), got {mask.shape}")
        usable &= mask.astype(bool)[rows, cols]
    p = p_all[rows, cols][usable]
    z = z_ref[usable]
    t = 1.0 / z if space == "inverse_depth" else z

    if z.size:
        z_lo, z_hi = float(z.min()) / prm.depth_clamp_ratio, float(z.max()) * prm.depth_clamp_ratio
    elif z_ref.size:
        z_lo, z_hi = float(z_ref.min()) / prm.depth_clamp_ratio, float(z_ref.max()) * prm.depth_clamp_ratio
    else:
        z_lo, z_hi = 1e-6, 1e6  # nothing to go by: only keep the output finite and positive

    reason = ""
    used = np.arange(p.size)
    a = b = float("nan")
    if p.size < prm.min_points:
        reason = f"only {p.size} usable reference points (need {prm.min_points})"
    elif np.std(p) <= _CONST_REL_STD * (abs(float(np.mean(p))) + 1e-300):
        reason = "the prior is constant over the reference points"
    else:
        if method == "lstsq":
            a, b = _lstsq(p, t)
        elif method == "trimmed":
            a, b, used = _trimmed(p, t, prm)
        elif method == "ransac":
            a, b, used = _ransac(p, t, prm)
        else:
            raise ValueError(f"unknown method {method!r}")
        if not (np.isfinite(a) and np.isfinite(b)):
            reason = "the fit is degenerate (no two distinct prior values with a positive slope)"
        elif a <= 0:
            reason = f"negative scale {a:.3g}: the prior is anti-correlated with the reference"

    if reason:
        used = np.arange(p.size)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = float(np.median(t) / np.median(p)) if p.size else float("nan")
        a, b = (ratio, 0.0) if np.isfinite(ratio) and ratio > 0 else (1.0, 0.0)

    depth, n_clamped = _to_depth(prior, a, b, space, z_lo, z_hi)
    if used.size:
        zu = depth[rows[usable][used], cols[usable][used]].astype(np.float64)
        residual = float(np.median(np.abs(zu - z[used]) / z[used]))
    else:
        residual = float("inf")
    return AlignResult(
        scale=float(a),
        shift=float(b),
        aligned_depth=depth,
        n_used=int(used.size),
        residual=residual,
        ok=not reason,
        reason=reason,
        space=space,
        n_clamped=n_clamped,
    )


def project_points(points: np.ndarray, w2c: np.ndarray, K: np.ndarray) -> np.ndarray:
    """World points (N,3) seen by a W2C camera (4,4) with intrinsics K (3,3): (M,3) samples (u, v, z) in
    pixels (centres at +0.5) and camera z, of the M points in front of the camera (z > 1e-6), in order.
    Points outside the image are kept (`reference_samples` drops them)."""
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    front = z > 1e-6
    uv = cam[front, :2] / z[front, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return np.column_stack([uv, z[front]])


@dataclass
class AlignedFrames:
    """depth (T,H,W) float32 camera z: each frame's prior aligned to the SfM points it sees (or the prior
    turned into depth where that failed), +inf where it is sky; scale, shift (T,) the fitted a, b (NaN
    where no fit); ok (T,) bool, the alignment held; reasons: "frame t: why" for each frame that failed."""

    depth: np.ndarray
    scale: np.ndarray
    shift: np.ndarray
    ok: np.ndarray
    reasons: list[str]


def align_frames(
    prior: np.ndarray,
    space: DepthKind,
    w2c: np.ndarray,
    points: np.ndarray,
    K: np.ndarray,
    params: AlignParams,
    sky_beyond_ref: float,
) -> AlignedFrames:
    """Each frame's depth prior (`prior` (T,H,W) in `space`) aligned (`align_scale_shift`) to the world
    `points` (N,3) projected through its W2C pose (`w2c` (T,4,4), NaN where unknown: no reference, the
    fallback) and K (3,3). Sky rule: monocular networks put the sky far away, not at infinity, so aligned
    depth beyond `sky_beyond_ref` times the farthest projected point's depth becomes +inf (frames that see
    no point are left as they are)."""
    n = len(prior)
    depth = np.empty(np.shape(prior)[:3], np.float32)
    scale, shift, ok, reasons = np.full(n, np.nan), np.full(n, np.nan), [], []
    for t in range(n):
        ref = project_points(points, w2c[t], K) if np.isfinite(w2c[t]).all() else np.zeros((0, 3))
        r = align_scale_shift(prior[t], ref, space=space, params=params)
        depth[t], scale[t], shift[t] = r.aligned_depth, r.scale, r.shift
        if len(ref):
            depth[t][depth[t] > sky_beyond_ref * ref[:, 2].max()] = np.inf
        ok.append(r.ok)
        if not r.ok:
            reasons.append(f"frame {t}: {r.reason}")
    return AlignedFrames(depth, scale, shift, np.array(ok, dtype=bool), reasons)
