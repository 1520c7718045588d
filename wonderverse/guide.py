"""Guides for scene-guided extensions: what is already known, rendered along a segment's planned path.

Before an extension segment is generated, the parent segment's frames are lifted by their depth to world
points (`lift_frames`) and forward-splatted along the new path (`render_points`) into a `Guide`: known
colours, their camera-space depth, and a mask of the pixels nobody has seen (True = unknown, the video model
must invent them). Once splats are trained, `guide_from_splats` renders those instead. `guide_errors`
measures a guide against the truth (the procedural backend renders it).

Conventions: OpenCV camera axes, W2C poses (4,4) float64, K in pixels with pixel centres at +0.5, depth =
camera z in scene units. Sky (depth +inf) is kept as directions at infinity, which move with the camera's
rotation only; its guide depth is +inf but its mask is False, because the sky is known content too.

Lifting: the last parent frame whole, and from every `frame_stride`-th frame before it only what no later
lifted frame holds (`dedup_lifted`), so each surface comes from the latest frame that saw it and nearby frames
add only what scrolled out of view or was hidden.

Splatting: each lifted pixel is a square footprint the size its source pixel projects to in the target view
(times `footprint_margin`, so neighbouring points overlap and no pinholes open between them), clipped to
`max_footprint_px`. A z-buffer (`np.minimum.at`) keeps the nearest surface per pixel; the points within
`depth_tol_rel` of it are the same surface, and those of the latest source frame among them are blended with
tent weights (a bilinear-like resampling), so farther points never show through. A last pass fills pinholes:
an unknown pixel, or a farther pixel showing through a gap, with nearer known pixels on both sides along a row
or a column within `hole_fill_radius_px`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from wonderverse.errors import WonderError
from wonderverse.video.base import Guide

if TYPE_CHECKING:
    from wonderverse.camera import Sim3
    from wonderverse.splats.renderer import Renderer

# Depth key of sky points in the z-buffer: above any finite depth, so any surface wins over the sky.
_SKY_KEY = np.float32(np.finfo(np.float32).max)
# Tent weight at a footprint's edge: positive, so a point whose footprint only just reaches a pixel counts.
_MIN_TENT_WEIGHT = 1e-3
# The lines (row, column) through a pixel along which the pinhole pass looks for known pixels on both sides;
# not the diagonals, which would fill the background notches of a staircase silhouette.
_AXES = ((0, 1), (1, 0))


class GuideParams(BaseModel):
    """How a guide is rendered from the parent segment's frames (or from the splats)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    frame_stride: int = Field(4, ge=1, description="lift every k-th parent frame, counted back from the last")
    pixel_stride_px: int = Field(1, ge=1, description="lift every k-th pixel of a frame (its footprint grows)")
    footprint_margin: float = Field(
        1.25, ge=1.0, le=4.0, description="footprint = the source pixel's projected size times this"
    )
    max_footprint_px: float = Field(4.0, ge=1.0, le=16.0, description="largest footprint side (close-ups)")
    depth_tol_rel: float = Field(
        0.03, gt=0, lt=1, description="points within this relative depth of a pixel's nearest are one surface"
    )
    dedup_lifted: bool = Field(
        True, description="skip parent pixels that a later lifted frame already shows (same surface)"
    )
    sky_as_directions: bool = Field(True, description="keep sky pixels as directions at infinity (known content)")
    hole_fill_radius_px: int = Field(2, ge=0, le=8, description="pinholes up to 2r-1 px wide are filled; 0 = off")
    see_through_rel: float = Field(
        0.1, gt=0, description="a pixel this much farther than known pixels on both sides shows through a gap"
    )
    splat_min_alpha: float = Field(0.5, gt=0, le=1, description="splat guides: alpha below this is unknown")


@dataclass
class GuidePoints:
    """What was lifted from the parent frames.

    anchor: (3,) float64 world point the points are stored relative to (the last parent camera's centre), so
    that far-off world coordinates keep their precision. offsets: (P,3) float64 world point minus anchor.
    sizes: (P,) float64 world size of each point's source pixel (scene units). directions: (S,3) float64 unit
    world directions of sky pixels; angles: (S,) float64 their source pixel's angular size (radians).
    colors: (P,3) and sky_colors: (S,3) float32 RGB 0..255. ranks: (P,) and sky_ranks: (S,) int32 how many
    lifted frames came after the point's source frame (0 = the last parent frame): where points of one surface
    from several frames meet, the latest frame's win.
    """

    anchor: np.ndarray
    offsets: np.ndarray
    sizes: np.ndarray
    colors: np.ndarray
    directions: np.ndarray
    angles: np.ndarray
    sky_colors: np.ndarray
    ranks: np.ndarray
    sky_ranks: np.ndarray


