"""`wonderverse report`: gather what a scene store holds into `SCENE_DIR/report.html`.

Works on a scene run to any step (or to none): every section shows what exists and says what does not.
Ground-truth metrics appear when the accepted attempts carry `gt/` (procedural world): the camera path's
ATE, per-attempt SfM ATE, and the depth/normal priors' errors; the splats' own metrics and training curves
come from `splats/` attributes; step times from each step group's `seconds` attribute (absent for steps
run by older versions, shown as not recorded). The Scene section shows the 3D result the outputs step
wrote beside the store: stills of `novel.mp4` and `flythrough.mp4` (which also play in the page) and
pictures of `mesh.ply` from the first camera of the video and from above and behind the camera path.
A scene of the user's own clips (video backend `files`) is described as what it is: a Clips table (each clip's
frames, size, where its K came from and the check's verdict) in place of the plan, and no rounds, moves,
planned paths or user's words. A scene without priors says so in one line, with how to add them.

`write_report(..., only_if_stale=True)` leaves a report alone when it was made from the same state
(`report_state`: a fingerprint of the store's metadata and the files beside it), so a cached re-run of a
complete scene does not redraw its plots.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from flows.inspect import clips as clip_rows
from flows.inspect import expected_keys, global_k, guide, priors, root_meta, run_config, scene_spec, step_statuses
from flows.report_cache import DrawingCache, metadata_files
from flows.scene_quality import gates_of, pose_quality, registration, splat_quality
from tasks import STEPS
from tasks.segments import accepted_attempt, attempt_ids, attempt_path, segment_ids, stitched
from tasks.wording import RunFacts, describe
from wonderverse import __version__
from wonderverse.config import scene_config
from wonderverse.report import (
    CLIP_VERDICTS,
    STATE_META,
    AttemptInfo,
    ClipInfo,
    FileEntry,
    Picture,
    ReportContent,
    ReportParams,
    SegmentInfo,
    StepTiming,
    VideoClip,
    render_html,
)
from wonderverse.schema import ATTEMPT, CHECK, OUTPUTS, PLAN, PRIORS_SEGMENT, SEGMENT, SFM, SPLATS
from wonderverse.schema.attrs import Bounds, OutputFrame, PruneRecord
from wonderverse.store import STORE_NAME, SceneStore, StoreError, check_writable

log = logging.getLogger("wonderverse.report")
REPORT_NAME = "report.html"
# A scene without depth or normal priors, in one line (what the splats trained on, and how to add priors).
NO_PRIORS_NOTE = (
    "no depth model was named, so the splats train on colours alone; add depth and normal priors with "
    "--depth-model PATH (a local Depth Anything V2 folder) or steps.priors.models in --config"
)
# The scene videos the outputs step writes, in the order the report shows them.
SCENE_VIDEOS = {"novel.mp4": "Novel views (off the training path)", "flythrough.mp4": "Fly-through"}
# Modules that decide what the report looks like: a report drawn by other code is redrawn.
_REPORT_CODE = (
    "flows/report.py",
    "flows/report_cache.py",
    "flows/inspect.py",
    "wonderverse/report.py",
    "wonderverse/plots.py",
    "wonderverse/mesh_view.py",
)

# Files other steps write beside the store (whatever exists is linked), with what they are.
KNOWN_FILES: dict[str, str] = {  # files no step describes (the outputs step lists its own files with what they hold)
    "preview.mp4": "the stitched video (wonderverse preview)",
    "contact_sheet.png": "frames of the stitched video (wonderverse preview)",
    "plots": "check plots (wonderverse preview)",
    "viewer.html": "the splats in the browser (wonderverse view)",
    STORE_NAME: "the scene store (zarr v3), source of truth for everything above",
}


# -- reading helpers -----------------------------------------------------------------------------


def _rows(store: SceneStore, path: str, idx: np.ndarray) -> np.ndarray:
    """Selected leading indices of an array (reads only their chunks)."""
    return np.asarray(store.open_array(path).oindex[idx])


def _shape(store: SceneStore, path: str) -> tuple[int, ...] | None:
    try:
        return tuple(store.open_array(path).shape)
    except Exception:
        return None


def _has_array(store: SceneStore, path: str) -> bool:
    return (store.path / path / "zarr.json").is_file()


def _check_params(store: SceneStore) -> Any:
    cfg = run_config(store)
    return cfg.steps.check.rules if cfg is not None else None


def _fault_words(faults: Any) -> str:
    """The injected fault in words ("" for a clean attempt)."""
    if not isinstance(faults, dict) or not faults.get("type"):
        return ""
    frames = faults.get("frames") or []
    where = f" at frame{'s' if len(frames) > 1 else ''} {', '.join(str(f) for f in frames)}" if frames else ""
    return f"{faults['type']}{where}"


def _aligned_to_gt(est: np.ndarray, gt: np.ndarray) -> np.ndarray | None:
    """`est` W2C poses moved into the ground-truth world (Sim3 of camera centres), None when impossible."""
    from wonderverse.camera import camera_centers, umeyama

    ok = np.isfinite(est).all(axis=(1, 2)) & np.isfinite(gt).all(axis=(1, 2))
    if ok.sum() < 3:
        return None
    try:
        sim = umeyama(camera_centers(est[ok]), camera_centers(gt[ok]), allow_degenerate=True)
    except ValueError:
        return None
    return sim.transform_w2c(est)


def _topview(est: np.ndarray, gt: np.ndarray | None, label: str, title: str) -> bytes:
    """Top view of an SfM path; with ground truth, both in the GT world (+z up, seen from above)."""
    from wonderverse.plots import trajectory_topview_plot

    aligned = None if gt is None else _aligned_to_gt(est, gt)
    if aligned is None:
        return trajectory_topview_plot([est], [label], title)
    return trajectory_topview_plot([gt, aligned], ["ground truth", f"{label} (Sim3-aligned)"], title, plane="xy")


def _ate_percent(est: np.ndarray, gt: np.ndarray) -> float | None:
    from wonderverse.metrics import ate

    try:
        return 100.0 * ate(est, gt)["rmse_frac"]
    except ValueError:
        return None


# -- sections ------------------------------------------------------------------------------------


def _attempt(store: SceneStore, seg: str, k: int, chosen: int | None, params: Any, cache: DrawingCache) -> AttemptInfo:
    from flows.preview import check_result
    from wonderverse.plots import segment_check_plot

    ap = ATTEMPT.at(seg=seg, attempt=k)
    attempt = store.meta(ap, complete=False)
    info = AttemptInfo(index=k, seed=attempt.seed if attempt is not None else None, chosen=k == chosen)
    truth = store.meta(ap.gt, complete=False)
    has_gt = truth is not None
    if truth is not None:
        info.fault = _fault_words(truth.faults)
    _guide(store, seg, k, info)
    check = store.meta(ap.check)
    if check is None:
        return info
    info.accepted = check.accepted
    info.reasons = list(check.reasons)
    info.notes = list(check.notes)
    info.flagged_frames = list(check.flagged_frames)
    info.registered_frac = check.registered_frac
    info.sfm_seconds = check.sfm_seconds
    title = f"{seg} attempt {k}"
    info.check_plot = cache.png(
        cache.key(f"check plot {title} {params.model_dump_json() if params is not None else ''}", ap),
        lambda: segment_check_plot(check_result(check), params, title),
    )
    if _has_array(store, ap.sfm.poses):
        est = store.array(ap.sfm.poses)
        gt = store.array(ap.gt.poses) if has_gt and _has_array(store, ap.gt.poses) else None
        info.topview = cache.png(
            cache.key(f"top view {title}", ap),
            lambda: _topview(est, gt, "SfM", f"{title}: camera path from above"),
        )
        if gt is not None:
            info.metrics["SfM ATE (% of path)"] = _ate_percent(est, gt)
    return info


def _guide(store: SceneStore, seg: str, k: int, info: AttemptInfo) -> None:
    """Into `info`: the guide attempt `k` was generated from (in words, and its share of known pixels) and its
    errors against the ground truth when the procedural backend measured them (attempts table columns)."""
    g = guide(store, seg, k)
    if g is None:
        return
    if g.source is None or g.coverage is None:
        info.guide = f"none: {g.reason or 'no reason recorded'}"
        return
    info.guide = f"{100 * g.coverage:.0f} % of pixels known, from {g.source}"
    info.guide_coverage = g.coverage
    if g.truth is not None:
        info.metrics["guide PSNR vs GT (dB)"] = g.truth.psnr_db
        info.metrics["guide depth AbsRel vs GT"] = g.truth.depth_absrel


def _status(store: SceneStore, seg: str, n_attempts: int) -> tuple[str, bool | None]:
    acc = store.meta(SEGMENT.at(seg=seg).accepted)
    if acc is not None:
        if acc.dropped:
            return f"dropped after {acc.attempts or n_attempts} attempts", False
        if acc.reasons:
            return f"kept failing attempt {acc.attempt} (best of {acc.attempts or n_attempts})", False
        return f"attempt {acc.attempt} accepted", True
    if n_attempts:
        return "not checked yet", None
    return "not generated yet", None


def _previews(store: SceneStore, seg: str, p: ReportParams, cache: DrawingCache) -> list[Picture]:
    """Depth/normal priors of a few frames beside the frame (and the ground truth when there is one)."""
    from wonderverse.report import depth_normal_preview

    if store.cache_key_of(PRIORS_SEGMENT.at(seg=seg)) is None or accepted_attempt(store, seg) is None:
        return []
    ap = attempt_path(store, seg)
    shape = _shape(store, PRIORS_SEGMENT.at(seg=seg).depth)
    if shape is None or not _has_array(store, PRIORS_SEGMENT.at(seg=seg).normals):
        return []
    idx = np.unique(np.linspace(0, shape[0] - 1, p.preview_frames).round().astype(int))
    gt = store.exists(ap.gt) and _has_array(store, ap.gt.depth) and _has_array(store, ap.gt.normals)
    png = cache.png(
        cache.key(f"priors preview {seg}", ap, PRIORS_SEGMENT.at(seg=seg)),
        lambda: depth_normal_preview(
            _rows(store, ap.frames, idx),
            _rows(store, PRIORS_SEGMENT.at(seg=seg).depth, idx),
            _rows(store, PRIORS_SEGMENT.at(seg=seg).normals, idx).astype(np.float32),
            [f"frame {i}" for i in idx],
            gt_depth=_rows(store, ap.gt.depth, idx) if gt else None,
            gt_normals=_rows(store, ap.gt.normals, idx).astype(np.float32) if gt else None,
            thumb_width_px=p.preview_thumb_width_px,
        ),
    )
    kind = store.meta(PRIORS_SEGMENT.at(seg=seg)).kind  # complete: its cache key was checked above
    words = f" (the network predicts {kind.replace('_', ' ')})" if kind else ""
    return [Picture(png, f"{seg}: depth (turbo, near = warm, sky grey) and normal priors{words}")]


def _global_gt(store: SceneStore) -> tuple[np.ndarray, np.ndarray] | None:
    """(global SfM poses, ground-truth poses of the same stitched frames), when every frame has GT."""
    sfm = store.meta(SFM.path)
    if sfm is None:
        return None
    segs = sfm.segments
    index = store.array(SFM.frame_index)
    gts: dict[str, np.ndarray] = {}
    for seg in segs:
        k = accepted_attempt(store, seg)
        if k is None or not _has_array(store, ATTEMPT.at(seg=seg, attempt=k).gt.poses):
            return None
        gts[seg] = store.array(ATTEMPT.at(seg=seg, attempt=k).gt.poses)
    gt = np.stack([gts[segs[a]][i] for a, i in index]) if len(index) else np.zeros((0, 4, 4))
    return store.array(SFM.poses), gt


def _prior_errors(
    store: SceneStore, segments: list[SegmentInfo], sfm_to_gt_scale: float, cache: DrawingCache
) -> dict[str, Any]:
    """Depth and normal errors of every segment's priors against the ground truth; per-segment figures go
    into the segments' metrics, the pixel-weighted totals are returned. The priors are in SfM units, so
    the ground truth depth is scaled by the global Sim3 scale (GT metres -> SfM units) first (the scale moves
    as the world grows: the depth errors are measured again, the normal errors are kept)."""
    from wonderverse.metrics import depth_errors, normal_errors

    tot = {"d_n": 0, "absrel": 0.0, "delta1": 0.0, "sq": 0.0, "n_n": 0, "deg": 0.0, "good": 0.0}
    for info in segments:
        seg = info.id
        if store.cache_key_of(PRIORS_SEGMENT.at(seg=seg)) is None or accepted_attempt(store, seg) is None:
            continue
        ap = attempt_path(store, seg)
        if not (_has_array(store, ap.gt.depth) and _has_array(store, ap.gt.normals)):
            continue
        prior = store.array(PRIORS_SEGMENT.at(seg=seg).depth)
        d = depth_errors(prior, store.array(ap.gt.depth) * sfm_to_gt_scale, mask=np.isfinite(prior))
        n = cache.figures(
            cache.key(f"normal errors {seg}", ap, PRIORS_SEGMENT.at(seg=seg)),
            lambda s=seg, a=ap: normal_errors(store.array(PRIORS_SEGMENT.at(seg=s).normals), store.array(a.gt.normals)),
        )
        info.metrics |= {
            "depth prior AbsRel": d["absrel"],
            "depth prior δ1 (%)": 100 * d["delta1"] if d["n"] else None,
            "normal prior mean angle (°)": n["mean_deg"],
            "normal prior within 11.25° (%)": n["pct_11_25"],
        }
        if d["n"]:
            tot["d_n"] += d["n"]
            tot["absrel"] += d["absrel"] * d["n"]
            tot["delta1"] += d["delta1"] * d["n"]
            tot["sq"] += d["rmse"] ** 2 * d["n"]
        if n["n"]:
            tot["n_n"] += n["n"]
            tot["deg"] += n["mean_deg"] * n["n"]
            tot["good"] += n["pct_11_25"] * n["n"]
    out: dict[str, Any] = {}
    if tot["d_n"]:
        out["Depth priors vs ground truth (GT scaled to SfM units by the camera-path Sim3)"] = {
            "AbsRel": tot["absrel"] / tot["d_n"],
            "δ1 (%)": 100 * tot["delta1"] / tot["d_n"],
            "RMSE (SfM units)": float(np.sqrt(tot["sq"] / tot["d_n"])),
            "pixels": tot["d_n"],
        }
    if tot["n_n"]:
        out["Normal priors vs ground truth"] = {
            "mean angle (°)": tot["deg"] / tot["n_n"],
            "within 11.25° (%)": tot["good"] / tot["n_n"],
            "pixels": tot["n_n"],
        }
    return out


def _clip_infos(store: SceneStore) -> list[ClipInfo] | None:
    """The user's clips in order (video backend `files`), as `inspect` reads them; None for other scenes."""
    rows = clip_rows(store)
    if rows is None:
        return None
    out = []
    for r in rows:
        width, height = r.size or (None, None)
        out.append(
            ClipInfo(
                segment=r.segment,
                name=r.name,
                kind=r.kind,
                folder=str(Path(r.source).parent) if r.source else "",
                frames=r.frames,
                width=width,
                height=height,
                k_source=r.k_source,
                fov_deg=r.fov_deg,
                verdict=r.verdict,
                reasons=tuple(r.reasons),
                notes=tuple(_read_notes(store, r.segment)),
            )
        )
    return out


