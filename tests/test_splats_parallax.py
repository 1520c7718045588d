"""Where the views can place a surface by parallax (`wonderverse.splats.parallax`), against two-view geometry:
a fronto-parallel plane at depth z seen from two cameras a baseline b apart triangulates to a relative error of
about z / (f b) for one pixel of match error."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from wonderverse.splats.parallax import parallax_gate, triangulation_error
from wonderverse.splats.params import LossParams, TrainParams
from wonderverse.splats.trainer import Views, _Data

F_PX, W, H = 100.0, 160, 120
K = torch.tensor([[F_PX, 0.0, W / 2], [0.0, F_PX, H / 2], [0.0, 0.0, 1.0]])


def shifted(x: float, origin: float = 0.0) -> torch.Tensor:
    """W2C of a camera looking down +z from (origin + x, origin, origin)."""
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 3] = -torch.tensor([origin + x, origin, origin], dtype=torch.float64)
    return m


def yawed(deg: float) -> torch.Tensor:
    """W2C of a camera at the origin turned `deg` about its y axis."""
    a = np.radians(deg)
    m = torch.eye(4, dtype=torch.float64)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    return m


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_a_plane_seen_from_two_cameras_triangulates_to_z_over_f_b(scale: float) -> None:
    b = 0.5 * scale
    others = torch.stack([shifted(0.0), shifted(b)])
    for z in (2.0 * scale, 20.0 * scale):
        err = triangulation_error(torch.full((H, W), z), K, shifted(0.0), others, torch.stack([K, K]))
        assert float(err[H // 2, W // 2]) == pytest.approx(z / (F_PX * b), rel=0.02)
        assert torch.isfinite(err).all()


def test_large_coordinates_keep_the_error() -> None:
    """Cameras a million units from the origin: the same error as at the origin (float64 inside)."""
    near = triangulation_error(
        torch.full((H, W), 5.0), K, shifted(0.0), torch.stack([shifted(0.0), shifted(0.5)]), torch.stack([K, K])
    )
    far = triangulation_error(
        torch.full((H, W), 5.0),
        K,
        shifted(0.0, 1e6),
        torch.stack([shifted(0.0, 1e6), shifted(0.5, 1e6)]),
        torch.stack([K, K]),
    )
    placed = near < 1e3  # the rest is framed by one camera alone: undetermined in both (arccos' noise floor)
    assert 0.3 < float(placed.float().mean()) < 1.0
    assert torch.allclose(far[placed], near[placed], rtol=1e-3)
    assert float(far[~placed].min()) > 1e3


def test_pure_rotation_places_nothing_and_the_prior_keeps_its_full_weight() -> None:
    views = torch.stack([yawed(0.0), yawed(5.0), yawed(-5.0)])
    err = triangulation_error(torch.full((H, W), 3.0), K, yawed(0.0), views, torch.stack([K, K, K]))
    assert torch.isinf(err).all() or float(err.min()) > 1e6
    texture = torch.full((H, W), 0.1)
    assert torch.allclose(parallax_gate(texture, err, 0.05), torch.ones(H, W))


def test_invalid_depth_and_unframed_points_count_as_undetermined() -> None:
    depth = torch.full((H, W), 4.0)
    depth[:, : W // 2] = torch.inf  # sky
    depth[:10] = float("nan")
    err = triangulation_error(depth, K, shifted(0.0), torch.stack([shifted(0.0), shifted(0.3)]), torch.stack([K, K]))
    assert float(err[H // 2, 10]) > 1e20 and float(err[2, W - 20]) > 1e20
    assert np.isfinite(float(err[H // 2, W - 20]))
    # a view that frames none of it (turned away) adds no parallax
    away = yawed(180.0)
    err2 = triangulation_error(torch.full((H, W), 4.0), K, shifted(0.0), torch.stack([away]), K[None])
    assert float(err2.min()) > 1e20


def test_the_gate_is_the_texture_weight_where_views_determine_and_one_where_they_cannot() -> None:
    texture = torch.tensor([0.05, 0.05, 0.05, 1.0])
    err = torch.tensor([1e-4, 0.05, 10.0, 1e-4])
    gated = parallax_gate(texture, err, 0.05)
    assert float(gated[0]) == pytest.approx(0.05, abs=1e-3)
    assert float(gated[1]) == pytest.approx(1 - 0.5 * 0.95)
    assert float(gated[2]) == pytest.approx(1.0, abs=1e-3)
    assert float(gated[3]) == 1.0


def test_the_trainer_gates_aligned_frames_and_leaves_unaligned_ones_to_texture() -> None:
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (3, H, W, 3), dtype=np.uint8)  # texture everywhere: small texture weights
    w2c = torch.stack([shifted(0.0), shifted(0.01), shifted(0.02)]).numpy()
    depth = np.full((3, H, W), 50.0, np.float32)  # far: 2 cm of baseline places nothing at 50 m
    views = Views(frames=frames, w2c=w2c, K=K.numpy(), prior_depth=depth, prior_aligned=np.array([True, True, False]))
    plain = _Data(views, TrainParams(), "cpu")
    gated = _Data(views, TrainParams(loss=LossParams(prior_parallax_ref=0.05)), "cpu", train_ids=[0, 1])
    assert float(plain.prior_weight.mean()) < 0.5
    assert float(gated.prior_weight[:2].min()) > 0.95
    assert torch.equal(gated.prior_weight[2], plain.prior_weight[2])
    params = TrainParams(loss=LossParams(prior_parallax_ref=0.05))
    assert _Data(views, params, "cpu", prior_weights=False).prior_weight is None  # what evaluation builds


def test_an_all_sky_prior_weighs_one_everywhere() -> None:
    frames = np.random.default_rng(1).integers(0, 255, (2, H, W, 3), dtype=np.uint8)
    w2c = torch.stack([shifted(0.0), shifted(1.0)]).numpy()
    views = Views(frames=frames, w2c=w2c, K=K.numpy(), prior_depth=np.full((2, H, W), np.inf, np.float32))
    data = _Data(views, TrainParams(loss=LossParams(prior_parallax_ref=0.05)), "cpu")
    assert torch.isfinite(data.prior_weight).all() and float(data.prior_weight.min()) == pytest.approx(1.0)
