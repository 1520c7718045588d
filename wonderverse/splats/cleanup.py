"""Gaussians no viewer should get: removed before the splats are exported (`prune_for_export`).

A trained scene holds Gaussians that no training camera constrains: on the preview Christmas scene (21,468
Gaussians), Gaussians out to 500 units where the SfM points end at 150, σ up to 59 units, and faint ones.
They barely show in the training views but ruin a viewer's automatic framing and novel views. A Gaussian is
removed when

- a coordinate is not finite, or
- its opacity is below `min_opacity` (nearly transparent), or
- its width (6 σ along its largest axis, the 3σ ellipsoid's diameter) is over `max_width_extent_frac` of the
  scene extent (absurdly large), or
- its centre is out of every camera's view — behind it, beyond `view_far_extent_frac` × extent, or off the
  image grown by `view_margin_frac` of its size on each side — **and** farther than
  `sfm_distance_extent_frac` × extent from every SfM point (so distant scenery the SfM saw stays).

On that scene the defaults remove 161 transparent, 73 too large and 485 out-of-view Gaussians (3.3 %), and
the training views rendered before and after differ by 42-48 dB PSNR.

Needles are shortened, not removed: a Gaussian whose largest axis is over `max_needle_ratio` times its middle
one (`axis_ratios`; a disc, two long axes and a short one, is no needle) gets its largest axis cut to that many
times the middle one (`shorten_needles`). Seen side-on from a viewpoint no training camera had, a needle is a
streak across the view. Removing needles leaves holes where they carried colour; shortening them keeps their
colour at their centre: on the default preview scene (2026-12-06, 21,084 Gaussians, PSNR of every 4th of its 49
training views against the frames), removing those over 5 cost 0.37 dB beyond the pruning, shortening them
0.05 dB. The default 10 is nearly free (12 Gaussians there, under 0.01 dB); lower limits cost more than they
show (3: 775 Gaussians, 0.24 dB, novel views barely changed). There, the streaks of novel views come from
Gaussians of ratio 2-5 that training views see side-on (their length is supported), which no export-time rule
removes for free: keeping only Gaussians near SfM points or inside the points' box cost 0.2-1.1 dB (distant
terrain the SfM did not triangulate). Figures: `python -m benchmarks.splat_cleanup` (docs/benchmarks.md).

Lengths are shares of the scene extent the caller gives: the outputs step passes `camera.scene_extent` of the
training cameras and their rendered depth, the one extent every output is measured by (paths, the mesh).

Everything is in the world frame: Gaussians in the `GaussianModel.to_numpy()` layout, W2C poses with OpenCV
axes, K in pixels (pixel centres at +0.5), points in world units.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

WIDTH_SIGMAS = 6.0  # a Gaussian's width: the diameter of its 3σ ellipsoid along the largest axis


class ExportPruneParams(BaseModel):
    """What counts as a floater, an absurd Gaussian or a transparent one (lengths relative to the scene extent)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    view_margin_frac: float = Field(
        0.5,
        ge=0,
        description="the image grown by this share of its width (height) on each side still counts as in view",
    )
    view_far_extent_frac: float = Field(
        1.5, gt=0, description="deeper than this many scene extents in front of a camera is out of its view"
    )
    sfm_distance_extent_frac: float = Field(
        0.1, gt=0, description="farther than this share of the extent from every SfM point is far from the points"
    )
    max_width_extent_frac: float = Field(
        1.0, gt=0, description="a Gaussian wider (6 σ, largest axis) than this share of the extent is absurdly large"
    )
    min_opacity: float = Field(1.0 / 255.0, ge=0, lt=1, description="less opaque than this is nearly transparent")
    max_needle_ratio: float = Field(
        10.0,
        gt=1,
        description="a Gaussian whose largest axis is over this many times its middle one (a needle) has it "
        "shortened to that many times (a streak in novel views); 1e9: never",
    )


REASONS = ("non_finite", "transparent", "too_large", "outside_views")


