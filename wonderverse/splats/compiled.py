"""torch.compile with an eager fallback: a training step is hundreds of tiny kernels eagerly, and on a
GPU launching them costs more than running them; compiled, they fuse into a handful."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import torch

log = logging.getLogger(__name__)


class Compiled:
    """`fn` compiled by torch.compile (static shapes) when `enabled`; the first call that fails
    to compile (no compiler toolchain, an unsupported op) logs once and runs `fn` eagerly from then on.

    `cuda_graphs`: replay the compiled kernels as CUDA graphs (mode "reduce-overhead"), which removes their
    launch cost; only for fixed input shapes (one graph is recorded per shape), and each call's outputs are
    overwritten by the next call, so use them (or copy them) before calling again."""

    def __init__(self, fn: Callable[..., Any], enabled: bool = True, cuda_graphs: bool = False) -> None:
        self.eager = fn
        mode = "reduce-overhead" if cuda_graphs else None
        self.fn = torch.compile(fn, dynamic=False, mode=mode) if enabled else fn

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        try:
            return self.fn(*args, **kwargs)
        except Exception as e:  # compilation errors surface at the first call
            if self.fn is self.eager:
                raise
            name = getattr(self.eager, "__name__", "a function")
            log.warning("torch.compile of %s failed (%s: %s); running eagerly", name, type(e).__name__, e)
            self.fn = self.eager
            return self.eager(*args, **kwargs)
