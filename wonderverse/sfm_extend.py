"""Register new frames into an existing reconstruction instead of re-solving every frame.

An extension adds one segment to a scene. Re-running global SfM over every stitched frame would redo
feature extraction, matching and mapping of frames already solved, and give a new arbitrary world frame
that then has to be mapped back onto the old one. `extend_reconstruction` processes only the new frames:
SIFT on them into the scene's one camera, matching of the pairs that COLMAP's sequential matcher would
choose over the whole sequence and that involve a new frame, then incremental mapping that starts from
the kept model with the old frames' poses and the intrinsics held fixed. So the old frames keep their
poses exactly, and whatever was fitted in their frame (priors alignment, splats) stays valid.

Like `sfm.reconstruct`, it never raises on bad video content: new frames that do not register are NaN
and the reason is in `problems` (the caller then falls back to a full re-solve). Only invalid arguments
raise ValueError.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from wonderverse.features import sequential_pairs
from wonderverse.progress import ProgressFn, no_progress
from wonderverse.sfm import (
    STAGES,
    SfmParams,
    SfmResult,
    SfmWorkspace,
    _checked_names,
    _extract,
    _feature_problems,
    _incremental_options,
    _input_problems,
    _match,
    _result_from_model,
    _validate_frames,
    write_png_frames,
)

# Fixed frames may still come back moved by rounding (measured: 6e-15 SfM units); more than this share of
# the old cameras' extent means they were not held fixed, and the poses already used downstream are stale.
MAX_OLD_DRIFT_FRAC = 1e-9


def _extension_options(params: SfmParams) -> Any:
    """The relaxed incremental options, with existing frames and the camera held fixed and one model only
    (a new model for frames that do not connect would be in another, unrelated frame)."""
    opts = _incremental_options(params, hold_camera=True)
    opts.fix_existing_frames = True
    opts.multiple_models = False
    # Colours are taken from the new frames only (below); the old frames' files are not at hand.
    opts.extract_colors = False
    return opts


def _poses_by_name(rec: Any) -> dict[str, Any]:
    """name -> (frame id, rig_from_world) of every posed image of a pycolmap Reconstruction."""
    return {im.name: (im.frame_id, rec.frames[im.frame_id].rig_from_world) for im in rec.images.values() if im.has_pose}


def _restore_old_poses(rec: Any, old: dict[str, Any]) -> float:
    """Put the old frames' exact poses back into `rec`; returns how far (max centre shift, SfM units) the
    mapper had moved them."""
    drift = 0.0
    for im in rec.images.values():
        if im.name in old and im.has_pose:
            _, before = old[im.name]
            after = rec.frames[im.frame_id].rig_from_world
            drift = max(drift, float(np.linalg.norm(after.inverse().translation - before.inverse().translation)))
            rec.frames[im.frame_id].rig_from_world = before
    return drift


def _new_frame_problems(res: SfmResult, is_new: np.ndarray, params: SfmParams) -> list[str]:
    """The registration gate applied to the new frames alone (the old ones are registered by construction,
    so the gate over all frames would pass an extension that registered none of them)."""
    m, k = int(is_new.sum()), int((res.registered & is_new).sum())
    if k < max(1, int(np.ceil(params.min_registered_frac * m))):
        return [f"only {k} of {m} new frames registered"]
    return []


def extend_reconstruction(
    workspace: SfmWorkspace,
    order: Sequence[str],
    new_frames: Mapping[str, np.ndarray],
    params: SfmParams | None = None,
    workdir: Path | None = None,
    progress: ProgressFn | None = None,
) -> tuple[SfmResult, SfmWorkspace]:
    """Register new frames into the reconstruction held by `workspace`; returns (result, updated workspace).

    order: every image name in sequence (stitched) order, the workspace's and the new ones; pairs are chosen
    over it as the sequential matcher would (`params.matcher_overlap`, `quadratic_overlap`).
    new_frames: name -> (H,W,3) uint8 frame, for exactly the names of `order` not in the workspace; they must
    have the workspace camera's size (else a problem, not an error).
    params: the same SfmParams as the workspace was made with (features and gates must match).
    workdir keeps the restored workspace, the new images and the models there (debugging); else a temp dir.

    The result is over `order`: W2C poses in the workspace model's frame (OpenCV axes, SfM units), the old
    frames' poses bit-identical to the model's, new frames registered or NaN; K is the workspace camera's
    (held fixed); `mapper` is "incremental". `problems` adds to the usual gates (`sfm._gate_problems` over
    all frames) the share of new frames registered and any movement of the old frames. The workspace
    returned (also `result.workspace`) describes the result: the input one when nothing could be mapped,
    else the database with the new frames' features and matches and the extended model. ValueError when
    `order` misses a workspace image, repeats a name, or `new_frames` does not match the names missing
    from the workspace.
    progress(stage, len(STAGES), what it is doing) as each stage starts, then done (4 of 4).
    """
    import pycolmap

    params = params or SfmParams()
    report = progress or no_progress
    order = _checked_names(order, len(order))
    frames = _validate_frames([new_frames[n] for n in new_frames])
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="wv-sfm-extend-") as tmp:
        work = Path(workdir) if workdir is not None else Path(tmp)
        db_path, model_dir = workspace.restore(work)
        old_rec = pycolmap.Reconstruction(model_dir)
        db = pycolmap.Database.open(db_path)
        try:
            known = {im.name for im in db.read_all_images()}
            cameras = db.read_all_cameras()
        finally:
            db.close()
        missing = sorted(known - set(order))
        if missing:
            raise ValueError(f"order misses {len(missing)} workspace image(s), e.g. {missing[0]!r}")
        wanted = [n for n in order if n not in known]
        if sorted(new_frames) != sorted(wanted):
            raise ValueError(f"new_frames must hold exactly the {len(wanted)} names of order not in the workspace")
        is_new = np.array([n not in known for n in order])
        camera = cameras[0]
        size_wh = (int(camera.width), int(camera.height))

        def unchanged(problems: list[str]) -> tuple[SfmResult, SfmWorkspace]:
            """The old model over `order` (new frames NaN), failed with `problems`."""
            res = _result_from_model(old_rec, order, size_wh, "incremental", params)
            res.problems = [*problems, *res.problems]
            res.gates_passed = False
            res.timings = timings | {"total": time.perf_counter() - t_start}
            res.workspace = workspace
            return res, workspace

        if not wanted:
            return unchanged(["no new frames given"])
        problems = _input_problems([size_wh] + [(int(f.shape[1]), int(f.shape[0])) for f in frames])
        if len(cameras) != 1:
            problems.append(f"the workspace has {len(cameras)} cameras; an extension needs exactly one")
        if problems:
            return unchanged(problems)

        image_dir = work / "images"
        image_dir.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        report(0, len(STAGES), f"writing {len(wanted)} new frames")
        write_png_frames(image_dir, wanted, [new_frames[n] for n in wanted])
        timings["write"] = time.perf_counter() - t

        t = time.perf_counter()
        pycolmap.set_random_seed(params.random_seed)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = params.camera_model
        reader.existing_camera_id = camera.camera_id  # the scene's one camera, with its solved intrinsics
        report(1, len(STAGES), "extracting features of the new frames")
        _extract(db_path, image_dir, wanted, params, reader)
        timings["extract"] = time.perf_counter() - t

        t = time.perf_counter()
        pairs = sequential_pairs(len(order), params.matcher_overlap, params.quadratic_overlap)
        new_pairs = [(order[i], order[j]) for i, j in pairs if is_new[i] or is_new[j]]
        report(2, len(STAGES), f"matching the new frames ({len(new_pairs)} pairs)")
        verification = _match(db_path, new_pairs, params)
        timings["match"] = time.perf_counter() - t
        feature_problems, _ = _feature_problems(db_path, order, verification.min_num_inliers)

        t = time.perf_counter()
        out_dir = work / "extended"
        out_dir.mkdir(exist_ok=True)
        report(3, len(STAGES), "registering the new frames into the model")
        models = pycolmap.incremental_mapping(
            db_path, image_dir, out_dir, options=_extension_options(params), input_path=model_dir
        )
        timings["map_incremental"] = time.perf_counter() - t
        old = _poses_by_name(old_rec)
        rec = next((r for r in models.values() if set(old) <= set(_poses_by_name(r))), None)
        if rec is None:
            return unchanged(["the incremental mapper lost the existing model", *feature_problems])
        drift = _restore_old_poses(rec, old)
        for im in rec.images.values():
            if im.name not in known and im.has_pose:
                rec.extract_colors_for_image(im.image_id, image_dir)  # colours only the new (black) points
        res = _result_from_model(rec, order, size_wh, "incremental", params)
        extra = _new_frame_problems(res, is_new, params)
        centres = np.array([pose.inverse().translation for _, pose in old.values()]).reshape(-1, 3)
        extent = float(np.ptp(centres, axis=0).max()) if len(centres) else 0.0
        if drift > MAX_OLD_DRIFT_FRAC * max(extent, 1e-12):
            extra.append(f"the mapper moved fixed frames by up to {drift:.3g} SfM units")
        res.problems = [*extra, *res.problems]
        if res.problems:
            res.problems += [p for p in feature_problems if not res.registered.all()]
        res.gates_passed = not res.problems
        res.workspace = SfmWorkspace.pack(db_path, rec, work / "kept")
    res.timings = timings | {"total": time.perf_counter() - t_start}
    report(len(STAGES), len(STAGES), f"{int(res.registered[is_new].sum())}/{len(wanted)} new frames registered")
    return res, res.workspace
