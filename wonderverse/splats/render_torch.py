"""Differentiable tile-based Gaussian rasteriser in plain PyTorch (CPU or any device), gsplat 1.5.3 semantics.

It plays the part of gsplat's `_torch_impl.py`: the readable reference beside the CUDA backend, and the
renderer the pipeline uses where there is no GPU. The maths follows gsplat 1.5.3's
`rasterization(..., render_mode="RGB+ED", packed=False, rasterize_mode="classic")`:

1. Projection (`project_gaussians`): camera-space means `t = R x + T` (viewmat = W2C, OpenCV axes);
   3D covariance Σ = (R_q S)(R_q S)^T; camera covariance R Σ R^T; EWA 2D covariance J Σ_c J^T with the
   Jacobian of the pinhole projection evaluated at the mean whose x/z and y/z are clamped to the
   frustum widened by 30% (gsplat's `lim = (W - cx)/fx + 0.3 tan_fov`), plus `eps2d` = 0.3 px^2 on the
   diagonal. means2d = (fx x/z + cx, fy y/z + cy) in pixels, with pixel (u, v) centred at (u+0.5, v+0.5).
   Culled (radius 0): z < near or z > far, non-positive determinant, opacity < 1/255, or a box that
   misses the image. The box half-widths are ceil(extend * sqrt(Σ2d_xx)), ceil(extend * sqrt(Σ2d_yy)) with
   extend = min(3.33, sqrt(2 ln(255 opacity))) -- the tight, opacity-aware box of gsplat 1.5.3 (the
   ellipse where alpha >= 1/255 lies inside it; sqrt(2 ln 255) = 3.329, so the cap never binds for
   opacity <= 1). Hence which tiles list a Gaussian never changes the image, only the work.
2. Binning: every Gaussian is listed in the 16x16 tiles its box touches; each tile's list is sorted by
   camera z (front to back).
3. Compositing, per pixel, over its tile's list in depth order: alpha_i = min(0.999, o_i exp(-½ dᵀ Σ2d⁻¹ d))
   (gsplat clamps at 0.999; the INRIA code at 0.99), skipped if alpha_i < 1/255 or the quadratic form is
   negative; T_i = Π_{j<i} (1 - alpha_j); a Gaussian that would bring T to <= 1e-4 is not drawn and ends
   the pixel (gsplat's rule). w_i = alpha_i T_i and
       rgb = Σ w_i c_i + T_final * background,   depth = Σ w_i z_i,   alpha = 1 - T_final,
       normals = Σ w_i n_i  (camera-space unit normals, see `gaussian_normals`).
   depth is NOT normalised: the expected depth of the visible surface is depth / alpha (gsplat's "ED").

Implementation (vectorised: no Python loop over Gaussians or pixels; tiles go in a few large chunks):
  * Binning sorts (tile, depth) keys of the Gaussian-tile overlaps (as gsplat's `isect_tiles`).
  * Candidate pairs (`_candidate_pairs`, no autograd): for each chunk of tiles, one matrix product
    evaluates every list entry's quadratic form at every pixel of its tile, laid out (tile pixel, entry),
    so reading the hits row by row yields each pixel's Gaussians contiguously and front to back.
  * Compositing (`_Composite`, a custom autograd Function): re-tests the candidates exactly, applies the
    T <= 1e-4 stop with a float64 segmented cumulative sum of log(1 - alpha), sums w_i f_i per pixel as a
    sparse (pixel x Gaussian) matrix product, and has gsplat's analytic backward (suffix sums instead of
    a back-to-front loop). Projection, SH and normals use ordinary autograd.
The returned `info["means2d"]` is the graph node densification reads view-space gradients from. Checked
against an independent float64 brute-force renderer and finite differences (tests/test_splats_render.py)
and against gsplat 1.5.3 on a GPU (tests/test_splats_gpu.py: outputs agree to ~3e-7, gradients ~6e-6).
"""

from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from wonderverse.splats.model import quat_to_rotmat, sh_colors

