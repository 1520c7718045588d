"""Segment geometry, for guided flows: a checked segment's accepted frames placed in the plan's world
(`segments/<seg>/geometry`), and the guide an extension is generated from.

When the video model takes guides, `generate_segments` runs each segment's check and then `place` in one
task per segment (`tasks.guided.check_and_place`, on Dask when there are workers), before the segments that
continue from it are generated. `place` reads the check's SfM of the accepted attempt, the depth model's raw output
for its frames (`tasks.raw_depth`: the priors step's `priors_raw/<seg>`, computed here when absent, under the
priors step's own key so that it is computed once), and maps both into the plan's world
(`wonderverse.segment_geometry`).
`parent_guide` renders an extension's guide from its parent's stored geometry.

Keys: a geometry is keyed by its segment's `accepted` key (the segment's key and the check's settings), the
accepted attempt, a digest of that attempt's frames and the depth settings (`depth_settings`), so an extension
keyed by its parent's geometry key is generated again whenever what its guide was made from changes.
"""

from __future__ import annotations

import hashlib
import logging
from typing import Any

import numpy as np

from tasks.raw_depth import ground_truth, raw_depth
from wonderverse.config import PriorsStepParams
from wonderverse.errors import WonderError
from wonderverse.guide import GuideParams
from wonderverse.priors.params import PriorsParams
from wonderverse.schema import ATTEMPT, SEGMENT
from wonderverse.schema.attrs import GeometryAttrs
from wonderverse.segment_geometry import GeometryParams
from wonderverse.store import SceneStore, cache_key, write_array
from wonderverse.video.base import Guide

VERSION = 1
log = logging.getLogger("wonderverse.generate_segments")
# Settings of the priors that only the normals read: held at their defaults in a geometry's key (and in the
# depth model it runs), so changing the normal prior never regenerates a guided extension.
NORMAL_FIELDS = ("normal_backend", "normal_model", "normal_output_axes", "normal_input_size_px", "from_depth")


def depth_settings(priors: PriorsStepParams) -> PriorsStepParams:
    """The priors' settings a segment's geometry reads: the depth model, its alignment and the sky rule (the
    normal settings at their defaults)."""
    defaults = PriorsParams()
    models = priors.models.model_copy(update={name: getattr(defaults, name) for name in NORMAL_FIELDS})
    return priors.model_copy(update={"models": models})


def frames_digest(frames: np.ndarray) -> str:
    """sha256 of an attempt's frames: what a geometry and the extensions guided by it were made from."""
    return hashlib.sha256(np.ascontiguousarray(frames).tobytes()).hexdigest()


def geometry_key(
    accepted_key: str, attempt: int, frames: np.ndarray, settings: PriorsStepParams, params: GeometryParams
) -> str:
    what = {"attempt": attempt, "depth": settings, "placement": params, "frames_sha256": frames_digest(frames)}
    return cache_key("segment_geometry", VERSION, what, [accepted_key])


def place(seg: str, scene_dir: str, settings: PriorsStepParams, params: GeometryParams) -> GeometryAttrs:
    """Place segment `seg`'s accepted attempt in the plan's world and store it (`segments/<seg>/geometry`),
    unless it is stored under the same key; returns its record. A segment the check dropped has no geometry
    (placed False, nothing stored); one whose SfM cannot be placed is stored with placed False and the reason.
    WonderError when the segment has not been checked, or the depth settings name no depth model."""
    store = SceneStore.open(scene_dir, mode="r+")
    at = SEGMENT.at(seg=seg)
    accepted, accepted_key = store.meta(at.accepted), store.cache_key_of(at.accepted)
    if accepted is None or accepted_key is None:
        raise WonderError(f"segment {seg} has not been checked; its geometry needs the check's SfM of its frames")
    if accepted.attempt is None:
        why = "; ".join(accepted.reasons) or "every attempt failed"
        return GeometryAttrs(placed=False, reason=f"the check dropped it ({why})")
    if settings.models.depth_backend == "none":
        raise WonderError(
            "guided extensions place each segment's frames by their depth: set steps.priors.models.depth_backend"
        )
    k = accepted.attempt
    frames = store.array(ATTEMPT.at(seg=seg, attempt=k).frames)
    key = geometry_key(accepted_key, k, frames, settings, params)
    if not store.is_complete(at.geometry, key):
        _place(store, seg, k, frames, key, settings, params)
    return store.meta(at.geometry)


