"""Diagnostic plots: valid PNGs of a sensible size, flagged steps drawn, trajectories projected right."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from wonderverse.camera import camera_centers, look_at
from wonderverse.check import CheckParams, check_trajectory
from wonderverse.plots import (
    segment_check_figure,
    segment_check_plot,
    trajectory_topview_figure,
    trajectory_topview_plot,
)


def dolly(n: int, jumps: tuple[int, ...] = ()) -> np.ndarray:
    """W2C poses moving along world x (looking along +y), with 10-step jumps after the given frames."""
    x = np.arange(n) * 0.2
    for j in jumps:
        x[j + 1 :] += 2.0
    return np.stack([look_at(np.array([xi, 0.0, 1.0]), np.array([xi, 5.0, 1.0])) for xi in x])


def open_png(data: bytes) -> Image.Image:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    im = Image.open(io.BytesIO(data))
    im.load()
    return im


@pytest.mark.parametrize("mode", ["scale_free", "absolute"])
def test_segment_check_plot_is_a_png_with_flagged_steps_marked(mode: str) -> None:
    params = CheckParams(translation_mode=mode, abs_trans_thresh=1.0)
    res = check_trajectory(dolly(20, jumps=(4, 11)), np.ones(20, bool), params)
    assert res.flagged_frames == [4, 11]
    png = segment_check_plot(res, params, "segment 3, attempt 0")
    im = open_png(png)
    assert im.format == "PNG" and 600 <= im.width <= 1200 and 300 <= im.height <= 800
    fig, info = segment_check_figure(res, params, "t")
    assert info == {"flagged_marked": 2, "n_steps": 19}
    # The red markers sit at the flagged frame pairs on both panels.
    for ax in fig.axes:
        (marks,) = [c for c in ax.collections if c.get_gid() == "flagged"]
        np.testing.assert_array_equal(marks.get_offsets()[:, 0], [4, 11])
    assert "rejected" in fig.get_suptitle()


def test_segment_check_plot_without_flags_and_with_nan_steps() -> None:
    poses = dolly(12)
    reg = np.ones(12, bool)
    reg[5] = False
    poses[5] = np.nan
    res = check_trajectory(poses, reg, CheckParams(allow_gaps=False))
    fig, info = segment_check_figure(res)
    assert info["flagged_marked"] == 0
    assert all(not [c for c in ax.collections if c.get_gid() == "flagged"] for ax in fig.axes)
    open_png(segment_check_plot(res))


def test_topview_pca_plane_recovers_the_plane_of_motion() -> None:
    # A circle of radius 3 in a tilted plane: its top view on the two main components is a circle again.
    a = np.radians(np.arange(0, 360, 15))
    tilt = np.radians(35.0)
    circle = np.stack([3 * np.cos(a), 3 * np.sin(a) * np.cos(tilt), 3 * np.sin(a) * np.sin(tilt)], axis=1)
    poses = np.stack([look_at(c, np.zeros(3)) for c in circle])
    fig, info = trajectory_topview_figure([poses], ["tilted orbit"], plane="pca")
    assert info == {"plane": "PC", "n_cameras": [len(a)]}
    line = fig.axes[0].lines[0]
    xy = np.stack([line.get_xdata(), line.get_ydata()], axis=1)
    np.testing.assert_allclose(np.linalg.norm(xy - xy.mean(0), axis=1), 3.0, rtol=1e-6)
    # Viewing directions point to the centre, so the in-plane arrows are radial and inward.
    q = fig.axes[0].collections[0]
    uv = np.stack([q.U, q.V], axis=1)
    inward = -(xy - xy.mean(0))
    cos = np.sum(uv * inward, axis=1) / (np.linalg.norm(uv, axis=1) * np.linalg.norm(inward, axis=1))
    np.testing.assert_allclose(cos, 1.0, atol=1e-6)


def test_topview_xy_plane_uses_world_coordinates_and_skips_unregistered() -> None:
    poses = dolly(10)
    poses[3] = np.nan
    est = poses.copy()
    est[:, :3, 3] += 0.01
    png = trajectory_topview_plot([poses, est, np.full((4, 4, 4), np.nan)], ["gt", "sfm", "failed"], "xy", "xy")
    im = open_png(png)
    assert 400 <= im.width <= 900 and 400 <= im.height <= 900
    fig, info = trajectory_topview_figure([poses, est, np.full((4, 4, 4), np.nan)], ["gt", "sfm", "failed"], "xy", "xy")
    assert info == {"plane": "xy", "n_cameras": [9, 9, 0]}
    gt_line = fig.axes[0].lines[0]
    np.testing.assert_allclose(gt_line.get_xdata(), np.delete(camera_centers(dolly(10))[:, 0], 3))
    np.testing.assert_allclose(gt_line.get_ydata(), 0.0, atol=1e-12)
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["gt", "sfm", "failed (no registered frames)"]


def test_topview_rejects_mismatched_labels() -> None:
    with pytest.raises(ValueError):
        trajectory_topview_plot([dolly(3)], ["a", "b"])
