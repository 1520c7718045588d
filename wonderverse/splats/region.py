"""The part of a grown scene an extension trains, so that an extension costs the same however large the world.

After `extend`, the splats are continued on the new frames. Training every Gaussian on every frame would make
each extension cost more than the last (every step renders and updates the whole world). Instead the
continuation trains a *region* (`extension_region`):

- the views: the new ones, plus at most `max_old_views` old views that see most of what the new views see (each
  seeing at least `min_overlap` of it), so that old Gaussians the new views move are held to the old views too;
- the Gaussians rendered: the old ones whose centre lies in one of those views (the image grown by `margin_frac`
  on each side, in front of the camera), plus the seeds of the new frames;
- the Gaussians trained: those of them no other old view sees (in its image), plus the seeds. A Gaussian an
  untrained old view shows is rendered but not changed, so what that view shows stays as it was.

Everything else is kept exactly as it was. The cost of a region depends on how much a few views see, not on the
size of the world. Held-out views are chosen per segment (`held_out`), so a frame keeps its role as the world
grows and the held-out figures of untouched segments remain held-out figures.

World frame throughout: W2C poses (OpenCV axes), K in pixels of `width` x `height` images.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class Region:
    """views: indices (ascending) of the views trained, the new ones included; rendered: (N,) bool over the old
    Gaussians, those the training renders; trained: (N,) bool, those of them it optimises (the others are kept
    as they are)."""

    views: list[int]
    rendered: np.ndarray
    trained: np.ndarray


def visibility(
    points: np.ndarray, w2c: np.ndarray, K: np.ndarray, width: int, height: int, margin_frac: float
) -> np.ndarray:
    """(V, N) bool: point n is in front of camera v and projects into its image grown by `margin_frac` of the
    width (height) on each side. Cameras with a non-finite pose see nothing. K (3,3) or (V,3,3)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    w2c = np.asarray(w2c, np.float64).reshape(-1, 4, 4)
    Ks = np.broadcast_to(np.asarray(K, np.float64), (len(w2c), 3, 3))
    out = np.zeros((len(w2c), len(points)), bool)
    lo_u, hi_u = -margin_frac * width, (1.0 + margin_frac) * width
    lo_v, hi_v = -margin_frac * height, (1.0 + margin_frac) * height
    for v, (pose, k) in enumerate(zip(w2c, Ks, strict=True)):
        if not np.isfinite(pose).all():
            continue
        cam = points @ pose[:3, :3].T + pose[:3, 3]
        z = cam[:, 2]
        front = z > 1e-9 * (1.0 + np.abs(cam[:, :2]).max(axis=1))
        zs = np.where(front, z, 1.0)
        u = (k[0, 0] * cam[:, 0] + k[0, 1] * cam[:, 1]) / zs + k[0, 2]
        w = k[1, 1] * cam[:, 1] / zs + k[1, 2]
        out[v] = front & (u >= lo_u) & (u <= hi_u) & (w >= lo_v) & (w <= hi_v)
    return out


def overlap(
    means: np.ndarray, w2c: np.ndarray, Ks: np.ndarray, width: int, height: int, new: Sequence[int], margin_frac: float
) -> np.ndarray:
    """(V,) float: for each view, the share of the Gaussians (centres `means` (N,3)) the `new` views see that it
    sees too; NaN for every view when the new views see none. Ks (V,3,3)."""
    seen_new = visibility(means, w2c[list(new)], Ks[list(new)], width, height, margin_frac).any(axis=0)
    if not seen_new.any():
        return np.full(len(w2c), np.nan)
    return visibility(means[seen_new], w2c, Ks, width, height, margin_frac).mean(axis=1)


