"""Settings of the no-reference quality metrics (imports only pydantic)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class QualityParams(BaseModel):
    """Which metrics to compute on rendered novel views. NIQE needs no weights and always runs; CLIP-S and
    Q-Align run only when a local model folder (written by `save_pretrained` / `hf download --local-dir`) is given."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    clip_model: str | None = Field(
        None, description="folder of a transformers CLIPModel + processor; None skips CLIP-S"
    )
    qalign_model: str | None = Field(
        None,
        description="folder of a vision-language model (Llava-style or the Q-Align checkpoint); None skips Q-Align",
    )
    qalign_trust_remote_code: bool = Field(
        False, description="let the Q-Align folder's own code run (the official mPLUG-Owl2 checkpoint needs it)"
    )
    qalign_scale: Literal["five_point", "unit"] = Field(
        "five_point", description="five_point: 1..5 as the paper's table; unit: 0..1 (weights 1, .75, .5, .25, 0)"
    )
    clip_weight: float = Field(2.5, gt=0, description="w of CLIP-S = w * max(cos, 0) (Hessel et al. use 2.5)")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="where CLIP and Q-Align run; auto: CUDA when available (NIQE runs on the CPU)"
    )
    fp16: bool = Field(True, description="half precision on CUDA (ignored on CPU)")
    batch_size: int = Field(8, ge=1, le=1024, description="images per forward pass of CLIP / Q-Align")
