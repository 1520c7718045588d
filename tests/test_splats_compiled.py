"""Compiled: eager when disabled; a compile failure at the first call falls back to eager, logged once."""

from __future__ import annotations

import logging

import pytest
import torch

from wonderverse.splats.compiled import Compiled


def _double(x: torch.Tensor) -> torch.Tensor:
    return 2 * x


def test_disabled_is_the_function_itself() -> None:
    c = Compiled(_double, enabled=False)
    assert c.fn is _double and float(c(torch.tensor(3.0))) == 6.0


def test_a_failing_compile_falls_back_to_eager(caplog: pytest.LogCaptureFixture) -> None:
    c = Compiled(_double, enabled=False)

    def broken(*_: object) -> torch.Tensor:
        raise RuntimeError("no C compiler")

    c.fn = broken  # what a compiled wrapper does when the toolchain is missing
    with caplog.at_level(logging.WARNING):
        assert float(c(torch.tensor(2.0))) == 4.0
        assert float(c(torch.tensor(5.0))) == 10.0
    assert c.fn is _double and sum("no C compiler" in r.message for r in caplog.records) == 1


def test_errors_of_the_function_itself_propagate() -> None:
    with pytest.raises(TypeError):
        Compiled(_double, enabled=False)("not a tensor", 1)
