"""Densification strategies (own code, gsplat's `Strategy` shape): small dataclasses with the hooks
`initialize_state()`, `step_pre_backward(params, optimizers, state, step, info)` and
`step_post_backward(params, optimizers, state, step, info, ...)`, each holding its settings as they are
configured (`splats.params.DefaultStrategyParams`, `MCMCStrategyParams`: gsplat's own field names, nothing
renamed on the way in); `make_strategy(settings)` picks the one their `kind` names.

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
  Gaussian budget (`cap_max`) caps growth, keeping the highest-gradient candidates.
* `MCMCStrategy`: 3DGS-as-MCMC: a fixed budget filled gradually (+5% per refinement up to `cap_max`),
  dead Gaussians relocated onto live ones sampled by opacity (opacity and scale corrected so the stack
  renders like the original), and noise on the positions of transparent Gaussians every step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from wonderverse.splats import triton_kernels
from wonderverse.splats.model import quat_to_rotmat
from wonderverse.splats.params import DefaultStrategyParams, MCMCStrategyParams, NoStrategy, StrategyParams

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
    """Add this step's view-space gradient norms of the visible Gaussians to `state` grad2d / count (and,
    where `state` tracks radii, keep each visible Gaussian's largest 2D radius / image side)."""
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
    if state.get("radii") is not None:
        radii = info["radii"].reshape(-1, 2)
        seen = (radii > 0).all(-1)
        side = radii.amax(-1).to(state["radii"].dtype) / float(max(info["width"], info["height"]))
        state["radii"] = torch.where(seen, torch.maximum(state["radii"], side), state["radii"])


@dataclass(frozen=True)
class DefaultStrategy:
    """3DGS adaptive density control with the settings `params` (gsplat's `DefaultStrategy` field names; see
    `DefaultStrategyParams`). Scales are compared with `scene_scale` (1 in the normalised frame)."""

    params: DefaultStrategyParams = field(default_factory=DefaultStrategyParams)

    def initialize_state(self, scene_scale: float = 1.0, n_fixed: int = 0) -> dict[str, Any]:
        """n_fixed: the first n Gaussians (an extended scene's existing ones) are never grown, pruned or reset.
        With the 2D radius criteria on, `radii` keeps each Gaussian's largest 2D radius / image side."""
        state = {"grad2d": None, "count": None, "scene_scale": scene_scale, "n_fixed": n_fixed}
        if self.params.refine_scale2d_stop_iter > 0:
            state["radii"] = None
        return state

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
        p = self.params
        stats = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if step >= p.refine_stop_iter:
            return stats
        n = params["means"].shape[0]
        if state["grad2d"] is None or len(state["grad2d"]) != n:
            _zero_statistics(state, n, params["means"].device)
        accumulate_view_space_grads(info, state)

        if (
            step > p.refine_start_iter
            and step % p.refine_every == 0
            and (p.reset_every <= 0 or step % p.reset_every >= p.pause_refine_after_reset)
        ):
            stats.update(self._grow(params, optimizers, state, step))
            stats["pruned"] = self._prune(params, optimizers, state, step)
            _zero_statistics(state, params["means"].shape[0], params["means"].device)
        if p.reset_every > 0 and step > 0 and step % p.reset_every == 0:
            cap = math.log(p.reset_opacity / (1.0 - p.reset_opacity))
            idx = torch.arange(state.get("n_fixed", 0), params["means"].shape[0], device=params["means"].device)
            set_values(params, optimizers, idx, {"logit_opacities": params["logit_opacities"].data[idx].clamp_max(cap)})
            stats["reset"] = 1
        return stats

    @torch.no_grad()
    def _grow(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int) -> dict[str, int]:
        p = self.params
        grads = state["grad2d"] / state["count"].clamp_min(1)
        high = grads > p.grow_grad2d
        high[: state.get("n_fixed", 0)] = False  # an extension densifies only the new region
        small = torch.exp(params["log_scales"]).amax(-1) <= p.grow_scale3d * state["scene_scale"]
        large = ~small
        if step < p.refine_scale2d_stop_iter:
            large |= state["radii"] > p.grow_scale2d
        clone = high & small
        split = high & large  # large on screen and small in the scene: cloned and split, as in gsplat
        if p.cap_max is not None:
            room = max(p.cap_max - params["means"].shape[0], 0)
            cand = torch.nonzero(clone | split)[:, 0]
            added = clone[cand].int() + split[cand].int()  # Gaussians each candidate adds
            if int(added.sum()) > room:  # keep the strongest candidates that fit in the budget
                order = torch.argsort(grads[cand], descending=True)
                keep = cand[order][torch.cumsum(added[order], 0) <= room]
                chosen = torch.zeros_like(clone)
                chosen[keep] = True
                clone &= chosen
                split &= chosen
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone:
            src = torch.nonzero(clone)[:, 0]
            append_copies(params, optimizers, src, {})
            split = torch.cat([split, torch.zeros(n_clone, dtype=torch.bool, device=split.device)])
            if state.get("radii") is not None:
                state["radii"] = torch.cat([state["radii"], state["radii"][src]])
        if n_split:
            self._split(params, optimizers, state, split)
        return {"cloned": n_clone, "split": n_split}

    def _split(self, params: Params, optimizers: Optimizers, state: dict[str, Any], split: Tensor) -> None:
        """Replace each selected Gaussian by two, drawn from it, with scales / split_factor (and with
        `revised_opacity`, opacity 1 - sqrt(1 - o) each, so the pair covers about what the parent did)."""
        src = torch.nonzero(split)[:, 0]
        src2 = torch.cat([src, src])
        scales = torch.exp(params["log_scales"].data[src2])
        R = quat_to_rotmat(params["quats"].data[src2])
        offsets = (R @ (scales * torch.randn_like(scales))[..., None])[..., 0]
        new = {
            "means": params["means"].data[src2] + offsets,
            "log_scales": torch.log(scales / self.params.split_factor),
        }
        if self.params.revised_opacity:
            opacity = torch.sigmoid(params["logit_opacities"].data[src2])
            new["logit_opacities"] = torch.logit(1.0 - torch.sqrt(1.0 - opacity))
        append_copies(params, optimizers, src2, new)
        keep = torch.ones(params["means"].shape[0], dtype=torch.bool, device=split.device)
        keep[src] = False
        keep_only(params, optimizers, keep)
        if state.get("radii") is not None:  # the children have not been seen yet
            state["radii"] = torch.cat([state["radii"], torch.zeros_like(state["radii"][src2])])[keep]

    @torch.no_grad()
    def _prune(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int) -> int:
        p = self.params
        prune = torch.sigmoid(params["logit_opacities"].data) < p.prune_opa
        if step > p.reset_every > 0:
            prune |= torch.exp(params["log_scales"].data).amax(-1) > p.prune_scale3d * state["scene_scale"]
            if step < p.refine_scale2d_stop_iter:
                prune |= state["radii"] > p.prune_scale2d
        prune[: state.get("n_fixed", 0)] = False  # so the fixed Gaussians keep the first indices
        n = int(prune.sum())
        if n:
            keep_only(params, optimizers, ~prune)
        return n


