"""Step `generate_segments`: render every planned segment with the video backend.

Segments form a tree (each extension continues from a frame of an earlier one), so they are
generated in waves; segments of one wave run concurrently. Each segment is its own cached unit
(`segments/<seg>`, keyed by its plan entry, the video settings and its parent's key), so adding an
extension or re-running after a kill regenerates only what is missing.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tasks.base import Step, StepContext
from tasks.parallel import fan_out
from tasks.plan import load_plan
from tasks.progress import advance
from tasks.segments import frames, stitched_frame_index
from wonderverse.camera import intrinsics, move_path
from wonderverse.config import Model, RunConfig, VideoSource
from wonderverse.schema import ATTEMPT, ATTEMPT_GT, SEGMENT, SEGMENTS, GroupPath
from wonderverse.store import SceneStore, cache_key, write_array

SEGMENT_VERSION = 2  # 2: keyed by the step's params model


class Params(Model):
    """What segments are rendered from: the video source, and the sideways travel per degree of a planned turn."""

    source: VideoSource
    strafe_m_per_deg: float


def params(cfg: RunConfig) -> Params:
    return Params(source=cfg.scene.video_source, strafe_m_per_deg=cfg.steps.plan.strafe_m_per_deg)


def attempt_seed(scene_seed: int, seg: str, attempt: int) -> int:
    """A distinct, reproducible seed per (scene, segment, attempt)."""
    ss = np.random.SeedSequence([scene_seed, int(seg.lstrip("s")), attempt])
    return int(ss.generate_state(1)[0])


def segment_prompt(scene_prompt: str, role: str, intent: str) -> str:
    """The paper's prompt template for a segment ("around left|right" for side extensions)."""
    around = {"left": " around left,", "right": " around right,"}.get(role, "")
    extra = f" {intent}." if intent else ""
    return f"aerial shot, soft lighting,{around} realistic, high-quality, displaying {scene_prompt}.{extra}"


def plan_paths(
    p: Params, plan: Any, start_w2c: np.ndarray, clip_lengths: list[int] | None = None
) -> dict[str, dict[str, Any]]:
    """Per segment: conditioning path (T,4,4) W2C, parent, reference index, cache key; generation order.
    User clips (`clip_lengths` frames each) have no conditioning path (NaN) and no reference frame."""
    T = p.source.video.frames_per_segment
    strafe = p.strafe_m_per_deg
    out: dict[str, dict[str, Any]] = {}
    for s in plan.segments:
        parent = out.get(s.reference_segment) if s.reference_segment else None
        if s.reference_segment and parent is None:
            raise ValueError(f"segment {s.id} continues from unknown segment {s.reference_segment}")
        if clip_lengths is not None:
            ref_idx, path = None, np.full((clip_lengths[len(out)], 4, 4), np.nan)
        else:
            ref_idx = stitched_frame_index(parent["reversed"], T, s.reference) if parent else None
            start = parent["path"][ref_idx] if parent else start_w2c
            m = s.move
            path = move_path(start, np.radians(m.yaw_deg), np.radians(m.pitch_deg), m.forward_m, strafe * m.yaw_deg, T)
        key = cache_key("segment", SEGMENT_VERSION, {"params": p, "segment": s}, [parent["key"]] if parent else [])
        out[s.id] = {
            "plan": s,
            "path": path,
            "parent": s.reference_segment,
            "ref_idx": ref_idx,
            "reversed": s.reversed,
            "key": key,
            "wave": parent["wave"] + 1 if parent else 0,
        }
    return out


def render_attempt(store: SceneStore, source: VideoSource, model: Any, seg: str, attempt: int) -> tuple[Any, int]:
    """Render attempt `attempt` of a segment whose plan (path, reference) is already in the store.

    The reference frame comes from the parent's accepted attempt; the seed is new for every attempt."""
    a = store.attrs(SEGMENT.at(seg=seg))
    parent = a.get("reference_segment")
    ref = frames(store, parent)[a["reference_frame"]] if parent else None
    path = store.array(SEGMENT.at(seg=seg).path)
    return _render(source, model, seg, attempt, a["role"], a.get("intent", ""), path, ref)


