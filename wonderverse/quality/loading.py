"""Shared plumbing of the network metrics: devices, local model folders, image lists. Imports torch lazily."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from wonderverse.errors import WonderError

if TYPE_CHECKING:
    import torch
    from PIL import Image


def pick_device(device: Literal["auto", "cpu", "cuda"], fp16: bool) -> tuple[torch.device, torch.dtype]:
    """(device, dtype): "auto" takes CUDA when present; half precision only on CUDA."""
    import torch

    if device == "cuda" and not torch.cuda.is_available():
        raise WonderError("quality.device is 'cuda' but no CUDA device is available; use 'auto' or 'cpu'")
    use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    return torch.device("cuda" if use_cuda else "cpu"), (torch.float16 if use_cuda and fp16 else torch.float32)


def model_dir(path: str | Path, what: str) -> str:
    """The folder of a local transformers model; WonderError when it is not a directory (nothing is downloaded)."""
    p = Path(path).expanduser()
    if not p.is_dir():
        raise WonderError(f"{what}: {p} is not a directory (give a folder written by save_pretrained / hf download)")
    return str(p)


def load_error(what: str, where: str, err: BaseException) -> WonderError:
    first = str(err).strip().splitlines()[0] if str(err).strip() else ""
    return WonderError(f"{what} in {where} could not be loaded: {type(err).__name__}: {first}")


def to_pil(images: np.ndarray | Sequence[np.ndarray]) -> list[Image.Image]:
    """RGB PIL images of an (N,H,W,3) uint8 array or a sequence of (H,W,3) uint8 arrays."""
    from PIL import Image

    out = []
    for im in images:
        a = np.asarray(im)
        if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
            raise ValueError(f"expected (H,W,3) uint8 images, got {a.shape} {a.dtype}")
        out.append(Image.fromarray(a, mode="RGB"))
    return out


def batches(n: int, size: int) -> list[slice]:
    return [slice(i, min(i + size, n)) for i in range(0, n, size)]
