"""The reconstruction loss of the paper (sec. "Geometric-Aware 3D Scene Reconstruction"):

    L = L_rgb + λ_d L_depth + λ_n L_normal

  L_rgb    = (1 - λ_ssim) mean|Ĉ - C| + λ_ssim (1 - SSIM(Ĉ, C))       (the 3DGS photometric loss)
  L_depth  = mean_valid log(1 + |D̂ - (a D + b)|)                       (log-L1, as DN-Splatter)
  L_normal = mean_valid ||N̂ - N||_1 + λ_s TV(N̂)

Ĉ, D̂, N̂ are rendered colour, depth and camera-space normals (D̂ = Σ w_i z_i and N̂ = Σ w_i n_i exactly as
the paper's equations: alpha-composited, not divided by alpha; `depth_use_expected` divides D̂ by alpha
instead). C is the frame, D the monocular depth prior and N the prior normals (OpenCV camera axes,
facing the camera). (a, b) = (1, 0) for a prior the priors step aligned to the SfM points (it is in the
scene's units: `depth_fit: unaligned`, the default); otherwise the per-image least-squares fit of the prior
to the render, argmin Σ_valid (a D + b - D̂)², computed without gradient: the loss is then measured in the
render's own depth units, so the scene scale is set by the cameras and never pulled towards the prior's
arbitrary scale, but only the prior's shape is enforced — fitted at every step it lets surfaces that
parallax does not place drift (`depth_fit: every`; measured 2026-12-02, commit 52ed9dc: docs/benchmarks.md). (The paper
writes the fit the other way round, (a D̂ + b) ≈ D; aligning the prior keeps the target fixed while the
gradient flows into D̂ alone.) Valid pixels: prior finite and positive (depth) or of
non-zero length (normals), the optional validity mask, and rendered alpha > `alpha_threshold`.
||·||_1 sums the three channels; "mean_valid" averages over valid pixels (0 when there are none).

TV(N̂) = mean over horizontally adjacent pixel pairs of Σ_c |N̂[y,x+1,c] - N̂[y,x,c]|
       + mean over vertically adjacent pixel pairs of Σ_c |N̂[y+1,x,c] - N̂[y,x,c]|,
over the whole image: the paper's sum Σ_ij |∇_i N̂| + |∇_j N̂| divided by the number of pairs, so λ_s
does not depend on the resolution. The total is exactly the weighted sum above: λ_d and λ_n multiply
their terms and nothing else (no (1 + λ) factors).

Robust weights (`loss.robust`): per-pixel weights w (`outlier_blobs`) from the frame's disagreement with the other
training frames warped into it by the rendered depth (`cross_view_residual`, `test: cross_view`) or from the render's
residual (`robust_weights`, `test: render`) replace the means of L_rgb by mean(w |Ĉ - C|) and mean(w (1 - SSIM
map)), and multiply the prior weights, so a moving person or car in a frame pulls on nothing (docs/usage.md,
transients).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from wonderverse.splats.params import LossParams, RobustLossParams


def _gaussian_window(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim_map(img: Tensor, ref: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Per-pixel SSIM (H,W,C) of images (H,W,C) in [0,1], the INRIA 3DGS formulation: Gaussian window,
    zero padding at the borders, C1 = 0.01², C2 = 0.03², channels separately. Differentiable."""
    c = img.shape[-1]
    x = img.permute(2, 0, 1)[None]
    y = ref.permute(2, 0, 1)[None]
    w = _gaussian_window(window, sigma, img.dtype, img.device).expand(c, 1, window, window)
    pad = window // 2

    def blur(t: Tensor) -> Tensor:
        return F.conv2d(t, w, padding=pad, groups=c)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x * mu_x
    syy = blur(y * y) - mu_y * mu_y
    sxy = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2))
    return s[0].permute(1, 2, 0)


