"""Running steps in dependency order over one scene store, skipping complete ones.

`execute` is the whole orchestration logic; `generate_flow` is the same run as a Prefect flow whose
task runs show each step. Either way the store is the source of truth: a killed run resumes from
the last complete step (and, inside a step, from the last complete segment).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from flows import progress
from tasks import STEPS, Step, StepResult, step_keys, steps_until
from wonderverse.config import RunConfig
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore, scene_lock

Call = Callable[[Step, str, RunConfig, str], str]
Engine = Literal["prefect", "local"]


class StepFailed(WonderError):
    """A step raised; `results` holds what ran before it (the store keeps their output)."""

    def __init__(self, step: str, cause: BaseException, results: list[StepResult]):
        super().__init__(f"step {step} failed: {type(cause).__name__}: {cause}")
        self.step, self.cause, self.results = step, cause, results


def _direct(step: Step, scene_dir: str, cfg: RunConfig, key: str) -> str:
    return step.run_in(scene_dir, cfg, key)


def execute(
    scene_dir: Path | str, cfg: RunConfig, until: str | None = None, call: Call = _direct, wait_s: float = 0.0
) -> list[StepResult]:
    """Run the steps `until` needs (all by default); returns one StepResult per step. One run writes a
    scene at a time: a second one waits up to `wait_s` seconds for the first, then refuses (WonderError)."""
    try:
        steps = steps_until(until)
    except KeyError:
        raise WonderError(f"unknown step {until!r}; steps are: {', '.join(s.name for s in STEPS)}") from None
    with scene_lock(scene_dir, wait_s=wait_s):
        return _execute(scene_dir, cfg, steps, call)


def _execute(scene_dir: Path | str, cfg: RunConfig, steps: list[Step], call: Call) -> list[StepResult]:
    store = SceneStore.open_or_create(scene_dir, spec=cfg.scene.model_dump(mode="json"))
    store.root.attrs["config"] = cfg.model_dump(mode="json")
    store.clean_staging()
    keys = step_keys(STEPS, cfg)
    reporter = progress.current.get()
    results: list[StepResult] = []
    for step in steps:
        key = keys[step.name]
        if store.is_complete(step.group, key):
            result = StepResult(step.name, "cached", 0.0, key)
        else:
            reporter.started(step.name, step.description)
            t0 = time.perf_counter()
            try:
                detail = call(step, str(scene_dir), cfg, key)
            except Exception as e:
                result = StepResult(step.name, "failed", time.perf_counter() - t0, key, str(e))
                reporter.finished(result)
                raise StepFailed(step.name, e, [*results, result]) from e
            result = StepResult(step.name, "ran", time.perf_counter() - t0, key, detail)
            store.group(step.group).attrs["seconds"] = result.seconds  # for inspect and the report
        reporter.finished(result)
        results.append(result)
    return results


def _prefect_call(step: Step, scene_dir: str, cfg: RunConfig, key: str) -> str:
    return step.task(scene_dir, cfg, key)


def _generate_flow(scene_dir: str, config: RunConfig, until: str | None = None) -> list[StepResult]:
    return execute(scene_dir, config, until, call=_prefect_call)


_flows: dict[str, Any] = {}


def generate_flow() -> Any:
    """The Prefect flow `generate` (built on first use so plain imports stay light)."""
    if "generate" not in _flows:
        from prefect import flow

        _flows["generate"] = flow(name="generate", log_prints=False, validate_parameters=False)(_generate_flow)
    return _flows["generate"]


def run_pipeline(
    scene_dir: Path | str, cfg: RunConfig, until: str | None = None, engine: Engine = "prefect"
) -> list[StepResult]:
    """Run a scene with the chosen engine: a Prefect flow (default) or plain in-process calls."""
    if engine == "local":
        return execute(scene_dir, cfg, until)
    return generate_flow()(str(scene_dir), cfg, until)
