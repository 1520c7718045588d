"""render_views: world cameras in, world-unit depth out, whatever the training normalisation."""

from __future__ import annotations

import numpy as np

from wonderverse.camera import Sim3
from wonderverse.splats.renderer import TorchRenderer
from wonderverse.splats.views import render_views


def _plane(z_world: float, norm: Sim3) -> dict[str, np.ndarray]:
    """A grid of flat, opaque Gaussians on the world plane z = z_world, in the training frame."""
    g = np.linspace(-3, 3, 25)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    world = np.concatenate([xy, np.full((len(xy), 1), z_world)], 1)
    n = len(world)
    step = (g[1] - g[0]) * norm.s
    return {
        "means": norm.apply(world).astype(np.float32),
        "quats": np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
        "log_scales": np.log(np.tile([step, step, 1e-3 * step], (n, 1))).astype(np.float32),
        "logit_opacities": np.full(n, 6.0, np.float32),
        "sh0": np.full((n, 1, 3), 0.5, np.float32),
        "shN": np.zeros((n, 0, 3), np.float32),
    }


def test_depth_in_world_units_and_sky_is_inf() -> None:
    norm = Sim3(0.37, np.eye(3), np.zeros(3), center=[1.0, -2.0, 0.5])
    arrays = _plane(5.0, norm)
    K = np.array([[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]])
    looking = np.eye(4)  # camera at the origin looking down +z at the plane
    away = np.eye(4)
    away[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down -z: nothing in front
    views = list(render_views(arrays, norm, np.stack([looking, away]), K, 64, 48, TorchRenderer()))
    centre = views[0].depth[16:32, 24:40]
    assert np.all(np.abs(centre - 5.0) < 0.05), centre
    assert np.all(np.abs(np.abs(views[0].normals[16:32, 24:40, 2]) - 1) < 1e-2)
    assert np.isinf(views[1].depth).all() and views[1].alpha.max() < 1e-3
    assert views[0].rgb.shape == (48, 64, 3) and views[0].rgb.min() >= 0 and views[0].rgb.max() <= 1


def test_renders_in_threads_match_one_at_a_time_and_keep_order() -> None:
    import torch

    norm = Sim3.identity()
    arrays = _plane(5.0, norm)
    arrays["sh0"] = np.random.default_rng(0).uniform(0, 1, arrays["sh0"].shape).astype(np.float32)
    K = np.array([[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]])
    poses = np.tile(np.eye(4), (7, 1, 1))
    poses[:, 0, 3] = np.linspace(-1, 1, 7)  # every view different, so a swapped order would show
    threads = torch.get_num_threads()
    one = list(render_views(arrays, norm, poses, K, 64, 48, TorchRenderer()))
    many = list(render_views(arrays, norm, poses, K, 64, 48, TorchRenderer(), workers=3))
    assert len(many) == 7
    for a, b in zip(one, many, strict=True):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
    assert not np.array_equal(one[0].rgb, one[-1].rgb)
    assert torch.get_num_threads() == threads  # the thread count is given back


def test_ordered_map_keeps_order_and_bounds_lookahead() -> None:
    import threading
    import time

    from wonderverse.splats.views import ordered_map

    started: list[int] = []
    lock = threading.Lock()

    def slow(i: int) -> int:
        with lock:
            started.append(i)
        time.sleep(0.01 * (i % 3))  # later items finish first sometimes
        return i * i

    out = []
    for r in ordered_map(slow, range(20), 2):
        out.append(r)
        with lock:
            assert len(started) <= len(out) + 4  # never more than 2 x workers ahead of the consumer
    assert out == [i * i for i in range(20)]
