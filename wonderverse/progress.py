"""Progress of long computations. Library functions take an optional `progress(done, total, note)`
callback and call it as work advances (iterations, views, frames); they never draw anything themselves.
The pipeline's steps (`tasks.progress`) turn those calls into what the user sees."""

from __future__ import annotations

from collections.abc import Callable

ProgressFn = Callable[[int, int, str], None]
"""progress(done, total, note): `done` of `total` units finished; `note` is a short detail ("loss 0.052")."""


def no_progress(done: int, total: int, note: str = "") -> None:
    """The default callback: reports nowhere."""
