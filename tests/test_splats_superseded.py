"""wonderverse.splats.superseded on constructed scenes whose geometry is known: a later frame's surface in front of
what an earlier frame shows supersedes those pixels and no others (a box before a wall, a tower against the sky);
a world that did not change supersedes nothing, even with smeared depth edges and from another viewpoint; a frame's
own and earlier segments never supersede it; and superseded pixels leave every loss term of training."""

from __future__ import annotations

import numpy as np
import torch

from wonderverse.config import TrainParams
from wonderverse.splats.model import init_from_points
from wonderverse.splats.renderer import make_renderer
from wonderverse.splats.superseded import superseded_masks, superseded_pixels, surface_points, with_superseded
from wonderverse.splats.trainer import Views, train

W, H = 64, 48
K = np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])
WALL = 20.0  # a wall at world z = 20, seen from cameras on the z axis looking along +z


def _camera(z: float, x: float = 0.0) -> np.ndarray:
    """W2C of a camera at (x, 0, z) with the world's axes (OpenCV: x right, y down, z ahead)."""
    w2c = np.eye(4)
    w2c[:3, 3] = [-x, 0.0, -z]
    return w2c


def _depth(w2c: np.ndarray, box: tuple[float, float, float, float, float] | None = None, sky_above: float = 99.0):
    """Camera z of each pixel of a camera at W2C looking along +z: the wall, sky (inf) where the wall's y is below
    -`sky_above` (OpenCV: y down), and an optional box face (x0, x1, y0, y1, z) in front of it."""
    t = -w2c[:3, 3]
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rx, ry = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    depth = np.full((H, W), WALL - t[2])
    depth[t[1] + ry * depth < -sky_above] = np.inf
    if box is not None:
        x0, x1, y0, y1, bz = box
        d = bz - t[2]
        x, y = t[0] + rx * d, t[1] + ry * d
        depth[(x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)] = d
    return depth


def _box_pixels(w2c: np.ndarray, box: tuple[float, float, float, float, float]) -> np.ndarray:
    return np.isfinite(_depth(w2c, box)) & (_depth(w2c, box) < _depth(w2c) - 1e-9)


BOX = (-1.0, 2.0, -3.0, 1.0, 12.0)  # a box face at z = 12, which the later frames show and the earlier did not


def test_a_later_surface_in_front_supersedes_exactly_the_pixels_it_covers() -> None:
    old, new = _camera(0.0), _camera(5.0)
    later = surface_points(_depth(new, BOX), K, new, stride_px=2)
    got = superseded_pixels(_depth(old), K, old, later, cell_px=4)
    truth = _box_pixels(old, BOX)
    assert truth.sum() > 100
    assert (got & truth).sum() / truth.sum() > 0.9  # recall
    near = np.zeros_like(truth)  # a cell and its dilation around the box: the only place a false mark may be
    ys, xs = np.nonzero(truth)
    near[max(ys.min() - 8, 0) : ys.max() + 9, max(xs.min() - 8, 0) : xs.max() + 9] = True
    assert not (got & ~near).any()


def test_a_tower_against_the_sky_supersedes_the_sky_it_stands_in() -> None:
    old, new = _camera(0.0), _camera(5.0)
    tower = (-1.0, 1.0, -4.0, 2.0, 12.0)  # up into what the old frame shows as sky (y < -2.5 there)
    later = surface_points(_depth(new, tower, sky_above=2.5), K, new, stride_px=2)
    got = superseded_pixels(_depth(old, sky_above=2.5), K, old, later, cell_px=4)
    sky_under_tower = _box_pixels(old, tower) & np.isinf(_depth(old, sky_above=2.5))
    assert sky_under_tower.sum() > 30 and (got & sky_under_tower).mean() / sky_under_tower.mean() > 0.9


