"""Real video diffusion models (diffusers) behind the `VideoModel` protocol.

The initial segment is text-to-video (no reference); every extension is image-to-video from the
reference frame it continues. The paper's prompt ("aerial shot, soft lighting, around left, ...") is
built by the pipeline and used here as is: these models take no camera input, so the camera path
reaches them only through the words of the prompt. The returned K is the pinhole of the configured
horizontal fov; neither it nor the path is known to the model, so downstream steps should estimate
poses (SfM) rather than trust the conditioning path.

Frame count and frame size are validated, not resampled: Wan and HunyuanVideo need `num_frames = 4k+1`,
CogVideoX `8k+1`, all sides multiples of 16 (VAE x patch); a mismatch is a `WonderError` naming the
setting and the nearest valid value. Resampling would change the frame rate or the intrinsics silently.
The models were trained at particular sizes (CogVideoX 720x480, 49 frames; Wan 832x480, 81 frames):
other valid sizes run, with lower quality.

`guidance_scale` goes to the pipeline as is; for HunyuanVideo it is the distilled (embedded) guidance,
and a negative prompt only acts there with true CFG, which this backend does not switch on.

Guided family (`wan_vace`, `WanVACEPipeline`): a segment can come with a `Guide`, what is already known along
its path (frames plus a mask of unknown pixels). The guide's frames go to the pipeline as `video` (unknown pixels
set to mid-grey, as VACE was trained) and its mask as `mask` (white = generate); `conditioning_scale` sets how
strongly they steer. The reference frame, whose pose is path[0], is written into frame 0 as known content and/or
passed as a VACE reference image (`guide_reference`). Without a guide the same pipeline runs with every pixel
unknown (text-to-video, or from the reference frame alone), so a guided family renders every segment. VACE keeps
known pixels closely but not exactly: they are generated again, not pasted back. Unguided families (cogvideox, wan,
hunyuan) have no mask-capable pipeline: a guide given to them is a `WonderError`; `takes_guide` tells callers
beforehand, so guides are rendered only for a backend that reads them.

Heavy imports (torch, diffusers, PIL) happen on the first `generate`; loaded pipelines are shared
within the process (keyed by everything that shapes them), so a second model built from the same
options (e.g. the check step's regenerations) does not load the weights again.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from wonderverse.camera import intrinsics
from wonderverse.errors import WonderError
from wonderverse.video.base import Guide, Video

Family = Literal["cogvideox", "wan", "hunyuan", "wan_vace"]
Mode = Literal["t2v", "i2v", "guided"]


@dataclass(frozen=True)
class FamilySpec:
    """What one model family needs: its diffusers pipelines per mode (None: the family has no such pipeline),
    its default weights and its size rules (frames = frame_step * k + 1, sides multiples of side_multiple_px).
    A family with a guided pipeline takes a `Guide`; one without t2v/i2v pipelines renders every segment with it."""

    t2v_pipeline: str | None
    i2v_pipeline: str | None
    t2v_default: str | None
    i2v_default: str | None
    frame_step: int = 4  # the VAE's temporal compression, or a multiple of it
    side_multiple_px: int = 16  # VAE spatial compression x transformer patch
    needs_ftfy: bool = False
    guided_pipeline: str | None = None  # takes known frames + a mask of pixels to generate
    guided_default: str | None = None

    def pipeline_class(self, mode: Mode) -> str | None:
        return {"t2v": self.t2v_pipeline, "i2v": self.i2v_pipeline, "guided": self.guided_pipeline}[mode]

    def default_weights(self, mode: Mode) -> str | None:
        return {"t2v": self.t2v_default, "i2v": self.i2v_default, "guided": self.guided_default}[mode]


FAMILIES: dict[str, FamilySpec] = {
    # CogVideoX's causal VAE decodes an even number of latent frames to 4 frames each (not 4k+1), so only
    # an odd latent count, i.e. 8k+1 frames (9, 17, 25, 49), comes back at the requested length
    "cogvideox": FamilySpec(
        "CogVideoXPipeline",
        "CogVideoXImageToVideoPipeline",
        "THUDM/CogVideoX-5b",
        "THUDM/CogVideoX-5b-I2V",
        frame_step=8,
    ),
    # diffusers' Wan prompt cleaning calls ftfy unguarded in the image-to-video pipeline
    "wan": FamilySpec(
        "WanPipeline",
        "WanImageToVideoPipeline",
        "Wan-AI/Wan2.1-T2V-1.3B-Diffusers",
        "Wan-AI/Wan2.1-I2V-14B-480P-Diffusers",
        needs_ftfy=True,
    ),
    "hunyuan": FamilySpec(
        "HunyuanVideoPipeline",
        "HunyuanVideoImageToVideoPipeline",
        "hunyuanvideo-community/HunyuanVideo",
        "hunyuanvideo-community/HunyuanVideo-I2V",
    ),
    # Wan 2.1 VACE: one pipeline for text-to-video, first-frame continuation and guided in-/outpainting.
    # Same VAE as Wan (4x temporal, 8x spatial) and 2x2 patches: 4k+1 frames, sides multiples of 16.
    # Trained at 832x480 (1.3B; the 14B also 1280x720), 81 frames.
    "wan_vace": FamilySpec(
        None,
        None,
        None,
        None,
        needs_ftfy=True,
        guided_pipeline="WanVACEPipeline",
        guided_default="Wan-AI/Wan2.1-VACE-1.3B-diffusers",
    ),
}


def family_takes_guide(family: str) -> bool:
    """Whether `family` has a mask-capable (guided) pipeline, i.e. reads a `Guide`."""
    return FAMILIES[family].guided_pipeline is not None


def _options_error(field: str, message: str, value: Any) -> ValidationError:
    """A validation error located at `field` of DiffusionParams (so the config names the setting)."""
    error = InitErrorDetails(type=PydanticCustomError("config", message), loc=(field,), input=value)
    return ValidationError.from_exception_data("DiffusionParams", [error])


class DiffusionParams(BaseModel):
    """`scene.video.options` of the diffusers backend."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    family: Family = Field("cogvideox", description="model family; picks the pipeline classes and size rules")
    t2v_model: str | None = Field(None, description="text-to-video weights: local folder or hub id (family default)")
    i2v_model: str | None = Field(None, description="image-to-video weights: local folder or hub id (family default)")
    guided_model: str | None = Field(
        None,
        description="guided families (wan_vace): weights of the guided pipeline, local folder or hub id "
        "(family default); unguided families do not read it",
    )
    conditioning_scale: float = Field(
        1.0,
        ge=0,
        le=5,
        description="guided families: how strongly the known frames, mask and reference frame steer each VACE "
        "layer; 1 = as trained, 0 = ignored (plain text-to-video)",
    )
    guide_reference: Literal["first_frame", "reference_image", "both"] = Field(
        "both",
        description="guided families, how the reference frame (pose path[0]) is given: first_frame = written into "
        "frame 0 as known pixels; reference_image = a VACE reference image (appearance, not placed); both",
    )
    dtype: Literal["auto", "float16", "bfloat16", "float32"] = Field(
        "auto", description="auto: bfloat16 on CUDA, float32 on CPU"
    )
    device: Literal["auto", "cuda", "cpu"] = Field("auto", description="auto: CUDA when available")
    offload: Literal["none", "model", "sequential"] = Field(
        "none", description="CUDA only: model = whole modules to the GPU in turn; sequential = layer by layer"
    )
    steps: int = Field(50, ge=1, le=1000, description="denoising steps")
    guidance_scale: float | None = Field(None, ge=0, le=50, description="None: the pipeline's default")
    negative_prompt: str = Field(
        "", max_length=2000, description="what the model should steer away from; empty: none passed to the pipeline"
    )
    allow_download: bool = Field(False, description="let from_pretrained fetch hub ids missing from the local cache")
    vae_tiling: bool = Field(False, description="decode in tiles (less GPU memory, slower)")
    vae_slicing: bool = Field(False, description="decode batch items one at a time")

    @model_validator(mode="after")
    def _weights_of_the_family(self) -> DiffusionParams:
        # t2v/i2v weights given to a family that renders everything with its guided pipeline would be silently
        # unused; guided_model is allowed (and unused) on unguided families, so one options block serves both
        spec = FAMILIES[self.family]
        for mode in ("t2v", "i2v"):
            field = f"{mode}_model"
            value = getattr(self, field)
            if value is not None and spec.pipeline_class(mode) is None:
                modes = ", ".join(f"{m}_model" for m in ("t2v", "i2v", "guided") if spec.pipeline_class(m))
                raise _options_error(field, f"the {self.family} family has no {mode} pipeline; it reads {modes}", value)
        return self