def extension_region(
    means: np.ndarray,
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    new: Sequence[int],
    max_old_views: int,
    min_overlap: float,
    margin_frac: float,
) -> Region:
    """The region to train after an extension (module docstring): `means` (N,3) the old Gaussians' centres,
    `w2c` (V,4,4) every view's pose, `new` the indices of the new views. An old view's overlap is the share of
    the old Gaussians the new views see that it sees too; where the new views see no old Gaussian at all (the
    world turned to empty space), the old views nearest the new cameras are taken instead. Cost: one projection
    of the Gaussians the region renders per old view, so it grows with the number of views, not with training."""
    from wonderverse.camera import camera_centers

    w2c = np.asarray(w2c, np.float64).reshape(-1, 4, 4)
    K = np.asarray(K, np.float64)
    Ks = K if K.ndim == 3 else np.broadcast_to(K, (len(w2c), 3, 3))
    new = sorted(set(new))
    old = np.setdiff1d(np.arange(len(w2c)), new)
    score = overlap(means, w2c, Ks, width, height, new, margin_frac)[old]
    if np.isfinite(score).all():
        eligible = score >= min_overlap
    else:
        centres = camera_centers(w2c)
        score = -np.linalg.norm(centres[old][:, None] - centres[new][None], axis=2).min(axis=1)
        eligible = np.ones(len(old), bool)
    ranked = old[np.argsort(-score, kind="stable")][: max(0, max_old_views)]
    chosen = sorted({*new, *(int(i) for i in ranked if eligible[np.searchsorted(old, i)])})
    rendered = visibility(means, w2c[chosen], Ks[chosen], width, height, margin_frac).any(axis=0)
    others = np.setdiff1d(old, chosen)
    shown = np.zeros(len(means), bool)  # rendered Gaussians an untrained old view shows in its image
    shown[rendered] = visibility(means[rendered], w2c[others], Ks[others], width, height, 0.0).any(axis=0)
    return Region(chosen, rendered, rendered & ~shown)


def held_out(names: Sequence[str], every: int) -> list[int]:
    """Indices of the held-out views among frames `names` (`s003_0007`: segment, frame), in order: within each
    segment, its every `every`-th frame in `names` (the `every`-th, 2·`every`-th, ...). A frame keeps its role as
    other segments are added around it. When no segment has `every` frames, every `every`-th frame overall; none
    when `every` ≤ 1 or there are fewer than 2 frames."""
    if every <= 1 or len(names) < 2:
        return []
    count: dict[str, int] = {}
    test = []
    for i, name in enumerate(names):
        seg = name.split("_")[0]
        count[seg] = count.get(seg, 0) + 1
        if count[seg] % every == 0:
            test.append(i)
    return test or list(range(every - 1, len(names), every))


def held_out_figures(
    fresh: dict[str, float], carried: dict[str, float] | None, test_names: Sequence[str]
) -> dict[str, float]:
    """Each held-out frame's figure (`test_names`): the `fresh` one where this run rendered it, else the one
    `carried` from the run that last did (a region's training leaves the rest of the scene as it was). Frames
    with neither are left out."""
    carried = carried or {}
    return {n: fresh[n] if n in fresh else carried[n] for n in test_names if n in fresh or n in carried}


def scene_figures(
    metrics: dict[str, Any], local: list[str], names: list[str], test: list[int], before: Any = None
) -> dict[str, Any]:
    """The trainer's `metrics` of a training over frames `local` restated for the whole scene, frames `names` with
    `test` held out: `train_views` / `test_views` index `names`; `rendered_test_views` the held-out ones rendered
    now; `test_psnr_by_frame` / `test_ssim_by_frame` each held-out frame's figure (`held_out_figures`, carried
    from the splats' metrics `before` for frames not rendered now) and `test_psnr` / `test_ssim` their means."""
    out = dict(metrics)
    at = {n: i for i, n in enumerate(names)}
    test_names = [names[i] for i in test]
    rendered = [local[i] for i in metrics.get("test_views", [])]
    for kind in ("psnr", "ssim"):
        values = out.pop(f"test_{kind}_views", [])
        fresh = dict(zip(rendered, values, strict=True)) if len(values) == len(rendered) else {}
        figures = held_out_figures(fresh, getattr(before, f"test_{kind}_by_frame", None), test_names)
        out[f"test_{kind}_by_frame"] = figures
        if figures:
            out[f"test_{kind}"] = float(np.mean(list(figures.values())))
    held = set(test)
    return out | {
        "test_views": list(test),
        "train_views": [i for i in range(len(names)) if i not in held],
        "rendered_test_views": [at[n] for n in rendered],
    }
