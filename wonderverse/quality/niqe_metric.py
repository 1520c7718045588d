"""NIQE (Mittal, Soundararajan & Bovik, IEEE SPL 2013): a no-reference image quality score, lower is better.

Follows the reference MATLAB code (`computequality.m`, `computefeature.m`, `estimatemodelparam.m`) and
scikit-video's port: greyscale float64 in [0,255] (MATLAB `rgb2gray` weights, rounded to uint8 as rgb2gray does
for uint8 input), image cropped to whole 96x96 blocks, MSCN coefficients (x - mu) / (sigma + 1) with a 7x7
Gaussian window (sigma 7/6, replicate borders), per block an AGGD fit of the MSCN coefficients (alpha, mean of
the two betas) and of the four pairwise products with circularly shifted neighbours within the block
(alpha, mean, beta_left, beta_right): 18 features; the same on a bicubic half-size image with 48x48 blocks
(the same image regions): 36 features per block. The test image's blocks are fitted by a multivariate
Gaussian (rows with a NaN feature dropped, as MATLAB's nancov does) and the score is
sqrt((mu_p - mu_t)^T ((S_p + S_t) / 2)^+ (mu_p - mu_t)).

The pristine model (mu_p, S_p) is THIS PROJECT's: fitted by `scripts/fit_niqe.py` on 103 real camera images from
the project's real-data folder (`--data`, default `../shared/data`; the MATLAB model, fitted on 125 other
photographs, is not used). Absolute scores therefore differ from MATLAB/pyiqa NIQE values; the ordering
properties (blur and noise raise the score, natural images score lower than noise) hold and are tested.
Differences from MATLAB in the half-size step:
Pillow's antialiased bicubic (a = -0.5, as MATLAB's imresize) on float32 replaces MATLAB's imresize.
"""

from __future__ import annotations

from collections.abc import Iterable
from functools import cache
from importlib import resources

import numpy as np
from scipy.ndimage import correlate1d
from scipy.special import gamma as gamma_fn

BLOCK_PX = 96  # block side at the first scale (MATLAB blocksizerow/blocksizecol)
SHARPNESS_FRACTION = 0.75  # pristine fitting keeps blocks with mean sigma >= this x the image's sharpest block
WINDOW_PX, WINDOW_SIGMA_PX = 7, 7.0 / 6.0
MSCN_C = 1.0  # the stabilising constant of (x - mu) / (sigma + C) on the [0,255] scale
N_FEATURES = 36
PRISTINE_FILE = "niqe_pristine.npz"
# MATLAB rgb2gray weights (the inverse of the NTSC YIQ matrix's first row, as rgb2gray computes them).
RGB2GRAY = np.array([0.298936021293775, 0.587043074451121, 0.114020904255103])
# circshift offsets (rows, cols) of computefeature.m: horizontal, vertical, main and anti diagonal neighbours.
PAIR_SHIFTS = ((0, 1), (1, 0), (1, 1), (-1, 1))
_GAM = np.arange(0.2, 10.0 + 5e-4, 0.001)  # MATLAB: gam = 0.2:0.001:10
_R_GAM = gamma_fn(2.0 / _GAM) ** 2 / (gamma_fn(1.0 / _GAM) * gamma_fn(3.0 / _GAM))


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H,W) float64 greyscale in [0,255] of an (H,W,3) uint8 RGB image (MATLAB rgb2gray, rounded to integers)
    or of an (H,W) image already in [0,255] (returned as float64, not rounded)."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 3:
        if a.dtype != np.uint8:
            raise ValueError(f"an RGB image must be uint8, got {a.dtype}")
        return np.round(a.astype(np.float64) @ RGB2GRAY).clip(0, 255)
    if a.ndim == 2:
        return a.astype(np.float64)
    raise ValueError(f"expected an (H,W,3) uint8 or (H,W) image, got shape {a.shape}")


def _gaussian_window() -> np.ndarray:
    x = np.arange(WINDOW_PX) - (WINDOW_PX - 1) / 2
    w = np.exp(-(x**2) / (2 * WINDOW_SIGMA_PX**2))
    return w / w.sum()  # separable: outer(w, w) is fspecial('gaussian', 7, 7/6) normalised


