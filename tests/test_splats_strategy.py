"""Densification: clone / split / prune / opacity reset, budgets, MCMC relocation, optimiser bookkeeping; the
settings in gsplat's names, from a YAML file to the strategy."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from wonderverse.config import build_config
from wonderverse.splats.params import DefaultStrategyParams, MCMCStrategyParams, NoStrategy
from wonderverse.splats.strategy import DefaultStrategy, MCMCStrategy, make_strategy, relocation_opacity_scale

NAMES = ("means", "quats", "log_scales", "logit_opacities", "sh0", "shN")


def _params(n: int, seed: int = 0) -> dict[str, torch.nn.Parameter]:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
        "quats": torch.nn.Parameter(torch.randn(n, 4, generator=g)),
        "log_scales": torch.nn.Parameter(torch.full((n, 3), math.log(0.005))),
        "logit_opacities": torch.nn.Parameter(torch.full((n,), 0.0)),
        "sh0": torch.nn.Parameter(torch.randn(n, 1, 3, generator=g)),
        "shN": torch.nn.Parameter(torch.randn(n, 3, 3, generator=g)),
    }


def _optimizers(params: dict) -> dict[str, torch.optim.Optimizer]:
    opts = {k: torch.optim.Adam([p], lr=0.0) for k, p in params.items()}
    for p in params.values():  # one step (at lr 0: values unchanged) so that the Adam moments exist
        p.grad = torch.ones_like(p)
    for o in opts.values():
        o.step()
        o.param_groups[0]["lr"] = 1e-3
    return opts


def _info(n: int, grad2d: torch.Tensor, visible: torch.Tensor | None = None) -> dict:
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = grad2d.reshape(1, n, 2).clone()
    vis = torch.ones(n, dtype=torch.int32) if visible is None else visible.int()
    radii = torch.ones(n, 2, dtype=torch.int32) * vis[:, None]
    return {"means2d": means2d, "radii": radii, "width": 200, "height": 100, "n_cameras": 1}


def _check_optimizers(params: dict, opts: dict) -> None:
    for k, p in params.items():
        (group,) = opts[k].param_groups
        assert group["params"][0] is p
        st = opts[k].state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
    # And the optimisers still step.
    for p in params.values():
        p.grad = torch.zeros_like(p)
    for o in opts.values():
        o.step()


def test_clone_split_prune_and_moments() -> None:
    n = 10
    params = _params(n)
    params["log_scales"].data[5:] = math.log(0.05)  # large: split; 0..4 small: clone
    params["logit_opacities"].data[9] = -10.0  # transparent: pruned
    opts = _optimizers(params)
    exp_avg_before = opts["means"].state[params["means"]]["exp_avg"].clone()
    # NDC gradient = pixel gradient * (W/2, H/2); rows 0, 1 (small) and 5, 6 (large) exceed 2e-4.
    grad = torch.zeros(n, 2)
    grad[[0, 1, 5, 6], 0] = 3e-4 / 100.0
    grad[2, 1] = 1e-4 / 50.0  # below the threshold
    strategy = DefaultStrategy(DefaultStrategyParams(refine_start_iter=0, refine_every=10, reset_every=1000))
    state = strategy.initialize_state()
    means_before = params["means"].data.clone()
    stats = strategy.step_post_backward(params, opts, state, step=10, info=_info(n, grad))
    assert stats == {"cloned": 2, "split": 2, "pruned": 1, "reset": 0}
    assert params["means"].shape[0] == n + 2 + 2 - 1
    # Survivors keep order and moments; clones are exact copies with zero moments; splits are new.
    kept = [0, 1, 2, 3, 4, 7, 8]
    np.testing.assert_array_equal(params["means"].data[:7].numpy(), means_before[kept].numpy())
    st = opts["means"].state[params["means"]]
    np.testing.assert_array_equal(st["exp_avg"][:7].numpy(), exp_avg_before[kept].numpy())
    np.testing.assert_array_equal(params["means"].data[7:9].numpy(), means_before[[0, 1]].numpy())
    assert torch.all(st["exp_avg"][7:] == 0)
    np.testing.assert_allclose(params["log_scales"].data[9:].numpy(), math.log(0.05 / 1.6), rtol=1e-6)
    assert torch.all((params["means"].data[9:11] - means_before[[5, 6]]).norm(dim=1) > 0)
    _check_optimizers(params, opts)


def test_gradients_accumulate_as_a_mean_over_visible_steps() -> None:
    n = 4
    params = _params(n)
    opts = _optimizers(params)
    strategy = DefaultStrategy(DefaultStrategyParams(refine_start_iter=0, refine_every=3, reset_every=1000))
    state = strategy.initialize_state()
    grad = torch.zeros(n, 2)
    grad[0, 0] = 5e-4 / 100  # once 5e-4, then invisible twice: mean over visible steps = 5e-4 -> clone
    grad[1, 0] = 3e-4 / 100  # 3e-4, then 0, 0 while visible: mean 1e-4 -> nothing
    strategy.step_post_backward(params, opts, state, 1, _info(n, grad))
    for step in (2, 3):
        stats = strategy.step_post_backward(
            params, opts, state, step, _info(n, torch.zeros(n, 2), torch.tensor([0, 1, 1, 1]))
        )
    assert stats["cloned"] == 1 and params["means"].shape[0] == n + 1


def test_opacity_reset_happens_unlike_gsplat_1_5_3() -> None:
    params = _params(6)
    params["logit_opacities"].data[:] = torch.tensor([5.0, 0.0, -2.0, -4.0, -4.5, -6.0])
    opts = _optimizers(params)
    strategy = DefaultStrategy(DefaultStrategyParams(refine_start_iter=10_000, reset_every=300))
    state = strategy.initialize_state()
    stats = strategy.step_post_backward(params, opts, state, 299, _info(6, torch.zeros(6, 2)))
    assert stats["reset"] == 0 and params["logit_opacities"].data[0] == 5.0
    stats = strategy.step_post_backward(params, opts, state, 300, _info(6, torch.zeros(6, 2)))
    assert stats["reset"] == 1
    op = torch.sigmoid(params["logit_opacities"].data)
    assert torch.all(op <= 0.01 + 1e-7)
    assert op[5] == pytest.approx(torch.sigmoid(torch.tensor(-6.0)).item())  # lower ones untouched
    assert torch.all(opts["logit_opacities"].state[params["logit_opacities"]]["exp_avg"] == 0)
    # gsplat 1.5.3 writes `step % reset_every == 0 & step > 0`, which is never true:
    assert not (300 % 300 == 0 & 300 > 0)


def test_budget_caps_growth_keeping_the_strongest() -> None:
    n = 10
    params = _params(n)
    opts = _optimizers(params)
    grad = torch.zeros(n, 2)
    grad[:, 0] = torch.linspace(3e-4, 9e-4, n) / 100
    strategy = DefaultStrategy(DefaultStrategyParams(refine_start_iter=0, refine_every=1, reset_every=1000, cap_max=13))
    state = strategy.initialize_state()
    means_before = params["means"].data.clone()
    stats = strategy.step_post_backward(params, opts, state, 1, _info(n, grad))
    assert stats["cloned"] == 3 and params["means"].shape[0] == 13
    np.testing.assert_array_equal(params["means"].data[10:].numpy(), means_before[[7, 8, 9]].numpy())


def test_relocation_preserves_the_stack_opacity() -> None:
    op = torch.tensor([0.9, 0.5, 0.2, 0.01, 0.7], dtype=torch.float64)
    scales = torch.ones(5, 3, dtype=torch.float64)
    ratios = torch.tensor([1, 2, 3, 5, 50])
    new_op, new_sc = relocation_opacity_scale(op, scales, ratios)
    # n stacked copies of opacity o' composite to 1 - (1 - o')^n = o.
    np.testing.assert_allclose((1 - (1 - new_op) ** ratios.double()).numpy(), op.numpy(), rtol=1e-10)
    np.testing.assert_allclose(new_sc[0].numpy(), 1.0, rtol=1e-12)  # a single copy is unchanged
    # n = 2 by hand: denom = o' + (o' - o'^2 / sqrt 2).
    o2 = new_op[1]
    assert new_sc[1, 0].item() == pytest.approx(0.5 / (2 * o2 - o2**2 / math.sqrt(2)).item(), rel=1e-12)
    assert torch.all(new_sc[1:] < 1.0 + 1e-9)


def test_mcmc_relocates_dead_adds_to_cap_and_keeps_moments_consistent() -> None:
    torch.manual_seed(0)
    n = 40
    params = _params(n)
    params["logit_opacities"].data[:10] = -10.0  # dead
    opts = _optimizers(params)
    strategy = MCMCStrategy(MCMCStrategyParams(cap_max=44, refine_start_iter=0, refine_every=5))
    state = strategy.initialize_state()
    means_before = params["means"].data.clone()
    stats = strategy.step_post_backward(params, opts, state, 5, {}, lr=0.0)
    assert stats == {"relocated": 10, "added": 2}  # int(1.05 * 40) = 42 <= cap 44
    assert params["means"].shape[0] == 42
    op = torch.sigmoid(params["logit_opacities"].data)
    assert torch.all(op > strategy.params.min_opacity)
    # Relocated Gaussians sit exactly on live ones.
    live = means_before[10:]
    d = torch.cdist(params["means"].data[:10], live, compute_mode="donot_use_mm_for_euclid_dist").min(dim=1).values
    assert torch.all(d == 0)
    _check_optimizers(params, opts)
    for step in range(10, 40, 5):
        strategy.step_post_backward(params, opts, state, step, {}, lr=0.0)
    assert params["means"].shape[0] == 44  # the cap


def test_mcmc_noise_moves_transparent_gaussians_only() -> None:
    torch.manual_seed(1)
    params = _params(20)
    params["log_scales"].data[:] = math.log(0.1)
    params["logit_opacities"].data[:10] = -9.0
    params["logit_opacities"].data[10:] = 3.0
    opts = _optimizers(params)
    before = params["means"].data.clone()
    MCMCStrategy(MCMCStrategyParams(refine_start_iter=10**6)).step_post_backward(params, opts, {}, 3, {}, lr=1.6e-4)
    moved = (params["means"].data - before).norm(dim=1)
    assert torch.all(moved[:10] > 1e-4) and torch.all(moved[10:] < 1e-6)


def test_regularization_terms() -> None:
    params = _params(5)
    assert DefaultStrategy().regularization(params) is None
    reg = MCMCStrategy(MCMCStrategyParams(opacity_reg=0.1, scale_reg=0.2)).regularization(params)
    assert float(reg.detach()) == pytest.approx(0.1 * 0.5 + 0.2 * 0.005, rel=1e-6)


def test_refinement_pauses_after_an_opacity_reset() -> None:
    """gsplat's pause_refine_after_reset: no growth until that many steps after each reset."""

    def info(n: int) -> dict:
        grad = torch.zeros(n, 2)
        grad[0, 0] = 3e-4 / 100  # NDC 3e-4 > 2e-4, small: cloned when refinement runs
        return _info(n, grad)

    counts = {}
    for pause in (0, 30):
        params = _params(4)
        opts = _optimizers(params)
        p = DefaultStrategyParams(refine_start_iter=0, refine_every=10, reset_every=100, pause_refine_after_reset=pause)
        strategy = DefaultStrategy(p)
        state = strategy.initialize_state()
        at_120 = strategy.step_post_backward(params, opts, state, 120, info(4))["cloned"]
        at_130 = strategy.step_post_backward(params, opts, state, 130, info(params["means"].shape[0]))["cloned"]
        counts[pause] = (at_120, at_130)
    assert counts[0] == (1, 1)  # grown at 120, 20 steps after the reset at 100, and again at 130
    assert counts[30] == (0, 1)  # paused at 120 (20 < 30), grown at 130


