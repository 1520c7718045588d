"""The camera-path products: a smooth fly-through along the training path and a novel track beside it, as our own
JSON files and as nerfstudio camera paths (what its viewer exports and `ns-render camera-path` reads)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wonderverse.exports import nerfstudio_dataparser_frame, write_camera_path, write_nerfstudio_camera_path
from wonderverse.paths import flythrough_path, novel_view_path
from wonderverse.products import Written


def video_paths(w2c: np.ndarray, frames: int, offset_frac: float, look: float | None) -> dict[str, np.ndarray]:
    """{"flythrough": a smooth W2C path (frames,4,4) through the training cameras w2c, "novel": a parallel one
    `offset_frac` of the scene's extent off it, looking `look` ahead (the median rendered depth; None: unknown)}."""
    return {
        "flythrough": flythrough_path(w2c, frames),
        "novel": novel_view_path(w2c, frames, offset_frac, look),
    }


def export_camera_paths(
    paths: dict[str, np.ndarray],
    K: np.ndarray,
    size: tuple[int, int],
    fps: float,
    world: str,
    out: Path,
    nerfstudio_of: np.ndarray | None = None,
) -> list[Written]:
    """out/camera_path.json (the fly-through) and out/novel_path.json (W2C, OpenCV axes; our format) for images of
    `size` (width, height) with K; with `nerfstudio_of` (the training cameras W2C the nerfstudio dataset was written
    from), also out/nerfstudio/camera_paths/{flythrough,novel}.json in that dataset's frame."""
    w, h = size
    files = []
    for name, ours in (("flythrough", "camera_path.json"), ("novel", "novel_path.json")):
        files.append(
            Written(write_camera_path(out / ours, paths[name], K, w, h, fps, world=world), f"{name} camera path")
        )
        if nerfstudio_of is not None:
            ns = out / "nerfstudio" / "camera_paths" / f"{name}.json"
            frame = nerfstudio_dataparser_frame(nerfstudio_of)
            write_nerfstudio_camera_path(ns, paths[name], K, w, h, fps, frame, world)
    return files
