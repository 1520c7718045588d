"""Configuration: the scene spec, every step's parameters, presets and YAML loading.

Precedence, lowest first: model defaults < preset (`configs/presets/NAME.yaml`) < scene file < CLI
arguments. Angles are degrees here (user-facing); the library converts to radians.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from wonderverse.check import CheckParams
from wonderverse.errors import ConfigError
from wonderverse.mesh import MeshParams
from wonderverse.priors.params import PriorsParams
from wonderverse.quality.params import QualityParams
from wonderverse.sfm import SfmParams
from wonderverse.splats.params import TrainParams

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
PRESET_DIR = CONFIG_DIR / "presets"
MAX_PROMPT_CHARS = 2000

Direction = Literal["left", "right", "up", "down", "forward", "back"]


class Model(BaseModel):
    """Base for every config model: unknown keys are errors, values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class ExtensionSpec(Model):
    """How the scene grows beyond the initial video (the paper repeats left+right `rounds` times)."""

    rounds: int = Field(1, ge=0, le=16, description="extension iterations n; each adds one segment per direction")
    directions: tuple[Direction, ...] = Field(("left", "right"), min_length=1)
    intents: tuple[str, ...] = Field((), description="the user's words for each extension, in order")
    added: tuple[str, ...] = Field(
        (), description="extensions added later (`wonderverse extend`), the user's words, oldest first"
    )


class VideoSpec(Model):
    """The video backend and the shape of what it renders."""

    backend: Literal["procedural", "files", "diffusers"] = Field(
        "procedural",
        description="procedural: the embedded world; files: the user's clips (`clips`), not generated; "
        "diffusers: a video diffusion model (CogVideoX, Wan, HunyuanVideo; `options` = DiffusionParams)",
    )
    clips: tuple[str, ...] = Field((), description="files backend: video files, image folders or globs, in order")
    frames_per_segment: int = Field(25, ge=2, le=1000)
    width: int = Field(480, ge=32, le=4096)
    height: int = Field(320, ge=32, le=4096)
    fps: float = Field(8.0, gt=0, le=240)
    fov_deg: float = Field(60.0, gt=5, lt=170, description="horizontal field of view")
    options: dict[str, Any] = Field(default_factory=dict, description="backend-specific, validated by it")

    @model_validator(mode="after")
    def _clips_match_backend(self) -> VideoSpec:
        if self.backend == "files" and not self.clips:
            raise ValueError("the files backend needs at least one clip")
        if self.backend != "files" and self.clips:
            raise ValueError(f"clips are only read by the files backend, not {self.backend!r}")
        return self


class PlannerSpec(Model):
    """Which planner turns the description and the user's words into camera moves."""

    backend: Literal["rules", "chat"] = "rules"
    base_url: str = Field("http://127.0.0.1:8000/v1", description="OpenAI-compatible endpoint (chat backend)")
    model: str = "gpt-4o-mini"
    api_key_env: str = Field("OPENAI_API_KEY", description="name of the environment variable holding the key")
    timeout_s: float = Field(30.0, gt=0, le=600)
    max_retries: int = Field(1, ge=0, le=5)


class SceneSpec(Model):
    """What the user asks for: everything that defines the scene's content."""

    prompt: str
    seed: int = Field(0, ge=0, lt=2**32)
    extensions: ExtensionSpec = ExtensionSpec()
    video: VideoSpec = VideoSpec()
    planner: PlannerSpec = PlannerSpec()

    @field_validator("prompt")
    @classmethod
    def _prompt_ok(cls, v: str) -> str:
        v = " ".join(v.split())
        if not v:
            raise ValueError("prompt is empty")
        if len(v) > MAX_PROMPT_CHARS:
            raise ValueError(f"prompt has {len(v)} characters; at most {MAX_PROMPT_CHARS} are allowed")
        return v


