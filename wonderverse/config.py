"""Configuration: the scene spec, every step's parameters, presets and YAML loading.

Precedence, lowest first: model defaults < preset (`configs/presets/NAME.yaml`) < scene file < CLI
arguments. Each layer is merged deeply into the one below it as data, and the result is validated once: a
partial block changes only the settings it names. Every setting is typed and checked when the config is built
(the video backend's own `options` included), so a run never starts on a config that would fail later.
Angles are degrees here (user-facing); the library converts to radians.
"""

from __future__ import annotations

import copy
import functools
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    ValidatorFunctionWrapHandler,
    field_validator,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError

from wonderverse.camera import DEFAULT_FOV_DEG
from wonderverse.check import CheckParams
from wonderverse.errors import ConfigError, shown
from wonderverse.guide import GuideParams
from wonderverse.mesh import MeshParams
from wonderverse.plan_following import PlanFollowingParams
from wonderverse.planning.params import ExtensionSpec, PlannerSpec, PlanParams
from wonderverse.priors.params import PriorsParams
from wonderverse.quality.params import QualityParams
from wonderverse.segment_geometry import GeometryParams
from wonderverse.sfm import SfmParams
from wonderverse.splats.cleanup import ExportPruneParams
from wonderverse.splats.params import TrainParams
from wonderverse.text import (  # noqa: F401 (re-exported: where callers have always found them)
    ALLOWED_CONTROLS,
    CONTROL_NAMES,
    MAX_PROMPT_CHARS,
    control_character,
    plain_words,
    redact_urls,
    url_credentials,
    visible,
    words_problem,
)
from wonderverse.video.diffusion import DiffusionParams, size_problem
from wonderverse.video.files import ClipParams
from wonderverse.video.procedural_options import ProceduralOptions
from wonderverse.yaml_files import MAX_CONFIG_BYTES, MAX_CONFIG_VALUES, read_yaml  # noqa: F401 (re-exported)

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
PRESET_DIR = CONFIG_DIR / "presets"
MAX_ERRORS_SHOWN = 5


