"""Step `poses`: one camera path in one world frame for every frame of the stitched video.

`source: sfm` solves it with `wonderverse.global_poses.solve_global_poses` (one reconstruction over the
accepted frames, extended or re-solved and mapped into the previous world frame; see there);
`source: conditioning` uses the path the video backend was conditioned on (exact for the procedural world,
guidance for real video models).

The `sfm` group keeps the COLMAP workspace (`colmap_database`, `colmap_model/<file>`, image names from
`global_poses.image_names`) and, in its attrs, what it was made from (`segment_sources`, `workspace_key`), the
Sim(3) from the COLMAP model to the world frame (`model_to_world`), the solve (`solve`: incremental | full,
`incremental_problems`, `segment_disagreement`, `segment_turn_error_deg`, `solves`, `seed_offset`), where K came
from (`k_source`, `K`, `fov_deg`, `pixel_aspect`), whether it was held fixed and why, in words (`k_held`,
`k_reason`: the user's camera is held unless `refine_intrinsics`) and the SfM's own report.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from tasks.base import Step, StepContext
from tasks.progress import advance
from tasks.segments import (
    accepted_attempt,
    attempt_path,
    camera_prior,
    check_readings,
    segment_meta,
    stitched,
    stitched_order,
)
from wonderverse.config import PosesParams, RunConfig
from wonderverse.errors import WonderError
from wonderverse.schema import SEGMENT, SFM, SFM_MODEL
from wonderverse.store import SceneStore, cache_key, write_array

if TYPE_CHECKING:
    from wonderverse.global_poses import PreviousSolve
    from wonderverse.sfm import SfmWorkspace

UNIT = "SfM stages"


Params = PosesParams  # the step reads its own settings only


def params(cfg: RunConfig) -> PosesParams:
    return cfg.steps.poses


def _workspace_key(p: PosesParams, held: bool = False) -> str:
    """What must not change for a reconstruction to be extended rather than re-solved."""
    # 2: image names sort in stitched order (`image_names`); a held camera's workspace differs from a refined one's
    held_key = {"held_camera": True} if held else {}  # absent: refined, as before
    return cache_key("sfm_workspace", 2, {"sfm": p.sfm, "frame_stride": p.frame_stride} | held_key)


def image_names(store: SceneStore, keys: list[tuple[str, int]]) -> list[str]:
    """COLMAP image names of stitched frames (segment, generation-order index): `global_poses.image_names`
    with the segments' playback order and roles from the store."""
    from wonderverse.global_poses import image_names as names

    order = stitched_order(store)
    roles = {seg: segment_meta(store, seg) for seg in order}
    left = {seg for seg, a in roles.items() if a.role == "left"}
    return names(keys, order, left, {seg for seg, a in roles.items() if a.reversed})


def _sources(store: SceneStore, segs: list[str]) -> dict[str, dict[str, Any]]:
    """Per segment, what its frames are: the segment's cache key and its accepted attempt."""
    return {s: {"key": store.cache_key_of(SEGMENT.at(seg=s)), "attempt": accepted_attempt(store, s)} for s in segs}


def _previous(store: SceneStore) -> PreviousSolve | None:
    """The last complete SfM solve in the `sfm` group, or None (none, or poses from the conditioning)."""
    from wonderverse.camera import Sim3
    from wonderverse.global_poses import PreviousSolve

    prev = store.meta(SFM.path)
    if prev is None or prev.source != "sfm":
        return None
    segs, index = prev.segments, store.array(SFM.frame_index)
    keys = [(segs[a], int(i)) for a, i in index]
    registered = {key for key, r in zip(keys, store.array(SFM.registered), strict=True) if r}
    stored = store.exists(SFM.colmap_model)
    return PreviousSolve(
        poses=dict(zip(keys, store.array(SFM.poses), strict=True)),
        registered=registered,
        names=prev.sfm_names,
        sources=prev.segment_sources,
        workspace_key=prev.workspace_key,
        model_to_world=None if prev.model_to_world is None else Sim3.from_dict(prev.model_to_world),
        kept_frame=prev.kept_frame,
        load_workspace=(lambda: _load_workspace(store)) if stored else None,
    )


def _check_mapper(store: SceneStore, segs: list[str]) -> tuple[str, bool] | None:
    """For a video of one segment: the mapper its check's SfM kept and whether that model passed its gates
    (None: several segments, or the check mapped nothing). Only for a guessed K: where the check holds a known K
    the global solve refines it, or holds it with the global mapper first, and the mapper that suits one does not
    suit the other (RealEstate10K `0c11` with its FOV given: incremental first here ended 9.4 % of the path off
    refined and 6.3 % held, global first 0.37 % and 0.33 %)."""
    if len(segs) != 1:
        return None
    a = store.meta(attempt_path(store, segs[0]).sfm)
    return (a.mapper, not a.problems) if a is not None and a.mapper else None


