"""CLIP-S (Hessel et al., EMNLP 2021): w * max(cos(E_image, E_text), 0) with w = 2.5, per image.

The paper (following WonderWorld) reports CLIP-S of 0.42-0.96 for its rendered views, which is the w = 2.5 scale
(cosines of 0.17-0.39); the x100 variant of other papers is not used. Runs a transformers `CLIPModel` loaded from
a local folder (no download); any CLIP checkpoint works, the paper does not name one (CLIPScore used ViT-B/32).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from wonderverse.quality.loading import batches, load_error, model_dir, pick_device, to_pil

WHAT = "CLIP-S model"


class ClipScorer:
    """CLIP-S of images against texts with a local CLIP checkpoint."""

    def __init__(
        self,
        path: str | Path,
        device: Literal["auto", "cpu", "cuda"] = "auto",
        fp16: bool = True,
        weight: float = 2.5,
        batch_size: int = 8,
    ) -> None:
        from transformers import AutoProcessor, CLIPModel

        where = model_dir(path, WHAT)
        self.device, self.dtype = pick_device(device, fp16)
        try:
            self.processor = AutoProcessor.from_pretrained(where, local_files_only=True)
            model = CLIPModel.from_pretrained(where, local_files_only=True)
        except (OSError, ValueError, KeyError) as err:
            raise load_error(WHAT, where, err) from None
        self.model = model.to(device=self.device, dtype=self.dtype).eval()
        self.weight, self.batch_size = float(weight), int(batch_size)
        self.max_tokens = int(model.config.text_config.max_position_embeddings)  # CLIP's context: 77

    def score(self, images: np.ndarray | Sequence[np.ndarray], texts: str | Sequence[str]) -> np.ndarray:
        """(N,) float64 CLIP-S in [0, weight] of image i against texts[i] (one string: the same text for all).
        Texts longer than the model's context are truncated (as CLIPScore does)."""
        import torch

        pil = to_pil(images)
        texts = [texts] * len(pil) if isinstance(texts, str) else list(texts)
        if len(texts) != len(pil):
            raise ValueError(f"{len(pil)} images but {len(texts)} texts")
        out = np.empty(len(pil), dtype=np.float64)
        for sl in batches(len(pil), self.batch_size):
            enc = self.processor(
                text=texts[sl],
                images=pil[sl],
                return_tensors="pt",
                padding=True,
                truncation=True,
                max_length=self.max_tokens,
            )
            enc = {k: v.to(self.device) for k, v in enc.items()}
            enc["pixel_values"] = enc["pixel_values"].to(self.dtype)
            with torch.no_grad():
                res = self.model(**enc)
            img = torch.nn.functional.normalize(res.image_embeds.float(), dim=-1)
            txt = torch.nn.functional.normalize(res.text_embeds.float(), dim=-1)
            cos = (img * txt).sum(-1)  # pair i with text i, not the all-pairs logits
            out[sl] = (self.weight * cos.clamp(min=0)).cpu().numpy()
        return out