class Model(BaseModel):
    """Base for every config model: unknown keys are errors, values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def field_error(loc: tuple[str, ...], message: str, value: Any) -> ValidationError:
    """A validation error located at `loc` (relative to the model that raises it), for checks that span fields:
    raised from a validator, it reports the field it names, not the model."""
    error = InitErrorDetails(type=PydanticCustomError("config", message), loc=loc, input=value)
    return ValidationError.from_exception_data("config", [error])


class VideoSpec(Model):
    """The video backend and the shape of what it renders."""

    backend: Literal["procedural", "files", "diffusers"] = Field(
        "procedural",
        description="procedural: the embedded world; files: the user's clips (`clips`), not generated; "
        "diffusers: a video diffusion model (CogVideoX, Wan, HunyuanVideo; `options` = DiffusionParams)",
    )
    clips: tuple[str, ...] = Field((), description="files backend: video files, image folders or globs, in order")
    frames_per_segment: int = Field(
        25,
        ge=2,
        le=1000,
        description="frames each generated segment is rendered with (diffusers: 8k+1 for CogVideoX, 4k+1 for Wan "
        "and HunyuanVideo); user clips keep their own count (`options.max_frames`)",
    )
    width: int = Field(
        480, ge=32, le=4096, description="generated frames' width in px (diffusers: a multiple of 16); not for clips"
    )
    height: int = Field(
        320, ge=32, le=4096, description="generated frames' height in px (diffusers: a multiple of 16); not for clips"
    )
    fps: float = Field(
        8.0, gt=0, le=240, description="frames per second the stitched video is played at in `preview.mp4`"
    )
    fov_deg: float = Field(DEFAULT_FOV_DEG, gt=5, lt=170, description="horizontal field of view")
    options: ProceduralOptions | ClipParams | DiffusionParams = Field(
        default_factory=dict,
        validate_default=True,
        description="the backend's own settings, by `backend`: ProceduralOptions, ClipParams or DiffusionParams",
        json_schema_extra={"defaults_by_backend": True},
    )

    @field_validator("options", mode="wrap")
    @classmethod
    def _options_of_the_backend(cls, v: Any, handler: ValidatorFunctionWrapHandler, info: ValidationInfo) -> Any:
        model = VIDEO_OPTIONS.get(info.data.get("backend", ""))
        if model is None:  # the backend itself is invalid, and reported so
            return v
        if isinstance(v, model):
            return v
        if isinstance(v, BaseModel):  # another backend's options
            v = v.model_dump()
        return model.model_validate(v)  # its errors keep their place: scene.video.options.<field>

    @model_validator(mode="after")
    def _clips_match_backend(self) -> VideoSpec:
        if self.backend == "files" and not self.clips:
            raise ValueError("the files backend needs at least one clip")
        if self.backend != "files" and self.clips:
            raise ValueError(f"clips are only read by the files backend, not {self.backend!r}")
        return self

    @model_validator(mode="after")
    def _size_fits_the_diffusion_model(self) -> VideoSpec:
        if self.backend == "diffusers" and isinstance(self.options, DiffusionParams):
            problem = size_problem(self.options.family, self.frames_per_segment, self.width, self.height)
            if problem is not None:
                name, why = problem
                raise field_error((name,), why, getattr(self, name))
        return self


VIDEO_OPTIONS: dict[str, type[BaseModel]] = {
    "procedural": ProceduralOptions,
    "files": ClipParams,
    "diffusers": DiffusionParams,
}


class VideoSource(Model):
    """What renders a scene's segments: the video settings, the scene's prompt and its seed."""

    video: VideoSpec
    prompt: str
    seed: int


class SceneSpec(Model):
    """What the user asks for: everything that defines the scene's content."""

    prompt: str = Field(
        description="the scene's description, at most 2000 characters; tabs and line breaks become spaces, other "
        "control characters are refused"
    )
    seed: int = Field(
        0,
        ge=0,
        lt=2**32,
        description="the scene's seed: the procedural world's layout and every attempt's seed (with the segment and "
        "the attempt number) derive from it",
    )
    extensions: ExtensionSpec = ExtensionSpec()
    video: VideoSpec = VideoSpec()
    planner: PlannerSpec = PlannerSpec()

    @property
    def video_source(self) -> VideoSource:
        return VideoSource(video=self.video, prompt=self.prompt, seed=self.seed)

    @field_validator("prompt")
    @classmethod
    def _prompt_ok(cls, v: str) -> str:
        problem = words_problem(v, "the prompt", MAX_PROMPT_CHARS)
        if problem is not None:
            raise ValueError(problem)
        return " ".join(v.split())

    @model_validator(mode="after")
    def _words_are_plain(self) -> SceneSpec:
        """The user's extension words (`extensions.intents`, `extensions.added`) are stored and shown as the prompt
        is: no control characters."""
        for name in ("intents", "added"):
            for i, words in enumerate(getattr(self.extensions, name)):
                try:
                    if not visible(plain_words(words, "the extension")) and words:
                        raise ValueError("the extension holds no visible character (only invisible ones)")
                except ValueError as e:
                    raise field_error(("extensions", name, str(i)), str(e), words) from None
        return self


class CheckStepParams(Model):
    """Step `check`: per-segment SfM, the abnormal-sequence decision, and regeneration."""

    sfm: SfmParams = SfmParams(max_image_size_px=480, num_threads=1)
    rules: CheckParams = CheckParams()
    max_attempts: int = Field(4, ge=1, le=50, description="attempts per segment, the first included")
    on_failure: Literal["fail", "drop", "keep_best"] = Field(
        "keep_best", description="when every attempt fails: stop the run, drop the segment, or keep the best"
    )
    plan_following: PlanFollowingParams | None = Field(
        PlanFollowingParams(),
        description="tolerances of the plan-following test (an attempt that ignored its camera instruction is "
        "regenerated); null: not judged",
    )


