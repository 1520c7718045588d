"""`wonderverse extend`: the paper's interactive extension. The user's words become one more extension in the
scene spec (`extensions.added`, the history); the planner continues the stored plan from them, and the
pipeline re-runs with every step cached except what the new segment changes: the new segment is generated
and checked; priors of the old segments keep their network output (`priors_raw/`); the new frames are
registered into the stored reconstruction with the old poses held fixed (a full re-solve, mapped into the
previous world frame, when that fails its gates); the splats continue from the existing Gaussians, new
ones seeded and densified only where the new frames see something new; the outputs are refreshed."""

from __future__ import annotations

from pathlib import Path

from tasks import StepResult
from wonderverse.config import RunConfig
from wonderverse.errors import WonderError
from wonderverse.store import SceneStore

MAX_WORDS_CHARS = 500


def extended_config(cfg: RunConfig, words: str) -> RunConfig:
    """`cfg` with one more user extension; WonderError for empty or over-long words."""
    words = " ".join(words.split())
    if not words:
        raise WonderError("the extension request is empty; say where to go, e.g. 'a frozen lake on the left'")
    if len(words) > MAX_WORDS_CHARS:
        raise WonderError(f"the extension request has {len(words)} characters; at most {MAX_WORDS_CHARS} are allowed")
    ext = cfg.scene.extensions
    scene = cfg.scene.model_copy(update={"extensions": ext.model_copy(update={"added": (*ext.added, words)})})
    return RunConfig.model_validate({**cfg.model_dump(), "scene": scene.model_dump()})


def stored_config(scene_dir: Path | str) -> RunConfig:
    """The configuration the scene was last run with."""
    attrs = SceneStore.open(scene_dir).root.attrs
    if "config" not in attrs:
        raise WonderError(f"{scene_dir} holds no run configuration; run `wonderverse generate` first")
    return RunConfig.model_validate(attrs["config"])


def extend(scene_dir: Path | str, words: str, engine: str = "local") -> list[StepResult]:
    """Add one segment planned from `words` to the scene in `scene_dir` and bring every step up to date."""
    from flows.pipeline import run_pipeline

    cfg = extended_config(stored_config(scene_dir), words)
    return run_pipeline(scene_dir, cfg, engine=engine, flow_name="extend")  # type: ignore[arg-type]
