"""ORACLE priors: degraded ground truth from the procedural world. For benchmarks only.

They read the renderer's exact depth and normals and damage them the way a monocular network's output is
damaged (unknown per-frame scale and shift, smooth warps, noise, blur at edges), seeded and per frame, so
the rest of the pipeline can be measured against a known answer. They are never the default, and they
cannot run on user videos: without ground truth there is nothing to degrade.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from wonderverse.camera import pixels_to_world
from wonderverse.priors.base import DepthKind, DepthPrediction, NormalPrediction, check_frames
from wonderverse.priors.params import ORACLE_LEVELS, OracleDegradation, OracleLevel

_STREAM_DEPTH = 0
_STREAM_NORMALS = 1
_STREAM_WORLD = 2
_WORLD_WAVES = 6


def _frame_rng(seed: int, index: int, stream: int) -> np.random.Generator:
    """One generator per (seed, frame, stream): a frame's degradation does not depend on the batching."""
    return np.random.default_rng([seed, index, stream])


def _smooth_field(rng: np.random.Generator, shape: tuple[int, int], cells: int) -> np.ndarray:
    """Zero-mean, unit-std, low-frequency random field of `shape`: `cells` control points on the short side."""
    h, w = shape
    short = min(h, w)
    ch = max(2, round(cells * h / short))
    cw = max(2, round(cells * w / short))
    coarse = rng.standard_normal((ch, cw))
    rows = np.linspace(0, ch - 1, h)
    cols = np.linspace(0, cw - 1, w)
    grid = np.meshgrid(rows, cols, indexing="ij")
    field = ndimage.map_coordinates(coarse, grid, order=3, mode="nearest")
    std = field.std()
    return (field - field.mean()) / std if std > 0 else field * 0.0


def _edge_band(values: np.ndarray, valid: np.ndarray, rel_step: float, width_px: float) -> np.ndarray:
    """Pixels within `width_px` of a depth edge (neighbour |dz|/z > rel_step) or of a valid/sky boundary."""
    edges = np.zeros(values.shape, dtype=bool)
    for axis in (0, 1):
        a = np.swapaxes(values, 0, axis)
        va = np.swapaxes(valid, 0, axis)
        with np.errstate(divide="ignore", invalid="ignore"):
            jump = np.abs(a[1:] - a[:-1]) / np.minimum(a[1:], a[:-1]) > rel_step
        jump |= va[1:] != va[:-1]
        e = np.swapaxes(edges, 0, axis)
        e[1:] |= jump
        e[:-1] |= jump
    iters = max(1, round(width_px))
    return ndimage.binary_dilation(edges, iterations=iters)