def nearest_frame_count(n: int, step: int) -> int:
    """The valid frame count (step*k + 1, at least step + 1) closest to n; ties go up."""
    k = max(1, int(np.floor((n - 1) / step + 0.5)))
    return step * k + 1


def nearest_side(px: int, multiple: int) -> int:
    """The positive multiple of `multiple` closest to px; ties go up."""
    return multiple * max(1, int(np.floor(px / multiple + 0.5)))


def size_problem(family: str, frames: int, width: int, height: int) -> tuple[str, str] | None:
    """(setting, why) for the first of frames_per_segment, width, height that the family cannot render, with its
    nearest valid value; None when the family renders this size."""
    spec = FAMILIES[family]
    f = spec.frame_step
    if frames < f + 1 or (frames - 1) % f:
        nearest = nearest_frame_count(frames, f)
        return (
            "frames_per_segment",
            f"{family} renders {f}k+1 frames (k >= 1); {frames} is not, nearest valid is {nearest}",
        )
    m = spec.side_multiple_px
    for name, px in (("width", width), ("height", height)):
        if px % m:
            return name, f"{family} needs a multiple of {m} px; {px} is not, nearest valid is {nearest_side(px, m)}"
    return None


def check_size(family: str, frames: int, width: int, height: int, where: str = "scene.video") -> None:
    """Raise WonderError naming the first setting the family cannot render, and its nearest valid value."""
    problem = size_problem(family, frames, width, height)
    if problem is not None:
        raise WonderError(f"{where}.{problem[0]}: {problem[1]}")


