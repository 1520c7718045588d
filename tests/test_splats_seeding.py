"""wonderverse.splats.seeding and Views on constructed arrays: extension seeds only where no Gaussian is,
old Gaussians carried into the new training frame, seeds sized by their nearest Gaussians, and view
subsets that keep every per-frame field."""

from __future__ import annotations

import numpy as np
import pytest

from wonderverse.camera import Sim3, look_at
from wonderverse.config import SplatsStepParams
from wonderverse.errors import WonderError
from wonderverse.splats.model import SH_C0, init_from_points, knn_mean_distance
from wonderverse.splats.seeding import (
    PreviousSplats,
    TrainingStart,
    extended_model,
    extension_seeds,
    initial_model,
    near_views,
    start_training,
)
from wonderverse.splats.trainer import Views, normalize_views

W, H, Z = 32, 24, 4.0  # views of a wall at camera depth 4: x in [-4, 4], y in [-3, 3] (world units)
K = np.array([[16.0, 0, W / 2], [0, 16.0, H / 2], [0, 0, 1]])


def _wall_views(n: int = 2) -> Views:
    """`n` views from the origin looking along +z (OpenCV axes = world axes) at the wall z = 4."""
    frames = np.full((n, H, W, 3), 200, np.uint8)
    return Views(
        frames=frames,
        w2c=np.repeat(np.eye(4)[None], n, axis=0),
        K=K,
        prior_depth=np.full((n, H, W), Z, np.float32),
        prior_normals=np.tile(np.array([0, 0, -1.0], np.float32), (n, H, W, 1)),
    )


def _left_half(spacing: float = 0.1) -> np.ndarray:
    """Gaussian centres covering the wall's left half (x < 0), world units."""
    x, y = np.meshgrid(np.arange(-4.0, 0.0, spacing), np.arange(-3.0, 3.0 + 1e-9, spacing))
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, Z)], -1)


PARAMS = SplatsStepParams().model_copy(update={"init_depth_stride_px": 1, "init_depth_frame_stride": 1})


def test_seeds_go_only_where_no_gaussian_is() -> None:
    old = _left_half()
    voxel = 0.1
    pts, rgb = extension_seeds(old, _wall_views(1), stride_px=1, frame_stride=1, voxel=voxel)
    assert len(pts) > 100
    from scipy.spatial import cKDTree

    assert (cKDTree(old).query(pts)[0] > 2 * voxel).all()  # never beside an old Gaussian
    assert pts[:, 0].min() > 0.0 and pts[:, 0].max() > 3.5  # the whole uncovered right half, nothing left
    np.testing.assert_allclose(pts[:, 2], Z, atol=1e-9)  # on the wall, from the depth prior
    np.testing.assert_allclose(rgb, 200 / 255)
    everywhere, _ = extension_seeds(np.zeros((0, 3)), _wall_views(1), 1, 1, voxel)
    assert everywhere[:, 0].min() < -3.5  # without old Gaussians the left half is seeded too


def test_extended_model_keeps_the_old_gaussians_in_the_new_frame_then_seeds() -> None:
    world_old = _left_half(0.2)
    before, after = Sim3(0.5, np.eye(3), np.zeros(3), center=[1.0, 0, 0]), Sim3(0.25, np.eye(3), np.zeros(3))
    seeded = init_from_points(before.apply(world_old), np.full((len(world_old), 3), 0.5), PARAMS.train.sh_degree)
    seeded = seeded.to_numpy()
    previous = PreviousSplats(seeded, before, ["s000_0000"])
    views = normalize_views(_wall_views(2), after)
    params = PARAMS.model_copy(update={"init_voxel_frac": 0.02})
    model, n_old = extended_model(previous, views, after, [1], params)
    arrays = model.to_numpy()
    assert n_old == len(world_old) and model.num_gaussians > n_old
    np.testing.assert_allclose(arrays["means"][:n_old], after.apply(world_old), atol=1e-5)  # same world places
    np.testing.assert_allclose(arrays["log_scales"][:n_old], seeded["log_scales"] + np.log(0.25 / 0.5), atol=1e-5)
    seeds = arrays["means"][n_old:].astype(np.float64)
    assert after.apply_inverse(seeds)[:, 0].min() > 0.0  # new Gaussians only on the uncovered half
    # each seed sized by its nearest Gaussians, old ones included (not by the distant other seeds alone)
    size = knn_mean_distance(seeds, 3, arrays["means"][:n_old].astype(np.float64))
    np.testing.assert_allclose(np.exp(arrays["log_scales"][n_old:, 0]), size, rtol=1e-5)


def test_the_old_views_near_the_new_ones_are_those_that_see_what_they_see() -> None:
    """Views of the wall, shifted sideways (a camera at x = c sees the wall's x in [c - 4, c + 4]): the new one (3) at
    c = -6 sees the Gaussians at x <= -2 of the left half; view 0 at -6 sees them all, view 1 at 1.8 a sliver of
    them (x >= -2.2), view 2 (turned away) none."""
    w2c = np.repeat(np.eye(4)[None], 4, axis=0)
    w2c[:, 0, 3] = [6.0, -1.8, 0.0, 6.0]  # W2C translation: minus the camera's x
    w2c[2] = look_at(np.array([-6.0, 0, 0]), np.array([-6.0, 0, -4.0]), np.array([0, -1.0, 0]))
    views = _wall_views(4).replace(w2c=w2c)
    old = _left_half()
    assert near_views(old, views, [3], min_overlap=0.05) == [0, 1]
    assert near_views(old, views, [3], min_overlap=0.5) == [0]
    assert near_views(np.zeros((0, 3)), views, [3], 0.05) == []  # no old Gaussian: nothing to hold