# How guided flows render guides. The depth a segment's frames are placed by is good to about 10 % (a monocular
# network aligned to a short clip's SfM), so points of one surface lifted from two frames disagree by that much:
# within 15 % they count as one surface and the frame the extension continues from wins, instead of a farther
# frame's point drawn over it (on 160x112 procedural extensions: +0.5 to +1.2 dB against the library's 3 %).
FLOW_GUIDE = GuideParams(depth_tol_rel=0.15)


class GenerateStepParams(Model):
    """Step `generate_segments`, read only by guided flows (a video model that takes guides: the procedural world
    with `accept_guide`, the `wan_vace` family): how each segment's frames are placed in the plan's world, and how
    an extension's guide is rendered from its parent's placed frames. Unguided flows read none of it, so their
    cache keys never depend on it."""

    geometry: GeometryParams = Field(
        GeometryParams(), description="placing a checked segment's frames in the plan's world (depth fusion, fit)"
    )
    guide: GuideParams = Field(FLOW_GUIDE, description="rendering an extension's guide from its parent's frames")


class PosesParams(Model):
    """Step `poses`: one camera path for the whole stitched video."""

    source: Literal["sfm", "conditioning"] = Field(
        "sfm", description="sfm: one reconstruction over all accepted frames; conditioning: the planned path"
    )
    frame_stride: int = Field(1, ge=1, le=100, description="use every Nth stitched frame for SfM")
    # a held K (the user's camera) is mapped global first here: on the seven RealEstate10K clips with their own
    # FOV held, incremental first ended 0.15-6.3 % of the path off, global first 0.10-0.56 % (wonderverse.sfm notes)
    sfm: SfmParams = SfmParams(max_image_size_px=480, num_threads=2, auto_order_known_k=("global", "incremental"))
    max_segment_disagreement_frac: float = Field(
        0.05, gt=0, description="a segment's poses this far (ATE, share of its path) from its own SfM: re-solve"
    )
    max_segment_turn_error_deg: float = Field(
        5.0,
        gt=0,
        description="a segment's turn (yaw, pitch, roll over its path) this far from what its check read: re-solve",
    )
    disagreement_retries: int = Field(2, ge=0, le=10, description="re-solves (next seeds) while a segment disagrees")
    refine_intrinsics: bool = Field(
        False,
        description="a camera the user gave (a clip's field of view: reconstruct --fov-deg) is held fixed through "
        "the global solve, so every output uses it; true refines it from there (reconstruct --refine-intrinsics). A "
        "guessed K is always estimated, a generated video's K always refined (wonderverse.sfm module notes)",
    )


class PriorsStepParams(Model):
    """Step `priors`. The embedded default (the procedural world has no monocular network to run
    offline) is the oracle with realistic degradation; real video uses Depth Anything V2."""

    models: PriorsParams = PriorsParams(depth_backend="oracle", normal_backend="from_depth")
    sky_beyond_ref: float = Field(
        1.5,
        gt=1,
        description="aligned depth beyond this many times the farthest SfM point seen in the frame is sky "
        "(at 4, 96 % of the realistic oracle's far sky stayed a surface: docs/benchmarks.md)",
    )