_CACHE: dict[tuple[Any, ...], Any] = {}
_CACHE_LOCK = threading.Lock()


def _torch_dtype(name: str, device: str) -> Any:
    import torch

    if name == "auto":
        return torch.bfloat16 if device == "cuda" else torch.float32
    if name == "float16" and device == "cpu":
        raise WonderError("video.options.dtype: float16 needs CUDA; use float32 (or auto) on CPU")
    return getattr(torch, name)


def resolve_device(params: DiffusionParams) -> str:
    """'cuda' or 'cpu' for these params; WonderError when CUDA is asked for and absent."""
    import torch

    has_cuda = torch.cuda.is_available()
    if params.device == "cuda" and not has_cuda:
        raise WonderError("video.options.device: cuda was asked for but torch sees no CUDA device")
    device = "cuda" if params.device == "cuda" or (params.device == "auto" and has_cuda) else "cpu"
    if params.offload != "none" and device != "cuda":
        raise WonderError(f"video.options.offload: {params.offload} offload needs CUDA; use none on CPU")
    return device


def _looks_local(source: str) -> bool:
    return source.startswith(("/", ".", "~")) or Path(source).expanduser().exists()


def load_pipeline(params: DiffusionParams, mode: Mode) -> Any:
    """The diffusers pipeline of `params.family` for `mode`, on its device and dtype (cached per process)."""
    spec = FAMILIES[params.family]
    cls_name = spec.pipeline_class(mode)
    if cls_name is None:
        raise WonderError(f"the {params.family} family has no {mode} pipeline")
    device = resolve_device(params)
    dtype = _torch_dtype(params.dtype, device)
    if spec.needs_ftfy:
        import importlib.util

        if importlib.util.find_spec("ftfy") is None:
            raise WonderError(f"the {params.family} pipelines need the ftfy package (pip install ftfy)")
    source = getattr(params, f"{mode}_model") or spec.default_weights(mode)
    assert source is not None, f"{params.family} names {cls_name} without default weights"
    field = f"video.options.{mode}_model"
    local = _looks_local(source)
    if local:
        folder = Path(source).expanduser()
        if not (folder / "model_index.json").is_file():
            what = "has no model_index.json (not a saved diffusers pipeline)" if folder.is_dir() else "does not exist"
            raise WonderError(f"{field}: {folder} {what}")
        if mode == "guided":  # diffusers loads another pipeline's folder with a warning, then fails deep inside
            saved = _saved_class(folder / "model_index.json")
            if saved != cls_name:
                raise WonderError(
                    f"{field}: {folder} holds a {saved or 'pipeline of unknown class'}, not a {cls_name}: the "
                    f"{params.family} family needs its mask-capable pipeline (known frames plus a mask of pixels to "
                    "generate)"
                )
        source = str(folder.resolve())
    key = (cls_name, source, str(dtype), device, params.offload, params.vae_tiling, params.vae_slicing)
    with _CACHE_LOCK:
        if key in _CACHE:
            return _CACHE[key]
        pipe = _from_pretrained(cls_name, source, dtype, local_only=local or not params.allow_download, field=field)
        if params.offload == "model":
            pipe.enable_model_cpu_offload(device=device)
        elif params.offload == "sequential":
            pipe.enable_sequential_cpu_offload(device=device)
        else:
            pipe.to(device)
        vae = getattr(pipe, "vae", None)
        if params.vae_tiling and hasattr(vae, "enable_tiling"):
            vae.enable_tiling()
        if params.vae_slicing and hasattr(vae, "enable_slicing"):
            vae.enable_slicing()
        pipe.set_progress_bar_config(disable=True)
        _CACHE[key] = pipe
        return pipe


