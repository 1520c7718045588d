"""Progress reporting for pipeline runs: a rich display in the CLI, silence elsewhere.

The reporter travels in a context variable so flows need no extra (unserialisable) parameter."""

from __future__ import annotations

from contextvars import ContextVar

from rich.console import Console
from rich.table import Table

from tasks.base import StepResult


class Reporter:
    """No-op base: subclasses show step starts and ends."""

    def started(self, step: str, description: str) -> None: ...

    def finished(self, result: StepResult) -> None: ...


class RichReporter(Reporter):
    def __init__(self, console: Console, total: int):
        self.console, self.total, self.done = console, total, 0
        self._status = None

    def started(self, step: str, description: str) -> None:
        self._status = self.console.status(f"[{self.done + 1}/{self.total}] {step}: {description} …")
        self._status.start()

    def finished(self, result: StepResult) -> None:
        if self._status is not None:
            self._status.stop()
            self._status = None
        self.done += 1
        style = {"ran": "green", "cached": "cyan", "failed": "red"}[result.status]
        detail = f" — {result.detail}" if result.detail else ""
        self.console.print(
            f"[{self.done}/{self.total}] {result.step}: [{style}]{result.status}[/] ({result.seconds:.1f} s){detail}",
            highlight=False,
        )


_SILENT = Reporter()
current: ContextVar[Reporter] = ContextVar("reporter", default=_SILENT)


def results_table(results: list[StepResult]) -> Table:
    t = Table(title="pipeline")
    for col, just in (("step", "left"), ("status", "left"), ("seconds", "right"), ("cache key", "left")):
        t.add_column(col, justify=just)
    for r in results:
        t.add_row(r.step, r.status, f"{r.seconds:.2f}", r.cache_key[:12])
    return t