def mscn(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(MSCN coefficients, local sigma), both (H,W) float64, of a [0,255] greyscale image."""
    w = _gaussian_window()

    def blur(a: np.ndarray) -> np.ndarray:
        return correlate1d(correlate1d(a, w, axis=0, mode="nearest"), w, axis=1, mode="nearest")

    mu = blur(gray)
    sigma = np.sqrt(np.abs(blur(gray * gray) - mu * mu))
    out = (gray - mu) / (sigma + MSCN_C)
    # A flat region gives round-off of ~1e-13 instead of 0; its sign pattern would be fitted as texture.
    out[np.abs(out) < 1e-9] = 0.0
    return out, sigma


def _blocks(a: np.ndarray, side: int) -> np.ndarray:
    """(n, side*side) non-overlapping blocks of a (side*r, side*c) array in row-major block order."""
    r, c = a.shape[0] // side, a.shape[1] // side
    return a[: r * side, : c * side].reshape(r, side, c, side).swapaxes(1, 2).reshape(r * c, side * side)


def aggd_fit(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(alpha, beta_left, beta_right), each (n,), of an asymmetric generalised Gaussian fitted by moment
    matching to each row of x (n, m) as estimateaggdparam.m does (alpha on MATLAB's 0.2:0.001:10 grid).
    NaN where a row has no negative or no positive values (MATLAB gives NaN there too)."""
    neg, pos = x < 0, x > 0
    sq = x * x
    with np.errstate(invalid="ignore", divide="ignore"):
        left = np.sqrt((sq * neg).sum(1) / neg.sum(1))
        right = np.sqrt((sq * pos).sum(1) / pos.sum(1))
        g = left / right
        r_hat = np.abs(x).mean(1) ** 2 / sq.mean(1)
        r_norm = r_hat * (g**3 + 1) * (g + 1) / (g**2 + 1) ** 2
    ok = np.isfinite(r_norm)
    # _R_GAM increases with alpha, so the grid's nearest value is one of the two neighbours of the insertion point.
    i = np.clip(np.searchsorted(_R_GAM, np.where(ok, r_norm, 0.0)), 1, len(_GAM) - 1)
    take_lo = (_R_GAM[i - 1] - r_norm) ** 2 <= (_R_GAM[i] - r_norm) ** 2  # MATLAB min() keeps the first on ties
    alpha = np.where(ok, _GAM[np.where(take_lo, i - 1, i)], np.nan)
    scale = np.sqrt(gamma_fn(1.0 / alpha) / gamma_fn(3.0 / alpha))
    return alpha, left * scale, right * scale


def block_features(coeffs: np.ndarray, side: int) -> np.ndarray:
    """(n_blocks, 18) features of computefeature.m for the side x side blocks of an MSCN map."""
    blocks = _blocks(coeffs, side)
    alpha, bl, br = aggd_fit(blocks)
    feats = [alpha, (bl + br) / 2]
    cube = blocks.reshape(-1, side, side)
    for shift in PAIR_SHIFTS:
        pair = (cube * np.roll(cube, shift, axis=(1, 2))).reshape(len(blocks), -1)
        a, pl, pr = aggd_fit(pair)
        mean = (pr - pl) * gamma_fn(2.0 / a) / gamma_fn(1.0 / a)
        feats += [a, mean, pl, pr]
    return np.stack(feats, axis=1)


def _half_size(gray: np.ndarray) -> np.ndarray:
    from PIL import Image

    h, w = gray.shape
    small = Image.fromarray(gray.astype(np.float32), mode="F").resize((w // 2, h // 2), Image.Resampling.BICUBIC)
    return np.asarray(small, dtype=np.float64)


def image_features(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(features (n_blocks, 36), sharpness (n_blocks,)) of an image: sharpness is each 96x96 block's mean local
    sigma at the first scale (used to pick pristine blocks). Raises ValueError below 2 blocks per side."""
    gray = to_gray(image)
    h, w = gray.shape
    if h < 2 * BLOCK_PX or w < 2 * BLOCK_PX:
        raise ValueError(
            f"NIQE needs at least {2 * BLOCK_PX}x{2 * BLOCK_PX} pixels (2 blocks of {BLOCK_PX} per side, "
            f"{BLOCK_PX // 2}-pixel blocks at half size), got {w}x{h}"
        )
    gray = gray[: h // BLOCK_PX * BLOCK_PX, : w // BLOCK_PX * BLOCK_PX]  # MATLAB crops before filtering
    coeffs, sigma = mscn(gray)
    sharpness = _blocks(sigma, BLOCK_PX).mean(1)
    f1 = block_features(coeffs, BLOCK_PX)
    f2 = block_features(mscn(_half_size(gray))[0], BLOCK_PX // 2)
    return np.concatenate([f1, f2], axis=1), sharpness


def fit_gaussian(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean (36,), covariance (36,36)) of feature rows, dropping rows with any NaN (MATLAB nancov);
    ValueError when fewer than 2 rows are left."""
    rows = features[np.isfinite(features).all(1)]
    if len(rows) < 2:
        raise ValueError(
            f"NIQE: only {len(rows)} of {len(features)} blocks have finite features (flat or one-signed "
            "blocks have none); the image has too little texture to be scored"
        )
    return rows.mean(0), np.cov(rows, rowvar=False)


@cache
def pristine_model() -> tuple[np.ndarray, np.ndarray]:
    """(mean (36,), covariance (36,36)) of the project's pristine model, wonderverse/data/niqe_pristine.npz."""
    with resources.files("wonderverse").joinpath("data", PRISTINE_FILE).open("rb") as f, np.load(f) as z:
        return z["mean"].astype(np.float64), z["cov"].astype(np.float64)


def niqe(image: np.ndarray, model: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """NIQE of one image ((H,W,3) uint8 RGB or (H,W) float in [0,255]) against `model` (mean, cov), by
    default the project's pristine model. Lower is better; 0 only for a feature distribution equal to the
    model's mean. ValueError for images under 192x192 or without enough textured blocks."""
    mu_p, cov_p = pristine_model() if model is None else model
    mu_t, cov_t = fit_gaussian(image_features(image)[0])
    d = mu_p - mu_t
    return float(np.sqrt(max(d @ np.linalg.pinv((cov_p + cov_t) / 2) @ d, 0.0)))


def niqe_many(frames: Iterable[np.ndarray], model: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Mean NIQE over frames (each scored on its own, as the paper's per-view evaluation does)."""
    scores = [niqe(f, model) for f in frames]
    if not scores:
        raise ValueError("niqe_many needs at least one frame")
    return float(np.mean(scores))