def _read_notes(store: SceneStore, seg: str) -> list[str]:
    """What reading a clip did to it, as its segment recorded (`SegmentAttrs.read_notes`; [] before it did)."""
    meta = store.meta(SEGMENT.at(seg=seg), complete=False)
    return list(meta.read_notes) if meta is not None else []


def _segments(
    store: SceneStore, p: ReportParams, cache: DrawingCache, clips: list[ClipInfo] | None = None
) -> list[SegmentInfo]:
    """Planned segments (from the plan, else from the store) with attempts, status and previews; for a scene
    of clips, each segment carries its clip (and no plan entry: nothing was planned)."""
    if clips is not None:
        return _clip_segments(store, p, cache, clips)
    params = _check_params(store)
    plan = store.meta(PLAN.path)
    planned = list(plan.plan.segments) if plan is not None else []
    moves = list(plan.moves) if plan is not None else []
    ids = [s.id for s in planned] + [s for s in segment_ids(store) if s not in {x.id for x in planned}]
    out = []
    for i, seg in enumerate(ids):
        entry = planned[i] if i < len(planned) else None
        # what the segment recorded when it was generated, else its plan entry (not generated yet)
        written = store.meta(SEGMENT.at(seg=seg), complete=False)
        role, intent, ref_seg, frame = "", "", None, None
        if written is not None:
            role, intent = written.role, written.intent
            ref_seg, frame = written.reference_segment, written.reference_frame
        elif entry is not None:
            role, intent, ref_seg = entry.role, entry.intent, entry.reference_segment
        if ref_seg:
            where = f"frame {frame}" if frame is not None else f"{entry.reference if entry else None} frame"
            ref = f"{ref_seg}, {where}"
        else:
            ref = ""
        ks = attempt_ids(store, seg)
        chosen = accepted_attempt(store, seg) if ks else None
        status, ok = _status(store, seg, len(ks))
        info = SegmentInfo(
            id=seg,
            role=role,
            move=(written.move if written is not None else "") or (moves[i] if i < len(moves) else ""),
            intent=intent,
            reference=ref,
            status=status,
            status_ok=ok,
            attempts=[_attempt(store, seg, k, chosen, params, cache) for k in ks],
        )
        if chosen is not None and ks:
            shape = _shape(store, ATTEMPT.at(seg=seg, attempt=chosen).frames)
            info.frames = shape[0] if shape else None
        info.previews = _previews(store, seg, p, cache)
        out.append(info)
    return out


