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

from tasks import STEPS, Step, StepResult, progress, step_keys, steps_until
from wonderverse.config import RunConfig
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore, scene_lock

Call = Callable[[Step, str, RunConfig, str], str]
OnCached = Callable[[Step, str], None]
Engine = Literal["prefect", "local"]


class StepFailed(WonderError):
    """A step raised; `results` holds what ran before it (the store keeps their output)."""

    def __init__(self, step: str, cause: BaseException, results: list[StepResult]):
        super().__init__(f"step {step} failed: {type(cause).__name__}: {cause}")
        self.step, self.cause, self.results = step, cause, results


def _direct(step: Step, scene_dir: str, cfg: RunConfig, key: str) -> str:
    return step.run_in(scene_dir, cfg, key)


def _nothing(step: Step, key: str) -> None:
    return None


def execute(
    scene_dir: Path | str,
    cfg: RunConfig,
    until: str | None = None,
    call: Call = _direct,
    wait_s: float = 0.0,
    on_cached: OnCached = _nothing,
) -> list[StepResult]:
    """Run the steps `until` needs (all by default); returns one StepResult per step. One run writes a
    scene at a time: a second one waits up to `wait_s` seconds for the first, then refuses (WonderError).
    `on_cached(step, key)` is called for each step skipped as complete (the flow records a "Cached" task run)."""
    try:
        steps = steps_until(until)
    except KeyError:
        raise WonderError(f"unknown step {until!r}; steps are: {', '.join(s.name for s in STEPS)}") from None
    with scene_lock(scene_dir, wait_s=wait_s):
        return _execute(scene_dir, cfg, steps, call, on_cached)


def _execute(
    scene_dir: Path | str, cfg: RunConfig, steps: list[Step], call: Call, on_cached: OnCached
) -> list[StepResult]:
    store = SceneStore.open_or_create(scene_dir, spec=cfg.scene.model_dump(mode="json"))
    store.root.attrs["config"] = cfg.model_dump(mode="json")
    store.clean_staging()
    keys = step_keys(STEPS, cfg)
    reporter = progress.current.get()
    results: list[StepResult] = []
    for step in steps:
        key = keys[step.name]
        if store.is_complete(step.group, key):
            on_cached(step, key)
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


def _cached_state(step: str, cache_key: str) -> Any:
    """The final state of a skipped step's task run: Completed, named "Cached" in the Prefect UI."""
    from prefect.states import Completed

    return Completed(name="Cached", message=f"{step}: complete in the store under key {cache_key[:12]}")


def _prefect_cached(step: Step, key: str) -> None:
    if "cached" not in _flows:
        from prefect import task
        from prefect.cache_policies import NO_CACHE

        _flows["cached"] = task(cache_policy=NO_CACHE, task_run_name="{step}")(_cached_state)
    _flows["cached"].with_options(name=step.name)(step.name, key)


def _generate_flow(scene_dir: str, config: RunConfig, until: str | None = None) -> list[StepResult]:
    return execute(scene_dir, config, until, call=_prefect_call, on_cached=_prefect_cached)


_flows: dict[str, Any] = {}


FlowName = Literal["generate", "extend", "reconstruct"]


def generate_flow(name: FlowName = "generate") -> Any:
    """The Prefect flow `name` (built on first use so plain imports stay light). `generate`, `extend` and
    `reconstruct` run the same cached steps; their names tell the runs apart in the UI."""
    if name not in _flows:
        from prefect import flow

        _flows[name] = flow(name=name, log_prints=False, validate_parameters=False)(_generate_flow)
    return _flows[name]


def run_pipeline(
    scene_dir: Path | str,
    cfg: RunConfig,
    until: str | None = None,
    engine: Engine = "prefect",
    flow_name: FlowName = "generate",
) -> list[StepResult]:
    """Run a scene with the chosen engine: the Prefect flow `flow_name` (default) or plain in-process calls."""
    if engine == "local":
        return execute(scene_dir, cfg, until)
    return generate_flow(flow_name)(str(scene_dir), cfg, until)