class SplatsStepParams(Model):
    """Step `splats`: geometry-aware 3D Gaussian splatting (RGB + depth + normal losses)."""

    train: TrainParams = TrainParams()
    max_side_px: int = Field(480, ge=16, le=8192, description="frames are downscaled to this longer side")
    frame_stride: int = Field(1, ge=1, description="train on every Nth stitched frame")
    init_from_depth: bool = Field(True, description="add back-projected aligned prior depth to the SfM points")
    init_depth_stride_px: int = Field(8, ge=1, description="pixel stride of the depth back-projection")
    init_depth_frame_stride: int = Field(4, ge=1, description="views back-projected: every Nth")
    init_voxel_frac: float = Field(0.01, gt=0, description="seeding voxel size, fraction of the scene scale")
    init_opacity: float = Field(0.1, gt=0, lt=1, description="opacity every seeded Gaussian starts with")
    newest_frames_win: bool = Field(
        True,
        description="where a later segment's frames show a surface in front of what an earlier frame shows there (the "
        "world changed under it: later words placed something), the earlier frame's pixels leave the losses "
        "(`splats.superseded`); else the splats blend both",
    )
    superseded_margin: float = Field(
        0.15, gt=0, lt=1, description="a later surface supersedes a pixel when nearer than this share of its depth"
    )
    # 0.4 and 0.75 (were 0.2 and 0.5): the old frames keep the same 0.1 of the iterations, the new frames get three
    # times as many. Measured (docs/benchmarks.md, benchmarks.scale): the old segments' held-out PSNR rose through
    # every extension either way, while a new segment arrived 3-6 dB below what training the world from scratch
    # gives it; the continuation's steps on the new frames, not the old Gaussians, were what the quality lacked.
    # Then 0.6 on the new frames and 0.75 of the rest on the old frames that see what they see (were 0.75 and none):
    # a world grown "further ahead" overlaps its last few segments, whose frames' share of the steps shrank as the
    # world grew while the new frames' steps moved their Gaussians; they lost 0.7-1.8 dB an extension
    # (docs/benchmarks.md, benchmarks.scale).
    extend_iterations_frac: float = Field(
        0.4, gt=0, le=1, description="after `extend`: iterations (share of train.iterations) continuing the old splats"
    )
    extend_new_view_share: float = Field(
        0.6,
        ge=0,
        lt=1,
        description="after `extend`: share of those iterations on the new frames (the rest keep the old)",
    )
    extend_near_view_share: float = Field(
        0.75,
        ge=0,
        lt=1,
        description="after `extend`: share of the old frames' iterations on those that see what the new frames see "
        "(at least `extend_min_overlap` of it): the new frames' steps move their Gaussians",
    )
    # None (the whole world) by default: on the 2-core CPU a region cost as much as the whole world (forward
    # segments see nearly all of it, and rendering, not the views, is the cost) and froze what the old views show
    # where training the whole world kept improving it (docs/benchmarks.md, benchmarks.scale, 9c4c48f).
    extend_old_views_max: int | None = Field(
        None,
        ge=0,
        description="after `extend`: train a region: the new views and at most this many old views (those seeing "
        "most of what the new views see); Gaussians none of them sees are kept as they are. None: the whole scene",
    )
    extend_min_overlap: float = Field(
        0.05,
        ge=0,
        le=1,
        description="after `extend`: an old view is trained beside the new ones when it sees this "
        "share of the Gaussians they see",
    )
    extend_view_margin_frac: float = Field(
        0.25, ge=0, description="after `extend`: a Gaussian this share of the image size off a trained view is in it"
    )


class OutputsParams(Model):
    """Step `outputs`: the files users open elsewhere (splats, mesh, points, COLMAP/nerfstudio data, videos)."""

    mesh: MeshParams = MeshParams()
    prune: ExportPruneParams = Field(
        ExportPruneParams(), description="Gaussians removed before the splat files are written (floaters, absurd)"
    )
    render_max_side_px: int = Field(480, ge=16, le=8192, description="renders for TSDF and videos: longer side")
    video_frames: int = Field(120, ge=2, le=10_000, description="frames of the fly-through and novel-view videos")
    video_fps: float = Field(
        24.0, gt=0, le=240, description="frames per second of the videos and of the camera-path files' timing"
    )
    novel_offset_frac: float = Field(
        0.1, ge=0, le=1, description="the novel-view path runs this share of the scene extent off the training path"
    )
    colmap: bool = Field(True, description="write colmap/ (images/ and sparse/0/: a dataset COLMAP trainers read)")
    nerfstudio: bool = Field(True, description="write nerfstudio/ (transforms.json, images, depths, camera paths)")
    quality: QualityParams = Field(
        QualityParams(), description="no-reference metrics of novel views: NIQE always; CLIP-S, Q-Align with weights"
    )
    quality_frames: int = Field(8, ge=1, le=1000, description="novel-view frames scored, evenly spaced")


# Below this many pixels of segments to check or give priors, the work runs in the calling process: a LocalCluster's
# start (spawning its workers, each importing the project) costs more than two workers win back (measured in
# `benchmarks.cluster_start`, docs/benchmarks.md)
LOCAL_CLUSTER_MIN_PIXELS = 2_000_000


