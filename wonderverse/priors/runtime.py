"""Shared plumbing of the network backends: device choice and weight locations. Imports torch lazily."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

from wonderverse.errors import WonderError

if TYPE_CHECKING:
    import torch


def resolve_device(device: Literal["auto", "cpu", "cuda"], fp16: bool) -> tuple[torch.device, torch.dtype]:
    """(device, dtype) to run on: "auto" takes CUDA when present; fp16 only on CUDA (CPU half is slow)."""
    import torch

    if device == "cuda" and not torch.cuda.is_available():
        raise WonderError("priors.device is 'cuda' but no CUDA device is available; use 'auto' or 'cpu'")
    use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    dev = torch.device("cuda" if use_cuda else "cpu")
    dtype = torch.float16 if (use_cuda and fp16) else torch.float32
    return dev, dtype


def looks_like_path(name: str) -> bool:
    """True for what the user meant as a filesystem path (absolute, ./, ../, ~), not a hub id."""
    return name.startswith(("/", "./", "../", "~", ".\\")) or Path(name).expanduser().exists()


def local_dir_or_hub_id(name: str, what: str) -> tuple[str, bool]:
    """(location, is_local) for a transformers-format model given as a directory or a hub id."""
    if looks_like_path(name):
        p = Path(name).expanduser()
        if not p.is_dir():
            raise WonderError(f"{what}: {p} is not a directory (expected one written by save_pretrained)")
        return str(p), True
    return name, False


def hub_error(name: str, what: str, allow_download: bool, err: BaseException) -> WonderError:
    """A one-line WonderError for a hub id that could not be loaded (no network, not cached, typo)."""
    first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    how = (
        "it is not in the Hugging Face cache and downloads are off (priors.allow_download=false)"
        if not allow_download
        else "it is not in the Hugging Face cache and could not be downloaded (no network, HF_HUB_OFFLINE=1, "
        "or a wrong id)"
    )
    return WonderError(
        f"{what} '{name}' could not be loaded: {how}. Download it once with `hf download {name} "
        f"--local-dir DIR` on a machine with network and point the setting at DIR. ({type(err).__name__}: {first})"
    )