@pytest.mark.parametrize("revised", [False, True])
def test_split_factor_and_revised_opacity_shape_the_children(revised: bool) -> None:
    params = _params(2)
    params["log_scales"].data[:] = math.log(0.05)  # larger than grow_scale3d 0.01: split
    params["logit_opacities"].data[:] = math.log(0.64 / 0.36)  # opacity 0.64
    opts = _optimizers(params)
    grad = torch.zeros(2, 2)
    grad[0, 0] = 3e-4 / 100
    p = DefaultStrategyParams(refine_start_iter=0, refine_every=1, split_factor=2.0, revised_opacity=revised)
    stats = DefaultStrategy(p).step_post_backward(
        params, opts, DefaultStrategy(p).initialize_state(), 1, _info(2, grad)
    )
    assert stats["split"] == 1 and params["means"].shape[0] == 3  # row 1 kept, row 0 replaced by two children
    np.testing.assert_allclose(params["log_scales"].data[1:].numpy(), math.log(0.05 / 2.0), rtol=1e-6)
    child_opacity = torch.sigmoid(params["logit_opacities"].data[1:])
    np.testing.assert_allclose(child_opacity.numpy(), 0.4 if revised else 0.64, rtol=1e-5)  # 1 - sqrt(0.36) = 0.4
    assert torch.sigmoid(params["logit_opacities"].data[0]).item() == pytest.approx(0.64, rel=1e-6)
    _check_optimizers(params, opts)


