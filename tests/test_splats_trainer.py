"""Splat training on frames of the procedural world (its own ground-truth depth and normals as priors)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from wonderverse.splats.model import init_from_points, normalization_from_cameras, voxel_downsample
from wonderverse.splats.params import (
    DefaultStrategyParams,
    LossParams,
    MCMCStrategyParams,
    NoStrategy,
    TrainParams,
)
from wonderverse.splats.renderer import make_renderer
from wonderverse.splats.trainer import (
    Views,
    continuation_params,
    evaluate,
    normalize_views,
    split_views,
    train,
    view_order,
)
from wonderverse.video.procedural import ProceduralVideo, demo_path

W, H, T = 64, 48, 8


@pytest.fixture(autouse=True)
def one_thread():
    # On a shared 2-core machine two OpenMP threads spin-wait for each other: small images run ~10x
    # faster on one thread.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def scene() -> dict:
    video = ProceduralVideo("a small house decorated for Christmas", 0, W, H, 60.0, {"fault_probability": 0.0})
    path = demo_path(video.world.start_pose(), T, yaw_deg=12.0, forward_m=0.6)
    vid = video.generate("", path, 0, None)
    depth, normals, K = vid.gt.depth, vid.gt.normals, vid.K
    # Initial points: ground-truth depth of two training views, back-projected (every other pixel).
    pts = []
    for i in (0, 4):
        v, u = np.mgrid[0:H:2, 0:W:2]
        z = depth[i, v, u]
        ok = np.isfinite(z)
        xc = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * z, (v + 0.5 - K[1, 2]) / K[1, 1] * z, z], -1)[ok]
        R, t = path[i, :3, :3], path[i, :3, 3]
        pts.append((xc - t) @ R)
    points, _ = voxel_downsample(np.concatenate(pts), None, 0.25)
    norm = normalization_from_cameras(path, points)
    views = Views(frames=vid.frames, w2c=path, K=K, prior_depth=depth, prior_normals=normals)
    return {"views": normalize_views(views, norm), "points": norm.apply(points), "norm": norm}


def _model(scene: dict, sh_degree: int = 1):
    pts = scene["points"]
    return init_from_points(pts, np.full((len(pts), 3), 0.5), sh_degree=sh_degree, init_opacity=0.5)


FAST = {"iterations": 150, "sh_degree": 1, "sh_degree_interval_iters": 100, "holdout_every": 4}


def test_auto_scene_scale() -> None:
    from wonderverse.camera import look_at
    from wonderverse.splats.trainer import auto_scene_scale

    w2c = np.stack([look_at(np.array([x, 0.0, 0.0]), np.array([x, 10.0, 0.0])) for x in (-1.0, 1.0)])
    near = np.array([[0.0, 0.5, 0.0], [0.2, 0.3, 0.0], [0.0, 0.4, 0.1]])
    assert auto_scene_scale(w2c, near) == pytest.approx(1.1)  # the camera extent dominates
    far = np.array([[0.0, 30.0, 0.0], [0.0, 40.0, 0.0], [0.0, 50.0, 0.0]])
    assert auto_scene_scale(w2c, far) == pytest.approx(40.0)  # the median distance of the content
    assert auto_scene_scale(w2c[:1], np.zeros((0, 3))) == 1.0


def test_split_views() -> None:
    assert split_views(16, 8) == ([*range(7), *range(8, 15)], [7, 15])
    assert split_views(5, 0) == ([0, 1, 2, 3, 4], [])
    assert split_views(1, 8) == ([0], [])


def test_view_order_gives_the_focus_views_their_share() -> None:
    ids, focus = list(range(40)), {30, 31, 32, 33, 34, 35, 36, 37, 38, 39}
    gen = torch.Generator().manual_seed(0)
    order = view_order(ids, [(focus, 0.5)], gen)
    counts = np.bincount(order, minlength=40)
    assert (counts[:30] == 1).all() and (counts[30:] == 3).all()  # 30 others once, 10 focus views 3 times
    assert sum(i in focus for i in order) / len(order) == 0.5
    assert sorted(view_order(ids, [(focus, 0.0)], gen)) == ids  # no share: one plain pass
    assert sorted(view_order(ids, [(set(), 0.5)], gen)) == ids  # no focus views: one plain pass
    assert sorted(view_order(ids, [(set(ids), 0.5)], gen)) == ids  # all focus: nothing to favour them over
    assert view_order(ids, [(focus, 0.5)], torch.Generator().manual_seed(1)) != order  # shuffled by the generator


def test_view_order_gives_each_focus_group_its_share() -> None:
    """New views half the steps, the old views near them 0.4, the 20 others 0.1 (each once); a view in both
    groups counts in the first."""
    ids, new, near = list(range(40)), set(range(30, 40)), set(range(20, 32))
    counts = np.bincount(view_order(ids, [(new, 0.5), (near, 0.4)], torch.Generator().manual_seed(0)), minlength=40)
    assert (counts[:20] == 1).all() and (counts[20:30] == 8).all() and (counts[30:] == 10).all()
    assert np.isclose(counts[30:].sum() / counts.sum(), 0.5, atol=0.01)
    assert np.isclose(counts[20:30].sum() / counts.sum(), 0.4, atol=0.01)


def test_continuation_compresses_the_schedule() -> None:
    p = TrainParams(iterations=7000, strategy=DefaultStrategyParams(refine_start_iter=500, refine_every=100))
    c = continuation_params(p, 0.2)
    assert c.iterations == 1400 and c.sh_degree_interval_iters == 1
    s = c.strategy
    assert (s.refine_start_iter, s.refine_every, s.refine_stop_iter) == (100, 20, 3000)
    assert s.reset_every == 0 and p.strategy.reset_every == 3000
    assert s.refine_scale2d_stop_iter == 0 and c.loss == p.loss  # off stays off (0 is not a step)
    assert s.model_copy(update={"refine_start_iter": 500, "refine_every": 100, "refine_stop_iter": 15000}) == (
        p.strategy.model_copy(update={"reset_every": 0})
    )  # nothing else of the strategy changes
    mcmc = continuation_params(TrainParams(iterations=7000, strategy=MCMCStrategyParams(cap_max=9)), 0.2).strategy
    assert (mcmc.refine_start_iter, mcmc.refine_every, mcmc.refine_stop_iter, mcmc.cap_max) == (100, 20, 5000, 9)
    assert continuation_params(TrainParams(strategy=NoStrategy()), 0.2).strategy == NoStrategy()
    tiny = continuation_params(TrainParams(iterations=3, strategy=DefaultStrategyParams(refine_every=1)), 0.01)
    assert tiny.iterations == 1 and tiny.strategy.refine_every == 1  # never zero


def test_training_fits_the_frames_and_treats_sky_as_background(scene: dict) -> None:
    # Colours start grey: a higher SH learning rate than 3DGS's lets 150 iterations fit them.
    params = TrainParams(**FAST, strategy=NoStrategy(), lr_sh0=0.05, lr_log_scales=0.01)
    renderer = make_renderer("torch")
    model = _model(scene)
    assert len(model.means) > 300
    views: Views = scene["views"]
    sky_colour = np.median(views.frames[np.isinf(views.prior_depth)].astype(np.float32) / 255, axis=0)
    before = evaluate(model, views, [3, 7], renderer, params, torch.tensor(sky_colour))
    model, curves, metrics = train(model, views, params, renderer)
    assert metrics["test_views"] == [3, 7] and metrics["skipped_steps"] == 0
    assert len(curves["total"]) == 150 and {"rgb", "depth", "normal", "sky_alpha"} <= set(curves)
    first, last = np.mean(curves["rgb"][:20]), np.mean(curves["rgb"][-20:])
    assert last < 0.5 * first
    assert metrics["test_psnr"] > before["psnr"] + 6.0, (before, metrics)  # seen: 11.2 -> 19.7 dB
    assert metrics["test_psnr"] > 17.0 and metrics["test_ssim"] > 0.6
    # Sky: explained by the background colour, with (nearly) no Gaussians in front of it.
    np.testing.assert_allclose(metrics["background_rgb"], sky_colour, atol=0.08)
    from wonderverse.splats.trainer import _Data, _render_view

    data = _Data(views, params, "cpu")
    with torch.no_grad():
        _, _, alpha, _, _ = _render_view(model, data, 3, renderer, params, torch.tensor(sky_colour), 1)
    assert float(alpha[..., 0][data.sky[3]].mean()) < 0.2
    assert float(alpha[..., 0][~data.sky[3]].mean()) > 0.8


def test_evaluate_scores_only_the_pixels_a_view_keeps(scene: dict) -> None:
    """A corrupted block left out of view 3's kept pixels does not move its kept PSNR, while its full PSNR falls;
    a view not in `keep` keeps every pixel, and one that keeps none has no figure."""
    import dataclasses

    params, renderer, model = TrainParams(**FAST), make_renderer("torch"), _model(scene)
    views: Views = scene["views"]
    block = np.zeros((H, W), bool)
    block[: H // 2, : W // 2] = True
    frames = views.frames.copy()
    frames[3][block] = np.where((np.indices((H, W)).sum(0) % 2 == 0)[block, None], 255, 0)  # black and white
    corrupted = dataclasses.replace(views, frames=frames)
    keep = {3: ~block}
    clean = evaluate(model, views, [3, 7], renderer, params, torch.zeros(3), per_view=True, keep=keep)
    bad = evaluate(model, corrupted, [3, 7], renderer, params, torch.zeros(3), per_view=True, keep=keep)
    assert bad["psnr_kept_views"][0] == pytest.approx(clean["psnr_kept_views"][0], abs=1e-9)
    assert bad["psnr_views"][0] < clean["psnr_views"][0] - 1.0
    assert bad["psnr_kept_views"][1] == pytest.approx(bad["psnr_views"][1], abs=1e-9)  # view 7: all kept
    none = evaluate(model, views, [3], renderer, params, torch.zeros(3), keep={3: np.zeros((H, W), bool)})
    assert np.isnan(none["psnr_kept_views"][0])


def test_densification_and_mcmc_change_the_model_size(scene: dict) -> None:
    renderer = make_renderer("torch")
    dens = DefaultStrategyParams(refine_start_iter=5, refine_every=10, reset_every=30, grow_grad2d=1e-5)
    params = TrainParams(**{**FAST, "iterations": 40}, strategy=dens)
    model = _model(scene)
    n0 = model.num_gaussians
    model, curves, metrics = train(model, scene["views"], params, renderer)
    assert metrics["n_gaussians"] == model.num_gaussians == int(curves["n_gaussians"][-1])
    assert max(curves["n_gaussians"]) > n0
    # The step-40 refinement prunes "too big" Gaussians; relative to the automatic scene scale (the
    # distant content, not the 0.6 m camera path) they are not, so the model survives.
    assert curves["n_gaussians"][-1] > n0 and metrics["scene_scale"] > 10
    assert np.isfinite(curves["total"]).all()

    mcmc = MCMCStrategyParams(refine_start_iter=5, refine_every=10, cap_max=n0 + 40)
    params = TrainParams(**{**FAST, "iterations": 40}, strategy=mcmc)
    model, curves, metrics = train(_model(scene), scene["views"], params, renderer)
    assert metrics["n_gaussians"] == n0 + 40
    assert np.isfinite(curves["total"]).all()


def test_non_finite_steps_are_skipped(scene: dict, caplog: pytest.LogCaptureFixture) -> None:
    views: Views = scene["views"]
    frames = views.frames.astype(np.float32) / 255
    frames[1, 10, 10] = np.nan  # view 1 gives a NaN loss every time it is drawn
    bad = views.replace(frames=frames)
    params = TrainParams(**{**FAST, "iterations": 14}, strategy=NoStrategy())
    with caplog.at_level(logging.WARNING, logger="wonderverse.splats.trainer"):
        model, curves, metrics = train(_model(scene), bad, params, make_renderer("torch"))
    assert metrics["skipped_steps"] == 2  # two epochs of 6 training views, then two more steps
    assert len(curves["total"]) == 12
    assert sum("non-finite" in r.message for r in caplog.records) == 2
    assert all(torch.isfinite(p).all() for p in model.param_dict().values())


@pytest.mark.parametrize(("sky_map_rows", "scale2d_stop"), [(0, 0), (8, 20)])
def test_checkpoint_and_resume_reproduce_the_run(scene: dict, sky_map_rows: int, scale2d_stop: int) -> None:
    """scale2d_stop > 0: the strategy state holds the largest 2D radii too, and they resume alike."""
    dens = DefaultStrategyParams(
        refine_start_iter=3, refine_every=4, reset_every=10, grow_grad2d=1e-5, refine_scale2d_stop_iter=scale2d_stop
    )
    params = TrainParams(
        **{**FAST, "iterations": 24},
        strategy=dens,
        checkpoint_every_iters=8,
        loss=LossParams(lambda_depth=0.5),
        sky_map_rows=sky_map_rows,
    )
    renderer = make_renderer("torch")
    saved: dict[int, dict] = {}
    full, curves, _ = train(_model(scene), scene["views"], params, renderer, checkpoint_cb=saved.__setitem__)
    assert sorted(saved) == [8, 16, 24]
    resumed, curves2, _ = train(_model(scene), scene["views"], params, renderer, resume_state=saved[16])
    assert resumed.num_gaussians == full.num_gaussians
    for k, v in full.param_dict().items():
        np.testing.assert_allclose(resumed.param_dict()[k].detach().numpy(), v.detach().numpy(), atol=1e-5, err_msg=k)
    np.testing.assert_allclose(curves2["total"], curves["total"], rtol=1e-4)


def test_a_sky_map_renders_the_sky_closer_than_one_colour(scene: dict) -> None:
    """The procedural sky has a gradient, clouds and the sun's glow: a colour per direction fits it better than
    one colour, in the trainer's own renders and in `render_views` (what the exports show)."""
    from wonderverse.camera import Sim3
    from wonderverse.splats.views import render_views

    views: Views = scene["views"]
    sky_px = np.isinf(views.prior_depth)
    truth = views.frames.astype(np.float32) / 255
    renderer, error, psnr = make_renderer("torch"), {}, {}
    for rows in (0, 8):
        params = TrainParams(**FAST, strategy=NoStrategy(), lr_sh0=0.05, sky_map_rows=rows, lr_background=0.03)
        model, _, metrics = train(_model(scene), views, params, renderer)
        sky = metrics.pop("sky_map", None)
        assert (sky is None) == (rows == 0)
        if rows:
            assert sky.shape == (8, 16, 3) and sky.dtype == np.float32
            np.testing.assert_allclose(metrics["background_rgb"], sky.reshape(-1, 3).mean(0), rtol=1e-5)
        shown = sky if rows else np.asarray(metrics["background_rgb"], np.float32)
        identity = Sim3(1.0, np.eye(3), np.zeros(3))
        rendered = list(render_views(model.to_numpy(), identity, views.w2c, views.K, W, H, renderer, shown))
        rgb, alpha = np.stack([v.rgb for v in rendered]), np.stack([v.alpha for v in rendered])
        clear = sky_px & (alpha < 0.05)  # sky with no Gaussian in front: the sky model alone
        assert clear.sum() > 0.7 * sky_px.sum()
        error[rows] = float(np.mean((rgb[clear] - truth[clear]) ** 2))
        psnr[rows] = metrics["test_psnr"]
    assert error[8] < 0.3 * error[0], error  # seen: 3.6e-4 -> 3.8e-5
    assert psnr[8] > psnr[0] - 0.1, psnr  # seen: 21.27 -> 21.34 dB (the sky is 12 % of the pixels)


