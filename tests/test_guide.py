"""Guides for scene-guided extensions: the parent's frames lifted by depth and rendered along the next path.

Ground truth is the procedural world rendered along the next path (colours and depth), which pixels the parent
saw (the truth's own pixels reprojected into the parent frames by this file's maths), and small scenes built
here (two planes, a wall of Gaussians) whose correct guide follows from their construction.
"""

from __future__ import annotations

import numpy as np
import pytest

from wonderverse.camera import Sim3, intrinsics, look_at, move_path
from wonderverse.errors import WonderError
from wonderverse.guide import GuideParams, guide_errors, guide_from_frames, guide_from_splats, validate_guide
from wonderverse.video import initial_pose
from wonderverse.video.base import Guide
from wonderverse.video.procedural import ProceduralVideo

W, H, T = 128, 96, 9
PROMPT = "a quiet village with houses and trees"
TURN_DEG = 30.0


def scene(scale: float = 1.0) -> dict:
    """Parent segment (forward 1 m) and the truth along the next path (turn left 30 deg, forward 0.5 m), in
    scene units (native metres times `scale`)."""
    model = ProceduralVideo(PROMPT, 3, W, H, 60.0, {"fault_probability": 0, "scene_scale": scale})
    parent_path = move_path(initial_pose(model), 0.0, 0.0, 1.0 * scale, 0.0, T)
    parent = model.generate("parent", parent_path, 0, None)
    path = move_path(parent_path[-1], np.radians(TURN_DEG), 0.0, 0.5 * scale, 0.0, T)
    truth = model.generate("next", path, 0, None)
    return {"parent": parent, "path": path, "truth": truth, "K": parent.K}


@pytest.fixture(scope="module")
def world() -> dict:
    return scene()


def guide_of(s: dict, params: GuideParams | None = None, path: np.ndarray | None = None) -> Guide:
    p = s["parent"]
    return guide_from_frames(
        p.frames, p.gt.depth, s["K"], p.gt.poses, s["path"] if path is None else path, s["K"], W, H, params
    )


def frame_errors(g: Guide, truth, i: int) -> dict:
    one = Guide(g.frames[i : i + 1], g.mask[i : i + 1], g.depth[i : i + 1])
    return guide_errors(one, truth.frames[i : i + 1], truth.gt.depth[i : i + 1])


