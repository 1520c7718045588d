"""Transient objects: procedural movers with exact masks (`video.movers`) and the robust photometric weights
(`losses.robust_weights`) that keep them out of the static scene. Ground truth comes from the procedural world: the
same clip rendered without movers, and synthetic images whose outlier blob is placed by the test."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from wonderverse.config import build_config
from wonderverse.errors import ConfigError
from wonderverse.splats.losses import (
    confirmed_by_render,
    cross_view_residual,
    outlier_blobs,
    robust_weights,
    total_loss,
    warp_frames,
)
from wonderverse.splats.params import LossParams, RobustLossParams
from wonderverse.splats.trainer import Views, nearest_views, prior_outlier_masks
from wonderverse.video.movers import Mover, render_movers
from wonderverse.video.procedural import ProceduralVideo, demo_path

PROMPT = "a small house decorated for Christmas"


def _clip(movers: int, frames: int = 6):
    video = ProceduralVideo(PROMPT, 0, 64, 48, 60.0, {"fault_probability": 0.0, "movers": movers})
    path = demo_path(video.world.start_pose(), frames, yaw_deg=10.0, forward_m=0.5)
    return video.generate("", path, 0, None)


def test_movers_change_exactly_their_masked_pixels_and_leave_the_truth_static():
    moving, static = _clip(4), _clip(0)
    assert static.gt.movers is None
    masks = moving.gt.movers
    assert masks is not None and masks.shape == moving.frames.shape[:3] and masks.dtype == bool
    changed = (moving.frames != static.frames).any(-1)
    assert not (changed & ~masks).any(), "a pixel outside the mover mask changed"
    assert (changed & masks).sum() >= 0.98 * masks.sum(), "the mask claims pixels that did not change"
    assert 0.005 < masks.mean() < 0.5  # movers are in view, and they do not fill it
    assert not (masks[0] == masks[-1]).all(), "the movers move"
    np.testing.assert_array_equal(moving.gt.depth, static.gt.depth)  # the truth stays the static world's
    again = _clip(4)
    np.testing.assert_array_equal(again.frames, moving.frames)  # reproducible from the seeds


def test_movers_hide_behind_nearer_world_surfaces():
    # rays (1, u, v) from the origin: camera z along world x, so a ray parameter is a depth; one 2 m cube mover
    # centred 5 m ahead (front face at depth 4) fills |u|, |v| < 1/4
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, 41), np.linspace(-0.5, 0.5, 41))
    dirs = np.stack([np.ones(u.size), u.ravel(), v.ravel()], 1)
    cube = Mover(
        "vehicle", np.zeros((1, 3)), np.ones((1, 3)), np.array([[1.0, 0.0, 0.0]]), 0.0, np.array([[5.0, 0, 0]])
    )
    depth = np.full(u.size, np.inf)
    depth[u.ravel() < 0] = 3.0  # a wall in front of the cube on the left
    depth[(u.ravel() >= 0) & (v.ravel() < 0)] = 4.5  # and one behind its front face on the lower right
    colour, mask = render_movers([cube], 0, np.zeros(3), dirs, depth, np.array([0.0, 0.0, 1.0]))
    inside = (np.abs(u.ravel()) < 0.24) & (np.abs(v.ravel()) < 0.24)
    outside = (np.abs(u.ravel()) > 0.26) | (np.abs(v.ravel()) > 0.26)
    assert not mask[u.ravel() < 0].any(), "hidden behind the nearer wall"
    assert mask[inside & (u.ravel() > 0.01)].all(), "in front of the sky and of the farther wall"
    assert not mask[outside].any()
    assert (colour[mask][:, 0] > 0.3).all() and (colour[mask][:, 1:] == 0).all()  # its own (red) colour, lit


def test_options_validate_and_keep_old_keys():
    opts = build_config(PROMPT, preset="preview", overrides={"scene": {"video": {"options": {"movers": 3}}}})
    assert opts.scene.video.options.movers == 3  # type: ignore[union-attr]
    with pytest.raises(ConfigError, match="movers"):
        build_config(PROMPT, preset="preview", overrides={"scene": {"video": {"options": {"movers": -1}}}})
    plain = build_config(PROMPT, preset="preview").scene.video.options.model_dump()  # type: ignore[union-attr]
    assert "movers" not in plain  # off, it is not written: cache keys made before it existed stay the same


def _blob_pair() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, np.ndarray]:
    """A render of fine texture, the frame it was fitted to (off by a little noise everywhere), the same frame with a
    12x10 blob of another colour painted in (a mover the render does not show), and the blob's mask."""
    g = torch.Generator().manual_seed(0)
    h, w = 48, 64
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    texture = 0.5 + 0.3 * torch.sin(xx * 0.9) * torch.cos(yy * 0.7)  # lines one or two pixels wide
    render = texture[..., None].repeat(1, 1, 3)
    frame = (render + 0.02 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    blob = np.zeros((h, w), dtype=bool)
    blob[20:32, 30:40] = True
    moving = frame.clone()
    moving[torch.from_numpy(blob)] = torch.tensor([0.9, 0.1, 0.1])
    return render, frame, moving, blob


def test_robust_weights_drop_a_blob_and_keep_a_clean_image():
    render, frame, moving, blob = _blob_pair()
    params = RobustLossParams(enabled=True, test="render", dilate_px=2)  # grown: the blob's corners are in too
    weights, mask = robust_weights(render, moving, params)
    w = weights.numpy()
    assert w.shape == blob.shape
    assert (w[blob] == 0).all(), "every blob pixel is given up"
    far = np.ones_like(blob)
    far[20 - 6 : 32 + 6, 30 - 6 : 40 + 6] = False  # beyond the patch and the dilation around the blob
    assert (w[far] == 1).all(), "pixels away from the blob keep their weight"
    assert blob.sum() <= mask.numpy().sum() < 2.5 * blob.sum()
    clean_w, clean_mask = robust_weights(render, frame, params)
    assert (clean_w == 1).all() and not clean_mask.any()
    # sparse strong outliers (60 inverted pixels: texture the render missed) are not a mover: nothing dropped
    specks = frame.clone().reshape(-1, 3)
    idx = torch.randperm(specks.shape[0], generator=torch.Generator().manual_seed(1))[:60]
    specks[idx] = 1.0 - specks[idx]
    speck_w, _ = robust_weights(render, specks.reshape(frame.shape), params)
    assert (speck_w == 1).all()


def test_the_render_confirms_the_mover_and_clears_the_world_it_walked_over():
    """The cross-view test flags the mover in this frame and also the world where a slow mover stood in the other
    frames (its trail). Once the scene is learnt, the render shows that world as the frame does and disagrees only
    with the mover: `confirmed_by_render` keeps exactly the mover."""
    render, _, moving, blob = _blob_pair()
    trail = np.zeros_like(blob)
    trail[20:32, 44:54] = True  # beside the mover, where the other frames showed it
    flagged = torch.from_numpy(blob | trail)
    kept = confirmed_by_render(flagged, render, moving, RobustLossParams(enabled=True)).numpy()
    assert kept[blob].all() and not kept[trail].any()
    # the price: a mover the scene already shows (a ghost) agrees with the render and trains as world
    assert not confirmed_by_render(flagged, moving, moving, RobustLossParams(enabled=True)).any()


def test_weighted_loss_ignores_the_dropped_pixels():
    render, frame, moving, _ = _blob_pair()
    weights, _ = robust_weights(render, moving, RobustLossParams(enabled=True, dilate_px=2))
    zeros = torch.zeros_like(render[..., :1])
    kw = {
        "rgb": render,
        "depth": zeros,
        "alpha": zeros + 1,
        "normals": torch.zeros_like(render),
        "params": LossParams(),
    }
    plain_blob = float(total_loss(gt_rgb=moving, **kw)[0])
    robust_blob = float(total_loss(gt_rgb=moving, rgb_weight=weights, **kw)[0])
    robust_clean = float(total_loss(gt_rgb=frame, rgb_weight=weights, **kw)[0])
    plain_clean = float(total_loss(gt_rgb=frame, **kw)[0])
    assert plain_blob - plain_clean > 0.02  # the blob is a large share of the plain loss
    # weighted, the blob adds only what the SSIM window sees past the dropped pixels' edge
    assert robust_blob - robust_clean < 0.15 * (plain_blob - plain_clean)
    assert abs(float(total_loss(gt_rgb=frame, rgb_weight=torch.ones_like(weights), **kw)[0]) - plain_clean) < 1e-6


def _cross_view_masks(clip, ids: list[int], params: RobustLossParams) -> dict[int, np.ndarray]:
    """The cross-view outlier masks of views `ids` of a clip, warped by the true static depth (sky at infinity)."""
    f = torch.from_numpy(clip.frames.astype(np.float32) / 255.0)
    w2c = torch.from_numpy(clip.gt.poses.astype(np.float32))
    K = torch.from_numpy(np.asarray(clip.K, np.float32))
    out = {}
    for i in ids:
        z = torch.from_numpy(np.nan_to_num(clip.gt.depth[i], posinf=1e4).astype(np.float32))
        o = nearest_views(i, ids, params.neighbours)
        warped, valid = warp_frames(z, K, w2c[i], f[o], K.expand(len(o), 3, 3), w2c[o])
        if i == ids[0]:
            static = (f[i][None] - warped).abs().mean(-1)[valid]
            assert valid.float().mean() > 0.6 and float(static.median()) < 0.02, "the static world warps onto itself"
        out[i] = outlier_blobs(cross_view_residual(f[i], warped, valid), params)[1].numpy()
    return out


def test_cross_view_test_finds_the_movers_and_nothing_on_static_footage():
    moving, static = _clip(4, frames=10), _clip(0, frames=10)
    params = RobustLossParams(enabled=True)
    ids = list(range(10))
    learned = _cross_view_masks(moving, ids, params)
    truth = moving.gt.movers
    tp = sum(int((m & truth[i]).sum()) for i, m in learned.items())
    n_learned, n_true = sum(int(m.sum()) for m in learned.values()), int(truth.sum())
    assert tp >= 0.7 * n_true, f"recall {tp / n_true:.2f}"
    assert tp >= 0.5 * n_learned, f"precision {tp / max(n_learned, 1):.2f}"
    clean = _cross_view_masks(static, ids, params)
    assert sum(int(m.sum()) for m in clean.values()) <= 0.002 * static.frames[..., 0].size
    # the same test on a depth prior (here the true one), as seeding would use it
    views = Views(frames=moving.frames, w2c=moving.gt.poses, K=moving.K, prior_depth=moving.gt.depth)
    seeds = prior_outlier_masks(views, ids, params)
    for i in ids:
        np.testing.assert_array_equal(seeds[i], learned[i])


def test_nearest_views_are_the_nearest_training_views():
    assert nearest_views(5, [0, 1, 2, 4, 5, 6, 8, 9], 4) == [4, 6, 2, 8]
    assert nearest_views(0, [0, 1], 4) == [1]


def test_robust_params_validate():
    assert RobustLossParams().enabled is False  # off by default (docs/usage.md, transients)
    assert RobustLossParams().test == "cross_view"
    with pytest.raises(ValidationError):
        RobustLossParams(patch_px=8)  # a patch is centred on its pixel
    with pytest.raises(ValidationError):
        RobustLossParams(outlier_weight=1.0)
    with pytest.raises(ValidationError):
        RobustLossParams(residual_ratio=0.5)
    cfg = build_config(
        PROMPT, preset="preview", overrides={"steps": {"splats": {"train": {"loss": {"robust": {"enabled": True}}}}}}
    )
    assert cfg.steps.splats.train.loss.robust.enabled
    with pytest.raises(ConfigError, match="robust"):
        build_config(
            PROMPT, preset="preview", overrides={"steps": {"splats": {"train": {"loss": {"robust": {"x": 1}}}}}}
        )
