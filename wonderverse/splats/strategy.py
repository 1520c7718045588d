"""Densification strategies (own code, gsplat's `Strategy` shape): small dataclasses with the hooks
`initialize_state()`, `step_pre_backward(params, optimizers, state, step, info)` and
`step_post_backward(params, optimizers, state, step, info, ...)`.

`params` maps names to nn.Parameters in `GaussianModel` naming (means, quats, log_scales, logit_opacities,
sh0, shN); `optimizers` maps the same names to optimisers with one param group holding that tensor. The
hooks replace entries of `params` (and the tensors inside the optimisers, with their moment estimates
kept for surviving Gaussians and zeroed for new ones) whenever the number of Gaussians changes; the caller
re-installs `params` into its model (`GaussianModel.replace_params`). `info` is the renderer's info dict
(`means2d` (1,N,2) graph node, `radii` (N,2), `width`, `height`, `n_cameras`).

* `DefaultStrategy`: 3DGS adaptive density control: clone small / split large Gaussians whose mean
  view-space gradient is high, prune transparent and oversized ones, and reset opacities periodically.
  (gsplat 1.5.3's DefaultStrategy tests `step % reset_every == 0 & step > 0`, which Python parses as
  `step % reset_every == (0 & step) > 0`, always False: it never resets. Ours does.) An optional
  Gaussian budget caps growth, keeping the highest-gradient candidates.
* `MCMCStrategy`: 3DGS-as-MCMC: a fixed budget filled gradually (+5% per refinement up to `cap_max`),
  dead Gaussians relocated onto live ones sampled by opacity (opacity and scale corrected so the stack
  renders like the original), and noise on the positions of transparent Gaussians every step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from wonderverse.splats import triton_kernels
from wonderverse.splats.model import quat_to_rotmat

Params = dict[str, nn.Parameter]
Optimizers = dict[str, torch.optim.Optimizer]


def _replace(
    params: Params,
    optimizers: Optimizers,
    param_fn: Callable[[str, Tensor], Tensor],
    state_fn: Callable[[str, Tensor], Tensor],
) -> None:
    """Swap every parameter for `param_fn(name, p)` and each optimiser moment for `state_fn(key, v)`."""
    for name in list(params):
        old = params[name]
        new = nn.Parameter(param_fn(name, old.data), requires_grad=old.requires_grad)
        params[name] = new
        opt = optimizers.get(name)
        if opt is None:
            continue
        for group in opt.param_groups:
            if not any(p is old for p in group["params"]):
                continue
            st = opt.state.pop(old, {})
            for key, v in list(st.items()):
                if key != "step" and isinstance(v, Tensor) and v.dim() > 0:
                    st[key] = state_fn(key, v)
            group["params"] = [new if p is old else p for p in group["params"]]
            if st:
                opt.state[new] = st


def keep_only(params: Params, optimizers: Optimizers, keep: Tensor) -> None:
    """Drop the Gaussians where `keep` (N,) is False."""
    idx = torch.nonzero(keep)[:, 0]
    _replace(params, optimizers, lambda _n, p: p[idx], lambda _k, v: v[idx])


def append_copies(params: Params, optimizers: Optimizers, src: Tensor, new_values: dict[str, Tensor]) -> None:
    """Append copies of Gaussians `src` (M,) int, with `new_values[name]` (M,...) replacing the copied values
    where given; their optimiser moments start at zero."""

    def param_fn(name: str, p: Tensor) -> Tensor:
        return torch.cat([p, new_values[name] if name in new_values else p[src]])

    def state_fn(_key: str, v: Tensor) -> Tensor:
        return torch.cat([v, torch.zeros((len(src), *v.shape[1:]), dtype=v.dtype, device=v.device)])

    _replace(params, optimizers, param_fn, state_fn)


def set_values(params: Params, optimizers: Optimizers, idx: Tensor, values: dict[str, Tensor]) -> None:
    """Overwrite Gaussians `idx` with `values[name]` (or copy them from `values['_src']` indices) and zero
    their optimiser moments."""
    src = values.get("_src")

    def param_fn(name: str, p: Tensor) -> Tensor:
        out = p.clone()
        if name in values:
            out[idx] = values[name]
        elif src is not None:
            out[idx] = p[src]
        return out

    def state_fn(_key: str, v: Tensor) -> Tensor:
        out = v.clone()
        out[idx] = 0
        return out

    _replace(params, optimizers, param_fn, state_fn)


def _accumulate_grad2d(
    g: Tensor, radii: Tensor, grad2d: Tensor, count: Tensor, ndc_x: float, ndc_y: float
) -> tuple[Tensor, Tensor]:
    """(grad2d, count) plus this step's |d loss / d means2d| in NDC units (`g` (N,2) pixels times `ndc_x`,
    `ndc_y`) of the Gaussians visible with a finite gradient. Fixed shapes: no host sync."""
    norms = torch.sqrt((g[:, 0] * ndc_x) ** 2 + (g[:, 1] * ndc_y) ** 2)
    counted = (radii > 0).all(-1) & torch.isfinite(norms)
    return grad2d + torch.where(counted, norms, 0.0), count + counted


def accumulate_view_space_grads(info: dict[str, Any], state: dict[str, Any]) -> None:
    """Add this step's view-space gradient norms of the visible Gaussians to `state` grad2d / count."""
    g = info["means2d"].grad
    if g is None:
        raise RuntimeError("means2d has no gradient: call step_pre_backward before loss.backward()")
    # Pixels -> normalised device coordinates (as 3DGS): the thresholds are resolution-independent.
    n_cam = info.get("n_cameras", 1)
    # on CUDA one Triton kernel, in place, instead of a dozen launches (the step waits on launches there)
    fn = triton_kernels.accumulate_grad2d if g.is_cuda and triton_kernels.available() else _accumulate_grad2d
    state["grad2d"], state["count"] = fn(
        g.detach().reshape(-1, 2),
        info["radii"].reshape(-1, 2),
        state["grad2d"],
        state["count"],
        info["width"] / 2.0 * n_cam,
        info["height"] / 2.0 * n_cam,
    )


