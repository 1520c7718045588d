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

Implementation (vectorised: no Python loop over Gaussians or pixels):
  * Binning sorts (tile, depth) keys of the Gaussian-tile overlaps (as gsplat's `isect_tiles`).
  * Candidate pairs (`_candidate_pairs`, no autograd): for every list entry and pixel row of its tile,
    the chord of the alpha >= 1/255 ellipse (solved in float64, with a margin for float32 rounding); one
    (pixel column, chord) boolean matrix read row by row yields each pixel's Gaussians contiguously and
    front to back, with no sort.
  * Compositing (`_Composite`, a custom autograd Function): re-tests the candidates exactly, applies the
    T <= 1e-4 stop with a float64 segmented cumulative sum of log(1 - alpha), sums w_i f_i per pixel as a
    sparse (pixel x Gaussian) matrix product, and has gsplat's analytic backward (suffix sums instead of
    a back-to-front loop). Pairs go in cache-sized chunks of whole pixels. Projection, SH and normals use
    ordinary autograd.
  * On the CPU, candidate pairs, compositing and its backward run in C++ (`native_raster`: the same pairs, the
    same sums to rounding, 2-5x faster); the torch code above is their reference and their fallback.
The returned `info["means2d"]` is the graph node densification reads view-space gradients from. Checked
against an independent float64 brute-force renderer and finite differences (tests/test_splats_render.py)
and against gsplat 1.5.3 on a GPU (tests/test_splats_gpu.py: outputs agree to ~3e-7, gradients ~6e-6).
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from wonderverse.splats import native_raster
from wonderverse.splats.model import quat_to_rotmat, sh_colors

TILE_SIZE = 16  # gsplat's; the image does not depend on it (tested)
EPS2D = 0.3  # px^2 added to the 2D covariance diagonal (gsplat's eps2d, a low-pass filter)
ALPHA_THRESHOLD = 1.0 / 255.0  # alphas below this are skipped; also sets the opacity-aware box
ALPHA_MAX = 0.999  # gsplat's clamp of a single Gaussian's alpha
TRANSMITTANCE_MIN = 1e-4  # a pixel ends before the Gaussian that would bring T to <= this
MAX_EXTEND_SIGMA = 3.33  # gsplat's largest box half-width in standard deviations
FRUSTUM_MARGIN = 0.3  # the Jacobian is evaluated at means clamped to the frustum widened by this fraction


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


@dataclass
class _Pairs:
    """Candidate (Gaussian, pixel) pairs, each pixel's pairs contiguous and front to back (a "run").

    gid (M,) int32 Gaussian of each pair; crow (S+1,) int32 run boundaries; seg_pixel (S,) int64 flat pixel
    index (v * width + u) of each run; seg_cx, seg_cy (S,) its pixel centre (u + 0.5, v + 0.5) in the working
    dtype; `seg` (M,) int32 the run of each pair.
    """

    gid: Tensor
    crow: Tensor
    seg_pixel: Tensor
    seg_cx: Tensor
    seg_cy: Tensor

    @functools.cached_property
    def seg(self) -> Tensor:
        first = torch.zeros(len(self.gid), dtype=torch.int32, device=self.gid.device)
        first[self.crow[1:-1].long()] = 1
        return torch.cumsum(first, 0, dtype=torch.int32)

    @staticmethod
    def from_crow(gid: Tensor, crow: Tensor, run_pixel: Tensor, width: int, dtype: torch.dtype) -> _Pairs:
        """Pairs from their Gaussian ids (int32), run boundaries (no empty runs) and the runs' flat pixel indices."""
        u = run_pixel % width
        v = torch.div(run_pixel, width, rounding_mode="floor")
        return _Pairs(gid, crow, run_pixel, u.to(dtype) + 0.5, v.to(dtype) + 0.5)

    @staticmethod
    def from_runs(gid: Tensor, run_lengths: Tensor, run_pixel: Tensor, width: int, dtype: torch.dtype) -> _Pairs:
        """Pairs from their Gaussian ids and the lengths and flat pixel indices of the runs (no empty runs)."""
        crow = torch.zeros(len(run_lengths) + 1, dtype=torch.int32, device=gid.device)
        torch.cumsum(run_lengths, 0, out=crow[1:])
        return _Pairs.from_crow(gid.int(), crow, run_pixel, width, dtype)

    @staticmethod
    def from_pixels(gid: Tensor, px: Tensor, py: Tensor, width: int, height: int, dtype: torch.dtype) -> _Pairs:
        """Pairs from (Gaussian id, pixel x, pixel y) lists whose pixels' pairs are already contiguous and
        front to back; pairs outside the image are dropped."""
        inside = torch.nonzero((px < width) & (py < height) & (px >= 0) & (py >= 0))[:, 0]
        gid, px, py = (v.index_select(0, inside).long() for v in (gid, px, py))
        pixel = py * width + px
        first = torch.ones_like(pixel, dtype=torch.bool)
        first[1:] = pixel[1:] != pixel[:-1]
        starts = torch.nonzero(first)[:, 0]
        lengths = torch.diff(starts, append=torch.tensor([len(pixel)], device=pixel.device))
        return _Pairs.from_runs(gid, lengths, pixel.index_select(0, starts), width, dtype)


