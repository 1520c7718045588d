"""What every pipeline step is: a plain function over the store plus a thin Prefect task.

The step contract: `run(store, params, ctx) -> one-line summary`. `params` is the step's own pydantic model,
built from the configuration by `Step.params`; that one object is both what the step's cache key hashes and
all of the configuration the step is given, so a step cannot read a setting its key ignores. `ctx` carries
the step's key (its group is marked complete under it) and the execution settings (workers, Dask, renderer:
where and how fast, never hashed). A step reads its inputs from the store through `wonderverse.schema`,
writes only its own group(s) through `SceneStore.staged`, and is skipped when its group is complete under the
same key. Keys are a Merkle chain computed from the config alone (`step_keys`), known before anything runs.

Adding a step: declare its group in `wonderverse/schema.py`, write `tasks/<name>.py` with its params model,
`params(cfg)`, `run` and `STEP`, and list it in `tasks/__init__.py` in dependency order.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Generic, Literal, TypeVar

from pydantic import BaseModel

from wonderverse.config import ExecutionParams, RunConfig
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore, cache_key, writing

P = TypeVar("P", bound=BaseModel)


@dataclass(frozen=True)
class StepContext:
    """What a step gets beside its params: its own cache key and the (unhashed) execution settings."""

    key: str
    execution: ExecutionParams = field(default_factory=ExecutionParams)


# Failures worth a retry: a lost connection to a Dask scheduler, a network timeout of a remote model or
# planner. Matched by class name so that this module imports neither distributed nor httpx.
_TRANSIENT_NAMES = frozenset({"CommClosedError", "StreamClosedError", "TransportError"})
RETRY_DELAYS_S = [10, 60]


def is_transient(exc: BaseException) -> bool:
    """Whether a step's exception may go away on a retry (connection lost, timeout); never a WonderError."""
    if isinstance(exc, WonderError):
        return False
    if isinstance(exc, (ConnectionError, TimeoutError)):
        return True
    return any(c.__name__ in _TRANSIENT_NAMES for c in type(exc).__mro__)


def retry_if_transient(task: Any, task_run: Any, state: Any) -> bool:
    """Prefect `retry_condition_fn`: retry transient failures only. Must stay a plain function: Prefect
    ignores (never retries on) any other kind of callable."""
    return isinstance(state.data, BaseException) and is_transient(state.data)


@dataclass(frozen=True)
class StepResult:
    step: str
    status: Literal["ran", "cached", "failed"]
    seconds: float
    cache_key: str
    detail: str = ""


@dataclass(frozen=True)
class Step(Generic[P]):
    """name, version (bumped when the step's results change for the same params), the steps it depends on,
    `params(cfg)` (the step's model: hashed and passed), `run(store, params, ctx)`, and the group it owns."""

    name: str
    version: int
    depends: tuple[str, ...]
    params: Callable[[RunConfig], P]
    run: Callable[[SceneStore, P, StepContext], str] = field(repr=False)
    description: str
    group: str
    retries: int = 2  # Prefect task retries, on transient failures only (a retry resumes from the store)

    @cached_property
    def task(self) -> Any:
        """The Prefect task over `run_in`; built lazily so importing steps does not import Prefect."""
        from prefect import task
        from prefect.cache_policies import NO_CACHE

        # Caching is ours (the store), not Prefect's: Prefect's cache would hide store state.
        return task(
            name=self.name,
            cache_policy=NO_CACHE,
            retries=self.retries,
            retry_delay_seconds=RETRY_DELAYS_S,
            retry_condition_fn=retry_if_transient,
        )(self.run_in)

    def run_in(self, scene_dir: str, params: P, ctx: StepContext) -> str:
        """Open the store at `scene_dir` and run (what the Prefect task calls)."""
        store = SceneStore.open(scene_dir, mode="r+")
        with writing(self.name):
            return self.run(store, params, ctx)


def step_keys(steps: list[Step], cfg: RunConfig) -> dict[str, str]:
    """Cache key of every step, in dependency order: sha256(name, version, params, input keys)."""
    keys: dict[str, str] = {}
    for s in steps:
        keys[s.name] = cache_key(s.name, s.version, s.params(cfg), [keys[d] for d in s.depends])
    return keys