@dataclass
class DefaultStrategy:
    """3DGS adaptive density control. Scales are compared with `scene_scale` (1 in the normalised frame).

    prune_opa: opacity below which Gaussians are removed; grow_grad2d: mean NDC gradient above which they
    grow; grow_scale3d: largest axis (relative to the scene scale) below which they are cloned, above
    which split; prune_scale3d: largest axis above which they are removed (after the first reset);
    reset_opacity: opacities are clamped to this every `reset_every` steps (0 disables); max_gaussians:
    the budget (None = unlimited); split_factor: a split child's scale = parent / this.
    """

    prune_opa: float = 0.005
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    prune_scale3d: float = 0.1
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    pause_refine_after_reset: int = 0
    reset_opacity: float = 0.01
    max_gaussians: int | None = None
    split_factor: float = 1.6

    def initialize_state(self, scene_scale: float = 1.0, n_fixed: int = 0) -> dict[str, Any]:
        """n_fixed: the first n Gaussians (an extended scene's existing ones) are never grown, pruned or reset."""
        return {"grad2d": None, "count": None, "scene_scale": scene_scale, "n_fixed": n_fixed}

    def regularization(self, params: Params) -> Tensor | None:
        """Extra loss terms this strategy needs (none)."""
        return None

    def step_pre_backward(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int, info: dict[str, Any]
    ) -> None:
        info["means2d"].retain_grad()

    def step_post_backward(
        self,
        params: Params,
        optimizers: Optimizers,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        lr: float | None = None,
    ) -> dict[str, int]:
        """Accumulate gradients; refine every `refine_every` steps; reset opacities. Returns counts of
        Gaussians cloned, split, pruned and whether opacities were reset."""
        stats = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if step >= self.refine_stop_iter:
            return stats
        n = params["means"].shape[0]
        if state["grad2d"] is None or len(state["grad2d"]) != n:
            state["grad2d"] = torch.zeros(n, device=params["means"].device)
            state["count"] = torch.zeros(n, device=params["means"].device)
        accumulate_view_space_grads(info, state)

        if (
            step > self.refine_start_iter
            and step % self.refine_every == 0
            and (self.reset_every <= 0 or step % self.reset_every >= self.pause_refine_after_reset)
        ):
            stats.update(self._grow(params, optimizers, state))
            stats["pruned"] = self._prune(params, optimizers, state, step)
            state["grad2d"] = torch.zeros(params["means"].shape[0], device=params["means"].device)
            state["count"] = torch.zeros_like(state["grad2d"])
        if self.reset_every > 0 and self.reset_opacity > 0 and step > 0 and step % self.reset_every == 0:
            cap = math.log(self.reset_opacity / (1.0 - self.reset_opacity))
            idx = torch.arange(state.get("n_fixed", 0), params["means"].shape[0], device=params["means"].device)
            set_values(params, optimizers, idx, {"logit_opacities": params["logit_opacities"].data[idx].clamp_max(cap)})
            stats["reset"] = 1
        return stats

    @torch.no_grad()
    def _grow(self, params: Params, optimizers: Optimizers, state: dict[str, Any]) -> dict[str, int]:
        grads = state["grad2d"] / state["count"].clamp_min(1)
        high = grads > self.grow_grad2d
        high[: state.get("n_fixed", 0)] = False  # an extension densifies only the new region
        small = torch.exp(params["log_scales"]).amax(-1) <= self.grow_scale3d * state["scene_scale"]
        clone = high & small
        split = high & ~small
        if self.max_gaussians is not None:
            room = max(self.max_gaussians - params["means"].shape[0], 0)
            cand = torch.nonzero(clone | split)[:, 0]
            if len(cand) > room:  # keep the strongest candidates that fit in the budget
                keep = cand[torch.argsort(grads[cand], descending=True)[:room]]
                chosen = torch.zeros_like(clone)
                chosen[keep] = True
                clone &= chosen
                split &= chosen
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone:
            append_copies(params, optimizers, torch.nonzero(clone)[:, 0], {})
            split = torch.cat([split, torch.zeros(n_clone, dtype=torch.bool, device=split.device)])
        if n_split:
            self._split(params, optimizers, split)
        return {"cloned": n_clone, "split": n_split}

    def _split(self, params: Params, optimizers: Optimizers, split: Tensor) -> None:
        """Replace each selected Gaussian by two, drawn from it, with scales / split_factor."""
        src = torch.nonzero(split)[:, 0]
        src2 = torch.cat([src, src])
        scales = torch.exp(params["log_scales"].data[src2])
        R = quat_to_rotmat(params["quats"].data[src2])
        offsets = (R @ (scales * torch.randn_like(scales))[..., None])[..., 0]
        new = {
            "means": params["means"].data[src2] + offsets,
            "log_scales": torch.log(scales / self.split_factor),
        }
        append_copies(params, optimizers, src2, new)
        keep = torch.ones(params["means"].shape[0], dtype=torch.bool, device=split.device)
        keep[src] = False
        keep_only(params, optimizers, keep)

    @torch.no_grad()
    def _prune(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int) -> int:
        prune = torch.sigmoid(params["logit_opacities"].data) < self.prune_opa
        if step > self.reset_every > 0:
            prune |= torch.exp(params["log_scales"].data).amax(-1) > self.prune_scale3d * state["scene_scale"]
        prune[: state.get("n_fixed", 0)] = False  # so the fixed Gaussians keep the first indices
        n = int(prune.sum())
        if n:
            keep_only(params, optimizers, ~prune)
        return n