def _place(
    store: SceneStore,
    seg: str,
    k: int,
    frames: np.ndarray,
    key: str,
    settings: PriorsStepParams,
    params: GeometryParams,
) -> None:
    """Attempt `k` of `seg` (its check's SfM and its raw depth) mapped into the plan's world and committed."""
    from wonderverse.segment_geometry import place_segment

    at, ap = SEGMENT.at(seg=seg), ATTEMPT.at(seg=seg, attempt=k)
    pred = raw_depth(store, seg, ap, settings.models, frames, ground_truth(store, ap))
    sfm = [store.array(a) for a in (ap.sfm.poses, ap.sfm.registered, ap.sfm.points, ap.sfm.K)]
    try:
        geo = place_segment(
            pred.depth, pred.kind, *sfm, store.array(at.path), settings.models.align, settings.sky_beyond_ref, params
        )
    except ValueError as e:  # SfM that cannot be placed: recorded, so the extensions say why
        with store.staged(at.geometry, key, placed=False, reason=str(e), attempt=k):
            pass
        return
    g_path = at.geometry
    with store.staged(
        g_path,
        key,
        placed=True,
        attempt=k,
        to_plan=geo.to_plan.to_dict(),
        fit_rms=geo.fit_rms,
        fit_rms_rel=geo.fit_rms_rel,
        registered_frames=int(geo.registered.sum()),
        aligned_frames=int(geo.aligned.sum()),
        reasons=geo.reasons[:20],
    ) as g:
        write_array(g, g_path.depth, geo.depth)
        write_array(g, g_path.poses, geo.poses)
        write_array(g, g_path.K, geo.K)
        write_array(g, g_path.registered, geo.registered)
        write_array(g, g_path.aligned, geo.aligned)


def parent_geometry_key(store: SceneStore, seg: str, parent: str) -> str:
    """The key of the geometry extension `seg` is guided by (its parent's); WonderError naming both when the
    parent has none: dropped by the check, or not checked and placed yet. (A parent whose SfM could not be placed
    has a geometry saying so: its extensions are generated without a guide, see `parent_guide`.)"""
    at = SEGMENT.at(seg=parent)
    accepted = store.meta(at.accepted)
    if accepted is not None and accepted.attempt is None:
        why = "; ".join(accepted.reasons) or "every attempt failed"
        raise WonderError(
            f"segment {seg}: its parent segment {parent} was dropped by the check ({why}), so there is no geometry "
            f"to guide it; keep {parent} with steps.check.on_failure keep_best, or allow more check.max_attempts"
        )
    key = store.cache_key_of(at.geometry)
    if key is None:
        raise WonderError(
            f"segment {seg}: its parent segment {parent} has no geometry yet (it is made once {parent} is checked, "
            "by generate_segments); run generate_segments"
        )
    return key


def parent_guide(
    store: SceneStore,
    seg: str,
    parent: str,
    reference_frame: int,
    path: np.ndarray,
    K_out: np.ndarray,
    width: int,
    height: int,
    params: GuideParams,
) -> tuple[Guide | None, dict[str, Any]]:
    """The guide of extension `seg`: its parent's stored geometry rendered along `path` (T,4,4 W2C, the plan's
    world) with K_out at width x height, the parent's `reference_frame` lifted last. Returns it with its record
    {source, coverage, geometry_key} (what the attempt stores). A parent whose SfM could not be placed gives no
    guide (None; the record says why, and a warning is logged): the extension is generated as an unguided one
    is. WonderError naming `seg` when the parent has no geometry at all (`parent_geometry_key`)."""
    from wonderverse.segment_geometry import guide_from_geometry

    key = parent_geometry_key(store, seg, parent)
    g_path = SEGMENT.at(seg=parent).geometry
    geometry = store.meta(g_path)
    if not geometry.placed or geometry.attempt is None:
        reason = f"its parent segment {parent} could not be placed in the plan's world: {geometry.reason}"
        log.warning("segment %s is generated without a guide: %s", seg, reason)
        return None, {"source": None, "coverage": 0.0, "geometry_key": key, "reason": reason}
    k = geometry.attempt
    try:
        guide = guide_from_geometry(
            store.array(ATTEMPT.at(seg=parent, attempt=k).frames),
            store.array(g_path.depth),
            store.array(g_path.poses),
            store.array(g_path.K),
            store.array(g_path.registered),
            reference_frame,
            path,
            K_out,
            width,
            height,
            params,
        )
    except (ValueError, WonderError) as e:
        raise WonderError(f"segment {seg}: no guide from its parent segment {parent}: {e}") from None
    return guide, {"source": f"segment {parent}, attempt {k}", "coverage": guide.coverage, "geometry_key": key}