def test_empty_model_trains_the_background_only(scene: dict) -> None:
    from wonderverse.splats.model import GaussianModel

    params = TrainParams(**{**FAST, "iterations": 10}, strategy=DefaultStrategyParams(), background_rgb=(0.0, 0.0, 0.0))
    model, curves, metrics = train(GaussianModel.empty(1), scene["views"], params, make_renderer("torch"))
    assert model.num_gaussians == 0 and metrics["skipped_steps"] == 0
    assert np.isfinite(curves["total"]).all() and curves["rgb"][-1] < curves["rgb"][0]
    assert min(metrics["background_rgb"]) > 0.05  # the background moved towards the frames' colours


@pytest.mark.parametrize("where", ["none", "loss", "grad"])
def test_found_inf_flags_the_loss_or_any_gradient_and_leaves_gradients_alone(where: str) -> None:
    from wonderverse.splats.trainer import _found_inf

    params = [
        torch.nn.Parameter(torch.zeros(4, 3)),
        torch.nn.Parameter(torch.zeros(2)),
        torch.nn.Parameter(torch.zeros(0)),
    ]
    params[0].grad = torch.arange(12.0).reshape(4, 3)
    params[1].grad = torch.tensor([1.5, -2.0])
    if where == "grad":
        params[1].grad[1] = float("inf")
    loss = torch.tensor(float("nan") if where == "loss" else 0.25)
    before = [p.grad.clone() for p in params[:2]]
    found = _found_inf(loss, params)
    assert found.shape == () and float(found) == (0.0 if where == "none" else 1.0)
    for b, p in zip(before, params[:2], strict=True):
        assert torch.equal(b, p.grad)
    assert where == "loss" or float(loss) == 0.25  # the loss itself is not touched