def relocation_opacity_scale(
    opacities: Tensor, scales: Tensor, ratios: Tensor, n_max: int = 51
) -> tuple[Tensor, Tensor]:
    """MCMC relocation (Kheradmand et al. 2024, eq. 9): for a Gaussian of opacity o and scales s that
    becomes `ratio` = n identical copies, each copy gets o' = 1 - (1 - o)^(1/n) and s' = s * o / Σ_{i=1..n}
    Σ_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1), so that the stack renders like the original."""
    n = ratios.clamp(1, n_max).to(opacities.dtype)
    new_op = 1.0 - torch.pow(1.0 - opacities, 1.0 / n)
    i = torch.arange(1, n_max + 1, dtype=opacities.dtype, device=opacities.device)
    k = torch.arange(n_max, dtype=opacities.dtype, device=opacities.device)
    binom = torch.exp(torch.lgamma(i[:, None]) - torch.lgamma(k[None, :] + 1) - torch.lgamma(i[:, None] - k[None, :]))
    valid_ik = k[None, :] <= i[:, None] - 1
    coef = torch.where(valid_ik, binom * (-1.0) ** k[None, :] / torch.sqrt(k[None, :] + 1), torch.zeros(()))
    powers = new_op[:, None] ** (k[None, :] + 1)  # (M, n_max)
    per_i = powers @ coef.T  # (M, n_max): inner sum for each i
    use_i = i[None, :] <= n[:, None]
    denom = (per_i * use_i).sum(-1)
    new_scales = scales * (opacities / denom.clamp_min(1e-12))[:, None]
    return new_op, new_scales