def test_initial_model_starts_at_the_sfm_points_plus_the_prior_depth() -> None:
    views = _wall_views(1)
    sfm = np.array([[-2.0, 0, 3.0], [2.0, 1, 3.5], [0.0, -2, 2.0]])  # in front of the wall, far apart
    colors = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    only_sfm = initial_model(views, sfm, colors, PARAMS.model_copy(update={"init_from_depth": False})).to_numpy()
    np.testing.assert_allclose(only_sfm["means"], sfm, atol=1e-6)  # one Gaussian per voxel, at the points
    np.testing.assert_allclose(only_sfm["sh0"][:, 0] * SH_C0 + 0.5, colors / 255, atol=1e-6)
    both = initial_model(views, sfm, colors, PARAMS).to_numpy()["means"]
    on_wall = np.abs(both[:, 2] - Z) < 1e-5
    assert on_wall.sum() > 50 and (~on_wall).sum() == 3  # the wall from the depth prior, and the SfM points
    assert both[on_wall, 0].min() < -3.5 and both[on_wall, 0].max() > 3.5


def test_start_training_continues_from_the_previous_run() -> None:
    views = _wall_views(4)
    names = [f"s000_{i:04d}" for i in range(4)]
    with pytest.raises(WonderError, match="no points"):
        initial_model(views.replace(prior_depth=None), np.zeros((0, 3)), np.zeros((0, 3), np.uint8), PARAMS)
    views.w2c[:, 0, 3] = [0.0, -0.5, -1.0, -1.5]  # cameras 0.5 apart along +x
    first = start_training(views, names, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), PARAMS)
    assert first.fixed == 0 and first.new_views == [] and first.train == PARAMS.train
    assert first.model.num_gaussians > 0 and first.normalization.s == pytest.approx(1 / 0.75)
    previous = PreviousSplats(first.model.to_numpy(), first.normalization, names[:2])
    again = start_training(views, names, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), PARAMS, previous)
    assert again.fixed == first.model.num_gaussians and again.new_views == [2, 3]
    assert again.train.iterations == round(PARAMS.train.iterations * PARAMS.extend_iterations_frac)


def test_held_out_frames_seed_nothing() -> None:
    """A held-out view that alone sees a second wall: no Gaussian starts there, first run or extension, so its
    held-out PSNR measures what training made of the other views."""
    views = _wall_views(4)
    views.prior_depth[3] = 2 * Z  # the last view sees a wall twice as far, which no other view sees
    names = [f"s000_{i:04d}" for i in range(2)] + [f"s001_{i:04d}" for i in range(2)]
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.uint8))

    def far_gaussians(start: TrainingStart) -> int:
        means = start.normalization.apply_inverse(start.model.to_numpy()["means"].astype(np.float64))
        return int((np.abs(means[:, 2] - 2 * Z) < 1e-3).sum())

    assert far_gaussians(start_training(views, names, *empty, PARAMS)) > 50  # seen, and seeded, when not held out
    assert far_gaussians(start_training(views, names, *empty, PARAMS, held_out=["s001_0001"])) == 0
    first = start_training(views.subset([0, 1]), names[:2], *empty, PARAMS)
    previous = PreviousSplats(first.model.to_numpy(), first.normalization, names[:2])
    views.prior_depth[2] = 3 * Z  # the new, trained view sees a third wall: it seeds
    extended = start_training(views, names, *empty, PARAMS, previous, held_out=["s001_0001"])
    assert extended.new_views == [2, 3] and extended.fixed == first.model.num_gaussians
    assert far_gaussians(extended) == 0 and extended.model.num_gaussians > extended.fixed


def test_views_subset_keeps_every_per_frame_field() -> None:
    n = 5
    rng = np.random.default_rng(0)
    per_frame_K = np.stack([K * (1 + i) for i in range(n)])
    views = Views(
        frames=rng.integers(0, 255, (n, 4, 6, 3), np.uint8),
        w2c=np.stack([look_at(np.array([i, 0.0, 0]), np.array([i, 1.0, 0])) for i in range(n)]),
        K=per_frame_K,
        prior_depth=rng.random((n, 4, 6)),
        prior_normals=rng.random((n, 4, 6, 3)),
        masks=rng.random((n, 4, 6)) > 0.5,
        sky=rng.random((n, 4, 6)) > 0.5,
    )
    mask = np.array([False, True, False, True, False])
    for idx, picked in (([3, 1], [3, 1]), (np.array([3, 1]), [3, 1]), (mask, [1, 3])):
        sub = views.subset(idx)
        for name in ("frames", "w2c", "prior_depth", "prior_normals", "masks", "sky"):
            np.testing.assert_array_equal(getattr(sub, name), getattr(views, name)[picked])
        np.testing.assert_array_equal(sub.K, per_frame_K[picked])  # a per-frame K is sliced too
        assert sub.K_of(0)[0, 0] == per_frame_K[picked[0]][0, 0]
    strided = views.subset(slice(None, None, 2))
    np.testing.assert_array_equal(strided.K, per_frame_K[::2])
    np.testing.assert_array_equal(strided.sky, views.sky[::2])
    shared = views.replace(K=K, masks=None).subset([4])
    assert shared.K is K and shared.masks is None and shared.sky.shape == (1, 4, 6)
    assert len(views.subset([])) == 0
    with pytest.raises(TypeError):
        Views(views.frames, views.w2c, K)  # type: ignore[misc]  # by keyword only
