"""The region an extension trains (wonderverse.splats.region): which views and Gaussians, held-out frames that keep
their role as a world grows, the kept Gaussians bit for bit, and the held-out figures restated for the scene.

Ground truth is the geometry of a camera row facing a wall: camera x sees the wall (at depth D) over
[x - D·W/(2f), x + D·W/(2f)], so which views overlap and which wall points they see follow by hand."""

from __future__ import annotations

import numpy as np
import pytest

from wonderverse.camera import Sim3
from wonderverse.config import SplatsStepParams
from wonderverse.schema.attrs import SplatMetrics
from wonderverse.splats.region import extension_region, held_out, held_out_figures, scene_figures, visibility
from wonderverse.splats.trainer import Views, split_views

W, H, F, DEPTH = 64, 48, 32.0, 10.0  # the wall is seen over ±DEPTH·W/(2F) = ±10 units around a camera's x
HALF = DEPTH * W / (2 * F)
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])


def _row(xs: np.ndarray) -> np.ndarray:
    """W2C of cameras at (x, 0, 0) looking along +z (OpenCV axes, no rotation)."""
    w2c = np.tile(np.eye(4), (len(xs), 1, 1))
    w2c[:, 0, 3] = -xs
    return w2c


def _wall(lo: float, hi: float, n: int) -> np.ndarray:
    x = np.linspace(lo, hi, n)
    return np.stack([x, np.zeros(n), np.full(n, DEPTH)], axis=1)


def test_visibility_follows_the_image_and_its_margin() -> None:
    w2c = _row(np.array([0.0]))
    pts = np.array([[0, 0, DEPTH], [HALF * 0.9, 0, DEPTH], [HALF * 1.2, 0, DEPTH], [0, 0, -DEPTH], [0, 0, 0]])
    assert visibility(pts, w2c, K, W, H, 0.0)[0].tolist() == [True, True, False, False, False]
    # grown by a quarter of the width on each side: out to 1.5 half-widths
    assert visibility(pts, w2c, K, W, H, 0.25)[0].tolist() == [True, True, True, False, False]
    bad = w2c.copy()
    bad[0, 0, 0] = np.nan
    assert not visibility(pts, bad, K, W, H, 0.25).any()  # a camera without a pose sees nothing


def test_the_region_is_the_new_views_and_the_old_ones_that_see_the_same_wall() -> None:
    old_x = np.arange(0.0, 100.0, 2.0)  # 50 old cameras along a 120-unit wall
    new_x = np.arange(100.0, 110.0, 1.0)  # 10 new ones beyond them
    w2c = _row(np.concatenate([old_x, new_x]))
    means = _wall(-HALF, 100 + HALF, 2000)  # the old Gaussians: what the old cameras saw
    new = list(range(50, 60))
    region = extension_region(means, w2c, K, W, H, new, max_old_views=8, min_overlap=0.05, margin_frac=0.0)
    old_chosen = [i for i in region.views if i < 50]
    # the new cameras see x in [90, 100 + HALF] of the old wall; the old cameras seeing most of it are the last 8
    assert old_chosen == list(range(42, 50))
    assert set(new) <= set(region.views)
    x = means[:, 0]
    seen_lo, seen_hi = old_x[42] - HALF, 100 + HALF  # the chosen cameras' view of the wall
    inside = (x >= seen_lo + 1e-6) & (x <= seen_hi - 1e-6)
    outside = (x < seen_lo - 1e-6) | (x > seen_hi + 1e-6)
    assert region.rendered[inside].all() and not region.rendered[outside].any()
    # most of the world is not even rendered: the share rendered is the share of the wall the chosen cameras see
    assert region.rendered.mean() == pytest.approx((seen_hi - seen_lo) / (100 + 2 * HALF), abs=2e-3)
    # trained: what no other old camera sees, i.e. right of the last unchosen camera's view (x = 82 + HALF)
    free = x > old_x[41] + HALF + 1e-6
    assert (region.trained == (region.rendered & free)).all() and region.trained.any()


