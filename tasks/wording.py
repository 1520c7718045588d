"""What each step does, in the words of the run at hand: the step lines of the terminal, the studio (progress JSON)
and the report.

A step's own `description` speaks of the generating flow (camera moves from the prompt, rendering, regeneration,
depth and normal losses). A reconstruction of the user's clips (video backend `files`) plans nothing, generates
nothing and regenerates nothing; a run without priors computes none and trains on colours alone. `describe` says
so, from a few facts the config (`run_description`) or a stored scene (the report) gives.
"""

from __future__ import annotations

from dataclasses import dataclass

from tasks.base import Step
from wonderverse.config import RunConfig

# What the check does with a clip that fails it (steps.check.on_failure): a clip is never regenerated.
CLIP_FAILURE = {
    "keep_best": "a clip that fails it is kept, with a warning",
    "drop": "a clip that fails it is dropped",
    "fail": "a clip that fails it stops the run",
}


@dataclass(frozen=True)
class RunFacts:
    """What decides a step's wording: clips (the user's own footage, not generated), which priors exist, and what
    the check does with a clip that fails it (`steps.check.on_failure`)."""

    clips: bool
    depth: bool
    normals: bool
    on_failure: str = "keep_best"

    @staticmethod
    def of(cfg: RunConfig) -> RunFacts:
        models = cfg.steps.priors.models
        return RunFacts(
            clips=cfg.scene.video.backend == "files",
            depth=models.depth_backend != "none",
            normals=models.normal_backend != "none",
            on_failure=cfg.steps.check.on_failure,
        )


def _losses(facts: RunFacts) -> str:
    if facts.depth and facts.normals:
        return "with depth and normal losses"
    if facts.depth or facts.normals:
        return f"with {'depth' if facts.depth else 'normal'} losses (no {'normal' if facts.depth else 'depth'} prior)"
    return "on colours alone (no priors)"


def describe(step: str, default: str, facts: RunFacts) -> str:
    """The step's description for a run of `facts`; `default` (the step's own) where nothing differs."""
    if step == "splats":
        return f"3D Gaussian splatting {_losses(facts)}"
    if step == "priors" and not (facts.depth or facts.normals):
        return "no priors (no depth model named): nothing to compute"
    if not facts.clips:
        return default
    return {
        "plan": "one segment per clip, in the order given (nothing planned)",
        "generate_segments": "read every clip (nothing generated)",
        "check": f"SfM check of each clip; {CLIP_FAILURE.get(facts.on_failure, 'a clip is never regenerated')}",
        "poses": "one camera path through the frames of every clip (global SfM)",
        "priors": "depth and normal priors of every clip, aligned to SfM",
    }.get(step, default)


def run_description(step: Step, cfg: RunConfig) -> str:
    """`describe` for a step of a run of `cfg` (what the step line shows when the step starts)."""
    return describe(step.name, step.description, RunFacts.of(cfg))