TILE_SIZE = 16  # gsplat's; the image does not depend on it (tested)
EPS2D = 0.3  # px^2 added to the 2D covariance diagonal (gsplat's eps2d, a low-pass filter)
ALPHA_THRESHOLD = 1.0 / 255.0  # alphas below this are skipped; also sets the opacity-aware box
ALPHA_MAX = 0.999  # gsplat's clamp of a single Gaussian's alpha
TRANSMITTANCE_MIN = 1e-4  # a pixel ends before the Gaussian that would bring T to <= this
MAX_EXTEND_SIGMA = 3.33  # gsplat's largest box half-width in standard deviations
FRUSTUM_MARGIN = 0.3  # the Jacobian is evaluated at means clamped to the frustum widened by this fraction
DENSE_CHUNK_ELEMS = 1 << 22  # (list entry x tile pixel) elements evaluated at once while selecting pairs


@dataclass
class Projection:
    """Per-Gaussian projection for one camera. Differentiable tensors: means_c, means2d, conics.

    means_c (N,3) camera-space means; means2d (N,2) pixels; conics (N,3) upper triangle (a, b, c) of the
    inverse 2D covariance; depths (N,) camera z; radii (N,2) int32 box half-widths in pixels, 0 = culled;
    covars2d (N,2,2) 2D covariances including eps2d.
    """

    means_c: Tensor
    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    covars2d: Tensor

    @property
    def visible(self) -> Tensor:
        return (self.radii > 0).all(dim=-1)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = EPS2D,
) -> Projection:
    """EWA projection of N Gaussians into one pinhole camera, gsplat 1.5.3's `fully_fused_projection`."""
    dtype = means.dtype
    viewmat = viewmat.to(dtype)
    K = K.to(dtype)
    Rv, tv = viewmat[:3, :3], viewmat[:3, 3]
    means_c = means @ Rv.T + tv
    RM = Rv @ (quat_to_rotmat(quats) * scales[:, None, :])  # camera-frame R_q S, so Σ_c = RM RM^T
    tx, ty, tz = means_c.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    in_depth = (tz >= near) & (tz <= far)
    # Culled Gaussians still flow through the maths below; a safe z keeps them (and their zero
    # gradients) finite, since 0 * inf would turn into NaN in the backward pass.
    z = torch.where(in_depth, tz, torch.ones_like(tz))
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + FRUSTUM_MARGIN * tan_fovx
    lim_x_neg = cx / fx + FRUSTUM_MARGIN * tan_fovx
    lim_y_pos = (height - cy) / fy + FRUSTUM_MARGIN * tan_fovy
    lim_y_neg = cy / fy + FRUSTUM_MARGIN * tan_fovy
    xc = z * torch.clamp(tx / z, min=-lim_x_neg, max=lim_x_pos)
    yc = z * torch.clamp(ty / z, min=-lim_y_neg, max=lim_y_pos)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * xc / (z * z), zero, fy / z, -fy * yc / (z * z)], -1).reshape(-1, 2, 3)
    JM = J @ RM
    cov2d = JM @ JM.transpose(1, 2) + eps2d * torch.eye(2, dtype=dtype, device=means.device)
    means2d = torch.stack([fx * tx / z + cx, fy * ty / z + cy], dim=-1)

    a, b, c = cov2d[:, 0, 0], 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0]), cov2d[:, 1, 1]
    det = a * c - b * b
    ok = in_depth & (det > 0) & torch.isfinite(det)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)

    with torch.no_grad():
        op = opacities.detach()
        ok = ok & (op >= ALPHA_THRESHOLD)  # not in place: `where` above keeps the old mask for backward
        extend = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
        extend = extend.clamp_max(MAX_EXTEND_SIGMA)
        rx = torch.ceil(extend * a.detach().clamp_min(0).sqrt())
        ry = torch.ceil(extend * c.detach().clamp_min(0).sqrt())
        ok &= torch.isfinite(rx) & torch.isfinite(ry) & ((rx > 0) | (ry > 0))
        # Boxes larger than the image are clamped to it so the integer conversion stays in range.
        rx = torch.where(ok, rx, torch.zeros_like(rx)).clamp_max(float(width))
        ry = torch.where(ok, ry, torch.zeros_like(ry)).clamp_max(float(height))
        m2 = means2d.detach()
        inside = (m2[:, 0] + rx > 0) & (m2[:, 0] - rx < width) & (m2[:, 1] + ry > 0) & (m2[:, 1] - ry < height)
        ok &= inside & torch.isfinite(m2).all(-1)
        radii = torch.stack([rx, ry], dim=-1) * ok[:, None]
        radii = radii.to(torch.int32)
    return Projection(means_c, means2d, conics, tz, radii, cov2d)


