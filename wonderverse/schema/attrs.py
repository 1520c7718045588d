"""The attributes of every group of the scene store, as pydantic models: validated when a step writes them
(`SceneStore.staged`, `mark_complete`), typed when they are read (`SceneStore.meta`).

The store keeps its own bookkeeping beside them (`cache_key`, `complete`, `chunk_digests`, `damaged`), which no
model holds. Values are JSON (non-finite floats are written as None). Keys a model does not declare are refused
when written and ignored when read (a store written by another version). Figures whose keys a library function
chooses (a report's timings, a metric per evaluation) are `dict[str, Any]` fields, read as whole tables.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from wonderverse.planning.segments import Plan


class Attrs(BaseModel):
    """A group's attributes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @field_validator("*", mode="before")
    @classmethod
    def _finite(cls, v: Any) -> Any:
        """Non-finite floats become None (JSON has none), as the writers always did."""
        return None if isinstance(v, float) and not math.isfinite(v) else v


class StepAttrs(Attrs):
    """A step's own group: also the seconds its last run took (written by the flow after the step ran)."""

    seconds: float | None = Field(None, description="seconds the step's last run took")


class FileEntry(Attrs):
    """A file (or folder) written beside the store."""

    path: str = Field(description="its name in the scene folder")
    bytes: int = Field(description="its size (a folder's files summed)")
    description: str = Field("", description="what it holds, and the conventions it follows")
    digest: str | None = Field(
        None,
        description="CRC-32C of its bytes (a folder: of its files' paths, sizes and CRCs), checked before the step's "
        "result is trusted: a file missing or altered makes its product run again (None: written before digests)",
    )


class RunRecord(Attrs):
    """One run that completed: when, how far the scene had grown, and the seconds of the steps it ran."""

    finished: str = Field(description="when it finished (ISO 8601, UTC)")
    extensions: int = Field(0, description="the user's extensions the scene had (`extend`)")
    segments: int = Field(0, description="segments the scene had")
    seconds: dict[str, float] = Field(default_factory=dict, description="seconds of each step it ran")


class FailedRun(Attrs):
    """The scene's last run, when it stopped on a failed step (`flows.pipeline`): where, why, and what it had done."""

    finished: str = Field(description="when it stopped (ISO 8601, UTC)")
    step: str = Field(description="the step that failed")
    error: str = Field(description="what went wrong, the line the user saw after `error: step <step> failed: `")
    completed: list[str] = Field(
        default_factory=list, description="the steps that run completed before it (ran or found complete), in order"
    )
    keys: dict[str, str] = Field(
        default_factory=dict, description="the cache key of every step that run needed (the failed one included)"
    )


class RootAttrs(Attrs):
    """The scene (the root group)."""

    format: int = Field(description="store format number; a store of a newer format is refused")
    wonderverse_version: str = Field("", description="the version that created the store")
    spec: dict[str, Any] | None = Field(None, description="the SceneSpec (JSON) of the latest run")
    config: dict[str, Any] | None = Field(
        None, description="the RunConfig (JSON) of the last run that completed; a failed run never replaces it"
    )
    segments_config: dict[str, Any] | None = Field(
        None, description="the RunConfig the segments were last generated under (what a re-run must not discard)"
    )
    runs: list[RunRecord] = Field(
        default_factory=list, description="the runs that completed, oldest first (at most 500)"
    )
    failed_run: FailedRun | None = Field(
        None, description="the last run, when it stopped on a failed step; None once a later run completes"
    )


class PlanAttrs(StepAttrs):
    plan: Plan = Field(description="the Plan: segments with roles, moves, references")
    moves: list[str] = Field(default_factory=list, description="paper-format moves, one per segment")
    intents: list[str] = Field(default_factory=list, description="the user's words per segment (clips: their paths)")


class SegmentsAttrs(StepAttrs):
    order: list[str] = Field(default_factory=list, description="segment ids in stitched order")


class SegmentAttrs(Attrs):
    role: str = Field("init", description="init|left|right|up|down|forward|back")
    reversed: bool = Field(False, description="plays reversed in the stitched video")
    move: str = Field("", description="paper-format move")
    intent: str = Field("", description="the user's words")
    reference_segment: str | None = Field(None, description="parent segment")
    reference_frame: int | None = Field(None, description="generation-order index of the parent frame it continues")
    repeats_reference: bool | None = Field(
        None, description="frame 0 is the parent's frame (None: as its role says, for older stores)"
    )
    k_is_guess: bool = Field(True, description="K guessed rather than known (the renderer's, or a given FOV)")
    read_notes: list[str] = Field(
        default_factory=list,
        description="a user's clip: what reading it did to it (frames subsampled or left out, resizing, assumptions)",
    )
    guide_geometry_key: str | None = Field(
        None, description="guided extensions: the key of the parent's geometry its guide was rendered from"
    )
    guide_params: dict[str, Any] | None = Field(
        None, description="guided extensions: the GuideParams its guide was rendered with (regenerations reuse them)"
    )

    @property
    def repeats(self) -> bool:
        """Whether frame 0 repeats the parent's frame (every generated extension's does)."""
        return self.role != "init" if self.repeats_reference is None else self.repeats_reference


