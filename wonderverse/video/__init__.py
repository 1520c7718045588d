"""Video backends behind one protocol (`VideoModel`), and the factory that picks one."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from wonderverse.video.base import GroundTruth, Video, VideoModel

if TYPE_CHECKING:  # the config pulls in YAML and every step's params; backends import only what they use
    from wonderverse.config import VideoSource

__all__ = ["GroundTruth", "Video", "VideoModel", "initial_pose", "make_video_model", "source_takes_guide"]


def make_video_model(source: VideoSource) -> VideoModel:
    """The backend named in `source.video`, built for this scene (its world, size and options; the options are
    already the backend's own model, validated when the config was built)."""
    v = source.video
    if v.backend == "procedural":
        from wonderverse.video.procedural import ProceduralVideo

        return ProceduralVideo(source.prompt, source.seed, v.width, v.height, v.fov_deg, v.options)
    if v.backend == "files":
        from wonderverse.video.files import FilesVideo

        return FilesVideo(list(v.clips), v.options)
    if v.backend == "diffusers":
        from wonderverse.video.diffusion import DiffusionVideo

        return DiffusionVideo(v.width, v.height, v.frames_per_segment, v.fov_deg, v.options)
    raise ValueError(f"unknown video backend {v.backend!r}")


def source_takes_guide(source: VideoSource) -> bool:
    """Whether the backend `source.video` names reads guides (`takes_guide` of the model it builds), known from
    the settings alone: the procedural world with `options.accept_guide`, a diffusers family with a mask-capable
    pipeline (wan_vace). User clips never do."""
    v = source.video
    if v.backend == "procedural":
        return bool(getattr(v.options, "accept_guide", False))
    if v.backend == "diffusers":
        from wonderverse.video.diffusion import family_takes_guide

        return family_takes_guide(v.options.family)  # type: ignore[union-attr]
    return False


def initial_pose(model: VideoModel) -> np.ndarray:
    """W2C pose the initial video starts from: its world's start pose when the backend has a world
    (the procedural one), else identity (real video models start wherever their first frame is)."""
    world = getattr(model, "world", None)
    return np.asarray(world.start_pose(), dtype=np.float64) if world is not None else np.eye(4)
