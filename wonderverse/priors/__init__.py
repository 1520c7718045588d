"""Depth and normal priors for the frames of a video segment, and their alignment to SfM depths.

Backends: Depth Anything V2 (transformers) for depth; normals from depth (default), an Omnidata
DPT-hybrid checkpoint, or the ORACLE (degraded procedural ground truth, for benchmarks only). Importing
this package is light: torch and transformers load only when a network backend is built.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from wonderverse.errors import WonderError
from wonderverse.priors.align import (
    AlignedFrames,
    AlignResult,
    align_frames,
    align_scale_shift,
    project_points,
    reference_samples,
)
from wonderverse.priors.base import DepthKind, DepthModel, DepthPrediction, NormalModel, NormalPrediction
from wonderverse.priors.from_depth import NormalsFromDepth, normals_from_depth, orient_towards_camera
from wonderverse.priors.params import (
    ORACLE_LEVELS,
    AlignParams,
    FromDepthParams,
    OracleDegradation,
    PriorsParams,
)

if TYPE_CHECKING:
    from wonderverse.video.base import GroundTruth

__all__ = [
    "ORACLE_LEVELS",
    "AlignParams",
    "AlignResult",
    "AlignedFrames",
    "DepthKind",
    "DepthModel",
    "DepthPrediction",
    "FromDepthParams",
    "NormalModel",
    "NormalPrediction",
    "NormalsFromDepth",
    "OracleDegradation",
    "PriorsParams",
    "align_frames",
    "align_scale_shift",
    "make_depth_model",
    "make_normal_model",
    "normals_from_depth",
    "orient_towards_camera",
    "project_points",
    "reference_samples",
]


def make_depth_model(params: PriorsParams, gt: GroundTruth | None = None) -> DepthModel:
    """The depth backend `params.depth_backend`; the oracle needs the segment's ground truth `gt`."""
    if params.depth_backend == "depth_anything":
        from wonderverse.priors.depth_anything import DepthAnythingV2

        return DepthAnythingV2(params)
    if params.depth_backend == "oracle":
        if gt is None:
            raise WonderError("depth prior 'oracle' needs ground truth; it only runs on procedural (benchmark) videos")
        from wonderverse.priors.oracle import OracleDepth

        return OracleDepth(gt.depth, params.oracle_level, params.oracle_space, params.oracle_seed)
    raise WonderError(f"unknown depth prior backend {params.depth_backend!r}")


def make_normal_model(params: PriorsParams, gt: GroundTruth | None = None) -> NormalModel:
    """The normal backend `params.normal_backend`; the oracle needs the segment's ground truth `gt`."""
    if params.normal_backend == "from_depth":
        return NormalsFromDepth(params.from_depth)
    if params.normal_backend == "dpt":
        from wonderverse.priors.omnidata import OmnidataNormals

        return OmnidataNormals(params)
    if params.normal_backend == "oracle":
        if gt is None:
            raise WonderError("normal prior 'oracle' needs ground truth; it only runs on procedural (benchmark) videos")
        from wonderverse.priors.oracle import OracleNormals

        return OracleNormals(gt.normals, params.oracle_level, params.oracle_seed)
    raise WonderError(f"unknown normal prior backend {params.normal_backend!r}")