def gaussian_normals(quats: Tensor, scales: Tensor, viewmat: Tensor, means_c: Tensor) -> Tensor:
    """Camera-space unit normals (N,3): each Gaussian's shortest axis rotated by the viewmat, flipped so it
    faces the camera (n . mean_c <= 0). The axis choice is not differentiable; the rotation is."""
    R = quat_to_rotmat(quats)  # columns are the Gaussian's axes in the world
    idx = torch.argmin(scales.detach(), dim=-1)
    n_world = torch.gather(R, 2, idx[:, None, None].expand(-1, 3, 1))[..., 0]
    n_cam = n_world @ viewmat[:3, :3].to(n_world.dtype).T
    facing = torch.where((n_cam * means_c).sum(-1, keepdim=True).detach() > 0, -1.0, 1.0)
    return n_cam * facing.to(n_cam.dtype)


def _tile_intersections(
    means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tiles_x: int, tiles_y: int
) -> tuple[Tensor, Tensor]:
    """(gaussian id, tile id) of every Gaussian-tile overlap, sorted by tile then depth (front first)."""
    device = means2d.device
    m = means2d.detach()
    r = radii.to(m.dtype)
    vis = (radii > 0).all(-1)
    tmin_x = torch.floor((m[:, 0] - r[:, 0]) / tile_size).clamp(0, tiles_x).long()
    tmax_x = torch.ceil((m[:, 0] + r[:, 0]) / tile_size).clamp(0, tiles_x).long()
    tmin_y = torch.floor((m[:, 1] - r[:, 1]) / tile_size).clamp(0, tiles_y).long()
    tmax_y = torch.ceil((m[:, 1] + r[:, 1]) / tile_size).clamp(0, tiles_y).long()
    w = (tmax_x - tmin_x).clamp_min(0)
    h = (tmax_y - tmin_y).clamp_min(0)
    counts = torch.where(vis, w * h, torch.zeros_like(w))
    gid = torch.repeat_interleave(torch.arange(len(counts), device=device), counts)
    if gid.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return empty, empty
    first = torch.cumsum(counts, 0) - counts
    k = torch.arange(gid.numel(), device=device) - first[gid]
    wg = w[gid]
    tile = (tmin_y[gid] + k // wg) * tiles_x + tmin_x[gid] + k % wg
    depth_rank = torch.empty_like(counts)
    depth_rank[torch.argsort(depths.detach(), stable=True)] = torch.arange(len(counts), device=device)
    order = torch.argsort(tile * len(counts) + depth_rank[gid])
    return gid[order], tile[order]


@torch.no_grad()
def _candidate_pairs(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    gid: Tensor,
    tile: Tensor,
    tile_size: int,
    tiles_x: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Candidate (Gaussian id, pixel x, pixel y) pairs: each pixel's pairs contiguous, front to back.

    Every entry of each tile's list is tested at every pixel of the tile (what gsplat's kernel visits).
    The test is one matrix product per chunk: the quadratic form of each entry in the pixel offsets
    (1, lx, ly, lx^2, ly^2, lx*ly) within its tile, laid out (tile pixel, entry), compared with
    ln(255 opacity) (i.e. alpha >= 1/255) plus a margin covering float32 rounding, so the candidates are a
    superset of the contributing pairs (`_Composite` re-tests them exactly). Reading the hits row by
    row gives, for each pixel, its tile's entries in depth order, contiguously: no sort is needed.
    Pixels may lie beyond the image in the last row/column of tiles; `_Composite` drops them.
    """
    device = means2d.device
    empty = torch.zeros(0, dtype=torch.long, device=device)
    n_entries = gid.numel()
    if n_entries == 0:
        return empty, empty, empty
    tile_px = tile_size * tile_size
    local = torch.arange(tile_px, device=device)
    lx, ly = local % tile_size, torch.div(local, tile_size, rounding_mode="floor")
    lxf, lyf = lx.double(), ly.double()
    basis = torch.stack([torch.ones_like(lxf), lxf, lyf, lxf * lxf, lyf * lyf, lxf * lyf], dim=1)
    basis_abs_max = basis.abs().amax(dim=0)
    basis32 = basis.float()  # (tile_px, 6)
    tile_change = torch.ones(n_entries, dtype=torch.bool, device=device)
    tile_change[1:] = tile[1:] != tile[:-1]
    tile_starts = torch.nonzero(tile_change)[:, 0]
    # Chunks end on tile boundaries so that each pixel's candidates stay contiguous.
    rows_per_chunk = max(1, DENSE_CHUNK_ELEMS // tile_px)
    starts_list = [*tile_starts.tolist(), n_entries]
    bounds = [0]
    while bounds[-1] < n_entries:
        s = bounds[-1]
        if s + rows_per_chunk >= n_entries:
            bounds.append(n_entries)
            break
        i = int(torch.searchsorted(tile_starts, s + rows_per_chunk, right=True)) - 1
        # The last tile start within budget; a single tile longer than the budget is taken whole.
        bounds.append(starts_list[i] if starts_list[i] > s else starts_list[i + 1])

    out_g: list[Tensor] = []
    out_x: list[Tensor] = []
    out_y: list[Tensor] = []
    for s, e in itertools.pairwise(bounds):
        g = gid[s:e]
        t = tile[s:e]
        x0 = t % tiles_x * tile_size
        y0 = torch.div(t, tiles_x, rounding_mode="floor") * tile_size
        m = means2d.index_select(0, g).double()
        con = conics.index_select(0, g).double()
        A, B, C = con[:, 0], con[:, 1], con[:, 2]
        ux = m[:, 0] - x0 - 0.5  # offset of the mean from the tile's first pixel centre
        uy = m[:, 1] - y0 - 0.5
        Q = torch.stack(
            [
                0.5 * A * ux * ux + 0.5 * C * uy * uy + B * ux * uy,
                -A * ux - B * uy,
                -C * uy - B * ux,
                0.5 * A,
                0.5 * C,
                B,
            ],
            dim=0,
        )  # (6, entries)
        thr = torch.log(opacities.index_select(0, g).double() / ALPHA_THRESHOLD)
        margin = 1e-5 * (Q.abs() * basis_abs_max[:, None]).sum(0) + 1e-4
        sigma = basis32 @ Q.float()  # (tile_px, entries)
        flat = torch.nonzero((sigma <= (thr + margin).float()).view(-1))[:, 0]
        row = torch.div(flat, e - s, rounding_mode="floor")
        col = flat - row * (e - s)
        out_g.append(g.index_select(0, col))
        out_x.append(x0.index_select(0, col) + lx.index_select(0, row))
        out_y.append(y0.index_select(0, col) + ly.index_select(0, row))
    return torch.cat(out_g), torch.cat(out_x), torch.cat(out_y)


def _segment_starts(first: Tensor) -> Tensor:
    """Index of the first element of each element's segment, given the segment-start flags."""
    idx = torch.arange(len(first), device=first.device)
    return torch.cummax(torch.where(first, idx, torch.zeros_like(idx)), 0)[0]


class _Composite(torch.autograd.Function):
    """Front-to-back alpha compositing of candidate pairs (each pixel's contiguous, front to back).

    Forward: alpha_i = min(0.999, o exp(-sigma_i)), pairs with alpha < 1/255 (or a negative quadratic
    form, or a pixel outside the image) skipped; T_i = exp(Σ_{j<i} log(1 - alpha_j)) by a float64
    segmented cumulative sum; the first pair that would bring T to <= 1e-4 and all after it dropped;
    acc_p = Σ w_i f_i with w_i = alpha_i T_i; T_final_p = Π (1 - alpha_i) over the drawn pairs.
    Backward (the analytic form of gsplat's kernel, vectorised):
      dL/df_i = w_i G_p,
      dL/dalpha_i = T_i (f_i . G_p) - (Σ_{j>i} w_j (f_j . G_p) + g_T T_final) / (1 - alpha_i),
    then through the clamp, the exponential and the quadratic form to means2d, conics and opacities.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, gid, px, py, width, height):  # type: ignore[override]
        n_pix = width * height
        dtype = features.dtype
        dev = features.device
        pk = torch.cat([means2d, conics, opacities[:, None]], dim=1).index_select(0, gid)
        dx = pk[:, 0] - (px.to(dtype) + 0.5)
        dy = pk[:, 1] - (py.to(dtype) + 0.5)
        sigma = 0.5 * (pk[:, 2] * dx * dx + pk[:, 4] * dy * dy) + pk[:, 3] * dx * dy
        raw = pk[:, 5] * torch.exp(-sigma)
        alpha = raw.clamp_max(ALPHA_MAX)
        hit = (alpha >= ALPHA_THRESHOLD) & (sigma >= 0) & (px < width) & (py < height)
        log1m = torch.log1p(-alpha.double()) * hit
        pixel = py * width + px
        first = torch.ones_like(hit)
        first[1:] = pixel[1:] != pixel[:-1]
        excl = torch.cumsum(log1m, 0) - log1m
        log_t = excl - excl.index_select(0, _segment_starts(first))
        keep = hit & ((log_t + log1m) > math.log(TRANSMITTANCE_MIN))
        idx = torch.nonzero(keep)[:, 0]
        gid, pixel, dx, dy, pk, raw, alpha, log1m, log_t = (
            v.index_select(0, idx) for v in (gid, pixel, dx, dy, pk, raw, alpha, log1m, log_t)
        )
        trans = torch.exp(log_t).to(dtype)
        w = alpha * trans
        # Per-pixel sums as a sparse (segment x Gaussian) matrix product: rows are the pixels' runs.
        first = torch.ones(len(pixel), dtype=torch.bool, device=dev)
        first[1:] = pixel[1:] != pixel[:-1]
        seg_first = torch.nonzero(first)[:, 0]
        seg_pixel = pixel.index_select(0, seg_first)
        crow = torch.cat([seg_first, torch.tensor([len(pixel)], device=dev)])
        n_seg = len(seg_first)
        with warnings.catch_warnings():  # "CSR support is in beta": the product below is tested
            warnings.simplefilter("ignore", UserWarning)
            weights = torch.sparse_csr_tensor(crow, gid, w, (n_seg, features.shape[0]), check_invariants=False)
        acc = torch.zeros(n_pix, features.shape[1], dtype=dtype, device=dev)
        if n_seg:
            acc[seg_pixel] = weights @ features
        log_tf = torch.zeros(n_pix, dtype=torch.float64, device=dev).index_add_(0, pixel, log1m)
        t_final = torch.exp(log_tf).to(dtype)
        ctx.save_for_backward(features, gid, pixel, first, dx, dy, pk, raw, alpha, trans, t_final)
        ctx.n_gaussians = means2d.shape[0]
        ctx.mark_non_differentiable(gid)
        return acc, t_final, gid

    @staticmethod
    def backward(ctx, g_acc, g_tf, _g_gid):  # type: ignore[override]
        features, gid, pixel, first, dx, dy, pk, raw, alpha, trans, t_final = ctx.saved_tensors
        dtype = features.dtype
        dev = features.device
        if g_acc is None:
            g_acc = torch.zeros(len(t_final), features.shape[1], dtype=dtype, device=dev)
        if g_tf is None:
            g_tf = torch.zeros_like(t_final)
        w = alpha * trans
        gp = g_acc.index_select(0, pixel)
        gdotf = (features.index_select(0, gid) * gp).sum(1)
        grad_features = torch.zeros_like(features).index_add_(0, gid, w[:, None] * gp)
        # Σ_{j>i} w_j (f_j . G_p) within each pixel, from a float64 running sum.
        v = (w * gdotf).double()
        incl = torch.cumsum(v, 0)
        seg_start = _segment_starts(first)
        total = torch.zeros(len(t_final), dtype=torch.float64, device=dev).index_add_(0, pixel, v)
        before = incl.index_select(0, seg_start) - v.index_select(0, seg_start)
        suffix = (total.index_select(0, pixel) - (incl - before)).to(dtype)
        g_alpha = trans * gdotf - (suffix + (g_tf * t_final).index_select(0, pixel)) / (1.0 - alpha)
        g_raw = torch.where(raw <= ALPHA_MAX, g_alpha, torch.zeros_like(g_alpha))
        g_sigma = -raw * g_raw
        per_pair = torch.stack(
            [
                g_sigma * (pk[:, 2] * dx + pk[:, 3] * dy),
                g_sigma * (pk[:, 4] * dy + pk[:, 3] * dx),
                g_sigma * 0.5 * dx * dx,
                g_sigma * dx * dy,
                g_sigma * 0.5 * dy * dy,
                g_raw * raw / pk[:, 5].clamp_min(1e-30),  # d raw / d opacity = exp(-sigma)
            ],
            dim=1,
        )
        grads = torch.zeros(ctx.n_gaussians, 6, dtype=dtype, device=dev).index_add_(0, gid, per_pair)
        return grads[:, :2], grads[:, 2:5], grads[:, 5], grad_features, None, None, None, None, None


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    gid: Tensor,
    px: Tensor,
    py: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, int]:
    """Differentiable compositing of candidate pairs (see `_Composite`).

    features (N,F) are the per-Gaussian quantities to blend (colour, depth, normal, ...). Returns
    (Σ w_i f_i as (H*W,F), final transmittance (H*W,), number of pairs drawn). Pixels without pairs get
    0 and T = 1.
    """
    acc, t_final, drawn = _Composite.apply(means2d, conics, opacities, features, gid, px, py, width, height)
    return acc, t_final, int(drawn.numel())


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
    tile_size: int = TILE_SIZE,
) -> tuple[Tensor, Tensor, Tensor, Tensor, dict[str, Any]]:
    """Render one camera. Inputs follow gsplat 1.5.3's `rasterization` for a single view:

    means (N,3), quats (N,4) wxyz (normalised here), scales (N,3) standard deviations (not log),
    opacities (N,) in [0,1], colors (N,3) RGB or, with `sh_degree`, SH coefficients (N,K,3) evaluated in
    the direction mean - camera centre (colour = max(SH + 0.5, 0)); viewmat (4,4) W2C; K (3,3) pixels.

    Returns rgb (H,W,3) with `background` (3,) composited behind (black if None); depth (H,W,1) = Σ w_i z_i,
    camera z, not normalised (expected depth = depth / alpha); alpha (H,W,1); normals (H,W,3) = Σ w_i n_i
    with camera-space unit normals facing the camera (not normalised); and info with radii (N,2) int32,
    means2d (1,N,2) pixels (gsplat's meta layout for one camera; a graph node: call `retain_grad()` on it
    before backward to read view-space gradients),
    depths (N,), visible (N,) bool, conics (N,3), width, height, n_cameras = 1.
    Computed in the dtype of `means` (float32 normally; float64 for gradient checks).
    """
    dtype = means.dtype
    device = means.device
    viewmat = torch.as_tensor(viewmat, dtype=dtype, device=device)
    K = torch.as_tensor(K, dtype=dtype, device=device)
    opacities = opacities.to(dtype)
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d)
    if sh_degree is not None:
        campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
        rgb_g = sh_colors(sh_degree, colors.to(dtype), means - campos)
    else:
        rgb_g = colors.to(dtype)
    normals_g = gaussian_normals(quats, scales, viewmat, proj.means_c)
    features = torch.cat([rgb_g, proj.depths[:, None], normals_g], dim=1)

    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    gid, tile = _tile_intersections(proj.means2d, proj.radii, proj.depths, tile_size, tiles_x, tiles_y)
    cand_gid, cand_x, cand_y = _candidate_pairs(
        proj.means2d.detach(), proj.conics.detach(), opacities.detach(), gid, tile, tile_size, tiles_x
    )
    # The (1,N,2) node gsplat's strategies read view-space gradients from (one camera, like gsplat's meta).
    means2d_node = proj.means2d[None]
    acc, trans, n_drawn = composite(
        means2d_node[0], proj.conics, opacities, features, cand_gid, cand_x, cand_y, width, height
    )
    rgb = acc[:, :3]
    if background is not None:
        rgb = rgb + trans[:, None] * torch.as_tensor(background, dtype=dtype, device=device)
    info = {
        "radii": proj.radii,
        "means2d": means2d_node,
        "depths": proj.depths,
        "conics": proj.conics,
        "visible": proj.visible,
        "width": width,
        "height": height,
        "n_cameras": 1,
        "n_pairs": n_drawn,
        "n_isects": int(gid.numel()),
    }
    return (
        rgb.reshape(height, width, 3),
        acc[:, 3:4].reshape(height, width, 1),
        (1.0 - trans).reshape(height, width, 1),
        acc[:, 4:7].reshape(height, width, 3),
        info,
    )
