"""Rendering a trained splat scene from arbitrary world cameras (exports, fly-throughs, TSDF fusion).

Input is what the `splats` step stores: the Gaussian arrays in the training frame and the
`SceneNormalization` that maps the world into it. Cameras are given in the world frame (W2C, OpenCV
axes); depths come back in world units, so callers never see the training frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from wonderverse.splats.model import GaussianModel, SceneNormalization
from wonderverse.splats.renderer import Renderer


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
    norm: SceneNormalization,
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    renderer: Renderer,
    background: np.ndarray | None = None,
    min_alpha: float = 0.5,
) -> Iterator[RenderedView]:
    """Render `arrays` (GaussianModel.to_numpy layout, training frame) from world W2C poses (N,4,4) with
    intrinsics K (3,3) or (N,3,3) at width×height; yields one RenderedView per camera, lazily."""
    model = GaussianModel.from_numpy(arrays).to(renderer.device)
    w2c_n = norm.apply_w2c(np.asarray(w2c, np.float64).reshape(-1, 4, 4))
    Ks = np.broadcast_to(np.asarray(K, np.float64), (len(w2c_n), 3, 3)).copy()
    bg = None if background is None else torch.as_tensor(np.asarray(background, np.float32), device=renderer.device)
    dev = renderer.device
    with torch.no_grad():
        scales, opac = model.scales, model.opacities
        colors = model.sh_coeffs
        for pose, k in zip(w2c_n, Ks, strict=True):
            rgb, depth, alpha, normals, _ = renderer(
                model.means,
                model.quats,
                scales,
                opac,
                colors,
                torch.as_tensor(pose, dtype=torch.float32, device=dev),
                torch.as_tensor(k, dtype=torch.float32, device=dev),
                width,
                height,
                background=bg,
                sh_degree=model.sh_degree,
            )
            a = alpha[..., 0].cpu().numpy().astype(np.float32)
            with np.errstate(invalid="ignore", divide="ignore"):
                z = depth[..., 0].cpu().numpy().astype(np.float32) / np.maximum(a, 1e-6) / norm.scale
            z = np.where(a >= min_alpha, z, np.inf).astype(np.float32)
            n = normals.cpu().numpy().astype(np.float32)
            length = np.linalg.norm(n, axis=-1, keepdims=True)
            n = np.where(length > 1e-6, n / np.maximum(length, 1e-6), 0.0).astype(np.float32)
            yield RenderedView(rgb.clamp(0, 1).cpu().numpy().astype(np.float32), z, a, n)
