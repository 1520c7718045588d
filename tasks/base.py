"""What every pipeline step is: a plain function over the store plus a thin Prefect task.

A step reads its inputs from the store, writes only its own group(s) through `SceneStore.staged`,
and is skipped when its group is complete under the same cache key. Keys are a Merkle chain
computed from the config alone (`step_keys`), so they are known before anything runs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal

from wonderverse.config import RunConfig
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore, cache_key

RunFn = Callable[[SceneStore, RunConfig, str], str]

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
class Step:
    """params: what of the config the step reads (hashed);
    run(store, cfg, key) -> one-line summary; it must end with the group marked complete."""

    name: str
    version: int
    depends: tuple[str, ...]
    params: Callable[[RunConfig], Any]
    run: RunFn = field(repr=False)
    description: str = ""
    group: str = ""  # the store group it owns; defaults to the step's name
    retries: int = 2  # Prefect task retries, on transient failures only (a retry resumes from the store)

    def __post_init__(self) -> None:
        if not self.group:
            object.__setattr__(self, "group", self.name)

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

    def run_in(self, scene_dir: str, cfg: RunConfig, key: str) -> str:
        """Open the store at `scene_dir` and run (what the Prefect task and Dask workers call)."""
        store = SceneStore.open(scene_dir, mode="r+")
        return self.run(store, cfg, key)


def step_keys(steps: list[Step], cfg: RunConfig) -> dict[str, str]:
    """Cache key of every step, in dependency order: sha256(name, version, params, input keys)."""
    keys: dict[str, str] = {}
    for s in steps:
        keys[s.name] = cache_key(s.name, s.version, s.params(cfg), [keys[d] for d in s.depends])
    return keys
