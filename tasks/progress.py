"""Progress of the running step, as the user sees it.

A step (or the library function it calls, through a `wonderverse.progress.ProgressFn`) reports how far it
is with `advance(done, total, unit, note)`. The reporter travels in a context variable, so flows need no
extra (unserialisable) parameter: the CLI sets one that draws a bar on a terminal or prints plain lines in
a log; inside a Prefect task run the same plain lines also go to the task run's log (the Prefect UI).
"""

from __future__ import annotations

import logging
import time
from contextvars import ContextVar
from dataclasses import dataclass, field

from tasks.base import StepResult
from tasks.fan_out import in_prefect_task
from wonderverse.progress import ProgressFn

PLAIN_EVERY_S = 10.0  # plain lines (logs, Prefect) at most this often per unit, plus each unit's first and last


class Reporter:
    """No-op base: subclasses show step starts, progress within a step, and step ends."""

    def started(self, step: str, description: str) -> None: ...

    def advance(self, done: int, total: int, unit: str, note: str = "", eta: bool = True) -> None: ...

    def finished(self, result: StepResult) -> None: ...


_SILENT = Reporter()
current: ContextVar[Reporter] = ContextVar("reporter", default=_SILENT)


@dataclass
class Rate:
    """Time left for one unit of work, from its pace since the unit was first reported."""

    unit: str = ""
    t0: float = 0.0
    done0: int = 0
    last_line_t: float = field(default=-1e9)

    def update(self, unit: str, done: int) -> None:
        if unit != self.unit or done < self.done0:
            self.unit, self.t0, self.done0, self.last_line_t = unit, time.monotonic(), done, -1e9

    def seconds_left(self, done: int, total: int) -> float | None:
        elapsed = time.monotonic() - self.t0
        if done <= self.done0 or elapsed < 1.0:
            return None
        return (total - done) * elapsed / (done - self.done0)

    def line_due(self, done: int, total: int) -> bool:
        """Whether a plain line is due (first report of a unit, the last one, or every PLAIN_EVERY_S)."""
        now = time.monotonic()
        if self.last_line_t < 0 or done >= total or now - self.last_line_t >= PLAIN_EVERY_S:
            self.last_line_t = now
            return True
        return False


def duration(seconds: float) -> str:
    """'45 s', '3 min 05 s', '1 h 02 min'."""
    s = round(seconds)
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def describe(done: int, total: int, unit: str, note: str, left_s: float | None) -> str:
    """'iterations 1200/7000 (17 %), loss 0.0521, 1 min 12 s left'."""
    pct = f" ({100 * done // total} %)" if total > 0 else ""
    parts = [f"{unit} {done}/{total}{pct}"]
    if note:
        parts.append(note)
    if left_s is not None and done < total:
        parts.append(f"{duration(left_s)} left")
    return ", ".join(parts)


_prefect_rate: ContextVar[Rate | None] = ContextVar("prefect_rate", default=None)


def _prefect_logger() -> logging.Logger | logging.LoggerAdapter | None:
    """The current Prefect task run's logger, when running inside one."""
    if not in_prefect_task():
        return None
    from prefect.logging import get_run_logger

    return get_run_logger()


def advance(done: int, total: int, unit: str, note: str = "", eta: bool = True) -> None:
    """Report that `done` of `total` `unit` of the running step are finished. `eta=False`: units of very
    unequal length (stages), whose pace so far says nothing of the time left: none is shown, and each
    report is a plain line (stages are few, and a long one would otherwise go unnamed in a log)."""
    current.get().advance(done, total, unit, note, eta=eta)
    logger = _prefect_logger()
    if logger is None:
        return
    rate = _prefect_rate.get()
    if rate is None:
        rate = Rate()
        _prefect_rate.set(rate)
    rate.update(unit, done)
    if rate.line_due(done, total) or not eta:
        logger.info(describe(done, total, unit, note, rate.seconds_left(done, total) if eta else None))


def callback(unit: str, eta: bool = True) -> ProgressFn:
    """A library progress callback that reports `unit` of the running step (`eta` as in `advance`)."""

    def report(done: int, total: int, note: str = "") -> None:
        advance(done, total, unit, note, eta)

    return report