def ssim(img: Tensor, ref: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of (H,W,C) images (see `ssim_map`)."""
    return ssim_map(img, ref, window, sigma).mean()


def _candidate_density(residual: Tensor, params: RobustLossParams) -> Tensor:
    """(1,1,H,W): the share of the `patch_px` square around each pixel whose residual (H,W) exceeds max(
    `residual_ratio` x the view's median, `min_residual`)."""
    tau = torch.clamp_min(params.residual_ratio * residual.median(), params.min_residual)
    k = params.patch_px
    cand = (residual > tau).to(residual.dtype)[None, None]
    return F.avg_pool2d(cand, k, stride=1, padding=k // 2, count_include_pad=False)


def outlier_blobs(residual: Tensor, params: RobustLossParams) -> tuple[Tensor, Tensor]:
    """Per-pixel weights (H,W) and the outlier mask (H,W) bool of a per-pixel residual (H,W) in colour units.

    A pixel is a candidate when its residual exceeds max(`residual_ratio` x the view's median, `min_residual`): the
    median stands for how well this view fits, and a mover covers well under half of it. Candidates count only in
    dense patches (more than `patch_share` of the `patch_px` square around the pixel), so thin lines (fine texture,
    depth edges) stay in, while a person's or a car's blob goes; the blob then grows by `dilate_px` to take its soft
    edges. A view whose outliers are fewer than `min_outlier_share` of its pixels keeps them all (static footage
    leaves stray specks), and so does one whose outliers are more than `max_outlier_share` (then the evidence, not
    the view, is wrong: a depth that does not yet fit). Outliers weigh `outlier_weight`, the rest 1. Fixed shapes and
    no host sync, like the rest of the loss."""
    r = residual
    out = (_candidate_density(r, params) > params.patch_share).to(r.dtype)
    if params.dilate_px > 0:
        d = params.dilate_px
        out = F.max_pool2d(out, 2 * d + 1, stride=1, padding=d)
    mask = out[0, 0] > 0.5
    share = mask.to(r.dtype).mean()
    mask = mask & (share >= params.min_outlier_share) & (share <= params.max_outlier_share)
    return outlier_weights(mask, params, r.dtype), mask


def outlier_weights(mask: Tensor, params: RobustLossParams, dtype: torch.dtype) -> Tensor:
    """Per-pixel weights (H,W) of an outlier mask (H,W) bool: `outlier_weight` on it, 1 elsewhere."""
    return torch.where(mask, params.outlier_weight, 1.0).to(dtype)


@torch.no_grad()
def robust_weights(rgb: Tensor, gt_rgb: Tensor, params: RobustLossParams) -> tuple[Tensor, Tensor]:
    """`outlier_blobs` of the residual r = mean_c |rgb - gt| of a render against its frame, both (H,W,3) in [0,1]:
    the render test (`robust.test: render`). Everything is of this one view, so no state crosses steps."""
    return outlier_blobs((rgb.detach() - gt_rgb).abs().mean(-1), params)


@torch.no_grad()
def confirmed_by_render(mask: Tensor, rgb: Tensor, gt_rgb: Tensor, params: RobustLossParams) -> Tensor:
    """The pixels of an outlier `mask` (H,W) where the render rgb (H,W,3) disagrees with its frame gt_rgb (H,W,3)
    too: more than `confirm_share` of the `patch_px` square around them exceed the render test's threshold (as in
    `outlier_blobs`). The cross-view test alone also flags the world a slow mover walks over, since the other frames
    show the mover there; once the scene is learnt, the render shows that world as the frame does. A mover the
    scene has not taken in disagrees with both."""
    return mask & (_candidate_density((rgb - gt_rgb).abs().mean(-1), params)[0, 0] > params.confirm_share)


@torch.no_grad()
def warp_frames(
    depth: Tensor, K: Tensor, w2c: Tensor, frames: Tensor, Ks: Tensor, w2cs: Tensor
) -> tuple[Tensor, Tensor]:
    """Other views' frames (N,H',W',3) resampled into a view of camera-z `depth` (H,W) (intrinsics K (3,3) in
    pixels, W2C (4,4)): each pixel's point at its depth, projected into frame n (Ks (N,3,3), w2cs (N,4,4)) and
    sampled there bilinearly. Returns the warped colours (N,H,W,3) and where they are valid (N,H,W) bool: in front
    of camera n and inside its frame. Pixel centres at +0.5 (as `splats.data.backproject_depth`)."""
    h, w = depth.shape
    v, u = torch.meshgrid(
        torch.arange(h, dtype=depth.dtype, device=depth.device),
        torch.arange(w, dtype=depth.dtype, device=depth.device),
        indexing="ij",
    )
    pix = torch.stack([u + 0.5, v + 0.5, torch.ones_like(u)], -1)
    cam = (pix @ torch.linalg.inv(K).T) * depth[..., None]
    c2w = torch.linalg.inv(w2c)
    world = cam @ c2w[:3, :3].T + c2w[:3, 3]
    pj = torch.einsum("nij,hwj->nhwi", w2cs[:, :3, :3], world) + w2cs[:, None, None, :3, 3]
    z = pj[..., 2]
    uv = torch.einsum("nij,nhwj->nhwi", Ks, pj)[..., :2] / z.clamp_min(1e-6)[..., None]
    hh, ww = frames.shape[1:3]
    grid = torch.stack([2 * uv[..., 0] / ww - 1, 2 * uv[..., 1] / hh - 1], -1)
    warped = F.grid_sample(frames.permute(0, 3, 1, 2), grid, mode="bilinear", align_corners=False)
    valid = (z > 1e-6) & (grid.abs() <= 1).all(-1)
    return warped.permute(0, 2, 3, 1), valid


@torch.no_grad()
def cross_view_residual(frame: Tensor, warped: Tensor, valid: Tensor) -> Tensor:
    """Per-pixel disagreement (H,W) of a frame (H,W,3) with the other views' frames warped into it (`warp_frames`):
    the median over those views of mean_c |frame - warped|, 0 where fewer than two see the pixel. The static world
    looks the same from every view, a mover is elsewhere in most of them, and a ghost in the scene is in no frame:
    so a high median marks a transient of this frame, whatever the render shows."""
    d = (frame[None] - warped).abs().mean(-1)
    d = torch.where(valid, d, torch.nan)
    med = torch.nanmedian(d, dim=0).values
    return torch.where(valid.sum(0) >= 2, torch.nan_to_num(med, nan=0.0), 0.0)


def fit_scale_shift(prior: Tensor, target: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """(a, b) minimising Σ_mask (a prior + b - target)², as float64 0-d tensors (closed form, no host sync).

    A prior that is constant over the mask gives a pure shift (a = 0 would erase it, so the scale is
    taken from the means instead: a = mean(target) / mean(prior), b = 0). Fewer than 2 pixels: (1, 0).
    """
    m = mask.reshape(prior.shape).double()
    p = torch.where(mask, prior, 0).double()
    t = torch.where(mask, target, 0).double()
    n = m.sum()
    pm, tm = p.sum() / n.clamp_min(1), t.sum() / n.clamp_min(1)
    var = (m * (p - pm) ** 2).sum() / n.clamp_min(1)
    cov = (m * (p - pm) * (t - tm)).sum() / n.clamp_min(1)
    flat = var <= 1e-12 * (pm * pm).clamp_min(1e-30)
    a_flat = torch.where(pm.abs() > 1e-30, tm / torch.where(pm.abs() > 1e-30, pm, 1.0), 1.0)
    a = torch.where(flat, a_flat, cov / torch.where(flat, 1.0, var))
    b = torch.where(flat, 0.0, tm - a * pm)
    few = n < 2
    return torch.where(few, 1.0, a), torch.where(few, 0.0, b)


def masked_mean(x: Tensor, mask: Tensor, weight: Tensor | None = None) -> Tensor:
    """Mean of x (times `weight` where given) over mask, 0 when the mask is empty; without indexing (no host
    sync, fixed shapes). The weights are not renormalised: a view whose pixels all weigh little adds little."""
    w = x if weight is None else x * weight
    return torch.where(mask, w, 0).sum() / mask.sum().clamp_min(1)


def texture_weight(frame: Tensor, ref: float) -> Tensor:
    """(H,W) prior weights of an (H,W,3) frame in [0,1]: 1 / (1 + (g / ref)²), g the grey-level gradient magnitude
    (Sobel / 8, replicated borders). Near 1 on plain surfaces, where colours say nothing about depth and the
    priors are all there is; small on texture, where the photometric loss pins the surface down across views
    better than a monocular prior can."""
    grey = frame.mean(-1)[None, None]
    kx = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=grey.dtype, device=grey.device)
    padded = F.pad(grey, (1, 1, 1, 1), mode="replicate")
    gx = F.conv2d(padded, (kx / 8)[None, None])[0, 0]
    gy = F.conv2d(padded, (kx.T / 8)[None, None])[0, 0]
    g2 = gx * gx + gy * gy
    return 1.0 / (1.0 + g2 / (ref * ref))


def depth_normals(depth: Tensor, K: Tensor, valid: Tensor, max_rel_step: float = 0.1) -> tuple[Tensor, Tensor]:
    """Camera-space unit normals (H,W,3) of a depth map (H,W) camera z with intrinsics K (3,3), from central
    differences of the back-projected points, turned to face the camera; and where they are defined (H,W):
    the pixel and its four neighbours `valid`, and no neighbour step |Δz| above `max_rel_step` × z (an occluding
    edge, where a difference spans two surfaces). Border pixels are invalid. Differentiable in depth."""
    h, w = depth.shape
    v, u = torch.meshgrid(
        torch.arange(h, device=depth.device, dtype=depth.dtype) + 0.5,
        torch.arange(w, device=depth.device, dtype=depth.dtype) + 0.5,
        indexing="ij",
    )
    z = torch.where(valid, depth, 1.0)
    pts = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    dx = F.pad((pts[:, 2:] - pts[:, :-2]).permute(2, 0, 1), (1, 1, 0, 0)).permute(1, 2, 0)
    dy = F.pad((pts[2:] - pts[:-2]).permute(2, 0, 1), (0, 0, 1, 1)).permute(1, 2, 0)
    n = torch.cross(dy, dx, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    n = torch.where((n * pts).sum(-1, keepdim=True) > 0, -n, n)
    ok = valid.clone()
    ok[0, :] = ok[-1, :] = False
    ok[:, 0] = ok[:, -1] = False
    ok[1:-1, 1:-1] &= valid[:-2, 1:-1] & valid[2:, 1:-1] & valid[1:-1, :-2] & valid[1:-1, 2:]
    zd = z.detach()
    step = torch.maximum((dx[..., 2].detach()).abs(), (dy[..., 2].detach()).abs()) / 2
    ok &= step <= max_rel_step * zd.abs()
    return n, ok


def depth_loss(
    depth: Tensor,
    alpha: Tensor,
    prior_depth: Tensor,
    valid: Tensor | None,
    params: LossParams,
    weight: Tensor | None = None,
    prior_aligned: Tensor | bool = True,
) -> tuple[Tensor, dict[str, Tensor]]:
    """L_depth (see the module docstring) for depth, alpha (H,W,1), prior (H,W) or (H,W,1), valid (H,W) bool.
    prior_aligned (0-d bool): the prior is in the render's units (the priors step aligned it); with
    `depth_fit: unaligned` it is then compared as it is, else fitted by scale and shift to the render.
    Fewer than `depth_min_valid_px` valid pixels: the term is 0 (and the fit NaN)."""
    d = depth[..., 0]
    a_r = alpha[..., 0]
    prior = prior_depth.reshape(d.shape).to(d.dtype)
    mask = torch.isfinite(prior) & (prior > 0) & (a_r.detach() > params.alpha_threshold)
    if valid is not None:
        mask &= valid.reshape(d.shape).bool()
    rendered = d / a_r.clamp_min(1e-10) if params.depth_use_expected else d
    n = mask.sum()
    enough = n >= params.depth_min_valid_px
    scale, shift = fit_scale_shift(prior, rendered.detach(), mask)
    if params.depth_fit == "unaligned":
        as_is = torch.as_tensor(prior_aligned, device=scale.device)
        scale, shift = torch.where(as_is, 1.0, scale), torch.where(as_is, 0.0, shift)
    aligned = scale.to(d.dtype) * torch.where(mask, prior, 0) + shift.to(d.dtype)
    err = (rendered - aligned).abs()
    if params.depth_units == "median":
        err = err / torch.nanmedian(torch.where(mask, aligned, torch.nan)).nan_to_num(1.0).clamp_min(1e-8)
    loss = torch.where(enough, masked_mean(torch.log1p(err), mask, weight), 0.0)
    nan = torch.full_like(scale, torch.nan)
    return loss, {
        "depth_scale": torch.where(enough, scale, nan),
        "depth_shift": torch.where(enough, shift, nan),
        "depth_valid_frac": torch.where(enough, n / mask.numel(), 0.0),
    }


def normal_tv(normals: Tensor) -> Tensor:
    """TV(N̂) of (H,W,3): mean over adjacent pairs of the L1 channel difference, x then y (module docstring)."""
    tv = normals.new_zeros(())
    if normals.shape[1] > 1:
        tv = tv + (normals[:, 1:] - normals[:, :-1]).abs().sum(-1).mean()
    if normals.shape[0] > 1:
        tv = tv + (normals[1:] - normals[:-1]).abs().sum(-1).mean()
    return tv


def normal_loss(
    normals: Tensor,
    alpha: Tensor,
    prior_normals: Tensor,
    valid: Tensor | None,
    params: LossParams,
    weight: Tensor | None = None,
    surface: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, dict[str, Tensor]]:
    """L_normal = mean_valid ||N - N_prior||_1 + λ_s TV(N̂) for rendered normals N̂ (H,W,3), alpha (H,W,1) and prior
    (H,W,3); N is N̂, or the rendered depth's normals `surface` = (normals, defined) (`normal_target`)."""
    prior = prior_normals.to(normals.dtype)
    norm = prior.norm(dim=-1)
    mask = torch.isfinite(norm) & (norm > 0.5) & (alpha[..., 0].detach() > params.alpha_threshold)
    if valid is not None:
        mask &= valid.reshape(mask.shape).bool()
    target = torch.nan_to_num(prior)
    tv = normal_tv(normals)
    l1 = masked_mean((normals - target).abs().sum(-1), mask, weight)
    if surface is not None and params.normal_target != "rendered":
        n_d, ok = surface
        l1_d = masked_mean((n_d - target).abs().sum(-1), mask & ok, weight)
        l1 = l1_d if params.normal_target == "depth" else 0.5 * (l1 + l1_d)
    return l1 + params.lambda_normal_tv * tv, {
        "normal_l1": l1.detach(),
        "normal_tv": tv.detach(),
        "normal_valid_frac": mask.float().mean(),
    }


def total_loss(
    *,
    rgb: Tensor,
    gt_rgb: Tensor,
    depth: Tensor,
    alpha: Tensor,
    normals: Tensor,
    params: LossParams,
    prior_depth: Tensor | None = None,
    prior_normals: Tensor | None = None,
    depth_valid: Tensor | None = None,
    normal_valid: Tensor | None = None,
    K: Tensor | None = None,
    prior_weight: Tensor | None = None,
    prior_scale: Tensor | float = 1.0,
    prior_aligned: Tensor | bool = True,
    rgb_weight: Tensor | None = None,
) -> tuple[Tensor, dict[str, Tensor]]:
    """L = L_rgb + s (λ_d L_depth + λ_n L_normal) + λ_dn L_dn for one view, every argument by name (the rendered
    rgb, depth, alpha, normals and the frame gt_rgb are all (H,W,C) tensors: by position they are easily swapped).
    Images (H,W,C) float in [0,1]; see the module docstring for every term. A missing prior drops its term;
    depth_valid and normal_valid (H,W) bool restrict the depth and the normal term (the trainer passes one mask for
    both). K (3,3) is needed for the rendered depth's normals (`normal_target` other than "rendered",
    `lambda_depth_normal`); prior_weight (H,W) weighs the prior terms per pixel (`texture_weight`); s = prior_scale,
    the schedule's factor; prior_aligned: the depth prior is in the render's units (`depth_loss`); rgb_weight (H,W):
    per-pixel weights of L_rgb (`robust_weights`: |Ĉ - C| and 1 - SSIM averaged with them) that multiply the prior
    weights too. Returns (total,
    {term: float}) with keys rgb_l1, ssim, rgb, depth, normal, total and the fit/validity diagnostics, all detached
    0-d tensors: nothing here waits for the device, so a training step runs without host syncs."""
    if rgb_weight is None:
        l1 = (rgb - gt_rgb).abs().mean()
        s = ssim(rgb, gt_rgb, params.ssim_window_px, params.ssim_sigma_px)
        l_rgb = (1.0 - params.lambda_ssim) * l1 + params.lambda_ssim * (1.0 - s)
    else:  # the weighted means of the same terms; outliers drop out of the priors too (they show the mover)
        w = rgb_weight.reshape(rgb.shape[:2])[..., None]
        l1 = (w * (rgb - gt_rgb).abs()).mean()
        s_map = ssim_map(rgb, gt_rgb, params.ssim_window_px, params.ssim_sigma_px)
        s = 1.0 - (w * (1.0 - s_map)).mean()
        l_rgb = (1.0 - params.lambda_ssim) * l1 + params.lambda_ssim * (1.0 - s)
        prior_weight = w[..., 0] if prior_weight is None else prior_weight * w[..., 0]
    terms = {"rgb_l1": l1.detach(), "ssim": s.detach(), "rgb": l_rgb.detach()}
    total = l_rgb
    surface = None
    wants_surface = params.lambda_depth_normal > 0 or (
        params.normal_target != "rendered" and prior_normals is not None and params.lambda_normal > 0
    )
    if K is not None and wants_surface:
        a = alpha[..., 0]
        defined = a.detach() > params.alpha_threshold
        if normal_valid is not None:
            defined &= normal_valid.reshape(defined.shape).bool()
        surface = depth_normals(depth[..., 0] / a.clamp_min(1e-10), K.to(depth.dtype), defined)
    if prior_depth is not None and params.lambda_depth > 0:
        l_d, extra = depth_loss(depth, alpha, prior_depth, depth_valid, params, prior_weight, prior_aligned)
        total = total + prior_scale * params.lambda_depth * l_d
        terms.update(extra, depth=l_d.detach())
    if prior_normals is not None and params.lambda_normal > 0:
        l_n, extra = normal_loss(normals, alpha, prior_normals, normal_valid, params, prior_weight, surface)
        total = total + prior_scale * params.lambda_normal * l_n
        terms.update(extra, normal=l_n.detach())
    if surface is not None and params.lambda_depth_normal > 0:
        n_d, ok = surface
        l_dn = masked_mean(1.0 - (normals * n_d).sum(-1), ok)
        total = total + params.lambda_depth_normal * l_dn
        terms["depth_normal"] = l_dn.detach()
    terms["total"] = total.detach()
    return total, terms


def flatten_loss(log_scales: Tensor) -> Tensor:
    """Mean over Gaussians of shortest axis / middle axis (0: flat discs, 1: spheres), from (N,3) log scales.
    A ratio, so it flattens without shrinking: the scene's scale and the Gaussians' sizes do not change it.
    0 for no Gaussian."""
    if log_scales.shape[0] == 0:
        return log_scales.sum() * 0.0
    s = torch.sort(log_scales, dim=-1).values
    return torch.exp(s[:, 0] - s[:, 1]).mean()
