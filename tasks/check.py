"""Step `check`: the paper's geometric correction over every segment (`tasks.segment_check.check_segment`: SfM,
the abnormal-sequence test, regeneration with a new seed until an attempt passes), segments in parallel on Dask.
The step's own group `check` holds the summary (extra trials per segment, dropped segments, kept failing ones).
"""

from __future__ import annotations

import numpy as np

from tasks.base import Step, StepContext
from tasks.parallel import map_segments
from tasks.progress import callback
from tasks.segment_check import CheckParams, check_segment, is_checked
from tasks.segments import pixels, segment_ids
from wonderverse.config import RunConfig
from wonderverse.schema import CHECK
from wonderverse.store import SceneStore

Params = CheckParams


def params(cfg: RunConfig) -> CheckParams:
    return CheckParams(check=cfg.steps.check, source=cfg.scene.video_source)


def run(store: SceneStore, p: CheckParams, ctx: StepContext) -> str:
    segs = segment_ids(store)
    # segments checked already (a guided flow checks them while generating) are read here; no workers start for them
    todo = [s for s in segs if not is_checked(store, p, s)]
    done = {s: check_segment(s, str(store.scene_dir), p) for s in segs if s not in todo}
    fresh = map_segments(
        check_segment,
        todo,
        str(store.scene_dir),
        p,
        workers=ctx.execution.segment_workers,
        address=ctx.execution.dask_address,
        step="check",
        pixels=pixels(store, todo),
        min_pixels=ctx.execution.cluster_min_pixels,
        progress=callback("clips checked" if p.source.video.backend == "files" else "segments checked"),
    )
    results = [done[s] if s in done else fresh[todo.index(s)] for s in segs]
    decisions = [r.decision for r in results]
    dropped = [d.segment for d in decisions if d.dropped]
    failing = [d.segment for d in decisions if d.reasons and not d.dropped]
    mean_extra = float(np.mean([d.extra_trials for d in decisions]))
    with store.staged(
        CHECK.path, ctx.key, segments=decisions, mean_extra_trials=mean_extra, dropped=dropped, kept_failing=failing
    ):
        pass
    cached = sum(r.cached for r in results)
    if p.source.video.backend == "files":  # the user's clips: checked, never regenerated
        return _clips_summary(len(segs), cached, dropped, failing)
    msg = f"{len(segs)} segments" + (f" ({cached} cached)" if cached else "")
    msg += f", {sum(r.regenerated for r in results)} regenerated this run"
    msg += f", dropped {', '.join(dropped)}" if dropped else ""
    return msg + (f", kept failing {', '.join(failing)}" if failing else "")


def _clips_summary(n: int, cached: int, dropped: list[str], failing: list[str]) -> str:
    """'2 clips checked (1 unchanged): 1 passed, kept failing s001 (warned)'."""
    passed = n - len(dropped) - len(failing)
    msg = f"{n} clip{'s' * (n != 1)} checked" + (f" ({cached} unchanged)" if cached else "") + f": {passed} passed"
    msg += f", dropped {', '.join(dropped)}" if dropped else ""
    return msg + (f", kept failing {', '.join(failing)} (warned)" if failing else "")


# 3: a guessed K is self-calibrated with its pixel aspect held; too little parallax stops SfM before mapping
STEP = Step(
    "check", 3, ("generate_segments",), params, run, "SfM pose check, regenerate abnormal segments", group=CHECK.path
)
