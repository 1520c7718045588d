"""The renderer interface of `render_torch.render` over gsplat 1.5.3's CUDA `rasterization` (CUDA only).

One call renders RGB, expected depth, alpha and camera-space normals of one camera:
`gsplat.rasterization(..., render_mode="RGB+ED", packed=False, rasterize_mode="classic")` with the
per-Gaussian camera-space normals appended to the colours as three extra channels (gsplat blends any
number of channels with the same weights, padding to a supported count). Consequences:
  * SH colours are evaluated here with gsplat's own fused `spherical_harmonics` kernel (+ 0.5, clamp at
    0, exactly what `rasterization` does inside; `model.sh_colors` is the same formula in plain torch),
    because extra channels need post-activation colours.
  * gsplat's "ED" channel is Σ w z / max(alpha, 1e-10); it is multiplied back by alpha so that `depth` is
    Σ w z exactly as the torch backend returns it (normalise with depth / alpha).
  * The background is given for the RGB channels only (zeros behind the normals; gsplat appends a zero
    behind the depth channel itself).
gsplat is imported inside the function: importing this module needs neither gsplat nor CUDA.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from wonderverse.errors import WonderError
from wonderverse.splats.compiled import Compiled
from wonderverse.splats.render_torch import EPS2D, gaussian_normals

GSPLAT_VERSION = "1.5.3"


def _camera_normals(means: Tensor, quats: Tensor, scales: Tensor, viewmat: Tensor) -> Tensor:
    return gaussian_normals(quats, scales, viewmat, means @ viewmat[:3, :3].T + viewmat[:3, 3])


_normals = Compiled(_camera_normals, dynamic=True)  # ~100 tiny kernels eagerly (forward + backward)


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
    depths (N,), visible (N,), conics (N,3), width, height, n_cameras = 1 and `meta`, gsplat's own dict.
    """
    try:
        from gsplat import rasterization, spherical_harmonics
    except ImportError as e:  # pragma: no cover - depends on the machine
        raise WonderError(f"the gsplat backend needs gsplat=={GSPLAT_VERSION} (pip install '.[gpu]'): {e}") from None
    if not means.is_cuda:
        raise WonderError("the gsplat backend needs CUDA tensors; use the torch backend on the CPU")
    device, dtype = means.device, means.dtype
    viewmat = torch.as_tensor(viewmat).to(device=device, dtype=dtype)
    K = torch.as_tensor(K).to(device=device, dtype=dtype)
    if sh_degree is not None:
        campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
        rgb_g = torch.clamp_min(spherical_harmonics(sh_degree, means - campos, colors) + 0.5, 0.0)
    else:
        rgb_g = colors
    # view_as: plain tensors, not Parameters, so the compiled graph treats N as dynamic (no recompiles)
    normals_g = _normals(means.view_as(means), quats.view_as(quats), scales, viewmat)
    feats = torch.cat([rgb_g, normals_g], dim=-1)  # (N, 6)
    backgrounds = None
    if background is not None:
        bg = torch.as_tensor(background).to(device=device, dtype=dtype).reshape(3)
        backgrounds = torch.cat([bg, torch.zeros(3, device=device, dtype=dtype)])[None]  # (1, 6)
    render_colors, render_alphas, meta = rasterization(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=feats,
        viewmats=viewmat[None],
        Ks=K[None],
        width=width,
        height=height,
        near_plane=near,
        far_plane=far,
        eps2d=eps2d,
        sh_degree=None,
        packed=False,
        tile_size=tile_size,
        backgrounds=backgrounds,
        render_mode="RGB+ED",
        rasterize_mode="classic",
    )
    out = render_colors[0]  # (H, W, 7): rgb, normals, expected depth
    alpha = render_alphas[0]  # (H, W, 1)
    radii = meta["radii"][0]
    if radii.dim() == 1:  # gsplat < 1.5 returned one radius per Gaussian
        radii = radii[:, None].expand(-1, 2)
    info = {
        "radii": radii.to(torch.int32),
        "means2d": meta["means2d"],
        "depths": meta["depths"][0],
        "conics": meta["conics"][0],
        "visible": (radii > 0).all(dim=-1),
        "width": width,
        "height": height,
        "n_cameras": 1,
        "meta": meta,
    }
    return out[..., 0:3], out[..., 6:7] * alpha, alpha, out[..., 3:6], info
