"""torch.compile with an eager fallback: a training step is hundreds of tiny kernels eagerly, and on a
GPU launching them costs more than running them; compiled, they fuse into a handful."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import torch

log = logging.getLogger(__name__)


class Compiled:
    """`fn` compiled by torch.compile (`dynamic` shapes or not) when `enabled`; the first call that fails
    to compile (no compiler toolchain, an unsupported op) logs once and runs `fn` eagerly from then on."""

    def __init__(self, fn: Callable[..., Any], enabled: bool = True, dynamic: bool = False) -> None:
        self.eager = fn
        self.fn = torch.compile(fn, dynamic=dynamic) if enabled else fn

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
