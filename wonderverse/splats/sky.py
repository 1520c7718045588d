"""The sky behind the Gaussians: one colour, or a colour per direction (an environment map).

Outdoor video shows a gradient from the horizon to the zenith, clouds and the sun's glow. One learnable colour
cannot render them, so held-out views lose PSNR on every sky pixel, while Gaussians free to paint the sky sit
at some depth in front of it. The map is a latitude-longitude texture (R, 2R, 3) over the directions of the
training frame (latitude from its +z axis, longitude atan2(y, x)), sampled bilinearly, wrapping in longitude;
every pixel shows rgb = Σ w c + (1 − α) sky(ray direction). A sky of shape (3,) is the single colour, which the
renderers composite themselves.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor


def initial_sky(colour: np.ndarray, rows: int) -> np.ndarray:
    """The sky to start from: `colour` (3,) itself when `rows` is 0, else a (rows, 2 rows, 3) map of it."""
    colour = np.asarray(colour, np.float32).reshape(3)
    return colour.copy() if rows == 0 else np.broadcast_to(colour, (rows, 2 * rows, 3)).copy()


def mean_colour(sky: np.ndarray) -> np.ndarray:
    """One colour for viewers that cannot show a map (a clear colour): the mean over the map's texels."""
    return np.asarray(sky, np.float32).reshape(-1, 3).mean(axis=0)


def is_map(sky: Tensor | np.ndarray | None) -> bool:
    return sky is not None and sky.ndim == 3


def ray_directions(w2c: Tensor, K: Tensor, width: int, height: int) -> Tensor:
    """Unit directions (H, W, 3) in the frame of `w2c` of the rays through the pixel centres (OpenCV axes)."""
    dev, dt = w2c.device, torch.float32
    v, u = torch.meshgrid(
        torch.arange(height, device=dev, dtype=dt) + 0.5, torch.arange(width, device=dev, dtype=dt) + 0.5, indexing="ij"
    )
    k = K.to(dt)
    cam = torch.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], torch.ones_like(u)], dim=-1)
    world = cam @ w2c[:3, :3].to(dt)  # row vectors: (R^T d)^T = d^T R
    return world / world.norm(dim=-1, keepdim=True)


def sample_sky(sky: Tensor, directions: Tensor) -> Tensor:
    """The map `sky` (R, C, 3) seen along `directions` (..., 3) unit: colours (..., 3), differentiable in `sky`."""
    cols = sky.shape[1]
    lon = torch.atan2(directions[..., 1], directions[..., 0])  # (-pi, pi]
    lat = torch.asin(directions[..., 2].clamp(-1.0, 1.0))  # [-pi/2, pi/2], +z up the texture
    # one texel column repeated on either side, so bilinear sampling wraps across longitude ±pi
    padded = torch.cat([sky[:, -1:], sky, sky[:, :1]], dim=1)
    x = lon / math.pi * (cols / (cols + 2))
    y = -lat / (math.pi / 2)
    grid = torch.stack([x, y], dim=-1).reshape(1, 1, -1, 2)
    out = torch.nn.functional.grid_sample(
        padded.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border", align_corners=False
    )
    return out[0, :, 0].T.reshape(*directions.shape[:-1], 3)


def composite(rgb: Tensor, alpha: Tensor, sky: Tensor, w2c: Tensor, K: Tensor) -> Tensor:
    """`rgb` (H, W, 3) rendered over black with `alpha` (H, W, 1), the map `sky` (R, C, 3) behind it."""
    height, width = rgb.shape[:2]
    return rgb + (1.0 - alpha) * sample_sky(sky, ray_directions(w2c, K, width, height))
