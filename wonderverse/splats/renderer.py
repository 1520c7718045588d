"""Choosing a splat renderer: the `Renderer` protocol both backends satisfy, and `make_renderer`."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Literal, Protocol

from torch import Tensor

from wonderverse.errors import WonderError

log = logging.getLogger(__name__)

Backend = Literal["auto", "torch", "gsplat"]
RenderResult = tuple[Tensor, Tensor, Tensor, Tensor, dict[str, Any]]


class Renderer(Protocol):
    """render(means, quats, scales, opacities, colors, viewmat, K, width, height, near, far, background,
    sh_degree) -> (rgb (H,W,3), depth (H,W,1) = Σ w z, alpha (H,W,1), normals (H,W,3), info).

    Conventions are those of `render_torch.render`. `device` is where the Gaussians must live.
    """

    name: str
    device: str

    def __call__(
        self,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        colors: Tensor,
        viewmat: Tensor,
        K: Tensor,
        width: int,
        height: int,
        near: float = 0.01,
        far: float = 1e10,
        background: Tensor | None = None,
        sh_degree: int | None = None,
    ) -> RenderResult: ...


@dataclass(frozen=True)
class TorchRenderer:
    """The PyTorch tile rasteriser (`render_torch.render`), on any device (the CPU by default)."""

    device: str = "cpu"
    name: str = "torch"

    def __call__(self, *args: Any, **kwargs: Any) -> RenderResult:
        from wonderverse.splats.render_torch import render

        return render(*args, **kwargs)


@dataclass(frozen=True)
class GsplatRenderer:
    """gsplat 1.5.3's CUDA rasteriser (`render_gsplat.render`)."""

    device: str = "cuda"
    name: str = "gsplat"

    def __call__(self, *args: Any, **kwargs: Any) -> RenderResult:
        from wonderverse.splats.render_gsplat import render

        return render(*args, **kwargs)


def gsplat_available() -> tuple[bool, str]:
    """(usable, reason): CUDA present and gsplat importable."""
    import torch

    if not torch.cuda.is_available():
        return False, "no CUDA device"
    try:
        import gsplat  # noqa: F401
    except Exception as e:  # an installed gsplat can fail at import while building its CUDA kernels
        return False, f"gsplat cannot be imported ({type(e).__name__}: {e})"
    return True, "CUDA and gsplat present"


def make_renderer(backend: Backend = "auto") -> Renderer:
    """The renderer for `backend`: "gsplat" (CUDA), "torch" (CPU), or "auto" = gsplat whenever CUDA and
    gsplat are available, otherwise the torch rasteriser on the CPU (logged). An explicit "gsplat" that
    cannot run is a WonderError."""
    if backend == "torch":
        return TorchRenderer()
    ok, why = gsplat_available()
    if backend == "gsplat":
        if not ok:
            raise WonderError(f"splat renderer 'gsplat' cannot run here: {why}; use backend 'torch'")
        return GsplatRenderer()
    if backend != "auto":
        raise WonderError(f"unknown splat renderer {backend!r}; choose auto, torch or gsplat")
    if ok:
        return GsplatRenderer()
    log.info("splat renderer: torch on the CPU (%s)", why)
    return TorchRenderer()