class PlanParams(Model):
    """Step `plan`: the initial camera move and the sizes of rule-planned extension moves."""

    initial_move: str = Field("up 0, right 30, forward 2", description="paper format, for the initial video")
    yaw_step_deg: float = Field(35.0, gt=0, le=180)
    pitch_step_deg: float = Field(15.0, gt=0, le=89)
    forward_step_m: float = Field(2.0, gt=0, le=100)
    yaw_forward_m: float = Field(0.5, gt=0, le=100, description="forward travel added to each turn")
    step_variation_ratio: float = Field(0.15, ge=0, lt=1, description="shrink of a repeated move on one side")
    max_pitch_deg: float = Field(60.0, gt=0, le=89, description="pitch limit of each extension chain")
    min_turn_deg: float = Field(1.0, gt=0, description="less room than this: the direction is exhausted")
    strafe_m_per_deg: float = Field(
        0.04, ge=0, le=1, description="sideways travel per degree of yaw, so turns keep parallax for SfM"
    )


class GenerateParams(Model):
    """Step `generate_segments`."""

    max_workers: int = Field(1, ge=1, le=64, description="segments rendered concurrently")


class CheckStepParams(Model):
    """Step `check`: per-segment SfM, the abnormal-sequence decision, and regeneration."""

    sfm: SfmParams = SfmParams(max_image_size_px=480, num_threads=1)
    rules: CheckParams = CheckParams()
    max_attempts: int = Field(4, ge=1, le=50, description="attempts per segment, the first included")
    on_failure: Literal["fail", "drop", "keep_best"] = Field(
        "keep_best", description="when every attempt fails: stop the run, drop the segment, or keep the best"
    )
    workers: int = Field(2, ge=1, le=256, description="segments checked at once (Dask LocalCluster workers)")
    dask_address: str | None = Field(None, description="existing Dask scheduler, e.g. tcp://host:8786")


class PosesParams(Model):
    """Step `poses`: one camera path for the whole stitched video."""

    source: Literal["sfm", "conditioning"] = Field(
        "sfm", description="sfm: one reconstruction over all accepted frames; conditioning: the planned path"
    )
    frame_stride: int = Field(1, ge=1, le=100, description="use every Nth stitched frame for SfM")
    sfm: SfmParams = SfmParams(max_image_size_px=480, num_threads=2)
    max_segment_disagreement_frac: float = Field(
        0.05, gt=0, description="a segment's poses this far (ATE, share of its path) from its own SfM: re-solve"
    )
    disagreement_retries: int = Field(2, ge=0, le=10, description="re-solves (next seeds) while a segment disagrees")


class PriorsStepParams(Model):
    """Step `priors`. The embedded default (the procedural world has no monocular network to run
    offline) is the oracle with realistic degradation; real video uses Depth Anything V2."""

    models: PriorsParams = PriorsParams(depth_backend="oracle", normal_backend="from_depth")
    sky_beyond_ref: float = Field(
        4.0, gt=1, description="aligned depth beyond this many times the farthest SfM point seen in the frame is sky"
    )
    workers: int = Field(2, ge=1, le=256, description="segments processed at once (Dask)")
    dask_address: str | None = Field(None, description="existing Dask scheduler, e.g. tcp://host:8786")


class SplatsStepParams(Model):
    """Step `splats`: geometry-aware 3D Gaussian splatting (RGB + depth + normal losses)."""

    train: TrainParams = TrainParams()
    renderer: Literal["auto", "torch", "gsplat"] = Field("auto", description="auto: gsplat whenever CUDA is there")
    max_side_px: int = Field(480, ge=16, le=8192, description="frames are downscaled to this longer side")
    frame_stride: int = Field(1, ge=1, description="train on every Nth stitched frame")
    init_from_depth: bool = Field(True, description="add back-projected aligned prior depth to the SfM points")
    init_depth_stride_px: int = Field(8, ge=1, description="pixel stride of the depth back-projection")
    init_depth_frame_stride: int = Field(4, ge=1, description="views back-projected: every Nth")
    init_voxel_frac: float = Field(0.01, gt=0, description="seeding voxel size, fraction of the scene scale")
    init_opacity: float = Field(0.1, gt=0, lt=1)
    extend_iterations_frac: float = Field(
        0.2, gt=0, le=1, description="after `extend`: iterations (share of train.iterations) continuing the old splats"
    )
    extend_new_view_share: float = Field(
        0.5,
        ge=0,
        lt=1,
        description="after `extend`: share of those iterations on the new frames (the rest keep the old)",
    )