class GuideRecord(Attrs):
    """The guide an extension was generated from."""

    source: str | None = Field(None, description="where it was rendered from; None: generated without one")
    coverage: float | None = Field(None, description="share of its pixels known (0..1)")
    geometry_key: str | None = Field(None, description="the key of the parent geometry it was rendered from")
    reason: str = Field("", description="why there was none")


class AttemptAttrs(Attrs):
    seed: int = Field(0, description="generation seed (0 for a read clip)")
    source: str = Field("", description="video backend")
    guide: GuideRecord | None = Field(None, description="guided extensions: the guide it was generated from")


class GuideTruth(Attrs):
    """A guide against the ground truth rendered along the same path (`wonderverse.guide.guide_errors`)."""

    coverage: float | None = None
    psnr_db: float | None = None
    depth_absrel: float | None = None
    depth_off_share: float | None = None


class GroundTruthAttrs(Attrs):
    faults: dict[str, Any] = Field(default_factory=dict, description="injected faults ({type, frames}; {} clean)")
    label_names: dict[str, str] = Field(
        default_factory=dict, description="label id -> what the words named, e.g. {'0': 'lake (frozen)'}"
    )
    guide: GuideTruth | None = Field(None, description="guided procedural attempts: the guide against the truth")


class KRecord(Attrs):
    """Where the K a reconstruction used came from (`wonderverse.sfm.k_record`)."""

    k_source: str | None = Field(
        None,
        description="given (the renderer's or a given FOV), estimated (refined or self-calibrated by SfM from a "
        "guess) or guessed (the guess kept as it was)",
    )
    K: list[list[float]] | None = Field(None, description="the K used, 3x3 pixels")
    fov_deg: float | None = Field(None, description="horizontal field of view of that K, degrees")
    pixel_aspect: float | None = Field(None, description="fy/fx of that K")


class AttemptSfmAttrs(KRecord):
    mapper: str | None = Field(None, description="the mapper that succeeded")
    reproj_error_px: float | None = None
    n_points: int = 0
    timings: dict[str, float | None] = Field(default_factory=dict, description="seconds per stage")
    problems: list[str] = Field(default_factory=list, description="what went wrong, in words")
    stopped: str = Field("", description="why SfM stopped before mapping (too little parallax); empty when it mapped")
    parallax: dict[str, Any] | None = Field(
        None, description="the look for parallax before mapping (`ParallaxReport.to_attrs`); None when K was known"
    )


class AttemptCheckAttrs(Attrs):
    """The abnormal-sequence decision on an attempt (`CheckResult.to_attrs`), with the plan-following test."""

    accepted: bool = Field(description="the attempt passed")
    reasons: list[str] = Field(default_factory=list, description="why not, in words")
    notes: list[str] = Field(default_factory=list)
    flagged_frames: list[int] = Field(default_factory=list)
    trans_steps: list[float | None] = Field(default_factory=list)
    step_ratio: list[float | None] = Field(default_factory=list)
    rot_steps: list[float | None] = Field(default_factory=list)
    median_step: float | None = None
    registered_frac: float = 0.0
    plan_following: dict[str, Any] | None = Field(
        None, description="the camera against its planned move (`SegmentFollowing.to_attrs`); absent for clips"
    )
    sfm_seconds: float | None = None


class AcceptedAttrs(Attrs):
    """The check's decision on a segment."""

    segment: str = ""
    attempt: int | None = Field(None, description="the attempt later steps follow; None: dropped")
    dropped: bool = False
    reasons: list[str] = Field(default_factory=list, description="why its kept attempt failed (empty: it passed)")
    attempts: int = Field(0, description="attempts judged")
    extra_trials: int = Field(0, description="attempts beyond the first")


