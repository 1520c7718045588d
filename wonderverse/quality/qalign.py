"""Q-Align (Wu et al., ICML 2024) image quality: a multimodal LM's belief over five text-defined levels.

The scoring rule of the Q-Align code: prompt "USER: How would you rate the quality of this image?\\n<image>\\n
ASSISTANT: The quality of the image is", take the next-token logits of the five level words (excellent, good,
fair, poor, bad), softmax over those five only, score = sum p_i w_i with w = (1, .75, .5, .25, 0) on the unit
scale, or 1 + 4 x that = sum p_i (5, 4, 3, 2, 1) on the five-point scale the paper's table uses (2.67-4.27).
Images are padded to a square with the processor's mean colour first (Q-Align's expand2square).

Runs over a transformers vision-language class (`AutoModelForImageTextToText`, e.g. LlavaForConditionalGeneration,
with its `AutoProcessor`) from a local folder. The official checkpoint (q-future/one-align, mPLUG-Owl2) ships its own
classes: with trust_remote_code=True a model exposing Q-Align's `score(images, task_="quality", input_="image")`
(five-point output) is used through that method; that path needs the checkpoint and is not covered by the tests.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from wonderverse.errors import WonderError
from wonderverse.quality.loading import batches, load_error, model_dir, pick_device, to_pil

WHAT = "Q-Align model"
LEVELS = ("excellent", "good", "fair", "poor", "bad")
LEVEL_WEIGHTS = np.array([1.0, 0.75, 0.5, 0.25, 0.0])
QUESTION = "USER: How would you rate the quality of this image?\n{image}\nASSISTANT: The quality of the image is"


def expand_to_square(image: np.ndarray, fill_rgb: np.ndarray) -> np.ndarray:
    """(S,S,3) uint8, S = max(H,W): the image centred on a canvas of fill_rgb (Q-Align's expand2square)."""
    h, w = image.shape[:2]
    s = max(h, w)
    out = np.empty((s, s, 3), dtype=np.uint8)
    out[:] = np.clip(np.round(fill_rgb), 0, 255).astype(np.uint8)
    y, x = (s - h) // 2, (s - w) // 2
    out[y : y + h, x : x + w] = image
    return out


def level_token_ids(tokenizer: object, answer_prefix: str = "The quality of the image is") -> list[int]:
    """Token id of each level word as the first token after the answer prefix (the way the LM would emit it).
    WonderError when two levels share a first token (the rule could not tell them apart)."""
    base = tokenizer(answer_prefix, add_special_tokens=False)["input_ids"]
    ids = []
    for word in LEVELS:
        full = tokenizer(f"{answer_prefix} {word}", add_special_tokens=False)["input_ids"]
        if full[: len(base)] != base or len(full) <= len(base):
            raise WonderError(f"{WHAT}: the tokenizer does not split '{answer_prefix} {word}' after the prefix")
        ids.append(full[len(base)])
    if len(set(ids)) != len(ids):
        raise WonderError(f"{WHAT}: the level words {LEVELS} do not start with distinct tokens ({ids})")
    return ids


class QAlignScorer:
    """Q-Align quality of images with a local vision-language checkpoint."""

    def __init__(
        self,
        path: str | Path,
        device: Literal["auto", "cpu", "cuda"] = "auto",
        fp16: bool = True,
        trust_remote_code: bool = False,
        scale: Literal["five_point", "unit"] = "five_point",
        batch_size: int = 8,
    ) -> None:
        from transformers import AutoModelForCausalLM, AutoModelForImageTextToText, AutoProcessor

        where = model_dir(path, WHAT)
        self.device, self.dtype = pick_device(device, fp16)
        self.scale, self.batch_size = scale, int(batch_size)
        kw = {"local_files_only": True, "trust_remote_code": trust_remote_code}
        try:
            try:
                model = AutoModelForImageTextToText.from_pretrained(where, dtype=self.dtype, **kw)
            except ValueError:  # not an image-text-to-text architecture: the official checkpoint's own class
                if not trust_remote_code:
                    raise
                model = AutoModelForCausalLM.from_pretrained(where, dtype=self.dtype, **kw)
            self.native = trust_remote_code and callable(getattr(model, "score", None))
            self.processor = None if self.native else AutoProcessor.from_pretrained(where, **kw)
        except (OSError, ValueError, KeyError) as err:
            raise load_error(WHAT, where, err) from None
        self.model = model.to(self.device).eval()
        if self.processor is not None:
            self.processor.tokenizer.padding_side = "left"  # the last position is every row's next token
            self.level_ids = level_token_ids(self.processor.tokenizer)
            image_token = getattr(self.processor, "image_token", None) or "<image>"
            self.prompt = QUESTION.format(image=image_token)
            mean = getattr(self.processor.image_processor, "image_mean", None) or [0.5, 0.5, 0.5]
            self.fill_rgb = np.asarray(mean, dtype=np.float64) * 255.0

    def level_probabilities(self, images: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
        """(N,5) float64 softmax over the five level words (excellent..bad) for each image."""
        import torch

        if self.processor is None:
            raise WonderError(f"{WHAT}: the checkpoint's own score() gives scores only, not level probabilities")
        arrays = [expand_to_square(np.asarray(a), self.fill_rgb) for a in images]
        pil = to_pil(arrays)
        out = np.empty((len(pil), len(LEVELS)), dtype=np.float64)
        for sl in batches(len(pil), self.batch_size):
            enc = self.processor(text=[self.prompt] * len(pil[sl]), images=pil[sl], return_tensors="pt", padding=True)
            enc = {k: v.to(self.device) for k, v in enc.items()}
            enc["pixel_values"] = enc["pixel_values"].to(self.dtype)
            with torch.no_grad():
                logits = self.model(**enc).logits[:, -1, self.level_ids].float()
            out[sl] = torch.softmax(logits, dim=-1).cpu().numpy()
        return out

    def score(self, images: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
        """(N,) float64 Q-Align quality: in [1,5] (five_point) or [0,1] (unit); higher is better."""
        import torch

        if self.native:
            with torch.no_grad():
                five = self.model.score(to_pil(images), task_="quality", input_="image")
            five = np.asarray(torch.as_tensor(five).float().cpu(), dtype=np.float64).reshape(-1)
            unit = (five - 1.0) / 4.0
        else:
            unit = self.level_probabilities(images) @ LEVEL_WEIGHTS
        return unit if self.scale == "unit" else 1.0 + 4.0 * unit