def _clip_segments(store: SceneStore, p: ReportParams, cache: DrawingCache, clips: list[ClipInfo]) -> list[SegmentInfo]:
    """One segment per clip, in the order given, with its attempts, verdict and previews."""
    params = _check_params(store)
    ok = {"accepted": True, "recovered": True, "kept_failing": False, "dropped": False}
    out = []
    for clip in clips:
        seg = clip.segment
        ks = attempt_ids(store, seg)
        chosen = accepted_attempt(store, seg) if ks else None
        info = SegmentInfo(
            id=seg,
            status=CLIP_VERDICTS.get(clip.verdict, clip.verdict),
            status_ok=ok.get(clip.verdict),
            frames=clip.frames,
            attempts=[_attempt(store, seg, k, chosen, params, cache) for k in ks],
            clip=clip,
        )
        info.previews = _previews(store, seg, p, cache)
        out.append(info)
    return out


def _recovered_words(store: SceneStore, seg: str, clips: dict[str, str]) -> str:
    """A recovered clip with both figures: "fox/ (check 26 of 49 frames registered, global solve 49 of 49)"."""
    check, poses = registration(store, seg)
    if check is None or poses is None:
        return clips.get(seg, seg)
    figures = f"check {check[0]} of {check[1]} frames registered, global solve {poses[0]} of {poses[1]}"
    return f"{clips.get(seg, seg)} ({figures})"


