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
from pydantic import BaseModel, ConfigDict, Field

from wonderverse.camera import intrinsics
from wonderverse.errors import WonderError
from wonderverse.video.base import Video

Family = Literal["cogvideox", "wan", "hunyuan"]


@dataclass(frozen=True)
class FamilySpec:
    """What one model family needs: its diffusers pipelines per mode, its default weights and its
    size rules (frames = frame_step * k + 1, sides multiples of side_multiple_px)."""

    t2v_pipeline: str
    i2v_pipeline: str
    t2v_default: str
    i2v_default: str
    frame_step: int = 4  # the VAE's temporal compression, or a multiple of it
    side_multiple_px: int = 16  # VAE spatial compression x transformer patch
    needs_ftfy: bool = False


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
}


class DiffusionParams(BaseModel):
    """`scene.video.options` of the diffusers backend."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    family: Family = Field("cogvideox", description="model family; picks the pipeline classes and size rules")
    t2v_model: str | None = Field(None, description="text-to-video weights: local folder or hub id (family default)")
    i2v_model: str | None = Field(None, description="image-to-video weights: local folder or hub id (family default)")
    dtype: Literal["auto", "float16", "bfloat16", "float32"] = Field(
        "auto", description="auto: bfloat16 on CUDA, float32 on CPU"
    )
    device: Literal["auto", "cuda", "cpu"] = Field("auto", description="auto: CUDA when available")
    offload: Literal["none", "model", "sequential"] = Field(
        "none", description="CUDA only: model = whole modules to the GPU in turn; sequential = layer by layer"
    )
    steps: int = Field(50, ge=1, le=1000, description="denoising steps")
    guidance_scale: float | None = Field(None, ge=0, le=50, description="None: the pipeline's default")
    negative_prompt: str = Field("", max_length=2000)
    allow_download: bool = Field(False, description="let from_pretrained fetch hub ids missing from the local cache")
    vae_tiling: bool = Field(False, description="decode in tiles (less GPU memory, slower)")
    vae_slicing: bool = Field(False, description="decode batch items one at a time")


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


def load_pipeline(params: DiffusionParams, mode: Literal["t2v", "i2v"]) -> Any:
    """The diffusers pipeline of `params.family` for `mode`, on its device and dtype (cached per process)."""
    spec = FAMILIES[params.family]
    device = resolve_device(params)
    dtype = _torch_dtype(params.dtype, device)
    if spec.needs_ftfy:
        import importlib.util

        if importlib.util.find_spec("ftfy") is None:
            raise WonderError(f"the {params.family} pipelines need the ftfy package (pip install ftfy)")
    source = (params.t2v_model if mode == "t2v" else params.i2v_model) or (
        spec.t2v_default if mode == "t2v" else spec.i2v_default
    )
    field = f"video.options.{mode}_model"
    local = _looks_local(source)
    if local:
        folder = Path(source).expanduser()
        if not (folder / "model_index.json").is_file():
            what = "has no model_index.json (not a saved diffusers pipeline)" if folder.is_dir() else "does not exist"
            raise WonderError(f"{field}: {folder} {what}")
        source = str(folder.resolve())
    cls_name = spec.t2v_pipeline if mode == "t2v" else spec.i2v_pipeline
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
    """A diffusers text-to-video / image-to-video pair as a `VideoModel`.

    generate returns frames (T,H,W,3) uint8 with T = len(path) and the configured size, and K (3,3)
    float64 from the horizontal fov (cx = W/2). The path itself is ignored (see the module doc).
    """

    def __init__(self, width: int, height: int, frames: int, fov_deg: float, params: DiffusionParams) -> None:
        check_size(params.family, frames, width, height)
        self.width, self.height, self.frames, self.fov_deg = width, height, frames, fov_deg
        self.params = params
        # fail on a device/dtype/offload mismatch now, before any segment work; weights load on first use
        self.device = resolve_device(params)
        _torch_dtype(params.dtype, self.device)
        self._lock = threading.Lock()  # one generation at a time: a GPU pipeline is not re-entrant

    def pipeline(self, mode: Literal["t2v", "i2v"]) -> Any:
        """The loaded diffusers pipeline for `mode` (loads on first use)."""
        return load_pipeline(self.params, mode)

    def generate(self, prompt: str, path: np.ndarray, seed: int, reference: np.ndarray | None) -> Video:
        """Frames for `prompt` continuing from `reference` (image-to-video) or from scratch (text-to-video)."""
        import torch

        path = np.asarray(path)
        if path.ndim != 3 or path.shape[1:] != (4, 4):
            raise WonderError(f"camera path must be (T,4,4) W2C poses, got shape {path.shape}")
        T = path.shape[0]
        check_size(self.params.family, T, self.width, self.height, where="path/scene.video")
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
        mode: Literal["t2v", "i2v"] = "t2v"
        if reference is not None:
            from PIL import Image

            ref = np.asarray(reference)
            if ref.ndim != 3 or ref.shape[2] != 3 or ref.dtype != np.uint8:
                raise WonderError(f"reference frame must be (H,W,3) uint8, got {ref.shape} {ref.dtype}")
            kwargs["image"] = Image.fromarray(ref)
            mode = "i2v"
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