def test_old_views_need_the_overlap_to_join_and_the_cap_holds() -> None:
    old_x = np.arange(0.0, 100.0, 2.0)
    w2c = _row(np.concatenate([old_x, [100.0]]))
    means = _wall(-HALF, 100 + HALF, 2000)
    # every old camera within 2·HALF of x=100 overlaps the new view: x > 80 (those at 82..98, nine)
    many = extension_region(means, w2c, K, W, H, [50], max_old_views=100, min_overlap=1e-9, margin_frac=0.0)
    assert [i for i in many.views if i < 50] == [i for i in range(50) if old_x[i] > 100 - 2 * HALF]
    half = extension_region(means, w2c, K, W, H, [50], max_old_views=100, min_overlap=0.5, margin_frac=0.0)
    assert [i for i in half.views if i < 50] == [i for i in range(50) if old_x[i] >= 100 - HALF]  # see ≥ half
    none = extension_region(means, w2c, K, W, H, [50], max_old_views=0, min_overlap=0.0, margin_frac=0.0)
    assert none.views == [50]


def test_a_turn_to_empty_space_takes_the_nearest_old_views() -> None:
    old_x = np.arange(0.0, 20.0, 2.0)
    w2c = _row(np.concatenate([old_x, [21.0]]))
    w2c[-1, :3, :3] = np.diag([-1.0, 1.0, -1.0])  # the new camera looks back, at nothing the old ones saw
    w2c[-1, :3, 3] = -w2c[-1, :3, :3] @ np.array([21.0, 0, 0])
    means = _wall(-HALF, 20 + HALF, 500)
    region = extension_region(means, w2c, K, W, H, [10], max_old_views=3, min_overlap=0.05, margin_frac=0.0)
    assert region.views == [7, 8, 9, 10]  # the three nearest old cameras (14, 16, 18 units along)


def test_held_out_frames_keep_their_role_as_segments_are_added() -> None:
    s1 = [f"s001_{i:04d}" for i in range(16)]
    s2 = [f"s002_{i:04d}" for i in range(16)]
    before = [s1[i] for i in held_out(s1, 8)]
    grown = s2 + s1  # a left extension: its frames come first in the stitched order
    after = [grown[i] for i in held_out(grown, 8)]
    assert before == ["s001_0007", "s001_0015"]
    assert set(before) < set(after) and {n for n in after if n.startswith("s002")} == {"s002_0007", "s002_0015"}
    one = [f"s000_{i:04d}" for i in range(30)]
    assert held_out(one, 8) == split_views(30, 8)[1]  # one clip: the trainer's own split
    short = [f"s{k:03d}_0000" for k in range(20)]  # no segment has 8 frames: every 8th overall
    assert held_out(short, 8) == [7, 15] and held_out(one, 0) == []


def test_figures_are_fresh_where_rendered_and_carried_elsewhere() -> None:
    carried = {"s000_0007": 25.0, "s001_0007": 21.0, "gone_0007": 30.0}
    out = held_out_figures({"s001_0007": 23.0}, carried, ["s000_0007", "s001_0007", "s002_0007"])
    assert out == {"s000_0007": 25.0, "s001_0007": 23.0}  # no figure for a frame never rendered


def test_scene_figures_restate_a_region_s_metrics_over_the_scene() -> None:
    names = [f"s000_{i:04d}" for i in range(8)] + [f"s001_{i:04d}" for i in range(8)]
    test = held_out(names, 4)  # s000_0003, s000_0007, s001_0003, s001_0007
    local = names[8:]  # the region: s001 only
    metrics = {"test_views": [3, 7], "test_psnr_views": [20.0, 22.0], "test_ssim_views": [0.5, 0.7], "test_psnr": 21}

    before = SplatMetrics(
        test_psnr_by_frame={"s000_0003": 30.0, "s000_0007": 28.0, "s001_0003": 10.0},
        test_ssim_by_frame={"s000_0003": 0.9, "s000_0007": 0.9},
    )
    out = scene_figures(metrics, local, names, test, before)
    assert out["test_views"] == [3, 7, 11, 15] and out["rendered_test_views"] == [11, 15]
    assert out["test_psnr_by_frame"] == {"s000_0003": 30.0, "s000_0007": 28.0, "s001_0003": 20.0, "s001_0007": 22.0}
    assert out["test_psnr"] == pytest.approx(25.0) and out["test_ssim"] == pytest.approx(0.75)
    assert len(out["train_views"]) == 12 and not set(out["train_views"]) & set(test)


