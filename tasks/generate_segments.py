"""Step `generate_segments`: render every planned segment with the video backend.

Segments form a tree (each extension continues from a frame of an earlier one), so they are
generated in waves; segments of one wave run concurrently. Each segment is its own cached unit
(`segments/<seg>`, keyed by its plan entry, the video settings and its parent's key), so adding an
extension or re-running after a kill regenerates only what is missing.

Guided flows (a video model that takes guides, `source_takes_guide`): an extension is generated from what its
parent already shows, rendered along its planned path (`tasks.segment_geometry.parent_guide`), so its parent
must be checked and placed in the plan's world first. Each wave is then rendered, checked (regenerated until
accepted, `tasks.check.check_segment`, under the check step's own keys, so that step later finds it done) and
placed (`tasks.segment_geometry.place`), one task per segment on Dask when there are workers, before the next
wave; the left and right branches of a wave run side by side. An extension's key adds its parent's geometry
key (the parent's accepted attempt, its frames and the depth settings), so whatever changes its guide
regenerates it. Unguided flows keep their keys and do not check here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tasks.base import Step, StepContext
from tasks.parallel import fan_out, segment_pool
from tasks.plan import load_plan
from tasks.progress import advance, callback
from tasks.segment_geometry import depth_settings, parent_geometry_key, parent_guide
from tasks.segments import frames, stitched_frame_index
from wonderverse.camera import intrinsics, move_path
from wonderverse.config import CheckStepParams, Model, PriorsStepParams, RunConfig, VideoSource
from wonderverse.errors import WonderError
from wonderverse.guide import GuideParams
from wonderverse.schema import ATTEMPT, ATTEMPT_GT, SEGMENT, SEGMENTS, GroupPath
from wonderverse.segment_geometry import GeometryParams
from wonderverse.store import SceneStore, cache_key, write_array
from wonderverse.video import source_takes_guide

SEGMENT_VERSION = 2  # 2: keyed by the step's params model


class Params(Model):
    """What segments are rendered from: the video source, and the sideways travel per degree of a planned turn."""

    source: VideoSource
    strafe_m_per_deg: float


class GuidedParams(Params):
    """A guided flow's: also what each extension's guide is made from, since every segment is checked and placed
    here before its extensions are generated: the check's settings (which attempt is accepted, its SfM), the depth
    settings that place its frames (`tasks.segment_geometry.depth_settings`), how they are placed and how guides
    are rendered (`steps.generate_segments`)."""

    check: CheckStepParams
    depth: PriorsStepParams
    geometry: GeometryParams
    guide: GuideParams


def params(cfg: RunConfig) -> Params:
    base = Params(source=cfg.scene.video_source, strafe_m_per_deg=cfg.steps.plan.strafe_m_per_deg)
    if not source_takes_guide(cfg.scene.video_source):
        return base
    g = cfg.steps.generate_segments
    depth = depth_settings(cfg.steps.priors)
    return GuidedParams(**dict(base), check=cfg.steps.check, depth=depth, geometry=g.geometry, guide=g.guide)


def _base(p: Params) -> Params:
    """The settings every segment is rendered with (a guided flow's extras left out): what a segment is keyed by."""
    return Params(source=p.source, strafe_m_per_deg=p.strafe_m_per_deg)


def guided_key(p: GuidedParams, plan_entry: Any, parent_key: str, geometry_key: str) -> str:
    """An extension's key in a guided flow: its plan entry and render settings, its parent's key and the key of
    the parent's geometry its guide is rendered from."""
    entry = {"params": _base(p), "segment": plan_entry, "guide": p.guide}
    return cache_key("segment", SEGMENT_VERSION, entry, [parent_key, geometry_key])


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
        entry = {"params": _base(p), "segment": s}
        key = cache_key("segment", SEGMENT_VERSION, entry, [parent["key"]] if parent else [])
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


def render_attempt(
    store: SceneStore, source: VideoSource, model: Any, seg: str, attempt: int
) -> tuple[Any, int, dict[str, Any] | None]:
    """Render attempt `attempt` of a segment whose plan (path, reference) is already in the store: the video,
    its seed, and the record of its guide (None when unguided).

    The reference frame comes from the parent's accepted attempt; the seed is new for every attempt. A segment
    generated from a guide is regenerated from the same one (its parent's geometry, which must not have changed
    since: WonderError)."""
    at = SEGMENT.at(seg=seg)
    a = store.attrs(at)
    parent = a.get("reference_segment")
    ref = frames(store, parent)[a["reference_frame"]] if parent else None
    path = store.array(at.path)
    guide = record = None
    if parent and a.get("guide_geometry_key"):
        v = source.video
        K_out = intrinsics(v.width, v.height, v.fov_deg)
        params = GuideParams.model_validate(a.get("guide_params") or {})
        guide, record = parent_guide(store, seg, parent, a["reference_frame"], path, K_out, v.width, v.height, params)
        if record["geometry_key"] != a["guide_geometry_key"]:
            raise WonderError(
                f"segment {seg}: the geometry of its parent segment {parent} changed since {seg} was generated; "
                "run generate_segments to generate it again"
            )
    video, seed = _render(source, model, seg, attempt, a["role"], a.get("intent", ""), path, ref, guide)
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


def _json_numbers(record: dict[str, Any]) -> dict[str, Any]:
    """`record` with non-finite floats as None (store attributes are JSON)."""
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in record.items()}


