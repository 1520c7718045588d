"""What the CLI shows while a run goes: a line per step, and within a long step how far it is.

On a terminal a live bar under the step lines (`RichReporter`); in a log (stderr not a terminal) plain
lines, a few per step (`PlainReporter`); for a program that runs the CLI and shows its progress itself (the
studio), JSON lines when the environment sets PROGRESS_ENV=json (`JsonReporter`). All read the same `advance`
calls (`tasks.progress`)."""

from __future__ import annotations

import json
import os
import sys
import time

from rich.console import Console
from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from tasks.base import StepResult
from tasks.progress import Rate, Reporter, current, describe

__all__ = ["JsonReporter", "PlainReporter", "Reporter", "RichReporter", "current", "make_reporter", "results_table"]


class _StepLines(Reporter):
    """The step lines both reporters print: '[3/7] check: ran (11.2 s) — 3 segments, 1 regenerated'."""

    def __init__(self, console: Console, total: int):
        self.console, self.total, self.done = console, total, 0
        self.step, self.t_step, self.rate = "", 0.0, Rate()

    def started(self, step: str, description: str) -> None:
        self.step, self.t_step, self.rate = step, time.monotonic(), Rate()

    def finished(self, result: StepResult) -> None:
        self.done += 1
        style = {"ran": "green", "cached": "cyan", "failed": "red"}[result.status]
        detail = f" — {result.detail}" if result.detail else ""
        self.console.print(
            f"[{self.done}/{self.total}] {result.step}: [{style}]{result.status}[/] ({result.seconds:.1f} s){detail}",
            highlight=False,
        )


class PlainReporter(_StepLines):
    """Plain lines for logs: a line when a step starts, then its progress every few seconds."""

    def started(self, step: str, description: str) -> None:
        super().started(step, description)
        self.console.print(f"[{self.done + 1}/{self.total}] {step}: {description} …", highlight=False)

    def advance(self, done: int, total: int, unit: str, note: str = "", eta: bool = True) -> None:
        self.rate.update(unit, done)
        if self.rate.line_due(done, total) or not eta:
            line = describe(done, total, unit, note, self.rate.seconds_left(done, total) if eta else None)
            self.console.print(f"[{self.done + 1}/{self.total}] {self.step}: {line}", highlight=False)


class RichReporter(_StepLines):
    """A live bar on a terminal: the step, what it is doing, how far, time spent and left."""

    def __init__(self, console: Console, total: int):
        super().__init__(console, total)
        self._bar: Progress | None = None
        self._task = 0

    def started(self, step: str, description: str) -> None:
        super().started(step, description)
        self._bar = Progress(
            SpinnerColumn(),
            TextColumn("{task.description}"),
            BarColumn(bar_width=24),
            TimeElapsedColumn(),
            console=self.console,
            transient=True,
        )
        self._task = self._bar.add_task(f"[{self.done + 1}/{self.total}] {step}: {description}", total=None)
        self._bar.start()

    def advance(self, done: int, total: int, unit: str, note: str = "", eta: bool = True) -> None:
        if self._bar is None:
            return
        self.rate.update(unit, done)
        line = describe(done, total, unit, note, self.rate.seconds_left(done, total) if eta else None)
        self._bar.update(
            self._task, description=f"[{self.done + 1}/{self.total}] {self.step}: {line}", completed=done, total=total
        )

    def finished(self, result: StepResult) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None
        super().finished(result)


PROGRESS_ENV = "WONDERVERSE_PROGRESS"
JSON_PREFIX = "wonderverse-progress: "  # JsonReporter's lines on stderr: this, then one JSON object
JSON_EVERY_S = 0.5  # progress events at most this often per unit, plus each unit's first and last


class JsonReporter(Reporter):
    """Machine-readable progress on stderr, one line per event, JSON_PREFIX then an object with `event`:
    `started` (step, description, index: 1-based, total), `progress` (step, done, total, unit, note, left_s,
    line: what the terminal shows) and `finished` (step, status, seconds, detail). The same units as the
    terminal's lines; other stderr lines (warnings, the `error:` line) stay as they are."""

    def __init__(self, total: int):
        self.total, self.done, self.step, self.rate, self.last_t = total, 0, "", Rate(), -1e9

    def _emit(self, event: str, **fields: object) -> None:
        line = json.dumps({"event": event, "step": self.step, **fields}, separators=(",", ":"))
        sys.stderr.write(JSON_PREFIX + line + "\n")
        sys.stderr.flush()

    def started(self, step: str, description: str) -> None:
        self.step, self.rate, self.last_t = step, Rate(), -1e9
        self._emit("started", description=description, index=self.done + 1, total=self.total)

    def advance(self, done: int, total: int, unit: str, note: str = "", eta: bool = True) -> None:
        first = unit != self.rate.unit or done < self.rate.done0
        self.rate.update(unit, done)
        now = time.monotonic()
        if not (first or done >= total or not eta or now - self.last_t >= JSON_EVERY_S):
            return
        self.last_t = now
        left = self.rate.seconds_left(done, total) if eta else None
        line = describe(done, total, unit, note, left)
        self._emit("progress", done=done, total=total, unit=unit, note=note, left_s=left, line=line)

    def finished(self, result: StepResult) -> None:
        self.done += 1
        self.step = result.step
        self._emit("finished", status=result.status, seconds=round(result.seconds, 3), detail=result.detail)


def make_reporter(console: Console, total: int) -> Reporter:
    """JSON lines when PROGRESS_ENV says so, else a live bar on a terminal, plain lines otherwise."""
    if os.environ.get(PROGRESS_ENV) == "json":
        return JsonReporter(total)
    return RichReporter(console, total) if console.is_terminal else PlainReporter(console, total)


def results_table(results: list[StepResult]) -> Table:
    t = Table(title="pipeline")
    for col, just in (("step", "left"), ("status", "left"), ("seconds", "right"), ("cache key", "left")):
        t.add_column(col, justify=just)
    for r in results:
        t.add_row(r.step, r.status, f"{r.seconds:.2f}", r.cache_key[:12])
    return t