def seen_by(depth: np.ndarray, pose: np.ndarray, K: np.ndarray, parents_depth, parents_pose, tol: float) -> np.ndarray:
    """(H,W) bool: the surface (or sky direction) a view with `depth` and W2C `pose` shows at each pixel is
    shown by some parent frame too (within `tol` relative depth; sky on sky)."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    z = depth.reshape(-1).astype(np.float64)
    sky = ~np.isfinite(z)
    R, t = pose[:3, :3], pose[:3, 3]
    world = (np.where(sky[:, None], 0.0, ray * np.where(sky, 0.0, z)[:, None]) - t) @ R  # R^T (cam - t)
    direction = ray @ R
    seen = np.zeros(len(z), bool)
    for pd, pp in zip(parents_depth, parents_pose, strict=True):
        Rp, tp = pp[:3, :3], pp[:3, 3]
        cam = np.where(sky[:, None], direction @ Rp.T, world @ Rp.T + tp)
        with np.errstate(divide="ignore", invalid="ignore"):
            pu, pv = cam[:, 0] / cam[:, 2] * K[0, 0] + K[0, 2], cam[:, 1] / cam[:, 2] * K[1, 1] + K[1, 2]
        inside = (cam[:, 2] > 0) & (pu >= 0) & (pu < w) & (pv >= 0) & (pv < h)
        idx = np.flatnonzero(inside)
        d = pd[pv[idx].astype(int), pu[idx].astype(int)]
        ok = np.where(sky[idx], ~np.isfinite(d), np.abs(d - cam[idx, 2]) <= tol * cam[idx, 2])
        seen[idx[ok]] = True
    return seen.reshape(h, w)


# ---------------------------------------------------------------- the procedural world


def test_first_guide_frame_is_the_parent_last_frame_again(world: dict) -> None:
    g = guide_of(world)
    assert g.frames.shape == (T, H, W, 3) and g.mask.shape == g.depth.shape == (T, H, W)
    assert g.frames.dtype == np.uint8 and g.mask.dtype == bool and g.depth.dtype == np.float32
    assert g.source == "parent frames"
    e = frame_errors(g, world["truth"], 0)
    # measured on 2026-12-04 (commit 088e394): coverage 1.0, 36.7 dB, AbsRel 0.0010; margins 3 dB (2x the squared
    # error) and 2x
    assert e["coverage"] > 0.97
    assert e["psnr_db"] > 33.5
    assert e["depth_absrel"] < 0.002


def test_turning_left_reveals_the_left_side_as_unknown(world: dict) -> None:
    g = guide_of(world)
    cov = np.array([1.0 - m.mean() for m in g.mask])
    assert np.all(np.diff(cov) <= 0.01), cov  # monotonically-ish less known along the turn
    assert cov[-1] < cov[0] - 0.3, cov
    # the last frame's left quarter shows what the parent never saw; its right half what it saw
    assert g.mask[-1][:, : W // 4].mean() > 0.9
    assert g.mask[-1][:, W // 2 :].mean() < 0.05
    # unknown pixels lie where the parent saw nothing, per the truth reprojected into every parent frame
    p, truth = world["parent"], world["truth"]
    for i in (2, 5, T - 1):
        seen = seen_by(truth.gt.depth[i], world["path"][i], world["K"], p.gt.depth, p.gt.poses, 0.03)
        known = ~g.mask[i]
        assert (known == seen).mean() > 0.95, (i, (known == seen).mean())
        assert (g.frames[i][g.mask[i]] == 0).all() and np.isposinf(g.depth[i][g.mask[i]]).all()


def test_known_pixels_match_the_truth_in_colour_and_depth(world: dict) -> None:
    e = guide_errors(guide_of(world), world["truth"].frames, world["truth"].gt.depth)
    # measured on 2026-12-04 (commit 088e394): 27.6 dB, AbsRel 0.0065, 1.3 % off; margins 3 dB and 2x
    assert e["psnr_db"] > 24.5, e
    assert e["depth_absrel"] < 0.013, e
    assert e["depth_off_share"] < 0.025, e


def test_no_farther_surface_shows_through_a_nearer_one(world: dict) -> None:
    # every parent frame lifted whole: surfaces that later frames hide are in the mix, for the z-buffer to hide
    g, truth = guide_of(world, GuideParams(frame_stride=1, dedup_lifted=False)), world["truth"]
    known = ~g.mask & np.isfinite(g.depth) & np.isfinite(truth.gt.depth)
    behind = g.depth[known] > truth.gt.depth[known] * 1.05
    assert behind.mean() < 1e-3, behind.mean()  # ~3e-3 when the farthest point wins instead


def test_sky_is_known_as_directions_when_asked(world: dict) -> None:
    truth = world["truth"]
    sky = ~np.isfinite(truth.gt.depth)
    assert sky[0].mean() > 0.1, "the test scene needs some sky"
    on = guide_of(world, GuideParams(sky_as_directions=True))
    off = guide_of(world, GuideParams(sky_as_directions=False))
    assert (~on.mask[0][sky[0]]).mean() > 0.97  # the sky the parent saw is known
    inner = sky & np.roll(sky, 1, 1) & np.roll(sky, -1, 1) & np.roll(sky, 1, 2) & np.roll(sky, -1, 2)
    assert np.isposinf(on.depth[~on.mask & inner]).mean() > 0.99  # at infinite depth (off the skyline's edge)
    diff = on.frames[~on.mask & inner].astype(float) - truth.frames[~on.mask & inner]
    assert 10 * np.log10(255.0**2 / np.mean(diff**2)) > 30.0  # the sky moves with rotation only
    assert (~off.mask[sky]).mean() < 0.05  # without: the sky is for the model to invent
    assert np.isposinf(off.depth[~off.mask]).mean() < 0.01


def test_footprints_close_pinholes_when_moving_closer(world: dict) -> None:
    s = world
    closer = move_path(s["path"][0], 0.0, 0.0, 0.6, 0.0, 3)  # magnifies what the parent saw
    full = guide_of(s, GuideParams(hole_fill_radius_px=0), closer)
    single = guide_of(s, GuideParams(hole_fill_radius_px=0, footprint_margin=1.0, max_footprint_px=1.0), closer)
    assert full.coverage > 0.99
    assert single.coverage < full.coverage - 0.01  # 1-pixel points leave pinholes the footprint closes


def test_lifting_every_other_pixel_still_covers_the_view(world: dict) -> None:
    g = guide_of(world, GuideParams(pixel_stride_px=2))
    e = frame_errors(g, world["truth"], 0)
    assert e["coverage"] > 0.97 and e["psnr_db"] > 22.0, e


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_scene_scale_changes_nothing(world: dict, scale: float) -> None:
    ref = guide_errors(guide_of(world), world["truth"].frames, world["truth"].gt.depth)
    s = scene(scale)
    e = guide_errors(guide_of(s), s["truth"].frames, s["truth"].gt.depth)
    assert e["coverage"] == pytest.approx(ref["coverage"], abs=2e-3)
    assert e["psnr_db"] == pytest.approx(ref["psnr_db"], abs=0.3)
    assert e["depth_absrel"] == pytest.approx(ref["depth_absrel"], abs=1e-3)


def test_far_from_the_origin_the_guide_is_the_same(world: dict) -> None:
    shift = np.array([1e5, -1e5, 1e5])  # the world moved: x' = x + shift, so W2C' = W2C with t' = t - R shift

    def moved(poses: np.ndarray) -> np.ndarray:
        out = poses.copy()
        out[:, :3, 3] -= np.einsum("nij,j->ni", poses[:, :3, :3], shift)
        return out

    p = world["parent"]
    ref = guide_of(world)
    g = guide_from_frames(p.frames, p.gt.depth, world["K"], moved(p.gt.poses), moved(world["path"]), world["K"], W, H)
    assert np.array_equal(g.mask, ref.mask) or np.mean(g.mask != ref.mask) < 1e-3
    agree = np.abs(g.frames.astype(int) - ref.frames).max(-1) <= 1
    assert agree.mean() > 0.999
    both = np.isfinite(g.depth) & np.isfinite(ref.depth)
    assert np.allclose(g.depth[both], ref.depth[both], rtol=1e-4)


# ---------------------------------------------------------------- scenes built here


def two_planes(width: int, height: int, K: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour and depth of a view (W2C `pose`) of a far wall (red, world y = 10) behind a near green square
    (y = 4, |x| <= 0.5, 0.5 <= z <= 1.5), ray-cast analytically. Cameras look along +y."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    ray_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R, t = pose[:3, :3], pose[:3, 3]
    c = -R.T @ t
    ray_w = ray_c @ R  # R^T ray: world directions whose camera z is 1
    s_far = (10.0 - c[1]) / ray_w[..., 1]
    s_near = (4.0 - c[1]) / ray_w[..., 1]
    hit = c + s_near[..., None] * ray_w
    on_square = (np.abs(hit[..., 0]) <= 0.5) & (hit[..., 2] >= 0.5) & (hit[..., 2] <= 1.5) & (s_near > 0)
    depth = np.where(on_square, s_near, s_far)  # s is camera z because the ray's camera z is 1
    rgb = np.where(on_square[..., None], np.array([0, 200, 0]), np.array([200, 0, 0])).astype(np.uint8)
    return rgb, depth.astype(np.float32)


def test_a_near_square_hides_the_far_wall_and_what_it_hid_is_unknown() -> None:
    w, h = 80, 60
    K = intrinsics(w, h, 60.0)
    parent_pose = look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 1.0]))
    rgb, depth = two_planes(w, h, K, parent_pose)
    path = np.stack([look_at(np.array([x, 0.0, 1.0]), np.array([x, 1.0, 1.0])) for x in (0.0, 0.4, 0.8)])
    g = guide_from_frames(rgb[None], depth[None], K, parent_pose[None], path, K, w, h)
    for i, pose in enumerate(path):
        true_rgb, true_depth = two_planes(w, h, K, pose)
        square = true_depth < 5
        core = square & np.roll(square, 2, 1) & np.roll(square, -2, 1) & np.roll(square, 2, 0) & np.roll(square, -2, 0)
        # inside the square, no red wall point shows through: the square is green and near
        assert (g.frames[i][core] == true_rgb[core]).all(), i
        assert np.allclose(g.depth[i][core], true_depth[core], rtol=1e-3)
        # the wall the square hid from the parent (wall now, square then) is unknown, beyond pinhole size
        hidden = seen_by(true_depth, pose, K, depth[None], parent_pose[None], 0.01)
        wall_unseen = ~square & ~hidden
        if wall_unseen.sum() > 50:
            assert g.mask[i][wall_unseen].mean() > 0.8
        known_wall = ~square & hidden & ~g.mask[i]
        assert (g.frames[i][known_wall] == true_rgb[known_wall]).all(axis=-1).mean() > 0.98
    assert g.mask[0].mean() == 0.0 and g.mask[2].mean() > 0.05


def test_guide_from_splats_knows_where_the_gaussians_are() -> None:
    from wonderverse.splats.model import init_from_points
    from wonderverse.splats.renderer import make_renderer

    w, h = 48, 32
    K = intrinsics(w, h, 60.0)
    # a dense opaque wall of Gaussians at y = 5 covering the left half of the view (x < 0) of a camera at the
    # origin looking along +y
    xs, zs = np.meshgrid(np.linspace(-6.0, -0.1, 60), np.linspace(-3.0, 3.0, 60))
    pts = np.stack([xs.ravel(), np.full(xs.size, 5.0), zs.ravel()], -1)
    model = init_from_points(pts, np.tile([0, 0, 220], (len(pts), 1)).astype(np.uint8), 0, init_opacity=0.99)
    pose = look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]))
    g = guide_from_splats(model.to_numpy(), Sim3.identity(), pose[None], K, w, h, renderer=make_renderer("torch"))
    assert g.source == "splats" and g.frames.shape == (1, h, w, 3)
    left, right = g.mask[0][:, : w // 2 - 3], g.mask[0][:, w // 2 + 3 :]
    assert not left.any() and right.all()
    assert np.allclose(g.depth[0][:, : w // 2 - 3], 5.0, rtol=0.02)
    assert np.isposinf(g.depth[0][g.mask[0]]).all() and (g.frames[0][g.mask[0]] == 0).all()
    assert np.abs(g.frames[0][:, : w // 2 - 3].astype(int) - [0, 0, 220]).max() <= 12


def test_guide_errors_of_guides_built_here() -> None:
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 240, (2, 8, 10, 3), dtype=np.uint8)
    depth = rng.uniform(1, 5, (2, 8, 10)).astype(np.float32)
    depth[:, 0] = np.inf  # a row of sky
    exact = Guide(frames.copy(), np.zeros((2, 8, 10), bool), depth.copy())
    e = guide_errors(exact, frames, depth)
    assert e == {"coverage": 1.0, "psnr_db": float("inf"), "depth_absrel": 0.0, "depth_off_share": 0.0}
    off = Guide(frames.copy(), np.zeros((2, 8, 10), bool), depth * np.float32(1.1))
    off.mask[:, 4:] = True  # half unknown
    off.frames[:, :4] += 10  # every known colour 10 levels off: MSE 100
    off.depth[:, 1, 0] = np.inf  # one known pixel of each frame called sky where there is ground
    e = guide_errors(off, frames, depth)
    assert e["coverage"] == 0.5
    assert e["depth_absrel"] == pytest.approx(0.1, rel=1e-5)
    # every known ground pixel is 10 % off; the row of sky is right (inf = inf)
    assert e["depth_off_share"] == pytest.approx((3 * 10 * 2) / (4 * 10 * 2))
    assert e["psnr_db"] == pytest.approx(10 * np.log10(255.0**2 / 100.0))


def test_a_parent_without_usable_depth_gives_an_all_unknown_guide(world: dict) -> None:
    p = world["parent"]
    depth = np.where(np.isfinite(p.gt.depth), np.nan, -1.0)  # NaN and <= 0: unknown, nothing to lift
    g = guide_from_frames(p.frames, depth, world["K"], p.gt.poses, world["path"], world["K"], W, H)
    assert g.mask.all() and (g.frames == 0).all() and np.isposinf(g.depth).all() and g.coverage == 0.0


# ---------------------------------------------------------------- bad input


def test_wrong_shapes_are_wonder_errors_naming_what_is_wrong(world: dict) -> None:
    p, path, K = world["parent"], world["path"], world["K"]
    f, d, poses = p.frames, p.gt.depth, p.gt.poses
    cases = [
        ((f[..., 0], d, K, poses, path, K, W, H), "frames"),
        ((f.astype(np.float32), d, K, poses, path, K, W, H), "uint8"),
        ((f, d[:, :-1], K, poses, path, K, W, H), "depth"),
        ((f, d, K[:2], poses, path, K, W, H), "K"),
        ((f, d, K, poses[:-1], path, K, W, H), "w2c"),
        ((f, d, K, poses, path[:, :3], K, W, H), "path"),
        ((f, d, K, poses, path, np.eye(4), W, H), "K_out"),
        ((f, d, K, poses, path, K, 0, H), "size"),
        ((f, d, K, poses * np.nan, path, K, W, H), "w2c"),
    ]
    for args, word in cases:
        with pytest.raises(WonderError, match=word):
            guide_from_frames(*args)
    g = guide_of(world)
    with pytest.raises(WonderError, match=r"guide frames is 128x96, 9 frames but the video is 64x96"):
        validate_guide(g, T, H, 64)
    with pytest.raises(WonderError, match="mask"):
        validate_guide(Guide(g.frames, g.mask[:, :, :-1], g.depth), T, H, W)
    with pytest.raises(WonderError, match="true_frames"):
        guide_errors(g, world["truth"].frames[:, :, :-1], world["truth"].gt.depth)
    validate_guide(g, T, H, W)  # the right size passes
