"""`wonderverse extend`: the paper's interactive extension. The user's words become one more extension in the
scene spec (`extensions.added`, the history); the planner continues the stored plan from them, and the
pipeline re-runs with every step cached except what the new segment changes: the new segment is generated
and checked; priors of the old segments keep their network output (`priors_raw/`); the new frames are
registered into the stored reconstruction with the old poses held fixed (a full re-solve, mapped into the
previous world frame, when that fails its gates); the splats continue from the existing Gaussians, new
ones seeded and densified only where the new frames see something new; the outputs are refreshed. With a video
model that takes guides, the new segment is generated from its parent's stored geometry (made then, when the
parent has none yet), checked and placed inside generate_segments, as every guided extension is."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from flows.engine import Engine
from wonderverse.errors import WonderError
from wonderverse.text import plain_words, visible

if TYPE_CHECKING:  # the CLI judges a request with this module: the config and the steps load only once it passes
    from tasks import StepResult
    from wonderverse.config import RunConfig

MAX_WORDS_CHARS = 500


def checked_words(words: str) -> str:
    """The extension request as it is stored (whitespace runs one space); WonderError for empty or over-long words,
    or words holding a control character (a terminal escape). The studio checks a request with this too, so its
    messages are the CLI's."""
    try:
        words = plain_words(words, "the extension request")
    except ValueError as e:
        raise WonderError(str(e)) from None
    if not words or not visible(words):
        raise WonderError("the extension request is empty; say where to go, e.g. 'a frozen lake on the left'")
    if len(words) > MAX_WORDS_CHARS:
        raise WonderError(f"the extension request has {len(words)} characters; at most {MAX_WORDS_CHARS} are allowed")
    return words


def extended_config(cfg: RunConfig, words: str) -> RunConfig:
    """`cfg` with one more user extension; WonderError for unusable words (`checked_words`)."""
    return with_extensions(cfg, (*cfg.scene.extensions.added, checked_words(words)))


def with_extensions(cfg: RunConfig, added: tuple[str, ...]) -> RunConfig:
    """`cfg` whose scene has the extensions `added` (the user's words, oldest first)."""
    from wonderverse.config import validate_config

    ext = cfg.scene.extensions
    scene = cfg.scene.model_copy(update={"extensions": ext.model_copy(update={"added": tuple(added)})})
    return validate_config({**cfg.model_dump(), "scene": scene.model_dump()})


def extension_config(scene_dir: Path | str, words: str) -> RunConfig:
    """The configuration of the scene in `scene_dir` with one more extension, `words` (or, when the last extension
    of a run that stopped before completing had these words, that configuration: the run resumes); WonderError when
    there is no scene, no completed run, or the words are unusable."""
    checked_words(words)  # the cheapest refusal first, before the config loads
    from wonderverse.config import scene_config

    cfg = scene_config(scene_dir, "config")
    if cfg is None:
        from wonderverse import STORE_FORMAT
        from wonderverse.folders import root_attrs

        fmt = (root_attrs(scene_dir) or {}).get("format")
        if not isinstance(fmt, int) or fmt > STORE_FORMAT:  # no scene at all, or a newer one: the store's own error
            from wonderverse.store import SceneStore

            SceneStore.open(scene_dir)
        raise WonderError(f"{scene_dir} holds no completed run; run `wonderverse generate` first")
    done = cfg.scene.extensions.added
    made = scene_config(scene_dir, "segments_config") or cfg  # kept: an extension whose run failed after its segment
    if "files" in (cfg.scene.video.backend, made.scene.video.backend):  # clips: no planned path to continue
        raise WonderError(
            f"{scene_dir} is a reconstruction of clips: extend grows generated scenes only; to add a clip, run "
            "`wonderverse reconstruct` again with every clip, the new one last"
        )
    cfg = with_extensions(cfg, made.scene.extensions.added)
    pending = cfg.scene.extensions.added[len(done) :]
    more = extended_config(cfg, words)
    if pending and more.scene.extensions.added[-1] == pending[-1]:
        return cfg  # the same words again after that run stopped: it resumes, nothing is added twice
    return more


def extend(scene_dir: Path | str, words: str, engine: Engine = "auto") -> list[StepResult]:
    """Add one segment planned from `words` to the scene in `scene_dir` and bring every step up to date."""
    from flows.pipeline import run_pipeline

    return run_pipeline(scene_dir, extension_config(scene_dir, words), engine=engine, flow_name="extend")
