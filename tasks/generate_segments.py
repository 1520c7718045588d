"""Step `generate_segments`: render every planned segment with the video backend.

Segments form a tree (each extension continues from a frame of an earlier one), so they are generated in waves
(`wonderverse.planning.paths`); segments of one wave run concurrently. Each segment is its own cached unit
(`segments/<seg>`, keyed by its plan entry, the video settings and its parent's key: `tasks.attempts.segment_key`),
so adding an extension or re-running after a kill regenerates only what is missing. Guided flows (a video model
that takes guides) check and place every wave before the next one: `tasks.guided`.
"""

from __future__ import annotations

from typing import Any

from tasks.attempts import RenderParams, generate_segment, segment_key
from tasks.base import Step, StepContext
from tasks.fan_out import fan_out
from tasks.guided import GuidedParams, run_guided
from tasks.plan import load_plan
from tasks.progress import advance
from tasks.segment_geometry import depth_settings
from wonderverse.config import RunConfig
from wonderverse.planning.paths import SegmentPath, conditioning_paths, waves
from wonderverse.schema import SEGMENT, SEGMENTS
from wonderverse.store import SceneStore
from wonderverse.video import source_takes_guide
from wonderverse.video.prompts import replay_content

Params = RenderParams


def params(cfg: RunConfig) -> RenderParams:
    base = RenderParams(source=cfg.scene.video_source, strafe_m_per_deg=cfg.steps.plan.strafe_m_per_deg)
    if not source_takes_guide(cfg.scene.video_source):
        return base
    g = cfg.steps.generate_segments
    depth = depth_settings(cfg.steps.priors)
    return GuidedParams(**dict(base), check=cfg.steps.check, depth=depth, geometry=g.geometry, guide=g.guide)


def segment_keys(p: RenderParams, paths: dict[str, SegmentPath]) -> dict[str, str]:
    """Every segment's key, in generation order (a parent's before its extensions')."""
    keys: dict[str, str] = {}
    for seg, sp in paths.items():
        keys[seg] = segment_key(p, sp, keys[sp.parent] if sp.parent else None)
    return keys


def _run_unguided(
    store: SceneStore,
    p: RenderParams,
    ctx: StepContext,
    model: Any,
    paths: dict[str, SegmentPath],
    keys: dict[str, str],
) -> str:
    todo = [seg for seg in paths if not store.is_complete(SEGMENT.at(seg=seg), keys[seg])]
    clips = p.source.video.backend == "files"  # the user's clips are read, not rendered
    unit = "clips read" if clips else "segments rendered"
    done = 0
    for wave in waves(paths):
        batch = [seg for seg in wave if seg in todo]

        def rendered(k: int, n: int, seg: str, before: int = done) -> None:
            """One count over every wave: a wave's k-th segment is the (earlier waves' + k)-th of the step."""
            if k or not before:
                advance(before + k, len(todo), unit, seg)

        fan_out(
            "generate_segments",
            batch,
            lambda seg: generate_segment(store, p.source, model, paths[seg], keys[seg]),
            ctx.execution.generate_workers,
            progress=rendered,
        )
        done += len(batch)
    if clips:
        return f"{len(todo)} read, {len(paths) - len(todo)} unchanged since the last run"
    return f"{len(todo)} rendered, {len(paths) - len(todo)} cached"


def run(store: SceneStore, p: RenderParams, ctx: StepContext) -> str:
    from wonderverse.planning import stitched_order
    from wonderverse.video import initial_pose, make_video_model

    plan = load_plan(store)
    model = make_video_model(p.source)
    clips = [len(c.frames) for c in model.clips] if p.source.video.backend == "files" else None  # type: ignore[attr-defined]
    v = p.source.video
    paths = conditioning_paths(plan, initial_pose(model), v.frames_per_segment, p.strafe_m_per_deg, clips)
    replay_content(model, p.source.prompt, [(sp.plan.role, sp.plan.intent, sp.path) for sp in paths.values()])
    keys = segment_keys(p, paths)
    if isinstance(p, GuidedParams):
        summary = run_guided(store, p, ctx, model, paths, keys)
    else:
        summary = _run_unguided(store, p, ctx, model, paths, keys)
    for stale in set(store.children(SEGMENTS.path)) - set(paths):
        store.remove(SEGMENT.at(seg=stale))
    store.mark_complete(SEGMENTS.path, ctx.key, order=stitched_order(plan.segments))
    return summary


STEP = Step("generate_segments", 2, ("plan",), params, run, "render every planned segment", group=SEGMENTS.path)