def _growth(store: SceneStore) -> Picture | None:
    """The seconds of every run since the scene was made, stacked by step, when it has been extended (how each
    extension's cost grew with the world); None before."""
    from wonderverse.plots import growth_plot

    root = root_meta(store)
    runs = root.runs if root is not None else []
    if not any(r.extensions for r in runs):
        return None
    labels = [f"+{r.extensions}" if r.extensions else "made" for r in runs]
    png = growth_plot([r.seconds for r in runs], labels, "seconds of each run (+k: after the k-th extension), by step")
    return Picture(png, f"{len(runs)} runs: the scene as made, then every run after an extension, by step")


def _run_facts(store: SceneStore, clips: bool) -> RunFacts:
    """What the steps' wording depends on (`tasks.wording`), read from the scene: its priors (unknown: as configured
    by default, with both) and the check's rule for a failing clip (from the stored config, else the one the
    segments were made under)."""
    pr = priors(store)
    cfg = run_config(store) or scene_config(store.scene_dir, "segments_config")
    depth, normals = pr.depth_backend, pr.normal_backend
    if not pr.computed and cfg is not None:  # a run that failed before the priors step: as it was configured
        depth, normals = cfg.steps.priors.models.depth_backend, cfg.steps.priors.models.normal_backend
    return RunFacts(
        clips=clips,
        depth=depth != "none",
        normals=normals != "none",
        on_failure=cfg.steps.check.on_failure if cfg is not None else "keep_best",
    )


def _timings(store: SceneStore, clips: bool = False) -> list[StepTiming]:
    status = {s.name: s.status for s in step_statuses(store)}
    facts = _run_facts(store, clips)
    out = []
    for s in STEPS:
        meta = store.meta(s.group)  # None unless complete (missing)
        seconds = meta.seconds if meta is not None else None
        out.append(StepTiming(s.name, status[s.name], seconds, describe(s.name, s.description, facts)))
    return out


def _files(store: SceneStore) -> list[FileEntry]:
    """Files and folders beside the store: the known ones, and those steps list in their attributes."""
    root = store.scene_dir.resolve()
    wanted: dict[str, str] = {}
    outputs = store.meta(OUTPUTS.path)
    for f in outputs.files if outputs is not None else []:
        if f.path:
            wanted.setdefault(f.path, f.description or KNOWN_FILES.get(f.path, f"written by {OUTPUTS.path}"))
    for name, what in KNOWN_FILES.items():
        wanted.setdefault(name, what)
    out = []
    for name, what in wanted.items():
        path = (root / name).resolve()
        if not path.is_relative_to(root) or path == root or not path.exists() or name == REPORT_NAME:
            continue
        size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else path.stat().st_size
        out.append(FileEntry(path.relative_to(root).as_posix(), size, path.is_dir(), what))
    # Exports first, the store last (it is the biggest and least looked at).
    return sorted(out, key=lambda f: (f.path == STORE_NAME, f.is_dir, f.path))