@dataclass
class MCMCStrategy:
    """3DGS-as-MCMC with a Gaussian budget `cap_max`. Every `refine_every` steps in
    (refine_start_iter, refine_stop_iter): relocate Gaussians with opacity <= min_opacity onto live ones
    sampled by opacity, then add min(cap_max, growth_rate * N) - N new ones the same way. Every step
    (until refine_stop_iter): position noise lr_means * noise_lr * Σ ε, weighted towards transparent
    Gaussians. Its `regularization` adds opacity_reg * mean(opacity) + scale_reg * mean(scale)."""

    cap_max: int = 200_000
    noise_lr: float = 5e5
    refine_start_iter: int = 500
    refine_stop_iter: int = 25_000
    refine_every: int = 100
    min_opacity: float = 0.005
    growth_rate: float = 1.05
    opacity_reg: float = 0.01
    scale_reg: float = 0.01

    def initialize_state(self, scene_scale: float = 1.0, n_fixed: int = 0) -> dict[str, Any]:
        """n_fixed is not honoured: relocation may move any Gaussian (the budget is what MCMC keeps)."""
        return {"scene_scale": scene_scale}

    def regularization(self, params: Params) -> Tensor:
        if params["means"].shape[0] == 0:
            return params["means"].new_zeros(())
        opacity = torch.sigmoid(params["logit_opacities"]).mean()
        return self.opacity_reg * opacity + self.scale_reg * torch.exp(params["log_scales"]).mean()

    def step_pre_backward(
        self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int, info: dict[str, Any]
    ) -> None:
        pass

    @torch.no_grad()
    def step_post_backward(
        self,
        params: Params,
        optimizers: Optimizers,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        lr: float | None = None,
    ) -> dict[str, int]:
        """Relocate / add (on refinement steps) and inject noise (`lr` = the means' learning rate)."""
        stats = {"relocated": 0, "added": 0}
        if step >= self.refine_stop_iter or params["means"].shape[0] == 0:
            return stats
        if step > self.refine_start_iter and step % self.refine_every == 0:
            stats["relocated"] = self._relocate(params, optimizers)
            stats["added"] = self._add(params, optimizers)
        if lr is not None and lr > 0:
            self._noise(params, lr)
        return stats

    def _sample(self, params: Params, n: int, alive: Tensor) -> Tensor:
        probs = torch.sigmoid(params["logit_opacities"].data) * alive
        return torch.multinomial(probs, n, replacement=True)

    def _copy_targets(self, params: Params, sampled: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Unique sampled sources and their corrected (logit opacity, log scale) for count+1 copies."""
        uniq, counts = torch.unique(sampled, return_counts=True)
        op = torch.sigmoid(params["logit_opacities"].data[uniq])
        sc = torch.exp(params["log_scales"].data[uniq])
        new_op, new_sc = relocation_opacity_scale(op, sc, counts + 1)
        new_op = new_op.clamp(self.min_opacity, 1.0 - 1e-6)
        return uniq, {"logit_opacities": torch.logit(new_op), "log_scales": torch.log(new_sc.clamp_min(1e-12))}

    def _relocate(self, params: Params, optimizers: Optimizers) -> int:
        dead = torch.sigmoid(params["logit_opacities"].data) <= self.min_opacity
        n_dead = int(dead.sum())
        if n_dead == 0 or n_dead == len(dead):
            return 0
        dead_idx = torch.nonzero(dead)[:, 0]
        sampled = self._sample(params, n_dead, ~dead)
        uniq, corrected = self._copy_targets(params, sampled)
        set_values(params, optimizers, uniq, corrected)  # the sources, corrected
        set_values(params, optimizers, dead_idx, {"_src": sampled})  # the dead become copies of them
        return n_dead

    def _add(self, params: Params, optimizers: Optimizers) -> int:
        n = params["means"].shape[0]
        n_new = min(self.cap_max, int(self.growth_rate * n)) - n
        if n_new <= 0:
            return 0
        alive = torch.ones(n, dtype=torch.bool, device=params["means"].device)
        sampled = self._sample(params, n_new, alive)
        uniq, corrected = self._copy_targets(params, sampled)
        set_values(params, optimizers, uniq, corrected)
        append_copies(params, optimizers, sampled, {})
        return n_new

    def _noise(self, params: Params, lr: float) -> None:
        op = torch.sigmoid(params["logit_opacities"].data)
        scales = torch.exp(params["log_scales"].data)
        R = quat_to_rotmat(params["quats"].data)
        cov = R @ torch.diag_embed(scales * scales) @ R.transpose(1, 2)
        # Only nearly transparent Gaussians move noticeably: sigmoid(100 (1 - o - 0.995)).
        weight = torch.sigmoid(100.0 * ((1.0 - op) - 0.995))
        eps = torch.randn_like(params["means"].data) * (weight * lr * self.noise_lr)[:, None]
        params["means"].data.add_((cov @ eps[..., None])[..., 0])
