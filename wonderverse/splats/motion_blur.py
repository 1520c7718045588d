"""Renders smeared the way the camera smeared the video: training on motion-blurred frames.

A frame exposed while the camera moves averages the scene over the open shutter. Compared with sharp renders,
blurred frames pull Gaussians into streaks and blur edges in depth. Like the deblurring splatting methods
(a linear camera motion within the exposure), the trainer can instead blur its render before the photometric
loss: each pixel is averaged over `samples` points along its image velocity times the shutter (the share of the
frame interval the shutter is open), centred on the pixel. The velocity comes from the rendered depth
(detached) and the neighbouring views' poses, as the central difference of where the pixel's point projects
in them. Sky (or empty) pixels move as directions. The Gaussians stay sharp; only the loss sees the smear.
"""

from __future__ import annotations

import torch
from torch import Tensor


def _project(world: Tensor, is_point: Tensor, w2c: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel coordinates (H,W,2) in `w2c` of world points (or directions where not `is_point`), and (H,W) bool
    where they lie in front of the camera."""
    cam = world @ w2c[:3, :3].T + torch.where(is_point[..., None], w2c[:3, 3], torch.zeros_like(w2c[:3, 3]))
    z = cam[..., 2]
    front = z > 1e-9
    zs = torch.where(front, z, torch.ones_like(z))
    u = K[0, 0] * cam[..., 0] / zs + K[0, 1] * cam[..., 1] / zs + K[0, 2]
    v = K[1, 1] * cam[..., 1] / zs + K[1, 2]
    return torch.stack([u, v], dim=-1), front


def image_velocity(depth: Tensor, alpha: Tensor, w2c: Tensor, prev: Tensor, nxt: Tensor, gap: int, K: Tensor) -> Tensor:
    """(H,W,2) pixels per frame interval: how what each pixel of view `w2c` shows moves, the central difference
    between its projections into `prev` and `nxt` (W2C), `gap` frame intervals apart. `depth` (H,W) camera z and
    `alpha` (H,W) of the render; a pixel less than half opaque is taken as a direction (sky). 0 where the point
    falls behind either camera, and everywhere when gap is 0."""
    h, w = depth.shape
    dev, dt = depth.device, depth.dtype
    if gap <= 0:
        return torch.zeros((h, w, 2), device=dev, dtype=dt)
    v, u = torch.meshgrid(
        torch.arange(h, device=dev, dtype=dt) + 0.5, torch.arange(w, device=dev, dtype=dt) + 0.5, indexing="ij"
    )
    k = K.to(dt)
    rays = torch.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], torch.ones_like(u)], dim=-1)
    is_point = (alpha > 0.5) & torch.isfinite(depth) & (depth > 0)
    z = torch.where(is_point, depth, torch.zeros_like(depth))[..., None]
    R, t = w2c[:3, :3].to(dt), w2c[:3, 3].to(dt)
    world = torch.where(is_point[..., None], (rays * z - t) @ R, rays @ R)  # R^T (x - t), or R^T d
    p_next, front_next = _project(world, is_point, nxt.to(dt), k)
    p_prev, front_prev = _project(world, is_point, prev.to(dt), k)
    vel = (p_next - p_prev) / gap
    return torch.where((front_next & front_prev)[..., None], vel, torch.zeros_like(vel))


def smear(rgb: Tensor, velocity: Tensor, shutter: float, samples: int, max_px: float) -> Tensor:
    """`rgb` (H,W,3) averaged over `samples` points along shutter x `velocity` (H,W,2), centred on each pixel, the
    smear capped at `max_px`; bilinear, edges clamped; differentiable in `rgb`."""
    h, w = rgb.shape[:2]
    trail = velocity * shutter
    length = trail.norm(dim=-1, keepdim=True)
    trail = trail * torch.clamp(max_px / length.clamp_min(1e-9), max=1.0)
    v, u = torch.meshgrid(
        torch.arange(h, device=rgb.device, dtype=rgb.dtype) + 0.5,
        torch.arange(w, device=rgb.device, dtype=rgb.dtype) + 0.5,
        indexing="ij",
    )
    offsets = torch.linspace(-0.5, 0.5, samples, device=rgb.device, dtype=rgb.dtype)
    x = (u[None] + offsets[:, None, None] * trail[None, ..., 0]).clamp(0.5, w - 0.5) / w * 2 - 1
    y = (v[None] + offsets[:, None, None] * trail[None, ..., 1]).clamp(0.5, h - 0.5) / h * 2 - 1
    grid = torch.stack([x, y], dim=-1).reshape(1, samples * h, w, 2)
    out = torch.nn.functional.grid_sample(
        rgb.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border", align_corners=False
    )
    return out[0].reshape(3, samples, h, w).mean(dim=1).permute(1, 2, 0)