def _render(
    source: VideoSource, model: Any, seg: str, attempt: int, role: str, intent: str, path: np.ndarray, ref: Any
) -> tuple[Any, int]:
    """One generation: the paper's prompt for the segment, a seed of its own for this attempt (a user clip is
    read, not generated)."""
    if source.video.backend == "files":
        return model.segment(int(seg.lstrip("s"))), 0
    seed = attempt_seed(source.seed, seg, attempt)
    return model.generate(segment_prompt(source.prompt, role, intent), path, seed, ref), seed


def write_attempt(group: Any, at: GroupPath, video: Any, seed: int, source: str) -> None:
    """Frames (and ground truth when the backend has it) of the attempt `at` into `group`, its staged copy."""
    group.attrs.update({"seed": seed, "source": source})
    write_array(group, at.frames, video.frames)
    if video.gt is not None:
        gt = group.create_group(ATTEMPT_GT.name)
        write_array(gt, at.gt.poses, video.gt.poses)
        write_array(gt, at.gt.depth, video.gt.depth)
        write_array(gt, at.gt.normals, video.gt.normals)
        gt.attrs["faults"] = video.gt.faults


def _generate_one(store: SceneStore, source: VideoSource, model: Any, seg: str, info: dict[str, Any]) -> None:
    s = info["plan"]
    ref = frames(store, info["parent"])[info["ref_idx"]] if info["ref_idx"] is not None else None
    video, seed = _render(source, model, seg, 0, s.role, s.intent, info["path"], ref)
    v = source.video
    K = video.K if video.K is not None else intrinsics(v.width, v.height, v.fov_deg)
    seg_attrs = {
        "role": s.role,
        "reversed": s.reversed,
        "move": s.move.to_paper(),
        "intent": s.intent,
        "reference_segment": info["parent"],
        "reference_frame": info["ref_idx"],
        "repeats_reference": info["ref_idx"] is not None,  # a generated extension's frame 0 is its reference
        "k_is_guess": video.K is None or video.k_is_guess,  # the check's SfM holds a known K
    }
    at = SEGMENT.at(seg=seg)
    with store.staged(at, info["key"], **seg_attrs) as g:
        write_array(g, at.path, info["path"])
        write_array(g, at.K, K)
        first = ATTEMPT.at(seg=seg, attempt=0)
        write_attempt(g.create_group(first.relative_to(at)), first, video, seed, v.backend)


def run(store: SceneStore, p: Params, ctx: StepContext) -> str:
    from wonderverse.planning import stitched_order
    from wonderverse.video import initial_pose, make_video_model

    plan = load_plan(store)
    model = make_video_model(p.source)
    clips = [len(c.frames) for c in model.clips] if p.source.video.backend == "files" else None  # type: ignore[attr-defined]
    info = plan_paths(p, plan, initial_pose(model), clips)
    todo = [seg for seg, i in info.items() if not store.is_complete(SEGMENT.at(seg=seg), i["key"])]
    done = 0
    for wave in sorted({i["wave"] for i in info.values()}):
        batch = [seg for seg in todo if info[seg]["wave"] == wave]

        def rendered(k: int, n: int, seg: str, before: int = done) -> None:
            """One count over every wave: a wave's k-th segment is the (earlier waves' + k)-th of the step."""
            if k or not before:
                advance(before + k, len(todo), "segments rendered", seg)

        fan_out(
            "generate_segments",
            batch,
            lambda seg: _generate_one(store, p.source, model, seg, info[seg]),
            ctx.execution.generate_workers,
            progress=rendered,
        )
        done += len(batch)
    for stale in set(store.children(SEGMENTS.path)) - set(info):
        store.remove(SEGMENT.at(seg=stale))
    store.mark_complete(SEGMENTS.path, ctx.key, order=stitched_order(plan.segments))
    return f"{len(todo)} rendered, {len(info) - len(todo)} cached"


STEP = Step("generate_segments", 2, ("plan",), params, run, "render every planned segment", group=SEGMENTS.path)
