"""Optimising Gaussian splats on posed frames with the paper's RGB + depth + normal loss.

`train(model, views, params, renderer)` works in whatever frame the model and the views share; the
pipeline normalises both first (`model.normalization_from_cameras`, `normalize_views`) so that learning rates and the
densification thresholds are scene-independent, and inverts it at export (`ply.write_ply`).

Sky: pixels marked sky (or, with `sky_from_invalid_prior`, where the depth prior is invalid, e.g. +inf)
are explained by a learnable sky composited behind the Gaussians, rgb = Σ w c + T sky — one colour, or with
`sky_map_rows` a colour per ray direction (`wonderverse.splats.sky`) — and
their rendered alpha is pushed to 0 (`sky_alpha_weight` * mean alpha over sky pixels), so the sky is not
modelled by Gaussians at infinity. Depth/normal terms ignore sky pixels (their priors are invalid).

Motion blur: with `motion_blur_shutter` > 0 each training render is smeared along its image motion over the
shutter before the photometric loss (`wonderverse.splats.motion_blur`), so blurred video does not pull the
Gaussians into streaks; held-out metrics compare the render smeared the same way with the frame.

Held-out views (every `holdout_every`-th, starting with view `holdout_every - 1`) are never trained on and
give the evaluation metrics. A step whose loss or gradients are not finite is skipped: fused Adam's
`found_inf` flag leaves parameters and moments untouched, its gradients add nothing to the densification
statistics, and it is logged (when the loss curves are next copied to the host).

Speed: a step never waits for the device. Loss terms stay on the device and reach the host every
`_FLUSH_EVERY` steps in one copy; the finite check is a device flag, not a Python branch; densification
statistics accumulate with fixed shapes. On a GPU the CPU can then run ahead of the kernels it queues.
Progress (`progress(done, total, note)`) is reported about every 1 % of the iterations with the loss last
copied to the host, so reporting adds no wait either.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from wonderverse.progress import ProgressFn, no_progress
from wonderverse.splats.compiled import Compiled
from wonderverse.splats.losses import (
    confirmed_by_render,
    cross_view_residual,
    flatten_loss,
    masked_mean,
    outlier_blobs,
    outlier_weights,
    robust_weights,
    texture_weight,
    total_loss,
    warp_frames,
)
from wonderverse.splats.model import GaussianModel
from wonderverse.splats.motion_blur import image_velocity, smear
from wonderverse.splats.parallax import parallax_gate, triangulation_error
from wonderverse.splats.params import DefaultStrategyParams, LossParams, NoStrategy, RobustLossParams, TrainParams
from wonderverse.splats.renderer import Renderer
from wonderverse.splats.sky import composite, initial_sky, is_map, mean_colour
from wonderverse.splats.strategy import make_strategy

if TYPE_CHECKING:
    from wonderverse.camera import Sim3

log = logging.getLogger(__name__)
_FLUSH_EVERY = 50  # steps between copies of the loss terms to the host (each copy waits for the device)


PER_FRAME = ("frames", "w2c", "prior_depth", "prior_aligned", "prior_normals", "masks", "sky", "superseded")


@dataclass(kw_only=True)
class Views:
    """Posed frames in the training frame. frames (T,H,W,3) uint8 or float in [0,1]; w2c (T,4,4) W2C;
    K (3,3) or (T,3,3) pixels; prior_depth (T,H,W) camera z, +inf/NaN/<=0 invalid, in the views' units where
    prior_aligned (T,) bool says so (None: every frame), else at any affine scale;
    prior_normals (T,H,W,3) camera-space unit normals facing the camera (zero = invalid);
    masks (T,H,W) bool, pixels whose priors may be used; sky (T,H,W) bool, pixels of sky; superseded (T,H,W) bool,
    pixels a later segment's frames contradict (`splats.superseded`): they leave every loss term.
    Built by keyword only; `subset` and `replace` give changed copies without dropping a field."""

    frames: np.ndarray
    w2c: np.ndarray
    K: np.ndarray
    prior_depth: np.ndarray | None = None
    prior_aligned: np.ndarray | None = None
    prior_normals: np.ndarray | None = None
    masks: np.ndarray | None = None
    sky: np.ndarray | None = None
    superseded: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.frames)

    def K_of(self, i: int) -> np.ndarray:
        return self.K if self.K.ndim == 2 else self.K[i]

    def subset(self, indices: Sequence[int] | slice | np.ndarray) -> Views:
        """The views at `indices` (a list, an index array, a boolean mask or a slice), in that order: every
        per-frame field sliced alike, K too when it is per frame (T,3,3)."""
        idx = indices if isinstance(indices, slice) else np.asarray(indices, dtype=None if len(indices) else int)
        fields = {name: None if getattr(self, name) is None else getattr(self, name)[idx] for name in PER_FRAME}
        return Views(K=self.K if self.K.ndim == 2 else self.K[idx], **fields)

    def replace(self, **changes: Any) -> Views:
        """A copy with the named fields replaced (the others shared, not copied)."""
        return dataclasses.replace(self, **changes)


def normalize_views(views: Views, norm: Sim3) -> Views:
    """The same views in the normalised frame `norm` (poses mapped; depth priors scaled by norm.s)."""
    depth = None if views.prior_depth is None else views.prior_depth * norm.s
    return views.replace(w2c=norm.transform_w2c(views.w2c), prior_depth=depth)


def split_views(n_views: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """(train, test) view indices: test = every `holdout_every`-th view (indices N-1, 2N-1, ...)."""
    if holdout_every <= 1 or n_views < 2:
        return list(range(n_views)), []
    test = [i for i in range(n_views) if i % holdout_every == holdout_every - 1]
    return [i for i in range(n_views) if i not in test], test


def auto_scene_scale(w2c: np.ndarray, means: np.ndarray) -> float:
    """The length that learning rates and densification sizes are relative to: the larger of 3DGS's
    camera extent (1.1 x `camera.camera_radius`, the largest camera distance from the cameras' centroid)
    and the median distance of the initial Gaussians from that centroid. The second term matters for
    videos whose camera moves little compared with the distance to what it sees: relative to the camera
    extent alone, every Gaussian of a distant scene would be "too big" and pruned, and means would barely
    move. (Not `camera.scene_extent`, the size that output paths and meshes follow: the two differ, and
    the training schedule was tuned on this one.)"""
    from wonderverse.camera import camera_centers, camera_radius

    w2c = np.asarray(w2c, dtype=np.float64).reshape(-1, 4, 4)
    c = camera_centers(w2c).mean(axis=0)
    cam = 1.1 * camera_radius(w2c)
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    content = float(np.median(np.linalg.norm(means - c, axis=1))) if len(means) else 0.0
    scale = max(cam, content)
    return scale if np.isfinite(scale) and scale > 1e-9 else 1.0


def continuation_params(params: TrainParams, frac: float) -> TrainParams:
    """`params` for continuing a trained model (after an extension) for `frac` of its iterations: the
    densification schedule compressed alike (at the full schedule's steps a short run would never
    densify), no opacity reset (it would wipe the trained Gaussians' opacities) and the full SH degree
    from the first steps (the trained Gaussians have their higher bands already)."""

    def squeeze(n: int) -> int:
        return max(1, round(n * frac))

    strategy = params.strategy
    if not isinstance(strategy, NoStrategy):
        steps = ("refine_start_iter", "refine_every", "refine_stop_iter")
        schedule: dict[str, int] = {name: squeeze(getattr(strategy, name)) for name in steps}
        if isinstance(strategy, DefaultStrategyParams):
            schedule["reset_every"] = 0
            if strategy.refine_scale2d_stop_iter > 0:  # 0 is "off", not a step
                schedule["refine_scale2d_stop_iter"] = squeeze(strategy.refine_scale2d_stop_iter)
        strategy = strategy.model_copy(update=schedule)
    return params.model_copy(
        update={"iterations": squeeze(params.iterations), "sh_degree_interval_iters": 1, "strategy": strategy}
    )


def prior_schedule(params: TrainParams, step: int) -> float:
    """The factor on λ_d and λ_n at `step`: 1 until `prior_decay_start_frac` of the iterations, then log-linear
    down to `prior_final_ratio` at the last one. Priors shape the surfaces while the Gaussians find them; later
    the photometric loss across views, sharper than any monocular prior where there is texture, has the last word
    (where there is none, nothing pulls the surfaces away from where the priors put them)."""
    lp = params.loss
    start = lp.prior_decay_start_frac * params.iterations
    if step < start or lp.prior_final_ratio >= 1.0:
        return 1.0
    t = (step - start) / max(params.iterations - 1 - start, 1.0)
    return float(lp.prior_final_ratio ** min(t, 1.0))


def _lr_means(params: TrainParams, scene_scale: float, step: int) -> float:
    t = min(step / max(params.iterations, 1), 1.0)
    return params.lr_means * scene_scale * params.lr_means_final_ratio**t


class _Data:
    """The views as tensors on the renderer's device, with per-view sky and validity masks, and (unless
    `prior_weights` is False: evaluation renders and never weighs a prior) the per-pixel prior weights."""

    def __init__(
        self,
        views: Views,
        params: TrainParams,
        device: str,
        train_ids: Sequence[int] | None = None,
        prior_weights: bool = True,
    ) -> None:
        frames = np.asarray(views.frames)
        frames = frames.astype(np.float32) / 255.0 if frames.dtype == np.uint8 else frames.astype(np.float32)
        self.frames = torch.from_numpy(frames).to(device)
        self.w2c = torch.from_numpy(np.asarray(views.w2c, dtype=np.float32)).to(device)
        self.K = [torch.from_numpy(np.asarray(views.K_of(i), dtype=np.float32)).to(device) for i in range(len(views))]
        t, h, w = frames.shape[:3]
        self.depth = None if views.prior_depth is None else torch.from_numpy(views.prior_depth.astype(np.float32))
        aligned = np.ones(t, bool) if views.prior_aligned is None else np.asarray(views.prior_aligned, bool)
        self.aligned = torch.from_numpy(aligned.copy()).to(device)
        self.normals = None if views.prior_normals is None else torch.from_numpy(views.prior_normals.astype(np.float32))
        sky = np.zeros((t, h, w), bool) if views.sky is None else np.asarray(views.sky, bool).copy()
        if params.sky_from_invalid_prior and views.prior_depth is not None:
            with np.errstate(invalid="ignore"):
                sky |= ~(np.isfinite(views.prior_depth) & (views.prior_depth > 0))
        # per view with superseded pixels, the weights that leave them out of every term (a later segment's
        # frames show the world there); the other views take the unweighted loss, which is cheaper
        self.keep: dict[int, torch.Tensor] = {}
        if views.superseded is not None:
            superseded = np.asarray(views.superseded, bool)
            sky &= ~superseded  # the sky an older frame shows where the world now has something
            for i in np.flatnonzero(superseded.any(axis=(1, 2))):
                self.keep[int(i)] = torch.from_numpy((~superseded[i]).astype(np.float32)).to(device)
        self.sky = torch.from_numpy(sky).to(device)
        valid = ~sky if views.masks is None else (np.asarray(views.masks, bool) & ~sky)
        self.valid = torch.from_numpy(valid).to(device)
        if self.depth is not None:
            self.depth = self.depth.to(device)
        if self.normals is not None:
            self.normals = self.normals.to(device)
        self.height, self.width = h, w
        self.prior_weight = None
        ref = params.loss.prior_texture_ref
        if prior_weights and ref is not None and (self.depth is not None or self.normals is not None):
            self.prior_weight = torch.stack([texture_weight(f, ref) for f in self.frames])
            if params.loss.prior_parallax_ref is not None and self.depth is not None:
                self._gate_by_parallax(params.loss.prior_parallax_ref, train_ids)

    def _gate_by_parallax(self, ref: float, train_ids: Sequence[int] | None) -> None:
        """Texture weights only as far as the training views determine the surface (`splats.parallax`); frames
        whose prior is not aligned (its depth's scale unknown) keep their texture weights."""
        ids = list(range(len(self.frames))) if train_ids is None else list(train_ids)
        others, others_K = self.w2c[ids], torch.stack([self.K[j] for j in ids])
        for i in range(len(self.frames)):
            if bool(self.aligned[i]):
                err = triangulation_error(self.depth[i], self.K[i], self.w2c[i], others, others_K)
                self.prior_weight[i] = parallax_gate(self.prior_weight[i], err, ref)

    def sky_colour(self) -> np.ndarray | None:
        if not bool(self.sky.any()):
            return None
        return self.frames[self.sky].median(dim=0).values.cpu().numpy()


def _render_view(model: GaussianModel, data: _Data, i: int, renderer: Renderer, params: TrainParams, sky, sh: int):
    """Render view i with the sky behind: a colour (3,) the renderer composites, or a map composited here."""
    rgb, depth, alpha, normals, info = renderer(
        model.means,
        model.quats,
        torch.exp(model.log_scales),
        torch.sigmoid(model.logit_opacities),
        torch.cat([model.sh0, model.shN], dim=1),
        data.w2c[i],
        data.K[i],
        data.width,
        data.height,
        near=params.near,
        far=params.far,
        background=None if is_map(sky) else sky,
        sh_degree=sh,
    )
    if is_map(sky):
        rgb = composite(rgb, alpha, sky, data.w2c[i], data.K[i])
    return rgb, depth, alpha, normals, info


def _blurred_like_the_video(
    rgb: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor, data: _Data, i: int, params: TrainParams, gap: int
) -> torch.Tensor:
    """The render of view i smeared along its image motion over the shutter (`wonderverse.splats.motion_blur`):
    the velocity from the neighbouring views, `gap` frames apart, and the render's own depth (no gradient)."""
    a, b = max(i - 1, 0), min(i + 1, len(data.w2c) - 1)
    with torch.no_grad():
        a_ = alpha[..., 0]
        z = depth[..., 0] / a_.clamp_min(1e-6)
        vel = image_velocity(z, a_, data.w2c[i], data.w2c[a], data.w2c[b], (b - a) * gap, data.K[i])
    return smear(rgb, vel, params.motion_blur_shutter, params.motion_blur_samples, params.motion_blur_max_px)


_FAR_DEPTH = 1e4  # camera z given to pixels with little rendered alpha (sky): warped as if at infinity
_MIN_ALPHA = 0.1  # below this rendered alpha a pixel's depth Σ w z / alpha is too thin to place it


def nearest_views(i: int, train_ids: Sequence[int], count: int) -> list[int]:
    """The `count` training views nearest view i in the video order (ties: the earlier first), i itself excluded:
    the frames that see most of what view i sees."""
    return sorted((j for j in train_ids if j != i), key=lambda j: (abs(j - i), j))[:count]


def _robust(
    rgb: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    data: _Data,
    i: int,
    params: TrainParams,
    step: int,
    train_ids: Sequence[int],
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The robust photometric weights of a training step on view i and their outlier mask, both (H,W); before
    `robust.start_frac` of the iterations every pixel weighs 1. (None, None) when the robust loss is off.

    `test: cross_view`: frame i against the nearest `neighbours` training frames warped into it by the rendered
    depth (`losses.cross_view_residual`), from `confirm_from_frac` of the iterations on kept only where the render
    disagrees too (`losses.confirmed_by_render`); nothing is kept across steps (checkpoints need no state), and
    held-out frames are never looked at. `test: render`: frame i against the render (`losses.robust_weights`)."""
    rp = params.loss.robust
    if not rp.enabled:
        return None, None
    if step < rp.start_frac * params.iterations:  # ones of the same shape: a compiled loss is traced once
        return torch.ones_like(rgb[..., 0]), torch.zeros_like(rgb[..., 0], dtype=torch.bool)
    with torch.no_grad():
        if rp.test == "render":
            return robust_weights(rgb.detach(), data.frames[i], rp)
        a = alpha.detach()[..., 0]
        z = torch.where(a > _MIN_ALPHA, depth.detach()[..., 0] / a.clamp_min(1e-6), _FAR_DEPTH)
        weights, mask = _cross_view(data.frames, data.K, data.w2c, i, z, train_ids, rp)
        if rp.confirm_from_frac is not None and step >= rp.confirm_from_frac * params.iterations:
            mask = confirmed_by_render(mask, rgb.detach(), data.frames[i], rp)
            weights = outlier_weights(mask, rp, weights.dtype)
        return weights, mask


def _cross_view(
    frames: torch.Tensor,
    K: Sequence[torch.Tensor],
    w2c: torch.Tensor,
    i: int,
    depth: torch.Tensor,
    train_ids: Sequence[int],
    rp: RobustLossParams,
) -> tuple[torch.Tensor, torch.Tensor]:
    """`losses.outlier_blobs` of frame i's disagreement with its nearest training frames warped into it by the
    camera-z `depth` (H,W); every pixel kept where fewer than two other training views exist."""
    others = nearest_views(i, train_ids, rp.neighbours)
    if len(others) < 2:
        return torch.ones_like(depth), torch.zeros_like(depth, dtype=torch.bool)
    warped, valid = warp_frames(depth, K[i], w2c[i], frames[others], torch.stack([K[j] for j in others]), w2c[others])
    return outlier_blobs(cross_view_residual(frames[i], warped, valid), rp)


@torch.no_grad()
def prior_outlier_masks(views: Views, train_ids: Sequence[int], rp: RobustLossParams) -> np.ndarray:
    """Outlier masks (T,H,W) bool of every view, by the cross-view test (`rp`, whatever its `test`) on the depth
    prior instead of a render: for seeding, before any Gaussian exists. A mover's pixels seed Gaussians at the
    mover's depth (or, coloured by the mover, at the world's) that the loss then has to remove: drop them. Views
    without a prior, and pixels whose prior is invalid (sky), are warped as if at infinity. Frames compared with
    are training views only."""
    frames = np.asarray(views.frames)
    f = torch.from_numpy(frames.astype(np.float32) / 255.0 if frames.dtype == np.uint8 else frames.astype(np.float32))
    w2c = torch.from_numpy(np.asarray(views.w2c, np.float32))
    K = [torch.from_numpy(np.asarray(views.K_of(i), np.float32)) for i in range(len(views))]
    out = np.zeros(frames.shape[:3], bool)
    for i in range(len(views)):
        z = np.full(frames.shape[1:3], _FAR_DEPTH, np.float32)
        if views.prior_depth is not None:
            with np.errstate(invalid="ignore"):
                ok = np.isfinite(views.prior_depth[i]) & (views.prior_depth[i] > 0)
            z[ok] = views.prior_depth[i][ok]
        out[i] = _cross_view(f, K, w2c, i, torch.from_numpy(z), train_ids, rp)[1].numpy()
    return out


@torch.no_grad()
def outlier_masks(
    model: GaussianModel,
    views: Views,
    indices: Sequence[int],
    train_ids: Sequence[int],
    renderer: Renderer,
    params: TrainParams,
    background: torch.Tensor,
) -> dict[int, np.ndarray]:
    """The outlier masks (H,W) bool the robust loss gives up on in views `indices` with the model as it is (the
    last steps' masks, for reports and benchmarks), whatever `robust.start_frac` says; empty when it is off."""
    if not params.loss.robust.enabled:
        return {}
    data = _Data(views, params, renderer.device, prior_weights=False)
    sh = min(params.sh_degree, model.sh_degree)
    out = {}
    for i in indices:
        rgb, depth, alpha, _, _ = _render_view(model, data, i, renderer, params, background, sh)
        _, mask = _robust(rgb, depth, alpha, data, i, params, params.iterations, train_ids)
        out[int(i)] = mask.cpu().numpy()
    return out


def view_order(train_ids: list[int], focus: Sequence[tuple[Collection[int], float]], gen: torch.Generator) -> list[int]:
    """One shuffled pass over `train_ids` (popped from the end). Each (views, share) of `focus` is repeated so that
    about `share` of the pass is its views' (a view counts in the first group it is in); every other view appears
    once. With no other view, or no share left for them, there is nothing to favour a group over: one plain pass."""
    ids = list(train_ids)
    groups, taken = [], set()
    for views, share in focus:
        members = set(views)  # a continuation's groups are lists: one pass over `ids`, not one per member
        mine = [i for i in ids if i in members and i not in taken]
        taken.update(mine)
        if mine and share > 0:
            groups.append((mine, share))
    rest, rest_share = len(ids) - sum(len(m) for m, _ in groups), 1.0 - sum(s for _, s in groups)
    if groups and rest > 0 and rest_share > 0:
        for mine, share in groups:
            ids += mine * (max(1, round(share / rest_share * rest / len(mine))) - 1)
    return [ids[j] for j in torch.randperm(len(ids), generator=gen).tolist()]


def loss_and_grads(
    rgb: torch.Tensor,
    gt_rgb: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    normals: torch.Tensor,
    params: LossParams,
    *,
    prior_depth: torch.Tensor | None,
    prior_normals: torch.Tensor | None,
    valid: torch.Tensor,
    sky: torch.Tensor,
    sky_alpha_weight: float,
    K: torch.Tensor | None = None,
    prior_weight: torch.Tensor | None = None,
    prior_scale: torch.Tensor | float = 1.0,
    prior_aligned: torch.Tensor | bool = True,
    rgb_weight: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor], tuple[torch.Tensor, ...]]:
    """(loss, its terms, its gradients with respect to rgb, depth, alpha and normals) of a training step:
    `total_loss` plus `sky_alpha_weight` x the mean alpha over the `sky` pixels (0 on a view without sky).

    Differentiated by torch.func instead of autograd: compiled on a GPU it is one CUDA graph replayed once
    a step, where the loss under autograd was two (forward, backward), each with its own host cost. The
    training step then back-propagates these gradients through the render."""

    def loss_of(rgb: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor, normals: torch.Tensor):
        loss, terms = total_loss(
            rgb=rgb,
            gt_rgb=gt_rgb,
            depth=depth,
            alpha=alpha,
            normals=normals,
            params=params,
            prior_depth=prior_depth,
            prior_normals=prior_normals,
            depth_valid=valid,
            normal_valid=valid,
            K=K,
            prior_weight=prior_weight,
            prior_scale=prior_scale,
            prior_aligned=prior_aligned,
            rgb_weight=rgb_weight,
        )
        if sky_alpha_weight > 0:
            terms["sky_alpha"] = masked_mean(alpha[..., 0], sky)
            loss = loss + sky_alpha_weight * terms["sky_alpha"]
        return loss, (loss.detach(), terms)

    grads, (loss, terms) = torch.func.grad(loss_of, argnums=(0, 1, 2, 3), has_aux=True)(rgb, depth, alpha, normals)
    return loss, terms, grads


def _found_inf(loss: torch.Tensor, params: list[torch.Tensor]) -> torch.Tensor:
    """0-d float32 device tensor: 1 when the loss or any gradient is NaN/inf, else 0 (no host sync).

    One fused check over every tensor: AMP's non-finite check with a scale of 1, which multiplies the
    tensors by 1 in place (a no-op on the gradients; the loss goes in as a copy: it may live in a CUDA
    graph's memory)."""
    grads = [p.grad for p in params if p.grad is not None and p.grad.numel()]
    tensors = [loss.detach().float().reshape(1).clone(), *grads]
    found = torch.zeros((), dtype=torch.float32, device=loss.device)
    torch._amp_foreach_non_finite_check_and_unscale_(tensors, found, torch.ones((), device=loss.device))
    return found


def _make_adam(params: dict[str, torch.Tensor], lrs: dict[str, float], eps: float = 1e-15) -> torch.optim.Adam:
    """One Adam over named param groups, stepped by `adam_step`. fused: its kernel honours `found_inf`, how
    a non-finite step is skipped."""
    groups = [{"params": [p], "lr": lrs[k], "name": k} for k, p in params.items()]
    return torch.optim.Adam(groups, eps=eps, fused=True)


def adam_step(optimizers: Collection[torch.optim.Adam], found_inf: torch.Tensor) -> None:
    """`Adam.step()` of fused Adams, all their groups at once: one step-count update, one fused kernel per
    group and one undo of the count where `found_inf` (no sync). The same state as `Adam.step()` with
    `found_inf` set (tested), for a tenth of its host time: torch's step sorts tensors by device and dtype
    and builds per-group lists on every call, which with one tensor per group costs more than the kernels."""
    steps: list[torch.Tensor] = []
    calls = []
    for opt in optimizers:
        for g in opt.param_groups:
            params = [p for p in g["params"] if p.grad is not None]
            if not params:
                continue
            for p in params:
                st = opt.state[p]
                if not st:  # as torch initialises it (fused: a float32 step on the parameter's device)
                    st["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                    st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            sts = [opt.state[p] for p in params]
            steps += [st["step"] for st in sts]
            calls.append((g, params, sts))
    if not calls:
        return
    torch._foreach_add_(steps, 1)
    for g, params, sts in calls:
        beta1, beta2 = g["betas"]
        torch._fused_adam_(
            params,
            [p.grad for p in params],
            [st["exp_avg"] for st in sts],
            [st["exp_avg_sq"] for st in sts],
            [],
            [st["step"] for st in sts],
            lr=g["lr"],
            beta1=beta1,
            beta2=beta2,
            weight_decay=g["weight_decay"],
            eps=g["eps"],
            amsgrad=False,
            maximize=False,
            grad_scale=None,
            found_inf=found_inf,
        )
    torch._foreach_sub_(steps, [found_inf] * len(steps))


@dataclass
class _Pending:
    """One step's loss terms, still on the device (`values`, stacked in `names` order), and host figures."""

    step: int
    names: list[str]
    values: torch.Tensor
    host: dict[str, float]


def _flush(pending: list[_Pending], curves: dict[str, list[float]]) -> None:
    """Copy the queued per-step terms to `curves` in one transfer; skipped steps are logged, not recorded."""
    if not pending:
        return
    flat = torch.cat([p.values.double() for p in pending]).cpu().tolist()
    at = 0
    for p in pending:
        values = dict(zip(p.names, flat[at : at + len(p.names)], strict=True))
        at += len(p.names)
        if values.pop("_skipped") > 0:
            log.warning("splat training step %d: non-finite loss or gradients; step skipped", p.step)
            curves.setdefault("skipped", []).append(float(p.step))
            continue
        for k, v in (values | p.host).items():
            curves.setdefault(k, []).append(v)
    pending.clear()


@torch.no_grad()
def evaluate(
    model: GaussianModel,
    views: Views,
    indices: list[int],
    renderer: Renderer,
    params: TrainParams,
    background,
    view_gap: int = 1,
    per_view: bool = False,
    keep: Mapping[int, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Mean PSNR / SSIM (wonderverse.metrics) of the renders of `indices` against their frames; with
    `motion_blur_shutter` the renders are smeared as the camera smeared the frames (`train`'s view_gap).
    With `per_view`, also `psnr_views` and `ssim_views`: each view's figure, in the order of `indices`. With
    `keep` (view index -> (H,W) bool at the views' size), also `psnr_kept_views`: each view's PSNR over the pixels
    it keeps (all of them for a view not in `keep`; NaN for one that keeps none)."""
    from wonderverse.metrics import psnr, ssim

    if not indices:
        return {}
    data = _Data(views, params, renderer.device, prior_weights=False)
    sh = min(params.sh_degree, model.sh_degree)
    ps, ss, kept = [], [], []
    for i in indices:
        rgb, depth, alpha, _, _ = _render_view(model, data, i, renderer, params, background, sh)
        if params.motion_blur_shutter > 0:
            rgb = _blurred_like_the_video(rgb, depth, alpha, data, i, params, view_gap)
        rgb = rgb.clamp(0, 1).cpu().numpy()
        gt = data.frames[i].cpu().numpy()
        ps.append(psnr(rgb, gt))
        if keep is not None:
            mask = keep.get(i, np.ones(rgb.shape[:2], bool))
            kept.append(psnr(rgb[mask], gt[mask]) if mask.any() else float("nan"))
        if min(rgb.shape[:2]) >= 11:
            ss.append(ssim(rgb, gt))
    out: dict[str, Any] = {"psnr": float(np.mean(ps))}
    if ss:
        out["ssim"] = float(np.mean(ss))
    if per_view:
        out |= {"psnr_views": [float(x) for x in ps], "ssim_views": [float(x) for x in ss]}
    if keep is not None:
        out["psnr_kept_views"] = [float(x) for x in kept]
    return out


def _sky_shape(params: TrainParams) -> tuple[int, ...]:
    rows = params.sky_map_rows
    return (rows, 2 * rows, 3) if rows else (3,)


def train(
    model: GaussianModel,
    views: Views,
    params: TrainParams,
    renderer: Renderer,
    checkpoint_cb: Callable[[int, dict[str, Any]], None] | None = None,
    resume_state: dict[str, Any] | None = None,
    fixed_gaussians: int = 0,
    focus: Sequence[tuple[Collection[int], float]] = (),
    progress: ProgressFn | None = None,
    view_gap: int = 1,
    test_views: Sequence[int] | None = None,
    sky_start: np.ndarray | None = None,
    frozen_gaussians: int = 0,
) -> tuple[GaussianModel, dict[str, list[float]], dict[str, Any]]:
    """Optimise `model` on `views` (see the module docstring). Returns (model, curves, metrics).

    curves: per iteration lists of every loss term, n_gaussians and step seconds ("skipped" marks steps
    with non-finite gradients). metrics: test/train PSNR and SSIM, view split, final Gaussian count, time.
    checkpoint_cb(step, state) is called every `checkpoint_every_iters` iterations and at the end; passing
    such a state as `resume_state` continues training from it (same views and params). The first
    `fixed_gaussians` Gaussians (an extended scene's existing ones) are optimised but never densified;
    each (views, share) of `focus` takes about `share` of the steps (an extension's new frames, and the old ones
    that see what they see), see `view_order`.
    Consecutive views are `view_gap` video frames apart (the motion-blur model's frame interval).
    `test_views`: the views held out (indices; None: every `holdout_every`-th, `split_views`). `sky_start`: the sky
    to start from, (3,) or a (R, 2R, 3) map (a continued scene's; None: from the sky pixels or `background_rgb`).
    The first `frozen_gaussians` (≤ `fixed_gaussians`) are rendered but never change (their gradients are zeroed:
    Adam, starting from zero moments, then moves them by exactly 0): Gaussians an extension's region shares with
    old views it does not train on.
    progress(iterations done, iterations, "loss 0.0521, 21468 Gaussians") is called at the start, about every
    1 % of the iterations and at the end; the loss is the last one copied to the host (module docstring).
    """
    report = progress or no_progress
    device = renderer.device
    model = model.to(device)
    if test_views is None:
        train_ids, test_ids = split_views(len(views), params.holdout_every)
    else:
        test_ids = sorted(set(test_views))
        train_ids = [i for i in range(len(views)) if i not in set(test_ids)]
    data = _Data(views, params, device, train_ids)
    if not train_ids:
        raise ValueError("no views to train on")
    gen = torch.Generator().manual_seed(params.seed)
    torch.manual_seed(params.seed)
    if params.background_rgb is not None:
        bg0 = np.asarray(params.background_rgb, np.float32)
    else:
        sky = data.sky_colour()
        bg0 = sky if sky is not None else np.zeros(3, np.float32)
    if sky_start is not None and sky_start.shape == _sky_shape(params):
        bg0 = sky_start
    else:
        bg0 = initial_sky(bg0, params.sky_map_rows)
    background = torch.nn.Parameter(torch.tensor(np.asarray(bg0, np.float32), device=device))
    scene_scale = params.scene_scale
    if resume_state is not None and "scene_scale" in resume_state:
        scene_scale = float(resume_state["scene_scale"])
    if scene_scale is None:
        scene_scale = auto_scene_scale(views.w2c, model.means.detach().cpu().numpy())
    lrs = {
        "means": _lr_means(params, scene_scale, 0),
        "quats": params.lr_quats,
        "log_scales": params.lr_log_scales,
        "logit_opacities": params.lr_logit_opacities,
        "sh0": params.lr_sh0,
        "shN": params.lr_shN,
    }
    pdict = model.param_dict()
    optimizer = _make_adam(pdict, lrs)
    optimizers = dict.fromkeys(pdict, optimizer)  # the strategies' view: each tensor's optimiser
    bg_lr = params.lr_background if params.learn_background else 0.0
    bg_opt = _make_adam({"background": background}, {"background": bg_lr}, eps=1e-8)
    strategy = make_strategy(params.strategy)
    strategy_state = strategy.initialize_state(scene_scale, fixed_gaussians) if strategy is not None else {}
    curves: dict[str, list[float]] = {}
    start = 0
    if resume_state is not None:
        start = int(resume_state["step"])
        restored = GaussianModel.from_numpy(resume_state["params"], sh_degree=model.sh_degree).to(device)
        model.replace_params(restored.param_dict())
        pdict = model.param_dict()
        optimizer = _make_adam(pdict, lrs)
        optimizers = dict.fromkeys(pdict, optimizer)
        optimizer.load_state_dict(resume_state["optimizer"])
        background.data.copy_(torch.as_tensor(resume_state["background"]))
        bg_opt.load_state_dict(resume_state["bg_optimizer"])
        strategy_state = dict(resume_state["strategy_state"])
        curves = {k: list(v) for k, v in resume_state["curves"].items()}
        gen.set_state(resume_state["rng_views"])
        torch.set_rng_state(resume_state["rng_torch"])
    order: list[int] = []
    if resume_state is not None:
        order = list(resume_state["order"])

    def snapshot(step: int) -> dict[str, Any]:
        return {
            "step": step,
            "scene_scale": scene_scale,
            "params": model.to_numpy(),
            # Deep copies: a state_dict holds the live moment tensors, which later steps update in place.
            "optimizer": copy.deepcopy(optimizer.state_dict()),
            "background": background.detach().cpu().numpy().copy(),
            "bg_optimizer": copy.deepcopy(bg_opt.state_dict()),
            "strategy_state": {k: (v.clone() if torch.is_tensor(v) else v) for k, v in strategy_state.items()},
            "curves": {k: list(v) for k, v in curves.items()},
            "rng_views": gen.get_state(),
            "rng_torch": torch.get_rng_state(),
            "order": list(order),
        }

    has_sky = bool(data.sky.any())
    prior_scale = torch.ones((), device=device)  # a tensor, so the compiled loss is not re-traced as it changes
    # CUDA graphs: the loss sees image-sized tensors only, whose shapes never change during a run
    loss_fn = Compiled(
        loss_and_grads, enabled=params.compile_loss and torch.device(device).type == "cuda", cuda_graphs=True
    )
    pending: list[_Pending] = []
    report_every = max(1, params.iterations // 100)

    def report_at(step: int) -> None:
        loss = curves.get("total")
        note = f"loss {loss[-1]:.4f}, " if loss else ""
        report(step, params.iterations, f"{note}{model.num_gaussians} Gaussians")

    report_at(start)
    t_start = time.perf_counter()
    for step in range(start, params.iterations):
        t0 = time.perf_counter()
        if not order:
            order = view_order(train_ids, focus, gen)
        i = order.pop()
        lr_m = _lr_means(params, scene_scale, step)
        for g in optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = lr_m
        sh = min(step // params.sh_degree_interval_iters, params.sh_degree, model.sh_degree)
        rgb, depth, alpha, normals, info = _render_view(model, data, i, renderer, params, background, sh)
        if params.motion_blur_shutter > 0:
            rgb = _blurred_like_the_video(rgb, depth, alpha, data, i, params, view_gap)
        if strategy is not None and model.num_gaussians:
            strategy.step_pre_backward(pdict, optimizers, strategy_state, step, info)
        rgb_weight, outliers = _robust(rgb, depth, alpha, data, i, params, step, train_ids)
        if i in data.keep:
            rgb_weight = data.keep[i] if rgb_weight is None else rgb_weight * data.keep[i]
        loss, terms, grads = loss_fn(
            rgb.detach(),
            data.frames[i],
            depth.detach(),
            alpha.detach(),
            normals.detach(),
            params.loss,
            prior_depth=None if data.depth is None else data.depth[i],
            prior_normals=None if data.normals is None else data.normals[i],
            valid=data.valid[i],
            sky=data.sky[i],
            sky_alpha_weight=params.sky_alpha_weight if has_sky else 0.0,
            K=data.K[i],
            prior_weight=None if data.prior_weight is None else data.prior_weight[i],
            prior_scale=prior_scale.fill_(prior_schedule(params, step)),
            prior_aligned=data.aligned[i],
            rgb_weight=rgb_weight,
        )
        if outliers is not None:
            terms["outlier_share"] = outliers.float().mean()
        # back-propagate the loss's gradients through the render (and the strategy's own terms)
        renders = (rgb, depth, alpha, normals)
        tensors = [r for r in renders if r.requires_grad]
        grad_tensors = [g for r, g in zip(renders, grads, strict=True) if r.requires_grad]
        reg = None if strategy is None else strategy.regularization(pdict)
        if params.loss.lambda_flatten > 0 and model.num_gaussians:
            flat = params.loss.lambda_flatten * flatten_loss(pdict["log_scales"])
            terms["flatten"] = flat.detach()
            reg = flat if reg is None else reg + flat
        if reg is not None:
            tensors.append(reg)
            grad_tensors.append(torch.ones_like(reg))
            loss = loss + reg.detach()
        if tensors:
            torch.autograd.backward(tensors, grad_tensors)
        trained = [*pdict.values(), background]
        found_inf = _found_inf(loss, trained)
        if frozen_gaussians:
            for p in pdict.values():
                if p.grad is not None:
                    p.grad[:frozen_gaussians] = 0
        adam_step((optimizer, bg_opt), found_inf)  # a non-finite step leaves parameters and moments as they were
        for p in trained:
            p.grad = None
        with torch.no_grad():
            background.clamp_(0.0, 1.0)  # colours: outside [0,1] they would only compensate other errors
        if strategy is not None and model.num_gaussians:
            n_before = model.num_gaussians
            strategy.step_post_backward(pdict, optimizers, strategy_state, step, info, lr=lr_m)
            model.replace_params(pdict)
            pdict = model.param_dict()
            if model.num_gaussians != n_before:
                log.debug("step %d: %d -> %d Gaussians", step, n_before, model.num_gaussians)
        terms |= {"total": loss.detach(), "_skipped": found_inf}
        names = list(terms)
        host = {"n_gaussians": float(model.num_gaussians), "step_s": time.perf_counter() - t0}
        pending.append(_Pending(step, names, torch.stack([terms[k].float() for k in names]), host))
        if len(pending) >= _FLUSH_EVERY:
            _flush(pending, curves)
        if checkpoint_cb is not None and (step + 1) % params.checkpoint_every_iters == 0:
            _flush(pending, curves)
            checkpoint_cb(step + 1, snapshot(step + 1))
        if (step + 1) % report_every == 0 and step + 1 < params.iterations:
            report_at(step + 1)
    _flush(pending, curves)
    report_at(params.iterations)
    if checkpoint_cb is not None and params.iterations % params.checkpoint_every_iters != 0:
        checkpoint_cb(params.iterations, snapshot(params.iterations))
    bg_final = background.detach()
    metrics: dict[str, Any] = {
        "train_views": train_ids,
        "test_views": test_ids,
        "n_gaussians": model.num_gaussians,
        "scene_scale": scene_scale,
        "seconds": time.perf_counter() - t_start,
        "background_rgb": mean_colour(bg_final.cpu().numpy()).tolist(),
        "skipped_steps": len(curves.get("skipped", [])),
    }
    for name, ids in (("test", test_ids), ("train", train_ids[:8])):
        for k, v in evaluate(model, views, ids, renderer, params, bg_final, view_gap, name == "test").items():
            metrics[f"{name}_{k}"] = v
    if is_map(bg_final):
        metrics["sky_map"] = bg_final.cpu().numpy()
    return model, curves, metrics