def _saved_class(model_index: Path) -> str | None:
    """The pipeline class a saved diffusers folder names (`_class_name` of its model_index.json); None if unreadable."""
    import json

    try:
        name = json.loads(model_index.read_text()).get("_class_name")
    except (OSError, ValueError, AttributeError):
        return None
    return name if isinstance(name, str) else None


def _from_pretrained(cls_name: str, source: str, dtype: Any, local_only: bool, field: str) -> Any:
    import importlib

    import diffusers

    cls = getattr(diffusers, cls_name, None)
    if cls is None:
        raise WonderError(f"diffusers {diffusers.__version__} has no {cls_name}; upgrade diffusers")
    # diffusers >= 0.36 renamed torch_dtype to dtype (the old name still works with a warning)
    try:
        renamed = hasattr(importlib.import_module("diffusers.utils.deprecation_utils"), "_resolve_dtype")
    except ImportError:
        renamed = False
    dtype_kw = "dtype" if renamed else "torch_dtype"
    try:
        return cls.from_pretrained(source, local_files_only=local_only, **{dtype_kw: dtype})
    except (OSError, ValueError) as e:
        hint = " (not in the local Hugging Face cache; set allow_download: true to fetch it)" if local_only else ""
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise WonderError(f"{field}: cannot load {cls_name} from {source}{hint}: {first}") from None