class OutputsParams(Model):
    """Step `outputs`: the files users open elsewhere (mesh, points, COLMAP/nerfstudio data, videos)."""

    mesh: MeshParams = MeshParams()
    render_max_side_px: int = Field(480, ge=16, le=8192, description="renders for TSDF and videos: longer side")
    render_workers: int = Field(
        0, ge=0, le=256, description="CPU renderer: views rendered at once (0 = one per core); no effect on results"
    )
    video_frames: int = Field(120, ge=2, le=10_000, description="frames of the fly-through and novel-view videos")
    video_fps: float = Field(24.0, gt=0, le=240)
    novel_offset_frac: float = Field(
        0.1, ge=0, le=1, description="the novel-view path runs this share of the scene extent off the training path"
    )
    colmap: bool = Field(True, description="write colmap/ (cameras.txt, images.txt, points3D.txt)")
    nerfstudio: bool = Field(True, description="write nerfstudio/ (transforms.json + images/)")
    quality: QualityParams = Field(
        QualityParams(), description="no-reference metrics of novel views: NIQE always; CLIP-S, Q-Align with weights"
    )
    quality_frames: int = Field(8, ge=1, le=1000, description="novel-view frames scored, evenly spaced")


class StepsConfig(Model):
    plan: PlanParams = PlanParams()
    generate: GenerateParams = GenerateParams()
    check: CheckStepParams = CheckStepParams()
    poses: PosesParams = PosesParams()
    priors: PriorsStepParams = PriorsStepParams()
    splats: SplatsStepParams = SplatsStepParams()
    outputs: OutputsParams = OutputsParams()


class RunConfig(Model):
    """A full run: the scene and every step's parameters."""

    preset: str = "standard"
    scene: SceneSpec
    steps: StepsConfig = StepsConfig()

    @model_validator(mode="after")
    def _poses_known(self) -> RunConfig:
        if self.steps.poses.source != "conditioning":
            return self
        if self.scene.video.backend == "files":
            raise ValueError("user clips have no conditioning path: use steps.poses.source sfm")
        if self.scene.video.backend == "diffusers":  # the path reaches these models only as words
            raise ValueError("diffusers video models take no camera input: use steps.poses.source sfm")
        return self


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Recursively merge `over` into a copy of `base` (dicts merge, everything else replaces)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def read_yaml(path: Path) -> dict[str, Any]:
    """A YAML mapping from `path`; a missing, malformed or non-mapping file is a ConfigError."""
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise ConfigError(f"cannot read config file {path}: {e.strerror or e}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"malformed YAML in {path}{where}: {problem}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path} must hold a mapping of settings, not a {type(data).__name__}")
    return data


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
    path = PRESET_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"unknown preset {name!r}; choose one of: {', '.join(preset_names())}")
    return read_yaml(path)


def format_validation_error(err: ValidationError) -> str:
    """One line per problem: `field.path: message (got VALUE)`."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "config"
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            lines.append(f"{loc}: unknown setting")
        elif e["type"] == "missing":
            lines.append(f"{loc}: required setting is missing")
        else:
            got = repr(e.get("input"))
            got = got if len(got) <= 60 else got[:57] + "..."
            lines.append(f"{loc}: {msg} (got {got})")
    return "; ".join(lines)


def build_config(
    prompt: str | None = None,
    preset: str | None = None,
    config_file: Path | None = None,
    overrides: dict[str, Any] | None = None,
) -> RunConfig:
    """Compose defaults, a preset, a scene file and explicit overrides into a validated RunConfig. The preset is
    `preset`, else the file's, else this machine's default (`default_preset`)."""
    file_data = read_yaml(config_file) if config_file else {}
    name = preset or file_data.get("preset") or default_preset()[0]
    if not isinstance(name, str):
        raise ConfigError(f"preset: must be a preset name (got {name!r})")
    merged = deep_merge(load_preset(name), file_data)
    merged["preset"] = name
    if prompt is not None:
        merged = deep_merge(merged, {"scene": {"prompt": prompt}})
    merged = deep_merge(merged, overrides or {})
    if "prompt" not in merged.get("scene", {}):
        raise ConfigError("scene.prompt: no prompt given (pass PROMPT or set scene.prompt in the config file)")
    return validate_config(merged)


def validate_config(data: dict[str, Any]) -> RunConfig:
    try:
        return RunConfig.model_validate(data)
    except ValidationError as e:
        raise ConfigError(f"invalid config: {format_validation_error(e)}") from None