class ExecutionParams(Model):
    """Where and how fast the steps run: never part of a cache key, since results do not depend on it (a scene
    made on a GPU with gsplat is complete on a CPU machine too)."""

    generate_workers: int = Field(1, ge=1, le=64, description="segments rendered at once")
    segment_workers: int = Field(
        2, ge=1, le=256, description="segments checked / given priors at once (Dask LocalCluster worker processes)"
    )
    cluster_min_pixels: int = Field(
        LOCAL_CLUSTER_MIN_PIXELS,
        ge=0,
        description="a LocalCluster is started only for segments of more pixels (frames x height x width, together) "
        "than this: its start costs seconds that smaller work does not win back (0: always)",
    )
    dask_address: str | None = Field(
        None, description="an existing Dask scheduler for per-segment work, tcp://host:8786 (no user:password@)"
    )
    renderer: Literal["auto", "torch", "gsplat"] = Field("auto", description="auto: gsplat whenever CUDA is there")
    render_workers: int = Field(
        0, ge=0, le=256, description="CPU renderer: views rendered at once in outputs (0 = one per core)"
    )

    @field_validator("dask_address")
    @classmethod
    def _no_credentials(cls, v: str | None) -> str | None:
        problem = url_credentials(v) if v is not None else None
        if problem is not None:
            raise ValueError(problem.replace(" and name it in api_key_env", ""))
        return v


class StepsConfig(Model):
    """Every step's parameters, by step name."""

    plan: PlanParams = PlanParams()
    generate_segments: GenerateStepParams = GenerateStepParams()
    check: CheckStepParams = CheckStepParams()
    poses: PosesParams = PosesParams()
    priors: PriorsStepParams = PriorsStepParams()
    splats: SplatsStepParams = SplatsStepParams()
    outputs: OutputsParams = OutputsParams()


class RunConfig(Model):
    """A full run: the scene and every step's parameters."""

    preset: str = Field(
        "standard",
        description="the preset the settings were composed on (`configs/presets/NAME.yaml`): `--preset`, else the "
        "config file's `preset`, else preview without a CUDA GPU and standard with one",
    )
    scene: SceneSpec

    steps: StepsConfig = StepsConfig()
    execution: ExecutionParams = ExecutionParams()

    @model_validator(mode="after")
    def _poses_known(self) -> RunConfig:
        if self.steps.poses.source != "conditioning":
            return self
        where = ("steps", "poses", "source")
        if self.scene.video.backend == "files":
            raise field_error(where, "user clips have no conditioning path: use steps.poses.source sfm", "conditioning")
        if self.scene.video.backend == "diffusers":  # the path reaches these models only as words
            raise field_error(
                where, "diffusers video models take no camera input: use steps.poses.source sfm", "conditioning"
            )
        return self

    @model_validator(mode="after")
    def _priors_fit_the_video(self) -> RunConfig:
        """The oracle priors read the procedural world's ground truth; no other video backend has any."""
        video = self.scene.video.backend
        if video == "procedural":
            return self
        models = self.steps.priors.models
        instead = {"depth_backend": "depth_anything", "normal_backend": "from_depth"}
        for name, other in instead.items():
            if getattr(models, name) == "oracle":
                raise field_error(
                    ("steps", "priors", "models", name),
                    f"the oracle prior needs the procedural world's ground truth, which {video} video has none of: "
                    f"use {other}",
                    "oracle",
                )
        return self


def default_data(model: type[BaseModel]) -> dict[str, Any]:
    """Every default of `model` as plain data, nested models as their own defaults' dicts (a field whose default
    is `SfmParams(max_image_size_px=480)` gives that 480, not the class's); required fields are left out, except
    models whose other fields have defaults (`RunConfig.scene` without its prompt)."""
    out: dict[str, Any] = {}
    for name, field in model.model_fields.items():
        if _defaults_by_backend(field):
            out[name] = {}
        elif not field.is_required():
            out[name] = _as_data(field.get_default(call_default_factory=True))
        elif isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            out[name] = default_data(field.annotation)
    return out


