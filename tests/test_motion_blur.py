"""Training renders smeared like the video: the trainer's blur against the procedural world's own (numpy,
wonderverse.video.defects) on a rendered frame with its true depth and poses."""

import numpy as np
import pytest
import torch

from wonderverse.camera import move_path
from wonderverse.splats.motion_blur import image_velocity, smear
from wonderverse.video import initial_pose
from wonderverse.video.defects import image_motion, motion_blur
from wonderverse.video.procedural import ProceduralVideo


@pytest.fixture(scope="module")
def clip() -> dict:
    model = ProceduralVideo("a small house decorated for Christmas", 0, 96, 64, 60.0, {"fault_probability": 0.0})
    path = move_path(initial_pose(model), np.radians(-20), 0.0, 1.5, -0.5, 5)
    video = model.generate("a small house", path, 0, None)
    return {"frames": video.frames, "depth": video.gt.depth, "poses": video.gt.poses, "K": video.K}


def test_the_velocity_is_the_procedural_worlds_image_motion_central_difference(clip: dict) -> None:
    d, P, K = clip["depth"][2], clip["poses"], clip["K"]
    want = (image_motion(d, P[2], P[3], K) - image_motion(d, P[2], P[1], K)) / 2
    t = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float64)  # noqa: E731
    alpha = torch.where(torch.isfinite(t(d)), 1.0, 0.0)
    got = image_velocity(t(d), alpha, t(P[2]), t(P[1]), t(P[3]), 2, t(K)).numpy()
    assert np.abs(want).max() > 1.0  # the camera moves: pixels travel more than a pixel per frame somewhere
    np.testing.assert_allclose(got, want, atol=1e-6 * np.abs(want).max())


def test_the_smear_matches_the_procedural_worlds_motion_blur(clip: dict) -> None:
    d, P, K = clip["depth"][2], clip["poses"], clip["K"]
    flow = (image_motion(d, P[2], P[3], K) - image_motion(d, P[2], P[1], K)) / 2
    frame = clip["frames"][2].astype(np.float32)
    want = motion_blur(frame, flow, 0.5, 7, 32.0)
    got = smear(torch.as_tensor(frame), torch.as_tensor(flow), 0.5, 7, 32.0).numpy()
    assert np.abs(want - frame).mean() > 1.0  # the blur changes the frame
    assert np.abs(got - want).max() < 1e-2 * 255


def test_no_motion_or_a_still_camera_leaves_the_render_as_it_is(clip: dict) -> None:
    rgb = torch.rand(16, 24, 3, requires_grad=True)
    out = smear(rgb, torch.zeros(16, 24, 2), 0.5, 5, 32.0)
    torch.testing.assert_close(out, rgb)
    out.sum().backward()  # differentiable in the render
    torch.testing.assert_close(rgb.grad, torch.ones_like(rgb))
    P, K = torch.as_tensor(clip["poses"][2]), torch.as_tensor(clip["K"])
    depth = torch.full((16, 24), 3.0, dtype=torch.float64)
    assert not image_velocity(depth, torch.ones_like(depth), P, P, P, 2, K).abs().any()
    assert not image_velocity(depth, torch.ones_like(depth), P, P, P, 0, K).abs().any()


def test_the_smear_is_capped(clip: dict) -> None:
    rgb = torch.zeros(8, 64, 3)
    rgb[:, 32] = 1.0  # one bright column
    out = smear(rgb, torch.tensor([1000.0, 0.0]).expand(8, 64, 2), 1.0, 33, 8.0)
    lit = (out[0, :, 0] > 0).nonzero().ravel()
    assert 8 <= int(lit.max() - lit.min()) + 1 <= 10  # 8 px long (bilinear: a pixel more at most)
    assert torch.isfinite(out).all()