def test_adam_step_matches_torch_adam_step_and_skips_non_finite_steps() -> None:
    from wonderverse.splats.trainer import _make_adam, adam_step

    gen = torch.Generator().manual_seed(0)
    start = {
        "a": torch.randn(5, 3, generator=gen),
        "b": torch.randn(4, generator=gen),
        "c": torch.randn(2, generator=gen),
    }
    lrs = {"a": 1e-2, "b": 3e-3, "c": 0.5}
    ours = {k: torch.nn.Parameter(v.clone()) for k, v in start.items()}
    ref = {k: torch.nn.Parameter(v.clone()) for k, v in start.items()}
    opt_ours = [_make_adam({k: ours[k] for k in "ab"}, lrs), _make_adam({"c": ours["c"]}, lrs, eps=1e-8)]
    opt_ref = [_make_adam({k: ref[k] for k in "ab"}, lrs), _make_adam({"c": ref["c"]}, lrs, eps=1e-8)]
    for step in range(6):
        grads = {k: torch.randn(v.shape, generator=gen) for k, v in start.items()}
        if step == 3:
            grads["b"][1] = float("nan")  # this step must change nothing
        found = torch.tensor(1.0 if step == 3 else 0.0)
        before = {k: p.detach().clone() for k, p in ours.items()}
        for params in (ours, ref):
            for k, p in params.items():
                p.grad = None if (step == 0 and k == "c") else grads[k].clone()  # a group with no gradient
        adam_step(opt_ours, found)
        for o in opt_ref:
            o.found_inf, o.grad_scale = found, None
            o.step()
        for k in start:
            torch.testing.assert_close(ours[k].detach(), ref[k].detach(), rtol=0, atol=0)
            if step == 3:
                assert torch.equal(ours[k].detach(), before[k])
            elif not (step == 0 and k == "c"):
                assert not torch.equal(ours[k].detach(), before[k])
    for o, r in zip(opt_ours, opt_ref, strict=True):
        for p, q in zip(
            [p for g in o.param_groups for p in g["params"]],
            [q for g in r.param_groups for q in g["params"]],
            strict=True,
        ):
            for key in ("step", "exp_avg", "exp_avg_sq"):
                assert torch.equal(o.state[p][key], r.state[q][key]), key
        assert [float(o.state[p]["step"]) for g in o.param_groups for p in g["params"]] in ([5.0, 5.0], [4.0])


