"""Rendering a trained splat scene from arbitrary world cameras (exports, fly-throughs, TSDF fusion).

Input is what the `splats` step stores: the Gaussian arrays in the training frame and the normalisation
(a `camera.Sim3`, `splats.model.normalization_from_cameras`) that maps the world into it. Cameras are
given in the world frame (W2C, OpenCV axes); depths come back in world units, so callers never see the
training frame.

On the CPU, `workers` > 1 renders that many views at once, one torch thread each: the torch rasteriser
is thousands of small ops per view, which one view's intra-op threads share poorly (2 cores, 24 views at
240x160: 7.5 s one at a time, 5.7 s two at once; identical images).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import torch

from wonderverse.camera import Sim3
from wonderverse.progress import ProgressFn, no_progress
from wonderverse.splats.model import GaussianModel
from wonderverse.splats.renderer import Renderer
from wonderverse.splats.sky import composite, is_map

T = TypeVar("T")
R = TypeVar("R")


@dataclass
class RenderedView:
    """One rendered view. rgb (H,W,3) float32 in [0,1]; depth (H,W) float32 world units along camera z,
    the alpha-normalised expected depth, +inf where alpha < the caller's threshold (nothing there: sky or
    background); alpha (H,W) float32; normals (H,W,3) float32 unit vectors in the camera frame
    (OpenCV axes), zero where there is nothing."""

    rgb: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray
    normals: np.ndarray


def render_views(
    arrays: dict[str, np.ndarray],
    norm: Sim3,
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    renderer: Renderer,
    background: np.ndarray | None = None,
    min_alpha: float = 0.5,
    workers: int = 1,
    progress: ProgressFn | None = None,
) -> Iterator[RenderedView]:
    """Render `arrays` (GaussianModel.to_numpy layout, training frame) from world W2C poses (N,4,4) with
    intrinsics K (3,3) or (N,3,3) at width×height, `background` behind (a colour (3,) or a sky map (R, 2R, 3)
    of the training frame's directions, `wonderverse.splats.sky`; black if None); yields one RenderedView per
    camera, in order, lazily (`workers` > 1 on the CPU: up to twice that many views ahead, see the module
    docstring).
    progress(views yielded, N, "") is called before the first view and as each one is yielded."""
    model = GaussianModel.from_numpy(arrays).to(renderer.device)
    w2c_n = norm.transform_w2c(np.asarray(w2c, np.float64).reshape(-1, 4, 4))
    Ks = np.broadcast_to(np.asarray(K, np.float64), (len(w2c_n), 3, 3)).copy()
    sky = None if background is None else torch.as_tensor(np.asarray(background, np.float32), device=renderer.device)
    dev = renderer.device
    scales, opac = model.scales.detach(), model.opacities.detach()
    colors = model.sh_coeffs.detach()

    def one(camera: tuple[np.ndarray, np.ndarray]) -> RenderedView:
        pose_t = torch.as_tensor(camera[0], dtype=torch.float32, device=dev)
        k_t = torch.as_tensor(camera[1], dtype=torch.float32, device=dev)
        with torch.no_grad():
            rgb, depth, alpha, normals, _ = renderer(
                model.means,
                model.quats,
                scales,
                opac,
                colors,
                pose_t,
                k_t,
                width,
                height,
                background=None if is_map(sky) else sky,
                sh_degree=model.sh_degree,
            )
            if is_map(sky):
                rgb = composite(rgb, alpha, sky, pose_t, k_t)
        a = alpha[..., 0].cpu().numpy().astype(np.float32)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = depth[..., 0].cpu().numpy().astype(np.float32) / np.maximum(a, 1e-6) / norm.s
        z = np.where(a >= min_alpha, z, np.inf).astype(np.float32)
        n = normals.cpu().numpy().astype(np.float32)
        length = np.linalg.norm(n, axis=-1, keepdims=True)
        n = np.where(length > 1e-6, n / np.maximum(length, 1e-6), 0.0).astype(np.float32)
        return RenderedView(rgb.clamp(0, 1).cpu().numpy().astype(np.float32), z, a, n)

    cameras = zip(w2c_n, Ks, strict=True)
    report, n = progress or no_progress, len(w2c_n)
    report(0, n, "")
    if workers <= 1 or torch.device(dev).type != "cpu":
        for i, view in enumerate(map(one, cameras)):
            yield view
            report(i + 1, n, "")
        return
    with torch_threads(1):
        for i, view in enumerate(ordered_map(one, cameras, workers)):
            yield view
            report(i + 1, n, "")


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op thread count set to `n` meanwhile (it is process-wide)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def ordered_map(fn: Callable[[T], R], items: Iterable[T], workers: int) -> Iterator[R]:
    """fn over items in `workers` threads, yielded in order, with at most 2 x workers results pending."""
    with ThreadPoolExecutor(workers) as pool:
        pending: deque = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= 2 * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