class GeometryAttrs(Attrs):
    placed: bool = Field(description="whether the geometry could be placed (False: `reason` says why; no arrays)")
    reason: str = Field("", description="why it could not be placed, in words")
    attempt: int | None = Field(None, description="the accepted attempt it belongs to")
    to_plan: dict[str, Any] | None = Field(None, description="the Sim3 taking the attempt's SfM world onto the plan's")
    fit_rms: float | None = Field(None, description="RMS of the camera centres' residuals after that Sim3, plan units")
    fit_rms_rel: float | None = Field(None, description="the same, share of the planned path's length")
    registered_frames: int | None = None
    aligned_frames: int | None = None
    reasons: list[str] = Field(default_factory=list, description="frames whose depth alignment failed, in words")


class CheckAttrs(StepAttrs):
    segments: list[AcceptedAttrs] = Field(default_factory=list, description="per-segment decisions")
    mean_extra_trials: float = 0.0
    dropped: list[str] = Field(default_factory=list)
    kept_failing: list[str] = Field(default_factory=list)


class SfmAttrs(StepAttrs, KRecord):
    source: Literal["sfm", "conditioning"] = Field("sfm", description="where the poses came from")
    segments: list[str] = Field(default_factory=list, description="segment ids, in the order frame_index numbers them")
    solve: Literal["full", "incremental"] | None = Field(
        None, description="full | incremental (an extension registered into the kept model)"
    )
    new_frames: int | None = Field(None, description="incremental solves: frames registered into the kept model")
    model_to_world: dict[str, Any] | None = Field(None, description="Sim3 (to_dict) from the COLMAP model to the world")
    kept_frame: dict[str, Any] | None = Field(
        None, description="a full re-solve mapped into the previous solve's world: {shared_frames, scale}"
    )
    incremental_problems: list[str] = Field(default_factory=list, description="why an incremental solve fell back")
    incremental_timings: dict[str, float | None] = Field(default_factory=dict)
    segment_disagreement: dict[str, float] = Field(
        default_factory=dict, description="per segment, its path against its own SfM's (share of the path)"
    )
    segment_turn_error_deg: dict[str, float] = Field(
        default_factory=dict, description="per segment, its turn against the one its check read (degrees)"
    )
    solves: int | None = Field(None, description="full solves tried")
    seed_offset: int | None = Field(None, description="the seed offset of the kept solve")
    mapper: str | None = None
    reproj_error_px: float | None = None
    problems: list[str] = Field(default_factory=list)
    timings: dict[str, float | None] = Field(default_factory=dict)
    frames_used: int | None = Field(None, description="frames given to SfM (every frame_stride-th)")
    sfm_names: list[str] = Field(default_factory=list, description="the COLMAP image names of those frames")
    segment_sources: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="per segment, what its frames are: {key, attempt}"
    )
    workspace_key: str | None = Field(None, description="what must not change for the model to be extended")
    k_held: bool | None = Field(
        None, description="the given K was held fixed through the solve (the user's camera); None: written before"
    )
    k_reason: str = Field("", description="why the outputs use this K, in words (empty: written before)")


class PriorsAttrs(StepAttrs):
    backends: list[str] = Field(default_factory=list, description="[depth backend, normal backend]")


class PriorsSegmentAttrs(Attrs):
    segment: str = ""
    kind: str = Field("none", description="depth|inverse_depth (none: no depth prior)")
    aligned_frames: int = 0
    frames: int = 0
    reasons: list[str] = Field(default_factory=list, description="frames whose alignment failed, in words")
    sky_share: float | None = Field(None, description="share of the segment's pixels whose aligned depth is +inf")


class PriorsRawAttrs(Attrs):
    kind: str = Field(description="depth|inverse_depth")


class SplatMetrics(BaseModel):
    """The trainer's figures: views, Gaussians, time, and PSNR/SSIM per evaluation (`test_psnr`, `train_ssim`, ...:
    what `trainer.evaluate` measured; extra keys are kept)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    train_views: list[int] = Field(default_factory=list)
    test_views: list[int] = Field(default_factory=list)
    n_gaussians: int = 0
    scene_scale: float | None = None
    seconds: float | None = None
    background_rgb: list[float] | None = None
    skipped_steps: int = 0
    test_psnr: float | None = None
    test_ssim: float | None = None
    train_psnr: float | None = None
    train_ssim: float | None = None
    test_psnr_by_frame: dict[str, float] = Field(
        default_factory=dict, description="each held-out frame's PSNR (dB), carried where not rendered again"
    )
    test_ssim_by_frame: dict[str, float] = Field(default_factory=dict, description="each held-out frame's SSIM")
    rendered_test_views: list[int] = Field(default_factory=list, description="the held-out views rendered this run")


class SplatsAttrs(StepAttrs):
    normalization: dict[str, Any] = Field(description="the Sim3 from the world to the training frame")
    metrics: SplatMetrics = Field(default_factory=SplatMetrics)
    frames: list[str] = Field(default_factory=list, description="the frames trained on (`s000_0007`)")
    train_digest: str = Field("", description="what must not change for an extension to continue the training")
    poses_digest: str | None = Field(
        None, description="sha256 of the poses of `frames` (W2C float64) trained with: moved, an extension trains all"
    )
    extended_from: dict[str, int] | None = Field(
        None,
        description="an extension's start: {frames, kept_gaussians (carried over), continued_gaussians (trained "
        "again), views (trained)}",
    )
    curves: dict[str, list[float]] = Field(default_factory=dict, description="per-iteration loss terms")


class CheckpointAttrs(Attrs):
    step: int = Field(description="iteration")
    run_key: str = Field(description="the training it belongs to")
    layout: dict[str, Any] = Field(description="the state's tree (JSON) and its tensors' dtypes and shapes")


class OutputFrame(BaseModel):
    """The output world frame: the transform from the `sfm/` frame, up, the statement every file carries and the
    evidence it was estimated from (`GravityFrame.evidence`: source, origin, the camera and ground-plane figures)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    world_from_sfm: dict[str, Any]
    up_in_sfm: list[float]
    world: str
    source: str = ""


