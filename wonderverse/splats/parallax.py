"""Where the training views can place a surface by parallax, and how much the priors should weigh there.

Texture lowers the depth and normal priors' weight (`losses.texture_weight`) because the photometric loss pins
a textured surface down across views better than a monocular prior can. That holds only where the views see it
from angles wide enough: a textured mountainside 40 m away, seen from a path 4 m long, is as undetermined by the
images as a plain wall, and there the prior is the better guess. So texture lowers the weight only as far as
triangulation would beat the prior: for a pixel with aligned prior depth z, the relative depth error of
triangulating it from this view and another training view that frames it, over the widest such angle θ, is
u = (σ / f) / θ for a match error of σ = 1 pixel; q = 1 / (1 + (u / ref)²) is how far the views determine it
against a prior of relative error `ref`, and the prior's weight becomes 1 - q (1 - t), t the texture weight.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

MATCH_SIGMA_PX = 1.0  # the match error the triangulation bound assumes, in training pixels


def triangulation_error(
    depth: Tensor, K: Tensor, w2c: Tensor, others: Tensor, others_K: Tensor, stride_px: int = 8, chunk_views: int = 64
) -> Tensor:
    """(H,W) relative depth error u = (σ / f) / θ of triangulating each pixel of one view, from its depth (H,W)
    camera z in the views' units (invalid: not finite or <= 0) with intrinsics K (3,3) and W2C (4,4), against
    the views `others` W2C (N,4,4) with intrinsics `others_K` (N,3,3) at the same image size: θ the widest angle
    between this view's ray to the pixel's surface point and the ray of another view that frames it (occlusion
    ignored: an upper bound on θ, a lower one on u). Evaluated every `stride_px` pixels and spread bilinearly
    (in log space); +inf where no other view frames the point or the depth is invalid."""
    h, w = depth.shape
    dev, dt = depth.device, torch.float64
    small = depth[stride_px // 2 :: stride_px, stride_px // 2 :: stride_px].to(dt)
    hs, ws = small.shape
    v, u = torch.meshgrid(
        torch.arange(hs, device=dev, dtype=dt) * stride_px + stride_px // 2 + 0.5,
        torch.arange(ws, device=dev, dtype=dt) * stride_px + stride_px // 2 + 0.5,
        indexing="ij",
    )
    Kd, pose = K.to(dt), w2c.to(dt)
    ok = torch.isfinite(small) & (small > 0)
    z = torch.where(ok, small, 1.0)
    cam = torch.stack([(u - Kd[0, 2]) / Kd[0, 0] * z, (v - Kd[1, 2]) / Kd[1, 1] * z, z], -1).reshape(-1, 3)
    R, t = pose[:3, :3], pose[:3, 3]
    world = (cam - t) @ R  # R^T (x - t), row vectors
    centre = -R.T @ t
    ray = F.normalize(world - centre, dim=-1)
    best = torch.zeros(len(world), device=dev, dtype=dt)
    for start in range(0, len(others), chunk_views):
        o, ko = others[start : start + chunk_views].to(dt), others_K[start : start + chunk_views].to(dt)
        Ro, to = o[:, :3, :3], o[:, :3, 3]
        pc = torch.einsum("nij,pj->npi", Ro, world) + to[:, None]  # (n,P,3)
        zc = pc[..., 2].clamp_min(1e-12)
        uc = ko[:, 0, 0, None] * pc[..., 0] / zc + ko[:, 0, 2, None]
        vc = ko[:, 1, 1, None] * pc[..., 1] / zc + ko[:, 1, 2, None]
        framed = (pc[..., 2] > 0) & (uc >= 0) & (uc < w) & (vc >= 0) & (vc < h)
        centres = -torch.einsum("nji,nj->ni", Ro, to)  # -R^T t per view
        rays = F.normalize(world[None] - centres[:, None], dim=-1)
        # atan2(|a × b|, a · b): exact for the small angles that matter, where arccos has a 1e-8 noise floor
        sin = torch.linalg.cross(rays, ray[None].expand_as(rays), dim=-1).norm(dim=-1)
        angle = torch.where(framed, torch.atan2(sin, (rays * ray[None]).sum(-1)), 0.0)
        best = torch.maximum(best, angle.max(dim=0).values)
    err = (MATCH_SIGMA_PX / Kd[0, 0]) / best.clamp_min(1e-12)
    err = torch.where(ok.reshape(-1) & (best > 0), err, torch.inf).reshape(1, 1, hs, ws)
    # spread in log space (the error spans decades); +inf stays +inf through a large finite stand-in
    logerr = torch.log(err.clamp_max(1e30))
    full = F.interpolate(logerr, size=(h, w), mode="bilinear", align_corners=False)[0, 0]
    return torch.exp(full).to(depth.dtype)


def parallax_gate(texture: Tensor, error: Tensor, ref: float) -> Tensor:
    """The prior's weight 1 - q (1 - t) from the texture weight t (H,W) and the triangulation error u (H,W),
    q = 1 / (1 + (u / ref)²) (module docstring): t where the views determine the surface, 1 where they cannot."""
    q = 1.0 / (1.0 + (error / ref).square())
    return 1.0 - q * (1.0 - texture)