def test_merged_keeps_the_untouched_gaussians_bit_for_bit_and_moves_the_trained_ones() -> None:
    from wonderverse.splats.model import GaussianModel, init_from_points, normalization_from_cameras
    from wonderverse.splats.seeding import PreviousSplats, merged, start_training

    rng = np.random.default_rng(0)
    old_x = np.arange(0.0, 40.0, 2.0)
    w2c_all = _row(np.concatenate([old_x, [40.0, 41.0]]))
    world = _wall(-HALF, 40 + HALF, 400) + rng.normal(0, 0.01, (400, 3))
    prev_norm = normalization_from_cameras(w2c_all[:20])
    arrays = init_from_points(prev_norm.apply(world), rng.uniform(0, 1, (400, 3)), 0).to_numpy()
    previous = PreviousSplats(arrays, prev_norm, [f"s000_{i:04d}" for i in range(20)])
    names = [*previous.frames, "s001_0000", "s001_0001"]
    region = extension_region(world, w2c_all, K, W, H, [20, 21], 4, 0.05, 0.0)
    frozen = region.rendered & ~region.trained
    assert region.trained.any() and frozen.any() and not region.rendered.all()
    frames = rng.integers(0, 255, (len(region.views), H, W, 3), dtype=np.uint8)
    views = Views(frames=frames, w2c=w2c_all[region.views], K=K)
    p = SplatsStepParams(init_from_depth=False)
    local = [names[i] for i in region.views]
    start = start_training(views, local, world, np.zeros((400, 3), np.uint8), p, previous, region)
    assert start.frozen == frozen.sum() and start.fixed == region.rendered.sum()
    assert len(start.kept["means"]) == 400 - region.trained.sum()
    # the model starts with the frozen ones, then the trained ones, each where it was (in the region's frame)
    first = start.model.to_numpy()["means"][: start.fixed]
    back = first / start.normalization.s + start.normalization.center
    np.testing.assert_allclose(back, np.concatenate([world[frozen], world[region.trained]]), atol=1e-4)
    trained = start.model.to_numpy()
    trained["means"][: start.frozen] += 5.0  # whatever happened to the frozen ones is not taken
    out = merged(start, trained, previous)
    kept = ~region.trained
    for k in GaussianModel.PARAM_NAMES:
        assert np.array_equal(out[k][: kept.sum()], arrays[k][kept]), k  # untouched: the very same values
    # the continued ones, not trained here, come back to where they were (world = centre + x / scale)
    back = out["means"][kept.sum() :] / prev_norm.s + prev_norm.center
    np.testing.assert_allclose(back[: region.trained.sum()], world[region.trained], atol=1e-4)
    assert len(out["means"]) == kept.sum() + len(trained["means"]) - start.frozen
    assert isinstance(prev_norm, Sim3)


def test_frozen_gaussians_are_rendered_but_never_change() -> None:
    """The trainer's `frozen_gaussians`: the first ones keep every value bit for bit while the others learn, and
    they are rendered (the frame they cover is fitted around them, not by the others)."""
    import torch

    from wonderverse.splats.model import init_from_points
    from wonderverse.splats.params import NoStrategy, TrainParams
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.trainer import train

    rng = np.random.default_rng(1)
    n = 300
    pts = np.stack([rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), np.full(n, DEPTH)], axis=1)
    model = init_from_points(pts, rng.uniform(0, 1, (n, 3)), sh_degree=0, init_opacity=0.5)
    w2c = _row(np.array([0.0, 0.5, 1.0, 1.5]))
    frames = rng.integers(0, 255, (4, H, W, 3), dtype=np.uint8)
    before = model.to_numpy()
    params = TrainParams(iterations=20, sh_degree=0, holdout_every=0, strategy=NoStrategy())
    torch.set_num_threads(1)
    out, _, _ = train(model, Views(frames=frames, w2c=w2c, K=K), params, make_renderer("torch"), frozen_gaussians=100)
    after = out.to_numpy()
    for k, a in before.items():
        assert np.array_equal(after[k][:100], a[:100]), k
    assert not np.allclose(after["sh0"][100:], before["sh0"][100:])  # the others learnt
