"""The video products: splat renders along the camera paths as H.264 files (the novel views' quality is scored by
`wonderverse.quality.score_views` on the frames `quality_picks` chooses)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wonderverse.media import write_mp4
from wonderverse.products import Written


def export_video(rgb: np.ndarray, fps: float, path: Path, description: str) -> Written:
    """Frames (N,H,W,3) uint8 as an H.264 MP4 (faststart) at `fps`."""
    return Written(write_mp4(rgb, path, fps), description)


def quality_picks(n_frames: int, count: int) -> np.ndarray:
    """Indices of the `count` frames of a video of `n_frames` that are scored, evenly spaced."""
    return np.linspace(0, n_frames - 1, min(count, n_frames)).round().astype(int)
