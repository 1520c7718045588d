"""Step `plan`: the scene description (and the user's words) -> one camera move per segment."""

from __future__ import annotations

from typing import Any

from tasks.base import Step
from wonderverse.config import RunConfig
from wonderverse.schema import PLAN
from wonderverse.store import SceneStore


def _params(cfg: RunConfig) -> dict[str, Any]:
    s = cfg.scene
    # The API key itself is never part of the config; only the variable's name is.
    return {
        "prompt": s.prompt,
        "extensions": s.extensions,
        "planner": s.planner,
        "plan": cfg.steps.plan,
        "fov_deg": s.video.fov_deg,
    }


def run(store: SceneStore, cfg: RunConfig, key: str) -> str:
    from wonderverse.planning import make_planner

    if cfg.scene.video.backend == "files":
        plan = clip_plan(cfg.scene.video.clips)
        with store.staged(
            PLAN.path, key, plan=plan.model_dump(mode="json"), moves=[], intents=list(cfg.scene.video.clips)
        ):
            pass
        return f"{len(plan.segments)} segments, one per clip"
    planner = make_planner(cfg.scene.planner)
    s, fov = cfg.scene, cfg.scene.video.fov_deg
    plan = planner.plan_scene(s.prompt, s.extensions.model_copy(update={"added": ()}), cfg.steps.plan, fov_deg=fov)
    for words in s.extensions.added:  # each later extension continues the plan as it stood (interactive)
        plan = plan.extended(planner.plan_extension(s.prompt, words, plan, cfg.steps.plan, fov_deg=fov))
    with store.staged(
        PLAN.path,
        key,
        plan=plan.model_dump(mode="json"),
        moves=[s.move.to_paper() for s in plan.segments],
        intents=[s.intent for s in plan.segments],
    ):
        pass
    note = f" ({plan.fallback_reason})" if plan.fallback_reason else ""
    return f"{len(plan.segments)} segments by {plan.planner}{note}"


def clip_plan(clips: tuple[str, ...]) -> Any:
    """The user's clips as segments in the given order: the first as `init`, the rest as `right` ones (played
    forward, after the previous); no camera moves are planned, none are generated."""
    from wonderverse.planning import CameraMove, Plan
    from wonderverse.planning.segments import next_segment

    segments: list[Any] = []
    for i, clip in enumerate(clips):
        segments.append(next_segment(tuple(segments), "init" if i == 0 else "right", CameraMove(), clip))
    return Plan(segments=tuple(segments), planner="clips")


def load_plan(store: SceneStore) -> Any:
    """The stored Plan (raises KeyError when the plan step has not completed)."""
    from wonderverse.planning import Plan

    attrs = store.attrs(PLAN.path)
    if attrs.get("complete") is not True:
        raise KeyError("plan")
    return Plan.model_validate(attrs["plan"])


STEP = Step("plan", 1, (), _params, run, "camera moves from the prompt (LLM or rules)", group=PLAN.path)
