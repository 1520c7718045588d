"""Pipeline steps, in dependency order. Each module holds `Params`, `params(cfg)`, `run(store, params, ctx)`, `STEP`."""

from __future__ import annotations

from tasks import check, generate_segments, outputs, plan, poses, priors, splats
from tasks.base import Step, StepResult, step_keys

STEPS: list[Step] = [
    plan.STEP,
    generate_segments.STEP,
    check.STEP,
    poses.STEP,
    priors.STEP,
    splats.STEP,
    outputs.STEP,
]
STEP_NAMES = [s.name for s in STEPS]

__all__ = ["STEPS", "STEP_NAMES", "Step", "StepResult", "step_keys", "steps_until"]


def steps_until(until: str | None) -> list[Step]:
    """The steps `until` needs (itself and its transitive dependencies), in order; all when None."""
    if until is None:
        return list(STEPS)
    by_name = {s.name: s for s in STEPS}
    if until not in by_name:
        raise KeyError(until)
    needed, stack = set(), [until]
    while stack:
        n = stack.pop()
        if n not in needed:
            needed.add(n)
            stack += by_name[n].depends
    return [s for s in STEPS if s.name in needed]