@torch.no_grad()
def _candidate_pairs(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    gid: Tensor,
    tile: Tensor,
    tile_size: int,
    tiles_x: int,
    width: int,
    height: int,
) -> _Pairs:
    """Candidate pairs: a superset of the (Gaussian, pixel) pairs with alpha >= 1/255, in gsplat's order.

    For every entry of every tile's list (`gid`, `tile`, sorted by tile then depth) and every pixel row y
    of its tile, the pixels where the quadratic form is at most ln(255 opacity) (alpha >= 1/255) plus a
    margin covering float32 rounding form an interval, the chord of an ellipse, solved in float64. The
    live (row, entry) chords, ordered by row then entry, become the columns of one boolean
    (pixel column x, chord) matrix; reading its hits row by row lists each pixel's entries in list order
    (front to back) contiguously, so no sort is needed. `_Composite` re-tests the candidates exactly, so the
    margin only adds work and never changes the image. The C++ kernel (`native_raster`) makes the same pairs.
    """
    if native_raster.usable(means2d):
        pairs = native_raster.candidates(means2d, conics, opacities, gid, tile, tile_size, tiles_x, width, height)
        return _Pairs.from_crow(*pairs, width, means2d.dtype)
    device = means2d.device
    dtype = means2d.dtype
    ts = tile_size
    n_tiles = tiles_x * ((height + ts - 1) // ts)
    m = means2d.index_select(0, gid).double()
    con = conics.index_select(0, gid).double()
    a, b, c = con.unbind(1)
    x0 = tile % tiles_x * ts
    y0 = torch.div(tile, tiles_x, rounding_mode="floor") * ts
    ux = m[:, 0] - x0 - 0.5  # the mean from the tile's first pixel centre: dx = ux - x, dy = uy - y
    uy = m[:, 1] - y0 - 0.5
    thr = torch.log(opacities.index_select(0, gid).double() / ALPHA_THRESHOLD)
    # The float32 quadratic form errs by a few ulps of the sum of its terms' magnitudes; this bounds that
    # sum over the tile, so every exact hit lies inside the widened ellipse.
    dxm = torch.maximum(ux.abs(), (ux - (ts - 1)).abs())
    dym = torch.maximum(uy.abs(), (uy - (ts - 1)).abs())
    bound = 0.5 * a.abs() * dxm * dxm + 0.5 * c.abs() * dym * dym + b.abs() * dxm * dym
    two_a_thr = 2.0 * a * (thr + 1e-4 + 1e-5 * bound)
    det = a * c - b * b
    ok = (a > 0) & torch.isfinite(two_a_thr) & torch.isfinite(det) & torch.isfinite(ux) & torch.isfinite(uy)
    # Degenerate conics get a chord of +-ts around the tile centre: every pixel is a candidate.
    inv_a = torch.where(ok, 1.0 / torch.where(ok, a, 1.0), 1.0)
    slope = torch.where(ok, b * inv_a, 0.0)
    det = torch.where(ok, det, 0.0)
    two_a_thr = torch.where(ok, two_a_thr, float(ts * ts))
    ux = torch.where(ok, ux, 0.5 * (ts - 1))
    uy = torch.where(ok, uy, 0.0)
    # Chords for every (row, entry): x in [mid - half, mid + half] with dx = ux - x the roots of
    # a dx^2 / 2 + b dx dy + c dy^2 / 2 = thr'. Without real roots the discriminant is clamped to a tiny
    # positive number (sqrt of negatives and zeros is ~10x slower on the CPU): a chord of length ~0 yields
    # at most one spurious candidate, which `_Composite` rejects.
    rows = torch.arange(ts, dtype=torch.float64, device=device)[:, None]
    dy = uy - rows  # (ts, E)
    half = torch.sqrt((two_a_thr - det * dy * dy).clamp_min_(1e-300)) * inv_a
    mid = ux + slope * dy
    lo = torch.ceil(mid - half).clamp_min_(0.0)
    x_last = (width - 1 - x0).clamp_max(ts - 1).double()
    hi_cap = torch.where(rows < (height - y0).double(), x_last, -1.0)  # rows below the image: none
    hi = torch.minimum(torch.floor(mid + half), hi_cap)
    chords = torch.nonzero((lo <= hi).view(-1))[:, 0]  # row-major: by row, then entry (tile, depth)
    if chords.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return _Pairs.from_runs(empty, empty, empty, width, dtype)
    n_entries = gid.numel()
    chord_row = torch.div(chords, n_entries, rounding_mode="floor")
    chord_entry = chords - chord_row * n_entries
    lo_c = lo.view(-1).index_select(0, chords)
    hi_c = hi.view(-1).index_select(0, chords)
    cols = torch.arange(ts, dtype=torch.int16, device=device)[:, None]
    hits = torch.nonzero((cols >= lo_c.to(torch.int16)) & (cols <= hi_c.to(torch.int16)))  # (x, chord), x-major
    pair_gid = gid.index_select(0, chord_entry).int().index_select(0, hits[:, 1].contiguous())
    # Runs: consecutive pairs share a pixel when they share x and the chord's (row, tile). The chords of
    # one (row, tile) are adjacent, so run lengths come from per-(row, tile) difference arrays over x.
    key = chord_row * n_tiles + tile.index_select(0, chord_entry)
    new_group = torch.ones_like(key, dtype=torch.bool)
    new_group[1:] = key[1:] != key[:-1]
    group = torch.cumsum(new_group, 0) - 1
    n_groups = int(group[-1]) + 1
    diff = torch.zeros((ts + 1) * n_groups, dtype=torch.int32, device=device)
    ones = torch.ones_like(group, dtype=torch.int32)
    diff.index_add_(0, lo_c.long() * n_groups + group, ones)
    diff.index_add_(0, (hi_c.long() + 1) * n_groups + group, -ones)
    counts = torch.cumsum(diff.view(ts + 1, n_groups)[:ts], 0, dtype=torch.int32).view(-1)  # (x, group)
    runs = torch.nonzero(counts)[:, 0]
    run_x = torch.div(runs, n_groups, rounding_mode="floor")
    run_group = runs - run_x * n_groups
    group_first = torch.nonzero(new_group)[:, 0]
    g_entry = chord_entry.index_select(0, group_first)
    g_pixel0 = (y0.index_select(0, g_entry) + chord_row.index_select(0, group_first)) * width + x0.index_select(
        0, g_entry
    )
    run_pixel = g_pixel0.index_select(0, run_group) + run_x
    return _Pairs.from_runs(pair_gid, counts.index_select(0, runs), run_pixel, width, dtype)


LOG_TRANSMITTANCE_MIN = math.log(TRANSMITTANCE_MIN)
CHUNK_PAIRS = 1 << 16  # pairs composited at once: the per-pair temporaries of a chunk stay in the L2 cache
COMPACT_BELOW = 0.75  # a chunk keeps only its drawn pairs for the backward pass when fewer than this share are


def _chunks(crow: Tensor, chunk_pairs: int) -> list[tuple[int, int, int, int]]:
    """(first pair, end pair, first run, end run) of consecutive chunks of about `chunk_pairs` pairs that
    end on run (pixel) boundaries, so that every per-pixel quantity is local to one chunk."""
    n_pairs = int(crow[-1])
    targets = torch.tensor(range(chunk_pairs, n_pairs, chunk_pairs), dtype=crow.dtype, device=crow.device)
    cuts = torch.searchsorted(crow, targets).tolist()  # the first run starting at or after each target
    n_runs = len(crow) - 1
    run_bounds = sorted({0, n_runs, *cuts})
    pair_bounds = crow[run_bounds].tolist()
    return [
        (pair_bounds[i], pair_bounds[i + 1], run_bounds[i], run_bounds[i + 1])
        for i in range(len(run_bounds) - 1)
        if pair_bounds[i + 1] > pair_bounds[i]
    ]


class _Composite(torch.autograd.Function):
    """Front-to-back alpha compositing of candidate pairs (each pixel's contiguous, front to back).

    Forward: alpha_i = min(0.999, o exp(-sigma_i)), pairs with alpha < 1/255 (or a negative quadratic
    form) skipped; T_i = exp(Σ_{j<i} log(1 - alpha_j)) by a float64 cumulative sum less its value before
    the pixel's first pair; the first pair that would bring T to <= 1e-4 and all after it dropped;
    acc_p = Σ w_i f_i with w_i = alpha_i T_i (a sparse (pixel x Gaussian) product);
    T_final_p = Π (1 - alpha_i) over the drawn pairs.
    Backward (the analytic form of gsplat's kernel, vectorised):
      dL/df_i = w_i G_p,
      dL/dalpha_i = T_i (f_i . G_p) - (Σ_{j>i} w_j (f_j . G_p) + g_T T_final) / (1 - alpha_i),
    then through the clamp, the exponential and the quadratic form: per-Gaussian sums of g_sigma times
    dx, dy, dx^2, dx dy, dy^2 give the gradients of means2d and conics.
    Speed on the CPU: pairs go in chunks of whole pixels small enough for the L2 cache (elementwise work
    is memory-bound: ~4x faster), and per-channel 1-D gathers and scatters replace row gathers of
    (pairs, channels) tensors.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, pairs: _Pairs, n_pix, for_backward: bool):  # type: ignore[override]
        dtype = features.dtype
        dev = features.device
        # Per-Gaussian coefficients of -sigma = (-a/2 dx) dx + (-c/2 dy) dy + (-b dx) dy: halving and
        # negation are exact, so this is bit for bit -(0.5 (a dx dx + c dy dy) + b dx dy).
        mx, my = means2d.detach().t().contiguous()
        nha, nb, nhc = (conics.detach() * torch.tensor([-0.5, -1.0, -0.5], dtype=dtype, device=dev)).t().contiguous()
        per_gaussian = (mx, my, nha, nb, nhc, opacities.detach().contiguous())
        ctx.native = native_raster.usable(features)
        if ctx.native:
            feats = features.detach().contiguous()
            run_tensors = (pairs.gid, pairs.crow, pairs.seg_cx, pairs.seg_cy)
            acc_runs, tf_runs, n_drawn = native_raster.forward(per_gaussian, feats, *run_tensors)
            saved: tuple[Tensor, ...] = (*per_gaussian, feats, *run_tensors) if for_backward else ()
        else:
            acc_runs, tf_runs, n_drawn, ctx.chunks, saved = _forward_chunks(per_gaussian, features, pairs, for_backward)
        acc = torch.zeros(n_pix, features.shape[1], dtype=dtype, device=dev)
        t_final = torch.ones(n_pix, dtype=dtype, device=dev)
        acc[pairs.seg_pixel] = acc_runs
        t_final[pairs.seg_pixel] = tf_runs
        ctx.n_pix = n_pix
        ctx.save_for_backward(conics, features, pairs.seg_pixel, tf_runs, *saved)
        n_drawn_t = torch.tensor(n_drawn)
        ctx.mark_non_differentiable(n_drawn_t)
        return acc, t_final, n_drawn_t

    @staticmethod
    def backward(ctx, g_acc, g_tf, _g_n):  # type: ignore[override]
        conics, features, seg_pixel, tf_runs, *saved = ctx.saved_tensors
        if g_acc is None:
            g_acc = torch.zeros(ctx.n_pix, features.shape[1], dtype=features.dtype, device=features.device)
        g_runs = g_acc.index_select(0, seg_pixel)  # (runs, F)
        rest_runs = g_tf.index_select(0, seg_pixel) * tf_runs if g_tf is not None else None  # g_T T_final
        if ctx.native:
            if rest_runs is None:
                rest_runs = torch.zeros_like(tf_runs)
            *per_gaussian, feats, gid, crow, cx, cy = saved
            grad_features, grad_op, grads = native_raster.backward(
                tuple(per_gaussian), feats, gid, crow, cx, cy, g_runs, rest_runs.contiguous()
            )
        else:
            grad_features, grad_op, grads = _backward_chunks(features, ctx.chunks, saved, g_runs, rest_runs)
        sx, sy, sxx, sxy, syy = grads
        a, b, c = conics.unbind(1)
        g_means2d = torch.stack([a * sx + b * sy, b * sx + c * sy], 1)
        g_conics = torch.stack([0.5 * sxx, sxy, 0.5 * syy], 1)
        return g_means2d, g_conics, grad_op, grad_features, None, None, None


def _forward_chunks(
    per_gaussian: tuple[Tensor, ...], features: Tensor, pairs: _Pairs, for_backward: bool
) -> tuple[Tensor, Tensor, int, list[tuple[int, int]], tuple[Tensor, ...]]:
    """`_Composite`'s forward in vectorised torch, chunk by chunk: (acc per run, T_final per run, pairs drawn,
    the chunks' run ranges, and the per-pair tensors the backward needs)."""
    mx, my, nha, nb, nhc, op = per_gaussian
    dtype = features.dtype
    dev = features.device
    n_runs = len(pairs.seg_pixel)
    acc_runs = torch.zeros(n_runs, features.shape[1], dtype=dtype, device=dev)
    tf_runs = torch.ones(n_runs, dtype=dtype, device=dev)
    chunks: list[tuple[int, int]] = []
    chunk_tensors: tuple[Tensor, ...] = ()
    n_drawn = 0
    for p0, p1, r0, r1 in _chunks(pairs.crow, CHUNK_PAIRS):
        g = pairs.gid[p0:p1]
        sg = pairs.seg[p0:p1] - r0  # the pair's run within the chunk
        crow = pairs.crow[r0 : r1 + 1] - p0
        dx = mx.index_select(0, g) - pairs.seg_cx[r0:r1].index_select(0, sg)
        dy = my.index_select(0, g) - pairs.seg_cy[r0:r1].index_select(0, sg)
        neg_sigma = nha.index_select(0, g).mul_(dx).mul_(dx)
        neg_sigma += nhc.index_select(0, g).mul_(dy).mul_(dy)
        neg_sigma += nb.index_select(0, g).mul_(dx).mul_(dy)
        e = torch.exp(neg_sigma)
        raw = op.index_select(0, g).mul_(e)
        alpha = raw.clamp_max(ALPHA_MAX)
        hit = (alpha >= ALPHA_THRESHOLD) & (neg_sigma <= 0)
        log1m = torch.where(hit, torch.log1p(-alpha), 0.0).double()
        # Σ_{j<=i} log(1 - alpha_j) within the pixel: a float64 running sum less its value before the run.
        incl = torch.cumsum(log1m, 0)
        starts = crow[:-1]
        incl -= (incl.index_select(0, starts) - log1m.index_select(0, starts)).index_select(0, sg)
        keep = hit & (incl > LOG_TRANSMITTANCE_MIN)
        trans = (incl - log1m).to(dtype).exp_()
        w = torch.where(keep, alpha * trans, 0.0)
        with warnings.catch_warnings():  # "CSR support is in beta": the product below is tested
            warnings.simplefilter("ignore", UserWarning)
            weights = torch.sparse_csr_tensor(crow, g, w, (r1 - r0, features.shape[0]), check_invariants=False)
        acc_runs[r0:r1] = weights @ features.detach()
        # log T_final: the running sum of the drawn pairs' log(1 - alpha) at each run's end.
        drawn = torch.where(keep, log1m, 0.0)
        run_sum = torch.cumsum(drawn, 0)
        log_tf = run_sum.index_select(0, crow[1:] - 1) - run_sum.index_select(0, starts)
        tf_runs[r0:r1] = (log_tf + drawn.index_select(0, starts)).exp_().to(dtype)
        n_keep = int(keep.sum())
        n_drawn += n_keep
        chunks.append((r0, r1))
        if not for_backward:
            continue
        mask = keep & (raw <= ALPHA_MAX)  # the drawn pairs whose alpha has a gradient
        saved = (g, sg, dx, dy, e, raw, alpha, trans, mask, w)
        if n_keep < COMPACT_BELOW * len(g):  # most pairs lie behind opaque surfaces: drop them
            idx = torch.nonzero(keep)[:, 0]
            saved = tuple(v.index_select(0, idx) for v in saved)
            crow = torch.zeros_like(crow)
            torch.cumsum(torch.bincount(saved[1].long(), minlength=r1 - r0), 0, out=crow[1:])
        chunk_tensors += (crow, *saved)
    return acc_runs, tf_runs, n_drawn, chunks, chunk_tensors


def _backward_chunks(
    features: Tensor,
    chunks: list[tuple[int, int]],
    chunk_tensors: list[Tensor],
    g_runs: Tensor,
    rest_runs: Tensor | None,
) -> tuple[Tensor, Tensor, Tensor]:
    """`_Composite`'s backward in vectorised torch over `_forward_chunks`' chunks: dL/dfeatures (N, F), dL/dopacity
    (N,) and Σ g_sigma (dx, dy, dx², dx dy, dy²) (5, N)."""
    per_chunk = len(chunk_tensors) // max(1, len(chunks))
    dtype = features.dtype
    dev = features.device
    n, n_feat = features.shape
    grad_features = torch.zeros(n_feat, n, dtype=dtype, device=dev)
    grads = torch.zeros(5, n, dtype=dtype, device=dev)  # Σ g_sigma (dx, dy, dx^2, dx dy, dy^2)
    grad_op = torch.zeros(n, dtype=dtype, device=dev)
    g_runs = g_runs.t().contiguous()  # (F, runs)
    rest_runs = rest_runs.double() if rest_runs is not None else None
    f_t = features.detach().t().contiguous()  # (F, N)
    for i, (r0, r1) in enumerate(chunks):
        crow, g, sg, dx, dy, e, raw, alpha, trans, mask, w = chunk_tensors[i * per_chunk : (i + 1) * per_chunk]
        g64 = g.long()  # scatters take int64 indices
        gdotf = torch.zeros_like(w)
        for k in range(n_feat):
            gk = g_runs[k, r0:r1].index_select(0, sg)
            gdotf.addcmul_(f_t[k].index_select(0, g), gk)
            grad_features[k].scatter_add_(0, g64, gk.mul_(w))
        # Σ_{j>i} w_j (f_j . G_p) + g_T T_final: the pixel's total less a float64 running sum.
        incl = torch.cumsum((w * gdotf).double(), 0)
        rest = incl.index_select(0, (crow[1:] - 1).clamp_min(0))  # empty runs are never read
        if rest_runs is not None:
            rest += rest_runs[r0:r1]
        suffix = (rest.index_select(0, sg) - incl).to(dtype)
        g_raw = torch.where(mask, trans * gdotf - suffix / (1.0 - alpha), 0.0)
        grad_op.scatter_add_(0, g64, e * g_raw)
        g_sigma = g_raw.mul_(raw).neg_()
        gx = g_sigma * dx
        grads[0].scatter_add_(0, g64, gx)
        grads[2].scatter_add_(0, g64, gx * dx)
        grads[3].scatter_add_(0, g64, gx.mul_(dy))
        gy = g_sigma.mul_(dy)
        grads[1].scatter_add_(0, g64, gy)
        grads[4].scatter_add_(0, g64, gy.mul_(dy))
    return grad_features.t(), grad_op, grads


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
    """Differentiable compositing of candidate pairs (see `_Composite`): (gid, px, py) lists whose pixels'
    pairs are contiguous and front to back; pairs outside the image are dropped.

    features (N,F) are the per-Gaussian quantities to blend (colour, depth, normal, ...). Returns
    (Σ w_i f_i as (H*W,F), final transmittance (H*W,), number of pairs drawn). Pixels without pairs get
    0 and T = 1.
    """
    pairs = _Pairs.from_pixels(gid, px, py, width, height, features.dtype)
    acc, t_final, drawn = _Composite.apply(
        means2d, conics, opacities, features, pairs, width * height, torch.is_grad_enabled()
    )
    return acc, t_final, int(drawn)


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
    pairs = _candidate_pairs(
        proj.means2d.detach(),
        proj.conics.detach(),
        opacities.detach(),
        gid,
        tile,
        tile_size,
        tiles_x,
        width,
        height,
    )
    # The (1,N,2) node gsplat's strategies read view-space gradients from (one camera, like gsplat's meta).
    means2d_node = proj.means2d[None]
    # Without autograd (renders for outputs and evaluation) nothing is kept for a backward pass.
    acc, trans, n_drawn_t = _Composite.apply(
        means2d_node[0], proj.conics, opacities, features, pairs, width * height, torch.is_grad_enabled()
    )
    n_drawn = int(n_drawn_t)
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