def _stitched_pictures(store: SceneStore, p: ReportParams) -> tuple[Picture | None, Picture | None]:
    """Contact sheet of the stitched video, and the global camera path from above."""
    from wonderverse.media import contact_sheet

    frames, index = stitched(store)
    overview = None
    if len(frames):
        pick = np.unique(np.linspace(0, len(frames) - 1, min(p.overview_frames, len(frames))).round().astype(int))
        png = contact_sheet(frames[pick], [f"{index[i][0]}:{index[i][1]}" for i in pick])
        overview = Picture(png, f"{len(frames)} stitched frames, {len(pick)} shown (segment:frame)")
    trajectory = None
    pair = _global_gt(store)
    sfm = store.meta(SFM.path)
    if sfm is not None:
        est = store.array(SFM.poses)
        gt = pair[1] if pair is not None else None
        src = sfm.source
        png = _topview(est, gt, f"global ({src})", "stitched video: global camera path from above")
        trajectory = Picture(png, "global camera path (square = first frame, arrows = viewing direction)")
    return overview, trajectory


def _video_clips(store: SceneStore, p: ReportParams) -> tuple[list[VideoClip], list[str]]:
    """The scene videos beside the store (with stills of a few frames), and a line for each one missing."""
    from wonderverse.media import contact_sheet
    from wonderverse.report import video_stills

    clips, notes, missing = [], [], []
    for name, title in SCENE_VIDEOS.items():
        path = store.scene_dir / name
        if not path.is_file():
            missing.append(name)
            continue
        try:
            frames, idx, n, seconds = video_stills(path, p.scene_stills)
        except (OSError, RuntimeError, ValueError) as e:
            notes.append(f"{name} could not be read: {_one_line(e)}")
            continue
        h, w = frames.shape[1:3]
        sheet = contact_sheet(frames, [f"frame {i}" for i in idx], cols=len(frames), thumb_width=p.still_width_px)
        still = Picture(sheet, f"{name}: {len(idx)} of its {n} frames, evenly spaced")
        clips.append(VideoClip(name, title, w, h, n, seconds, still))
    if missing:
        verb = "is" if len(missing) == 1 else "are"
        notes.insert(0, f"No renders of the splats yet: {' and '.join(missing)} {verb} written by the outputs step.")
    return clips, notes


def _one_line(e: BaseException) -> str:
    """An error in one short line (ffmpeg's messages run over many)."""
    lines = [line.strip() for line in str(e).splitlines() if line.strip()]
    return (lines[0][:200] if lines else "") or type(e).__name__


def _first_camera(store: SceneStore) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int] | None:
    """(W2C of the first posed frame, every finite W2C, K, width, height) of the global poses, or None."""
    sfm = store.meta(SFM.path)
    if sfm is None or not _has_array(store, SFM.K):
        return None
    poses = store.array(SFM.poses)
    finite = np.isfinite(poses).all(axis=(1, 2))
    if not finite.any():
        return None
    first = int(np.flatnonzero(finite)[0])
    seg_index, _ = store.array(SFM.frame_index)[first]
    seg = sfm.segments[int(seg_index)]
    shape = _shape(store, attempt_path(store, seg).frames) if accepted_attempt(store, seg) is not None else None
    if shape is None:
        return None
    try:  # mesh.ply is in the outputs' gravity-aligned frame: the cameras go there too
        from tasks.outputs import output_frame

        poses = output_frame(store).transform_w2c(poses)
    except KeyError:  # a scene whose outputs predate the frame: its files are in the sfm/ frame
        pass
    return poses[first], poses[finite], np.asarray(store.array(SFM.K), np.float64), shape[2], shape[1]


def _mesh_views(store: SceneStore, p: ReportParams) -> tuple[list[Picture], list[str]]:
    """`mesh.ply` from the first camera of the video and from above and behind the camera path."""
    path = store.scene_dir / "mesh.ply"
    if not path.is_file():
        return [], ["No mesh yet: mesh.ply is written by the outputs step."]
    cam = _first_camera(store)
    if cam is None:
        return [], ["mesh.ply is not shown: the store holds no camera poses (sfm/) to view it from."]
    import open3d as o3d
    from PIL import Image, ImageDraw

    from wonderverse.camera import camera_centers
    from wonderverse.mesh_view import MeshViewParams, overview_camera, render_mesh_views
    from wonderverse.report import png_bytes

    mesh = o3d.io.read_triangle_mesh(str(path))
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    if not len(F):
        return [], ["mesh.ply holds no triangle."]
    C = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
    first, poses, K, width, height = cam
    scale = p.mesh_view_width_px / width
    w, h = p.mesh_view_width_px, max(1, round(height * scale))
    Ks = K.copy()
    Ks[0] *= w / width
    Ks[1] *= h / height
    mp = MeshViewParams(supersample=p.mesh_supersample)
    over_pose = overview_camera(V, poses, Ks, w, h, mp)
    front, over_rgb = render_mesh_views(V, F, C, Ks, np.stack([first, over_pose]), w, h, mp)
    over = Image.fromarray(over_rgb)
    # the camera path drawn on top (not hidden behind the mesh), its first camera as a dot
    centres = camera_centers(poses)
    cam_pts = centres @ over_pose[:3, :3].T + over_pose[:3, 3]
    if (cam_pts[:, 2] > 0).all():
        uv = (cam_pts @ Ks.T)[:, :2] / cam_pts[:, 2:]
        draw = ImageDraw.Draw(over)
        draw.line([tuple(q) for q in uv], fill=(214, 39, 40), width=2)
        x, y = uv[0]
        draw.ellipse((x - 4, y - 4, x + 4, y + 4), fill=(214, 39, 40))
    front_caption = f"mesh.ply ({len(F):,} triangles) from the first camera of the video, shaded by facing"
    over_caption = "mesh.ply from above and behind the camera path (red; the dot is the first camera)"
    return [Picture(png_bytes(front), front_caption), Picture(png_bytes(np.asarray(over)), over_caption)], []


