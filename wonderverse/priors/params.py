"""Parameters of the priors step: which depth/normal backends, where their weights are, how to align.

Imports only pydantic, so configs can be validated without torch or transformers.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

DepthBackend = Literal["depth_anything", "oracle", "none"]  # none: no depth prior (the splats train on colours)
NormalBackend = Literal["from_depth", "dpt", "oracle", "none"]
OracleLevel = Literal["none", "mild", "realistic", "harsh"]
AlignMethod = Literal["lstsq", "trimmed", "ransac"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class AlignParams(_Model):
    """Per-image scale/shift alignment of a monocular prior to reference depths (SfM points)."""

    method: AlignMethod = Field(
        "trimmed",
        description="lstsq: one least-squares fit; trimmed: refit without the worst `trim_fraction`, up to "
        "`max_iters` passes; ransac: scale/shift from point pairs, refit on the inliers",
    )
    min_points: int = Field(20, ge=2, description="fewer usable reference points than this -> fallback")
    trim_fraction: float = Field(0.2, ge=0.0, lt=0.9, description="share of worst residuals dropped per pass")
    max_iters: int = Field(10, ge=1, le=100, description="trimmed-LS passes")
    ransac_iters: int = Field(256, ge=1, le=100_000, description="RANSAC hypotheses (point pairs) tried per image")
    ransac_rel_thresh: float = Field(
        0.05, gt=0, description="inlier if |a*p+b - t| <= thresh * |t| (relative, so scale-free)"
    )
    ransac_max_score_points: int = Field(
        4096, ge=16, le=10_000_000, description="hypotheses are scored on this many samples"
    )
    depth_clamp_ratio: float = Field(
        10.0, gt=1, description="aligned depth is clamped to [min_ref/ratio, max_ref*ratio]"
    )
    seed: int = Field(0, ge=0, description="seed of RANSAC's sampling")


class FromDepthParams(_Model):
    """Normals from depth by back-projection (the default normal prior)."""

    max_rel_step: float | None = Field(
        None, gt=0, description="pixels whose smallest neighbour step |dz|/z exceeds this are invalid; None: off"
    )
    smooth_px: float = Field(
        1.5,
        ge=0,
        description="Gaussian sigma (px) applied to log-depth first: a network's depth is smooth, "
        "per-pixel noise is not, and differentiating amplifies it; 0: off",
    )


class OracleDegradation(_Model):
    """How the oracle turns exact ground truth into something that looks like a monocular network's output.

    Depth, per frame: edge blur, smooth multiplicative warp, multiplicative noise, then unknown scale/shift.
    Normals: stronger blur at creases, a smooth low-frequency error, per-pixel noise, smoothing, re-normalised.
    """

    scale_range: tuple[float, float] = Field((1.0, 1.0), description="per-frame scale, log-uniform")
    shift_frac_range: tuple[float, float] = Field((0.0, 0.0), description="per-frame shift / median value")
    warp_log_amp: float = Field(0.0, ge=0, description="std of the low-frequency log-multiplicative warp")
    warp_cells: int = Field(4, ge=1, description="control points of the warp along the short image side")
    noise_rel: float = Field(0.0, ge=0, lt=0.5, description="per-pixel multiplicative noise std")
    edge_blur_px: float = Field(0.0, ge=0, description="Gaussian sigma of the blur across depth edges")
    edge_rel_step: float = Field(0.05, gt=0, description="neighbour |dz|/z that counts as a depth edge")
    sky_far_ratio: float = Field(3.0, gt=1, description="sky depth = this * farthest ground-truth depth")
    world_warp_log_amp: float = Field(
        0.0,
        ge=0,
        description="std of a log-multiplicative depth error fixed to the world's surfaces, the same in every frame "
        "(a network's consistent mistakes, which averaging over frames cannot remove); needs the cameras",
    )
    world_warp_wavelength_m: tuple[float, float] = Field(
        (1.0, 4.0), description="wavelengths of its six world-space sinusoids, log-uniform in this range (world units)"
    )
    normal_warp_amp: float = Field(
        0.0, ge=0, description="std of a low-frequency additive field on unit normals (structured error)"
    )
    normal_noise_std: float = Field(0.0, ge=0, description="additive per-pixel noise std on unit normals")
    normal_smooth_px: float = Field(0.0, ge=0, description="Gaussian sigma of the normal smoothing")
    normal_edge_blur_px: float = Field(0.0, ge=0, description="extra sigma at normal creases")
    normal_crease_deg: float = Field(30.0, gt=0, lt=180, description="neighbour angle that counts as a crease")

    @field_validator("world_warp_wavelength_m")
    @classmethod
    def _positive_range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not 0 < v[0] <= v[1] < float("inf"):
            raise ValueError(f"wavelengths must satisfy 0 < low <= high < inf, got {v}")
        return v


# Levels are named presets of OracleDegradation. Measured at 480x320 on a ground + wall + sky scene
# (AbsRel after per-frame alignment / mean normal error): mild ~3 % / ~4 deg, realistic ~7 % / ~12 deg
# (the range of Depth Anything V2 and Omnidata on real benchmarks), harsh ~15 % / ~23 deg.
ORACLE_LEVELS: dict[str, OracleDegradation] = {
    "none": OracleDegradation(),
    "mild": OracleDegradation(
        scale_range=(0.5, 2.0),
        shift_frac_range=(0.0, 0.1),
        warp_log_amp=0.02,
        noise_rel=0.005,
        edge_blur_px=1.0,
        normal_warp_amp=0.05,
        normal_noise_std=0.03,
        normal_smooth_px=0.7,
        normal_edge_blur_px=1.0,
    ),
    "realistic": OracleDegradation(
        scale_range=(0.1, 10.0),
        shift_frac_range=(0.0, 0.3),
        warp_log_amp=0.06,
        noise_rel=0.01,
        edge_blur_px=2.0,
        normal_warp_amp=0.15,
        normal_noise_std=0.08,
        normal_smooth_px=1.5,
        normal_edge_blur_px=2.5,
    ),
    "harsh": OracleDegradation(
        scale_range=(0.01, 100.0),
        shift_frac_range=(0.0, 0.6),
        warp_log_amp=0.15,
        warp_cells=6,
        noise_rel=0.03,
        edge_blur_px=4.0,
        normal_warp_amp=0.3,
        normal_noise_std=0.2,
        normal_smooth_px=2.5,
        normal_edge_blur_px=5.0,
    ),
}


class PriorsParams(_Model):
    """The priors step: a depth prior and a normal prior per frame, aligned to SfM depths downstream.

    depth_model: a local directory written by `save_pretrained` (model + image processor) or a Hugging Face
    hub id (downloaded once into the HF cache when `allow_download`). normal_model: a local Omnidata
    DPT-hybrid normal checkpoint (.ckpt / .pth / .pt / .safetensors), needed only for normal_backend="dpt".
    """

    depth_backend: DepthBackend = Field(
        "depth_anything",
        description="depth_anything: Depth Anything V2 (`depth_model`); oracle: the procedural world's degraded ground "
        "truth (benchmarks only); none: no depth prior",
    )
    normal_backend: NormalBackend = Field(
        "from_depth",
        description="from_depth: back-projected from the depth prior; dpt: Omnidata's DPT-hybrid (`normal_model`); "
        "oracle: degraded ground truth; none: no normal prior",
    )
    depth_model: str = Field(
        "depth-anything/Depth-Anything-V2-Small-hf", description="local directory or hub id (transformers format)"
    )
    normal_model: str | None = Field(None, description="path of an Omnidata DPT-hybrid normal checkpoint")
    normal_output_axes: Literal["opengl", "opencv"] = Field(
        "opengl", description="camera axes the DPT normal checkpoint predicts in; converted to OpenCV"
    )
    allow_download: bool = Field(True, description="let a hub id download; False: local directory or cache only")
    allow_unsafe_pickle: bool = Field(
        False, description="load a normal checkpoint that is not a plain tensor file (runs pickled code)"
    )
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="where the depth and normal networks run; auto: CUDA when available"
    )
    fp16: bool = Field(True, description="half precision on CUDA; ignored on CPU")
    batch_size: int = Field(8, ge=1, le=512, description="frames per forward pass of a depth or normal network")
    depth_input_size_px: int | None = Field(
        None, ge=14, le=4096, description="network input size; None: the image processor's own (518 for DA-V2)"
    )
    normal_input_size_px: int = Field(384, ge=32, le=4096, description="short side fed to the DPT normal model")
    oracle_level: OracleLevel = Field(
        "realistic",
        description="how far the oracle degrades the truth: none, mild (~3 % AbsRel), realistic (~7 %, a monocular "
        "network's range), harsh (~15 %)",
    )
    oracle_space: Literal["depth", "inverse_depth"] = Field(
        "inverse_depth", description="space the oracle degrades in and reports (DA-V2 predicts inverse depth)"
    )
    oracle_seed: int = Field(0, ge=0, description="seed of the oracle's per-frame degradation")
    from_depth: FromDepthParams = FromDepthParams()
    align: AlignParams = AlignParams()

    @model_validator(mode="after")
    def _normals_have_their_input(self) -> PriorsParams:
        if self.depth_backend == "none" and self.normal_backend == "from_depth":
            raise ValueError("normal_backend from_depth needs a depth prior: with depth_backend none use none (or dpt)")
        return self

    @property
    def any(self) -> bool:
        """Whether there is any prior to compute (else the splats train on colours alone)."""
        return self.depth_backend != "none" or self.normal_backend != "none"