@pytest.mark.parametrize("stop", [0, 100])
def test_screen_size_criteria_apply_until_refine_scale2d_stop_iter(stop: int) -> None:
    """Small in the scene but 20 px of a 200 px image (0.1 > grow_scale2d 0.05): cloned and, while the 2D
    criteria apply, split too (gsplat); 40 px (0.2 > prune_scale2d 0.15) after a reset: pruned."""
    n = 3
    params = _params(n)
    opts = _optimizers(params)
    grad = torch.zeros(n, 2)
    grad[0, 0] = 3e-4 / 100
    info = _info(n, grad)
    info["radii"] = torch.tensor([[20, 12], [40, 40], [3, 3]], dtype=torch.int32)
    p = DefaultStrategyParams(refine_start_iter=0, refine_every=10, reset_every=5, refine_scale2d_stop_iter=stop)
    strategy = DefaultStrategy(p)
    state = strategy.initialize_state()
    assert ("radii" in state) == (stop > 0)
    stats = strategy.step_post_backward(params, opts, state, 10, info)
    if stop:
        assert (stats["cloned"], stats["split"], stats["pruned"]) == (1, 1, 1)
        assert params["means"].shape[0] == n + 1 + 1 - 1
        assert state["radii"].shape == (params["means"].shape[0],) and torch.all(state["radii"] == 0)
    else:
        assert (stats["cloned"], stats["split"], stats["pruned"]) == (1, 0, 0)
        assert params["means"].shape[0] == n + 1
    _check_optimizers(params, opts)


def test_settings_in_a_yaml_file_reach_the_strategy(tmp_path) -> None:
    """A gsplat field set in a scene file arrives unrenamed; a new `kind` starts from that kind's defaults."""
    f = tmp_path / "scene.yaml"
    f.write_text(
        "steps:\n  splats:\n    train:\n      strategy: {pause_refine_after_reset: 200, revised_opacity: true}\n"
    )
    strategy = make_strategy(build_config("a forest", preset="high", config_file=f).steps.splats.train.strategy)
    assert isinstance(strategy, DefaultStrategy)
    assert strategy.params.pause_refine_after_reset == 200 and strategy.params.revised_opacity
    assert strategy.params.refine_stop_iter == 15_000  # the preset's, kept
    f.write_text("steps:\n  splats:\n    train:\n      strategy: {kind: mcmc, cap_max: 5000}\n")
    strategy = make_strategy(build_config("a forest", preset="preview", config_file=f).steps.splats.train.strategy)
    assert isinstance(strategy, MCMCStrategy)
    assert strategy.params == MCMCStrategyParams(cap_max=5000)  # preview's default-strategy schedule left behind
    assert make_strategy(NoStrategy()) is None
