"""The renderer interface of `render_torch.render` over gsplat 1.5.3's CUDA kernels (CUDA only).

One call renders RGB, depth Σ w z, alpha and camera-space normals of one camera, calling gsplat's
kernels the way its `rasterization(..., packed=False, rasterize_mode="classic")` does (projection with
opacity-aware radii, tile intersection, rasterisation), without that function's wrapping:
  * The rasterised channels are [rgb, per-Gaussian camera-space normals, camera z, 0]: 8 is a channel
    count gsplat's kernels support, so nothing is padded, and the depth channel is Σ w z itself (its
    "ED" mode divides by alpha, which we would multiply back).
  * SH colours are evaluated with gsplat's fused `spherical_harmonics` kernel (+ 0.5, clamp at 0, as
    `rasterization` does; `model.sh_colors` is the same formula in plain torch).
  * The background is given for the RGB channels (zeros behind the others).
  * The image is split into its parts by one autograd function, whose backward is one concatenation;
    slicing it would add a full-image zero-fill and copy per part to every backward pass.
On an H100 the direct calls took 0.46 ms of host time per training step where `rasterization` took
0.88 ms, and the step is host-bound (docs/benchmarks.md, 2026-11-23).
gsplat is imported inside the function: importing this module needs neither gsplat nor CUDA.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from wonderverse.errors import WonderError
from wonderverse.splats import triton_kernels
from wonderverse.splats.render_torch import EPS2D

GSPLAT_VERSION = "1.5.3"


class _CameraNormals(torch.autograd.Function):
    """`render_torch.gaussian_normals` with a hand-written backward, where Triton is missing (else
    `triton_kernels`, one kernel each way): each Gaussian's shortest axis rotated into the camera and
    flipped to face it, in ~40 kernel launches instead of ~100 eagerly.

    The axis e_k of R(q) is a = e + 2w (u x e) + 2 u x (u x e) for the unit quaternion (w, u), so a zero
    quaternion (u = 0) gives a = e, the identity's axis, with a zero gradient. Only `quats` get a
    gradient: the axis choice and the facing sign are not differentiable."""

    @staticmethod
    def forward(ctx: Any, quats: Tensor, scales: Tensor, means: Tensor, viewmat: Tensor) -> Tensor:
        rot = viewmat[:3, :3]
        norm = quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        q = quats / norm
        w, u = q[:, :1], q[:, 1:]
        e = torch.zeros_like(u).scatter_(1, scales.argmin(-1, keepdim=True), 1.0)
        ue = torch.linalg.cross(u, e)
        n = (e + 2 * (w * ue + torch.linalg.cross(u, ue))) @ rot.T
        means_c = means @ rot.T + viewmat[:3, 3]
        sign = torch.where((n * means_c).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(n.dtype)
        ctx.save_for_backward(q, e, ue, norm, sign, rot)
        return n * sign

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None, None, None]:
        q, e, ue, norm, sign, rot = ctx.saved_tensors
        g = (grad * sign) @ rot  # d/da
        w, u = q[:, :1], q[:, 1:]
        ge, gu_ = (g * e).sum(-1, keepdim=True), (g * u).sum(-1, keepdim=True)
        g_w = 2 * (g * ue).sum(-1, keepdim=True)
        # d/du of g.(u x e) = e x g; of g.(u (u.e) - e |u|^2) = (u.e) g + (g.u) e - 2 (g.e) u
        g_u = 2 * (w * torch.linalg.cross(e, g) + (u * e).sum(-1, keepdim=True) * g + gu_ * e - 2 * ge * u)
        g_q = torch.cat([g_w, g_u], dim=-1)
        return (g_q - q * (q * g_q).sum(-1, keepdim=True)) / norm, None, None, None


class _Parts(torch.autograd.Function):
    """(1,H,W,8) image [rgb, normals, depth, 0] and (1,H,W,1) alpha -> rgb, depth, alpha, normals (H,W,·)."""

    @staticmethod
    def forward(ctx: Any, image: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        im = image[0]
        return im[..., 0:3], im[..., 6:7], alpha[0], im[..., 3:6]

    @staticmethod
    def backward(ctx: Any, g_rgb: Tensor, g_depth: Tensor, g_alpha: Tensor, g_normals: Tensor) -> tuple[Tensor, Tensor]:
        g_image = torch.cat([g_rgb, g_normals, g_depth, torch.zeros_like(g_depth)], dim=-1)
        return g_image[None], g_alpha[None]


def render(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    background: Tensor | None = None,
    sh_degree: int | None = None,
    eps2d: float = EPS2D,
    tile_size: int = 16,
) -> tuple[Tensor, Tensor, Tensor, Tensor, dict[str, Any]]:
    """Same arguments and returns as `render_torch.render` (see there for every convention), on CUDA.

    Inputs must be float32 CUDA tensors (viewmat/K/background may be CPU or float64; they are moved).
    info holds radii (N,2) int32, means2d (1,N,2) (gsplat's graph node: `retain_grad()` before backward),
    depths (N,), visible (N,), conics (N,3), width, height and n_cameras = 1.
    """
    try:
        from gsplat import (
            fully_fused_projection,
            isect_offset_encode,
            isect_tiles,
            rasterize_to_pixels,
            spherical_harmonics,
        )
    except ImportError as e:  # pragma: no cover - depends on the machine
        raise WonderError(f"the gsplat backend needs gsplat=={GSPLAT_VERSION} (pip install '.[gpu]'): {e}") from None
    if not means.is_cuda:
        raise WonderError("the gsplat backend needs CUDA tensors; use the torch backend on the CPU")
    device, dtype = means.device, means.dtype
    viewmat = torch.as_tensor(viewmat).to(device=device, dtype=dtype)
    K = torch.as_tensor(K).to(device=device, dtype=dtype)
    radii, means2d, depths, conics, _ = fully_fused_projection(
        means,
        None,
        quats,
        scales,
        viewmat[None],
        K[None],
        width,
        height,
        eps2d=eps2d,
        near_plane=near,
        far_plane=far,
        packed=False,
        calc_compensations=False,
        opacities=opacities,
    )
    if sh_degree is not None:
        campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
        rgb_g = torch.clamp_min(spherical_harmonics(sh_degree, means - campos, colors) + 0.5, 0.0)
    else:
        rgb_g = colors
    normals_fn = triton_kernels.camera_normals if triton_kernels.available() else _CameraNormals.apply
    normals_g = normals_fn(quats, scales.detach(), means.detach(), viewmat)
    feats = torch.cat([rgb_g, normals_g, depths[0, :, None], depths.new_zeros(len(means), 1)], dim=-1)
    backgrounds = None
    if background is not None:
        bg = torch.as_tensor(background).to(device=device, dtype=dtype).reshape(1, 3)
        backgrounds = torch.nn.functional.pad(bg, (0, 5))  # (1, 8): zeros behind normals, depth, padding
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    _, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, tile_size, tiles_x, tiles_y, n_images=1)
    offsets = isect_offset_encode(isect_ids, 1, tiles_x, tiles_y).reshape(1, tiles_y, tiles_x)
    image, alpha = rasterize_to_pixels(
        means2d, conics, feats[None], opacities[None], width, height, tile_size, offsets, flatten_ids, backgrounds
    )
    rgb, depth, alpha, normals = _Parts.apply(image, alpha)
    radii = radii[0]
    info = {
        "radii": radii.to(torch.int32),
        "means2d": means2d,
        "depths": depths[0],
        "conics": conics[0],
        "visible": (radii > 0).all(dim=-1),
        "width": width,
        "height": height,
        "n_cameras": 1,
    }
    return rgb, depth, alpha, normals, info
