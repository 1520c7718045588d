"""What every depth and normal prior returns, and the protocols the backends implement.

Conventions: camera space with OpenCV axes (x right, y down, z forward); depth is camera-space z.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

DepthKind = Literal["depth", "inverse_depth"]


def check_frames(frames: np.ndarray) -> tuple[int, int, int]:
    """(B,H,W) of a (B,H,W,3) uint8 RGB batch; ValueError otherwise."""
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be (B,H,W,3) uint8, got {frames.shape} {frames.dtype}")
    b, h, w = frames.shape[:3]
    return b, h, w


@dataclass
class DepthPrediction:
    """depth: (B,H,W) float32, finite. kind: "depth" = camera z up to the backend's scale (metric
    backends: metres); "inverse_depth" = affine-invariant disparity, larger is nearer (what relative
    Depth Anything V2 predicts; align it in inverse-depth space). confidence: (B,H,W) float32 in [0,1] or None.
    """

    depth: np.ndarray
    kind: DepthKind
    confidence: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.depth.ndim != 3 or self.depth.dtype != np.float32:
            raise ValueError(f"depth must be (B,H,W) float32, got {self.depth.shape} {self.depth.dtype}")
        if self.kind not in ("depth", "inverse_depth"):
            raise ValueError(f"unknown depth kind {self.kind!r}")
        if self.confidence is not None and self.confidence.shape != self.depth.shape:
            raise ValueError("confidence must have the depth's shape")


@dataclass
class NormalPrediction:
    """normals: (B,H,W,3) float32 unit vectors in camera space (OpenCV axes), facing the camera
    (n . ray < 0; a wall seen head-on has n = (0,0,-1)); zero where unknown (sky, invalid).
    confidence: (B,H,W) float32 in [0,1] or None.
    """

    normals: np.ndarray
    confidence: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = self.normals
        if n.ndim != 4 or n.shape[-1] != 3 or n.dtype != np.float32:
            raise ValueError(f"normals must be (B,H,W,3) float32, got {n.shape} {n.dtype}")
        if self.confidence is not None and self.confidence.shape != n.shape[:3]:
            raise ValueError("confidence must be (B,H,W)")


class DepthModel(Protocol):
    """predict((B,H,W,3) uint8 RGB) -> DepthPrediction at the frames' resolution."""

    def predict(self, frames: np.ndarray) -> DepthPrediction: ...


class NormalModel(Protocol):
    """predict(frames, K, depth) -> NormalPrediction at the frames' resolution.

    K: (3,3) or (B,3,3) pixel intrinsics (pixel centres at +0.5) when known; depth: (B,H,W) camera z
    (scale-free is fine, an unknown shift is not) for backends that derive normals from depth.
    """

    def predict(
        self, frames: np.ndarray, K: np.ndarray | None = None, depth: np.ndarray | None = None
    ) -> NormalPrediction: ...