def _defaults_by_backend(field: Any) -> bool:
    """True for a field whose model (hence whose defaults) depends on another field's value: `VideoSpec.options`."""
    return bool((field.json_schema_extra or {}).get("defaults_by_backend"))


def _as_data(value: Any) -> Any:
    """`value` as plain data: a model as the dict of its fields' values (a backend-keyed field as {})."""
    if not isinstance(value, BaseModel):
        return copy.deepcopy(value)
    fields = type(value).model_fields
    return {name: {} if _defaults_by_backend(f) else _as_data(getattr(value, name)) for name, f in fields.items()}


def deep_merge(base: dict[str, Any], over: dict[str, Any], where: str = "") -> dict[str, Any]:
    """`over` merged into a copy of `base`: mappings merge key by key, anything else replaces. A value that is not
    a mapping where `base` holds one (a block of settings) is a ConfigError naming the block; an empty block
    (None) changes nothing. A tagged block (one of several models, told apart by its `kind`: the splat training's
    `strategy`) whose `kind` changes is replaced, not merged: the other kind's settings would not fit it.
    `where`: the dotted path of `base`, for messages."""
    out = dict(base)
    for k, v in over.items():
        path = f"{where}.{k}" if where else str(k)
        if isinstance(v, BaseModel):  # a whole model given in code: all of its values
            v = v.model_dump()
        if isinstance(out.get(k), dict):
            if v is None:
                continue
            if not isinstance(v, dict):
                raise ConfigError(
                    f"invalid config: {_shown_path(path)}: must be a mapping of settings (got {shown(v)})", field=path
                )
            same_kind = "kind" not in v or v["kind"] == out[k].get("kind")
            out[k] = deep_merge(out[k] if same_kind else {}, v, path)
        else:
            out[k] = v
    return out


def _shown_path(path: str, part_chars: int = 40) -> str:
    """A dotted settings path for a message, each part cut to `part_chars` characters."""
    parts = path.split(".")
    return ".".join(p if len(p) <= part_chars else p[: part_chars - 3] + "..." for p in parts)


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))


@functools.cache
def default_preset() -> tuple[str, str]:
    """(preset, why) for a run that names none: one that finishes on this machine. Without a CUDA GPU the
    splats train on the CPU, where `standard` runs for hours; `preview` takes minutes. Without NVIDIA's driver
    there is no CUDA device to ask torch about (importing it costs ~2 s)."""
    if Path("/proc/driver/nvidia/version").exists() or Path("/dev/nvidiactl").exists():
        import torch

        if torch.cuda.is_available():
            return "standard", "a CUDA GPU is available"
    return "preview", "no CUDA GPU; --preset standard or high for more accuracy"


def load_preset(name: str) -> dict[str, Any]:
    """The settings of the preset `name`, one of `preset_names()` (a name, never a path: a file of settings is a
    config file); ConfigError listing the names otherwise."""
    names = preset_names()
    if not isinstance(name, str) or name not in names:
        raise ConfigError(
            f"unknown preset {shown(name)}; choose one of: {', '.join(names)} (a file of settings is a --config)"
        )
    return read_yaml(PRESET_DIR / f"{name}.yaml")


def format_validation_error(err: ValidationError) -> str:
    """One line per problem (the first MAX_ERRORS_SHOWN): `field.path: message (got VALUE)`, VALUE cut short."""
    lines = []
    errors = err.errors()
    for e in errors[:MAX_ERRORS_SHOWN]:
        loc = _shown_path(".".join(str(p) for p in e["loc"])) or "config"
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            lines.append(f"{loc}: unknown setting")
        elif e["type"] == "missing":
            lines.append(f"{loc}: required setting is missing")
        else:
            msg = msg if len(msg) <= 200 else msg[:197] + "..."
            lines.append(f"{loc}: {msg} (got {shown(e.get('input'))})")
    if len(errors) > MAX_ERRORS_SHOWN:
        lines.append(f"and {len(errors) - MAX_ERRORS_SHOWN} more")
    return redact_urls("; ".join(lines))  # a refused URL is quoted, never its password