def axis_ratios(log_scales: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(largest / middle, largest / smallest) axis of each Gaussian, from (N,3) log scales. The first is large for
    a needle only; the second for a needle and for a flat disc alike."""
    srt = np.sort(np.asarray(log_scales, np.float64).reshape(-1, 3), axis=1)
    with np.errstate(over="ignore", invalid="ignore"):
        return np.exp(srt[:, 2] - srt[:, 1]), np.exp(srt[:, 2] - srt[:, 0])


def shorten_needles(log_scales: np.ndarray, max_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(log scales with every needle's largest axis cut to `max_ratio` times its middle axis, same dtype; (N,) bool
    of the needles shortened). A needle: largest / middle axis over `max_ratio`; other Gaussians are unchanged."""
    ls = np.asarray(log_scales)
    srt = np.sort(ls.reshape(-1, 3).astype(np.float64), axis=1)
    cap = srt[:, 1] + np.log(max_ratio)
    needle = srt[:, 2] > cap
    out = ls.copy()
    out[needle] = np.minimum(ls[needle], cap[needle, None]).astype(ls.dtype)
    return out, needle


def in_any_view(
    points: np.ndarray,
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    margin_frac: float,
    far: float,
) -> np.ndarray:
    """(N,) bool: the world point is in front of at least one camera (0 < depth <= `far`) and projects into
    its image grown by `margin_frac` of the width (height) on each side. Cameras with a non-finite pose are
    skipped. W2C (M,4,4) OpenCV axes; K (3,3) or (M,3,3) in pixels."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    w2c = np.asarray(w2c, np.float64).reshape(-1, 4, 4)
    Ks = np.broadcast_to(np.asarray(K, np.float64), (len(w2c), 3, 3))
    seen = np.zeros(len(points), bool)
    lo_u, hi_u = -margin_frac * width, (1.0 + margin_frac) * width
    lo_v, hi_v = -margin_frac * height, (1.0 + margin_frac) * height
    for pose, k in zip(w2c, Ks, strict=True):
        if not np.isfinite(pose).all():
            continue
        todo = ~seen
        cam = points[todo] @ pose[:3, :3].T + pose[:3, 3]
        z = cam[:, 2]
        front = (z > 0.0) & (z <= far)
        zs = np.where(front, z, 1.0)
        u = k[0, 0] * cam[:, 0] / zs + k[0, 1] * cam[:, 1] / zs + k[0, 2]
        v = k[1, 1] * cam[:, 1] / zs + k[1, 2]
        seen[np.flatnonzero(todo)[front & (u >= lo_u) & (u <= hi_u) & (v >= lo_v) & (v <= hi_v)]] = True
    return seen


def _bounds(means: np.ndarray) -> dict[str, list[float]] | None:
    finite = means[np.isfinite(means).all(axis=1)]
    if not len(finite):
        return None
    return {"min": finite.min(0).tolist(), "max": finite.max(0).tolist()}


def prune_for_export(
    gaussians: dict[str, np.ndarray],
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    sfm_points: np.ndarray | None,
    extent: float,
    params: ExportPruneParams | None = None,
) -> tuple[dict[str, np.ndarray], dict]:
    """The Gaussians worth exporting, and what was removed.

    `gaussians`: world-frame arrays in the GaussianModel.to_numpy() layout (any other array of one row per
    Gaussian is carried along: its kept rows are returned); `w2c` (M,4,4) the training cameras
    (OpenCV axes; non-finite poses ignored) with intrinsics K (3,3) or (M,3,3) for width×height images;
    `sfm_points` (P,3) world points or None; `extent` the scene's size in world units (`camera.scene_extent`).
    Returns (the kept Gaussians, same arrays and dtypes, in their order, needles shortened; a report dict):
    `before`, `after` (counts), `removed` {non_finite, transparent, too_large, outside_views} (each removed
    Gaussian counted once, under the first reason in that order), `needles_shortened` (count), `extent` (world
    units), `bounds_before` / `bounds_after` ({min, max} of the finite centres, world units; None when empty)
    and `params`.
    """
    params = params or ExportPruneParams()
    means = np.asarray(gaussians["means"], np.float64).reshape(-1, 3)
    n = len(means)
    finite = np.ones(n, bool)
    for a in gaussians.values():
        finite &= np.isfinite(np.asarray(a, np.float64).reshape(n, -1)).all(axis=1) if n else finite
    extent = float(extent) if np.isfinite(extent) and extent > 0 else 1.0
    logit = np.asarray(gaussians["logit_opacities"], np.float64).reshape(n)
    with np.errstate(over="ignore", invalid="ignore"):
        opacity = 1.0 / (1.0 + np.exp(-logit))
        width_world = WIDTH_SIGMAS * np.exp(np.asarray(gaussians["log_scales"], np.float64).reshape(n, 3).max(axis=1))
    transparent = finite & ~(opacity >= params.min_opacity)
    too_large = finite & ~transparent & ~(width_world <= params.max_width_extent_frac * extent)
    rest = finite & ~transparent & ~too_large
    outside = np.zeros(n, bool)
    idx = np.flatnonzero(rest)
    if len(idx):
        seen = in_any_view(
            means[idx], w2c, K, width, height, params.view_margin_frac, params.view_far_extent_frac * extent
        )
        far = np.ones(len(idx), bool)
        pts = None if sfm_points is None else np.asarray(sfm_points, np.float64).reshape(-1, 3)
        pts = None if pts is None else pts[np.isfinite(pts).all(axis=1)]
        if pts is not None and len(pts) and (~seen).any():
            from scipy.spatial import cKDTree

            dist, _ = cKDTree(pts).query(means[idx[~seen]], k=1)
            far[~seen] = dist > params.sfm_distance_extent_frac * extent
        outside[idx[~seen & far]] = True
    keep = finite & ~transparent & ~too_large & ~outside
    kept = {name: np.asarray(a)[keep] for name, a in gaussians.items()}
    kept["log_scales"], needles = shorten_needles(kept["log_scales"], params.max_needle_ratio)
    report = {
        "before": int(n),
        "after": int(keep.sum()),
        "removed": {
            "non_finite": int((~finite).sum()),
            "transparent": int(transparent.sum()),
            "too_large": int(too_large.sum()),
            "outside_views": int(outside.sum()),
        },
        "needles_shortened": int(needles.sum()),
        "extent": extent,
        "bounds_before": _bounds(means),
        "bounds_after": _bounds(means[keep]),
        "params": params.model_dump(),
    }
    return kept, report