def _scene(store: SceneStore, p: ReportParams) -> tuple[list[VideoClip], list[Picture], list[str]]:
    clips, notes = _video_clips(store, p)
    views, mesh_notes = _mesh_views(store, p)
    notes += mesh_notes
    if (clips or views) and store.cache_key_of(OUTPUTS.path) is None:
        notes.append("The outputs step has not completed: the videos and the mesh may be from an earlier run.")
    return clips, views, notes


def _planned_paths(store: SceneStore, segments: list[SegmentInfo]) -> Picture | None:
    from wonderverse.plots import trajectory_topview_plot

    with_path = [s for s in segments if s.clip is None and _has_array(store, SEGMENT.at(seg=s.id).path)]
    if not with_path:
        return None
    png = trajectory_topview_plot(
        [store.array(SEGMENT.at(seg=s.id).path) for s in with_path],
        [f"{s.id} ({s.role})" for s in with_path],
        "planned camera paths from above (world +z up)",
        plane="xy",
    )
    return Picture(png, "the camera path each segment was conditioned on")


def _metrics(
    store: SceneStore, segments: list[SegmentInfo], cache: DrawingCache
) -> tuple[dict[str, dict[str, Any]], dict[str, Any]]:
    """Metric groups, and headline figures for the summary."""
    metrics: dict[str, dict[str, Any]] = {}
    headline: dict[str, Any] = {}
    check = store.meta(CHECK.path)
    clips = {s.id: s.clip.label for s in segments if s.clip is not None}
    if check is not None and clips:  # a clip cannot be regenerated: no extra trials to count
        verdicts = {s.id: s.clip.verdict for s in segments if s.clip is not None}
        recovered = [s for s in check.kept_failing if verdicts.get(s) == "recovered"]
        metrics["Geometric correction"] = {
            "dropped clips": ", ".join(clips.get(s, s) for s in check.dropped) or "none",
            "kept although failing": ", ".join(clips.get(s, s) for s in check.kept_failing if s not in recovered)
            or "none",
            "recovered by the global solve": ", ".join(_recovered_words(store, s, clips) for s in recovered) or "none",
        }
    elif check is not None:
        metrics["Geometric correction"] = {
            "mean extra trials per segment": check.mean_extra_trials,
            "dropped segments": ", ".join(check.dropped) or "none",
            "kept failing": ", ".join(check.kept_failing) or "none",
        }
    guided = _guided_extensions(segments)
    if guided:
        metrics["Guided extensions"] = guided
    sfm = store.meta(SFM.path)
    if sfm is not None:
        poses = store.array(SFM.poses)
        points = _shape(store, SFM.points3d)
        metrics["Global camera path"] = {
            "source": sfm.source,
            "mapper": sfm.mapper,
            "frames posed": f"{int(np.isfinite(poses[:, 0, 0]).sum())} of {len(poses)}",
            "frames used by SfM": sfm.frames_used,
            "reprojection error (px)": sfm.reproj_error_px,
            "3D points": points[0] if points else None,
        }
        k = global_k(store)
        if k is not None:
            fov = f", {k.fov_deg:.1f}° horizontal field of view" if k.fov_deg is not None else ""
            why = f": {k.reason}" if k.reason else ""
            metrics["Global camera path"]["intrinsics (K) every output uses"] = f"{k.k_source}{fov}{why}"
        q = pose_quality(store, gates_of(run_config(store)))
        if q is not None and q.passed is not None:
            metrics["Global camera path"]["quality gates"] = (
                "passed" if q.passed else "FAILED: " + "; ".join(q.problems)
            )
            if not q.passed:
                headline["camera poses"] = "fail the quality gates: " + "; ".join(q.problems)
    pair = _global_gt(store)
    if pair is not None:
        from wonderverse.camera import camera_centers, umeyama
        from wonderverse.metrics import ate

        est, gt = pair
        try:
            e = ate(est, gt)
        except ValueError as err:
            log.info("no camera-path ATE: %s", err)
        else:
            metrics["Camera path vs ground truth (Sim3-aligned ATE)"] = {
                "RMSE (GT metres)": e["rmse"],
                "RMSE / path length (%)": 100 * e["rmse_frac"],
                "frames": e["n"],
            }
            headline["camera path ATE"] = f"{100 * e['rmse_frac']:.2f} % of the path length"
            ok = np.isfinite(est).all(axis=(1, 2)) & np.isfinite(gt).all(axis=(1, 2))
            scale = umeyama(camera_centers(gt[ok]), camera_centers(est[ok]), allow_degenerate=True).s
            metrics |= _prior_errors(store, segments, scale, cache)
    splats = store.meta(SPLATS.path)
    if splats is not None:
        m = splats.metrics
        metrics["Gaussian splats"] = {
            "held-out PSNR (dB)": m.test_psnr,
            "held-out SSIM": m.test_ssim,
            "training PSNR (dB)": m.train_psnr,
            "training SSIM": m.train_ssim,
            "Gaussians": m.n_gaussians,
            "views (training / held out)": f"{len(m.train_views)} / {len(m.test_views)}",
            "training time (s)": m.seconds,
            "skipped steps (non-finite)": m.skipped_steps,
        }
        sq = splat_quality(store)
        if sq is not None and sq.psnr_db is not None:  # held-out only where views were held out
            headline[f"{sq.psnr_label} PSNR"] = f"{sq.psnr_db:.2f} dB"
    outputs = store.meta(OUTPUTS.path)
    if outputs is not None and "quality" in outputs.model_fields_set:  # older outputs scored nothing
        q = outputs.quality
        metrics["Novel views, no reference"] = {
            "NIQE (lower is better)": q.niqe,
            "CLIP-S (0..2.5)": q.clip_s,
            "Q-Align": q.q_align,
        }
    if outputs is not None and outputs.pruned is not None:
        metrics["Exported splats"] = _export_facts(outputs.pruned, outputs.frame)
    return metrics, headline


