"""The sky map behind the Gaussians: which texel a ray sees, the wrap at longitude ±180°, rays through pixels."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from wonderverse.camera import look_at
from wonderverse.splats.sky import composite, initial_sky, mean_colour, ray_directions, sample_sky

ROWS = 8


def _direction(lat_deg: float, lon_deg: float) -> torch.Tensor:
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    return torch.tensor([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])


def _texel_centre(row: int, col: int) -> tuple[float, float]:
    """(latitude, longitude) in degrees of a texel's centre: row 0 at the +z pole, column 0 from -180°."""
    return 90.0 - (row + 0.5) * 180.0 / ROWS, -180.0 + (col + 0.5) * 360.0 / (2 * ROWS)


def test_a_ray_through_a_texel_centre_sees_exactly_that_texel() -> None:
    sky = torch.zeros(ROWS, 2 * ROWS, 3)
    for row, col in [(0, 0), (3, 5), (7, 15), (4, 8)]:
        sky.zero_()
        sky[row, col] = torch.tensor([1.0, 0.5, 0.25])
        got = sample_sky(sky, _direction(*_texel_centre(row, col))[None])[0]
        torch.testing.assert_close(got, sky[row, col])
        # half a texel east the colour is half-way to the next (empty) texel: bilinear
        lat, lon = _texel_centre(row, col)
        half = sample_sky(sky, _direction(lat, lon + 180.0 / (2 * ROWS))[None])[0]
        torch.testing.assert_close(half, sky[row, col] / 2)


def test_sampling_wraps_across_longitude_180() -> None:
    sky = torch.zeros(ROWS, 2 * ROWS, 3)
    sky[:, 0] = 1.0  # the first column (from -180°) only
    lat = _texel_centre(3, 0)[0]
    # the seam lies half a texel west of column 0's centre: there the first and the last column mix evenly
    for lon in (180.0, -180.0, 179.999):
        got = sample_sky(sky, _direction(lat, lon)[None])[0]
        torch.testing.assert_close(got, torch.full((3,), 0.5), atol=1e-3, rtol=0)


def test_a_one_colour_map_is_that_colour_everywhere_even_at_the_poles() -> None:
    colour = np.array([0.2, 0.4, 0.9], np.float32)
    sky = torch.from_numpy(initial_sky(colour, ROWS))
    assert sky.shape == (ROWS, 2 * ROWS, 3) and initial_sky(colour, 0).shape == (3,)
    dirs = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    dirs = torch.cat([dirs, torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])])
    torch.testing.assert_close(sample_sky(sky, dirs), torch.from_numpy(colour).expand(len(dirs), 3))
    np.testing.assert_allclose(mean_colour(sky.numpy()), colour, rtol=1e-5)


def test_rays_through_pixels_leave_the_camera_along_its_axes() -> None:
    eye, target = np.array([1.0, 2.0, 3.0]), np.array([4.0, 6.0, 3.0])  # looking along (3, 4, 0) / 5
    w2c = torch.tensor(look_at(eye, target, np.array([0.0, 0.0, 1.0])), dtype=torch.float32)
    w, h, f = 41, 31, 30.0
    K = torch.tensor([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    d = ray_directions(w2c, K, w, h)
    assert d.shape == (h, w, 3)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(h, w))
    torch.testing.assert_close(d[15, 20], torch.tensor([0.6, 0.8, 0.0]), atol=1e-6, rtol=0)  # the centre pixel
    assert d[0, 20, 2] > 0.4 and d[30, 20, 2] < -0.4  # image rows run down (OpenCV y), world z is up


@pytest.mark.parametrize("alpha", [0.0, 0.25, 1.0])
def test_the_map_shows_through_where_the_gaussians_are_transparent(alpha: float) -> None:
    w2c = torch.eye(4)
    K = torch.tensor([[4.0, 0.0, 2.0], [0.0, 4.0, 2.0], [0.0, 0.0, 1.0]])
    sky = torch.rand(ROWS, 2 * ROWS, 3, generator=torch.Generator().manual_seed(1))
    rgb = torch.full((4, 4, 3), 0.3) * alpha
    out = composite(rgb, torch.full((4, 4, 1), alpha), sky, w2c, K)
    behind = sample_sky(sky, ray_directions(w2c, K, 4, 4))
    torch.testing.assert_close(out, rgb + (1 - alpha) * behind)