def write_attempt(
    group: Any, at: GroupPath, video: Any, seed: int, source: str, guide: dict[str, Any] | None = None
) -> None:
    """Frames (and ground truth when the backend has it) of the attempt `at` into `group`, its staged copy;
    `guide`: the record of the guide it was generated from (guided extensions)."""
    group.attrs.update({"seed": seed, "source": source})
    if guide is not None:
        group.attrs["guide"] = _json_numbers(guide)
    write_array(group, at.frames, video.frames)
    if video.gt is not None:
        gt = group.create_group(ATTEMPT_GT.name)
        write_array(gt, at.gt.poses, video.gt.poses)
        write_array(gt, at.gt.depth, video.gt.depth)
        write_array(gt, at.gt.normals, video.gt.normals)
        gt.attrs["faults"] = video.gt.faults
        if video.gt.labels is not None:
            write_array(gt, at.gt.labels, video.gt.labels)
            gt.attrs["label_names"] = {str(k): v for k, v in video.gt.label_names.items()}
        if getattr(video.gt, "guide", None) is not None:
            gt.attrs["guide"] = _json_numbers(video.gt.guide)


def _generate_one(
    store: SceneStore,
    source: VideoSource,
    model: Any,
    seg: str,
    info: dict[str, Any],
    guide_params: GuideParams | None = None,
) -> None:
    """Render a segment's first attempt and commit the segment; `guide_params`: a guided flow's (an extension is
    then generated from its parent's geometry)."""
    s = info["plan"]
    ref = frames(store, info["parent"])[info["ref_idx"]] if info["ref_idx"] is not None else None
    v = source.video
    guide = record = None
    if guide_params is not None and info["parent"] is not None:
        K_out = intrinsics(v.width, v.height, v.fov_deg)
        guide, record = parent_guide(
            store, seg, info["parent"], info["ref_idx"], info["path"], K_out, v.width, v.height, guide_params
        )
    video, seed = _render(source, model, seg, 0, s.role, s.intent, info["path"], ref, guide)
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
    if record is not None:  # regenerations (the check's) render the same guide, from the same geometry
        seg_attrs["guide_geometry_key"] = record["geometry_key"]
        seg_attrs["guide_params"] = guide_params.model_dump(mode="json")
    at = SEGMENT.at(seg=seg)
    with store.staged(at, info["key"], **seg_attrs) as g:
        write_array(g, at.path, info["path"])
        write_array(g, at.K, K)
        first = ATTEMPT.at(seg=seg, attempt=0)
        write_attempt(g.create_group(first.relative_to(at)), first, video, seed, v.backend, record)


def _side_by_side(store: SceneStore, waves: list[list[str]]) -> bool:
    """Whether some wave has two segments never checked before (a new scene, new extensions): then the workers are
    started ahead, while the first wave renders. (A re-run, or a new extension alone in its wave, starts none.)"""
    return any(sum(not store.exists(SEGMENT.at(seg=seg).accepted) for seg in batch) >= 2 for batch in waves)


