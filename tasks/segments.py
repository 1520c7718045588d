"""Reading segments back from the store: accepted attempts, reference frames, the stitched video."""

from __future__ import annotations

from collections.abc import Callable, Collection
from typing import Any

import numpy as np

from wonderverse.camera import CameraPrior
from wonderverse.schema import ATTEMPT, ATTEMPTS, SEGMENT, SEGMENTS, SFM, GroupPath
from wonderverse.schema.attrs import SegmentAttrs
from wonderverse.store import SceneStore


def segment_ids(store: SceneStore) -> list[str]:
    return store.children(SEGMENTS.path)


def attempt_ids(store: SceneStore, seg: str) -> list[int]:
    return sorted(int(a) for a in store.children(ATTEMPTS.at(seg=seg)) if a.isdigit())


def segment_meta(store: SceneStore, seg: str) -> SegmentAttrs:
    """A segment's attributes (role, move, reference, ...); the defaults for a segment not written yet."""
    return store.meta(SEGMENT.at(seg=seg), complete=False) or SegmentAttrs()


def stitched_order(store: SceneStore) -> list[str]:
    """Segment ids in playback order (the plan's, once generate_segments has recorded it; else generation order)."""
    meta = store.meta(SEGMENTS.path, complete=False)
    return (meta.order if meta is not None else []) or segment_ids(store)


def accepted_attempt(store: SceneStore, seg: str) -> int | None:
    """The attempt later steps follow: the check step's `accepted` pointer (None: segment dropped);
    before any check, attempt 0."""
    a = store.meta(SEGMENT.at(seg=seg).accepted)
    return 0 if a is None else a.attempt


def attempt_path(store: SceneStore, seg: str, attempt: int | None = None) -> GroupPath:
    """Group of an attempt (the accepted one by default; KeyError when the segment was dropped)."""
    k = accepted_attempt(store, seg) if attempt is None else attempt
    if k is None:
        raise KeyError(f"segment {seg} was dropped by the check")
    return ATTEMPT.at(seg=seg, attempt=k)


def frames(store: SceneStore, seg: str, attempt: int | None = None) -> np.ndarray:
    """(T,H,W,3) uint8 frames of an attempt (the accepted one by default), in generation order."""
    return store.array(attempt_path(store, seg, attempt).frames)


def pixels(store: SceneStore, segs: Collection[str]) -> int:
    """Pixels in the frames of the segments' accepted attempts (frames x height x width, together; from the arrays'
    metadata, nothing read): how much per-segment work there is. A dropped segment counts none."""
    total = 0
    for seg in segs:
        try:
            shape = store.open_array(attempt_path(store, seg).frames).shape
        except (KeyError, FileNotFoundError):
            continue
        total += int(np.prod(shape[:3]))
    return total


def camera_prior(store: SceneStore, seg: str) -> CameraPrior:
    """A segment's K (3,3) and where it came from: given (the renderer's, or a clip's given field of view) or
    guessed; stores written before the flag existed count as guessed."""
    source = "guessed" if segment_meta(store, seg).k_is_guess else "given"
    return CameraPrior(store.array(SEGMENT.at(seg=seg).K), source)


def stitched(store: SceneStore) -> tuple[np.ndarray, list[tuple[str, int]]]:
    """The stitched video: frames (N,H,W,3) and, per frame, (segment id, generation-order index).

    Left extensions play reversed; every generated extension's frame 0 repeats its reference frame and
    is dropped so the video never stalls at a seam (user clips keep all their frames). Segments the check
    dropped are left out."""
    out, index = [], []
    for seg in stitched_order(store):
        if accepted_attempt(store, seg) is None:
            continue
        attrs = segment_meta(store, seg)
        f = frames(store, seg)
        idx = np.arange(len(f))
        if attrs.repeats:
            idx = idx[1:]
        if attrs.reversed:
            idx = idx[::-1]
        out.append(f[idx])
        index += [(seg, int(i)) for i in idx]
    return np.concatenate(out) if out else np.zeros((0, 1, 1, 3), np.uint8), index


def posed_stitched(
    store: SceneStore, arrays: dict[str, Callable[[str], str]], only: Collection[str] | None = None
) -> tuple[dict[str, np.ndarray], np.ndarray, list[str]]:
    """The stitched frames with a global pose (`sfm/`), in stitched order: {name: per-frame rows stacked} for each
    `arrays[name](seg)` (the path of a (T, ...) array of the segment), W2C poses (N,4,4) and frame names
    (`s000_0007`: segment, generation-order index); with `only`, the frames of those names alone. Each segment's
    arrays are read once, and only for a segment with a frame wanted."""
    segs = store.meta(SFM.path).segments
    index, poses = store.array(SFM.frame_index), store.array(SFM.poses)
    read: dict[str, dict[str, np.ndarray]] = {}
    rows: dict[str, list[np.ndarray]] = {name: [] for name in arrays}
    names, kept = [], []
    for k, (a, i) in enumerate(index):
        seg, name = segs[a], f"{segs[a]}_{int(i):04d}"
        if not np.isfinite(poses[k]).all() or (only is not None and name not in only):
            continue
        if seg not in read:
            read[seg] = {key: store.array(path(seg)) for key, path in arrays.items()}
        for key in arrays:
            rows[key].append(read[seg][key][i])
        names.append(name)
        kept.append(k)
    return {key: np.stack(r) if r else np.zeros((0,)) for key, r in rows.items()}, poses[kept], names


def check_readings(store: SceneStore, segs: list[str]) -> dict[str, dict[str, Any]]:
    """What the checks read of each segment's path, for the global solve to be held to (`solve_global_poses`):
    `own`, its own SfM poses where the check passed on them (a segment kept although its check failed has no
    trustworthy path, nor one whose SfM path two-view geometry contradicted: the planar twin, which a global
    solve can settle in too), and `turns`, its planned path and the check's reading of its turn against it
    (`global_poses.segment_turn_error`) where the check judged its plan-following."""
    from wonderverse.global_poses import turn_angles

    own, turns = {}, {}
    for seg in segs:
        ap = attempt_path(store, seg)
        check = store.meta(ap.check)
        if check is None or not check.accepted:
            continue
        pf = check.plan_following or {}
        if store.exists(ap.sfm.poses) and pf.get("source", "sfm") == "sfm":
            own[seg] = store.array(ap.sfm.poses)
        if pf.get("ok") and pf.get("estimated") and pf.get("planned"):
            reading = turn_angles(pf["estimated"]) - turn_angles(pf["planned"])
            if np.isfinite(reading).all():
                turns[seg] = (store.array(SEGMENT.at(seg=seg).path), reading)
    return {"own": own, "turns": turns}
