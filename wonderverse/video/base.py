"""The video-model interface every backend implements."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np


@dataclass
class GroundTruth:
    """What a synthetic backend knows exactly. Never read by the pipeline, only by metrics.

    poses: (T,4,4) float64 W2C of the camera that actually rendered each frame (faults included).
    depth: (T,H,W) float32 camera-space z in metres; +inf where the ray hits nothing (sky).
    normals: (T,H,W,3) float32 unit normals in camera space (OpenCV axes), facing the camera; 0 for sky.
    faults: what went wrong on purpose, e.g. {"type": "teleport", "frames": [12]}; {} when clean.
    guide: for a guided generation, the guide measured against the truth rendered (`wonderverse.guide.guide_errors`:
    coverage, psnr_db, depth_absrel, depth_off_share); None when no guide was used.
    labels: (T,H,W) int16 per pixel, the id of the placed content it shows (what the segments' words named,
    `wonderverse.video.content`), -1 for none (the world's own surfaces, sky); None when the world holds no placed
    content. label_names: label id -> the content's name, its kind and variant ("lake (frozen)", "trees (pine)",
    "table"; kinds are `content.VOCABULARY`'s keys). Pixels with a label >= 0 have finite depth.
    movers: (T,H,W) bool, the pixels showing a moving person or vehicle (`video.movers`), None without movers. depth,
    normals and labels are the static world's, under the movers too; the frames without movers are the static truth.
    """

    poses: np.ndarray
    depth: np.ndarray
    normals: np.ndarray
    faults: dict[str, Any] = field(default_factory=dict)
    guide: dict[str, float] | None = None
    labels: np.ndarray | None = None
    label_names: dict[int, str] = field(default_factory=dict)
    movers: np.ndarray | None = None


@dataclass
class Guide:
    """What is already known along a segment's planned path, for a guided video model to keep.

    frames: (T,H,W,3) uint8 RGB of the known content rendered along the path (0 where unknown).
    mask: (T,H,W) bool, True where nothing is known and the model must invent the pixel.
    depth: (T,H,W) float32 camera-space z of the known content in scene units; +inf where unknown or sky.
    source: what was rendered, e.g. "parent frames" or "splats".
    """

    frames: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    source: str = "parent frames"

    @property
    def coverage(self) -> float:
        """Share of pixels that are known."""
        return float(1.0 - self.mask.mean()) if self.mask.size else 0.0


@dataclass
class Video:
    """frames: (T,H,W,3) uint8 RGB. K: (3,3) float64 pixel intrinsics, exact when `k_is_guess` is False
    (the renderer used them, or the user gave the clip's field of view), else from an assumed field of view."""

    frames: np.ndarray
    K: np.ndarray | None = None
    gt: GroundTruth | None = None
    k_is_guess: bool = True


class VideoModel(Protocol):
    """generate(prompt, camera path, seed, reference frame, guide=None) -> Video.

    path: (T,4,4) float64 W2C poses the video is conditioned on (world frame of the scene); a
    backend that cannot follow a path exactly treats it as guidance. reference: (H,W,3) uint8 frame
    the segment must continue from (its pose is path[0]), or None for the initial video. guide: what is
    already known along `path` (a `Guide` of T frames at the video's size), for a backend that reads one: it
    keeps the known pixels (mask False) and invents the rest. A backend says whether it reads guides with a
    `takes_guide` property (absent: False); callers render and pass a guide only to one that does, and a
    backend that cannot use a guide it is given raises a WonderError (or ignores it, saying so in its doc).
    """

    def generate(
        self, prompt: str, path: np.ndarray, seed: int, reference: np.ndarray | None, guide: Guide | None = None
    ) -> Video: ...