# ----------------------------------------------------------------------------------------------- validation


def _array(name: str, value: Any, ndim_shape: tuple[int | None, ...], what: str) -> np.ndarray:
    """`value` as an array whose shape matches `ndim_shape` (None = any size), else a WonderError naming it."""
    a = np.asarray(value)
    ok = a.ndim == len(ndim_shape) and all(n is None or n == s for n, s in zip(ndim_shape, a.shape, strict=True))
    if not ok:
        raise WonderError(f"guide: {name} must be {what}, got shape {a.shape}")
    return a


def _finite(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if not np.isfinite(a).all():
        raise WonderError(f"guide: {name} has non-finite values")
    return a


def _intrinsics(name: str, K: Any, n: int) -> np.ndarray:
    """K (3,3) or (n,3,3) as (n,3,3) float64 with positive focal lengths."""
    K = _finite(name, np.asarray(K, np.float64))
    if K.shape == (3, 3):
        K = np.broadcast_to(K, (n, 3, 3))
    if K.shape != (n, 3, 3):
        raise WonderError(f"guide: {name} must be (3,3) or ({n},3,3), got shape {K.shape}")
    if not ((K[:, 0, 0] > 0) & (K[:, 1, 1] > 0)).all():
        raise WonderError(f"guide: {name} must have positive focal lengths")
    return K


def _poses(name: str, w2c: Any, n: int | None = None) -> np.ndarray:
    what = f"({n if n is not None else 'N'},4,4) W2C poses"
    P = _finite(name, _array(name, w2c, (n, 4, 4), what))
    if not len(P):
        raise WonderError(f"guide: {name} has no poses")
    return P


def validate_guide(guide: Guide, n_frames: int, height: int, width: int) -> None:
    """Raise a WonderError naming what is wrong unless `guide` fits a video of n_frames x height x width:
    frames (T,H,W,3) uint8, mask (T,H,W) bool, depth (T,H,W)."""
    want = (n_frames, height, width)
    for name, a, shape in (
        ("frames", guide.frames, (*want, 3)),
        ("mask", guide.mask, want),
        ("depth", guide.depth, want),
    ):
        if np.shape(a) != shape:
            got = np.shape(a)
            size = f"{got[2]}x{got[1]}, {got[0]} frames" if len(got) >= 3 else f"shape {got}"
            raise WonderError(
                f"guide {name} is {size} but the video is {width}x{height}, {n_frames} frames (guide {name} "
                f"shape {got}, expected {shape})"
            )
    if np.asarray(guide.frames).dtype != np.uint8:
        raise WonderError(f"guide frames must be uint8, got {np.asarray(guide.frames).dtype}")
    if np.asarray(guide.mask).dtype != np.bool_:
        raise WonderError(f"guide mask must be bool, got {np.asarray(guide.mask).dtype}")


# ----------------------------------------------------------------------------------------------- lifting


def _rotate(R: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """R @ p for each row of pts (n,3), float64: as three fused multiply-adds per row, many times faster than
    numpy's matmul of an (n,3) by a (3,3) matrix."""
    return np.stack([pts[:, 0] * R[a, 0] + pts[:, 1] * R[a, 1] + pts[:, 2] * R[a, 2] for a in range(3)], axis=1)


def _pixel_rays(K: np.ndarray, width: int, height: int, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row and column indices of the sampled pixels and their camera rays (z = 1), (n,3) float64."""
    rows, cols = np.meshgrid(np.arange(0, height, stride), np.arange(0, width, stride), indexing="ij")
    rows, cols = rows.ravel(), cols.ravel()
    rays = np.stack([(cols + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1], np.ones(len(rows))], axis=-1)
    return rows, cols, rays


def _seen_in(cam: np.ndarray, is_sky: bool, depth: np.ndarray, K: np.ndarray, tol: float) -> np.ndarray:
    """Which camera-space points (n,3) (or sky directions) a lifted frame already holds: one of the 2x2 pixels
    of its kept-points map `depth` (NaN where no point was kept) whose centres surround the point's projection
    has its depth within `tol` (relative), or +inf for sky directions. The 2x2 neighbourhood makes a surface's
    edge points, which land a fraction of a pixel beside the edge, count as held too."""
    h, w = depth.shape
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(cam[:, 0] / z * K[0, 0] + K[0, 2] - 0.5)
        v = np.floor(cam[:, 1] / z * K[1, 1] + K[1, 2] - 0.5)
    out = np.zeros(len(cam), bool)
    for du in (0, 1):
        for dv in (0, 1):
            uu, vv = u + du, v + dv
            idx = np.flatnonzero((z > 0) & (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h) & ~out)
            d = depth[vv[idx].astype(np.intp), uu[idx].astype(np.intp)]
            out[idx] = np.isposinf(d) if is_sky else np.abs(d - z[idx]) <= tol * z[idx]
    return out


def _grid_intrinsics(K: np.ndarray, stride: int) -> np.ndarray:
    """K of the grid of every `stride`-th pixel (pixel (r s, c s) becomes (r, c), centres still at +0.5)."""
    Kg = K.copy()
    Kg[:2, :2] /= stride
    Kg[:2, 2] = (K[:2, 2] - 0.5) / stride + 0.5
    return Kg


def lift_frames(
    frames: np.ndarray, depth: np.ndarray, K: np.ndarray, w2c: np.ndarray, params: GuideParams | None = None
) -> GuidePoints:
    """World points (and sky directions) of the parent frames (T,H,W,3) uint8 with camera-z depth (T,H,W)
    (+inf = sky; NaN or <= 0 = unknown, skipped), intrinsics K (3,3) or (T,3,3), W2C poses (T,4,4).

    Lifts the last frame and every `frame_stride`-th before it; with `dedup_lifted`, a pixel that an already
    lifted (later) frame shows at the same depth is skipped, so each surface comes mostly from the latest
    frame that saw it. Sky pixels become directions when `sky_as_directions`."""
    p = params or GuideParams()
    frames = _array("frames", frames, (None, None, None, 3), "(T,H,W,3) uint8 RGB")
    if frames.dtype != np.uint8:
        raise WonderError(f"guide: frames must be uint8, got {frames.dtype}")
    T, H, W = frames.shape[:3]
    if not (T and H and W):
        raise WonderError(f"guide: frames are empty, shape {frames.shape}")
    depth = _array("depth", depth, (T, H, W), f"(T,H,W) = {(T, H, W)} like the frames")
    Ks = _intrinsics("K", K, T)
    poses = _poses("w2c", w2c, T)
    depth = np.asarray(depth, np.float32)

    order = list(range(T - 1, -1, -p.frame_stride))
    anchor = -poses[-1, :3, :3].T @ poses[-1, :3, 3]
    grid = (len(range(0, H, p.pixel_stride_px)), len(range(0, W, p.pixel_stride_px)))
    # per lifted frame: depth of the points it kept on its pixel grid (NaN elsewhere), the grid's K, its pose;
    # a pixel counts as held only by a point that was kept, so that "held by a later frame" never chains
    done: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    offs, sizes, cols, dirs, angles, sky_cols, ranks, sky_ranks = [], [], [], [], [], [], [], []
    for rank, t in enumerate(order):
        rows, colsx, rays = _pixel_rays(Ks[t], W, H, p.pixel_stride_px)
        z = depth[t, rows, colsx].astype(np.float64)
        rgb = frames[t, rows, colsx].astype(np.float32)
        R, tr = poses[t, :3, :3], poses[t, :3, 3]
        centre = -R.T @ tr
        pix_angle = p.pixel_stride_px / np.sqrt(Ks[t, 0, 0] * Ks[t, 1, 1])  # radians per sampled pixel
        solid = np.isfinite(z) & (z > 0)
        sky = np.isposinf(z) if p.sky_as_directions else np.zeros(len(z), bool)
        cam = rays[solid] * z[solid, None]
        # world offset from the anchor: R^T (cam - t) - anchor = R^T cam + (centre - anchor), exact far away
        off = _rotate(R.T, cam) + (centre - anchor)
        d = rays[sky] / np.linalg.norm(rays[sky], axis=1, keepdims=True)
        dw = _rotate(R.T, d)
        keep, keep_sky = np.ones(len(off), bool), np.ones(len(dw), bool)
        if p.dedup_lifted:
            for dj, Kj, Pj in done:
                cj = -Pj[:3, :3].T @ Pj[:3, 3]
                rest = np.flatnonzero(keep)
                if len(rest):
                    cam_j = _rotate(Pj[:3, :3], off[rest]) + Pj[:3, :3] @ (anchor - cj)
                    keep[rest[_seen_in(cam_j, False, dj, Kj, p.depth_tol_rel)]] = False
                rest = np.flatnonzero(keep_sky)
                if len(rest):
                    keep_sky[rest[_seen_in(_rotate(Pj[:3, :3], dw[rest]), True, dj, Kj, 0.0)]] = False
        held = np.full(grid[0] * grid[1], np.nan, np.float32)
        held[np.flatnonzero(solid)[keep]] = z[solid][keep]
        held[np.flatnonzero(sky)[keep_sky]] = np.inf
        done.append((held.reshape(grid), _grid_intrinsics(Ks[t], p.pixel_stride_px), poses[t]))
        offs.append(off[keep])
        sizes.append(z[solid][keep] * pix_angle)
        cols.append(rgb[solid][keep])
        dirs.append(dw[keep_sky])
        angles.append(np.full(int(keep_sky.sum()), pix_angle))
        sky_cols.append(rgb[sky][keep_sky])
        ranks.append(np.full(int(keep.sum()), rank, np.int32))
        sky_ranks.append(np.full(int(keep_sky.sum()), rank, np.int32))
    return GuidePoints(
        anchor=anchor,
        offsets=np.concatenate(offs),
        sizes=np.concatenate(sizes),
        colors=np.concatenate(cols),
        directions=np.concatenate(dirs),
        angles=np.concatenate(angles),
        sky_colors=np.concatenate(sky_cols),
        ranks=np.concatenate(ranks),
        sky_ranks=np.concatenate(sky_ranks),
    )


# ----------------------------------------------------------------------------------------------- splatting


def _splat_view(
    cam: tuple[np.ndarray, np.ndarray, np.ndarray],
    size: np.ndarray,
    colors: np.ndarray,
    sky: np.ndarray,
    rank: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    p: GuideParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward-splat camera-space points (x, y, z arrays of n) with source sizes (n,) (scene units, or radians
    for sky points, whose camera coordinates are a direction) into one view: (rgb (H,W,3) float32, depth (H,W)
    float32 +inf unknown or sky, known (H,W) bool). Per pixel the nearest surface wins; of its points (within
    `depth_tol_rel`), those of the lowest `rank` are blended with tent weights."""
    npx = width * height
    x, y, z = cam
    front = np.flatnonzero(z > 0)
    z = z[front]
    inv_z = 1.0 / z
    # pixel coordinates and footprints in float32 (a ten-thousandth of a pixel): half the memory traffic
    u = (x[front] * inv_z * K[0, 0] + K[0, 2]).astype(np.float32)
    v = (y[front] * inv_z * K[1, 1] + K[1, 2]).astype(np.float32)
    s = (size[front] * inv_z * p.footprint_margin).astype(np.float32)
    z = z.astype(np.float32)
    wx = np.clip(s * np.float32(K[0, 0]), 1.0, p.max_footprint_px)
    wy = np.clip(s * np.float32(K[1, 1]), 1.0, p.max_footprint_px)
    # pixels whose centres (i + 0.5) lie inside [u - w/2, u + w/2], clipped to the image
    i0 = np.maximum(np.ceil(u - wx / 2 - 0.5), 0)
    i1 = np.minimum(np.floor(u + wx / 2 - 0.5), width - 1)
    j0 = np.maximum(np.ceil(v - wy / 2 - 0.5), 0)
    j1 = np.minimum(np.floor(v + wy / 2 - 0.5), height - 1)
    on = np.flatnonzero((i1 >= i0) & (j1 >= j0))
    pts = front[on]  # index into the caller's arrays
    u, v, z, wx, wy = u[on], v[on], z[on], wx[on], wy[on]
    i0, j0 = i0[on].astype(np.int64), j0[on].astype(np.int64)
    ni, nj = i1[on].astype(np.int64) - i0 + 1, j1[on].astype(np.int64) - j0 + 1
    # one candidate per (point, covered pixel): repeat each point over its ni x nj footprint
    count = ni * nj
    src = np.repeat(np.arange(len(pts)), count)
    k = np.arange(len(src)) - np.repeat(np.cumsum(count) - count, count)
    di, dj = k % ni[src], k // ni[src]
    ii, jj = i0[src] + di, j0[src] + dj
    pix = jj * width + ii
    is_sky = sky[pts]
    key = np.where(is_sky, _SKY_KEY, z).astype(np.float32)[src]
    rgb = np.zeros((npx, 3), np.float32)
    out_depth = np.full(npx, np.inf, np.float32)
    if not len(pix):
        return rgb.reshape(height, width, 3), out_depth.reshape(height, width), np.zeros((height, width), bool)
    zbuf = np.full(npx, np.inf, np.float32)
    np.minimum.at(zbuf, pix, key)
    # one surface: within depth_tol_rel of the nearest (sky keys only match sky, whose key is the maximum)
    with np.errstate(over="ignore"):  # the sky key times (1 + tol) is +inf, still above every sky key
        same = key <= zbuf[pix] * np.float32(1.0 + p.depth_tol_rel)
    r = rank[pts][src]
    best = np.full(npx, np.iinfo(np.int32).max, np.int32)
    np.minimum.at(best, pix[same], r[same])
    keep = np.flatnonzero(same & (r == best[pix]))
    pix, src, ii, jj = pix[keep], src[keep], ii[keep], jj[keep]
    # tent weights, half-width w/2 + 0.5: a bilinear kernel at footprint 1
    tx = np.maximum(1.0 - np.abs(ii + 0.5 - u[src]) / (wx[src] / 2 + 0.5), _MIN_TENT_WEIGHT)
    ty = np.maximum(1.0 - np.abs(jj + 0.5 - v[src]) / (wy[src] / 2 + 0.5), _MIN_TENT_WEIGHT)
    wt = tx * ty
    wsum = np.bincount(pix, weights=wt, minlength=npx)
    known = wsum > 0
    col = colors[pts]
    for c in range(3):
        rgb[:, c] = np.bincount(pix, weights=wt * col[src, c], minlength=npx)
    rgb /= np.maximum(wsum, _MIN_TENT_WEIGHT**2)[:, None].astype(np.float32)
    solid = np.flatnonzero(~is_sky[src])
    zsum = np.bincount(pix[solid], weights=wt[solid] * z[src[solid]], minlength=npx)
    wsolid = np.bincount(pix[solid], weights=wt[solid], minlength=npx)
    has = wsolid > 0
    out_depth[has] = zsum[has] / wsolid[has]
    return rgb.reshape(height, width, 3), out_depth.reshape(height, width), known.reshape(height, width)


def _fill_pinholes(
    rgb: np.ndarray, depth: np.ndarray, known: np.ndarray, p: GuideParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fill unknown pixels, and farther pixels showing through a gap, that have nearer known pixels on both
    sides along a row or a column within `hole_fill_radius_px`: with the mean of the two sides,
    averaged over every such line. Depth edges stay: a background pixel beside a foreground edge has the
    foreground on one side only."""
    r = p.hole_fill_radius_px
    if r == 0:
        return rgb, depth, known
    h, w = depth.shape
    key = np.full((h + 2 * r, w + 2 * r), np.nan, np.float32)  # sky +inf (known, farthest); unknown NaN
    key[r : r + h, r : r + w] = np.where(known, depth, np.nan)
    centre = key[r : r + h, r : r + w]
    acc_n = np.zeros((h, w), np.int32)
    lines: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (filled pixels, side a, side b) flat indices
    for ay, ax in _AXES:
        sides = []
        for sign in (1, -1):
            step = np.zeros((h, w), np.int8)  # distance to the nearest known pixel on this side; 0 = none
            z = np.full((h, w), np.nan, np.float32)
            for k in range(r, 0, -1):  # nearest last, so it wins
                dy, dx = sign * k * ay, sign * k * ax
                kz = key[r + dy : r + dy + h, r + dx : r + dx + w]
                hit = ~np.isnan(kz)
                step[hit], z[hit] = k, kz[hit]
            sides.append((step, z))
        (sa, za), (sb, zb) = sides
        with np.errstate(invalid="ignore"):
            # a hole, or a pixel clearly farther than both sides (a farther surface seen through a gap)
            target = np.isnan(centre) | (centre > np.maximum(za, zb) * (1.0 + p.see_through_rel))
        y, x = np.nonzero(target & (sa > 0) & (sb > 0))
        if len(y):
            ka, kb = sa[y, x].astype(np.int64), sb[y, x].astype(np.int64)
            lines.append((y * w + x, (y + ka * ay) * w + x + ka * ax, (y - kb * ay) * w + x - kb * ax))
            acc_n[y, x] += 1
    if not lines:
        return rgb, depth, known
    flat_rgb, flat_z = rgb.reshape(-1, 3), depth.reshape(-1)
    n = h * w
    acc_rgb = np.zeros((n, 3), np.float64)
    acc_z = np.zeros(n, np.float64)
    acc_solid = np.zeros(n, np.int64)
    for at, ia, ib in lines:
        acc_rgb[at] += (flat_rgb[ia].astype(np.float64) + flat_rgb[ib]) / 2
        za, zb = flat_z[ia], flat_z[ib]
        finite = np.isfinite(za) & np.isfinite(zb)  # a line with sky on a side fills sky
        acc_z[at[finite]] += (za[finite].astype(np.float64) + zb[finite]) / 2
        acc_solid[at[finite]] += 1
    fill = np.flatnonzero(acc_n.reshape(-1) > 0)
    cnt = acc_n.reshape(-1)[fill]
    rgb, depth, known = rgb.copy(), depth.copy(), known.copy()
    rgb.reshape(-1, 3)[fill] = (acc_rgb[fill] / cnt[:, None]).astype(np.float32)
    solid = acc_solid[fill] > 0
    zf = np.full(len(fill), np.inf)
    zf[solid] = acc_z[fill][solid] / acc_solid[fill][solid]
    depth.reshape(-1)[fill] = zf.astype(np.float32)
    known.reshape(-1)[fill] = True
    return rgb, depth, known


def render_points(
    points: GuidePoints, path: np.ndarray, K_out: np.ndarray, width: int, height: int, params: GuideParams | None = None
) -> Guide:
    """Guide (frames (N,H,W,3) uint8, mask True = unknown, depth float32 +inf unknown or sky) of lifted
    `points` seen along `path` (N,4,4 W2C) with intrinsics K_out (3,3) or (N,3,3) at width x height."""
    p = params or GuideParams()
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise WonderError(f"guide: size must be positive whole pixels, got {width}x{height}")
    width, height = int(width), int(height)
    poses = _poses("path", path)
    Ks = _intrinsics("K_out", K_out, len(poses))
    n_solid = len(points.offsets)
    sky = np.concatenate([np.zeros(n_solid, bool), np.ones(len(points.directions), bool)])
    size = np.concatenate([points.sizes, points.angles])
    rank = np.concatenate([points.ranks, points.sky_ranks])
    colors = np.concatenate([points.colors, points.sky_colors]).astype(np.float32)
    frames = np.zeros((len(poses), height, width, 3), np.uint8)
    mask = np.ones((len(poses), height, width), bool)
    depth = np.full((len(poses), height, width), np.inf, np.float32)
    for n, (P, K) in enumerate(zip(poses, Ks, strict=True)):
        R = P[:3, :3]
        t = R @ points.anchor + P[:3, 3]  # camera point = R (anchor + offset) + t, formed once in float64
        o, d = points.offsets, points.directions
        # row by row: (n,3) @ (3,3) matmul is many times slower than three fused multiply-adds
        cam = tuple(
            np.concatenate([o[:, 0] * R[a, 0] + o[:, 1] * R[a, 1] + o[:, 2] * R[a, 2] + t[a], d @ R[a]])
            for a in range(3)
        )
        rgb, z, known = _splat_view(cam, size, colors, sky, rank, K, width, height, p)
        rgb, z, known = _fill_pinholes(rgb, z, known, p)
        frames[n] = np.where(known[..., None], np.clip(np.rint(rgb), 0, 255), 0).astype(np.uint8)
        mask[n], depth[n] = ~known, np.where(known, z, np.inf)
    return Guide(frames=frames, mask=mask, depth=depth, source="parent frames")


def guide_from_frames(
    frames: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    path: np.ndarray,
    K_out: np.ndarray,
    width: int,
    height: int,
    params: GuideParams | None = None,
) -> Guide:
    """The parent segment's frames (T,H,W,3) uint8, lifted by their camera-z depth (T,H,W) (+inf = sky, NaN or
    <= 0 = unknown) with K (3,3) or (T,3,3) and W2C poses w2c (T,4,4), rendered along `path` (N,4,4 W2C) with
    K_out at width x height. Returns a Guide with source "parent frames"; see `lift_frames`, `render_points`."""
    return render_points(lift_frames(frames, depth, K, w2c, params), path, K_out, width, height, params)


def guide_from_splats(
    arrays: dict[str, np.ndarray],
    norm: Sim3,
    path: np.ndarray,
    K_out: np.ndarray,
    width: int,
    height: int,
    params: GuideParams | None = None,
    renderer: Renderer | None = None,
) -> Guide:
    """Trained splats (`GaussianModel.to_numpy` arrays in the training frame, `norm` the world-to-training
    Sim3) rendered along `path` (N,4,4 world W2C) with K_out at width x height by `renderer` (default
    `make_renderer("auto")`). Mask = alpha < `splat_min_alpha` (splats hold no sky, so sky is unknown);
    depth in world units. Returns a Guide with source "splats"."""
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.views import render_views

    p = params or GuideParams()
    poses = _poses("path", path)
    Ks = _intrinsics("K_out", K_out, len(poses))
    views = render_views(
        arrays, norm, poses, Ks, int(width), int(height), renderer or make_renderer("auto"), min_alpha=p.splat_min_alpha
    )
    frames, mask, depth = [], [], []
    for view in views:
        unknown = view.alpha < p.splat_min_alpha
        rgb = np.clip(np.rint(view.rgb * 255.0), 0, 255).astype(np.uint8)
        frames.append(np.where(unknown[..., None], 0, rgb).astype(np.uint8))
        mask.append(unknown)
        depth.append(np.where(unknown, np.inf, view.depth).astype(np.float32))
    return Guide(frames=np.stack(frames), mask=np.stack(mask), depth=np.stack(depth), source="splats")


# ----------------------------------------------------------------------------------------------- errors


def guide_errors(
    guide: Guide, true_frames: np.ndarray, true_depth: np.ndarray, off_rel: float = 0.05
) -> dict[str, float]:
    """How a guide compares with the truth rendered along the same path (true_frames (N,H,W,3) uint8,
    true_depth (N,H,W) camera z, +inf = sky). Returns:
    coverage: share of pixels known;
    psnr_db: colour PSNR (dB, 8-bit peak) over known pixels (inf when identical; NaN when none is known);
    depth_absrel: mean |guide - true| / true over known pixels where both depths are finite (NaN if none);
    depth_off_share: share of known pixels whose depth is off by more than `off_rel` (relative), a known
    pixel that is sky in one and a surface in the other counting as off (NaN when none is known)."""
    N, H, W = np.shape(true_depth) if np.ndim(true_depth) == 3 else (-1, -1, -1)
    if N < 0:
        raise WonderError(f"guide_errors: true_depth must be (N,H,W), got shape {np.shape(true_depth)}")
    validate_guide(guide, N, H, W)
    if np.shape(true_frames) != (N, H, W, 3):
        raise WonderError(f"guide_errors: true_frames shape {np.shape(true_frames)} does not match {(N, H, W, 3)}")
    known = ~guide.mask
    n = int(known.sum())
    out = {"coverage": guide.coverage}
    if n == 0:
        return out | {"psnr_db": float("nan"), "depth_absrel": float("nan"), "depth_off_share": float("nan")}
    diff = guide.frames[known].astype(np.float64) - np.asarray(true_frames)[known].astype(np.float64)
    mse = float(np.mean(diff**2))
    out["psnr_db"] = float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))
    gz = guide.depth[known].astype(np.float64)
    tz = np.asarray(true_depth, np.float64)[known]
    both = np.isfinite(gz) & np.isfinite(tz) & (tz > 0)
    rel = np.abs(gz[both] - tz[both]) / tz[both]
    out["depth_absrel"] = float(rel.mean()) if rel.size else float("nan")
    sky_mismatch = np.isfinite(gz) != np.isfinite(tz)
    out["depth_off_share"] = float(((rel > off_rel).sum() + sky_mismatch.sum()) / n)
    return out