@pytest.mark.parametrize("units", ["median", "scene"])
def test_loss_and_grads_by_torch_func_match_autograd_of_the_loss_and_sky_term(units: str) -> None:
    from wonderverse.splats.losses import masked_mean, total_loss
    from wonderverse.splats.trainer import loss_and_grads

    g = torch.Generator().manual_seed(0)
    h, w = 24, 32
    rgb, gt = torch.rand(h, w, 3, generator=g), torch.rand(h, w, 3, generator=g)
    alpha = torch.rand(h, w, 1, generator=g)
    depth = (torch.rand(h, w, 1, generator=g) + 1) * alpha
    normals = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g), dim=-1)
    prior_depth = torch.rand(h, w, generator=g) * 3 + 1
    prior_depth[:4] = float("inf")  # invalid prior: sky
    prior_normals = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g), dim=-1)
    prior_normals[:, :3] = 0.0  # no prior there
    sky = ~torch.isfinite(prior_depth)
    params = LossParams(lambda_depth=0.3, lambda_normal=0.2, depth_units=units)
    rest = {"prior_depth": prior_depth, "prior_normals": prior_normals, "valid": ~sky, "sky": sky}

    leaves = [t.clone().requires_grad_() for t in (rgb, depth, alpha, normals)]
    rgb_, depth_, alpha_, normals_ = leaves
    ref, ref_terms = total_loss(
        rgb=rgb_,
        gt_rgb=gt,
        depth=depth_,
        alpha=alpha_,
        normals=normals_,
        params=params,
        prior_depth=prior_depth,
        prior_normals=prior_normals,
        depth_valid=~sky,
        normal_valid=~sky,
    )
    ref_terms["sky_alpha"] = masked_mean(leaves[2][..., 0], sky)
    ref = ref + 0.1 * ref_terms["sky_alpha"]
    ref.backward()
    loss, terms, grads = loss_and_grads(rgb, gt, depth, alpha, normals, params, **rest, sky_alpha_weight=0.1)
    torch.testing.assert_close(loss, ref.detach())
    assert terms.keys() == ref_terms.keys() and "sky_alpha" in terms
    for k in terms:
        torch.testing.assert_close(terms[k], ref_terms[k], equal_nan=True)
    for mine, leaf in zip(grads, leaves, strict=True):
        assert mine.shape == leaf.shape and leaf.grad.abs().sum() > 0
        torch.testing.assert_close(mine, leaf.grad)


