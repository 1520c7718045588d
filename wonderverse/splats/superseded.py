"""Where a later segment's frames contradict an earlier one's, the newest frames win.

A scene that grows can change under frames already made: an extension's words put a clock tower where an older
segment, filmed before it existed, shows trees and sky. No static scene agrees with both, and trained on both the
splats blend them: a ghost of the tower over the trees, right for neither view. What the user asked for last is
what the world now is, so the older frames give way where the newer ones contradict them.

The test is free space: a surface a later frame shows (its depth prior, back-projected) that lies in front of what
an earlier frame shows along the same ray (by more than `margin` of that depth, or against its sky) should have been
in that frame. In a static scene with exact depth that never happens; depth priors are not exact, so a pixel is
superseded only where most of the later surfaces landing on it say so, and only in patches of at least
`min_area_frac` of the image (a depth edge's smear gives thin slivers, not patches). A frame's own segment and
earlier ones never supersede it: only the segments made after it can have changed the world under it."""

from __future__ import annotations

import logging
from collections.abc import Collection, Sequence
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from wonderverse.camera import pixels_to_world, world_to_pixels

if TYPE_CHECKING:
    from wonderverse.splats.trainer import Views

log = logging.getLogger(__name__)


def _far_where_invalid(depth: np.ndarray) -> np.ndarray:
    depth = np.asarray(depth, np.float64)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(depth) & (depth > 0), depth, np.inf)


def surface_points(depth: np.ndarray, K: np.ndarray, w2c: np.ndarray, stride_px: int, edge: float = 0.1) -> np.ndarray:
    """World points (N,3) of a camera-z `depth` (H,W) sampled every `stride_px` pixels. Skipped: invalid depth,
    and depth edges (a neighbour `stride_px` away more than `edge` nearer or farther): a prior's depth smears
    across a silhouette, and those points float in the free space between the object and what is behind it."""
    z = _far_where_invalid(depth)
    lo = ndimage.minimum_filter(z, size=2 * stride_px + 1, mode="nearest")
    hi = ndimage.maximum_filter(z, size=2 * stride_px + 1, mode="nearest")
    h, w = z.shape
    v, u = np.mgrid[0:h:stride_px, 0:w:stride_px] + 0.5
    z, lo, hi = (a[::stride_px, ::stride_px] for a in (z, lo, hi))
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(hi) & (lo > (1.0 - edge) * z) & (hi < (1.0 + edge) * z)
    return pixels_to_world(u[ok], v[ok], z[ok], K, w2c)


def superseded_pixels(
    depth: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    later: np.ndarray,
    margin: float = 0.15,
    cell_px: int = 4,
    min_area_frac: float = 0.002,
) -> np.ndarray:
    """(H,W) bool: the pixels of one frame (camera-z `depth` (H,W), its depth prior in the scene's units, NaN, inf
    or <= 0 where it shows sky or nothing; K (3,3); W2C (4,4)) that the world points `later` (N,3: what later frames
    show) contradict. Each `cell_px` cell is superseded when most of the later points landing on it lie nearer than
    (1 - margin) of its own depth there; patches under `min_area_frac` of the image are dropped, the rest grown by a
    cell (their borders are where depth smears)."""
    h, w = depth.shape
    gh, gw = -(-h // cell_px), -(-w // cell_px)
    out = np.zeros((h, w), bool)
    if len(later) == 0:
        return out
    u, v, z, framed = world_to_pixels(later, K, np.asarray(w2c, np.float64), h, w)
    u, v, z = u[framed], v[framed], z[framed]
    # the nearest surface the frame shows around the pixel: near its own silhouettes a later point may land a
    # pixel off, on the sky or the background beside the object it belongs to
    nearest = ndimage.minimum_filter(_far_where_invalid(depth), size=2 * cell_px + 1, mode="nearest")
    own = nearest[v.astype(int), u.astype(int)]
    cell = (v.astype(int) // cell_px) * gw + u.astype(int) // cell_px
    landed = np.bincount(cell, minlength=gh * gw)
    nearer = np.bincount(cell, weights=z < (1.0 - margin) * own, minlength=gh * gw)
    grid = (nearer > 0.5 * landed).reshape(gh, gw)
    labels, n = ndimage.label(grid)
    if n == 0:
        return out
    sizes = np.bincount(labels.ravel(), minlength=n + 1) * cell_px * cell_px
    grid = (sizes >= min_area_frac * h * w)[labels] & (labels > 0)
    grid = ndimage.binary_dilation(grid, iterations=1)
    return np.repeat(np.repeat(grid, cell_px, axis=0), cell_px, axis=1)[:h, :w]


def superseded_masks(
    depth: np.ndarray,
    K: Sequence[np.ndarray],
    w2c: np.ndarray,
    order: Sequence[int],
    targets: Sequence[int],
    sources: Sequence[int],
    stride_px: int = 4,
    margin: float = 0.15,
) -> np.ndarray | None:
    """(T,H,W) bool of views with camera-z depth priors `depth` (T,H,W) in one frame of units, K per view and W2C
    (T,4,4): for each view in `targets`, the pixels the `sources` of a later segment contradict (`order`: each
    view's segment in the order they were made); None when none is. The sources' depth is sampled every
    `stride_px` pixels, and a target's cells are `stride_px` wide."""
    order = np.asarray(order)
    points = {j: surface_points(depth[j], K[j], w2c[j], stride_px) for j in sources}
    out = np.zeros(depth.shape, bool)
    for i in targets:
        later = [points[j] for j in sources if order[j] > order[i]]
        if later:
            out[i] = superseded_pixels(depth[i], K[i], w2c[i], np.concatenate(later), margin, stride_px)
    return out if out.any() else None


def with_superseded(views: Views, names: Sequence[str], held_out: Collection[str], margin: float) -> Views:
    """`views` (named "s003_0008": segment, frame) with `superseded` set: each training view's pixels that a later
    segment's training views contradict (every 4th of each segment's is a witness). Held-out views are neither: they are
    only scored. Views whose depth prior is not in the views' units (`prior_aligned` False) take no part."""
    if views.prior_depth is None:
        return views
    segments = sorted({n.split("_")[0] for n in names})  # segment ids count up as segments are made
    order = [segments.index(n.split("_")[0]) for n in names]
    aligned = np.ones(len(views), bool) if views.prior_aligned is None else np.asarray(views.prior_aligned, bool)
    train = [i for i, n in enumerate(names) if n not in held_out and aligned[i]]
    witnesses = [i for seg in range(len(segments)) for i in [j for j in train if order[j] == seg][::4]]
    K = [views.K_of(i) for i in range(len(views))]
    masks = superseded_masks(views.prior_depth, K, views.w2c, order, train, witnesses, margin=margin)
    if masks is None:
        return views
    older = masks[masks.any(axis=(1, 2))]
    log.info("later segments supersede %.1f %% of the pixels of %d older frames", 100 * older.mean(), len(older))
    return views.replace(superseded=masks)