def _run_guided(store: SceneStore, p: GuidedParams, ctx: StepContext, model: Any, info: dict[str, Any]) -> str:
    """Wave by wave: render the wave's segments (an extension from its parent's guide), then check and place
    each of them (one task per segment, on Dask when there are workers), then the next wave.

    One cluster serves every wave (started ahead, while the first wave renders, when a wave will have segments
    to check side by side), and a segment's check is submitted to it as soon as the segment is rendered, so it
    runs while the wave's other segments render. Without workers the order is render all, then check each."""
    from tasks.check import THIS_RUN, is_checked
    from tasks.check import Params as CheckParams
    from tasks.segment_geometry import check_and_place

    if p.depth.models.depth_backend == "none":
        raise WonderError(
            "the video model takes guides, and an extension's guide is its parent's frames placed by their depth: "
            "set steps.priors.models.depth_backend (none names no depth model)"
        )
    check_p = CheckParams(check=p.check, source=p.source)
    scene_dir = str(store.scene_dir)
    waves = [[seg for seg, i in info.items() if i["wave"] == w] for w in sorted({i["wave"] for i in info.values()})]
    n, rendered, regenerated, dropped, unplaced = len(info), 0, 0, [], []
    workers = min(ctx.execution.segment_workers, max(len(batch) for batch in waves))
    with segment_pool(workers, ctx.execution.dask_address) as pool:
        if _side_by_side(store, waves):
            pool.start()
        for wave, batch in enumerate(waves):
            submitted: dict[str, Any] = {}

            def generate(seg: str, submitted: dict[str, Any] = submitted) -> bool:
                """Render `seg` unless it is complete under its key (an extension's needs its parent's geometry),
                then submit its check unless it is checked already. True when rendered."""
                i = info[seg]
                if i["parent"] is not None:
                    geometry = parent_geometry_key(store, seg, i["parent"])
                    i["key"] = guided_key(p, i["plan"], info[i["parent"]]["key"], geometry)
                fresh = not store.is_complete(SEGMENT.at(seg=seg), i["key"])
                if fresh:
                    _generate_one(store, p.source, model, seg, i, p.guide)
                if not is_checked(store, check_p, seg):
                    args = (seg, scene_dir, check_p, p.depth, p.geometry)
                    submitted[seg] = pool.submit(check_and_place, *args, only_if_started=True)
                return fresh

            try:
                progress = callback(f"segments of wave {wave + 1} generated")
                workers_g = ctx.execution.generate_workers
                rendered += sum(fan_out("generate_segments", batch, generate, workers_g, progress))
                # segments checked before (a re-run, an extension's older siblings) are placed here, in-process
                done = {
                    seg: check_and_place(seg, scene_dir, check_p, p.depth, p.geometry)
                    for seg in batch
                    if seg not in submitted
                }
                todo = [seg for seg in batch if seg in submitted]
                checked = callback(f"segments of wave {wave + 1} checked and placed")
                fresh = dict(zip(todo, pool.gather("check", todo, submitted, checked), strict=True))
            except Exception:
                pool.settle(submitted.values())  # what the workers are writing is finished before they stop
                raise
            out = [fresh[seg] if seg in fresh else done[seg] for seg in batch]
            regenerated += sum(r[THIS_RUN]["regenerated"] for r in out)
            dropped += [r["segment"] for r in out if r["dropped"]]
            unplaced += [r["segment"] for r in out if not r["dropped"] and not r["geometry"]["placed"]]
    msg = f"{rendered} rendered, {n - rendered} cached; checked and placed ({regenerated} regenerated"
    msg += f", dropped {', '.join(dropped)}" if dropped else ""
    msg += f", not placed {', '.join(unplaced)}" if unplaced else ""
    return msg + ")"


def _run_unguided(store: SceneStore, p: Params, ctx: StepContext, model: Any, info: dict[str, Any]) -> str:
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
    return f"{len(todo)} rendered, {len(info) - len(todo)} cached"


def replay_content(model: Any, source: VideoSource, segments: list[tuple[str, str, np.ndarray]]) -> None:
    """Give a fresh video model what every planned segment's words placed in its world ((role, intent, path) per
    segment), so a segment rendered now — a later `extend`, a regeneration in the check — sees the lake an earlier
    segment's words put there. Only backends that keep a world (the procedural one) have `place_content`."""
    place = getattr(model, "place_content", None)
    if place is None:
        return
    for role, intent, path in segments:
        if intent and np.isfinite(path).all():
            place(segment_prompt(source.prompt, role, intent), path)


def stored_words(store: SceneStore) -> list[tuple[str, str, np.ndarray]]:
    """(role, intent, path) of every stored segment whose user's words are not empty, for `replay_content`."""
    out = []
    for seg in store.children(SEGMENTS.path):
        a = store.attrs(SEGMENT.at(seg=seg))
        if a.get("intent") and store.exists(SEGMENT.at(seg=seg).path):
            out.append((a.get("role", ""), a["intent"], store.array(SEGMENT.at(seg=seg).path)))
    return out


def run(store: SceneStore, p: Params, ctx: StepContext) -> str:
    from wonderverse.planning import stitched_order
    from wonderverse.video import initial_pose, make_video_model

    plan = load_plan(store)
    model = make_video_model(p.source)
    clips = [len(c.frames) for c in model.clips] if p.source.video.backend == "files" else None  # type: ignore[attr-defined]
    info = plan_paths(p, plan, initial_pose(model), clips)
    replay_content(model, p.source, [(i["plan"].role, i["plan"].intent, i["path"]) for i in info.values()])
    if isinstance(p, GuidedParams):
        summary = _run_guided(store, p, ctx, model, info)
    else:
        summary = _run_unguided(store, p, ctx, model, info)
    for stale in set(store.children(SEGMENTS.path)) - set(info):
        store.remove(SEGMENT.at(seg=stale))
    store.mark_complete(SEGMENTS.path, ctx.key, order=stitched_order(plan.segments))
    return summary


STEP = Step("generate_segments", 2, ("plan",), params, run, "render every planned segment", group=SEGMENTS.path)