def test_an_unchanged_world_supersedes_nothing_even_with_smeared_edges() -> None:
    """Both frames show the same box; the later frame's depth is smeared across its silhouette (as a depth prior
    is), and is seen from a camera beside and ahead of the first."""
    old, new = _camera(0.0), _camera(5.0, x=1.5)
    smeared = _depth(new, BOX)
    k = np.ones(5) / 5
    smeared = np.apply_along_axis(lambda r: np.convolve(r, k, "same"), 1, smeared)[:, 2:-2]
    smeared = np.pad(smeared, ((0, 0), (2, 2)), mode="edge")
    later = surface_points(smeared, K, new, stride_px=2)
    assert not superseded_pixels(_depth(old, BOX), K, old, later, cell_px=4).any()


def test_surfaces_behind_what_a_frame_shows_do_not_supersede_it() -> None:
    old, new = _camera(0.0), _camera(5.0)
    behind = (-1.0, 2.0, -3.0, 1.0, 25.0)  # hidden from the old frame by the wall: no contradiction
    depth_new = _depth(new)
    later = np.concatenate([surface_points(depth_new, K, new, 2), surface_points(_depth(new, behind), K, new, 2)])
    assert not superseded_pixels(_depth(old), K, old, later).any()


def test_only_later_segments_supersede_a_frame() -> None:
    cams = np.stack([_camera(0.0), _camera(5.0), _camera(5.0)])
    depth = np.stack([_depth(cams[0]), _depth(cams[1], BOX), _depth(cams[2], BOX)])
    Ks = [K] * 3
    masks = superseded_masks(depth, Ks, cams, order=[0, 1, 1], targets=[0, 1, 2], sources=[0, 1, 2])
    assert masks is not None and masks[0].any() and not masks[1:].any()
    # the same frames made in the other order: the box came first, the empty wall later supersedes nothing
    assert superseded_masks(depth, Ks, cams, order=[1, 0, 0], targets=[0, 1, 2], sources=[0, 1, 2]) is None
    views = Views(frames=np.zeros((3, H, W, 3), np.uint8), w2c=cams, K=K, prior_depth=depth.astype(np.float32))
    named = with_superseded(views, ["s000_0000", "s001_0000", "s001_0001"], held_out=(), margin=0.15)
    assert named.superseded is not None and named.superseded[0].any() and not named.superseded[1:].any()
    held = with_superseded(views, ["s000_0000", "s001_0000", "s001_0001"], held_out={"s000_0000"}, margin=0.15)
    assert held.superseded is None  # a held-out frame is only scored: nothing is taken from it


def test_superseded_pixels_leave_every_loss_term() -> None:
    """Two trainings that differ only in what a view shows where it is superseded end bit for bit alike (inside
    the superseded patch: the SSIM windows of the pixels around it reach into its border)."""
    rng = np.random.default_rng(0)
    cams = np.stack([_camera(0.0, x) for x in (-0.5, 0.0, 0.5)])
    frames = rng.integers(0, 255, (3, H, W, 3), np.uint8)
    depth = np.stack([_depth(c) for c in cams]).astype(np.float32)
    superseded = np.zeros((3, H, W), bool)
    superseded[1, 10:30, 20:50] = True
    inside = np.zeros_like(superseded)  # farther in than an SSIM window reaches from the pixels that count
    inside[1, 16:24, 26:44] = True
    other = frames.copy()
    other[inside] = 255 - other[inside]
    points = rng.uniform([-8, -6, WALL - 1], [8, 6, WALL + 1], (300, 3))
    colours = rng.random((300, 3))
    params = TrainParams(iterations=12, sh_degree=0, holdout_every=0, checkpoint_every_iters=1000)

    def trained(f: np.ndarray, masks: np.ndarray | None) -> dict[str, np.ndarray]:
        torch.manual_seed(0)
        views = Views(frames=f, w2c=cams, K=K, prior_depth=depth, superseded=masks)
        model, _, _ = train(init_from_points(points, colours, sh_degree=0), views, params, make_renderer("torch"))
        return model.to_numpy()

    first, second = trained(frames, superseded), trained(other, superseded)
    for name, a in first.items():
        assert np.array_equal(a, second[name]), name
    assert not np.array_equal(trained(other, None)["sh0"], second["sh0"])  # unmasked, those pixels count