def _guided_extensions(segments: list[SegmentInfo]) -> dict[str, Any]:
    """Over the extensions of a guided flow (the attempt each follows: the accepted one, else the last): how many
    were generated from a guide, and the mean share of their guides' pixels that were known. Empty when none
    looked for a guide."""
    shown = []
    for s in segments:
        chosen = next((a for a in s.attempts if a.chosen), s.attempts[-1] if s.attempts else None)
        if chosen is not None and chosen.guide is not None:
            shown.append(chosen.guide_coverage)
    if not shown:
        return {}
    known = [c for c in shown if c is not None]
    return {
        "generated from a guide": f"{len(known)} of {len(shown)}",
        "known pixels of their guides (mean)": f"{100 * np.mean(known):.0f} %" if known else None,
    }


def _export_facts(pruned: PruneRecord, frame: OutputFrame) -> dict[str, Any]:
    """What `prune_for_export` removed (and how many needles it shortened) before splats.ply/.spz/.glb were
    written, their bounds, and the frame."""

    def box(bounds: Bounds | None) -> str | None:
        if bounds is None:
            return None
        lo, hi = np.asarray(bounds.min, float), np.asarray(bounds.max, float)
        size = " × ".join(f"{v:.3g}" for v in hi - lo)
        return f"{size} (from {np.round(lo, 3).tolist()} to {np.round(hi, 3).tolist()})"

    facts = {
        "Gaussians exported": f"{pruned.after} of {pruned.before}",
        "removed": ", ".join(f"{n} {why.replace('_', ' ')}" for why, n in pruned.removed.items() if n) or "none",
        "needles shortened": str(pruned.needles_shortened),
        "bounds before (world units)": box(pruned.bounds_before),
        "bounds exported (world units)": box(pruned.bounds_after),
    }
    if frame.source:
        facts["world frame: +Z up from"] = frame.source
    return facts


def _clip_count(clips: list[ClipInfo]) -> str:
    """How many clips, in words ("3 clips", "1 clip")."""
    return f"{len(clips)} clip{'s' * (len(clips) != 1)}"


def _facts(store: SceneStore, clips: list[ClipInfo] | None = None) -> dict[str, Any]:
    from wonderverse.video.files import ClipParams

    root, spec, cfg = root_meta(store), scene_spec(store), run_config(store)
    written = f"format {root.format}, written by WonderVerse {root.wonderverse_version}"
    facts: dict[str, Any] = {"scene folder": str(store.scene_dir)}
    if cfg is not None and cfg.preset:
        facts["preset"] = cfg.preset
    if clips is not None:  # nothing generated or planned: no seed, rounds or frame counts of a video model
        opts = spec.video.options if spec is not None else None
        most = opts.max_frames if isinstance(opts, ClipParams) else None
        side = opts.max_side_px if isinstance(opts, ClipParams) else None
        facts["scene"] = f"reconstruction of {_clip_count(clips)}, one segment each, in the order given (backend files)"
        facts["clips read"] = (
            f"{'every frame' if most is None else f'at most {most} frames'} per clip, evenly spread; "
            f"{'full size' if side is None else f'longer side at most {side} px'}"
        )
        facts["store"] = written
        return facts
    if spec is not None:
        video, ext = spec.video, spec.extensions
        facts["seed"] = spec.seed
        facts["video"] = (
            f"{video.backend} backend, {video.width}×{video.height} px, "
            f"{video.frames_per_segment} frames per segment at {video.fps} fps, {video.fov_deg}° field of view"
        )
        facts["extensions"] = f"{ext.rounds} round(s) towards {', '.join(ext.directions)}" if ext.rounds else "none"
    facts["store"] = written
    return facts


def _priors_note(store: SceneStore) -> str:
    """One line when the scene has no depth or normal prior (by its priors step, or, before that step ran,
    by its stored configuration); "" when it has priors."""
    pr = priors(store)
    return NO_PRIORS_NOTE if (pr.depth_backend, pr.normal_backend) == ("none", "none") else ""


def failure_note(store: SceneStore) -> str:
    """Where and why the scene's last run stopped, what it completed first and what it did not reach, in words; ""
    when its last run did not fail (`RootAttrs.failed_run`)."""
    f = root_meta(store).failed_run
    if f is None:
        return ""
    needed = list(f.keys) or [s.name for s in STEPS]
    done = ", ".join(f.completed) if f.completed else "no step"
    after = needed[needed.index(f.step) + 1 :] if f.step in needed else []
    later = f" It did not reach {', '.join(after)}." if after else ""
    when = f.finished.replace("T", " ").replace("+00:00", " UTC")
    return (
        f"The last run failed at step {f.step} ({when}): {f.error}. It completed {done} first (kept: a re-run "
        f"resumes from there).{later}"
    )