ENHANCED = LossParams(
    prior_texture_ref=0.02,
    prior_parallax_ref=0.05,
    prior_decay_start_frac=0.3,
    prior_final_ratio=0.05,
    normal_target="both",
    lambda_depth_normal=0.05,
    lambda_flatten=0.01,
)


@pytest.mark.parametrize(("scale", "log_scale_shift"), [(1e-3, 0.0), (1e3, 0.0), (1.0, -6.0), (1.0, 6.0)])
def test_enhanced_prior_terms_train_at_the_extremes(scene: dict, scale: float, log_scale_shift: float) -> None:
    """Texture weights gated by parallax, the decay, the rendered depth's normals, depth-normal consistency and
    the flatten term: finite, no skipped step, at scene scales 1e-3 / 1e3 (the views and points scaled alike) and
    with tiny / huge Gaussians."""
    views: Views = scene["views"]
    w2c = views.w2c.copy()
    w2c[:, :3, 3] *= scale
    scaled = views.replace(w2c=w2c, prior_depth=views.prior_depth * scale)
    model = init_from_points(scene["points"] * scale, np.full((len(scene["points"]), 3), 0.5), 1, init_opacity=0.5)
    with torch.no_grad():
        model.log_scales += log_scale_shift
    params = TrainParams(**(FAST | {"iterations": 12}), strategy=NoStrategy(), loss=ENHANCED)
    model, curves, metrics = train(model, scaled, params, make_renderer("torch"))
    assert metrics["skipped_steps"] == 0
    assert {"depth", "normal", "depth_normal", "flatten"} <= set(curves)
    assert np.isfinite(curves["total"]).all() and np.isfinite(model.means.detach().numpy()).all()
