"""The guided flow's scheduler: when the video model takes guides (`source_takes_guide`), an extension is generated
from what its parent already shows, rendered along its planned path (`tasks.segment_geometry.parent_guide`), so its
parent must be checked and placed in the plan's world first.

Wave by wave: the wave's segments are rendered (`tasks.attempts.generate_segment`), then each is checked
(`tasks.segment_check.check_segment`, regenerated until accepted, under the check step's own keys, so that step later
finds it done) and placed (`tasks.segment_geometry.place`), one task per segment on Dask when there are workers,
before the next wave; the left and right branches of a wave run side by side. An extension's key adds its parent's
geometry key (the parent's accepted attempt, its frames and the depth settings), so whatever changes its guide
regenerates it.

One cluster serves every wave (started ahead, while the first wave renders, when a wave will have segments to check
side by side), and a segment's check is submitted to it as soon as the segment is rendered, so it runs while the
wave's other segments render. Without workers the order is render all, then check each.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from tasks.attempts import RenderParams, generate_segment, guided_key
from tasks.base import StepContext
from tasks.fan_out import fan_out
from tasks.parallel import SegmentPool, segment_pool
from tasks.progress import callback
from tasks.segment_check import CheckParams, SegmentChecked, check_segment, is_checked
from tasks.segment_geometry import parent_geometry_key, place
from wonderverse.config import CheckStepParams, PriorsStepParams
from wonderverse.errors import WonderError
from wonderverse.guide import GuideParams
from wonderverse.planning.paths import SegmentPath, waves
from wonderverse.schema import SEGMENT
from wonderverse.schema.attrs import GeometryAttrs
from wonderverse.segment_geometry import GeometryParams
from wonderverse.store import SceneStore


class GuidedParams(RenderParams):
    """A guided flow's: also what each extension's guide is made from, since every segment is checked and placed
    before its extensions are generated: the check's settings (which attempt is accepted, its SfM), the depth
    settings that place its frames (`tasks.segment_geometry.depth_settings`), how they are placed and how guides
    are rendered (`steps.generate_segments`)."""

    check: CheckStepParams
    depth: PriorsStepParams
    geometry: GeometryParams
    guide: GuideParams


def check_and_place(
    seg: str, scene_dir: str, check_params: CheckParams, settings: PriorsStepParams, params: GeometryParams
) -> tuple[SegmentChecked, GeometryAttrs]:
    """One segment's check (regenerating until an attempt passes), and then its geometry (`place`)."""
    checked = check_segment(seg, scene_dir, check_params)
    return checked, place(seg, scene_dir, settings, params)


@dataclass
class _Waves:
    """One guided run over the waves of a scene: what every wave needs, and the tally of what they did."""

    store: SceneStore
    p: GuidedParams
    ctx: StepContext
    model: Any
    paths: dict[str, SegmentPath]
    keys: dict[str, str]  # each segment's key; an extension's is completed once its parent's geometry is known
    pool: SegmentPool
    rendered: int = 0
    regenerated: int = 0
    dropped: list[str] = field(default_factory=list)
    unplaced: list[str] = field(default_factory=list)

    def run(self, wave: int, batch: list[str]) -> None:
        """Render the wave's segments, submitting each one's check and placement as soon as it is rendered, then
        gather them (segments checked before are placed in-process)."""
        p, scene_dir = self.p, str(self.store.scene_dir)
        check_p = CheckParams(check=p.check, source=p.source)
        submitted: dict[str, Any] = {}

        def generate(seg: str) -> bool:
            fresh = self._generate(seg)
            if not is_checked(self.store, check_p, seg):
                args = (seg, scene_dir, check_p, p.depth, p.geometry)
                submitted[seg] = self.pool.submit(check_and_place, *args, only_if_started=True)
            return fresh

        try:
            progress = callback(f"segments of wave {wave + 1} generated")
            self.rendered += sum(
                fan_out("generate_segments", batch, generate, self.ctx.execution.generate_workers, progress)
            )
            done = {
                seg: check_and_place(seg, scene_dir, check_p, p.depth, p.geometry)
                for seg in batch
                if seg not in submitted
            }
            todo = [seg for seg in batch if seg in submitted]
            checked = callback(f"segments of wave {wave + 1} checked and placed")
            done |= dict(zip(todo, self.pool.gather("check", todo, submitted, checked), strict=True))
        except Exception:
            self.pool.settle(submitted.values())  # what the workers are writing is finished before they stop
            raise
        results = [done[seg] for seg in batch]
        self.regenerated += sum(checked.regenerated for checked, _ in results)
        self.dropped += [c.decision.segment for c, _ in results if c.decision.dropped]
        self.unplaced += [c.decision.segment for c, g in results if not c.decision.dropped and not g.placed]

    def _generate(self, seg: str) -> bool:
        """Render `seg` unless it is complete under its key (an extension's needs its parent's geometry). True when
        rendered."""
        sp = self.paths[seg]
        if sp.parent is not None:
            geometry = parent_geometry_key(self.store, seg, sp.parent)
            self.keys[seg] = guided_key(self.p, self.p.guide, sp, self.keys[sp.parent], geometry)
        if self.store.is_complete(SEGMENT.at(seg=seg), self.keys[seg]):
            return False
        generate_segment(self.store, self.p.source, self.model, sp, self.keys[seg], self.p.guide)
        return True

    def summary(self) -> str:
        msg = f"{self.rendered} rendered, {len(self.paths) - self.rendered} cached; checked and placed "
        msg += f"({self.regenerated} regenerated"
        msg += f", dropped {', '.join(self.dropped)}" if self.dropped else ""
        msg += f", not placed {', '.join(self.unplaced)}" if self.unplaced else ""
        return msg + ")"


def run_guided(
    store: SceneStore,
    p: GuidedParams,
    ctx: StepContext,
    model: Any,
    paths: dict[str, SegmentPath],
    keys: dict[str, str],
) -> str:
    """Every wave rendered, checked and placed in turn (see the module); `keys`: each segment's key, an
    extension's completed here once its parent's geometry is known. Returns the step's summary line."""
    if p.depth.models.depth_backend == "none":
        raise WonderError(
            "the video model takes guides, and an extension's guide is its parent's frames placed by their depth: "
            "set steps.priors.models.depth_backend (none names no depth model)"
        )
    batches = waves(paths)
    workers = min(ctx.execution.segment_workers, max(len(batch) for batch in batches))
    with segment_pool(workers, ctx.execution.dask_address, "generate_segments") as pool:
        if _side_by_side(store, batches):
            pool.start()
        run = _Waves(store, p, ctx, model, paths, keys, pool)
        for wave, batch in enumerate(batches):
            run.run(wave, batch)
    return run.summary()


def _side_by_side(store: SceneStore, batches: list[list[str]]) -> bool:
    """Whether some wave has two segments never checked before (a new scene, new extensions): then the workers are
    started ahead, while the first wave renders. (A re-run, or a new extension alone in its wave, starts none.)"""
    return any(sum(not store.exists(SEGMENT.at(seg=seg).accepted) for seg in batch) >= 2 for batch in batches)