class DiffusionVideo:
    """A diffusers model family as a `VideoModel`: text-to-video / image-to-video, or guided (see the module doc).

    generate returns frames (T,H,W,3) uint8 with T = len(path) and the configured size, and K (3,3)
    float64 from the horizontal fov (cx = W/2). The path itself is not read (see the module doc); a guided
    family follows it through the guide rendered along it.
    """

    def __init__(self, width: int, height: int, frames: int, fov_deg: float, params: DiffusionParams) -> None:
        check_size(params.family, frames, width, height)
        self.width, self.height, self.frames, self.fov_deg = width, height, frames, fov_deg
        self.params = params
        # fail on a device/dtype/offload mismatch now, before any segment work; weights load on first use
        self.device = resolve_device(params)
        _torch_dtype(params.dtype, self.device)
        self._lock = threading.Lock()  # one generation at a time: a GPU pipeline is not re-entrant

    @property
    def takes_guide(self) -> bool:
        """Whether `generate` reads a `Guide` (the family has a mask-capable pipeline); False: passing one is an
        error, so callers need not render it."""
        return family_takes_guide(self.params.family)

    def pipeline(self, mode: Mode) -> Any:
        """The loaded diffusers pipeline for `mode` (loads on first use)."""
        return load_pipeline(self.params, mode)

    def generate(
        self, prompt: str, path: np.ndarray, seed: int, reference: np.ndarray | None, guide: Guide | None = None
    ) -> Video:
        """Frames for `prompt` continuing from `reference` (image-to-video) or from scratch (text-to-video); a
        guided family keeps what `guide` knows (frames where `guide.mask` is False) and invents the rest.

        WonderError when the family cannot take a guide, or the guide's size is not (T, height, width)."""
        import torch

        path = np.asarray(path)
        if path.ndim != 3 or path.shape[1:] != (4, 4):
            raise WonderError(f"camera path must be (T,4,4) W2C poses, got shape {path.shape}")
        T = path.shape[0]
        check_size(self.params.family, T, self.width, self.height, where="path/scene.video")
        spec = FAMILIES[self.params.family]
        if guide is not None and not self.takes_guide:
            raise WonderError(
                f"the {self.params.family} family cannot take a guide: it has no mask-capable pipeline "
                f"(guided families: {', '.join(f for f in FAMILIES if family_takes_guide(f))})"
            )
        ref = None
        if reference is not None:
            ref = np.asarray(reference)
            if ref.ndim != 3 or ref.shape[2] != 3 or ref.dtype != np.uint8:
                raise WonderError(f"reference frame must be (H,W,3) uint8, got {ref.shape} {ref.dtype}")
        if guide is not None:
            self._check_guide(guide, T)
        kwargs: dict[str, Any] = dict(
            prompt=prompt,
            height=self.height,
            width=self.width,
            num_frames=T,
            num_inference_steps=self.params.steps,
            # a CPU generator: the same seed gives the same initial noise on any device
            generator=torch.Generator(device="cpu").manual_seed(int(seed)),
            output_type="np",
        )
        if self.params.guidance_scale is not None:
            kwargs["guidance_scale"] = self.params.guidance_scale
        if self.params.negative_prompt:
            kwargs["negative_prompt"] = self.params.negative_prompt
        mode: Mode
        if guide is not None or spec.t2v_pipeline is None:
            mode = "guided"
            kwargs.update(self._guided_inputs(T, ref, guide))
        elif ref is not None:
            from PIL import Image

            kwargs["image"] = Image.fromarray(ref)
            mode = "i2v"
        else:
            mode = "t2v"
        with self._lock:
            pipe = self.pipeline(mode)
            try:
                out = pipe(**kwargs).frames
            except torch.cuda.OutOfMemoryError:
                raise WonderError(
                    "the GPU ran out of memory generating video; try offload: model or sequential, vae_tiling: true"
                ) from None
            except ValueError as e:  # the pipelines' own input checks
                raise WonderError(f"{type(pipe).__name__} refused the request: {str(e).splitlines()[0]}") from None
        return Video(frames=self._to_uint8(out, T), K=intrinsics(self.width, self.height, self.fov_deg))

    def _check_guide(self, guide: Guide, T: int) -> None:
        frames, mask = np.asarray(guide.frames), np.asarray(guide.mask)
        if frames.ndim != 4 or frames.shape[3] != 3 or frames.dtype != np.uint8:
            raise WonderError(f"guide frames must be (T,H,W,3) uint8, got {frames.shape} {frames.dtype}")
        if mask.shape != frames.shape[:3] or mask.dtype != np.bool_:
            raise WonderError(f"guide mask must be (T,H,W) bool like its frames {frames.shape[:3]}, got {mask.shape}")
        want = (T, self.height, self.width)
        if frames.shape[:3] != want:
            size = "x".join(map(str, frames.shape[:3]))
            raise WonderError(
                f"the guide is {size} (frames x height x width) but the video is {'x'.join(map(str, want))}"
            )

    def _guided_inputs(self, T: int, ref: np.ndarray | None, guide: Guide | None) -> dict[str, Any]:
        """`video`, `mask`, `reference_images` and `conditioning_scale` for the guided pipeline."""
        from PIL import Image

        use = self.params.guide_reference
        if guide is not None:
            frames = np.array(guide.frames, dtype=np.uint8)
            unknown = np.array(guide.mask, dtype=bool)
        else:
            frames = np.zeros((T, self.height, self.width, 3), np.uint8)
            unknown = np.ones((T, self.height, self.width), bool)
        if ref is not None and use in ("first_frame", "both"):
            if ref.shape[:2] != (self.height, self.width):
                raise WonderError(
                    f"reference frame is {ref.shape[0]}x{ref.shape[1]} but the video is {self.height}x{self.width} "
                    "(height x width); guide_reference first_frame/both writes it into frame 0"
                )
            frames[0], unknown[0] = ref, False  # the reference is the frame at path[0]
        # VACE was trained with unknown pixels grey (0 after the [-1, 1] normalisation); 128 as diffusers' example
        frames[unknown] = 128
        kwargs: dict[str, Any] = {"conditioning_scale": self.params.conditioning_scale}
        # with nothing known no video is passed: the pipeline's own all-unknown default (plain text-to-video)
        if not unknown.all():
            # lists of PIL images: the pipeline reads a numpy video's size from the wrong axes
            kwargs["video"] = [Image.fromarray(f) for f in frames]
            kwargs["mask"] = [Image.fromarray(m.astype(np.uint8) * 255) for m in unknown]  # white = generate
        if ref is not None and use in ("reference_image", "both"):
            kwargs["reference_images"] = [Image.fromarray(ref)]
        return kwargs

    def _to_uint8(self, out: Any, T: int) -> np.ndarray:
        arr = np.asarray(out[0] if isinstance(out, list) else out)
        if arr.ndim == 5:
            arr = arr[0]
        want = (T, self.height, self.width, 3)
        if arr.shape != want:
            raise WonderError(f"the {self.params.family} pipeline returned frames of shape {arr.shape}, not {want}")
        if not np.all(np.isfinite(arr)):
            raise WonderError("the video pipeline returned non-finite frames (float16 overflow? try bfloat16)")
        return np.round(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8)