def gather(store: SceneStore, params: ReportParams | None = None, cache: DrawingCache | None = None) -> ReportContent:
    """Everything the report shows, read from the store (nothing is written); what is drawn per segment is read from
    `cache` (`flows.report_cache`) where it holds it, and drawn into it where not."""
    p = params or ReportParams()
    cache = cache or DrawingCache(store, _code_fingerprint(p))
    spec = scene_spec(store)
    plan = store.meta(PLAN.path)
    clips = _clip_infos(store)
    segments = _segments(store, p, cache, clips)
    overview, trajectory = _stitched_pictures(store, p)
    videos, mesh_views, scene_notes = _scene(store, p)
    metrics, headline = _metrics(store, segments, cache)
    timings = _timings(store, clips is not None)
    splats = store.meta(SPLATS.path)
    curves = {k: [float(x) for x in v] for k, v in (splats.curves if splats is not None else {}).items()}
    skipped = curves.pop("skipped", [])
    notes = []
    stale = [t.step for t in timings if t.status == "stale"]
    if stale:
        notes.append(
            f"Stale steps (made with other settings than the stored config, shown as they are): {', '.join(stale)}."
        )
    failure = failure_note(store)
    if failure:
        notes.insert(0, failure)
    elif not any(t.status == "complete" for t in timings):
        command = "reconstruct" if clips is not None else "generate"
        notes.append(f"Nothing has completed yet: run `wonderverse {command}` on this scene.")
    facts = _facts(store, clips) | headline
    if clips is not None:
        prompt = f"Reconstruction of {_clip_count(clips)}: {', '.join(c.label for c in clips)}"
    else:
        prompt = spec.prompt if spec is not None else ""
    return ReportContent(
        title=f"WonderVerse report — {store.scene_dir.name}",
        prompt=prompt,
        facts=facts,
        planner=plan.plan.planner if plan is not None and clips is None else "",
        plan_note=f"fallback: {plan.plan.fallback_reason}" if plan is not None and plan.plan.fallback_reason else "",
        segments=segments,
        overview=overview,
        trajectory=trajectory,
        videos=videos,
        mesh_views=mesh_views,
        scene_notes=scene_notes,
        planned_paths=_planned_paths(store, segments),
        timings=timings,
        growth=_growth(store),
        metrics=metrics,
        curves=curves,
        curves_note=f"{len(skipped)} iterations skipped (non-finite loss or gradients)." if skipped else "",
        files=_files(store),
        notes=notes,
        generated=f"written {datetime.now(UTC):%Y-%m-%d %H:%M} UTC by WonderVerse {__version__}",
        clips=clips,
        priors_note=_priors_note(store),
    )


def _code_fingerprint(p: ReportParams) -> str:
    """sha256 hex of what draws the report: WonderVerse's version, the report modules' source and `p`."""
    h = hashlib.sha256(f"{__version__}\0{p.model_dump_json()}".encode())
    code_root = Path(__file__).resolve().parents[1]
    for rel in _REPORT_CODE:
        with_code = code_root / rel
        h.update(f"\0{rel}\0".encode() + (with_code.read_bytes() if with_code.is_file() else b""))
    return h.hexdigest()


def report_state(store: SceneStore, params: ReportParams | None = None) -> str:
    """sha256 hex fingerprint of everything a report of this store is made from.

    Covers every group's attributes (cache keys and completeness of the steps, segments, attempts, checks,
    accepted pointers and priors; the spec and config; step times; metrics and curves) and every array's
    metadata, all as the bytes of the store's `zarr.json` files; the step keys the stored config expects
    now (they decide complete or stale); the scene folder's path and the name and size of each file
    beside the store; the report's parameters; and the code that draws the report (WonderVerse's version
    and the report modules' source). Cheap: metadata files only, no array and no plotting library
    (4 ms on a tiny scene; 0.09 s with 10 MB of training curves in the splats' attributes)."""

    p = params or ReportParams()
    h = hashlib.sha256()

    def add(label: str, data: bytes) -> None:
        h.update(f"{label}\0{len(data)}\0".encode())
        h.update(data)

    add("code", _code_fingerprint(p).encode())
    add("folder", str(store.scene_dir.resolve()).encode())  # the page names it
    add("expected keys", json.dumps(expected_keys(store), sort_keys=True).encode())
    for rel, raw in metadata_files(store.path):
        add(f"store:{rel}", raw)
    beside = []
    with os.scandir(store.scene_dir) as entries:
        for e in entries:
            if e.name.startswith(".") or e.name in (REPORT_NAME, STORE_NAME):
                continue  # the lock file, reports being written, this report, the store (above)
            # Name and size, as the Files table shows them (a file rewritten by a step changes the store too).
            beside.append((e.name, e.is_dir(), 0 if e.is_dir() else e.stat().st_size))
    add("beside", json.dumps(sorted(beside)).encode())
    return h.hexdigest()


def written_state(report: Path) -> str | None:
    """The store state a report file says it was made from (None: no report, or one without it)."""
    try:
        with open(report, "rb") as f:
            head = f.read(4096).decode("utf-8", errors="replace")
    except OSError:
        return None
    m = re.search(rf'<meta name="{STATE_META}" content="([0-9a-f]{{64}})">', head)
    return m.group(1) if m else None


def write_report(scene_dir: Path | str, params: ReportParams | None = None, *, only_if_stale: bool = False) -> Path:
    """Write `SCENE_DIR/report.html` (atomically: a half-written report never replaces a good one);
    returns its path. Raises StoreError when the folder holds no scene.

    With `only_if_stale`, an existing report made from the same state (`report_state`, recorded in the
    page) is returned as it is, unwritten: a cached re-run of a finished scene costs milliseconds, not the
    seconds its plots take to draw."""
    store = SceneStore.open(scene_dir)
    out = Path(scene_dir) / REPORT_NAME
    # The state is taken before the content is read: were the store to change meanwhile, the report
    # records the older state and the next call draws it again (never the other way round).
    state = report_state(store, params)
    if only_if_stale and written_state(out) == state:
        log.debug("report %s is up to date", out)
        return out
    check_writable(scene_dir, f"{REPORT_NAME} in {scene_dir}")  # before the seconds of drawing, not after
    cache = DrawingCache(store, _code_fingerprint(params or ReportParams()))
    content = gather(store, params, cache)
    content.state = state
    text = render_html(content, params)
    tmp = out.with_name(f".{REPORT_NAME}.{uuid.uuid4().hex}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, out)
    except OSError as e:  # a full disk: the old report (if any) stays as it was
        raise StoreError(f"cannot write {REPORT_NAME} in {scene_dir}: {e.strerror or e}") from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
    cache.save()
    return out
