"""A segment's attempts: rendering one with the video backend and writing it to the store.

The first attempt of a segment is committed with the segment itself (`generate_segment`: its conditioning path, K
and the plan's record of it); every later one is a regeneration of the check (`add_attempt`: a new attempt group,
never an overwrite). Both render through `_render` — the paper's prompt for the segment, a seed of its own per
attempt (`wonderverse.video.prompts`), the reference frame from the parent's accepted attempt and, in guided flows,
the guide rendered from the parent's geometry (`tasks.segment_geometry.parent_guide`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tasks.segment_geometry import parent_guide
from tasks.segments import frames, segment_meta
from wonderverse.camera import intrinsics
from wonderverse.config import Model, VideoSource
from wonderverse.errors import WonderError
from wonderverse.guide import GuideParams
from wonderverse.planning.paths import SegmentPath
from wonderverse.schema import ATTEMPT, ATTEMPT_GT, SEGMENT, SEGMENTS, GroupPath
from wonderverse.store import SceneStore, attrs_json, cache_key, write_array
from wonderverse.video.prompts import attempt_seed, replay_content, segment_prompt

SEGMENT_VERSION = 2  # 2: keyed by the step's params model
ATTEMPT_VERSION = 4  # the check's version when regenerations moved here: their keys are unchanged


class RenderParams(Model):
    """What segments are rendered from: the video source, and the sideways travel per degree of a planned turn."""

    source: VideoSource
    strafe_m_per_deg: float


def _rendered_with(p: RenderParams) -> RenderParams:
    """The settings every segment is rendered with (a guided flow's extras left out): what a segment is keyed by."""
    return RenderParams(source=p.source, strafe_m_per_deg=p.strafe_m_per_deg)


def segment_key(p: RenderParams, sp: SegmentPath, parent_key: str | None) -> str:
    """A segment's key: its plan entry, the render settings and its parent's key."""
    entry = {"params": _rendered_with(p), "segment": sp.plan}
    return cache_key("segment", SEGMENT_VERSION, entry, [parent_key] if parent_key else [])


def guided_key(p: RenderParams, guide: GuideParams, sp: SegmentPath, parent_key: str, geometry_key: str) -> str:
    """An extension's key in a guided flow: its plan entry and render settings, its parent's key and the key of
    the parent's geometry its guide is rendered from."""
    entry = {"params": _rendered_with(p), "segment": sp.plan, "guide": guide}
    return cache_key("segment", SEGMENT_VERSION, entry, [parent_key, geometry_key])


def generate_segment(
    store: SceneStore,
    source: VideoSource,
    model: Any,
    sp: SegmentPath,
    key: str,
    guide_params: GuideParams | None = None,
) -> None:
    """Render a segment's first attempt and commit the segment under `key`; `guide_params`: a guided flow's (an
    extension is then generated from its parent's geometry)."""
    seg, s, v = sp.plan.id, sp.plan, source.video
    ref = frames(store, sp.parent)[sp.ref_idx] if sp.parent is not None and sp.ref_idx is not None else None
    guide = record = None
    if guide_params is not None and sp.parent is not None:
        K_out = intrinsics(v.width, v.height, v.fov_deg)
        guide, record = parent_guide(store, seg, sp.parent, sp.ref_idx, sp.path, K_out, v.width, v.height, guide_params)
    video, seed = _render(source, model, seg, 0, s.role, s.intent, sp.path, ref, guide)
    K = video.K if video.K is not None else intrinsics(v.width, v.height, v.fov_deg)
    seg_attrs = {
        "role": s.role,
        "reversed": s.reversed,
        "move": s.move.to_paper(),
        "intent": s.intent,
        "reference_segment": sp.parent,
        "reference_frame": sp.ref_idx,
        "repeats_reference": sp.ref_idx is not None,  # a generated extension's frame 0 is its reference
        "k_is_guess": video.K is None or video.k_is_guess,  # the check's SfM holds a known K
    }
    if v.backend == "files":  # what reading the clip did to it, for the report
        seg_attrs["read_notes"] = list(model.clips[int(seg.lstrip("s"))].notes)
    if record is not None:  # regenerations (the check's) render the same guide, from the same geometry
        seg_attrs["guide_geometry_key"] = record["geometry_key"]
        seg_attrs["guide_params"] = guide_params.model_dump(mode="json")
    at = SEGMENT.at(seg=seg)
    with store.staged(at, key, **seg_attrs) as g:
        write_array(g, at.path, sp.path)
        write_array(g, at.K, K)
        first = ATTEMPT.at(seg=seg, attempt=0)
        write_attempt(g.create_group(first.relative_to(at)), first, video, seed, v.backend, record)


def add_attempt(store: SceneStore, source: VideoSource, model: Any, seg: str, attempt: int, seg_key: str) -> None:
    """Render attempt `attempt` (> 0) of a committed segment and commit it as a group of its own."""
    video, seed, guide = render_attempt(store, source, model, seg, attempt)
    at = ATTEMPT.at(seg=seg, attempt=attempt)
    with store.staged(at, cache_key("attempt", ATTEMPT_VERSION, {"seed": seed}, [seg_key])) as g:
        write_attempt(g, at, video, seed, source.video.backend, guide)


def render_attempt(
    store: SceneStore, source: VideoSource, model: Any, seg: str, attempt: int
) -> tuple[Any, int, dict[str, Any] | None]:
    """Render attempt `attempt` of a segment whose plan (path, reference) is already in the store: the video,
    its seed, and the record of its guide (None when unguided).

    The reference frame comes from the parent's accepted attempt; the seed is new for every attempt. A segment
    generated from a guide is regenerated from the same one (its parent's geometry, which must not have changed
    since: WonderError)."""
    a = segment_meta(store, seg)
    parent, ref_idx = a.reference_segment, a.reference_frame
    ref = frames(store, parent)[ref_idx] if parent and ref_idx is not None else None
    path = store.array(SEGMENT.at(seg=seg).path)
    guide = record = None
    if parent and ref_idx is not None and a.guide_geometry_key:
        v = source.video
        K_out = intrinsics(v.width, v.height, v.fov_deg)
        params = GuideParams.model_validate(a.guide_params or {})
        guide, record = parent_guide(store, seg, parent, ref_idx, path, K_out, v.width, v.height, params)
        if record["geometry_key"] != a.guide_geometry_key:
            raise WonderError(
                f"segment {seg}: the geometry of its parent segment {parent} changed since {seg} was generated; "
                "run generate_segments to generate it again"
            )
    video, seed = _render(source, model, seg, attempt, a.role, a.intent, path, ref, guide)
    return video, seed, record


def _render(
    source: VideoSource,
    model: Any,
    seg: str,
    attempt: int,
    role: str,
    intent: str,
    path: np.ndarray,
    ref: Any,
    guide: Any = None,
) -> tuple[Any, int]:
    """One generation: the paper's prompt for the segment, a seed of its own for this attempt, the guide when
    there is one (a user clip is read, not generated). A model that takes guides names the segment in its
    errors (a guide that does not fit the video, a family whose pipeline cannot take the guide)."""
    if source.video.backend == "files":
        return model.segment(int(seg.lstrip("s"))), 0
    seed = attempt_seed(source.seed, seg, attempt)
    prompt = segment_prompt(source.prompt, role, intent)
    if guide is None and not getattr(model, "takes_guide", False):
        return model.generate(prompt, path, seed, ref), seed
    try:
        if guide is None:
            return model.generate(prompt, path, seed, ref), seed
        from wonderverse.guide import validate_guide

        v = source.video
        validate_guide(guide, len(path), v.height, v.width)
        return model.generate(prompt, path, seed, ref, guide=guide), seed
    except WonderError as e:
        raise WonderError(f"segment {seg}: {e}") from None


def write_attempt(
    group: Any, at: GroupPath, video: Any, seed: int, source: str, guide: dict[str, Any] | None = None
) -> None:
    """Frames (and ground truth when the backend has it) of the attempt `at` into `group`, its staged copy;
    `guide`: the record of the guide it was generated from (guided extensions)."""
    group.attrs.update(attrs_json(at, {"seed": seed, "source": source, "guide": guide}))
    write_array(group, at.frames, video.frames)
    if video.gt is not None:
        gt = group.create_group(ATTEMPT_GT.name)
        write_array(gt, at.gt.poses, video.gt.poses)
        write_array(gt, at.gt.depth, video.gt.depth)
        write_array(gt, at.gt.normals, video.gt.normals)
        truth: dict[str, Any] = {"faults": video.gt.faults, "guide": getattr(video.gt, "guide", None)}
        if video.gt.labels is not None:
            write_array(gt, at.gt.labels, video.gt.labels)
            truth["label_names"] = {str(k): v for k, v in video.gt.label_names.items()}
        gt.attrs.update(attrs_json(at.gt, truth))


def video_model(store: SceneStore, source: VideoSource) -> Any:
    """A video model for regenerating this scene's segments, given what every stored segment's words placed."""
    from wonderverse.video import make_video_model

    model = make_video_model(source)
    replay_content(model, source.prompt, _stored_words(store))
    return model


def _stored_words(store: SceneStore) -> list[tuple[str, str, np.ndarray]]:
    """(role, intent, path) of every stored segment whose user's words are not empty, for `replay_content`."""
    out = []
    for seg in store.children(SEGMENTS.path):
        a = segment_meta(store, seg)
        if a.intent and store.exists(SEGMENT.at(seg=seg).path):
            out.append((a.role, a.intent, store.array(SEGMENT.at(seg=seg).path)))
    return out
