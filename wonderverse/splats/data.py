"""Training data preparation: downscaling posed views and seeding Gaussians from depth."""

from __future__ import annotations

import numpy as np

from wonderverse.camera import fit_intrinsics, pixels_to_world
from wonderverse.splats.trainer import Views


def _resize(stack: np.ndarray, size: tuple[int, int], nearest: bool) -> np.ndarray:
    from PIL import Image

    w, h = size
    out = []
    for a in stack:
        if a.dtype == np.uint8:
            out.append(np.asarray(Image.fromarray(a).resize((w, h), Image.NEAREST if nearest else Image.BILINEAR)))
        else:  # float channels one at a time (PIL's float mode is single-channel)
            chans = a[..., None] if a.ndim == 2 else a
            r = [
                np.asarray(Image.fromarray(np.ascontiguousarray(c, np.float32)).resize((w, h), Image.NEAREST))
                for c in np.moveaxis(chans, -1, 0)
            ]
            out.append(np.stack(r, -1).reshape((h, w, *a.shape[2:])))
    return np.stack(out)


def downscale_views(views: Views, max_side_px: int) -> Views:
    """The same views with the longer image side at most `max_side_px` (intrinsics scaled to match;
    priors resampled nearest so sky/invalid pixels stay exactly invalid)."""
    h, w = views.frames.shape[1:3]
    if max_side_px >= max(h, w):
        return views
    nw, nh, K = fit_intrinsics(w, h, views.K, max_side_px)
    opt = {
        name: None if getattr(views, name) is None else _resize(getattr(views, name), (nw, nh), True)
        for name in ("prior_depth", "prior_normals", "masks", "sky", "superseded")
    }
    return views.replace(frames=_resize(views.frames, (nw, nh), False), K=K, **opt)


def backproject_depth(views: Views, stride_px: int, frame_stride: int) -> tuple[np.ndarray, np.ndarray]:
    """World points (N,3) and colours (N,3) uint8 from the prior depth of every `frame_stride`-th view,
    sampled every `stride_px` pixels; invalid depth (sky, holes) is skipped."""
    pts, cols = [], []
    if views.prior_depth is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    for i in range(0, len(views), frame_stride):
        z = views.prior_depth[i][::stride_px, ::stride_px].astype(np.float64)
        h, w = views.prior_depth.shape[1:]
        v, u = np.mgrid[0:h:stride_px, 0:w:stride_px] + 0.5
        ok = np.isfinite(z) & (z > 0)
        pts.append(pixels_to_world(u[ok], v[ok], z[ok], views.K_of(i), views.w2c[i]))
        frame = views.frames[i]
        c = frame[::stride_px, ::stride_px][ok]
        cols.append(c if c.dtype == np.uint8 else np.clip(c * 255, 0, 255).astype(np.uint8))
    return np.concatenate(pts), np.concatenate(cols)
