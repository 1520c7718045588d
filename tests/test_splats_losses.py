"""The paper's splat loss: SSIM, depth alignment and log-L1, normal L1 + TV, and their weighted sum."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from wonderverse.metrics import ssim as ssim_metric
from wonderverse.splats.losses import (
    LossParams,
    depth_loss,
    depth_normals,
    fit_scale_shift,
    normal_loss,
    normal_tv,
    ssim,
    ssim_map,
    texture_weight,
    total_loss,
)

H, W = 24, 32


def _images(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(H, W, 3, generator=g, dtype=torch.float64)
    b = (a + 0.2 * torch.randn(H, W, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    return a, b


def test_ssim_interior_matches_the_metrics_module() -> None:
    # wonderverse.metrics.ssim averages the map where the window fits; the padded loss map agrees there.
    a, b = _images()
    m = ssim_map(a, b)
    assert m.shape == (H, W, 3)
    ref = ssim_metric(a.numpy(), b.numpy())
    assert float(m[5:-5, 5:-5].mean()) == pytest.approx(ref, abs=1e-10)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-12)
    assert float(ssim(a, b)) < 0.9


def test_ssim_is_differentiable() -> None:
    a, b = _images(1)
    a8, b8 = a[:12, :12].clone().requires_grad_(), b[:12, :12]
    assert torch.autograd.gradcheck(lambda x: ssim(x, b8), (a8,), eps=1e-6, atol=1e-6)


def _floats(result: tuple[torch.Tensor, dict[str, torch.Tensor]]) -> tuple[torch.Tensor, dict[str, float]]:
    """(loss, terms as Python floats): the loss functions keep their diagnostics on the device."""
    loss, terms = result
    return loss, {k: float(v) for k, v in terms.items()}


def test_fit_scale_shift_recovers_an_affine_map() -> None:
    g = torch.Generator().manual_seed(2)
    prior = torch.rand(H, W, generator=g, dtype=torch.float64) * 5 + 1
    target = 0.37 * prior + 1.25
    mask = torch.ones(H, W, dtype=torch.bool)
    a, b = map(float, fit_scale_shift(prior, target, mask))
    assert (a, b) == (pytest.approx(0.37, rel=1e-12), pytest.approx(1.25, rel=1e-12))
    noisy = target + 0.05 * torch.randn(H, W, generator=g, dtype=torch.float64)
    mask[:5] = False
    a, b = map(float, fit_scale_shift(prior, noisy, mask))
    ref = np.polyfit(prior[mask].numpy(), noisy[mask].numpy(), 1)
    np.testing.assert_allclose([a, b], ref, rtol=1e-10)
    flat = fit_scale_shift(torch.full((4, 4), 2.0), torch.full((4, 4), 6.0), torch.ones(4, 4, dtype=bool))
    assert tuple(map(float, flat)) == (3.0, 0.0)
    assert tuple(map(float, fit_scale_shift(prior, target, torch.zeros(H, W, dtype=torch.bool)))) == (1.0, 0.0)


def test_depth_loss_value_mask_and_gradient() -> None:
    g = torch.Generator().manual_seed(3)
    params = LossParams(depth_use_expected=False, depth_units="scene")  # the paper's formula, literally
    rendered = (torch.rand(H, W, 1, generator=g, dtype=torch.float64) * 4 + 2).requires_grad_()
    alpha = torch.ones(H, W, 1, dtype=torch.float64)
    alpha[:, :4] = 0.1  # below the alpha threshold
    prior = (rendered.detach()[..., 0] - 0.5) / 2.0  # affine in the render: the aligned prior is exact
    prior[0, 10] = math.inf  # sky
    prior[1, 10] = math.nan
    prior[2, 10] = -1.0
    prior[3, 10:] = 123.0  # excluded by the validity mask
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[3] = False
    loss, info = _floats(depth_loss(rendered, alpha, prior, valid, params, prior_aligned=False))
    assert float(loss.detach()) == pytest.approx(0.0, abs=1e-12)
    assert (info["depth_scale"], info["depth_shift"]) == (pytest.approx(2.0), pytest.approx(0.5))
    n_valid = H * (W - 4) - 3 - (W - 4)
    assert info["depth_valid_frac"] == pytest.approx(n_valid / (H * W))
    # A known residual: +0.3 on a valid block shifts the fit a little; check the value by hand.
    shifted = rendered.detach().clone()
    shifted[10:14, 10:14] += 0.3
    shifted.requires_grad_()
    loss, info = _floats(depth_loss(shifted, alpha, prior, valid, params, prior_aligned=False))
    mask = torch.isfinite(prior) & (prior > 0) & (alpha[..., 0] > 0.5) & valid
    aligned = info["depth_scale"] * prior + info["depth_shift"]
    r = (shifted.detach()[..., 0] - aligned)[mask]
    assert float(loss.detach()) == pytest.approx(float(torch.log1p(r.abs()).mean()), rel=1e-12)
    loss.backward()
    expect = torch.zeros(H, W, dtype=torch.float64)
    expect[mask] = torch.sign(r) / (1 + r.abs()) / mask.sum()  # (a, b) are held fixed
    np.testing.assert_allclose(shifted.grad[..., 0].numpy(), expect.numpy(), atol=1e-15)
    # the default measures the residual in units of the frame's median aligned prior depth (scale-free)
    scaled = LossParams(depth_use_expected=False)
    loss_m, _ = depth_loss(shifted, alpha, prior, valid, scaled, prior_aligned=False)
    assert float(loss_m.detach()) == pytest.approx(float(torch.log1p(r.abs() / aligned[mask].median()).mean()))
    loss_10, _ = depth_loss(shifted * 10, alpha, prior * 10, valid, scaled, prior_aligned=False)
    assert float(loss_10.detach()) == pytest.approx(float(loss_m.detach()), rel=1e-9)
    assert torch.isfinite(shifted.grad).all()


def test_an_aligned_prior_is_compared_as_it_is_unless_every_frame_is_fitted() -> None:
    """A prior the priors step aligned is in the render's units: the loss sees its absolute error (a render twice
    as far as the prior is wrong); an unaligned one, or `depth_fit: every`, is fitted by scale and shift first."""
    g = torch.Generator().manual_seed(5)
    prior = torch.rand(H, W, generator=g, dtype=torch.float64) * 4 + 2
    rendered = (2.0 * prior)[..., None].requires_grad_()  # right up to scale: wrong in absolute terms
    alpha = torch.ones(H, W, 1, dtype=torch.float64)
    params = LossParams(depth_use_expected=False, depth_units="scene")
    as_is, info = _floats(depth_loss(rendered, alpha, prior, None, params, prior_aligned=True))
    assert (info["depth_scale"], info["depth_shift"]) == (1.0, 0.0)
    assert float(as_is.detach()) == pytest.approx(float(torch.log1p(prior).mean()), rel=1e-12)  # |2p - p| = p
    fitted, info = _floats(depth_loss(rendered, alpha, prior, None, params, prior_aligned=False))
    assert float(fitted.detach()) == pytest.approx(0.0, abs=1e-12) and info["depth_scale"] == pytest.approx(2.0)
    every = params.model_copy(update={"depth_fit": "every"})
    assert float(depth_loss(rendered, alpha, prior, None, every, prior_aligned=True)[0].detach()) == pytest.approx(
        0.0, abs=1e-12
    )
    # as a tensor flag (how the trainer passes it, per frame): the same
    flag, _ = depth_loss(rendered, alpha, prior, None, params, prior_aligned=torch.tensor(True))
    assert float(flag.detach()) == pytest.approx(float(as_is.detach()), rel=1e-12)


def test_depth_loss_without_valid_pixels_is_zero_and_differentiable() -> None:
    rendered = torch.ones(H, W, 1, requires_grad=True)
    loss, info = _floats(depth_loss(rendered, torch.zeros(H, W, 1), torch.ones(H, W), None, LossParams()))
    loss.backward()
    assert float(loss.detach()) == 0.0 and info["depth_valid_frac"] == 0.0 and torch.all(rendered.grad == 0)


def test_depth_use_expected_divides_by_alpha() -> None:
    depth = torch.full((H, W, 1), 3.0, dtype=torch.float64)
    alpha = torch.full((H, W, 1), 0.75, dtype=torch.float64)
    prior = torch.linspace(1, 2, H * W, dtype=torch.float64).reshape(H, W)
    prior_const = torch.full((H, W), 2.0, dtype=torch.float64)
    _, info = _floats(
        depth_loss(depth, alpha, prior_const, None, LossParams(depth_use_expected=True), prior_aligned=False)
    )
    assert info["depth_scale"] == pytest.approx(2.0)  # 3 / 0.75 = 4 = 2 * 2
    loss, _ = depth_loss(depth, alpha, prior, None, LossParams(), prior_aligned=False)
    assert float(loss) == pytest.approx(0.0, abs=1e-12)  # a constant render: a = 0, b = 3


def test_normal_loss_l1_and_tv() -> None:
    params = LossParams(lambda_normal_tv=0.5)
    prior = torch.zeros(H, W, 3, dtype=torch.float64)
    prior[..., 2] = -1.0
    rendered = prior.clone()
    rendered[:, W // 2 :, 0] = 0.2  # a vertical step of 0.2 in x
    alpha = torch.ones(H, W, 1, dtype=torch.float64)
    prior[0, 0] = 0.0  # invalid prior normal
    loss, info = _floats(normal_loss(rendered, alpha, prior, None, params))
    n_valid = H * W - 1
    l1 = 0.2 * H * (W - W // 2) / n_valid
    tv = 0.2 * H / (H * (W - 1))  # one step per row, averaged over all horizontal pairs; no vertical change
    assert info["normal_l1"] == pytest.approx(l1, rel=1e-12)
    assert info["normal_tv"] == pytest.approx(tv, rel=1e-12)
    assert float(loss) == pytest.approx(l1 + 0.5 * tv, rel=1e-12)
    assert float(normal_tv(prior[1:, 1:])) == 0.0
    # TV is a mean: the same step at twice the resolution has half the per-pair mean, not twice the sum.
    big = torch.zeros(2 * H, 2 * W, 3, dtype=torch.float64)
    big[:, W:, 0] = 0.2
    assert float(normal_tv(big)) == pytest.approx(0.2 / (2 * W - 1), rel=1e-12)


def test_total_is_the_weighted_sum_and_each_weight_acts_alone() -> None:
    a, b = _images(4)
    g = torch.Generator().manual_seed(5)
    depth = torch.rand(H, W, 1, generator=g, dtype=torch.float64) + 2
    alpha = torch.full((H, W, 1), 0.9, dtype=torch.float64)
    normals = torch.nn.functional.normalize(torch.randn(H, W, 3, generator=g, dtype=torch.float64), dim=-1)
    prior_d = torch.rand(H, W, generator=g, dtype=torch.float64) + 1
    prior_n = torch.nn.functional.normalize(torch.randn(H, W, 3, generator=g, dtype=torch.float64), dim=-1)

    images = {"rgb": a, "gt_rgb": b, "depth": depth, "alpha": alpha, "normals": normals}

    def run(**kw) -> tuple[torch.Tensor, dict]:
        return total_loss(**images, params=LossParams(**kw), prior_depth=prior_d, prior_normals=prior_n)

    total, t = _floats(run())
    p = LossParams()
    assert t["rgb"] == pytest.approx((1 - p.lambda_ssim) * t["rgb_l1"] + p.lambda_ssim * (1 - t["ssim"]), rel=1e-12)
    assert float(total) == pytest.approx(t["rgb"] + p.lambda_depth * t["depth"] + p.lambda_normal * t["normal"])
    assert t["normal"] == pytest.approx(t["normal_l1"] + p.lambda_normal_tv * t["normal_tv"], rel=1e-12)
    for key, term in (("lambda_depth", "depth"), ("lambda_normal", "normal")):
        _, t2 = _floats(run(**{key: 3.0}))
        assert t2["total"] - t["total"] == pytest.approx((3.0 - getattr(p, key)) * t[term], rel=1e-9)
    _, t0 = _floats(run(lambda_depth=0.0, lambda_normal=0.0))
    assert t0["total"] == pytest.approx(t["rgb"]) and "depth" not in t0 and "normal" not in t0
    _, t3 = _floats(total_loss(**images, params=p))
    assert t3["total"] == pytest.approx(t["rgb"])


def test_loss_params_are_strict() -> None:
    with pytest.raises(ValidationError):
        LossParams(lambda_dpeth=1.0)  # type: ignore[call-arg]
    with pytest.raises(ValidationError):
        LossParams(lambda_ssim=1.5)
    p = LossParams()
    with pytest.raises(ValidationError):
        p.lambda_depth = 2.0  # type: ignore[misc]


def _plane_depth(normal_cam: np.ndarray, d0: float, K: np.ndarray, h: int, w: int) -> np.ndarray:
    """Camera z of the plane n·X = -d0 (n facing the camera) seen through K, per pixel centre."""
    v, u = np.mgrid[0:h, 0:w] + 0.5
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return -d0 / (rays @ normal_cam)


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_depth_normals_of_a_tilted_plane_at_any_scale(scale: float) -> None:
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    n = np.array([0.3, -0.4, -1.0])
    n /= np.linalg.norm(n)
    z = _plane_depth(n, 5.0 * scale, K, 48, 64)
    normals, ok = depth_normals(torch.tensor(z), torch.tensor(K), torch.ones(48, 64, dtype=torch.bool))
    assert ok[1:-1, 1:-1].all() and not ok[0].any() and not ok[:, -1].any()
    err = np.degrees(np.arccos(np.clip(normals[ok].numpy() @ n, -1, 1)))
    assert err.max() < 0.01


def test_depth_normals_skip_occluding_edges_and_invalid_pixels() -> None:
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    z = np.full((48, 64), 4.0)
    z[:, 32:] = 9.0  # a step: the pixels beside it span two surfaces
    valid = torch.ones(48, 64, dtype=torch.bool)
    valid[10, 10] = False
    _, ok = depth_normals(torch.tensor(z), torch.tensor(K), valid)
    assert not ok[:, 31].any() and not ok[:, 32].any() and ok[1:-1, 20].all()
    assert not ok[10, 9:12].any() and not ok[9:12, 10].any() and ok[9, 9] and ok[20, 20]


def test_texture_weight_is_one_on_plain_surfaces_and_small_on_texture() -> None:
    rng = np.random.default_rng(0)
    frame = np.full((32, 48, 3), 0.4)
    frame[:, 24:] = rng.uniform(0, 1, (32, 24, 3))
    wt = texture_weight(torch.tensor(frame), 0.02).numpy()
    assert np.allclose(wt[:, :20], 1.0)
    assert np.median(wt[:, 28:]) < 0.1


def test_normal_target_depth_moves_the_surface_and_weights_scale_the_terms() -> None:
    K = torch.tensor([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    h, w = 48, 64
    n_true = np.array([0.0, -0.5, -1.0])
    n_true /= np.linalg.norm(n_true)
    prior_n = torch.tensor(np.broadcast_to(n_true, (h, w, 3)).copy(), dtype=torch.float32)
    depth = torch.full((h, w, 1), 5.0, requires_grad=True)  # fronto-parallel: wrong against the prior
    alpha = torch.ones(h, w, 1)
    rendered_n = torch.zeros(h, w, 3)
    rendered_n[..., 2] = -1.0
    rgb = torch.zeros(h, w, 3)
    params = LossParams(lambda_depth=0.0, lambda_normal=1.0, lambda_normal_tv=0.0, normal_target="depth")
    images = {"rgb": rgb, "gt_rgb": rgb, "alpha": alpha, "normals": rendered_n, "prior_normals": prior_n, "K": K}
    loss, terms = total_loss(**images, depth=depth, params=params)
    loss.backward()
    assert terms["normal_l1"] > 0.3 and depth.grad.abs().sum() > 0  # the rendered depth gets the gradient
    rendered_only = params.model_copy(update={"normal_target": "rendered"})
    loss_r, _ = total_loss(**images, depth=depth.detach(), params=rendered_only)
    half = torch.full((h, w), 0.5)
    loss_h, _ = total_loss(**images, depth=depth.detach(), params=rendered_only, prior_weight=half)
    assert loss_h.item() == pytest.approx(0.5 * loss_r.item(), rel=1e-5)
    loss_s, _ = total_loss(**images, depth=depth.detach(), params=rendered_only, prior_scale=0.1)
    assert loss_s.item() == pytest.approx(0.1 * loss_r.item(), rel=1e-5)


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_new_terms_are_finite_at_the_extremes(scale: float) -> None:
    """Constant-depth prior, all-sky view (nothing valid), tiny/huge scene scales: finite losses and gradients."""
    K = torch.tensor([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    h, w = 48, 64
    params = LossParams(normal_target="both", lambda_depth_normal=0.1, prior_texture_ref=0.02)
    rgb = torch.rand(h, w, 3)
    for alpha_value in (1.0, 0.0):  # a surface everywhere, then all sky
        depth = torch.full((h, w, 1), 3.0 * scale, requires_grad=True)
        normals = torch.zeros(h, w, 3, requires_grad=True)
        alpha = torch.full((h, w, 1), alpha_value)
        prior_d = torch.full((h, w), 2.0 * scale)
        prior_n = torch.zeros(h, w, 3)
        prior_n[..., 2] = -1.0
        loss, _ = total_loss(
            rgb=rgb,
            gt_rgb=rgb,
            depth=depth,
            alpha=alpha,
            normals=normals,
            params=params,
            prior_depth=prior_d,
            prior_normals=prior_n,
            K=K,
            prior_weight=texture_weight(rgb, 0.02),
        )
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(depth.grad).all() and torch.isfinite(normals.grad).all()


def test_prior_schedule_decays_log_linearly_after_its_start() -> None:
    from wonderverse.splats.params import TrainParams
    from wonderverse.splats.trainer import prior_schedule

    tp = TrainParams(iterations=1001, loss=LossParams(prior_decay_start_frac=0.5, prior_final_ratio=0.01))
    values = [prior_schedule(tp, s) for s in range(1001)]
    assert values[0] == values[500] == 1.0
    assert values[-1] == pytest.approx(0.01)
    assert all(a >= b for a, b in itertools.pairwise(values))
    off = LossParams(prior_decay_start_frac=1.0, prior_final_ratio=1.0)
    assert prior_schedule(TrainParams(iterations=100, loss=off), 99) == 1.0


def test_flatten_loss_is_the_shortest_over_the_middle_axis_and_flattens_without_shrinking() -> None:
    from wonderverse.splats.losses import flatten_loss

    log_scales = torch.log(torch.tensor([[1.0, 1.0, 1.0], [4.0, 0.5, 2.0], [1e-3, 1e3, 1.0]])).requires_grad_()
    loss = flatten_loss(log_scales)
    assert loss.item() == pytest.approx((1.0 + 0.25 + 1e-3) / 3, rel=1e-5)
    loss.backward()
    g = log_scales.grad
    # descent shrinks each shortest axis and grows each middle one; the longest is left alone
    assert g[1, 1] > 0 and g[1, 2] < 0 and g[1, 0] == 0
    assert g[2, 0] > 0 and g[2, 2] < 0 and g[2, 1] == 0
    # the same Gaussians 1e6 times larger or smaller: the same loss (a ratio of axes)
    for shift in (-6.0, 6.0):
        scaled = flatten_loss(log_scales.detach() + shift * np.log(10.0))
        assert scaled.item() == pytest.approx(loss.item(), rel=1e-5)
    assert flatten_loss(torch.zeros(0, 3)).item() == 0.0