def users_camera(store: SceneStore, segs: list[str]) -> bool:
    """Whether every segment is one of the user's clips (video backend `files`, recorded on its attempt) with the
    camera the user gave (`--fov-deg`, `--intrinsics`): a camera to hold, where a generated video's K is refined."""
    for seg in segs:
        attempt = store.meta(attempt_path(store, seg), complete=False)
        if attempt is None or attempt.source != "files" or not camera_prior(store, seg).given:
            return False
    return True


def k_reason(prior_source: str, users: bool, held: bool, source: str) -> str:
    """Why the outputs use the K they use, in words (the `k_reason` attribute; `inspect` and the report show it)."""
    if source == "conditioning":
        return "the K the video was generated with; poses from the conditioning path, no SfM"
    if held:
        return "the camera you gave (--fov-deg or --intrinsics), held fixed through the global solve"
    if users:
        return "refined by the global solve from the camera you gave, as --refine-intrinsics asks"
    if prior_source == "given":
        return "the generated video's K, refined by the global solve"
    return "no field of view given: self-calibrated by the global solve"


def _load_workspace(store: SceneStore) -> SfmWorkspace:
    from wonderverse.sfm import SfmWorkspace

    files = store.children(SFM.colmap_model)
    model = {f: store.array(SFM.colmap_model.array(f)).tobytes() for f in files}
    return SfmWorkspace(database=store.array(SFM.colmap_database).tobytes(), model=model)


def _write_workspace(g: Any, ws: SfmWorkspace) -> None:
    """The COLMAP database and model files as byte arrays (`colmap_database`, `colmap_model/<file>`)."""
    write_array(g, SFM.colmap_database, np.frombuffer(ws.database, np.uint8))
    model = g.create_group(SFM_MODEL.name)
    for name, data in ws.model.items():
        write_array(model, SFM.colmap_model.array(name), np.frombuffer(data, np.uint8))


def run(store: SceneStore, p: PosesParams, ctx: StepContext) -> str:
    from wonderverse.camera import CameraPrior
    from wonderverse.global_poses import select_frames, solve_global_poses
    from wonderverse.sfm import k_record

    frames, index = stitched(store)
    if len(frames) == 0:
        raise WonderError("no accepted frames to pose (every segment was dropped)")
    segs = sorted({s for s, _ in index})
    K = store.array(SEGMENT.at(seg=index[0][0]).K)
    guessed = not all(camera_prior(store, s).given for s in segs)  # a guess anywhere: self-calibrate
    prior = CameraPrior(K, "guessed" if guessed else "given")
    users = users_camera(store, segs)
    held = users and not p.refine_intrinsics and p.source == "sfm"
    n = len(frames)
    frame_index = np.array([(segs.index(s), i) for s, i in index], dtype=np.int32)
    points = np.zeros((0, 3))
    colors = np.zeros((0, 3), np.uint8)
    attrs: dict[str, Any] = {"source": p.source, "segments": segs}
    workspace: SfmWorkspace | None = None
    if p.source == "conditioning":
        paths = {s: store.array(SEGMENT.at(seg=s).path) for s in segs}
        poses = np.stack([paths[s][i] for s, i in index])
        registered = np.ones(n, bool)
        attrs |= k_record(None, prior)
    else:
        solved = solve_global_poses(
            frames,
            index,
            prior,
            p,
            names=image_names(store, [index[k] for k in select_frames(index, p.frame_stride)]),
            sources=_sources(store, segs),
            workspace_key=_workspace_key(p, held),
            **check_readings(store, segs),
            previous=_previous(store),
            progress=lambda done, total, note: advance(done, total, UNIT, note, eta=False),  # stages: no pace
            check_mapper=_check_mapper(store, segs) if guessed else None,
            hold_given=held,
        )
        poses, registered, points, colors = solved.poses, solved.registered, solved.points, solved.colors
        K, workspace = solved.K, solved.workspace
        attrs |= solved.attrs
    attrs |= {"k_held": held, "k_reason": k_reason(prior.source, users, held, p.source)}
    with store.staged(SFM.path, ctx.key, **attrs) as g:
        write_array(g, SFM.poses, poses)
        write_array(g, SFM.registered, registered)
        write_array(g, SFM.K, K)
        write_array(g, SFM.frame_index, frame_index)
        write_array(g, SFM.points3d, points.reshape(-1, 3))
        write_array(g, SFM.colors, colors.reshape(-1, 3))
        if workspace is not None:
            _write_workspace(g, workspace)
    posed = int(np.isfinite(poses[:, 0, 0]).sum())
    solve = store.meta(SFM.path).solve
    how = f", {solve} solve" if solve else ""
    return f"{posed}/{n} frames posed ({p.source}{how}), {len(points)} points"


# 2: the group keeps the COLMAP workspace (extensions register only their new frames); frames selected per segment
# 3: image names in stitched order; full solves checked against each segment's own SfM
# 4: the step contract
# 5: a guessed K is self-calibrated; k_source recorded; one segment: its check's mapper first
# 6: the user's camera (a clip's given field of view) held unless refine_intrinsics; k_held, k_reason recorded
# 7: a held camera is held after the global mapper (set back, bundle-adjusted), not from its start
STEP = Step("poses", 7, ("check",), params, run, "one camera path for the stitched video", group=SFM.path)