def world_warp(depth: np.ndarray, K: np.ndarray, w2c: np.ndarray, deg: OracleDegradation, seed: int) -> np.ndarray:
    """A zero-mean, unit-std (H,W) field fixed to the world: six sinusoids over the world point each pixel of
    camera z `depth` sees (K (3,3) at the depth's size, W2C (4,4)), with directions, wavelengths and phases drawn
    once per `seed`, so the same surface gets the same value in every frame. 0 where there is no surface (sky)."""
    rng = np.random.default_rng([seed, _STREAM_WORLD])
    dirs = rng.standard_normal((_WORLD_WAVES, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    lo, hi = deg.world_warp_wavelength_m
    waves = 2.0 * np.pi / np.exp(rng.uniform(np.log(lo), np.log(hi), _WORLD_WAVES))
    phases = rng.uniform(0.0, 2.0 * np.pi, _WORLD_WAVES)
    h, w = depth.shape
    valid = np.isfinite(depth) & (depth > 0)
    v, u = np.mgrid[0:h, 0:w] + 0.5
    world = pixels_to_world(u, v, np.where(valid, depth, 0.0), K, w2c)
    field = sum(np.sin(world @ dirs[i] * waves[i] + phases[i]) for i in range(_WORLD_WAVES))
    return np.where(valid, field / np.sqrt(_WORLD_WAVES / 2.0), 0.0)


def degrade_depth(
    depth: np.ndarray,
    deg: OracleDegradation,
    space: DepthKind,
    rng: np.random.Generator,
    world: np.ndarray | None = None,
) -> np.ndarray:
    """One degraded (H,W) float32 map in `space` from camera z with +inf (or NaN / <= 0) for sky.

    Sky becomes a far constant (sky_far_ratio times the farthest surface) before anything else, so the
    output is finite everywhere; then edge blur, a smooth multiplicative warp, the world-fixed error `world`
    (`world_warp`'s field, scaled by world_warp_log_amp; None: none), multiplicative noise and an affine map
    with an unknown scale and shift, all in `space` (the inverse-depth one mimics DA-V2).
    """
    z = depth.astype(np.float64)
    valid = np.isfinite(z) & (z > 0)
    far = deg.sky_far_ratio * (float(z[valid].max()) if valid.any() else 1.0)
    z = np.where(valid, z, far)
    x = 1.0 / z if space == "inverse_depth" else z

    if deg.edge_blur_px > 0:
        band = _edge_band(z, valid, deg.edge_rel_step, 2.0 * deg.edge_blur_px)
        x = np.where(band, ndimage.gaussian_filter(x, deg.edge_blur_px, mode="nearest"), x)
    if deg.warp_log_amp > 0:
        x = x * np.exp(deg.warp_log_amp * _smooth_field(rng, x.shape, deg.warp_cells))
    if world is not None and deg.world_warp_log_amp > 0:
        x = x * np.exp(deg.world_warp_log_amp * world)
    if deg.noise_rel > 0:
        x = x * np.clip(1.0 + deg.noise_rel * rng.standard_normal(x.shape), 0.5, 1.5)
    lo, hi = deg.scale_range
    scale = float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) if hi > lo else lo
    f_lo, f_hi = deg.shift_frac_range
    shift = float(rng.uniform(f_lo, f_hi)) * float(np.median(x)) if f_hi > f_lo else f_lo * float(np.median(x))
    return (scale * x + shift).astype(np.float32)


def degrade_normals(normals: np.ndarray, deg: OracleDegradation, rng: np.random.Generator) -> np.ndarray:
    """One degraded (H,W,3) float32 normal map: crease blur, smooth error field, noise, smoothing, unit length.

    Input: unit camera-space normals, zero for sky. Sky stays zero; smoothing is normalised over the
    non-sky pixels so sky does not bleed in.
    """
    n = normals.astype(np.float64)
    valid = np.linalg.norm(n, axis=-1) > 0.5
    w = valid.astype(np.float64)

    def blur(v: np.ndarray, sigma: float) -> np.ndarray:
        if sigma <= 0:
            return v
        num = np.stack([ndimage.gaussian_filter(v[..., c] * w, sigma, mode="nearest") for c in range(3)], -1)
        den = ndimage.gaussian_filter(w, sigma, mode="nearest")[..., None]
        return np.where(den > 1e-6, num / np.maximum(den, 1e-6), v)

    if deg.normal_edge_blur_px > 0:
        cos_min = np.cos(np.radians(deg.normal_crease_deg))
        crease = np.zeros(valid.shape, dtype=bool)
        dot_x = (n[:, 1:] * n[:, :-1]).sum(-1) < cos_min
        dot_y = (n[1:] * n[:-1]).sum(-1) < cos_min
        crease[:, 1:] |= dot_x
        crease[:, :-1] |= dot_x
        crease[1:] |= dot_y
        crease[:-1] |= dot_y
        band = ndimage.binary_dilation(crease & valid, iterations=max(1, round(deg.normal_edge_blur_px)))
        n = np.where(band[..., None], blur(n, deg.normal_edge_blur_px), n)
    if deg.normal_warp_amp > 0:
        field = np.stack([_smooth_field(rng, valid.shape, deg.warp_cells) for _ in range(3)], axis=-1)
        n = n + deg.normal_warp_amp * field
    if deg.normal_noise_std > 0:
        n = n + deg.normal_noise_std * rng.standard_normal(n.shape)
    n = blur(n, deg.normal_smooth_px)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = valid & (norm[..., 0] > 1e-6)
    out = np.where(ok[..., None], n / np.maximum(norm, 1e-12), 0.0)
    return out.astype(np.float32)


def _indices(b: int, t: int, indices: np.ndarray | None) -> np.ndarray:
    if indices is None:
        if b != t:
            raise ValueError(f"a batch of {b} frames from a {t}-frame oracle needs `indices`")
        return np.arange(t)
    idx = np.asarray(indices, dtype=np.int64)
    if idx.shape != (b,) or (idx < 0).any() or (idx >= t).any():
        raise ValueError(f"indices must be {b} frame numbers in [0, {t})")
    return idx


class OracleDepth:
    """ORACLE depth prior — for benchmarks only, never the default for user videos.

    gt_depth: (T,H,W) camera z with +inf for sky (the procedural world's GroundTruth.depth). predict()
    returns a degraded copy at `level` (a named level, "none": exact, sky at a far constant, or an
    OracleDegradation), in `space` ("inverse_depth" mimics Depth Anything V2 and is the default), seeded per
    (seed, frame index). A level with `world_warp_log_amp` > 0 needs the cameras: K (3,3) and W2C (T,4,4).
    """

    def __init__(
        self,
        gt_depth: np.ndarray,
        level: OracleLevel | OracleDegradation = "realistic",
        space: DepthKind = "inverse_depth",
        seed: int = 0,
        K: np.ndarray | None = None,
        w2c: np.ndarray | None = None,
    ) -> None:
        if gt_depth.ndim != 3:
            raise ValueError(f"gt_depth must be (T,H,W), got {gt_depth.shape}")
        self.gt_depth = gt_depth
        self.degradation = level if isinstance(level, OracleDegradation) else ORACLE_LEVELS[level]
        self.space: DepthKind = space
        self.seed = seed
        self.K, self.w2c = K, w2c
        if self.degradation.world_warp_log_amp > 0 and (
            K is None or w2c is None or np.shape(w2c) != (gt_depth.shape[0], 4, 4)
        ):
            raise ValueError(f"a world-fixed error needs K and one W2C per frame ({gt_depth.shape[0]}, 4, 4)")

    def _world(self, i: int) -> np.ndarray | None:
        if self.degradation.world_warp_log_amp == 0 or self.K is None or self.w2c is None:
            return None
        return world_warp(self.gt_depth[i], self.K, self.w2c[i], self.degradation, self.seed)

    def predict(self, frames: np.ndarray, indices: np.ndarray | None = None) -> DepthPrediction:
        """Degraded depth for frames[i] = video frame indices[i] (all T frames in order when None)."""
        b, h, w = check_frames(frames)
        if (h, w) != self.gt_depth.shape[1:]:
            raise ValueError(f"frames are {h}x{w}, ground truth is {self.gt_depth.shape[1:]}")
        idx = _indices(b, self.gt_depth.shape[0], indices)
        out = np.stack(
            [
                degrade_depth(
                    self.gt_depth[i],
                    self.degradation,
                    self.space,
                    _frame_rng(self.seed, int(i), _STREAM_DEPTH),
                    self._world(int(i)),
                )
                for i in idx
            ]
        )
        return DepthPrediction(depth=out, kind=self.space)


class OracleNormals:
    """ORACLE normal prior — for benchmarks only, never the default for user videos.

    gt_normals: (T,H,W,3) unit camera-space normals (OpenCV axes, facing the camera, 0 for sky).
    predict() returns a noisy, smoothed, edge-blurred copy at `level`, seeded per (seed, frame index).
    """

    def __init__(self, gt_normals: np.ndarray, level: OracleLevel = "realistic", seed: int = 0) -> None:
        if gt_normals.ndim != 4 or gt_normals.shape[-1] != 3:
            raise ValueError(f"gt_normals must be (T,H,W,3), got {gt_normals.shape}")
        self.gt_normals = gt_normals
        self.degradation = ORACLE_LEVELS[level]
        self.seed = seed

    def predict(
        self,
        frames: np.ndarray,
        K: np.ndarray | None = None,
        depth: np.ndarray | None = None,
        indices: np.ndarray | None = None,
    ) -> NormalPrediction:
        """Degraded normals for frames[i] = video frame indices[i]; K and depth are not needed."""
        b, h, w = check_frames(frames)
        if (h, w) != self.gt_normals.shape[1:3]:
            raise ValueError(f"frames are {h}x{w}, ground truth is {self.gt_normals.shape[1:3]}")
        idx = _indices(b, self.gt_normals.shape[0], indices)
        out = np.stack(
            [
                degrade_normals(self.gt_normals[i], self.degradation, _frame_rng(self.seed, int(i), _STREAM_NORMALS))
                for i in idx
            ]
        )
        return NormalPrediction(normals=out)
