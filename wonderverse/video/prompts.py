"""What a segment is generated from besides its camera path: the paper's prompt for it, and a seed per attempt."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np


def segment_prompt(scene_prompt: str, role: str, intent: str) -> str:
    """The paper's prompt template for a segment ("around left|right" for side extensions), with the user's words
    for it (`intent`) at the end."""
    around = {"left": " around left,", "right": " around right,"}.get(role, "")
    extra = f" {intent}." if intent else ""
    return f"aerial shot, soft lighting,{around} realistic, high-quality, displaying {scene_prompt}.{extra}"


def attempt_seed(scene_seed: int, seg: str, attempt: int) -> int:
    """A distinct, reproducible seed per (scene, segment `sNNN`, attempt)."""
    ss = np.random.SeedSequence([scene_seed, int(seg.lstrip("s")), attempt])
    return int(ss.generate_state(1)[0])


def replay_content(model: Any, scene_prompt: str, segments: Iterable[tuple[str, str, np.ndarray]]) -> None:
    """Give a fresh video model what every planned segment's words placed in its world ((role, intent, W2C path) per
    segment), so a segment rendered now — a later `extend`, a regeneration in the check — sees the lake an earlier
    segment's words put there. Only backends that keep a world (the procedural one) have `place_content`."""
    place = getattr(model, "place_content", None)
    if place is None:
        return
    for role, intent, path in segments:
        if intent and np.isfinite(path).all():
            place(segment_prompt(scene_prompt, role, intent), path)