class MeshFigures(Attrs):
    triangles: int
    vertices: int
    extent: float | None = Field(None, description="the scene extent the mesh's lengths followed (input units)")
    look: float | None = Field(None, description="median of the fused views' median rendered depths")
    points: int | None = Field(None, description="points in points.ply")
    fused: list[str] = Field(default_factory=list, description="the cameras its fusion holds (pose digests)")
    keys: list[str] = Field(
        default_factory=list, description="those of `fused` that are frames' poses (the others lie between two)"
    )
    view_depths: list[float | None] = Field(default_factory=list, description="each fused view's median depth")


class Bounds(Attrs):
    """An axis-aligned box: its lowest and highest corner."""

    min: list[float]
    max: list[float]


class PruneRecord(BaseModel):
    """What `splats.cleanup.prune_for_export` removed before the splat files were written (extra keys are kept)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    before: int = Field(description="Gaussians trained")
    after: int = Field(description="Gaussians exported")
    removed: dict[str, int] = Field(default_factory=dict, description="Gaussians removed, by reason")
    needles_shortened: int = Field(0, description="needles whose largest axis was cut to `max_needle_ratio`")
    extent: float | None = Field(None, description="the scene extent the thresholds followed (world units)")
    bounds_before: Bounds | None = Field(None, description="the box of the finite centres before (world units)")
    bounds_after: Bounds | None = Field(None, description="the box of the exported centres (world units)")
    params: dict[str, Any] = Field(default_factory=dict, description="the ExportPruneParams it ran with")


class QualityScores(Attrs):
    niqe: float | None = None
    clip_s: float | None = None
    q_align: float | None = None


class OutputProductAttrs(Attrs):
    """One product of the outputs step: its files, and its figures (only the product's own field is set)."""

    files: list[FileEntry] = Field(default_factory=list)
    settings: str = Field("", description="digest of the settings it was made with (what going on from it needs)")
    frames: dict[str, str] = Field(
        default_factory=dict, description="datasets: per frame, a digest of the pixels and pose its files hold"
    )
    frame: OutputFrame | None = None
    mesh: MeshFigures | None = None
    pruned: PruneRecord | None = Field(None, description="the splat files: what pruning removed")
    points: int | None = Field(None, description="the point cloud: its points")
    colmap: dict[str, Any] | None = Field(None, description="the COLMAP dataset: {tracks_from}")
    nerfstudio: dict[str, Any] | None = Field(None, description="the nerfstudio dataset: depth pixels written, clipped")
    quality: QualityScores | None = None


class OutputsAttrs(StepAttrs):
    files: list[FileEntry] = Field(default_factory=list, description="every file written beside the store")
    frame: OutputFrame = Field(description="the output world frame")
    mesh: MeshFigures
    render_size: list[int] = Field(description="[width, height] of the renders")
    quality: QualityScores = Field(default_factory=QualityScores)
    pruned: PruneRecord | None = Field(None, description="what pruning removed before the splat files")
    colmap: dict[str, Any] | None = None
    nerfstudio: dict[str, Any] | None = None
    made: list[str] = Field(default_factory=list, description="the products the last run made (the rest unchanged)")

    @field_validator("pruned", mode="before")
    @classmethod
    def _nothing_pruned(cls, v: Any) -> Any:
        """Older stores wrote {} when nothing was recorded."""
        return v or None


class NoAttrs(Attrs):
    """A group that carries no attributes of its own."""