def _zero_statistics(state: dict[str, Any], n: int, device: torch.device) -> None:
    """Fresh per-Gaussian statistics (gradient sums, counts and, when tracked, largest 2D radii) for n Gaussians."""
    state["grad2d"] = torch.zeros(n, device=device)
    state["count"] = torch.zeros(n, device=device)
    if "radii" in state:
        state["radii"] = torch.zeros(n, device=device)


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


@dataclass(frozen=True)
class MCMCStrategy:
    """3DGS-as-MCMC with the settings `params` (gsplat's `MCMCStrategy` field names; see `MCMCStrategyParams`).
    Every `refine_every` steps in (refine_start_iter, refine_stop_iter): relocate Gaussians with opacity <=
    min_opacity onto live ones sampled by opacity, then add min(cap_max, growth_rate * N) - N new ones the same
    way. Every step (until refine_stop_iter): position noise lr_means * noise_lr * Σ ε, weighted towards
    transparent Gaussians. Its `regularization` adds opacity_reg * mean(opacity) + scale_reg * mean(scale)."""

    params: MCMCStrategyParams = field(default_factory=MCMCStrategyParams)

    def initialize_state(self, scene_scale: float = 1.0, n_fixed: int = 0) -> dict[str, Any]:
        """n_fixed is not honoured: relocation may move any Gaussian (the budget is what MCMC keeps)."""
        return {"scene_scale": scene_scale}

    def regularization(self, params: Params) -> Tensor:
        if params["means"].shape[0] == 0:
            return params["means"].new_zeros(())
        opacity = torch.sigmoid(params["logit_opacities"]).mean()
        return self.params.opacity_reg * opacity + self.params.scale_reg * torch.exp(params["log_scales"]).mean()

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
        if step >= self.params.refine_stop_iter or params["means"].shape[0] == 0:
            return stats
        if step > self.params.refine_start_iter and step % self.params.refine_every == 0:
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
        new_op = new_op.clamp(self.params.min_opacity, 1.0 - 1e-6)
        return uniq, {"logit_opacities": torch.logit(new_op), "log_scales": torch.log(new_sc.clamp_min(1e-12))}

    def _relocate(self, params: Params, optimizers: Optimizers) -> int:
        dead = torch.sigmoid(params["logit_opacities"].data) <= self.params.min_opacity
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
        n_new = min(self.params.cap_max, int(self.params.growth_rate * n)) - n
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
        eps = torch.randn_like(params["means"].data) * (weight * lr * self.params.noise_lr)[:, None]
        params["means"].data.add_((cov @ eps[..., None])[..., 0])


def make_strategy(params: StrategyParams) -> DefaultStrategy | MCMCStrategy | None:
    """The strategy its settings name (`kind`); None for `NoStrategy`."""
    if isinstance(params, DefaultStrategyParams):
        return DefaultStrategy(params)
    if isinstance(params, MCMCStrategyParams):
        return MCMCStrategy(params)
    if isinstance(params, NoStrategy):
        return None
    raise TypeError(f"not a strategy's settings: {type(params).__name__}")
