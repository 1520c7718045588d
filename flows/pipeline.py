"""Running steps in dependency order over one scene store, skipping complete ones.

`execute` is the whole orchestration logic; `generate_flow` is the same run as a Prefect flow whose
task runs show each step. Either way the store is the source of truth: a killed run resumes from
the last complete step (and, inside a step, from the last complete segment).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from flows.engine import Engine, resolve_engine
from tasks import STEPS, Step, StepResult, progress, step_keys, steps_until
from tasks.base import StepContext
from tasks.wording import run_description
from wonderverse.config import RunConfig
from wonderverse.errors import WonderError, shown
from wonderverse.schema import ROOT, SEGMENT, SEGMENTS
from wonderverse.schema.attrs import FailedRun, RunRecord
from wonderverse.store import STORE_NAME, SceneStore, scene_lock

Call = Callable[[Step, str, Any, StepContext], str]
OnCached = Callable[[Step, str], None]

# The root's RunConfigs (`schema.attrs.RootAttrs`): `config`, the configuration of the last run that completed
# (every step it ran finished; a failed or stopped run never replaces it), and `segments_config`, the configuration
# the scene's segments were last generated under, written when the segments step starts, so it holds even after a
# run that failed later (what `refuse_replacing_segments` compares with, and whose extensions a re-run continues).
log = logging.getLogger("wonderverse.pipeline")
SEGMENTS_STEP = "generate_segments"
MAX_RUNS = 500  # runs kept in a scene's history


class StepFailed(WonderError):
    """A step raised; `results` holds what ran before it (the store keeps their output). Its message is the user's
    line: `step <step> failed: <why>` (`failure_words`: no Python class name)."""

    def __init__(self, step: str, cause: BaseException, results: list[StepResult]):
        super().__init__(f"step {step} failed: {failure_words(cause)}")
        self.step, self.cause, self.results = step, cause, results


def failure_words(cause: BaseException) -> str:
    """Why a step failed, in words for the user: a WonderError's own message; a file-system error's file and reason;
    anything else (a bug, or a library's error) its message marked unexpected. Never a Python class name."""
    if isinstance(cause, WonderError):
        return str(cause) or "failed with no message"
    if isinstance(cause, MemoryError):
        return "out of memory" + (f" ({cause})" if str(cause) else "")
    if isinstance(cause, OSError) and cause.strerror:
        return f"{cause.filename}: {cause.strerror}" if cause.filename else cause.strerror
    text = " ".join(str(cause).split())
    if isinstance(cause, KeyError) and text:
        text = f"missing entry {text}"
    return f"unexpected error: {text}" if text else "unexpected error (no message)"


def _direct(step: Step, scene_dir: str, params: Any, ctx: StepContext) -> str:
    return step.run_in(scene_dir, params, ctx)


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
    steps = needed_steps(until)
    with scene_lock(scene_dir, wait_s=wait_s):
        return _execute(scene_dir, cfg, steps, call, on_cached)


def needed_steps(until: str | None) -> list[Step]:
    """The steps `until` needs, in order (all when None); WonderError naming the steps when `until` is none of them."""
    try:
        return steps_until(until)
    except KeyError:
        raise WonderError(f"unknown step {shown(until)}; steps are: {', '.join(s.name for s in STEPS)}") from None


def _execute(
    scene_dir: Path | str, cfg: RunConfig, steps: list[Step], call: Call, on_cached: OnCached
) -> list[StepResult]:
    store = SceneStore.open_or_create(scene_dir, spec=cfg.scene.model_dump(mode="json"))
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
            if step.name == SEGMENTS_STEP:
                store.update_attrs(ROOT.path, segments_config=cfg.model_dump(mode="json"))
            reporter.started(step.name, run_description(step, cfg))
            t0 = time.perf_counter()
            try:
                detail = call(step, str(scene_dir), step.params(cfg), StepContext(key, cfg.execution))
            except Exception as e:
                result = StepResult(step.name, "failed", time.perf_counter() - t0, key, failure_words(e))
                reporter.finished(result)
                failure = StepFailed(step.name, e, [*results, result])
                _record_failure(store, failure, {s.name: keys[s.name] for s in steps})
                raise failure from e
            result = StepResult(step.name, "ran", time.perf_counter() - t0, key, detail)
            store.update_attrs(step.group, seconds=result.seconds)  # for inspect and the report
        reporter.finished(result)
        results.append(result)
    # the run completed: its config is the scene's now, and no failure stands
    store.update_attrs(ROOT.path, config=cfg.model_dump(mode="json"), failed_run=None)
    _record_run(store, cfg, results)
    return results


def _record_failure(store: SceneStore, failure: StepFailed, keys: dict[str, str]) -> None:
    """Keep where and why the run stopped (`RootAttrs.failed_run`: what `inspect` and the report say), with the keys
    of the steps it needed, so that what it completed reads as such. Best effort: a store that cannot take it (a full
    disk) must not hide the step's own failure."""
    record = FailedRun(
        finished=datetime.now(UTC).isoformat(timespec="seconds"),
        step=failure.step,
        error=failure_words(failure.cause),
        completed=[r.step for r in failure.results if r.status != "failed"],
        keys=keys,
    )
    try:
        store.update_attrs(ROOT.path, failed_run=record.model_dump(mode="json"))
    except Exception as e:  # the failure being recorded is the one to report
        log.warning("could not record the failed run in %s: %s", store.scene_dir, failure_words(e))


def _record_run(store: SceneStore, cfg: RunConfig, results: list[StepResult]) -> None:
    """Add the run to the scene's history (`RootAttrs.runs`: what the report's growth plot shows), if it ran
    anything."""
    ran = {r.step: r.seconds for r in results if r.status == "ran"}
    if not ran:
        return
    root = store.meta(ROOT.path, complete=False)
    record = RunRecord(
        finished=datetime.now(UTC).isoformat(timespec="seconds"),
        extensions=len(cfg.scene.extensions.added),
        segments=len(store.children(SEGMENTS.path)),
        seconds=ran,
    )
    store.update_attrs(ROOT.path, runs=[*root.runs, record][-MAX_RUNS:])


def _prefect_call(step: Step, scene_dir: str, params: Any, ctx: StepContext) -> str:
    return step.task(scene_dir, params, ctx)


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


def _generate_flow(
    scene_dir: str, config: RunConfig, until: str | None = None, lock_held: bool = False
) -> list[StepResult]:
    """The flow body. `lock_held`: the caller (`run_pipeline`) already holds the scene's lock, taken before
    Prefect started so that a busy scene is refused at once."""
    if lock_held:
        return _execute(scene_dir, config, needed_steps(until), _prefect_call, _prefect_cached)
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


@contextmanager
def claimed(scene_dir: Path | str, cfg: RunConfig, replace_segments: bool = False) -> Iterator[None]:
    """Hold the scene for a run of `cfg` while the block runs: its lock taken (a busy scene is refused at once), its
    store, when it has one, opened for writing (a newer, damaged or read-only store is refused), and a run that
    would replace the scene's segments refused unless `replace_segments` (WonderError each). What `run_pipeline`
    does before any engine starts; the CLI does it before its first line, so that a refusal is its only line. Every
    refusal is judged before the lock is taken or anything written, and again under the lock (`scene_lock`)."""

    def judge() -> None:
        if (Path(scene_dir) / STORE_NAME).exists():
            SceneStore.open(scene_dir, mode="r+")
        if not replace_segments:
            refuse_replacing_segments(scene_dir, cfg)

    with scene_lock(scene_dir, judge=judge):
        yield


def run_pipeline(
    scene_dir: Path | str,
    cfg: RunConfig,
    until: str | None = None,
    engine: Engine = "auto",
    flow_name: FlowName = "generate",
    replace_segments: bool = False,
    lock_held: bool = False,
) -> list[StepResult]:
    """Run a scene with the chosen engine (`flows.engine`): a Prefect flow named `flow_name`, or plain
    in-process calls, inside `claimed` (taken here unless `lock_held`: the caller is inside it already)."""
    steps = needed_steps(until)
    with nullcontext() if lock_held else claimed(scene_dir, cfg, replace_segments):
        if resolve_engine(engine) == "local":
            return _execute(scene_dir, cfg, steps, _direct, _nothing)
        return generate_flow(flow_name)(str(scene_dir), cfg, until, lock_held=True)


def stored_config(scene_dir: Path | str) -> RunConfig | None:
    """The configuration of the scene's last completed run; None for a new scene, one whose runs all failed, or
    one this version cannot read."""
    return _config_attr(scene_dir, "config")


def segments_config(scene_dir: Path | str) -> RunConfig | None:
    """The configuration the scene's segments were last generated under (a run that failed after generating them
    included); else the stored config (scenes made before this was recorded); None when neither is readable."""
    return _config_attr(scene_dir, "segments_config") or stored_config(scene_dir)


def _config_attr(scene_dir: Path | str, name: Literal["config", "segments_config"]) -> RunConfig | None:
    from wonderverse.config import scene_config

    return scene_config(scene_dir, name)


def refuse_replacing_segments(scene_dir: Path | str, cfg: RunConfig) -> None:
    """WonderError when running `cfg` would regenerate segments the scene already holds: what the segments
    are made from (the `plan` and `generate_segments` steps' parameters: prompt, seed, video settings,
    planner, extensions) differs from what they were made with (`segments_config`). Extensions added since
    (`extend`) are fine."""
    from tasks.segments import segment_ids

    old = segments_config(scene_dir)
    if old is None:
        return
    store = SceneStore.open(scene_dir)
    made = [s for s in segment_ids(store) if store.cache_key_of(SEGMENT.at(seg=s)) is not None]
    if not made:
        return
    added_old, added_new = old.scene.extensions.added, cfg.scene.extensions.added
    changed = [] if added_new[: len(added_old)] == added_old else ["scene.extensions.added"]
    by_name = {s.name: s for s in STEPS}
    for name in ("plan", "generate_segments"):
        before = _flat(_jsonable(by_name[name].params(old)))
        after = _flat(_jsonable(by_name[name].params(cfg)))
        changed += [k for k in sorted(before.keys() | after.keys()) if before.get(k) != after.get(k)]
    # the plan and the segments read some settings both (the prompt): name each once, as the user writes it
    changed = [c.removeprefix("source.") for c in changed if not c.startswith("extensions.added")]
    changed = list(dict.fromkeys(changed))
    if not changed:
        return
    raise WonderError(
        f"{scene_dir} holds {len(made)} segment(s) made with other settings ({', '.join(changed[:4])}"
        f"{', …' if len(changed) > 4 else ''}); this run would replace them. Pass --replace-segments to do so, "
        "or --out another folder"
    )


def _jsonable(params: Any) -> Any:
    import json

    from pydantic_core import to_jsonable_python

    return json.loads(json.dumps(to_jsonable_python(params)))


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    """{'video.width': 320, ...} from nested dicts (lists stay values)."""
    if not isinstance(d, dict):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out |= _flat(v, f"{prefix}.{k}" if prefix else str(k))
    return out
