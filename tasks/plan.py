"""Step `plan`: the scene description (and the user's words) -> one camera move per segment."""

from __future__ import annotations

from typing import Literal

from tasks.base import Step, StepContext
from wonderverse.config import ExtensionSpec, Model, PlannerSpec, PlanParams, RunConfig
from wonderverse.planning.segments import Plan
from wonderverse.schema import PLAN
from wonderverse.store import SceneStore


class Params(Model):
    """What the plan is made from. The API key itself is never part of the config; only its variable's name."""

    prompt: str
    extensions: ExtensionSpec
    planner: PlannerSpec
    plan: PlanParams
    video_backend: Literal["procedural", "files", "diffusers"]
    clips: tuple[str, ...]
    fov_deg: float


def params(cfg: RunConfig) -> Params:
    s = cfg.scene
    return Params(
        prompt=s.prompt,
        extensions=s.extensions,
        planner=s.planner,
        plan=cfg.steps.plan,
        video_backend=s.video.backend,
        clips=s.video.clips,
        fov_deg=s.video.fov_deg,
    )


def run(store: SceneStore, p: Params, ctx: StepContext) -> str:
    from wonderverse.planning import make_planner
    from wonderverse.planning.segments import clip_plan

    if p.video_backend == "files":
        plan = clip_plan(p.clips)
        with store.staged(PLAN.path, ctx.key, plan=plan.model_dump(mode="json"), moves=[], intents=list(p.clips)):
            pass
        n = len(plan.segments)
        return f"{n} clip{'s' * (n != 1)}, one segment each, in the order given"
    planner = make_planner(p.planner)
    first = p.extensions.model_copy(update={"added": ()})
    plan = planner.plan_scene(p.prompt, first, p.plan, fov_deg=p.fov_deg)
    for words in p.extensions.added:  # each later extension continues the plan as it stood (interactive)
        plan = plan.extended(planner.plan_extension(p.prompt, words, plan, p.plan, fov_deg=p.fov_deg))
    moves = [s.move.to_paper() for s in plan.segments]
    intents = [s.intent for s in plan.segments]
    with store.staged(PLAN.path, ctx.key, plan=plan.model_dump(mode="json"), moves=moves, intents=intents):
        pass
    note = f" ({plan.fallback_reason})" if plan.fallback_reason else ""
    return f"{len(plan.segments)} segments by {plan.planner}{note}"


def load_plan(store: SceneStore) -> Plan:
    """The stored Plan (raises KeyError when the plan step has not completed)."""
    meta = store.meta(PLAN.path)
    if meta is None:
        raise KeyError("plan")
    return meta.plan


# 2: the step contract (hashes the video backend and clips it branches on)
STEP = Step("plan", 2, (), params, run, "camera moves from the prompt (LLM or rules)", group=PLAN.path)