def build_config(
    prompt: str | None = None,
    preset: str | None = None,
    config_file: Path | None = None,
    overrides: dict[str, Any] | None = None,
) -> RunConfig:
    """Compose defaults, a preset, a scene file and explicit overrides into a validated RunConfig. The preset is
    `preset`, else the file's, else this machine's default (`default_preset`). Every layer is merged deeply into
    the full defaults as data (`deep_merge`), then the whole is validated once; ConfigError names the field."""
    file_data = read_yaml(config_file) if config_file else {}
    name = preset if preset is not None else file_data.get("preset")
    if name is None:
        name = default_preset()[0]
    merged = deep_merge(default_data(RunConfig), load_preset(name))
    merged = deep_merge(merged, file_data)
    merged["preset"] = name
    if prompt is not None:
        merged = deep_merge(merged, {"scene": {"prompt": prompt}})
    merged = deep_merge(merged, overrides or {})
    merged = _with_video_option_defaults(merged)
    merged = _with_prior_defaults(merged, [load_preset(name), file_data, overrides or {}])
    if "prompt" not in merged["scene"]:
        raise ConfigError("scene.prompt: no prompt given (pass PROMPT or set scene.prompt in the config file)")
    return validate_config(merged)


def _with_video_option_defaults(data: dict[str, Any]) -> dict[str, Any]:
    """`data` with `scene.video.options` merged into the defaults of its backend's options model (which model
    holds the options is known only once every layer has named the backend)."""
    video = data["scene"]["video"]
    model = VIDEO_OPTIONS.get(video.get("backend")) if isinstance(video.get("backend"), str) else None
    if model is None or not isinstance(video.get("options"), dict):
        return data  # validation reports the bad backend or options
    options = deep_merge(default_data(model), video["options"], "scene.video.options")
    return deep_merge(data, {"scene": {"video": {"options": options}}})


def _with_prior_defaults(data: dict[str, Any], layers: list[dict[str, Any]]) -> dict[str, Any]:
    """`data` whose priors, when no layer names a depth backend, fit its video: the oracle (a degraded copy of the
    ground truth) on the procedural world, none on other video, where a depth network needs weights someone
    must name (`steps.priors.models.depth_model`, `--depth-model`): the splats then train on colours alone."""

    def named(layer: Any) -> bool:
        models = ((layer.get("steps") or {}).get("priors") or {}).get("models") if isinstance(layer, dict) else None
        return isinstance(models, dict) and ("depth_backend" in models or "normal_backend" in models)

    backend = data["scene"]["video"].get("backend")
    if backend == "procedural" or any(named(layer) for layer in layers):
        return data
    return deep_merge(data, {"steps": {"priors": {"models": {"depth_backend": "none", "normal_backend": "none"}}}})


def validate_config(data: dict[str, Any]) -> RunConfig:
    try:
        return RunConfig.model_validate(data)
    except ValidationError as e:
        first = ".".join(str(p) for p in e.errors()[0]["loc"]) if e.errors() else None
        raise ConfigError(f"invalid config: {format_validation_error(e)}", field=first) from None


def scene_config(scene_dir: Path | str, name: Literal["config", "segments_config"] = "config") -> RunConfig | None:
    """A RunConfig a scene's root records (`schema.attrs.RootAttrs`): `config`, its last completed run's, or
    `segments_config`, the one its segments were last generated under. Read from the root's metadata without zarr
    (a command judges its inputs with it before anything heavy loads); None for a new scene, a store of a newer
    format, or a record this version cannot read."""
    from wonderverse import STORE_FORMAT
    from wonderverse.folders import root_attrs

    attrs = root_attrs(scene_dir)
    if attrs is None:
        return None
    fmt, data = attrs.get("format"), attrs.get(name)
    if not isinstance(fmt, int) or fmt > STORE_FORMAT or not isinstance(data, dict):
        return None
    try:
        return RunConfig.model_validate(data)
    except (ValidationError, ValueError):
        return None
